"""Independent references the tests compare against: float64 NumPy, no project code."""

from __future__ import annotations

from fractions import Fraction

import numpy as np


def brute_force_closest_hit(vertices, faces, origins, directions, t_max=np.inf, chunk=64):
    """Closest hit of every ray against every triangle, Moller-Trumbore in float64.

    Returns (t, prim) with (inf, -1) for a miss. Triangles are tested in chunks of rays so memory
    stays at chunk * F. ``t_max``: one number or one per ray.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    e1, e2 = b - a, c - a
    o_all = np.asarray(origins, dtype=np.float64)
    d_all = np.asarray(directions, dtype=np.float64)
    limits = np.broadcast_to(np.asarray(t_max, dtype=np.float64), (len(o_all),))
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
            ok = (det != 0) & (u >= -eps) & (w >= -eps) & (u + w <= 1 + eps) & (t > 0)
            ok &= t < limits[s : s + chunk, None]
            ok &= np.isfinite(t)
            t = np.where(ok, t, np.inf)
            idx = np.argmin(t, axis=1)
            best = t[np.arange(len(idx)), idx]
            t_out[s : s + chunk] = best
            p_out[s : s + chunk] = np.where(np.isfinite(best), idx, -1)
    return t_out, p_out


def numpy_all_hits(vertices, faces, origins, directions, t_max):
    """Every (ray, triangle) hit with t in (0, t_max), Moller-Trumbore in float64; the t of each pair,
    and how far inside its triangle the crossing lies (the least barycentric)."""
    v = np.asarray(vertices, np.float64)
    a, b, c = (v[np.asarray(faces)[:, k]] for k in range(3))
    e1, e2 = b - a, c - a
    o = np.asarray(origins, np.float64)[:, None]
    d = np.asarray(directions, np.float64)[:, None]
    with np.errstate(all="ignore"):
        p = np.cross(d, e2[None])
        det = np.einsum("rfk,fk->rf", p, e1)
        tv = o - a[None]
        u = np.einsum("rfk,rfk->rf", tv, p) / det
        q = np.cross(tv, e1[None])
        w = np.einsum("rfk,rfk->rf", np.broadcast_to(d, q.shape), q) / det
        t = np.einsum("rfk,fk->rf", q, e2) / det
        margin = np.minimum(np.minimum(u, w), 1 - u - w)
    hit = (det != 0) & (margin >= 0) & (t > 0) & (t < t_max)
    return hit, t, margin


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


def nested_shells():
    """Nested shells and a box beside them: most rays cross several surfaces, so a range or an
    ignored triangle changes which one a ray finds. ``(vertices, faces)`` as float32 and int32."""
    import trimesh

    outer = trimesh.creation.icosphere(subdivisions=3)
    inner = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    box = trimesh.creation.box(extents=(0.5, 0.5, 0.5)).apply_translation((1.6, 0, 0))
    mesh = trimesh.util.concatenate([outer, inner, box])
    return np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)


def expected_range_hits(verts, faces, o, d, t_min, ignore, t_max=np.inf, scale=None):
    """The float64 closest hit in (t_min, t_max) on any triangle but the ray's ``ignore``, and
    which rays are ambiguous: a crossing within float32 error of t_min, of a finite t_max or of a
    triangle's edge (the oracle is not watertight), or two crossings at nearly one t (within 1e-5
    of ``scale``, by default of the distance)."""
    hit, t, margin = numpy_all_hits(verts, faces, o, d, np.inf)
    lows = np.broadcast_to(np.asarray(t_min, np.float64), (len(o),))[:, None]
    highs = np.broadcast_to(np.asarray(t_max, np.float64), (len(o),))[:, None]
    skips = np.broadcast_to(np.asarray(ignore), (len(o),))[:, None]
    others = np.arange(len(faces))[None] != skips
    counted = hit & (t > lows) & (t < highs) & others
    t_counted = np.where(counted, t, np.inf)
    prim = np.argmin(t_counted, axis=1)
    best = t_counted[np.arange(len(o)), prim]
    prim = np.where(np.isfinite(best), prim, -1)
    near_end = hit & others & (np.abs(t - lows) <= 1e-4 * np.maximum(1.0, lows))
    near_end |= hit & others & np.isfinite(highs) & (np.abs(t - highs) <= 1e-4 * np.maximum(1.0, highs))
    near_edge = others & (margin > -1e-6) & (margin < 1e-6) & (t > 0)
    second = np.sort(t_counted, axis=1)[:, 1] if len(faces) > 1 else np.full(len(o), np.inf)
    with np.errstate(invalid="ignore"):
        tie = np.isfinite(second) & (second - best <= 1e-5 * (np.maximum(1.0, best) if scale is None else scale))
    ambiguous = near_end.any(axis=1) | near_edge.any(axis=1) | tie
    return best, prim, ambiguous


def assert_range_hits_match(t, prim, best, prim_ref, ambiguous):
    """The hits of a ray range agree with `expected_range_hits` on every ray it does not call
    ambiguous (the same triangle, t within float32 error), which must be most of them."""
    clear = ~ambiguous
    assert clear.sum() > 0.8 * len(prim), "too many ambiguous rays for the comparison to mean anything"
    assert np.array_equal(prim[clear], prim_ref[clear]), f"{int((prim[clear] != prim_ref[clear]).sum())} rays differ"
    hit = clear & (prim_ref >= 0)
    np.testing.assert_allclose(t[hit], best[hit], rtol=1e-5)


def crossings(verts, faces, o, d):
    """Each ray's first and second crossing distances in float64 (inf where there is none)."""
    hit, t, _ = numpy_all_hits(verts, faces, o, d, np.inf)
    ts = np.sort(np.where(hit, t, np.inf), axis=1)
    return ts[:, 0], ts[:, 1]


