"""``python -m hlbvh_warp bench-pairs``: overlapping triangle pairs per second against ``wp.mesh_query_aabb``.

For each mesh, one BVH per method and one ``wp.Mesh`` of the same triangles answer the same box
queries in the same process, one thread per query triangle:

- ``self``: every triangle's box against the mesh's own tree, each pair once (the broad phase of
  a self-intersection or self-collision check);
- ``moved``: the boxes of a copy of the mesh turned by 30 degrees about the vertical axis and
  moved by a tenth of its box diagonal, which passes through the mesh (two bodies in contact).

Warp's query may return a face whose leaf overlaps but whose own box does not; its kernel tests
the face's box, as this package's does, so both count the same pairs. On ``moved`` a query
disagrees when the counts differ; on ``self`` the disagreement is the difference of the totals,
since Warp's kernel keeps partners with a larger face id and this package's those later in its
tree's order (each pair once either way), which skips the subtrees before the query's own leaf.
Each count pass is timed as the best of ``--repeats`` launches, interleaved.

The narrow phase (`intersecting_pairs`' exact triangle test, ``kernels/collide.py``) has no peer
in Warp: its row gives the time per candidate pair and how many pairs intersect.
"""

from __future__ import annotations

import pathlib

import numpy as np
import warp as wp

from .collide import _candidates, launch_box_pairs
from .ray_bench import best_times, mesh_method_parser, run_rows


#: Largest finite float32: the trees are built over float32 coordinates.
FLOAT32_MAX = float(np.finfo(np.float32).max)


def moved_copy(vertices: np.ndarray) -> np.ndarray:
    """The mesh turned by 30 degrees about y through its centre and moved by a tenth of its diagonal.

    Computed in float64: a finite float32 mesh whose box spans more than float32's range (corners
    near -3e38 and +3e38) overflowed in its own diagonal, and the build then blamed the file for
    the NaN this made.

    Raises:
        ValueError: a vertex has a NaN or Inf coordinate, or the moved copy leaves float32's range
            (a finite mesh reaching near +-3.4e38, which the turn's corners or the shift push past
            it; the mesh itself is not at fault then).
    """
    v = np.asarray(vertices, dtype=np.float64)
    if not np.isfinite(v).all():
        # Checked first: a NaN made the shift NaN, and the message below blamed float32's range.
        row = int(np.argwhere(~np.isfinite(v))[0][0])
        raise ValueError(f"the mesh has a NaN or Inf coordinate (first at vertex {row}: {v[row].tolist()})")
    lo, hi = v.min(0), v.max(0)
    center = 0.5 * (lo + hi)
    angle = np.radians(30.0)
    c, s = np.cos(angle), np.sin(angle)
    turn = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    shift = 0.1 * np.linalg.norm(hi - lo) * np.array([1.0, 0.0, 0.0])
    moved = (v - center) @ turn.T + center + shift
    largest = float(np.abs(moved).max())
    if not largest <= FLOAT32_MAX:
        raise ValueError(f"the benchmark's moved copy of the mesh (turned by 30 degrees and shifted by {shift[0]:.3g} "
                         f"along x) overflows float32: a coordinate reaches {largest:.3g}, past {FLOAT32_MAX:.3g}; "
                         "the mesh is finite, but too near float32's limit for the 'moved' scene")
    return moved.astype(np.float32)


def count_disagreements(ours: np.ndarray, reference: np.ndarray, order: np.ndarray, self_pairs: bool) -> int:
    """Queries whose pair counts differ; for self pairs, the difference of the totals.

    Ours runs query k on face ``order[k]`` (tree order) and, for self pairs, keeps partners later in
    the tree's order; Warp's kernel runs query k on face k and keeps partners with a larger id.
    """
    if self_pairs:
        return abs(int(ours.sum(dtype=np.int64)) - int(reference.sum(dtype=np.int64)))
    by_face = np.empty_like(ours)
    by_face[order] = ours
    return int((by_face != reference).sum())


