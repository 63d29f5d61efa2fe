"""Command line: ``python -m hlbvh_warp <command> [options]``.

Each command lives in its own module with a ``main(argv)``; this file only dispatches.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

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


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1 (frames, triangles, pixels, repeats)."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def non_negative_int(text: str) -> int:
    """argparse type: an integer >= 0 (warm-up runs, thread counts, subdivisions)."""
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be at least 0, got {value}")
    return value


def device_name(text: str) -> str:
    """argparse type: a Warp device this machine has ("cpu", "cuda", "cuda:1"). Warp names an
    unknown one with a ValueError but a CUDA device on a machine without CUDA with a
    RuntimeError, which left ``--device cuda`` a traceback on CPU-only machines."""
    import warp as wp

    wp.config.quiet = True
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


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in COMMANDS:
        if argv and argv[0] not in ("-h", "--help"):
            print(f"hlbvh_warp: unknown command {argv[0]!r}", file=sys.stderr)
        print("usage: python -m hlbvh_warp <command> [options]\n\ncommands:")
        for name, (_, text) in COMMANDS.items():
            print(f"  {name:12s} {text}")
        return 0 if not argv or argv[0] in ("-h", "--help") else 2
    module = importlib.import_module(COMMANDS[argv[0]][0])
    try:
        return int(module.main(argv[1:]) or 0)
    except (ValueError, OSError, NotImplementedError) as error:
        # Bad input the library names (a file that is not a mesh, an unknown builder or device,
        # an empty scene): one line, not a traceback. Anything else is a bug and keeps its trace.
        print(f"hlbvh_warp {argv[0]}: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