def crossings_prim(verts, faces, o, d):
    """The triangle each ray crosses first (float64), -1 for none."""
    hit, t, _ = numpy_all_hits(verts, faces, o, d, np.inf)
    t = np.where(hit, t, np.inf)
    prim = np.argmin(t, axis=1)
    return np.where(np.isfinite(t[np.arange(len(o)), prim]), prim, -1)


def directions_off_surface(rng, verts, faces, prims):
    """A random unit direction from each of the triangles ``prims`` into either side of its
    surface, never close to its plane (secondary rays leaving a hit point), as float32."""
    tri = np.asarray(verts, np.float64)[np.asarray(faces)[prims]]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    raw = rng.normal(size=normal.shape)
    raw -= 0.8 * (raw * normal).sum(1, keepdims=True) * normal
    raw += np.where(rng.random((len(raw), 1)) < 0.5, 0.3, -0.3) * normal
    return (raw / np.linalg.norm(raw, axis=1, keepdims=True)).astype(np.float32)


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
    assert (end[leaves] - begin[leaves] <= max_leaf_size).all(), "leaf too large"
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


def _hull_area_2d(points: np.ndarray, scale: float = 1.0) -> float:
    """Area of the convex hull of 2D points (Andrew's monotone chain, shoelace); coincident points
    are merged at 15 digits of `scale`, the size of the coordinates (absolute digits merged every
    point of a 1e-30 triangle into one)."""
    pts = sorted(set(map(tuple, np.round(np.asarray(points) / scale, 15))))
    if len(pts) < 3:
        return 0.0

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower, upper = [], []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    hull = np.array(lower[:-1] + upper[:-1])
    if len(hull) < 3:
        return 0.0
    x, y = hull[:, 0], hull[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))) * scale * scale


