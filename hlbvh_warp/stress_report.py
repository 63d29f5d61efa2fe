"""``python -m hlbvh_warp stress``: every builder on adversarial scenes, checked in float64.

Each scene family (identical triangles, duplicates, zero-area triangles, coordinates near 1e18
and 1e-18, mixed scales, a flat scene, slivers, one and two triangles, a random soup, a closed mesh) is built
with every builder in ``api.BUILDERS`` and shot with random, axis-aligned, vertex- and
edge-aimed rays and rays starting on the surface. Closest hits are compared with a float64
brute-force reference; one fixed-format row per (family, builder) gives the tree's depth and
node count, the rays that disagree, and how many of those are not near-ties.

A disagreement is a *near-tie* (documented tolerance, `NEAR_TIE_TOL`) when every triangle on
which the two answers differ is decided within rounding: the ray passes within
``NEAR_TIE_TOL * scale`` of the triangle's boundary, passes within that distance of the line
through one of its edges, grazes its plane, starts within that distance of its plane, or the
triangle has (almost) no area; ``scale`` is the largest coordinate magnitude of the ray origin
and the triangle. The edge-line test matters for rays that graze a triangle near an edge: the
watertight test decides each edge by the sign of a ray-space edge function, which is the
distance between the ray's line and the edge's line (Woop et al. 2013, sec. 3), and float32
rounding decides that sign only up to about eps * scale even where the hit point lies well
inside the triangle in its own plane. The float32 watertight test and a
float64 test may legitimately decide such rays differently; any other disagreement is a bug.
"""

from __future__ import annotations

import argparse

import numpy as np

from .cli import command_prog, device_name, non_negative_int, quiet_warp
from .reference import brute_force_closest_hit, past_range_ties, unmet_ties

#: Relative tolerance of a near-tie: about 170 float32 ulps of the coordinates involved.
NEAR_TIE_TOL = 1e-5
#: Hits at distances equal to this relative tolerance are the same hit (ties between triangles).
T_RTOL = 1e-5


# ------------------------------------------------------------------ scene families
def _soup(rng, n, scale=1.0, offset=0.0):
    v = (rng.random((3 * n, 3)) * scale + offset).astype(np.float32)
    return v, np.arange(3 * n, dtype=np.int32).reshape(-1, 3)


def _concat(*parts):
    verts, faces, base = [], [], 0
    for v, f in parts:
        verts.append(v)
        faces.append(f + base)
        base += v.shape[0]
    return np.concatenate(verts).astype(np.float32), np.concatenate(faces).astype(np.int32)


def scene_identical(rng):
    v = rng.random((3, 3)).astype(np.float32)
    return v, np.tile(np.arange(3, dtype=np.int32), (200, 1))


def scene_duplicates(rng):
    v, f = _soup(rng, 60)
    f = np.repeat(f, 5, axis=0)
    return v, f[rng.permutation(f.shape[0])]


def scene_zero_area(rng):
    tris, faces = _soup(rng, 100)
    points = np.repeat(rng.random((100, 1, 3)), 3, axis=1).reshape(-1, 3).astype(np.float32)
    a, b = rng.random((100, 3)), rng.random((100, 3))
    segs = np.stack([a, b, 0.5 * (a + b)], axis=1).reshape(-1, 3).astype(np.float32)
    seq = np.arange(300, dtype=np.int32).reshape(-1, 3)
    return _concat((tris, faces), (points, seq), (segs, seq))


def scene_huge(rng):
    return _soup(rng, 300, scale=1e18, offset=1e18)


def scene_tiny(rng):
    return _soup(rng, 300, scale=1e-18, offset=1e-18)


def scene_mixed_scales(rng):
    small = _soup(rng, 150, scale=1e-6)
    big = _soup(rng, 150, scale=1e6, offset=-5e5)
    return _concat(small, big)


def scene_flat(rng):
    v, f = _soup(rng, 300)
    v[:, 2] = 0.25
    return v, f


def scene_slivers(rng):
    n = 300
    a = rng.random((n, 3))
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    side = np.cross(axis, rng.normal(size=(n, 3)))
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    v = np.stack([a, a + axis, a + 1e-4 * side], axis=1).reshape(-1, 3).astype(np.float32)
    return v, np.arange(3 * n, dtype=np.int32).reshape(-1, 3)


def scene_one(rng):
    return _soup(rng, 1)


def scene_two(rng):
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float32)
    return v, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)


