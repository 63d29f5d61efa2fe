"""``python -m hlbvh_warp bench-points``: closest-point queries per second against ``wp.mesh_query_point_no_sign``.

For each mesh, one BVH per method and one ``wp.Mesh`` of the same triangles answer the same
points in the same process:

- ``box``: uniform in the bounding box grown by a fifth on each side: most lie far from the
  surface, where many boxes are about as near as the nearest triangle and the search opens the
  most nodes;
- ``near``: mesh vertices moved by a normal offset of 1% of the box diagonal, the points a
  collision or a projection step asks about;
- ``near-bounded``: the same with ``max_dist`` = 5% of the diagonal, as a contact query bounds
  its search;
- ``far`` (with ``--far-distance D``): points D box diagonals from the box's centre in random
  directions, where float32 no longer tells one box's distance from another's and the search
  takes its float64 walk (``kernels/proximity.py``, `packed_far_point_query`).

Answers are checked first. This package's are checked against a float64 brute force
(`brute_force_closest`) on an even sample of each set and on every point where ``wp.Mesh``
disagrees (up to `ORACLE_POINTS` of each): a point is wrong when it finds a triangle where none
lies within ``max_dist`` or the reverse, or when its distance, or the distance to the triangle it
names, is off the brute force's by more than `ORACLE_RTOL` of the coordinates involved. Wrong
points are the exit status. ``wp.Mesh``'s answers are compared with this package's and reported,
not judged: a point disagrees when the two distances differ by more than 1e-5 of the box diagonal
(Warp computes in float32, which on thin triangles loses more than a few ulps; this package
computes the distance in float64, see ``kernels/proximity.py``), or when one finds a triangle and
the other does not. ``wp.Mesh`` finds nothing on some valid meshes (all triangles on one line,
coordinates near float32's limit), where the brute force agrees with this package. Then each
kernel is timed as the best of ``--repeats`` launches, interleaved, and one fixed-format row is
printed per run.
"""

from __future__ import annotations

import functools
import pathlib

import numpy as np
import warp as wp

from .cli import command_prog
from .reference import FLOAT32_MAX, brute_force_closest, point_triangle_d2
from .ray_bench import best_times, checked_verdict, far_distance, mesh_method_parser, run_rows

#: Disagreement with wp.Mesh: distances further apart than this fraction of the box diagonal.
DISAGREE_RTOL = 1e-5
#: Points of each set checked against the brute force: this many evenly spaced, and as many of
#: the points where wp.Mesh disagrees.
ORACLE_POINTS = 256
#: Agreement with the brute force: within this fraction of the largest coordinate of the point
#: and of the triangles compared. The kernel reads float32 coordinates, decides in float64 and
#: rounds the distance to float32 once, about 6e-8 of it: this is 10 times that rounding, the
#: tolerance of tests/test_proximity.py, and 5 or more orders of magnitude below the distances
#: between a mesh's triangles.
ORACLE_RTOL = 1e-6


