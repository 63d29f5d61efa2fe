"""``python -m hlbvh_warp bench-points``: closest-point queries per second against ``wp.mesh_query_point_no_sign``.

For each mesh, one BVH per method and one ``wp.Mesh`` of the same triangles answer the same
points in the same process:

- ``box``: uniform in the bounding box grown by a fifth on each side: most lie far from the
  surface, where many boxes are about as near as the nearest triangle and the search opens the
  most nodes;
- ``near``: mesh vertices moved by a normal offset of 1% of the box diagonal, the points a
  collision or a projection step asks about;
- ``near-bounded``: the same with ``max_dist`` = 5% of the diagonal, as a contact query bounds
  its search.

Distances are compared first: a point disagrees when the two distances differ by more than 1e-5
of the box diagonal (Warp computes in float32, which on thin triangles loses more than a few
ulps; this package computes the distance in float64, see ``kernels/proximity.py``), or when one
finds a triangle and the other does not. Then each kernel is timed as the best of ``--repeats``
launches, interleaved, and one fixed-format row is printed per run.
"""

from __future__ import annotations

import pathlib

import numpy as np
import warp as wp

from .ray_bench import best_times, mesh_method_parser, run_rows

DISAGREE_RTOL = 1e-5


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
    return {
        "box": (box.astype(np.float32), float("inf")),
        "near": (near.astype(np.float32), float("inf")),
        "near-bounded": (near.astype(np.float32), 0.05 * diag),
    }


def count_disagreements(d_a, prim_a, d_b, prim_b, scale: float, rtol: float = DISAGREE_RTOL) -> int:
    found_a, found_b = prim_a >= 0, prim_b >= 0
    with np.errstate(invalid="ignore"):  # inf - inf where neither found anything
        close = np.abs(d_a.astype(np.float64) - d_b.astype(np.float64)) <= rtol * scale
    agree = (~found_a & ~found_b) | (found_a & found_b & close)
    return int((~agree).sum())


def run(mesh_path: pathlib.Path, vertices: np.ndarray, faces: np.ndarray, method: str, num_points: int, repeats: int,
        device, seed: int = 0, max_leaf_size: int = 1) -> list[dict]:
    """One row per point set on the mesh of ``mesh_path``, read and checked (`cli.read_mesh`)."""
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
    for kind, (points, max_dist) in point_sets(rng, vertices, num_points).items():
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
        disagree = count_disagreements(d_ours, p_ours, d_ref, p_ref, scale)
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
                "disagree": disagree,
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
    f"{'mesh':10s} {'tris':>8s} {'method':8s} {'points':12s} {'num':>8s} {'found':>8s} {'disagree':>8s} "
    f"{'max diff':>9s} {'Mpts/s':>7s} {'wp.Mesh':>7s} {'ratio':>6s} {'n_s':>7s} {'n_t':>6s}"
)


def format_row(r: dict) -> str:
    return (
        f"{r['mesh']:10s} {r['tris']:8d} {r['method']:8s} {r['points']:12s} {r['num_points']:8d} {r['found']:8d} "
        f"{r['disagree']:8d} {r['max_diff']:9.1e} {r['mpts_ours']:7.3f} {r['mpts_wp_mesh']:7.3f} {r['ratio']:6.2f} "
        f"{r['n_s']:7.1f} {r['n_t']:6.2f}"
    )


def main(argv=None) -> int:
    parser = mesh_method_parser("python -m hlbvh_warp bench-points", __doc__.splitlines()[0], "--points", 200_000,
                                "points per set (default 200k)")
    args = parser.parse_args(argv)
    return run_rows(parser, args, args.points, run, HEADER, format_row,
                    "ratio = wp.mesh_query_point_no_sign time / ours (> 1: ours is faster); max diff = largest "
                    "distance difference over the box diagonal")