def scene_soup(rng):
    return _soup(rng, 3000)


def scene_closed(rng):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=3)
    return np.asarray(m.vertices, dtype=np.float32), np.asarray(m.faces, dtype=np.int32)


SCENE_FAMILIES = {
    "identical": scene_identical,
    "duplicates": scene_duplicates,
    "zero_area": scene_zero_area,
    "huge_1e18": scene_huge,
    "tiny_1e-18": scene_tiny,
    "mixed_1e-6_1e6": scene_mixed_scales,
    "flat": scene_flat,
    "slivers": scene_slivers,
    "one": scene_one,
    "two": scene_two,
    "soup": scene_soup,
    "closed": scene_closed,
}


# ------------------------------------------------------------------ ray families
def _unit(d):
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def ray_families(rng, vertices, faces, num_rays: int = 120) -> dict:
    """Named ``(origins, directions)`` float32 sets for one scene."""
    v = np.asarray(vertices, dtype=np.float64)
    tri = v[faces]
    lo, hi = v.min(0), v.max(0)
    center, radius = 0.5 * (lo + hi), 0.5 * np.linalg.norm(hi - lo)
    radius = max(radius, np.abs(center).max() * 1e-6, 1e-30)
    out = {}
    # Random: from a sphere around the scene towards uniform points of its box.
    dirs = _unit(rng.normal(size=(num_rays, 3)))
    origins = center - 2.0 * radius * dirs
    targets = lo + rng.random((num_rays, 3)) * (hi - lo)
    out["random"] = (origins, targets - origins)
    # Axis-aligned through vertices: the origin lies on slab faces of the vertex's boxes.
    idx = rng.integers(0, v.shape[0], num_rays)
    axis = rng.integers(0, 3, num_rays)
    sign = rng.choice([-1.0, 1.0], num_rays)
    d = np.zeros((num_rays, 3))
    d[np.arange(num_rays), axis] = sign
    out["axis"] = (v[idx] - 3.0 * radius * d, d)
    # Aimed exactly at vertices and at edge midpoints, from outside.
    dirs = _unit(rng.normal(size=(num_rays, 3)))
    origins = center - 2.0 * radius * dirs
    out["vertex"] = (origins, v[idx] - origins)
    f = rng.integers(0, faces.shape[0], num_rays)
    e = rng.integers(0, 3, num_rays)
    mid = 0.5 * (tri[f, e] + tri[f, (e + 1) % 3])
    out["edge"] = (origins, mid - origins)
    # Starting on the surface, in random directions.
    w = rng.dirichlet(np.ones(3), num_rays)
    on_surface = np.einsum("rk,rkj->rj", w, tri[f])
    out["surface"] = (on_surface, rng.normal(size=(num_rays, 3)))
    return {name: (o.astype(np.float32), d.astype(np.float32)) for name, (o, d) in out.items()}


def is_marginal(vertices, faces, prim: int, origin, direction, tol: float = NEAR_TIE_TOL) -> bool:
    """Whether ray vs triangle ``prim`` is decided within rounding (see the module docstring)."""
    v = np.asarray(vertices, dtype=np.float64)
    a, b, c = v[faces[prim]]
    o = np.asarray(origin, dtype=np.float64)
    d = np.asarray(direction, dtype=np.float64)
    scale = max(np.abs(o).max(), np.abs(v[faces[prim]]).max(), 1e-300)
    n = np.cross(b - a, c - a)
    n_len = np.linalg.norm(n)
    longest = max(np.linalg.norm(b - a), np.linalg.norm(c - b), np.linalg.norm(a - c))
    if n_len <= tol * longest * longest or longest == 0.0:
        return True  # a point, a segment or nearly so
    nd = float(np.dot(n, d))
    if abs(nd) <= tol * n_len * np.linalg.norm(d):
        return True  # grazing: the ray (nearly) lies in the plane
    height = float(np.dot(n, a - o))
    if abs(height) <= tol * scale * n_len:
        return True  # the origin lies on the triangle's plane: a hit at t ~ 0 either way
    # Signed distance between the ray's line and each edge's line: the quantity whose sign the
    # watertight test's edge functions compute (same sign on all three: the line crosses the
    # triangle). Where one is within rounding of zero and the others agree in sign, flipping it
    # flips the answer: a tie, wherever the hit point falls in the triangle's plane.
    d_unit = d / np.linalg.norm(d)
    side, near = [], []
    for q0, q1 in ((a, b), (b, c), (c, a)):
        m = np.cross(q1 - q0, d_unit)
        m_len = np.linalg.norm(m)
        dist = float(np.dot(q0 - o, m)) / m_len if m_len > 0.0 else 0.0
        near.append(abs(dist) <= tol * scale)
        side.append(np.sign(dist))
    decided = {sd for sd, nr in zip(side, near) if not nr}
    if any(near) and len(decided) <= 1:
        return True
    t = height / nd
    p = o + t * d
    dist = min(
        float(np.dot(np.cross(q1 - q0, p - q0), n)) / (n_len * np.linalg.norm(q1 - q0))
        for q0, q1 in ((a, b), (b, c), (c, a))
    )
    return abs(dist) <= tol * scale


