"""``python -m hlbvh_warp bench-pairs``: overlapping triangle pairs per second against ``wp.mesh_query_aabb``.

For each mesh, one BVH per method and one ``wp.Mesh`` of the same triangles answer the same box
queries in the same process, one thread per query triangle:

- ``self``: every triangle's box against the mesh's own tree, each pair once (the broad phase of
  a self-intersection or self-collision check);
- ``moved``: the boxes of a copy of the mesh turned by 30 degrees about the vertical axis and
  moved by a tenth of its box diagonal, which passes through the mesh (two bodies in contact).

Answers are checked first. This package's are checked against a brute force that tests a query's
box against every triangle's box (`brute_force_partners`), exact: a box is the minimum and
maximum of a triangle's float32 corners and the overlap test compares boxes, neither of which
rounds. It checks an even sample of each scene's queries and, on ``moved``, every query whose
count ``wp.Mesh`` disagrees with (up to `ORACLE_QUERIES` of each). A query is wrong when its
count in the timed pass, or its partners in the pair listing the narrow phase reads
(`collide._candidates`), differ from the brute force's. On ``self`` a query counts the partners
at later positions of its tree's order and the listing names each pair once, so the pairs that
name a face in either place must be exactly the other faces whose boxes overlap its box. Wrong
queries are the exit status.

``wp.Mesh``'s counts are compared with this package's and reported, not judged. Warp's query may
return a face whose leaf overlaps but whose own box does not; its kernel tests the face's box, as
this package's does, so both count the same pairs. On ``moved`` a query disagrees when the counts
differ; on ``self`` the disagreement is the difference of the totals, since Warp's kernel keeps
partners with a larger face id and this package's those later in its tree's order (each pair once
either way), which skips the subtrees before the query's own leaf. Each count pass is timed as
the best of ``--repeats`` launches, interleaved.

The narrow phase (`intersecting_pairs`' exact triangle test, ``kernels/collide.py``) has no peer
in Warp: its row gives the time per candidate pair and how many pairs intersect.
"""

from __future__ import annotations

import pathlib

import numpy as np
import warp as wp

from .cli import command_prog
from .collide import _candidates, launch_box_pairs
from .ray_bench import best_times, checked_verdict, mesh_method_parser, run_rows
from .reference import FLOAT32_MAX


#: Queries of each scene checked against the brute force: this many evenly spaced, and as many of
#: the queries whose count wp.Mesh disagrees with. Each costs one pass over the mesh's boxes: about
#: 0.1 s for 512 queries on a 100k-triangle mesh.
ORACLE_QUERIES = 256
#: Query boxes tested against every box at once: 64 x 100k triangles is about 6 MB per temporary.
ORACLE_CHUNK = 64


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


def differing_queries(ours: np.ndarray, reference: np.ndarray, order: np.ndarray) -> np.ndarray:
    """Positions k of the queries whose counts differ, ours (query k on face ``order[k]``, tree
    order) against Warp's (query k on face k)."""
    return np.flatnonzero(ours != reference[order])


def count_disagreements(ours: np.ndarray, reference: np.ndarray, order: np.ndarray, self_pairs: bool) -> int:
    """Queries whose pair counts differ; for self pairs, the difference of the totals.

    Ours runs query k on face ``order[k]`` (tree order) and, for self pairs, keeps partners later in
    the tree's order; Warp's kernel runs query k on face k and keeps partners with a larger id.
    """
    if self_pairs:
        return abs(int(ours.sum(dtype=np.int64)) - int(reference.sum(dtype=np.int64)))
    return len(differing_queries(ours, reference, order))