def bench_box(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """``(lo, hi, diag)``: the box the point sets fill and its diagonal, the scale of every
    tolerance and offset. A mesh whose vertices all coincide (degenerate triangles are valid
    input) has no box: a cube around its one point stands in, as large as its coordinates (1 at
    the origin), so the sets still spread around it and the tolerances are not zero."""
    v = np.asarray(vertices, dtype=np.float64)
    lo, hi = v.min(0), v.max(0)
    diag = float(np.linalg.norm(hi - lo))
    if not diag > 0.0:
        side = float(np.abs(v).max()) or 1.0
        lo, hi = lo - 0.5 * side, hi + 0.5 * side
        diag = float(np.linalg.norm(hi - lo))
    return lo, hi, diag


def point_sets(rng, vertices: np.ndarray, num_points: int) -> dict:
    """The benchmark's point sets, with each one's max_dist (inf when unbounded)."""
    lo, hi, diag = bench_box(vertices)
    box = lo - 0.2 * (hi - lo) + rng.random((num_points, 3)) * 1.4 * (hi - lo)
    near = vertices[rng.integers(0, len(vertices), num_points)] + rng.normal(0.0, 0.01 * diag, (num_points, 3))
    # Within float32's range: around a mesh near its limit the grown box and the offsets reach
    # past it, and those points became Inf, queries that find nothing.
    box, near = np.clip(box, -FLOAT32_MAX, FLOAT32_MAX), np.clip(near, -FLOAT32_MAX, FLOAT32_MAX)
    return {
        "box": (box.astype(np.float32), float("inf")),
        "near": (near.astype(np.float32), float("inf")),
        "near-bounded": (near.astype(np.float32), 0.05 * diag),
    }


def far_points(rng, vertices: np.ndarray, num_points: int, distance: float) -> np.ndarray:
    """Points ``distance`` box diagonals from the centre of `bench_box`, in uniformly random
    directions, as float32 (`ray_bench.far_rays`' origins)."""
    lo, hi, diag = bench_box(vertices)
    dirs = rng.normal(size=(num_points, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    with np.errstate(over="ignore"):
        points = (0.5 * (lo + hi) + distance * diag * dirs).astype(np.float32)
    if not np.isfinite(points).all():
        raise ValueError(f"--far-distance {distance:g} puts points past float32's range for a mesh whose box "
                         f"diagonal is {diag:.3g}")
    return points


def disagreeing(d_a, prim_a, d_b, prim_b, scale: float, rtol: float = DISAGREE_RTOL) -> np.ndarray:
    """Mask of the points whose two answers disagree: one finds a triangle and the other does not,
    or their distances differ by more than ``rtol * scale``."""
    found_a, found_b = prim_a >= 0, prim_b >= 0
    with np.errstate(invalid="ignore"):  # inf - inf where neither found anything
        close = np.abs(d_a.astype(np.float64) - d_b.astype(np.float64)) <= rtol * scale
    return ~((~found_a & ~found_b) | (found_a & found_b & close))


def count_wrong(vertices, faces, points, distance, prim, max_dist: float, reference) -> int:
    """Points whose answer (``distance``, ``prim``) is wrong by the brute force's ``reference``
    (``brute_force_closest``'s answer for the same points), within `ORACLE_RTOL` of the largest
    coordinate of the point and of the triangles compared.

    Wrong: a triangle found for a NaN or Inf point; found / not found other than the brute force
    says (a point whose distance lies within the tolerance of ``max_dist`` may go either way); a
    distance off the brute force's (one past float32's range reads inf); or a triangle that is not
    at that distance, or not a triangle of the mesh.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    d_ref, prim_ref = reference
    found = prim >= 0
    valid = prim < len(f)
    answerable = prim_ref >= 0  # a finite point: some triangle is nearest
    mine = np.where(found & valid, prim, 0)
    # The kernel takes the bound as the float32 at or above it.
    bound = np.float32(max_dist)
    if bound < max_dist:
        bound = np.nextafter(bound, np.float32(np.inf))
    with np.errstate(invalid="ignore", over="ignore"):
        scale = np.maximum.reduce([np.abs(np.where(answerable[:, None], pts, 0.0)).max(axis=1),
                                   np.abs(v[f[np.maximum(prim_ref, 0)]]).max(axis=(1, 2)),
                                   np.abs(v[f[mine]]).max(axis=(1, 2))])
        tol = ORACLE_RTOL * scale
        decided = ~(np.abs(d_ref - float(bound)) <= tol)
        should_find = answerable & (d_ref <= float(bound))
        d = distance.astype(np.float64)
        same_distance = (d == d_ref.astype(np.float32)) | (np.abs(d - d_ref) <= tol)
        tri = v[f[mine]]
        own = np.sqrt(point_triangle_d2(pts, tri[:, 0], tri[:, 1], tri[:, 2]))
        nearest = np.abs(own - d_ref) <= tol
    wrong = (found & ~answerable) | (decided & (found != should_find)) | (found & ~valid)
    wrong |= found & valid & answerable & ~(same_distance & nearest)
    return int(wrong.sum())


def run(mesh_path: pathlib.Path, vertices: np.ndarray, faces: np.ndarray, method: str, num_points: int, repeats: int,
        device, seed: int = 0, max_leaf_size: int = 1, far_distance: float = 0.0) -> list[dict]:
    """One row per point set on the mesh of ``mesh_path``, read and checked (`cli.read_mesh`); a
    fourth set, ``far``, from ``far_distance`` diagonals away, when it is positive."""
    from . import api, query
    from .config import BuildConfig
    from .kernels import proximity

    bvh = api.build(vertices, faces, method=method, device=device, config=BuildConfig(max_leaf_size=max_leaf_size))
    wmesh = wp.Mesh(
        points=wp.array(vertices, dtype=wp.vec3, device=device),
        indices=wp.array(faces.ravel(), dtype=wp.int32, device=device),
    )
    bvh_view = query.view(bvh)
    _, _, scale = bench_box(vertices)
    rng = np.random.default_rng(seed)
    rows = []
    sets = point_sets(rng, vertices, num_points)
    if far_distance > 0.0:
        sets["far"] = (far_points(rng, vertices, num_points, far_distance), float("inf"))
    for kind, (points, max_dist) in sets.items():
        n = points.shape[0]
        pw = wp.array(points, dtype=wp.vec3, device=device)
        ours_out = [wp.empty(n, dtype=wp.vec3, device=device), wp.empty(n, dtype=float, device=device),
                    wp.empty(n, dtype=wp.int32, device=device)]
        ref_out = [wp.empty(n, dtype=wp.vec3, device=device), wp.empty(n, dtype=float, device=device),
                   wp.empty(n, dtype=wp.int32, device=device)]
        none_f, none_i = wp.empty(0, dtype=float, device=device), wp.empty(0, dtype=wp.int32, device=device)
        # wp.mesh_query_point_no_sign takes a finite bound.
        ref_max = max_dist if np.isfinite(max_dist) else 1.0e30

        def ours():
            wp.launch(proximity.closest_point_kernel, dim=n, device=device,
                      inputs=[bvh_view, pw, float(max_dist), *ours_out, none_f, none_f, none_i, none_i])

        def reference():
            wp.launch(proximity.warp_mesh_closest_point_kernel, dim=n, device=device,
                      inputs=[wmesh.id, pw, ref_max, *ref_out])

        ours()
        reference()
        d_ours, p_ours = ours_out[1].numpy(), ours_out[2].numpy()
        d_ref, p_ref = ref_out[1].numpy(), ref_out[2].numpy()
        differ = disagreeing(d_ours, p_ours, d_ref, p_ref, scale)
        # Ours against the brute force: an even sample, and where wp.Mesh disagrees, since either
        # answer may be the wrong one there.
        checked = np.union1d(np.linspace(0, n - 1, min(ORACLE_POINTS, n)).astype(np.int64),
                             np.flatnonzero(differ)[:ORACLE_POINTS])
        wrong = count_wrong(vertices, faces, points[checked], d_ours[checked], p_ours[checked], max_dist,
                            brute_force_closest(vertices, faces, points[checked]))
        both = (p_ours >= 0) & (p_ref >= 0)
        max_diff = float(np.abs(d_ours[both].astype(np.float64) - d_ref[both]).max()) / scale if both.any() else 0.0
        _, _, _, stats = query.closest_point(bvh, points, max_dist=max_dist, stats=True)
        t_ours, t_ref = best_times([ours, reference], repeats, device)
        rows.append(
            {
                "mesh": mesh_path.stem,
                "tris": faces.shape[0],
                "method": method,
                "points": kind,
                "num_points": n,
                "found": int((p_ours >= 0).sum()),
                "checked": int(len(checked)),
                "wrong": wrong,
                "disagree": int(differ.sum()),
                "max_diff": max_diff,
                "mpts_ours": n / t_ours / 1e6,
                "mpts_wp_mesh": n / t_ref / 1e6,
                "ratio": t_ref / t_ours,
                "n_s": stats.summary()["mean_nodes_visited"],
                "n_t": stats.summary()["mean_prims_tested"],
            }
        )
    return rows


HEADER = (
    f"{'mesh':10s} {'tris':>8s} {'method':8s} {'points':12s} {'num':>8s} {'found':>8s} {'checked':>7s} {'wrong':>5s} "
    f"{'wp differ':>9s} {'max diff':>9s} {'Mpts/s':>7s} {'wp.Mesh':>7s} {'ratio':>6s} {'n_s':>7s} {'n_t':>6s}"
)


def format_row(r: dict) -> str:
    return (
        f"{r['mesh']:10s} {r['tris']:8d} {r['method']:8s} {r['points']:12s} {r['num_points']:8d} {r['found']:8d} "
        f"{r['checked']:7d} {r['wrong']:5d} {r['disagree']:9d} {r['max_diff']:9.1e} {r['mpts_ours']:7.3f} "
        f"{r['mpts_wp_mesh']:7.3f} {r['ratio']:6.2f} {r['n_s']:7.1f} {r['n_t']:6.2f}"
    )


def verdict(rows: list[dict]) -> tuple[str, bool]:
    """bench-points' `ray_bench.checked_verdict`."""
    return checked_verdict(rows, "float64", "points", "wp.Mesh differs from ours on {} points")


#: The exit status, for --help.
EPILOG = (f"Exit status 1 when one of the points checked (up to {ORACLE_POINTS} of each set, and as many where "
          "wp.Mesh differs) has an answer a float64 brute force finds wrong; 2 on an error in the options or a "
          "mesh; else 0. wp.Mesh's disagreements are reported, not judged: it finds nothing on some valid meshes.")


def main(argv=None) -> int:
    parser = mesh_method_parser(command_prog("bench-points"), __doc__.splitlines()[0], "--points", 200_000,
                                "points per set (default 200k)", EPILOG)
    parser.add_argument("--far-distance", type=far_distance, default=0.0,
                        help="also query points this many bounding-box diagonals from the mesh (default: none). "
                             "Past 256 box extents the search walks in float64")
    args = parser.parse_args(argv)
    return run_rows(parser, args, args.points, functools.partial(run, far_distance=args.far_distance), HEADER,
                    format_row,
                    "checked: points checked against the float64 brute force (an even sample and where wp.Mesh "
                    "differs), wrong: ours wrong among them; wp differ: points where wp.Mesh's answer differs from "
                    "ours; ratio = wp.mesh_query_point_no_sign time / ours (> 1: ours is faster); max diff = largest "
                    "distance difference over the box diagonal", verdict)
