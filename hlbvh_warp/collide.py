"""Mesh-mesh and self-intersection queries: host wrappers around ``kernels/collide.py``.

- `overlapping_pairs`: the broad phase. One thread per primitive of the smaller side walks the
  other side's BVH with the primitive's box (Karras, HPG 2012, Sec. 4): a count pass, a prefix
  sum, a write pass, no atomics. A self query keeps partners later in the tree's order only, and
  skips the subtrees that hold none.
- `intersecting_pairs`: the narrow phase on those candidates, one thread per pair, with the exact
  triangle-triangle test of ``kernels/collide.py``; self queries apply its neighbour rule.
- `triangles_intersect`: the same test on rows of two triangle arrays.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from . import inputs
from .bvh import Bvh, held, not_a_bvh
from .kernels import collide, traversal
from .query import _offsets, _require_mesh, _require_whole_boxes, view


def _check_tree(bvh, name: str, mesh: bool):
    if mesh:
        _require_mesh(bvh, name)
    elif not isinstance(bvh, Bvh):
        raise ValueError(not_a_bvh(name, bvh))
    _require_whole_boxes(bvh, name)


def _sides(a, b, name: str, mesh: bool):
    """(query side, tree side, swapped): the smaller side queries the larger one's tree, since a
    query costs about the log of the tree's size; ``swapped`` when the tree is ``a``."""
    _check_tree(a, name, mesh)
    if b is None:
        return a, a, False
    _check_tree(b, name, mesh)
    if a.device != b.device:
        raise ValueError(f"{name}() needs both BVHs on one device, got {a.device} and {b.device}")
    if b.num_prims >= a.num_prims:
        return a, b, False
    return b, a, True


def launch_box_pairs(queries: Bvh, tree: Bvh, self_pairs: bool, offsets, counts, out_pairs):
    """One pass of the box query: counts when ``out_pairs`` is empty, else the pairs at ``offsets``.

    The queries run in ``queries``' tree order (coherent walks); a self query also skips what
    earlier queries covered (``traversal.bvh_aabb_query``).
    """
    wp.launch(traversal.aabb_query_kernel, dim=queries.num_prims, device=tree.device,
              inputs=[view(tree), queries.prim_lowers, queries.prim_uppers, queries.prim_order, 1 if self_pairs else 0,
                      offsets, counts, out_pairs])


def _candidates(queries: Bvh, tree: Bvh, self_pairs: bool) -> wp.array:
    """Device array of ``(query prim, tree prim)`` pairs whose boxes overlap."""
    device = tree.device
    counts = wp.zeros(queries.num_prims, dtype=wp.int32, device=device)
    none = wp.empty(0, dtype=wp.vec2i, device=device)
    launch_box_pairs(queries, tree, self_pairs, counts, counts, none)
    offsets, total = _offsets(counts, "overlapping pairs")
    if total == 0:
        return none
    pairs = wp.empty(total, dtype=wp.vec2i, device=device)
    launch_box_pairs(queries, tree, self_pairs, offsets, counts, pairs)
    return pairs