def _behind_near_ties(vertices, faces, origin, direction, t: float, prim: int) -> bool:
    """Whether a hit on ``prim`` at ``t``, past the reference's closest hit, is the ray's next
    answer once near-ties are excused: the ray meets ``prim`` there (the float64 test, within
    rounding of the coordinates along the ray, as `classify` measures a distance; or the ray
    passes within rounding of ``prim``), and every triangle it hits before is a near-tie."""
    from .reference import BARYCENTRIC_EPS, _moller_trumbore

    if not 0 <= prim < len(faces):
        return False
    v = np.asarray(vertices, dtype=np.float64)
    tri = v[np.asarray(faces, dtype=np.int64)]
    count = len(tri)
    o, d = np.asarray(origin, dtype=np.float64), np.asarray(direction, dtype=np.float64)
    with np.errstate(all="ignore"):
        t_all = _moller_trumbore(np.broadcast_to(o, (count, 3)), np.broadcast_to(d, (count, 3)), tri[:, 0],
                                 tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], np.inf, BARYCENTRIC_EPS)
    # Distances along the ray within rounding of the coordinates: the ray origin's and the named
    # triangle's, as `classify` tells the same triangle at another distance.
    slack = NEAR_TIE_TOL * max(np.abs(o).max(), np.abs(tri[prim]).max(), 1e-300) / np.linalg.norm(d)
    if not (abs(t_all[prim] - t) <= slack or is_marginal(vertices, faces, prim, origin, direction)):
        return False
    before = np.flatnonzero(t_all < t - slack)
    return all(is_marginal(vertices, faces, int(p), origin, direction) for p in before)


def classify(vertices, faces, origins, directions, t, prim, t_ref, prim_ref):
    """``(disagreements, unexplained)``: rays whose answers differ, and those that are not near-ties."""
    t = np.asarray(t, dtype=np.float64)
    hit, hit_ref = prim >= 0, prim_ref >= 0
    same_t = np.isclose(t, t_ref, rtol=T_RTOL, atol=0.0)
    # The same triangle is the same answer only at the same distance: within the float32 rounding
    # of the coordinates (the distance along the ray against NEAR_TIE_TOL * scale, as near-ties
    # are measured), not at any t.
    v = np.asarray(vertices, dtype=np.float64)
    far_t = np.zeros(len(t), dtype=bool)
    for r in np.nonzero(hit & hit_ref & (prim == prim_ref) & ~same_t)[0]:
        o, d = np.asarray(origins[r], dtype=np.float64), np.asarray(directions[r], dtype=np.float64)
        scale = max(np.abs(o).max(), np.abs(v[faces[prim[r]]]).max(), 1e-300)
        far_t[r] = abs(t[r] - t_ref[r]) * np.linalg.norm(d) > NEAR_TIE_TOL * scale
    # Another triangle at the same t is a tie only if the ray meets that triangle there: on the
    # distance alone, a hit reported under a wrong id passed.
    unmet = unmet_ties(vertices, faces, origins, directions, t, prim, t_ref, prim_ref, T_RTOL)
    agree = ((~hit & ~hit_ref) | (hit & hit_ref & (((prim == prim_ref) & ~far_t) | same_t))) & ~unmet
    # A hit against a miss at float32's largest distance: rounding decides whether it overflows.
    agree |= past_range_ties(t, prim, t_ref, prim_ref, T_RTOL)
    unexplained = int(unmet.sum())
    for r in np.nonzero(~agree & ~unmet)[0]:
        involved = []
        # We hit something before the reference's closest hit: the reference rejected it.
        if hit[r] and (not hit_ref[r] or t[r] < t_ref[r]):
            involved.append(int(prim[r]))
        # The reference hit something before ours: we rejected it.
        if hit_ref[r] and (not hit[r] or t_ref[r] < t[r]):
            involved.append(int(prim_ref[r]))
        if not all(is_marginal(vertices, faces, p, origins[r], directions[r]) for p in involved):
            unexplained += 1
        elif hit[r] and hit_ref[r] and t_ref[r] < t[r] and not _behind_near_ties(vertices, faces, origins[r],
                                                                                 directions[r], t[r], prim[r]):
            # A near-tie excuses missing the grazed triangle, not whatever was reported behind it:
            # a triangle the ray does not meet there, or one past a triangle the ray crosses.
            unexplained += 1
    return int((~agree).sum()), unexplained


