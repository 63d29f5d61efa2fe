"""Independent references the tests compare against: float64 NumPy, no project code."""

from __future__ import annotations

import numpy as np


def brute_force_closest_hit(vertices, faces, origins, directions, t_max=np.inf, chunk=64):
    """Closest hit of every ray against every triangle, Moller-Trumbore in float64.

    Returns (t, prim) with (inf, -1) for a miss. Triangles are tested in chunks of rays so memory
    stays at chunk * F.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    e1, e2 = b - a, c - a
    o_all = np.asarray(origins, dtype=np.float64)
    d_all = np.asarray(directions, dtype=np.float64)
    t_out = np.full(len(o_all), np.inf)
    p_out = np.full(len(o_all), -1, dtype=np.int64)
    with np.errstate(all="ignore"):
        for s in range(0, len(o_all), chunk):
            o = o_all[s : s + chunk, None, :]
            d = d_all[s : s + chunk, None, :]
            p = np.cross(d, e2[None])
            det = np.einsum("rfk,fk->rf", p, e1)
            inv = 1.0 / det
            tv = o - a[None]
            u = np.einsum("rfk,rfk->rf", tv, p) * inv
            q = np.cross(tv, e1[None])
            w = np.einsum("rk,rfk->rf", d[:, 0], q) * inv
            t = np.einsum("rfk,fk->rf", q, e2) * inv
            eps = 1e-12
            ok = (det != 0) & (u >= -eps) & (w >= -eps) & (u + w <= 1 + eps) & (t > 0) & (t < t_max)
            ok &= np.isfinite(t)
            t = np.where(ok, t, np.inf)
            idx = np.argmin(t, axis=1)
            best = t[np.arange(len(idx)), idx]
            t_out[s : s + chunk] = best
            p_out[s : s + chunk] = np.where(np.isfinite(best), idx, -1)
    return t_out, p_out


def assert_hits_match(t, prim, t_ref, prim_ref, rtol=1e-5):
    """Same hit primitive, or (on ties and near-ties) the same t within rtol; misses agree."""
    t = np.asarray(t, dtype=np.float64)
    hit, hit_ref = prim >= 0, prim_ref >= 0
    assert (hit == hit_ref).all(), f"{int((hit != hit_ref).sum())} rays disagree on hit/miss"
    same = prim == prim_ref
    close = np.isclose(t, t_ref, rtol=rtol, atol=0.0) | (~hit)
    bad = ~(same | close)
    assert not bad.any(), f"{int(bad.sum())} rays hit a different primitive at a different t"
    both = hit & hit_ref
    assert np.allclose(t[both], t_ref[both], rtol=rtol, atol=0.0), "hit distances differ"


def check_tree_invariants(tree: dict, num_prims: int, max_leaf_size: int = 1, exact_node_count=None):
    """Each primitive exactly once, leaf ranges partition prim_order, children inside parents."""
    left, right = tree["node_left"], tree["node_right"]
    begin, end = tree["node_begin"], tree["node_end"]
    lo, hi = tree["node_lowers"], tree["node_uppers"]
    order = tree["prim_order"]
    n_nodes = left.shape[0]
    assert np.array_equal(np.sort(order), np.arange(num_prims)), "prim_order is not a permutation"
    assert begin[0] == 0 and end[0] == num_prims, "the root does not cover every primitive"
    interior = np.nonzero(left >= 0)[0]
    leaves = np.nonzero(left < 0)[0]
    assert (right[leaves] < 0).all(), "a leaf has a right child"
    assert (right[interior] >= 0).all(), "an interior node lacks a right child"
    # Every node but the root is the child of exactly one interior node.
    kids = np.concatenate([left[interior], right[interior]])
    assert np.array_equal(np.sort(kids), np.arange(1, n_nodes)), "children do not cover nodes 1..n-1 once"
    # Child ranges are adjacent halves of the parent range, both non-empty.
    assert (begin[left[interior]] == begin[interior]).all()
    assert (end[left[interior]] == begin[right[interior]]).all()
    assert (end[right[interior]] == end[interior]).all()
    assert (end > begin).all(), "an empty node"
    # The Bvh layout: children numbered after their parent, and parents linked back.
    assert (left[interior] > interior).all() and (right[interior] > interior).all(), "a child before its parent"
    if "node_parent" in tree:
        parent = tree["node_parent"]
        assert parent[0] == -1, "the root has a parent"
        assert (parent[left[interior]] == interior).all() and (parent[right[interior]] == interior).all(), \
            "a child's parent link does not name its parent"
    # Leaves partition [0, N).
    lb = np.sort(begin[leaves])
    le = np.sort(end[leaves])
    assert lb[0] == 0 and le[-1] == num_prims and np.array_equal(lb[1:], le[:-1]), "leaf ranges do not partition"
    assert (end[leaves] - begin[leaves] <= max_leaf_size).all() or exact_node_count is None, "leaf too large"
    # Boxes: children inside parents; leaves contain their primitives.
    for child in (left[interior], right[interior]):
        assert (lo[child] >= lo[interior]).all() and (hi[child] <= hi[interior]).all(), "child box outside parent"
    plo, phi = tree["prim_lowers"][order], tree["prim_uppers"][order]
    leaf_of_pos = np.repeat(leaves[np.argsort(begin[leaves])], np.diff(np.append(lb, num_prims)))
    assert (plo >= lo[leaf_of_pos]).all() and (phi <= hi[leaf_of_pos]).all(), "primitive outside its leaf box"
    if exact_node_count is not None:
        assert n_nodes == exact_node_count, f"{n_nodes} nodes, expected {exact_node_count}"


def random_soup(rng, num_tris, scale=1.0):
    v = (rng.random((num_tris * 3, 3)) * scale).astype(np.float32)
    return v, np.arange(num_tris * 3, dtype=np.int32).reshape(-1, 3)


def random_rays(rng, vertices, num_rays):
    """Rays from outside the bounding box aimed at random points of it."""
    v = np.asarray(vertices, dtype=np.float64)
    lo, hi = v.min(0), v.max(0)
    center, radius = 0.5 * (lo + hi), 0.5 * np.linalg.norm(hi - lo) + 1e-6
    dirs = rng.normal(size=(num_rays, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origins = center - 2.0 * radius * dirs
    targets = lo + rng.random((num_rays, 3)) * (hi - lo)
    d = targets - origins
    return origins.astype(np.float32), (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


def numpy_node_boxes(tree: dict, lowers: np.ndarray, uppers: np.ndarray):
    """Every node's box as the union of the boxes of the primitives in its range (min and max are
    exact, so a float32 tree's boxes must equal these of the same floats)."""
    order = tree["prim_order"]
    ranges = list(zip(tree["node_begin"], tree["node_end"]))
    lo = np.array([lowers[order[b:e]].min(axis=0) for b, e in ranges])
    hi = np.array([uppers[order[b:e]].max(axis=0) for b, e in ranges])
    return lo, hi


def brute_overlaps(lowers, uppers, q_lo, q_hi):
    """(Q, N) closed-box overlap of every query box with every box: touching counts."""
    return ((lowers[None] <= q_hi[:, None]) & (uppers[None] >= q_lo[:, None])).all(-1)
