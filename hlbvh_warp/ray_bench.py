"""``python -m hlbvh_warp bench-rays``: closest-hit rays per second against ``wp.mesh_query_ray``.

For each mesh, one BVH per method and one ``wp.Mesh`` of the same triangles trace the same rays
(random rays through the bounding box, pinhole camera rays, and with ``--far-distance D`` random
rays from D mesh sizes away) in the same process.

Hits are checked first. This package's are checked against a float64 brute force
(`brute_force_closest_hit`) on an even sample of each kind and on every ray where ``wp.Mesh``
disagrees (up to `ORACLE_RAYS` of each), by the rule of the ``stress`` command
(`stress_report.classify`). A ray is wrong when its answer differs from the brute force's (a hit
against a miss, or a hit at a t not within 1e-5 relative of the brute force's: a different
triangle at the same t is a tie where the ray meets it there, `reference.unmet_ties`) and the
difference is not a near-tie: every triangle on which the two answers differ decided within
float32's rounding, the ray passing within 1e-5 x scale of the triangle's boundary or of the
line through one of its edges (scale:
the largest coordinate of the ray's origin and the triangle), grazing the triangle's plane or
starting on it, or the triangle having almost no area. On a shared edge or vertex the watertight
test may pick either triangle, and on the mesh's silhouette a hit or a miss. Wrong rays are the
exit status. ``wp.Mesh``'s hits are compared with this package's and reported, not judged: a ray
disagrees when the two report different triangles at distances that are not equal to 1e-5
relative, or one hits and the other does not. ``wp.Mesh`` misses every ray on some valid meshes
(spheres of radius 1e-20, and of 1e20 or more), where the brute force agrees with this package.
Then each kernel is timed as the best of ``--repeats`` launches and one fixed-format row is
printed per run.
"""

from __future__ import annotations

import argparse
import functools
import pathlib
import time

import numpy as np
import warp as wp

from .cli import (command_prog, device_name, finite_float, leaf_size, non_negative_int, positive_int, query_count,
                  quiet_warp, read_mesh)
from .reference import brute_force_closest_hit, origins_within_float32
from .stress_report import classify

DEFAULT_MESHES = ("bunny", "armadillo")
SHARED_MESHES = pathlib.Path(__file__).resolve().parents[1].parent / "shared" / "meshes"
#: ``../shared/meshes`` as the help and the README write it: from the current folder.
RELATIVE_MESHES = pathlib.Path("..") / "shared" / "meshes"


def default_mesh_paths() -> list[pathlib.Path] | None:
    """The bunny and the armadillo of bench-rays, bench-points and bench-pairs without ``--mesh``:
    from ``../shared/meshes`` beside the current folder (the README runs the commands from the
    repository root), else beside the checkout this package runs from; None where neither holds
    them. Only the second was looked at, which for an installed package is a folder beside
    site-packages: the default failed there, naming that folder, whatever the current one."""
    for folder in (RELATIVE_MESHES, SHARED_MESHES):
        paths = [folder / f"{name}.ply" for name in DEFAULT_MESHES]
        if all(path.is_file() for path in paths):
            return paths
    return None


#: Rays of each kind checked against the float64 brute force: this many evenly spaced, and as many
#: of the rays where wp.Mesh disagrees. The brute force takes under half a second for 512 rays on
#: the bunny or the armadillo (70k and 100k triangles), against seconds for the timed launches.
ORACLE_RAYS = 256