# ------------------------------------------------------------------ the report
def run_family(family: str, method: str, device, seed: int = 0, reference_cache: dict | None = None) -> dict:
    """Build one scene with one builder, trace every ray family, compare with the reference."""
    from . import api, query

    rng = np.random.default_rng(seed)
    vertices, faces = SCENE_FAMILIES[family](rng)
    rays = ray_families(rng, vertices, faces)
    bvh = api.build(vertices, faces, method=method, device=device)
    row = {"family": family, "method": method, "prims": faces.shape[0], "nodes": bvh.num_nodes,
           "depth": bvh.depth, "rays": 0, "disagree": 0, "unexplained": 0, "per_rays": {}}
    for kind, (o, d) in rays.items():
        t, p = query.intersect(bvh, o, d)
        key = (family, seed, kind)
        if reference_cache is not None and key in reference_cache:
            t_ref, p_ref = reference_cache[key]
        else:
            t_ref, p_ref = brute_force_closest_hit(vertices, faces, o, d, eps=0.0)
            if reference_cache is not None:
                reference_cache[key] = (t_ref, p_ref)
        n_bad, n_unexplained = classify(vertices, faces, o, d, t, p, t_ref, p_ref)
        row["rays"] += o.shape[0]
        row["disagree"] += n_bad
        row["unexplained"] += n_unexplained
        row["per_rays"][kind] = (n_bad, n_unexplained)
    return row


HEADER = (
    f"{'family':16s} {'method':10s} {'prims':>6s} {'nodes':>6s} {'depth':>5s} {'rays':>5s} "
    f"{'disagree':>8s} {'not_tie':>7s}"
)


def format_row(r: dict) -> str:
    return (
        f"{r['family']:16s} {r['method']:10s} {r['prims']:6d} {r['nodes']:6d} {r['depth']:5d} {r['rays']:5d} "
        f"{r['disagree']:8d} {r['unexplained']:7d}"
    )


def main(argv=None) -> int:
    import warp as wp

    from . import api

    parser = argparse.ArgumentParser(prog=command_prog("stress"), description=__doc__.splitlines()[0])
    parser.add_argument("--device", action="append", type=device_name,
                        help="Warp device (repeatable); default: every device")
    parser.add_argument("--family", action="append", choices=sorted(SCENE_FAMILIES), help="default: all")
    parser.add_argument("--method", action="append", help="default: every builder in api.BUILDERS")
    parser.add_argument("--seed", type=non_negative_int, default=0)
    args = parser.parse_args(argv)
    quiet_warp()
    wp.init()
    api._load_optional_builders()
    devices = args.device or ["cpu"] + [str(d) for d in wp.get_cuda_devices()]
    methods = args.method or sorted(api.BUILDERS)
    # Every name before the first build, as the other commands check theirs: an unknown one was
    # found only when the loop reached it, after the methods before it had run.
    unknown = [m for m in methods if m not in api.BUILDERS]
    if unknown:
        parser.error(f"unknown method(s) {unknown} in --method; choose from {sorted(api.BUILDERS)}")
    families = args.family or list(SCENE_FAMILIES)
    cache = {}
    total_unexplained = 0
    print(f"near-tie tolerance {NEAR_TIE_TOL:g} x coordinate scale; not_tie must be 0")
    for device in devices:
        print(f"device {device}")
        print(HEADER)
        for family in families:
            for method in methods:
                row = run_family(family, method, device, args.seed, cache)
                total_unexplained += row["unexplained"]
                print(format_row(row), flush=True)
    print(f"disagreements that are not near-ties: {total_unexplained}")
    return 1 if total_unexplained else 0


if __name__ == "__main__":
    raise SystemExit(main())