def triangle_boxes(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every triangle's box from its float32 corners: a minimum and a maximum, exact."""
    corners = np.asarray(vertices, dtype=np.float32)[np.asarray(faces, dtype=np.int64)]
    return corners.min(axis=1), corners.max(axis=1)


def brute_force_partners(q_lo: np.ndarray, q_hi: np.ndarray, lowers: np.ndarray, uppers: np.ndarray,
                         chunk: int = ORACLE_CHUNK) -> list[np.ndarray]:
    """For each query box, the ids of the boxes ``(lowers, uppers)`` it overlaps, closed (touching
    counts), ascending: every pair tested."""
    partners = []
    # One axis at a time over contiguous rows: a third of the memory traffic of (queries, boxes, 3).
    lowers, uppers = np.ascontiguousarray(lowers.T), np.ascontiguousarray(uppers.T)
    for start in range(0, len(q_lo), chunk):
        lo, hi = q_lo[start:start + chunk], q_hi[start:start + chunk]
        meets = (lowers[0] <= hi[:, 0:1]) & (lo[:, 0:1] <= uppers[0])
        for axis in (1, 2):
            meets &= (lowers[axis] <= hi[:, axis:axis + 1]) & (lo[:, axis:axis + 1] <= uppers[axis])
        partners.extend(np.flatnonzero(row) for row in meets)
    return partners


def count_wrong(positions, counts, pairs, order, tree_order, query_boxes, tree_boxes, self_pairs: bool) -> int:
    """Queries at ``positions`` (of ``order``) whose count in ``counts`` or whose partners in the
    pair listing ``pairs`` ((query face, tree face) rows) differ from `brute_force_partners`'.

    A self query at position k counts the partners at positions after k in ``tree_order`` (the
    same tree's), and every pair is listed once: a face's partners are read from both columns.
    """
    faces = order[positions]
    expected = brute_force_partners(*(b[faces] for b in query_boxes), *tree_boxes)
    sampled = np.zeros(len(order), dtype=bool)
    sampled[faces] = True
    query_of, partner_of = pairs[:, 0], pairs[:, 1]

    def names_sampled(ids):
        # A wrong listing may hold ids past the mesh: those name no sampled face, and a sampled
        # face's query that lists one as a partner is wrong by the comparison below.
        return sampled[np.clip(ids, 0, len(sampled) - 1)] & (ids >= 0) & (ids < len(sampled))

    pick = names_sampled(query_of)
    listed_face, listed = [query_of[pick]], [partner_of[pick]]
    if self_pairs:
        pick = names_sampled(partner_of)
        listed_face.append(partner_of[pick])
        listed.append(query_of[pick])
        tree_position = np.empty(len(tree_order), dtype=np.int64)
        tree_position[tree_order] = np.arange(len(tree_order))
    listed_face, listed = np.concatenate(listed_face), np.concatenate(listed)
    by_face = np.lexsort((listed, listed_face))
    listed_face, listed = listed_face[by_face], listed[by_face]
    wrong = 0
    for k, face, partners in zip(positions, faces, expected):
        if self_pairs:
            partners = partners[partners != face]
            count = int((tree_position[partners] > k).sum())
        else:
            count = len(partners)
        mine = listed[np.searchsorted(listed_face, face):np.searchsorted(listed_face, face, side="right")]
        wrong += int(counts[k] != count or not np.array_equal(mine, partners))
    return wrong


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
    for scene, queries, query_vertices, self_pairs in (("self", bvh, vertices, 1), ("moved", other, moved, 0)):
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
        counts, ref = ours_counts.numpy(), ref_counts.numpy()
        order = queries.prim_order.numpy()
        disagree = count_disagreements(counts, ref, order, self_pairs == 1)
        pairs = _candidates(queries, bvh, self_pairs == 1)
        # Ours against the brute force: an even sample, and on "moved" where wp.Mesh disagrees,
        # since either answer may be the wrong one there (on "self" Warp's counts are per face id,
        # ours per tree position: only the totals compare).
        positions = np.linspace(0, n - 1, min(ORACLE_QUERIES, n)).astype(np.int64)
        if not self_pairs:
            positions = np.union1d(positions, differing_queries(counts, ref, order)[:ORACLE_QUERIES])
        wrong = count_wrong(positions, counts, pairs.numpy().reshape(-1, 2), order, bvh.prim_order.numpy(),
                            triangle_boxes(query_vertices, faces), triangle_boxes(vertices, faces), self_pairs == 1)
        t_ours, t_ref = best_times([ours, reference], repeats, device)

        # The narrow phase on every candidate pair, timed alone.
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
                "pairs": int(counts.sum(dtype=np.int64)),
                "checked": int(len(positions)),
                "wrong": wrong,
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
    f"{'mesh':10s} {'tris':>8s} {'method':8s} {'scene':6s} {'queries':>8s} {'pairs':>9s} {'checked':>7s} {'wrong':>5s} "
    f"{'wp differ':>9s} {'Mq/s':>7s} {'wp.Mesh':>7s} {'ratio':>6s} {'ns/pair':>8s} {'meet':>7s}"
)


def format_row(r: dict) -> str:
    return (
        f"{r['mesh']:10s} {r['tris']:8d} {r['method']:8s} {r['scene']:6s} {r['queries']:8d} {r['pairs']:9d} "
        f"{r['checked']:7d} {r['wrong']:5d} {r['disagree']:9d} {r['mq_ours']:7.3f} {r['mq_wp_mesh']:7.3f} "
        f"{r['ratio']:6.2f} {r['ns_per_pair']:8.1f} {r['intersecting']:7d}"
    )


def verdict(rows: list[dict]) -> tuple[str, bool]:
    """bench-pairs' `ray_bench.checked_verdict` (on ``self`` a disagreement is a difference of
    totals, not of queries)."""
    return checked_verdict(rows, "exact", "queries", "wp.Mesh's disagreements with ours: {}")


#: The exit status, for --help.
EPILOG = (f"Exit status 1 when one of the queries checked (up to {ORACLE_QUERIES} of each scene, and on moved as "
          "many where wp.Mesh differs) has a pair count or partners other than an exact brute force's; 2 on an "
          "error in the options or a mesh; else 0. wp.Mesh's disagreements are reported, not judged.")


def main(argv=None) -> int:
    from . import api

    parser = mesh_method_parser(command_prog("bench-pairs"), __doc__.splitlines()[0], epilog=EPILOG)
    args = parser.parse_args(argv)
    # A builder that cuts triangles (sbvh) lists some in several leaves, each under a box of its
    # part only; the pair queries refuse such trees (`collide`), which surfaced only after the
    # build, as a NumPy broadcast error in the disagreement count.
    split = [m for m in dict.fromkeys(args.method or []) if api.needs_mesh(m)]
    if split:
        parser.error(f"--method {', '.join(split)}: spatial-split trees list a triangle in several leaves, which the "
                     "pair queries do not take; choose an object-split method (hlbvh, lbvh, hlbvh_sah, sweep_sah, ...)")
    return run_rows(parser, args, 0, run, HEADER, format_row,
                    "checked: queries checked against the exact brute force (an even sample and, on moved, where "
                    "wp.Mesh differs), wrong: ours wrong among them (count or partners); wp differ: queries whose "
                    "count differs from wp.Mesh's (self: the difference of the totals); ratio = wp.mesh_query_aabb "
                    "time / ours (> 1: ours is faster); ns/pair = exact triangle test per candidate pair; meet = "
                    "pairs that intersect (self: beyond shared vertices)", verdict)
