"""Brute-force references for checking builds from package code (benchmarks, demos, the stress
report).

Float64 NumPy and nothing of the BVH: a benchmark checks a batch of rays (or of closest-point
queries, `brute_force_closest`) against this before it reports a time. The tests keep their own
plain copies (tests/oracles.py, tests/test_proximity.py), independent of the package, and check
these against them.
"""

from __future__ import annotations

import numpy as np

from .host_morton import morton_order

#: Barycentric slack of the float64 reference, far below float32 traversal error.
BARYCENTRIC_EPS = 1e-12

#: Ray-group or ray-triangle pairs held at once: about 16 MB per float64 temporary.
PAIR_BUDGET = 1 << 21

#: Float32's largest finite value. The library's hit distance is a float32, and a hit farther
#: than this is a miss (`traversal.ray_scaled_t_max`); the float64 brute force found such hits
#: on meshes near float32's limit, and the commands reported the library's misses there as wrong.
FLOAT32_MAX = float(np.finfo(np.float32).max)


#: Triangles the closest-point brute force takes together, under one box: a group farther from a
#: point than some triangle is never tested against it.
CLOSEST_GROUP_SIZE = 64
#: Point-triangle pairs the closest-point brute force holds at once: 1.5 MB per temporary of
#: float64 3-vectors.
CLOSEST_PAIR_BUDGET = 1 << 16


