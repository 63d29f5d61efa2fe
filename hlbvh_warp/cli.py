"""Command line: ``python -m hlbvh_warp <command> [options]``.

Each command lives in its own module with a ``main(argv)``; this file only dispatches.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import math
import os
import sys

from .inputs import MAX_PRIMS
from .scenes import MIN_SCENE_TRIS

COMMANDS = {
    "demo": ("hlbvh_warp.demo", "build a generated scene with each method, check rays, print timings"),
    "bench": ("hlbvh_warp.bench", "build time against tree quality for every builder (JSON + plot)"),
    "bench-rays": ("hlbvh_warp.ray_bench", "closest-hit rays per second against wp.Mesh"),
    "bench-points": ("hlbvh_warp.point_bench", "closest-point queries per second against wp.Mesh"),
    "bench-pairs": ("hlbvh_warp.pair_bench", "overlapping triangle pairs per second against wp.Mesh"),
    "bench-wide": ("hlbvh_warp.wide_bench", "closest-hit rays through wide BVHs (k = 2, 4, 8, 16)"),
    "quality": ("hlbvh_warp.quality", "SAH, end-point overlap and measured ray cost of every builder"),
    "stress": ("hlbvh_warp.stress_report", "disagreements with the float64 oracle per scene family"),
}


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """argparse's defaults in ``--help``, but none for a default of None: such an option's text
    says what its absence means ("Warp's default device", "the generated scene"), and a trailing
    "(default: None)" contradicted it."""

    def _get_help_string(self, action):
        if action.default is None:
            return action.help
        return super()._get_help_string(action)


#: Triangles of a generated scene or a subdivided mesh: a tree holds fewer than `MAX_PRIMS`
#: primitives (int32 node ids, 2N - 1 nodes), so a larger scene could only fail in the build.
MAX_TRIS = MAX_PRIMS - 1
#: Rays or points in one batch of a command: a bench-rays or bench-points set, the rays bench and
#: demo check against the brute force, quality's and bench-wide's views x side^2 rays, demo's
#: pixels per frame. Measured on the CPU, a bench-rays ray holds about 140 bytes of host memory at
#: the peak and a bench-points point (three sets) about 280: 2.3 and 4.7 GB at this bound, which is
#: 16 times bench-rays' default of 1M. Larger counts went on to allocate until the process died.
MAX_QUERIES = 1 << 24
#: Pixels per side of a square image: MAX_QUERIES pixels (4096 x 4096).
MAX_IMAGE_SIDE = 1 << 12
#: BuildConfig's own limit on max_leaf_size, checked here so that the error names the option.
MAX_LEAF_SIZE = 1 << 16
#: Why each bound is there, for the error message.
TRIS_LIMIT = f"a tree holds fewer than 2^{MAX_PRIMS.bit_length() - 1} triangles"
MEMORY_LIMIT = "a run's memory grows with it, to gigabytes at this bound"


def program() -> str:
    """How the user ran the command line, for usage and error lines: the installed
    ``hlbvh-warp`` script or ``python -m hlbvh_warp``. A usage line naming the other form would
    tell a script user to type a command they did not."""
    name = os.path.basename(sys.argv[0] if sys.argv else "")
    return "hlbvh-warp" if name.startswith("hlbvh-warp") else "python -m hlbvh_warp"


def command_prog(command: str) -> str:
    """argparse's ``prog`` of one command: ``<program> <command>``."""
    return f"{program()} {command}"


def int_in_range(minimum: int, maximum: int, why: str):
    """argparse type: an integer in ``[minimum, maximum]``; ``why`` says in the error what the
    upper bound protects. Sizes without an upper bound reached NumPy's allocator, which failed
    with a MemoryError traceback or a message naming no option, or got the process killed."""

    def parse(text: str) -> int:
        value = int(text)
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, got {value}")
        if value > maximum:
            raise argparse.ArgumentTypeError(f"must be at most {maximum} ({why}), got {value}")
        return value

    parse.__name__ = "int"  # argparse's message for text that is no integer: "invalid int value"
    return parse