def run(mesh_path: pathlib.Path, vertices: np.ndarray, faces: np.ndarray, method: str, count: int, repeats: int,
        device, seed: int = 0, max_leaf_size: int = 1) -> list[dict]:
    """One row per scene on the mesh of ``mesh_path``, read and checked (`cli.read_mesh`); every
    triangle queries (``count`` and ``seed`` are unused: the scenes are fixed)."""
    from . import api
    from .config import BuildConfig
    from .kernels import collide

    # Before any build: a copy that cannot be moved within float32 is named before the work.
    try:
        moved = moved_copy(vertices)
    except ValueError as error:
        raise ValueError(f"{mesh_path}: {error}") from None
    config = BuildConfig(max_leaf_size=max_leaf_size)
    bvh = api.build(vertices, faces, method=method, device=device, config=config)
    points = wp.array(vertices, dtype=wp.vec3, device=device)
    indices = wp.array(faces.ravel(), dtype=wp.int32, device=device)
    wmesh = wp.Mesh(points=points, indices=indices)
    other = api.build(moved, faces, method=method, device=device, config=config)
    rows = []
    for scene, queries, self_pairs in (("self", bvh, 1), ("moved", other, 0)):
        n = faces.shape[0]
        ours_counts = wp.empty(n, dtype=wp.int32, device=device)
        ref_counts = wp.empty(n, dtype=wp.int32, device=device)
        none = wp.empty(0, dtype=wp.vec2i, device=device)

        def ours():
            launch_box_pairs(queries, bvh, self_pairs == 1, ours_counts, ours_counts, none)

        def reference():
            wp.launch(collide.warp_mesh_box_pairs_kernel, dim=n, device=device,
                      inputs=[wmesh.id, points, indices, queries.prim_lowers, queries.prim_uppers, self_pairs,
                              ref_counts])

        ours()
        reference()
        disagree = count_disagreements(ours_counts.numpy(), ref_counts.numpy(), queries.prim_order.numpy(),
                                       self_pairs == 1)
        t_ours, t_ref = best_times([ours, reference], repeats, device)

        # The narrow phase on every candidate pair, timed alone.
        pairs = _candidates(queries, bvh, self_pairs == 1)
        meets = wp.empty(max(pairs.shape[0], 1), dtype=wp.int32, device=device)

        def narrow():
            wp.launch(collide.triangle_pairs_kernel, dim=pairs.shape[0], device=device,
                      inputs=[queries.vertices, queries.faces, bvh.vertices, bvh.faces, pairs, self_pairs, meets])

        (t_narrow,) = best_times([narrow], repeats, device)
        num_pairs = pairs.shape[0]
        rows.append(
            {
                "mesh": mesh_path.stem,
                "tris": faces.shape[0],
                "method": method,
                "scene": scene,
                "queries": n,
                "pairs": int(ours_counts.numpy().sum()),
                "disagree": disagree,
                "mq_ours": n / t_ours / 1e6,
                "mq_wp_mesh": n / t_ref / 1e6,
                "ratio": t_ref / t_ours,
                "ns_per_pair": 1e9 * t_narrow / max(num_pairs, 1),
                "intersecting": int(meets.numpy()[:num_pairs].sum()),
            }
        )
    return rows


HEADER = (
    f"{'mesh':10s} {'tris':>8s} {'method':8s} {'scene':6s} {'queries':>8s} {'pairs':>9s} {'disagree':>8s} "
    f"{'Mq/s':>7s} {'wp.Mesh':>7s} {'ratio':>6s} {'ns/pair':>8s} {'meet':>7s}"
)


def format_row(r: dict) -> str:
    return (
        f"{r['mesh']:10s} {r['tris']:8d} {r['method']:8s} {r['scene']:6s} {r['queries']:8d} {r['pairs']:9d} "
        f"{r['disagree']:8d} {r['mq_ours']:7.3f} {r['mq_wp_mesh']:7.3f} {r['ratio']:6.2f} "
        f"{r['ns_per_pair']:8.1f} {r['intersecting']:7d}"
    )


def main(argv=None) -> int:
    from . import api

    parser = mesh_method_parser("python -m hlbvh_warp bench-pairs", __doc__.splitlines()[0])
    args = parser.parse_args(argv)
    # A builder that cuts triangles (sbvh) lists some in several leaves, each under a box of its
    # part only; the pair queries refuse such trees (`collide`), which surfaced only after the
    # build, as a NumPy broadcast error in the disagreement count.
    split = [m for m in dict.fromkeys(args.method or []) if api.needs_mesh(m)]
    if split:
        parser.error(f"--method {', '.join(split)}: spatial-split trees list a triangle in several leaves, which the "
                     "pair queries do not take; choose an object-split method (hlbvh, lbvh, hlbvh_sah, sweep_sah, ...)")
    return run_rows(parser, args, 0, run, HEADER, format_row,
                    "ratio = wp.mesh_query_aabb time / ours (> 1: ours is faster); ns/pair = exact triangle test "
                    "per candidate pair; meet = pairs that intersect (self: beyond shared vertices)")