def triangle_box_area(tri, lower, upper, tol=1e-12) -> float:
    """Area of a triangle inside a closed box, in float64, as the convex hull of the corners of
    their intersection: the triangle's vertices in the box, its edges' crossings of the box's
    planes, and the box's edges' (and corners') points on the triangle. Not a polygon clipper."""
    tri = np.asarray(tri, dtype=np.float64)
    lo = np.asarray(lower, dtype=np.float64)
    hi = np.asarray(upper, dtype=np.float64)
    a, b, c = tri
    normal = np.cross(b - a, c - a)
    twice = np.linalg.norm(normal)
    if twice == 0.0:
        return 0.0
    # Tolerances relative to the coordinates' size, at any scale (a floor of 1 made them
    # absolute below it: a 1e-5 triangle came out 1% off, a 1e-30 one empty).
    scale = max(np.abs(tri).max(), np.abs(lo).max(), np.abs(hi).max())
    eps = tol * scale
    longest = max(np.linalg.norm(b - a), np.linalg.norm(c - b), np.linalg.norm(a - c))

    def in_box(p):
        return bool(np.all(p >= lo - eps) and np.all(p <= hi + eps))

    def on_triangle(p):
        # Barycentric coordinates from sub-triangle areas, signed along the normal.
        n = normal / twice
        if abs(np.dot(p - a, n)) > eps:
            return False
        w = [np.dot(np.cross(c - b, p - b), n), np.dot(np.cross(a - c, p - c), n),
             np.dot(np.cross(b - a, p - a), n)]
        # Each w is an edge times a difference of coordinates, whose rounding is about eps: the
        # slack scales with the longest edge (eps * scale let a corner off a small triangle far
        # from the origin count as on it, and doubled its area in a 1e4 box of side 2^-10).
        return min(w) >= -eps * longest

    points = [p for p in tri if in_box(p)]
    for p, q in ((a, b), (b, c), (c, a)):
        for axis in range(3):
            if p[axis] == q[axis]:
                continue
            for bound in (lo[axis], hi[axis]):
                t = (bound - p[axis]) / (q[axis] - p[axis])
                if 0.0 <= t <= 1.0:
                    x = p + t * (q - p)
                    x[axis] = bound
                    if in_box(x):
                        points.append(x)
    corners = np.array([[(lo, hi)[(k >> j) & 1][j] for j in range(3)] for k in range(8)])
    points += [p for p in corners if on_triangle(p)]
    for k in range(8):
        for j in range(3):
            if (k >> j) & 1:
                continue
            p, q = corners[k], corners[k | (1 << j)]
            denom = np.dot(q - p, normal)
            if denom == 0.0:
                continue
            t = np.dot(a - p, normal) / denom
            if 0.0 <= t <= 1.0:
                x = p + t * (q - p)
                if on_triangle(x):
                    points.append(x)
    if len(points) < 3:
        return 0.0
    # Coordinates in the triangle's plane.
    u = (b - a) / np.linalg.norm(b - a)
    w = np.cross(normal / twice, u)
    pts = np.array(points) - a
    return _hull_area_2d(np.stack([pts @ u, pts @ w], axis=1), scale)


def numpy_end_point_overlap(tree: dict, vertices, faces, t1=1.0, t2=1.0, node_boxes=None):
    """EPO (Aila, Karras & Laine 2013) of a tree by brute force over every (node, triangle):
    (sum over nodes of term(n) * area of the foreign triangles inside box(n)) / total area, with
    term(n) = 2 t1 (interior) or t2 * N (leaf; N counts references). A triangle is foreign to n
    when no entry of n's range of prim_order names it (a spatial-split tree lists some triangles
    in several leaves). Node boxes are rebuilt from the whole triangles, or taken from
    ``node_boxes`` = (lowers, uppers) (a spatial-split tree's boxes bound parts of triangles).
    Returns (epo, per_node)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    tris = v[f]
    left, begin, end, order = tree["node_left"], tree["node_begin"], tree["node_end"], tree["prim_order"]
    areas = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
    tri_lo, tri_hi = tris.min(axis=1), tris.max(axis=1)
    per_node = np.zeros(len(left))
    for n in range(len(left)):
        own = order[begin[n]:end[n]]
        if node_boxes is None:
            lo, hi = tri_lo[own].min(0), tri_hi[own].max(0)
        else:
            lo, hi = (np.asarray(b[n], dtype=np.float64) for b in node_boxes)
        foreign = np.setdiff1d(np.arange(len(f)), own)
        meets = foreign[np.all(tri_lo[foreign] <= hi, axis=1) & np.all(tri_hi[foreign] >= lo, axis=1)]
        overlap = sum(triangle_box_area(tris[p], lo, hi) for p in meets)
        term = 2.0 * t1 if left[n] >= 0 else t2 * (end[n] - begin[n])
        per_node[n] = term * overlap
    return per_node.sum() / areas.sum(), per_node


def triangle_slab_bounds(tri, axis: int, lower: float, upper: float):
    """Bounding box (float64) of the part of a triangle with lower <= x[axis] <= upper: its
    vertices in the slab and its edges' crossings of the two planes. None when they miss."""
    tri = np.asarray(tri, dtype=np.float64)
    points = [p for p in tri if lower <= p[axis] <= upper]
    for i in range(3):
        p, q = tri[i], tri[(i + 1) % 3]
        if p[axis] == q[axis]:
            continue
        for bound in (lower, upper):
            t = (bound - p[axis]) / (q[axis] - p[axis])
            if 0.0 < t < 1.0:
                x = p + t * (q - p)
                x[axis] = bound
                points.append(x)
    if not points:
        return None
    pts = np.array(points)
    return pts.min(axis=0), pts.max(axis=0)