def morton_groups(corners: np.ndarray, group_size: int):
    """The brute forces' partition of triangles ``corners`` (F, 3, 3): ``(ids, lowers, uppers)``,
    ``ids`` (G, group_size) consecutive triangles along a Morton curve of their centroids, the last
    group padded by repeating its last triangle, and each group's box. A box can only cost a brute
    force time, never an answer: the grouping needs no care beyond being a partition."""
    order = morton_order(corners.mean(axis=1))
    num_groups = -(-len(corners) // group_size)
    order = np.concatenate([order, np.full(num_groups * group_size - len(corners), order[-1])])
    ids = order.reshape(num_groups, group_size)
    grouped = corners[ids].reshape(num_groups, group_size * 3, 3)
    return ids, grouped.min(axis=1), grouped.max(axis=1)


def _boxes_met(lower, upper, origins, directions):
    """(rays, boxes) mask: the ray's half-line meets the closed box, touching included (a flat
    box, or a ray along a face, must pass). A direction component below 1e-300 is parallel to
    its slabs: the ray is in a slab for every t or for none, by where its origin lies (the
    reciprocal would give 0 * inf = NaN, or a zero bound, on a slab boundary)."""
    parallel = np.abs(directions) < 1e-300
    inv = 1.0 / np.where(parallel, 1.0, directions)
    o = origins[:, None, :]
    with np.errstate(over="ignore"):
        t1 = (lower[None] - o) * inv[:, None, :]
        t2 = (upper[None] - o) * inv[:, None, :]
    enter, leave = np.minimum(t1, t2), np.maximum(t1, t2)
    if parallel.any():
        inside = (lower[None] <= o) & (o <= upper[None])
        along = parallel[:, None, :]
        enter = np.where(along, np.where(inside, -np.inf, np.inf), enter)
        leave = np.where(along, np.where(inside, np.inf, -np.inf), leave)
    near, far = enter.max(axis=2), leave.min(axis=2)
    return (near <= far) & (far >= 0)


def _moller_trumbore(o, d, a, e1, e2, t_max, eps):
    """Row-wise ray/triangle test in float64 (Moeller & Trumbore, "Fast, Minimum Storage
    Ray/Triangle Intersection", JGT 1997); t where accepted, inf elsewhere."""
    p = np.cross(d, e2)
    det = np.einsum("pk,pk->p", p, e1)
    inv = 1.0 / det
    tv = o - a
    u = np.einsum("pk,pk->p", tv, p) * inv
    q = np.cross(tv, e1)
    w = np.einsum("pk,pk->p", d, q) * inv
    t = np.einsum("pk,pk->p", q, e2) * inv
    ok = (det != 0) & (u >= -eps) & (w >= -eps) & (u + w <= 1 + eps) & (t > 0) & (t < t_max) & np.isfinite(t)
    return np.where(ok, t, np.inf)


def brute_force_closest_hit(vertices, faces, origins, directions, t_max=np.inf, eps=BARYCENTRIC_EPS,
                            group_size=None, pair_budget=PAIR_BUDGET):
    """Closest hit of every ray against every triangle (Moeller & Trumbore, JGT 1997; float64).

    Returns ``(t, prim)``; a miss is ``(inf, -1)``; of triangles hit at the same least t, the
    lowest face id. ``eps`` is the barycentric slack of the accept test. A hit farther than
    `FLOAT32_MAX` is a miss, as the library documents for its float32 distances (a hit within
    rounding of that bound may go either way: `past_range_ties`).

    Exact, like testing every pair, but not as slow: the triangles are grouped ``group_size`` at
    a time (default about 2 F^(1/3), which balances the box tests, F / group_size per ray,
    against the triangle tests in the groups a ray crosses) along a Morton curve of their
    centroids, and a group's triangles are tested only
    against the rays that meet the group's box, grown by more than the accept test's slack and
    float64 rounding can carry a hit outside it. A group's box can only cost time, never a hit,
    so the grouping needs no care beyond being a partition. Memory stays at ``pair_budget``
    pairs whatever the mesh: testing 64 rays against every triangle at once took 17 GB and
    12 minutes at 1.6M triangles and 2,000 rays.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    o_all = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d_all = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    num_rays, num_faces = len(o_all), len(f)
    # Hits up to float32's largest value, inclusive (`t < t_max` in the accept test).
    t_max = min(float(t_max), np.nextafter(FLOAT32_MAX, np.inf))
    t_out = np.full(num_rays, np.inf)
    p_out = np.full(num_rays, -1, dtype=np.int64)
    if num_rays == 0 or num_faces == 0:
        return t_out, p_out
    if group_size is None:
        group_size = int(np.clip(2.0 * num_faces ** (1.0 / 3.0), 16, 512))
    group_size = max(1, int(group_size))
    # A duplicate (the padding) changes no closest hit.
    ids, g_lo, g_hi = morton_groups(v[f], group_size)
    num_groups = len(ids)
    order = ids.reshape(-1)
    # The accept test takes points up to ~eps * (edge lengths) outside a triangle; rounding, about
    # 1e-16 of the coordinates' magnitude. Grow every box well past both.
    scale = max(np.abs(v).max(), np.abs(o_all).max(), 1e-300)
    pad = (8.0 * eps * np.linalg.norm(g_hi - g_lo, axis=1) + 1e-9 * scale)[:, None]
    g_lo, g_hi = g_lo - pad, g_hi + pad
    a_all = v[f[:, 0]]
    e1_all, e2_all = v[f[:, 1]] - a_all, v[f[:, 2]] - a_all
    rays_per_chunk = max(1, pair_budget // num_groups)
    pairs_per_piece = max(1, pair_budget // group_size)
    lane = np.arange(group_size)
    with np.errstate(all="ignore"):
        for s in range(0, num_rays, rays_per_chunk):
            met = _boxes_met(g_lo, g_hi, o_all[s : s + rays_per_chunk], d_all[s : s + rays_per_chunk])
            ray_idx, group_idx = np.nonzero(met)
            ray_idx += s
            for k in range(0, len(ray_idx), pairs_per_piece):
                r = np.repeat(ray_idx[k : k + pairs_per_piece], group_size)
                faces_hit = order[(group_idx[k : k + pairs_per_piece, None] * group_size + lane).reshape(-1)]
                t = _moller_trumbore(o_all[r], d_all[r], a_all[faces_hit], e1_all[faces_hit], e2_all[faces_hit],
                                     t_max, eps)
                hit = np.isfinite(t)
                r, t, faces_hit = r[hit], t[hit], faces_hit[hit]
                if len(r) == 0:
                    continue
                # Per ray: least t, then lowest face id; then against what earlier pieces found.
                first = np.lexsort((faces_hit, t, r))
                r, t, faces_hit = r[first], t[first], faces_hit[first]
                heads = np.r_[True, r[1:] != r[:-1]]
                r, t, faces_hit = r[heads], t[heads], faces_hit[heads]
                better = (t < t_out[r]) | ((t == t_out[r]) & (faces_hit < p_out[r]))
                t_out[r[better]] = t[better]
                p_out[r[better]] = faces_hit[better]
    return t_out, p_out


def origins_within_float32(origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Float64 ray origins as float32, each one past float32's range first moved along its ray to
    where the ray enters that range: every triangle lies within it, so the ray meets the same
    ones. A ray that never enters it meets nothing, and keeps an Inf coordinate (such a ray finds
    nothing). Cast as they were, origins past the range of a mesh near float32's limit became Inf
    with NumPy's "overflow encountered in cast" warning, and rays that cross the mesh found nothing."""
    origins = np.array(origins, dtype=np.float64)
    # Below float32's largest value by a margin, so the moved origins round to finite float32.
    limit = FLOAT32_MAX * (1.0 - 1e-6)
    out = np.flatnonzero((np.abs(origins) > limit).any(axis=1))
    if len(out):
        o, d = origins[out], np.broadcast_to(np.asarray(directions, dtype=np.float64), origins.shape)[out]
        with np.errstate(divide="ignore", invalid="ignore"):
            lo, hi = (-limit - o) / d, (limit - o) / d
        # The slabs of float32's range; an axis the ray runs along (d = 0) bounds nothing, its
        # origin being within range there or the ray never entering.
        near = np.where(d != 0.0, np.minimum(lo, hi), np.where(np.abs(o) <= limit, -np.inf, np.inf)).max(axis=1)
        far = np.where(d != 0.0, np.maximum(lo, hi), np.inf).min(axis=1)
        enters = (near <= far) & (far >= 0.0)
        origins[out[enters]] = o[enters] + np.maximum(near[enters], 0.0)[:, None] * d[enters]
    with np.errstate(over="ignore"):
        return origins.astype(np.float32)


def rays_at_box(rng, vertices, num_rays):
    """Rays from a sphere around the bounding box aimed at random points inside it."""
    v = np.asarray(vertices, dtype=np.float64)
    lo, hi = v.min(0), v.max(0)
    center, radius = 0.5 * (lo + hi), 0.5 * np.linalg.norm(hi - lo) + 1e-6
    dirs = rng.normal(size=(num_rays, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origins = center - 2.0 * radius * dirs
    targets = lo + rng.random((num_rays, 3)) * (hi - lo)
    d = targets - origins
    return origins_within_float32(origins, d), (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


def unmet_ties(vertices, faces, origins, directions, t, prim, t_ref, prim_ref, rtol=1e-5) -> np.ndarray:
    """Mask of the rays whose hit names another triangle than the reference's at the same t
    (within ``rtol``) that the ray does not meet there: neither the float64 test (`_moller_trumbore`)
    hits the named triangle at that t, nor does the ray pass within rounding of it
    (`stress_report.is_marginal`: a shared edge or vertex, where either triangle may be hit).

    A tie was accepted on the distance alone: a traversal that reported the right distance under
    another triangle's id (a leaf's slot in ``prim_order`` instead of the face it holds) passed
    every check of the commands."""
    from .stress_report import is_marginal

    t = np.asarray(t, dtype=np.float64)
    prim, prim_ref = np.asarray(prim), np.asarray(prim_ref)
    tie = (prim >= 0) & (prim_ref >= 0) & (prim != prim_ref) & np.isclose(t, t_ref, rtol=rtol, atol=0.0)
    unmet = np.zeros(len(t), dtype=bool)
    rows = np.flatnonzero(tie)
    if len(rows) == 0:
        return unmet
    # A named id outside the mesh meets nothing.
    valid = prim[rows] < len(faces)
    unmet[rows[~valid]] = True
    rows = rows[valid]
    v = np.asarray(vertices, dtype=np.float64)
    tri = v[np.asarray(faces, dtype=np.int64)[prim[rows]]]
    o = np.asarray(origins, dtype=np.float64)[rows]
    d = np.asarray(directions, dtype=np.float64)[rows]
    with np.errstate(all="ignore"):
        t_named = _moller_trumbore(o, d, tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], np.inf,
                                   BARYCENTRIC_EPS)
    met = np.isclose(t_named, t[rows], rtol=rtol, atol=0.0)
    for r, ok in zip(rows, met):
        if not ok and not is_marginal(vertices, faces, int(prim[r]), origins[r], directions[r]):
            unmet[r] = True
    return unmet


def past_range_ties(t, prim, t_ref, prim_ref, rtol=1e-5) -> np.ndarray:
    """Mask of the rays where one answer hits and the other misses, and the hit lies within
    ``rtol`` of `FLOAT32_MAX`: there float32 rounding decides whether the distance overflows, and
    a hit past it is a miss (`brute_force_closest_hit`), so either answer is right."""
    t, t_ref = np.asarray(t, dtype=np.float64), np.asarray(t_ref, dtype=np.float64)
    hit, hit_ref = np.asarray(prim) >= 0, np.asarray(prim_ref) >= 0
    edge = FLOAT32_MAX * (1.0 - rtol)
    return (hit & ~hit_ref & (t >= edge)) | (hit_ref & ~hit & (t_ref >= edge))


def count_mismatches(t, prim, t_ref, prim_ref, rtol=1e-5, rays=None) -> int:
    """Rays whose hit disagrees with the reference: hit/miss differs, or a different primitive at
    a different distance. Ties between primitives at the same t are accepted; with ``rays``
    (``(vertices, faces, origins, directions)``) only where the ray meets the named triangle
    there (`unmet_ties`); so is a hit against a miss at float32's largest distance
    (`past_range_ties`)."""
    t = np.asarray(t, dtype=np.float64)
    hit, hit_ref = np.asarray(prim) >= 0, np.asarray(prim_ref) >= 0
    same = np.asarray(prim) == np.asarray(prim_ref)
    close = np.isclose(t, t_ref, rtol=rtol, atol=0.0)
    bad = ((hit != hit_ref) & ~past_range_ties(t, prim, t_ref, prim_ref, rtol)) | (hit & hit_ref & ~(same | close))
    if rays is not None:
        bad |= unmet_ties(*rays, t, prim, t_ref, prim_ref, rtol)
    return int(bad.sum())


def _dot(x, y):
    return np.einsum("...k,...k->...", x, y)


def point_triangle_d2(p, a, b, c) -> np.ndarray:
    """Squared distance from points ``p`` to triangles ``abc`` (broadcast), float64.

    The nearest of the three edges' clamped projections and, where the projection of p on the
    triangle's plane falls inside the triangle, that point: every candidate is a point of the
    triangle and the nearest one is among them. A degenerate triangle (a segment or a point: no
    plane) is its edges. The kernel instead decides by the signs of edge functions; the two share
    no code.

    The projection's coordinates (s, t) come from cross products with the normal n = ab x ac,
    not from the normal (Gram) equations, whose determinant |ab|^2 |ac|^2 - (ab.ac)^2 cancels
    to |n|^2 and on a sliver loses most of its digits (a distance of 2.4e-6 for an exact 3.0e-8).
    The distance is then measured to the point a + s ab + t ac, not read as p's height over the
    plane, (ap.n) / |n|: an error in (s, t) slides that point within the plane, which moves the
    distance only to second order, where an error in n's direction tilts the plane by it, and
    on a sliver n comes from a difference of nearly equal products.
    """
    ab, ac, ap = b - a, c - a, p - a
    with np.errstate(all="ignore"):  # a degenerate triangle divides by zero; np.where drops it
        n = np.cross(ab, ac)
        nn = _dot(n, n)
        s = _dot(np.cross(ap, ac), n) / nn
        t = _dot(np.cross(ab, ap), n) / nn
        inside = (nn > 0) & (s >= 0) & (t >= 0) & (s + t <= 1)
        face = s[..., None] * ab + t[..., None] * ac - ap
        best = np.where(inside, _dot(face, face), np.inf)
        for origin, edge in ((a, ab), (a, ac), (b, c - b)):
            length2 = _dot(edge, edge)
            w = np.where(length2 > 0, np.clip(_dot(p - origin, edge) / length2, 0.0, 1.0), 0.0)
            off = origin + w[..., None] * edge - p
            best = np.minimum(best, _dot(off, off))
    return best


def brute_force_closest(vertices, faces, points) -> tuple[np.ndarray, np.ndarray]:
    """``(distance, prim)``: the float64 distance from every point to the mesh and the lowest id
    of a triangle at that distance; ``(inf, -1)`` for a point with a NaN or Inf coordinate.

    Exact, like testing every pair, but not as slow: the triangles are grouped
    `CLOSEST_GROUP_SIZE` at a time along a Morton curve of their centroids, and a group is tested
    against a point only where its box is no farther than the farthest corner of the nearest
    group's box, a distance that group's triangles all lie within. A group's box can only cost
    time, never an answer: the grouping is a partition, nothing more.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    distance = np.full(len(pts), np.inf)
    prim = np.full(len(pts), -1, dtype=np.int64)
    # A duplicate (the padding) changes no distance.
    ids, g_lo, g_hi = morton_groups(v[f], CLOSEST_GROUP_SIZE)
    num_groups = len(ids)
    corners = v[f[ids]]  # (groups, size, 3 corners, 3)
    finite = np.flatnonzero(np.isfinite(pts).all(axis=1))
    chunk = max(1, CLOSEST_PAIR_BUDGET // num_groups)
    for begin in range(0, len(finite), chunk):
        rows = finite[begin:begin + chunk]
        p = pts[rows][:, None, :]
        near = np.maximum(g_lo - p, 0.0) + np.maximum(p - g_hi, 0.0)
        lower = np.sqrt(_dot(near, near))
        far = np.maximum(np.abs(p - g_lo), np.abs(p - g_hi))
        upper = np.sqrt(_dot(far, far)).min(axis=1)
        # The nearest group's own bound always passes; the slack keeps rounding from dropping a
        # group whose box lies exactly at the bound.
        point_of, group_of = np.nonzero(lower <= upper[:, None] * (1.0 + 1e-12))
        found_d2, found_id, found_row = [], [], []
        step = max(1, CLOSEST_PAIR_BUDGET // CLOSEST_GROUP_SIZE)
        for start in range(0, len(point_of), step):
            pp, gg = point_of[start:start + step], group_of[start:start + step]
            tri = corners[gg]
            d2 = point_triangle_d2(pts[rows[pp]][:, None, :], tri[:, :, 0], tri[:, :, 1], tri[:, :, 2])
            found_d2.append(d2.reshape(-1))
            found_id.append(ids[gg].reshape(-1))
            found_row.append(np.repeat(pp, CLOSEST_GROUP_SIZE))
        d2, tri_id, row = (np.concatenate(x) for x in (found_d2, found_id, found_row))
        # Per point: the least distance, and of equal ones the lowest triangle id.
        pick = np.lexsort((tri_id, d2, row))
        first = pick[np.unique(row[pick], return_index=True)[1]]
        distance[rows[row[first]]] = np.sqrt(d2[first])
        prim[rows[row[first]]] = tri_id[first]
    return distance, prim