def random_rays(rng, vertices: np.ndarray, num_rays: int):
    """Rays from a sphere around the bounding box aimed at uniform points inside it."""
    # In float64: float32's squares overflowed in the diagonal of a box wider than 1.8e19, and
    # every ray came out NaN.
    v = np.asarray(vertices, dtype=np.float64)
    lo, hi = v.min(0), v.max(0)
    center, radius = 0.5 * (lo + hi), 0.5 * np.linalg.norm(hi - lo)
    dirs = rng.normal(size=(num_rays, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origins = center - 2.0 * radius * dirs
    d = lo + rng.random((num_rays, 3)) * (hi - lo) - origins
    return origins_within_float32(origins, d), (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


def far_rays(rng, vertices: np.ndarray, num_rays: int, distance: float):
    """`random_rays` whose origins lie ``distance`` bounding-box diagonals from the box's centre: a
    far camera or a sun's rays cast from outside the scene, where float32 coordinates relative to the
    origin no longer resolve a triangle."""
    v = np.asarray(vertices, dtype=np.float64)
    lo, hi = v.min(0), v.max(0)
    dirs = rng.normal(size=(num_rays, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    with np.errstate(over="ignore"):
        origins = (0.5 * (lo + hi) - distance * np.linalg.norm(hi - lo) * dirs).astype(np.float32)
    if not np.isfinite(origins).all():
        raise ValueError(f"--far-distance {distance:g} puts ray origins past float32's range for a mesh whose "
                         f"box diagonal is {np.linalg.norm(hi - lo):.3g}")
    # Aimed from the float32 origins: at 1e8 diagonals a float32 direction still turns a ray off
    # the mesh by more than its size, and few rays hit.
    d = lo + rng.random((num_rays, 3)) * (hi - lo) - origins.astype(np.float64)
    return origins, (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


def camera_rays(vertices: np.ndarray, num_rays: int):
    """A square pinhole image of about ``num_rays`` pixels looking at the mesh along -z, 40 degree fov."""
    v = np.asarray(vertices, dtype=np.float64)  # as in `random_rays`
    lo, hi = v.min(0), v.max(0)
    center, radius = 0.5 * (lo + hi), 0.5 * np.linalg.norm(hi - lo)
    side = max(1, int(round(np.sqrt(num_rays))))
    half = np.tan(np.radians(20.0))
    s = (np.arange(side) + 0.5) / side * 2.0 - 1.0
    x, y = np.meshgrid(s * half, -s * half)
    d = np.stack([x.ravel(), y.ravel(), -np.ones(side * side)], axis=1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    eye = center + np.array([0.0, 0.0, 2.5 * radius])
    return origins_within_float32(np.repeat(eye[None], side * side, axis=0), d), d.astype(np.float32)


def disagreeing(t_a, prim_a, t_b, prim_b, rtol: float = 1e-5) -> np.ndarray:
    """Mask of the rays whose two answers disagree: one hits and the other does not, or they hit
    different triangles at distances further apart than ``rtol`` relative (a near-tie on a shared
    edge is not a disagreement)."""
    hit_a, hit_b = prim_a >= 0, prim_b >= 0
    same_t = np.isclose(t_a.astype(np.float64), t_b.astype(np.float64), rtol=rtol, atol=0.0)
    return ~((~hit_a & ~hit_b) | (hit_a & hit_b & ((prim_a == prim_b) | same_t)))


def count_wrong(vertices, faces, origins, directions, t, prim) -> int:
    """Rays whose closest hit (``t``, ``prim``) is wrong by the float64 brute force, near-ties
    excused (`stress_report.classify`, the module docstring), or names no triangle of the mesh."""
    faces = np.asarray(faces)
    prim = np.asarray(prim)
    # Judged apart: the near-tie rule reads the triangle a hit names.
    named = (prim >= -1) & (prim < len(faces))
    reference = brute_force_closest_hit(vertices, faces, origins[named], directions[named])
    return int((~named).sum()) + classify(vertices, faces, origins[named], directions[named], t[named], prim[named],
                                          *reference)[1]


def best_times(fns, repeats: int, device) -> list[float]:
    """Best wall time of each function; launches interleave so both see the same machine load."""
    best = [float("inf")] * len(fns)
    for _ in range(repeats):
        for i, fn in enumerate(fns):
            wp.synchronize_device(device)
            start = time.perf_counter()
            fn()
            wp.synchronize_device(device)
            best[i] = min(best[i], time.perf_counter() - start)
    return best


def run(mesh_path: pathlib.Path, vertices: np.ndarray, faces: np.ndarray, method: str, num_rays: int, repeats: int,
        device, seed: int = 0, max_leaf_size: int = 1, far_distance: float = 0.0) -> list[dict]:
    """One row per kind of ray on the mesh of ``mesh_path``, read and checked (`cli.read_mesh`);
    a third kind, from ``far_distance`` diagonals away, when it is positive."""
    from . import api, query
    from .config import BuildConfig
    from .kernels import traversal

    config = BuildConfig(max_leaf_size=max_leaf_size)
    bvh = api.build(vertices, faces, method=method, device=device, config=config)
    wmesh = wp.Mesh(
        points=wp.array(vertices, dtype=wp.vec3, device=device),
        indices=wp.array(faces.ravel(), dtype=wp.int32, device=device),
    )
    bvh_view = query.view(bvh)
    rng = np.random.default_rng(seed)
    rows = []
    kinds = [("random", random_rays(rng, vertices, num_rays)), ("camera", camera_rays(vertices, num_rays))]
    if far_distance > 0.0:
        kinds.append(("far", far_rays(rng, vertices, num_rays, far_distance)))
    for kind, (o, d) in kinds:
        n = o.shape[0]
        ow = wp.array(o, dtype=wp.vec3, device=device)
        dw = wp.array(d, dtype=wp.vec3, device=device)
        ours_t, ours_p = wp.empty(n, dtype=float, device=device), wp.empty(n, dtype=wp.int32, device=device)
        ref_t, ref_p = wp.empty(n, dtype=float, device=device), wp.empty(n, dtype=wp.int32, device=device)

        def ours():
            wp.launch(traversal.closest_hit_kernel, dim=n, inputs=[bvh_view, ow, dw, float("inf"), ours_t, ours_p],
                      device=device)

        def reference():
            wp.launch(traversal.warp_mesh_closest_hit_kernel, dim=n, inputs=[wmesh.id, ow, dw, ref_t, ref_p],
                      device=device)

        # Check before timing: ours against the brute force on an even sample, and where wp.Mesh
        # disagrees, since either answer may be the wrong one there.
        ours()
        reference()
        t_ours, p_ours = ours_t.numpy(), ours_p.numpy()
        differ = disagreeing(t_ours, p_ours, ref_t.numpy(), ref_p.numpy())
        checked = np.union1d(np.linspace(0, n - 1, min(ORACLE_RAYS, n)).astype(np.int64),
                             np.flatnonzero(differ)[:ORACLE_RAYS])
        wrong = count_wrong(vertices, faces, o[checked], d[checked], t_ours[checked], p_ours[checked])
        _, _, stats = query.intersect(bvh, o, d, stats=True)
        time_ours, time_ref = best_times([ours, reference], repeats, device)
        rows.append(
            {
                "mesh": mesh_path.stem,
                "tris": faces.shape[0],
                "method": method,
                "rays": kind,
                "num_rays": n,
                "hits": int((p_ours >= 0).sum()),
                "checked": int(len(checked)),
                "wrong": wrong,
                "disagree": int(differ.sum()),
                "mrays_ours": n / time_ours / 1e6,
                "mrays_wp_mesh": n / time_ref / 1e6,
                "ratio": time_ref / time_ours,
                "n_s": stats.summary()["mean_nodes_visited"],
                "n_t": stats.summary()["mean_prims_tested"],
            }
        )
    return rows


HEADER = (
    f"{'mesh':10s} {'tris':>8s} {'method':8s} {'rays':7s} {'num_rays':>9s} {'hits':>9s} {'checked':>7s} {'wrong':>5s} "
    f"{'wp differ':>9s} {'Mrays/s':>8s} {'wp.Mesh':>8s} {'ratio':>6s} {'n_s':>7s} {'n_t':>6s}"
)


def format_row(r: dict) -> str:
    return (
        f"{r['mesh']:10s} {r['tris']:8d} {r['method']:8s} {r['rays']:7s} {r['num_rays']:9d} {r['hits']:9d} "
        f"{r['checked']:7d} {r['wrong']:5d} {r['disagree']:9d} {r['mrays_ours']:8.3f} {r['mrays_wp_mesh']:8.3f} "
        f"{r['ratio']:6.2f} {r['n_s']:7.1f} {r['n_t']:6.2f}"
    )


def mesh_method_parser(prog: str, description: str, count_option: str | None = None, count_default: int = 0,
                       count_help: str = "", epilog: str | None = None):
    """The options the bench-rays, bench-points and bench-pairs commands share: meshes, builders, repeats,
    device, seed, leaf size, and the number of queries per kind (``count_option``, where there is one).
    ``epilog``: what the exit status says, after the options."""
    parser = argparse.ArgumentParser(prog=prog, description=description, epilog=epilog)
    parser.add_argument("--mesh", action="append", type=pathlib.Path,
                        help="a mesh file (repeatable); default: bunny and armadillo from ../shared/meshes")
    if count_option is not None:
        parser.add_argument(count_option, type=query_count, default=count_default, help=count_help)
    parser.add_argument("--method", action="append", help="builder (repeatable); default hlbvh")
    parser.add_argument("--repeats", type=positive_int, default=3,
                        help="launches timed per kernel; the best is kept (default: %(default)s)")
    parser.add_argument("--device", type=device_name, default="cpu", help="Warp device (default cpu)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="seed of the queries (default: %(default)s)")
    parser.add_argument("--max-leaf-size", type=leaf_size, default=1,
                        help="BuildConfig.max_leaf_size of the trees (default 1)")
    return parser


def checked_verdict(rows: list[dict], oracle: str, queries: str, differ_text: str) -> tuple[str, bool]:
    """The summary line and whether the run failed, shared by the bench commands: on this package's
    answers against the brute force alone (``oracle``: which one; ``queries``: what was checked).
    wp.Mesh's disagreements are reported beside them, as wp.Mesh's, by ``differ_text`` with the
    total in place of ``{}``."""
    wrong, checked = sum(r["wrong"] for r in rows), sum(r["checked"] for r in rows)
    differ = sum(r["disagree"] for r in rows)
    return (f"ours against the {oracle} brute force: {wrong} wrong of {checked} {queries} checked; "
            f"{differ_text.format(differ)} (reported, not the exit status)"), wrong > 0


def verdict(rows: list[dict]) -> tuple[str, bool]:
    """bench-rays' `checked_verdict`."""
    return checked_verdict(rows, "float64", "rays", "wp.Mesh differs from ours on {} rays")


def run_rows(parser, args, count: int, run_fn, header: str, format_fn, footer: str, verdict) -> int:
    """Print one row per mesh, method and query kind, then the footer and ``verdict(rows)``'s
    summary; exit 1 when the verdict is a failure (as bench-wide and quality do, so a script can
    rely on the status)."""
    quiet_warp()
    wp.init()
    paths = args.mesh or default_mesh_paths()
    if paths is None:
        names = " and ".join(f"{name}.ply" for name in DEFAULT_MESHES)
        parser.error(f"no --mesh given, and the default meshes ({names}) are not in {RELATIVE_MESHES}; "
                     "pass --mesh FILE")
    missing = [str(p) for p in paths if not p.exists()]
    if missing:
        parser.error(f"mesh not found: {', '.join(missing)}")
    from . import api

    # Every name before the first mesh is read and built, not when the loop reaches it.
    api._load_optional_builders()
    unknown = [m for m in args.method or [] if m not in api.BUILDERS]
    if unknown:
        parser.error(f"unknown method(s) {unknown} in --method; choose from {sorted(api.BUILDERS)}")
    device = wp.get_device(args.device)
    # Every file read and checked before the first is measured, each error naming its file (the
    # build's own "vertices has a NaN or Inf coordinate" named none). As every other command reads
    # a mesh: a file of several objects is one mesh, an empty one an error.
    meshes = [(path, *read_mesh(path)) for path in paths]
    print(header)
    rows = []
    with wp.ScopedDevice(device):
        for path, vertices, faces in meshes:
            for method in args.method or ["hlbvh"]:
                for row in run_fn(path, vertices, faces, method, count, args.repeats, device, args.seed,
                                  args.max_leaf_size):
                    rows.append(row)
                    print(format_fn(row), flush=True)
    summary, failed = verdict(rows)
    print(f"{footer}; {summary}")
    return 1 if failed else 0


#: The exit status, for --help.
EPILOG = (f"Exit status 1 when one of the rays checked (up to {ORACLE_RAYS} of each kind, and as many where wp.Mesh "
          "differs) has a closest hit a float64 brute force finds wrong, near-ties on shared edges excused; 2 on an "
          "error in the options or a mesh; else 0. wp.Mesh's disagreements are reported, not judged: it misses every "
          "ray on some valid meshes.")


def far_distance(text: str) -> float:
    """argparse type of ``--far-distance``: 0 (none) or a distance from 1 to 1e30 diagonals; past
    that the origins' float32 coordinates overflow on a mesh of unit size (sooner on a larger one)."""
    value = finite_float(text)
    if value != 0.0 and not 1.0 <= value <= 1e30:
        raise argparse.ArgumentTypeError(f"must be 0 or between 1 and 1e30, got {text}")
    return value


def main(argv=None) -> int:
    parser = mesh_method_parser(command_prog("bench-rays"), __doc__.splitlines()[0], "--rays", 1_000_000,
                                "rays per kind (default 1M)", EPILOG)
    parser.add_argument("--far-distance", type=far_distance, default=0.0,
                        help="also trace random rays from this many bounding-box diagonals away (default: none). "
                             "Past 256 box extents the walk starts at the box; from about 1e8 a float32 "
                             "direction no longer aims within the mesh, and few rays hit")
    args = parser.parse_args(argv)
    return run_rows(parser, args, args.rays, functools.partial(run, far_distance=args.far_distance), HEADER,
                    format_row,
                    "checked: rays checked against the float64 brute force (an even sample and where wp.Mesh "
                    "differs), wrong: ours wrong among them beyond near-ties; wp differ: rays where wp.Mesh's hit "
                    "differs from ours; ratio = wp.mesh_query_ray time / ours (> 1: ours is faster)", verdict)