tris_count = int_in_range(1, MAX_TRIS, TRIS_LIMIT)
# The examples' --num-tris sizes the generated scene, which cannot be smaller: below this the
# arguments were accepted and `default_scene` ended the run with a traceback.
scene_tris = int_in_range(MIN_SCENE_TRIS, MAX_TRIS, TRIS_LIMIT)
query_count = int_in_range(1, MAX_QUERIES, MEMORY_LIMIT)
query_count_or_zero = int_in_range(0, MAX_QUERIES, MEMORY_LIMIT)
image_side = int_in_range(1, MAX_IMAGE_SIDE, MEMORY_LIMIT)
leaf_size = int_in_range(1, MAX_LEAF_SIZE, "BuildConfig's limit")


def check_ray_count(parser: argparse.ArgumentParser, views: int, side: int):
    """End the program with an argparse error unless ``views`` images of ``side`` x ``side``
    pixels (quality's and bench-wide's primary rays) are at most `MAX_QUERIES` rays."""
    rays = views * side * side
    if rays > MAX_QUERIES:
        parser.error(f"--views {views} of --side {side} make {rays} primary rays, more than {MAX_QUERIES} "
                     f"({MEMORY_LIMIT}); choose fewer views or a smaller side")


def check_animation_pixels(parser: argparse.ArgumentParser, frames: int, side: int, option: str = "--image-size"):
    """End the program with an argparse error unless ``frames`` images of ``side`` x ``side``
    pixels, every one kept for an animated GIF, are at most the demo's `MAX_ANIMATION_PIXELS`
    (about 7 bytes a pixel in memory at the save)."""
    from .demo import MAX_ANIMATION_PIXELS

    pixels = frames * side * side
    if pixels > MAX_ANIMATION_PIXELS:
        parser.error(f"--num-frames {frames} at {option} {side} keeps {pixels} pixels of frames for the GIF, more "
                     f"than {MAX_ANIMATION_PIXELS} (about 7 bytes each in memory); choose fewer frames or a smaller "
                     "image")


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1 (frames, triangles, pixels, repeats)."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def non_negative_int(text: str) -> int:
    """argparse type: an integer >= 0 (warm-up runs, thread counts, seeds: NumPy's generators take
    no negative seed, and said so without naming the option)."""
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be at least 0, got {value}")
    return value


def quiet_warp():
    """Turn off Warp's informational output (its banner, and a line per kernel module loaded,
    which fell between the rows of every command's table); warnings and errors still show.
    Warp 1.19 filters by `config.log_level`; earlier versions read `config.quiet`."""
    import warp as wp

    wp.config.quiet = True
    if hasattr(wp, "LOG_WARNING"):
        wp.config.log_level = wp.LOG_WARNING


def device_name(text: str) -> str:
    """argparse type: a Warp device this machine has ("cpu", "cuda", "cuda:1"). Warp names an
    unknown one with a ValueError but a CUDA device on a machine without CUDA with a
    RuntimeError, which left ``--device cuda`` a traceback on CPU-only machines."""
    import warp as wp

    quiet_warp()
    try:
        wp.get_device(text)
    except (RuntimeError, ValueError) as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return text


def mesh_file(text: str) -> str:
    """argparse type: a path to an existing file (read later by trimesh)."""
    if os.path.isdir(text):
        raise argparse.ArgumentTypeError(f"{text} is a directory, not a mesh file")
    if not os.path.isfile(text):
        raise argparse.ArgumentTypeError(f"no such mesh file: {text}")
    return text


def finite_float(text: str) -> float:
    """argparse type: a finite number (costs, limits); "nan" and "inf" parse as floats but would
    only fail mid-run, in the arithmetic they feed."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
    return value


def non_negative_float(text: str) -> float:
    """argparse type: a number >= 0, inf included (a limit that never binds); NaN and negatives
    refused, which every comparison with them would get wrong."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
    if not value >= 0.0:
        raise argparse.ArgumentTypeError(f"must be a number >= 0, got {text}")
    return value


@contextlib.contextmanager
def argument_errors(parser: argparse.ArgumentParser):
    """A ValueError of the checks inside (an output path, a mesh file) ends the program as
    argparse ends it on a bad option: ``parser.error``'s one line and exit status 2."""
    try:
        yield
    except ValueError as error:
        parser.error(str(error))