def _box_area(lo, hi) -> float:
    d = np.asarray(hi, dtype=np.float64) - np.asarray(lo, dtype=np.float64)
    return float(2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0]))


def sbvh_root_candidates(vertices, faces, num_bins: int) -> dict:
    """Every split candidate of the root of a spatial-split BVH (Stich et al. 2009), priced by
    A(L) N(L) + A(R) N(R) in float64, enumerated candidate by candidate:

    - object splits: the triangles whose box centroid falls in centroid bins below boundary j
      (bins: float32 ``B * (c - c_min) / extent``, clamped), on each axis;
    - spatial splits at the float32 planes ``lo + extent * (j / B)`` of the root box: a triangle
      whose box starts below the plane goes left, one whose box ends above it goes right (both:
      each side boxed by the triangle's part on that side, ``triangle_slab_bounds``).

    Returns the cheapest object cost, the cheapest spatial cost, and the overlap area of the
    cheapest object split's two boxes."""
    v = np.asarray(vertices, dtype=np.float32)
    tris = v[np.asarray(faces, dtype=np.int64)]
    lo, hi = tris.min(axis=1), tris.max(axis=1)
    n = len(tris)
    c = np.float32(0.5) * (lo + hi)
    c_lo, c_hi = c.min(0), c.max(0)
    best_obj, obj_boxes = np.inf, None
    for axis in range(3):
        extent = c_hi[axis] - c_lo[axis]
        if extent <= 0:
            continue
        bins = np.clip(((np.float32(num_bins) * (c[:, axis] - c_lo[axis])) / extent).astype(np.int64), 0,
                       num_bins - 1)
        for j in range(1, num_bins):
            side = bins < j
            n_left = int(side.sum())
            if 0 < n_left < n:
                boxes = (lo[side].min(0), hi[side].max(0), lo[~side].min(0), hi[~side].max(0))
                cost = _box_area(boxes[0], boxes[1]) * n_left + _box_area(boxes[2], boxes[3]) * (n - n_left)
                if cost < best_obj:
                    best_obj, obj_boxes = cost, boxes
    overlap = 0.0
    if obj_boxes is not None:
        o_lo, o_hi = np.maximum(obj_boxes[0], obj_boxes[2]), np.minimum(obj_boxes[1], obj_boxes[3])
        overlap = _box_area(o_lo, o_hi) if (o_lo <= o_hi).all() else 0.0
    box_lo, box_hi = lo.min(0), hi.max(0)
    best_sp = np.inf
    for axis in range(3):
        size = box_hi[axis] - box_lo[axis]
        if size <= 0:
            continue
        planes = [np.float32(box_lo[axis] + size * np.float32(np.float32(j) / np.float32(num_bins)))
                  for j in range(num_bins)]
        for j in range(1, num_bins):
            plane = float(planes[j])
            goes_left = lo[:, axis] < plane
            # A box ending on the plane stays left whole; one lying flat on it goes right.
            goes_right = (hi[:, axis] > plane) | ~goes_left
            n_left, n_right = int(goes_left.sum()), int(goes_right.sum())
            if not (0 < n_left < n and 0 < n_right < n):
                continue
            parts = {True: [], False: []}
            for t in range(n):
                both = goes_left[t] and goes_right[t]
                for to_left, wanted in ((True, goes_left[t]), (False, goes_right[t])):
                    if not wanted:
                        continue
                    if both:
                        box = triangle_slab_bounds(tris[t], axis, -np.inf if to_left else plane,
                                                   plane if to_left else np.inf)
                        if box is not None:
                            parts[to_left].append(box)
                    else:
                        parts[to_left].append((lo[t], hi[t]))
            l_lo = np.min([p[0] for p in parts[True]], axis=0)
            l_hi = np.max([p[1] for p in parts[True]], axis=0)
            r_lo = np.min([p[0] for p in parts[False]], axis=0)
            r_hi = np.max([p[1] for p in parts[False]], axis=0)
            cost = _box_area(l_lo, l_hi) * n_left + _box_area(r_lo, r_hi) * n_right
            best_sp = min(best_sp, cost)
    return {"object": best_obj, "spatial": best_sp, "object_overlap": overlap}