def _sorted_pairs(pairs: np.ndarray, swapped: bool, self_pairs: bool) -> np.ndarray:
    pairs = pairs.astype(np.int64).reshape(-1, 2)
    if self_pairs:
        pairs = np.sort(pairs, axis=1)  # found in tree order: either id may come first
    elif swapped:
        pairs = pairs[:, ::-1]
    # One int64 key per pair sorts several times faster than a lexsort of the two columns.
    span = int(pairs[:, 1].max()) + 1 if len(pairs) else 1
    keys = np.sort(pairs[:, 0] * span + pairs[:, 1])
    return np.ascontiguousarray(np.stack([keys // span, keys % span], axis=1))


def overlapping_pairs(a: Bvh, b: Bvh | None = None) -> np.ndarray:
    """Pairs of primitives whose boxes overlap (closed boxes: touching counts): a broad phase.

    One thread per primitive of the smaller side walks the other side's BVH with the primitive's
    box, independently of the others: the broad phase of Karras (2012).

    Args:
        a, b: BVHs on one device, over meshes or bare boxes (`build_from_bounds`), from any
            object-split builder. ``b`` None asks for the pairs within ``a``.

    Returns:
        ``(K, 2)`` int64 pairs ``(prim of a, prim of b)``, sorted; within ``a``, ``i < j`` only.
    """
    with held(a, b):
        queries, tree, swapped = _sides(a, b, "overlapping_pairs", mesh=False)
        pairs = _candidates(queries, tree, b is None)
        if pairs.shape[0] == 0:
            return np.zeros((0, 2), np.int64)
        return _sorted_pairs(pairs.numpy(), swapped, b is None)


def intersecting_pairs(a: Bvh, b: Bvh | None = None) -> np.ndarray:
    """Pairs of triangles that intersect, touching included, decided exactly for the float32
    coordinates (``kernels/collide.py``).

    The candidates of `overlapping_pairs`, then one exact test per pair: every edge of each
    triangle against the other triangle in signed volumes (not Moeller's 1997 interval test nor
    Guigue & Devillers' 2003 cascade), every sign from Shewchuk's filtered exact predicates
    ("Adaptive Precision Floating-Point Arithmetic and Fast Robust Geometric Predicates", DCG 1997).

    Args:
        a, b: mesh BVHs on one device, from any object-split builder. ``b`` None asks for the
            self-intersections of ``a``: pairs touching only at vertex positions they share
            (coordinates equal, welded or not), or along a shared edge, are not reported;
            zero-area triangles are not reported against their neighbours; a duplicated face
            (the same three positions) is (`collide.neighbours_meet`).

    Returns:
        ``(K, 2)`` int64 pairs ``(face of a, face of b)``, sorted; within ``a``, ``i < j`` only.
    """
    with held(a, b):
        queries, tree, swapped = _sides(a, b, "intersecting_pairs", mesh=True)
        pairs = _candidates(queries, tree, b is None)
        if pairs.shape[0] == 0:
            return np.zeros((0, 2), np.int64)
        device = tree.device
        meets = wp.empty(pairs.shape[0], dtype=wp.int32, device=device)
        wp.launch(collide.triangle_pairs_kernel, dim=pairs.shape[0], device=device,
                  inputs=[queries.vertices, queries.faces, tree.vertices, tree.faces, pairs, 1 if b is None else 0,
                          meets])
        found = pairs.numpy()[meets.numpy() == 1]
    return _sorted_pairs(found, swapped, b is None)


def _triangle_rows(values, name: str) -> np.ndarray:
    arr = inputs._to_numpy(values, name)
    if arr.dtype.kind not in "fiu":
        raise ValueError(f"{name} must hold real numbers, got dtype {arr.dtype}")
    if arr.shape == (3, 3):
        arr = arr.reshape(1, 3, 3)
    if arr.ndim != 3 or arr.shape[1:] != (3, 3):
        raise ValueError(f"{name} must have shape (K, 3, 3): K triangles of three vertices, got {arr.shape}")
    if arr.dtype.kind in "iu":
        # Straight to float32, rounded once, as a mesh's vertices are (`inputs._check_points`):
        # through float64 an integer past 2^53 is rounded twice, to another float32 at times.
        return np.ascontiguousarray(arr.astype(np.float32))
    # Checked and narrowed from the given dtype, as a mesh's vertices are: through float64 a long
    # double is rounded twice (to another float32 at times), and one past float64's range would
    # be refused as the infinity it became. Checked as triangles, so that a NaN is named by
    # triangle and vertex (flattened, triangle 1's third vertex read "row 5").
    inputs.check_float32_range(arr, name)
    return np.ascontiguousarray(arr, dtype=np.float32)


def triangles_intersect(tri_a, tri_b, neighbours: bool = False, device=None) -> np.ndarray:
    """Whether triangle ``tri_a[k]`` and triangle ``tri_b[k]`` intersect, for every row k: the
    exact test of `intersecting_pairs` (edges against triangles, Shewchuk's predicates, DCG 1997).

    Args:
        tri_a, tri_b: ``(K, 3, 3)`` vertex coordinates (or one ``(3, 3)`` triangle each), narrowed
            to float32 first; the test is exact for those. Zero-area triangles are the segments
            or points they span.
        neighbours: apply the self-intersection rule of `intersecting_pairs` (contact at shared
            vertex positions does not count).
        device: the Warp device to run on (default: Warp's default device).

    Returns:
        ``(K,)`` bool.
    """
    if not isinstance(neighbours, (bool, np.bool_)):
        raise ValueError(f"neighbours must be True or False, got {neighbours!r}")
    ta, tb = _triangle_rows(tri_a, "tri_a"), _triangle_rows(tri_b, "tri_b")
    if ta.shape != tb.shape:
        raise ValueError(f"tri_a and tri_b differ in shape: {ta.shape} vs {tb.shape}")
    if ta.shape[0] == 0:
        return np.zeros(0, bool)
    device = wp.get_device(device)
    # As two soups of K faces each, row k against row k: the kernel `intersecting_pairs` runs.
    k = ta.shape[0]
    faces = wp.array(np.arange(3 * k, dtype=np.int32).reshape(k, 3), dtype=wp.int32, device=device)
    rows = wp.array(np.repeat(np.arange(k, dtype=np.int32), 2).reshape(k, 2), dtype=wp.vec2i, device=device)
    meets = wp.empty(k, dtype=wp.int32, device=device)
    wp.launch(collide.triangle_pairs_kernel, dim=k, device=device,
              inputs=[wp.array(ta.reshape(-1, 3), dtype=wp.vec3, device=device), faces,
                      wp.array(tb.reshape(-1, 3), dtype=wp.vec3, device=device), faces, rows, 1 if neighbours else 0,
                      meets])
    return meets.numpy() == 1