def _nearest_existing(path: str) -> str:
    path = os.path.abspath(path)
    while not os.path.exists(path):
        path = os.path.dirname(path)
    return path


def _check_can_make_folder(folder: str, label: str):
    # os.makedirs names only the last path it tried ("[Errno 17] File exists: '/dev/null'" for
    # /dev/null/x): the file in the way is named here instead.
    existing = _nearest_existing(folder)
    if not os.path.isdir(existing):
        raise ValueError(f"{label}: cannot make the folder, {existing} is a file")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ValueError(f"{label}: cannot make the folder, {existing} is not writable")


def check_out_folder(path: str):
    """Raise a ValueError naming ``--out`` (every command's output folder) and ``path`` unless
    ``path`` is a writable folder or one that can be made. Nothing is made: the writer makes the
    folder when it writes, and a run that fails later leaves no empty folder behind. Called
    before the long work, which used to end in NotADirectoryError only after every frame had run."""
    label = f"--out {path}"
    if os.path.exists(path):
        if not os.path.isdir(path):
            raise ValueError(f"{label} is a file, not a folder")
        if not os.access(path, os.W_OK | os.X_OK):
            raise ValueError(f"{label}: the folder is not writable")
        return
    _check_can_make_folder(path, label)


def check_out_file(path: str, option: str):
    """As `check_out_folder`, for an output file: ``path`` must not be a folder, and its folder
    must be writable or possible to make."""
    label = f"{option} {path}"
    if os.path.isdir(path):
        raise ValueError(f"{label} is a folder, not a file")
    if os.path.exists(path):
        if not os.access(path, os.W_OK):
            raise ValueError(f"{label}: the file is not writable")
        return
    folder = os.path.dirname(os.path.abspath(path))
    if os.path.isdir(folder):
        if not os.access(folder, os.W_OK | os.X_OK):
            raise ValueError(f"{label}: the folder {folder} is not writable")
        return
    _check_can_make_folder(folder, label)


def read_mesh(path: str):
    """``(vertices, faces)`` of a mesh file, checked as a build checks them (face indices in
    range, finite coordinates), or a ValueError naming the file: the examples read their
    ``--mesh`` through this before any work, so a file trimesh cannot read (a text file, a
    broken or points-only PLY) is one line, not a traceback from the first frame."""
    from . import inputs, scenes

    vertices, faces = scenes.load_mesh(path)
    try:
        return inputs.mesh_arrays(vertices, faces)
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None


def read_meshes(paths) -> list:
    """``(name, vertices, faces)`` of every mesh file, named by its stem and checked by
    `read_mesh`: the measuring commands read all their ``--mesh`` files this way before any work,
    so a NaN coordinate or a face index out of range is named with its file (the build's own
    message named neither), and a bad second file is found before the first is measured."""
    import pathlib

    return [(pathlib.Path(p).stem, *read_mesh(p)) for p in paths]


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in COMMANDS:
        if argv and argv[0] not in ("-h", "--help"):
            print(f"{program()}: unknown command {argv[0]!r}", file=sys.stderr)
        print(f"usage: {program()} <command> [options]\n\ncommands:")
        for name, (_, text) in COMMANDS.items():
            print(f"  {name:12s} {text}")
        return 0 if not argv or argv[0] in ("-h", "--help") else 2
    module = importlib.import_module(COMMANDS[argv[0]][0])
    try:
        return int(module.main(argv[1:]) or 0)
    except (ValueError, OSError, NotImplementedError) as error:
        # Bad input the library names (a file that is not a mesh, an unknown builder or device,
        # an empty scene): one line, not a traceback. Anything else is a bug and keeps its trace.
        print(f"{command_prog(argv[0])}: error: {error}", file=sys.stderr)
        return 2
    except MemoryError as error:
        # The bounds on sizes keep a run to what the library and a few GB hold, not to what this
        # machine has: a run that still does not fit is one line naming it, not a traceback.
        detail = f" ({error})" if str(error) else ""
        print(f"{command_prog(argv[0])}: error: out of memory{detail}; choose smaller sizes", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