def morton_reference(lowers, uppers, bits):
    """3n-bit Morton codes of box centroids, quantized in float64 over the centroid bounds."""
    c = (np.float32(0.5) * (lowers + uppers)).astype(np.float32)
    lo, hi = c.min(0).astype(np.float64), c.max(0).astype(np.float64)
    extent = hi - lo
    cells = 1 << bits
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(extent > 0, (c.astype(np.float64) - lo) / np.where(extent > 0, extent, 1.0), 0.0)
    q = np.clip((t * cells).astype(np.int64), 0, cells - 1)
    code = np.zeros(len(c), dtype=np.int64)
    for bit in range(bits):
        for axis in range(3):  # x is the most significant of each triple
            code |= ((q[:, axis] >> bit) & 1) << (3 * bit + 2 - axis)
    return code


def numpy_sah(tree: dict, t1: float = 1.0, t2: float = 1.0) -> float:
    """The paper's SAH cost (eq. 1) in float64 from the node arrays, unrolled over the nodes."""
    lo = tree["node_lowers"].astype(np.float64)
    hi = tree["node_uppers"].astype(np.float64)
    d = np.maximum(hi - lo, 0.0)
    area = 2.0 * (d[:, 0] * d[:, 1] + d[:, 1] * d[:, 2] + d[:, 2] * d[:, 0])
    leaf = tree["node_left"] < 0
    cost = np.where(leaf, t2 * (tree["node_end"] - tree["node_begin"]), 2.0 * t1)
    return float((cost * area).sum() / area[0])


def sphere_past_float32_extent(rng):
    """An icosphere of radius 1.7 (shuffled faces) as ``(small, big, faces)``: its vertices in
    float32 at that size and scaled by 2^127 (2.9e38), where the centroids of its triangles span
    more than float32's largest value on every axis (checked), though every coordinate is finite.
    A builder should split the big one as it splits the small one."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=2)
    v = np.asarray(mesh.vertices, np.float64) * 1.7
    f = np.asarray(mesh.faces, np.int32)[rng.permutation(len(mesh.faces))]
    small = v.astype(np.float32)
    big = (v * 2.0**127).astype(np.float32)
    c = np.float32(0.5) * small[f].min(1) + np.float32(0.5) * small[f].max(1)
    assert ((c.max(0).astype(np.float64) - c.min(0)) * 2.0**127 > np.finfo(np.float32).max).all()
    return small, big, f


def exact_distance_sq(p, a, b, c) -> Fraction:
    """Squared distance of float32 point p to the closed float32 triangle abc, in rationals: the
    Gram equations' interior point when it lies in the triangle, and the three clamped edge
    projections (the minimum over points of the triangle, so exact)."""
    p, a, b, c = ([Fraction(float(x)) for x in np.float32(v)] for v in (p, a, b, c))

    def sub(x, y):
        return [x[i] - y[i] for i in range(3)]

    def dot(x, y):
        return sum(x[i] * y[i] for i in range(3))

    ab, ac, ap = sub(b, a), sub(c, a), sub(p, a)
    g00, g01, g11, r0, r1 = dot(ab, ab), dot(ab, ac), dot(ac, ac), dot(ap, ab), dot(ap, ac)
    det = g00 * g11 - g01 * g01
    candidates = []
    if det > 0:
        s, t = (g11 * r0 - g01 * r1) / det, (g00 * r1 - g01 * r0) / det
        if s >= 0 and t >= 0 and s + t <= 1:
            d = [ap[i] - s * ab[i] - t * ac[i] for i in range(3)]
            candidates.append(dot(d, d))
    for origin, edge in ((a, ab), (a, ac), (b, sub(c, b))):
        den, op = dot(edge, edge), sub(p, origin)
        w = Fraction(0) if den == 0 else min(max(dot(op, edge) / den, Fraction(0)), Fraction(1))
        d = [op[i] - w * edge[i] for i in range(3)]
        candidates.append(dot(d, d))
    return min(candidates)


def assert_exact_node_boxes(tree: dict, vertices: np.ndarray, faces: np.ndarray):
    """Every node box of `tree` (``Bvh.to_numpy()``) is the union of its triangles' boxes: min
    and max of the same floats, so equal to the bit."""
    corners = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    node_lo, node_hi = numpy_node_boxes(tree, corners.min(axis=1), corners.max(axis=1))
    np.testing.assert_array_equal(tree["node_lowers"], node_lo.astype(np.float32))
    np.testing.assert_array_equal(tree["node_uppers"], node_hi.astype(np.float32))
