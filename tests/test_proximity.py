"""Closest-point queries: `hlbvh_warp.closest_point`, the `bvh_closest_point` ``@wp.func`` called
from a user kernel (packed and canonical views), `ProximityQuery` and views kept across `Builder`
refits and rebuilds.

Every answer is checked against an independent float64 NumPy brute force written here
(`oracle_point_triangle`): the closest point of a triangle as the minimum of
|a + s ab + t ac - p|^2, from the 2x2 normal (Gram) equations when their solution lies in the
triangle, else from the three edges' clamped projections. The kernel instead projects onto the
plane and decides inside / outside by the signs of edge functions; the two share no code.
trimesh is not an oracle here: ``trimesh.triangles.closest_point`` was seen off by 3e-5 relative
on a bunny triangle, and ``trimesh.proximity`` needs ``rtree`` (not installed).

Tolerance: the kernel reads float32 coordinates, computes in float64 and rounds the distance and
the point to float32. The distance is then within about an ulp of float32 of itself and the point
within half an ulp of float32 per coordinate, i.e. ~1e-7 of the coordinates involved; the oracle's
own error (normal equations, worse on thin triangles) stays far below that on these scenes; needles
too thin for it are checked against a hand-worked answer (`test_thin_triangle_face_region`) and
rational arithmetic (`test_needles_whose_vertices_differ_widely_in_magnitude`). So answers are compared
within ``REL_TOL * scale`` with ``scale`` the largest coordinate magnitude of the query point and
of the oracle's nearest triangle: 10x the rounding, and still 5 or more orders of magnitude below
the distances between the triangles of every scene, whatever its scale (1e-18 ... 1e18).
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
import warp as wp
from conftest import shared_mesh, TEST_KERNEL_OPTIONS
from handmade_trees import canonical_view, caterpillar
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from oracles import exact_distance_sq, random_soup

import hlbvh_warp
from hlbvh_warp import api, host_morton, query, stress_report
from hlbvh_warp.builder import Builder
from hlbvh_warp.bvh import bvh_from_numpy
from hlbvh_warp.config import TRAVERSAL_STACK_SIZE, BuildConfig
from hlbvh_warp.kernels import proximity, traversal

wp.set_module_options(TEST_KERNEL_OPTIONS)  # quick CPU compiles of this file's kernels (conftest)

api._load_optional_builders()
METHODS = sorted(api.BUILDERS)
#: Seconds to minutes on the 1,280- and 3,000-triangle scenes: kept to the small ones.
SLOW_METHODS = ("recursive_sah",)
#: Builders `Builder` rebuilds and refits per frame.
DYNAMIC_METHODS = ("hlbvh", "lbvh", "hlbvh_sah")
#: See the module docstring: 10x the float32 rounding of the answer, relative to the coordinates.
REL_TOL = 1e-6


# ----------------------------------------------------------------------------- the oracle
def _dot(x, y):
    return np.einsum("...k,...k->...", x, y)


def oracle_point_triangle(p, a, b, c):
    """Squared distance and closest point of triangle(s) abc to point(s) p, float64, broadcast.

    The unconstrained minimum of |a + s ab + t ac - p|^2 is p's projection on the plane, with
    s = (ap x ac).n / n.n and t = (ab x ap).n / n.n for the normal n = ab x ac; when (s, t) lies
    in the triangle it is a candidate. The three edges' clamped projections always are. The answer
    is the nearest candidate: every candidate is a point of the triangle, and the true closest
    point is either the interior minimum or on an edge, so the minimum is exact. A degenerate
    triangle (segment, point: n = 0) is its edges alone; a zero-length edge is its start point.
    n.n from n, not the Gram determinant |ab|^2 |ac|^2 - (ab.ac)^2, which cancels on a sliver
    (`test_the_oracles_are_exact_on_slivers`).
    """
    p, a, b, c = (np.asarray(x, dtype=np.float64) for x in (p, a, b, c))
    ab, ac, ap = b - a, c - a, p - a
    with np.errstate(all="ignore"):
        n = np.cross(ab, ac)
        nn = _dot(n, n)
        s = _dot(np.cross(ap, ac), n) / nn
        t = _dot(np.cross(ab, ap), n) / nn
        interior = (nn > 0) & (s >= 0) & (t >= 0) & (s + t <= 1)
        face = a + s[..., None] * ab + t[..., None] * ac
        candidates = [np.where(interior[..., None], face, np.nan)]
        for origin, edge in ((a, ab), (a, ac), (b, c - b)):
            den = _dot(edge, edge)
            w = np.where(den > 0, np.clip(_dot(p - origin, edge) / den, 0.0, 1.0), 0.0)
            candidates.append(origin + w[..., None] * edge)
        q = np.stack(np.broadcast_arrays(*candidates))
        d2 = _dot(q - p, q - p)
    d2 = np.where(np.isnan(d2), np.inf, d2)
    k = np.argmin(d2, axis=0)
    best_d2 = np.take_along_axis(d2, k[None], axis=0)[0]
    best_q = np.take_along_axis(q, k[None, ..., None], axis=0)[0]
    return best_d2, best_q


def oracle_closest(vertices, faces, points, budget=300_000):
    """Brute force over every triangle: ``(distance, prim, closest)`` per point, float64; the
    lowest id among exactly equal distances (np.argmin); ``(inf, -1, NaN)`` for a NaN/Inf point.
    Points are taken in chunks so that a chunk holds about ``budget`` point-triangle pairs."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    a, b, c = v[f[:, 0]][None], v[f[:, 1]][None], v[f[:, 2]][None]
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    dist = np.full(len(pts), np.inf)
    prim = np.full(len(pts), -1, dtype=np.int64)
    closest = np.full((len(pts), 3), np.nan)
    chunk = max(1, budget // len(f))
    for s in range(0, len(pts), chunk):
        d2, q = oracle_point_triangle(pts[s : s + chunk, None], a, b, c)
        k = np.argmin(d2, axis=1)
        rows = np.arange(len(k))
        best = d2[rows, k]
        ok = np.isfinite(best)
        dist[s : s + chunk] = np.where(ok, np.sqrt(best), np.inf)
        prim[s : s + chunk] = np.where(ok, k, -1)
        closest[s : s + chunk] = np.where(ok[:, None], q[rows, k], np.nan)
    return dist, prim, closest


def oracle_distance_to(vertices, faces, points, prims):
    """Float64 distance from each point to its own triangle ``prims[i]``."""
    v = np.asarray(vertices, dtype=np.float64)
    tri = v[np.asarray(faces, dtype=np.int64)[np.asarray(prims)]]
    d2, _ = oracle_point_triangle(np.asarray(points, dtype=np.float64), tri[:, 0], tri[:, 1], tri[:, 2])
    return np.sqrt(d2)


def lowest_duplicate(vertices, faces):
    """For each triangle, the lowest id of a triangle with the very same coordinates (vertex by
    vertex): such triangles are at bitwise equal distances from any point, so the rule "equal
    distances go to the lowest id" makes that one the only valid answer among them."""
    tri = np.ascontiguousarray(np.asarray(vertices, dtype=np.float32)[np.asarray(faces)].reshape(len(faces), 9))
    _, first, inverse = np.unique(tri, axis=0, return_index=True, return_inverse=True)
    return first[inverse.reshape(-1)]


def check_answers(vertices, faces, points, closest, distance, prim, u=None, v=None, max_dist=np.inf):
    """Compare one batched answer with the oracle; returns the oracle's ``(distance, prim)``.

    A point whose oracle distance lies within tolerance of ``max_dist`` may go either way; every
    other one must be found exactly when some triangle lies within ``max_dist``. A found answer
    must be at the oracle's distance, on a triangle at that distance (near-ties may pick another
    triangle than the oracle's), be a point of that triangle, lie at the reported distance from
    the query point and be the lowest id among identical triangles; ``u, v`` must rebuild it.
    """
    verts = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    pts = np.asarray(points, dtype=np.float32).astype(np.float64).reshape(-1, 3)
    n = len(pts)
    assert closest.shape == (n, 3) and distance.shape == (n,) and prim.shape == (n,)
    assert closest.dtype == np.float32 and distance.dtype == np.float32 and prim.dtype == np.int32
    d_ref, prim_ref, _ = oracle_closest(verts, faces, pts)
    valid = np.isfinite(pts).all(axis=1)
    with np.errstate(invalid="ignore"):
        scale = np.maximum(np.abs(np.where(valid[:, None], pts, 0.0)).max(axis=1),
                           np.abs(verts[faces[np.maximum(prim_ref, 0)]]).max(axis=(1, 2)))
    tol = REL_TOL * scale
    max_dist = float(np.float32(max_dist))  # the kernel's bound is a float32
    found_ref = (prim_ref >= 0) & (d_ref <= max_dist)
    with np.errstate(invalid="ignore"):  # inf - inf for NaN points under an infinite bound
        decided = ~(np.abs(d_ref - max_dist) <= tol)
    found = prim >= 0
    assert np.array_equal(found[decided], found_ref[decided]), \
        f"{int((found != found_ref)[decided].sum())} points disagree on found / not found"
    assert (prim[~found] == -1).all()
    assert np.isnan(closest[~found]).all() and np.isposinf(distance[~found]).all()
    if u is not None:
        assert u.shape == (n,) and v.shape == (n,)
        assert (u[~found] == 0).all() and (v[~found] == 0).all()
    if not found.any():
        return d_ref, prim_ref
    pf, q, d, k, t = pts[found], closest[found].astype(np.float64), distance[found].astype(np.float64), prim[found], \
        tol[found]
    assert (k < len(faces)).all()
    err = np.abs(d - d_ref[found])
    assert (err <= t).all(), f"distance off the oracle by up to {(err / np.maximum(t, 1e-300)).max():.3g} tolerances"
    own = oracle_distance_to(verts, faces, pf, k)
    assert (np.abs(own - d_ref[found]) <= t).all(), "the returned triangle is not a nearest one"
    assert (oracle_distance_to(verts, faces, q, k) <= t).all(), "the closest point is not on its triangle"
    assert (np.abs(np.linalg.norm(pf - q, axis=1) - d) <= t).all(), "distance and closest point disagree"
    assert np.array_equal(k, lowest_duplicate(verts, faces)[k]), "a higher id among identical triangles"
    if u is not None:
        uf, vf = u[found].astype(np.float64), v[found].astype(np.float64)
        tri = verts[faces[k]]
        rebuilt = (1 - uf - vf)[:, None] * tri[:, 0] + uf[:, None] * tri[:, 1] + vf[:, None] * tri[:, 2]
        assert (np.abs(rebuilt - q).max(axis=1) <= t).all(), "u, v do not rebuild the closest point"
        assert (uf >= 0).all() and (vf >= 0).all() and (uf + vf <= 1 + 1e-6).all()
    return d_ref, prim_ref


def query_points(rng, vertices, faces, n=30):
    """Named float32 point sets for one scene: far outside, inside its box, near the surface
    (offsets from 1e-4 to 1e-1 of its extent), exactly on vertices, and on edge midpoints."""
    v = np.asarray(vertices, dtype=np.float64)
    tri = v[np.asarray(faces)]
    lo, hi = v.min(0), v.max(0)
    center, extent = 0.5 * (lo + hi), float((hi - lo).max())
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    pick = rng.integers(0, len(tri), n)
    w = rng.dirichlet(np.ones(3), n)
    on = np.einsum("nk,nkd->nd", w, tri[pick])
    offset = 10.0 ** rng.uniform(-4, -1, (n, 1)) * extent * rng.normal(size=(n, 3))
    corner = rng.integers(0, 3, n)
    mid = 0.5 * (tri[pick, corner] + tri[pick, (corner + 1) % 3])
    return {
        "far": (center + 10.0 * extent * dirs).astype(np.float32),
        "inside": (lo + rng.random((n, 3)) * (hi - lo)).astype(np.float32),
        "near": (on + offset).astype(np.float32),
        "vertex": np.asarray(vertices, dtype=np.float32)[rng.integers(0, len(v), n)],
        "edge": mid.astype(np.float32),
    }


def check_vertex_points(points, closest):
    """A query point exactly on a vertex: the closest point is that vertex, bit for bit ("vertices
    come back exactly", kernels/proximity.py); `check_answers` checks the distance (see
    `test_point_exactly_on_a_vertex_is_at_distance_zero` for why not == 0 here)."""
    assert np.array_equal(closest, points)


# ----------------------------------------------------------------------------- helpers
def make_scene(family: str, seed: int = 0):
    return stress_report.SCENE_FAMILIES[family](np.random.default_rng(seed))


@wp.kernel
def _closest_point_user_kernel(
    bvh: hlbvh_warp.BvhView,
    points: wp.array(dtype=wp.vec3),
    max_dist: wp.array(dtype=float),
    out_point: wp.array(dtype=wp.vec3),
    out_distance: wp.array(dtype=float),
    out_prim: wp.array(dtype=int),
    out_uv: wp.array(dtype=wp.vec2),
    out_counts: wp.array(dtype=wp.vec2i),
):
    # What a user writes: one query per thread, its own bound per point.
    tid = wp.tid()
    r = hlbvh_warp.bvh_closest_point(bvh, points[tid], max_dist[tid])
    out_point[tid] = r.point
    out_distance[tid] = r.distance
    out_prim[tid] = r.prim
    out_uv[tid] = wp.vec2(r.u, r.v)
    out_counts[tid] = wp.vec2i(r.nodes_visited, r.prims_tested)


def run_user_kernel(view, points, max_dist, device):
    """`_closest_point_user_kernel` on ``points``; returns closest, distance, prim, u, v, visits, tests."""
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    n = len(points)
    bounds = np.broadcast_to(np.asarray(max_dist, dtype=np.float32), (n,)).copy()
    out = [wp.zeros(n, dtype=wp.vec3, device=device), wp.zeros(n, dtype=float, device=device),
           wp.zeros(n, dtype=int, device=device), wp.zeros(n, dtype=wp.vec2, device=device),
           wp.zeros(n, dtype=wp.vec2i, device=device)]
    wp.launch(_closest_point_user_kernel, dim=n, device=device,
              inputs=[view, wp.array(points, dtype=wp.vec3, device=device),
                      wp.array(bounds, dtype=float, device=device)] + out)
    closest, distance, prim, uv, counts = (a.numpy() for a in out)
    return (closest.reshape(n, 3), distance, prim.astype(np.int32), uv[:, 0], uv[:, 1], counts[:, 0], counts[:, 1])


def all_points(sets: dict):
    return np.concatenate(list(sets.values()))


# ----------------------------------------------------------------------------- the oracle itself
def test_oracle_on_hand_computed_cases():
    """The oracle's own regions against distances worked out by hand: face, edge, vertex, a
    degenerate segment and a point triangle."""
    a, b, c = np.array([0.0, 0, 0]), np.array([2.0, 0, 0]), np.array([0.0, 2, 0])
    cases = [([0.5, 0.5, 0.75], [0.5, 0.5, 0], 0.75),  # above the face
             ([1.0, -0.5, 0.0], [1.0, 0, 0], 0.5),  # beside edge ab, in the plane
             ([2.0, 2.0, 0.0], [1.0, 1.0, 0], np.sqrt(2.0)),  # beside the hypotenuse
             ([-0.375, -0.5, 0.0], [0, 0, 0], 0.625),  # vertex a's region
             ([3.0, -1.0, 1.0], [2.0, 0, 0], np.sqrt(3.0))]  # vertex b's region
    for p, q_ref, d_ref in cases:
        d2, q = oracle_point_triangle(np.array(p), a, b, c)
        assert np.sqrt(d2) == pytest.approx(d_ref, abs=1e-15) and np.allclose(q, q_ref, atol=1e-15)
    # A segment (collinear vertices) and a point: their edges only.
    d2, q = oracle_point_triangle(np.array([1.0, 1.0, 0.0]), a, b, np.array([1.0, 0, 0]))
    assert d2 == pytest.approx(1.0) and np.allclose(q, [1, 0, 0])
    d2, q = oracle_point_triangle(np.array([1.0, 2.0, 2.0]), a, a, a)
    assert d2 == pytest.approx(9.0) and np.allclose(q, a)


def _exact_point_triangle_d2(p, a, b, c):
    """The squared distance in exact rational arithmetic: the plane projection where it lies in
    the triangle, else the nearest clamped edge projection (a third oracle, sharing no rounding)."""
    from fractions import Fraction

    p, a, b, c = ([Fraction(float(x)) for x in v] for v in (p, a, b, c))

    def sub(u, v):
        return [x - y for x, y in zip(u, v)]

    def dot(u, v):
        return sum(x * y for x, y in zip(u, v))

    def cross(u, v):
        return [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]]

    ab, ac, ap = sub(b, a), sub(c, a), sub(p, a)
    n = cross(ab, ac)
    nn = dot(n, n)
    if nn > 0:
        s, t = dot(cross(ap, ac), n) / nn, dot(cross(ab, ap), n) / nn
        if s >= 0 and t >= 0 and s + t <= 1:
            return dot(ap, n) ** 2 / nn
    best = None
    for origin, end in ((a, b), (a, c), (b, c)):
        edge = sub(end, origin)
        length2 = dot(edge, edge)
        w = min(max(dot(sub(p, origin), edge) / length2, Fraction(0)), Fraction(1)) if length2 else Fraction(0)
        off = sub([o + w * e for o, e in zip(origin, edge)], p)
        best = dot(off, off) if best is None else min(best, dot(off, off))
    return best


def test_the_oracles_are_exact_on_slivers(rng):
    """Both float64 oracles (this file's and the benchmarks' `reference.point_triangle_d2`)
    against exact rational arithmetic on slivers: triangles 1e-7 to 1e-4 thick, points 1e-9 to
    1e-3 off their plane. The normal (Gram) equations they once solved cancel there (a distance
    of 2.4e-6 for an exact 3.0e-8 on a unit triangle)."""
    from hlbvh_warp.reference import point_triangle_d2

    for _ in range(300):
        a, b = rng.uniform(-1.0, 1.0, (2, 3))
        side = np.cross(b - a, rng.normal(size=3))
        side /= np.linalg.norm(side)
        c = a + rng.uniform(-0.5, 1.5) * (b - a) + 10.0 ** rng.uniform(-7, -4) * side
        a, b, c = (x.astype(np.float32).astype(np.float64) for x in (a, b, c))
        normal = np.cross(b - a, c - a)
        normal /= np.linalg.norm(normal)
        s, t = rng.uniform(-0.2, 1.0, 2)
        height = rng.choice([-1.0, 1.0]) * 10.0 ** rng.uniform(-9, -3)
        p = (a + s * (b - a) + t * (c - a) + height * normal).astype(np.float32).astype(np.float64)
        exact = np.sqrt(float(_exact_point_triangle_d2(p, a, b, c)))
        ours, _ = oracle_point_triangle(p, a, b, c)
        bench = point_triangle_d2(p, a, b, c)
        # The barycentrics of a 1e-7-thick sliver keep about 1e-9 of float64's digits, which
        # slides the nearest point within the plane by up to about 1e-11 (seen: 2e-11 for a
        # point on the triangle); the Gram form was off by 1e-7 to 2e-5.
        assert abs(np.sqrt(ours) - exact) <= 1e-10, (p, a, b, c, exact, np.sqrt(ours))
        assert abs(np.sqrt(bench) - exact) <= 1e-10, (p, a, b, c, exact, np.sqrt(bench))


def test_checker_rejects_wrong_answers(rng):
    """`check_answers` passes the oracle's own answers rounded to float32 and fails answers that
    are wrong by a little more than the tolerance: another triangle, a distance, a point off its
    triangle, weights that do not rebuild it, a higher duplicate id, a miss."""
    verts, faces = random_soup(rng, 60)
    faces = np.concatenate([faces, faces[:5]])  # triangle 60 duplicates triangle 0
    points = np.concatenate([verts[faces[0, :1]], all_points(query_points(rng, verts, faces, 10))])
    d_ref, prim_ref, q_ref = oracle_closest(verts, faces, points)
    tri = verts.astype(np.float64)[faces[prim_ref]]
    # Weights of q_ref (least squares in the triangle's plane), for the u, v check.
    uv = np.array([np.linalg.lstsq(np.column_stack([t[1] - t[0], t[2] - t[0]]), q - t[0], rcond=None)[0]
                   for t, q in zip(tri, q_ref)])
    uv = np.clip(uv, 0.0, 1.0)
    good = [q_ref.astype(np.float32), d_ref.astype(np.float32), prim_ref.astype(np.int32),
            uv[:, 0].astype(np.float32), uv[:, 1].astype(np.float32)]
    assert prim_ref[0] == 0
    check_answers(verts, faces, points, *good)
    i = int(np.argmax(d_ref))  # a point far from everything: its neighbours are clearly farther
    d_other = oracle_distance_to(verts, faces, points[i : i + 1].repeat(len(faces), 0), np.arange(len(faces)))
    farthest = int(np.argmax(d_other))
    assert d_other[farthest] > d_ref[i] * (1 + 1e-4)
    step = 3 * REL_TOL * np.abs(points[i]).max()
    away = (q_ref[i] - points[i]) / d_ref[i]  # moving the point along it changes its distance by step
    mutations = {
        "distance": lambda g: g[1].__setitem__(i, g[1][i] + step),
        "triangle": lambda g: g[2].__setitem__(i, farthest),
        "point": lambda g: g[0].__setitem__(i, g[0][i] + step * away),
        "weights": lambda g: g[3].__setitem__(i, g[3][i] + 0.1),
        "miss": lambda g: g[2].__setitem__(i, -1),
        "duplicate": lambda g: g[2].__setitem__(0, 60),
    }
    for name, mutate in mutations.items():
        bad = [x.copy() for x in good]
        mutate(bad)
        with pytest.raises(AssertionError):
            check_answers(verts, faces, points, *bad)
            pytest.fail(f"a wrong {name} passed")  # only reached when nothing raised


# ----------------------------------------------------------------------------- scenes against the oracle
@pytest.mark.parametrize("method", METHODS)
def test_random_soup_against_oracle(device, rng, method):
    verts, faces = random_soup(rng, 200)
    bvh = hlbvh_warp.build(verts, faces=faces, method=method, device=device)
    sets = query_points(rng, verts, faces, n=40)
    points = all_points(sets)
    closest, distance, prim, u, v, stats = hlbvh_warp.closest_point(bvh, points, return_barycentrics=True,
                                                                    stats=True)
    check_answers(verts, faces, points, closest, distance, prim, u, v)
    assert (prim >= 0).all()
    at = slice(len(points) - 2 * len(sets["vertex"]), len(points) - len(sets["edge"]))
    check_vertex_points(points[at], closest[at])
    # Every found point entered the root and tested at least one triangle.
    assert (stats.nodes_visited >= 1).all() and (stats.prims_tested >= 1).all()
    # Pruning works: far fewer triangle tests than the brute force, on average.
    assert stats.prims_tested.mean() < 0.5 * len(faces)


@pytest.mark.parametrize("method", ["hlbvh", "sbvh", "binned_sah"])
@pytest.mark.parametrize("shape", ["icosphere", "box"])
def test_closed_mesh_against_oracle(device, rng, method, shape):
    """Points inside, outside and on a closed mesh; a vertex shared by several triangles is an
    exact tie at distance 0 and must go to the lowest of them."""
    mesh = trimesh.creation.icosphere(subdivisions=3) if shape == "icosphere" else \
        trimesh.creation.box(extents=(1.0, 2.0, 0.5))
    verts, faces = np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)
    bvh = hlbvh_warp.build(verts, faces=faces, method=method, device=device)
    dirs = rng.normal(size=(100, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    radii = np.concatenate([rng.uniform(0.0, 0.4, 50), rng.uniform(1.2, 3.0, 50)])
    inside_outside = (dirs * radii[:, None]).astype(np.float32)
    for points in (inside_outside, all_points(query_points(rng, verts, faces, n=20))):
        closest, distance, prim, u, v = hlbvh_warp.closest_point(bvh, points, return_barycentrics=True)
        check_answers(verts, faces, points, closest, distance, prim, u, v)
    closest, distance, prim = hlbvh_warp.closest_point(bvh, verts)
    check_answers(verts, faces, verts, closest, distance, prim)
    check_vertex_points(verts, closest)
    # Each vertex is answered by a triangle that uses it (the mesh is closed and convex-ish: no
    # other triangle passes through a vertex).
    assert (faces[prim] == np.arange(len(verts))[:, None]).any(axis=1).all()


def _family_params():
    for family in stress_report.SCENE_FAMILIES:
        for method in METHODS:
            if method in SLOW_METHODS and family in ("soup", "closed"):
                continue
            yield family, method


@pytest.mark.parametrize(("family", "method"), list(_family_params()))
def test_stress_families_against_oracle(device, family, method):
    """Every adversarial scene of the stress report (identical and duplicated triangles, zero-area
    ones, 1e18 and 1e-18 coordinates, mixed scales, flat, slivers, one and two triangles)."""
    verts, faces = make_scene(family)
    bvh = hlbvh_warp.build(verts, faces=faces, method=method, device=device)
    sets = query_points(np.random.default_rng(1), verts, faces, n=25)
    points = all_points(sets)
    closest, distance, prim, u, v = hlbvh_warp.closest_point(bvh, points, return_barycentrics=True)
    check_answers(verts, faces, points, closest, distance, prim, u, v)
    vert = sets["vertex"]
    at = slice(len(points) - len(sets["edge"]) - len(vert), len(points) - len(sets["edge"]))
    check_vertex_points(vert, closest[at])


def test_shared_bunny_against_oracle(device, rng):
    mesh = shared_mesh("bunny")
    verts, faces = np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)
    bvh = hlbvh_warp.build(verts, faces=faces, device=device)
    sets = query_points(rng, verts, faces, n=30)
    points = all_points(sets)
    closest, distance, prim, u, v = hlbvh_warp.closest_point(bvh, points, return_barycentrics=True)
    check_answers(verts, faces, points, closest, distance, prim, u, v)


# ----------------------------------------------------------------------------- exact geometry
def _axis_aligned_scene(scale=1.0):
    """Four pairs of right triangles with legs of 2: triangle 2j in the plane z = 0 and 2j + 1 in
    z = 4, both at x offset 8j. From float32 points with few mantissa bits, distances to them are
    exact in float64 (normal (0, 0, 4), its square and the coordinates are dyadic), also after
    scaling by a power of two, so bounds and ties can be hit exactly."""
    base = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0]], np.float32)
    tris = [base + np.array([8.0 * (k // 2), 0, 4.0 * (k % 2)], np.float32) for k in range(8)]
    verts = np.concatenate(tris) * np.float32(scale)
    return verts, np.arange(len(verts), dtype=np.int32).reshape(-1, 3)


@pytest.mark.parametrize("method", METHODS)
def test_max_dist_is_inclusive(device, method):
    """A triangle at exactly max_dist counts; one float32 step below, it does not."""
    # (point, exact distance to triangle 0, the nearest): below its face, beside an edge, in a
    # vertex's region, on an edge, inside it and on its hypotenuse (distance 0).
    cases = [([0.5, 0.5, -0.75], 0.75), ([1.0, -0.5, 0.0], 0.5), ([-0.375, -0.5, 0.0], 0.625),
             ([1.0, 0.0, 0.0], 0.0), ([0.5, 0.5, 0.0], 0.0), ([1.0, 1.0, 0.0], 0.0)]
    for scale in (2.0**-40, 1.0, 2.0**40):  # exact scalings: the distances scale exactly
        verts, faces = _axis_aligned_scene(scale)
        bvh = hlbvh_warp.build(verts, faces=faces, method=method, device=device)
        for p, d in cases:
            p = np.array(p, np.float32) * np.float32(scale)
            d = float(np.float32(d * scale))
            closest, distance, prim = hlbvh_warp.closest_point(bvh, p, max_dist=d)
            assert prim[0] == 0 and distance[0] == d, (p, d, scale)
            check_answers(verts, faces, p, closest, distance, prim, max_dist=d)
            if d > 0:
                below = float(np.nextafter(np.float32(d), np.float32(0)))
                closest, distance, prim = hlbvh_warp.closest_point(bvh, p, max_dist=below)
                assert prim[0] == -1 and np.isinf(distance[0]) and np.isnan(closest).all(), (p, d, scale)


def test_max_dist_between_float32_values_still_includes_its_triangle(device, rng):
    """The kernel takes max_dist in float32: the host rounds it up, never down, so a triangle at
    exactly a float64 max_dist counts (half of these were dropped when it rounded to nearest)."""
    verts, faces = random_soup(rng, 200)
    bvh = hlbvh_warp.build(verts, faces=faces, device=device)
    points = rng.uniform(-0.5, 1.5, (60, 3)).astype(np.float32)
    exact, nearest, _ = oracle_closest(verts, faces, points)
    assert (np.float32(exact) != exact).sum() > 50  # most distances fall between float32 values
    for p, d, k in zip(points, exact, nearest):
        _, distance, prim = hlbvh_warp.closest_point(bvh, p, max_dist=d)
        assert prim[0] == k and abs(distance[0] - d) <= 1e-6 * d, (p, d)
        # A relative 1e-6 below lies more than one float32 step below the distance: nothing.
        assert hlbvh_warp.closest_point(bvh, p, max_dist=d * (1.0 - 1e-6))[2][0] == -1, (p, d)


@pytest.mark.parametrize("sort_from", [16, 10**9])
def test_one_max_dist_per_point(device, rng, monkeypatch, sort_from):
    """A bound per point, as a contact query with a thickness per particle asks: each bound rounds
    up on its own (a triangle at exactly its float64 distance counts, a relative 1e-6 below does
    not) and follows its point through the query order the CPU sorts points into."""
    verts, faces = random_soup(rng, 200)
    bvh = hlbvh_warp.build(verts, faces=faces, device=device)
    points = rng.uniform(-0.5, 1.5, (400, 3)).astype(np.float32)
    exact, nearest, _ = oracle_closest(verts, faces, points)
    below = np.arange(len(points)) % 2 == 1
    bounds = np.where(below, exact * (1.0 - 1e-6), exact)
    monkeypatch.setattr(query, "SORT_QUERIES_FROM", sort_from)
    if sort_from == 16 and wp.get_device(device).is_cpu:
        assert query._point_order(points, wp.get_device(device)) is not None  # the sorted path runs
    for bound_array in (bounds, wp.array(bounds, dtype=wp.float64, device=device)):
        closest, distance, prim = hlbvh_warp.closest_point(bvh, points, max_dist=bound_array)
        assert (prim[below] == -1).all() and np.isinf(distance[below]).all()
        assert np.array_equal(prim[~below], nearest[~below])
        assert np.allclose(distance[~below], exact[~below], rtol=1e-6, atol=0.0)
    # One bound in a one-element array is every point's bound.
    one = float(np.median(exact))
    _, distance, prim = hlbvh_warp.closest_point(bvh, points, max_dist=np.array([one]))
    found_ref = exact <= one * (1 - 1e-6)
    assert np.array_equal(prim[found_ref], nearest[found_ref])
    assert (prim[exact > one * (1 + 1e-6)] == -1).all()


@wp.kernel
def _integer_limit_kernel(limits: wp.array(dtype=wp.int32), out: wp.array(dtype=float)):
    i = wp.tid()
    out[i] = traversal.query_limit(limits[i], i) + traversal.query_limit(float(limits[i]), i)


def test_the_kernel_takes_a_bound_as_its_float_parameter_always_did(device, rng):
    """`closest_point_kernel` keeps the signature of the one-bound kernel users launched: an int or
    a NumPy float is a bound as a Python float is (its generic form could not take them). And an
    integer limit reads as the same float, so no launch of a generic kernel with one fails to
    compile (Warp would keep that failure for the whole module)."""
    verts, faces = random_soup(rng, 100)
    bvh = hlbvh_warp.build(verts, faces=faces, device=device)
    points = rng.uniform(-0.5, 1.5, (50, 3)).astype(np.float32)
    expected = hlbvh_warp.closest_point(bvh, points, max_dist=0.25)[2]
    assert 0 < (expected >= 0).sum() < len(points)
    n = len(points)
    none_f, none_i = wp.empty(0, dtype=float, device=device), wp.empty(0, dtype=wp.int32, device=device)
    for bound in (0.25, np.float32(0.25), np.float64(0.25)):
        out = [wp.empty(n, dtype=wp.vec3, device=device), wp.empty(n, dtype=float, device=device),
               wp.empty(n, dtype=wp.int32, device=device)]
        wp.launch(proximity.closest_point_kernel, dim=n, device=device,
                  inputs=[hlbvh_warp.view(bvh), wp.array(points, dtype=wp.vec3, device=device), bound, *out,
                          none_f, none_f, none_i, none_i])
        assert np.array_equal(out[2].numpy(), expected), bound
    wp.launch(proximity.closest_point_kernel, dim=n, device=device,
              inputs=[hlbvh_warp.view(bvh), wp.array(points, dtype=wp.vec3, device=device), 2, *out,
                      none_f, none_f, none_i, none_i])
    assert np.array_equal(out[2].numpy(), hlbvh_warp.closest_point(bvh, points, max_dist=2.0)[2])
    values = wp.array([3, -1, 0], dtype=wp.int32, device=device)
    doubled = wp.empty(3, dtype=float, device=device)
    wp.launch(_integer_limit_kernel, dim=3, device=device, inputs=[values, doubled])
    assert doubled.numpy().tolist() == [6.0, -2.0, 0.0]

def test_bad_max_dist_arrays_name_the_point(device):
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float32)
    bvh = hlbvh_warp.build(verts, faces=np.array([[0, 1, 2]]), device=device)
    points = np.zeros((4, 3))
    with pytest.raises(ValueError, match=r"shape \(4,\), got \(3,\)"):
        hlbvh_warp.closest_point(bvh, points, max_dist=np.ones(3))
    with pytest.raises(ValueError, match=r"max_dist must be >= 0, got nan \(point 2\)"):
        hlbvh_warp.closest_point(bvh, points, max_dist=np.array([1.0, 2.0, np.nan, -1.0]))
    with pytest.raises(ValueError, match="real numbers"):
        hlbvh_warp.closest_point(bvh, points, max_dist=np.array(["a"] * 4))
    # A (1, 1) or (P, 1) array is neither one bound nor one per point; booleans are no distances.
    for bad in (np.array([[5.0]]), np.full((4, 1), 5.0)):
        with pytest.raises(ValueError, match=r"max_dist must be a number or have shape \(4,\)"):
            hlbvh_warp.closest_point(bvh, points, max_dist=bad)
    with pytest.raises(ValueError, match="max_dist must hold real numbers, got dtype bool"):
        hlbvh_warp.closest_point(bvh, points, max_dist=np.array([True, False, True, True]))
    # Bounds past float32's range are unbounded, quietly, one or one per point.
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for huge in (1e39, 10**40, np.float64(1e300), np.full(4, 1e39), [1e39]):
            assert hlbvh_warp.closest_point(bvh, points, max_dist=huge)[2].tolist() == [0] * 4
    # Nothing was left behind: the next query answers.
    assert hlbvh_warp.closest_point(bvh, points, max_dist=np.full(4, 0.5))[2].tolist() == [0] * 4

@pytest.mark.parametrize("method", METHODS)
def test_exact_ties_go_to_the_lowest_id(device, rng, method):
    """Points midway between the two triangles of a pair are at bitwise equal distances from both
    (different triangles, different leaves): the lower id wins, whatever the tree."""
    verts, faces = _axis_aligned_scene()
    perm = rng.permutation(len(faces))
    faces = faces[perm]  # the triangle made as k now has id inv[k]
    inv = np.argsort(perm)
    bvh = hlbvh_warp.build(verts, faces=faces, method=method, device=device)
    xy = np.array([[0.5, 0.25], [0.25, 1.0], [1.0, 0.5], [0.0, 0.0], [1.0, 1.0], [2.0, 0.0], [-1.0, -0.5],
                   [3.0, 3.0]], np.float32)  # inside, on edges and vertices, beside them
    pair = np.arange(len(xy)) % 4
    points = np.column_stack([8.0 * pair + xy[:, 0], xy[:, 1], np.full(len(xy), 2.0)]).astype(np.float32)
    closest, distance, prim = hlbvh_warp.closest_point(bvh, points)
    assert np.array_equal(prim, np.minimum(inv[2 * pair], inv[2 * pair + 1]))
    check_answers(verts, faces, points, closest, distance, prim)
    # The mirror images are found as well, at the same distances.
    check_answers(verts, faces, points * [1, 1, 0], *hlbvh_warp.closest_point(bvh, points * [1, 1, 0]))


@pytest.mark.parametrize(("method", "exponent"), [(m, e) for m in METHODS for e in (-15, -6, 0, 6, 15)
                                                  if m not in SLOW_METHODS or e == 0])
def test_duplicate_triangles_go_to_the_lowest_id(device, rng, method, exponent):
    """Each triangle listed four times under shuffled ids: only the lowest id of the four is a
    valid answer, for every builder, at every scale whose squared distances are normal floats
    (the slow builder at one scale)."""
    scale = 10.0**exponent
    verts, faces = stress_report._soup(rng, 40, scale=scale, offset=rng.normal() * scale)
    faces = np.concatenate([faces] * 4)[rng.permutation(4 * len(faces))]
    bvh = hlbvh_warp.build(verts, faces=faces, method=method, device=device)
    points = all_points(query_points(rng, verts, faces, n=30))
    closest, distance, prim = hlbvh_warp.closest_point(bvh, points)
    check_answers(verts, faces, points, closest, distance, prim)  # includes the lowest-duplicate rule


def _two_leaf_duplicate(tri, device):
    """Triangle 1 duplicates triangle 0; the root's first leaf (visited first: equal boxes) holds 1."""
    return bvh_from_numpy(
        method="handmade", config=BuildConfig(), device=device,
        prim_lowers=np.repeat(tri.min(0)[None], 2, 0), prim_uppers=np.repeat(tri.max(0)[None], 2, 0),
        prim_order=np.array([1, 0]), node_left=np.array([1, -1, -1]), node_right=np.array([2, -1, -1]),
        node_begin=np.array([0, 0, 1]), node_end=np.array([2, 1, 2]),
        vertices=wp.array(tri, dtype=wp.vec3, device=device),
        faces=wp.array(np.array([[0, 1, 2], [0, 1, 2]], np.int32), dtype=wp.int32, device=device))


def test_duplicate_tie_with_normal_squared_distances(device):
    """The control of the test below: the same geometry scaled by 2^40 keeps the rule."""
    tri = np.array([[2.4275658e-23, 7.7269566e-21, 2.2281929e-21], [7.8830522e-21, 1.9420459e-22, 7.0277119e-21],
                    [8.9744347e-21, 3.7384161e-21, 6.8685831e-21]], np.float32) * np.float32(2.0**40)
    point = np.array([-2.1696194e-21, 1.1519425e-20, 2.0663103e-21], np.float32) * np.float32(2.0**40)
    bvh = _two_leaf_duplicate(tri, device)
    for view in (query.view(bvh), canonical_view(bvh)):
        closest, distance, prim = run_user_kernel(view, point, np.inf, device)[:3]
        assert prim[0] == 0 and np.array_equal(closest[0], tri[0])


def test_duplicate_tie_with_subnormal_squared_distance(device):
    """Equal distances must go to the lowest id also where the squared distance is a float32
    subnormal (distance < 1.1e-19: points near a surface of the 1e-18 scene family). The box
    pruning compares float32 box distances with a relative margin of 1e-6, and a subnormal has
    fewer mantissa bits: with that margin alone the box of the lower duplicate rounded above the
    best distance and was pruned (the absolute PRUNE_SLACK covers it). Point nearest to vertex 0
    (a box corner): box distance = triangle distance."""
    tri = np.array([[2.4275658e-23, 7.7269566e-21, 2.2281929e-21], [7.8830522e-21, 1.9420459e-22, 7.0277119e-21],
                    [8.9744347e-21, 3.7384161e-21, 6.8685831e-21]], np.float32)
    point = np.array([-2.1696194e-21, 1.1519425e-20, 2.0663103e-21], np.float32)
    bvh = _two_leaf_duplicate(tri, device)
    closest, distance, prim = hlbvh_warp.closest_point(bvh, point)
    assert np.array_equal(closest[0], tri[0])
    assert prim[0] == 0, f"prim {prim[0]}: the duplicate with the higher id"


def test_point_exactly_on_a_vertex_is_at_distance_zero(device):
    """A query point exactly on a vertex is at distance exactly 0 (the kernel returns the vertex
    itself as the closest point), so an inclusive bound of 0 finds it. On vertex b or c the edge
    functions are (0, 0, nn), the face branch, whose plane projection left a float64 rounding
    residue of 1.6e-17 before vertices were matched exactly."""
    tri = np.array([[0.8050029, 0.8079408, 0.51532555], [0.28580138, 0.053930704, 0.38336888],
                    [0.4084732, 0.045275193, 0.04875771]], np.float32)
    bvh = hlbvh_warp.build(tri, faces=np.array([[0, 1, 2]], np.int32), device=device)
    closest, distance, prim = hlbvh_warp.closest_point(bvh, tri)
    assert np.array_equal(closest, tri) and prim.tolist() == [0, 0, 0]  # holds
    assert distance.tolist() == [0.0, 0.0, 0.0]
    assert hlbvh_warp.closest_point(bvh, tri, max_dist=0.0)[2].tolist() == [0, 0, 0]


def test_thin_triangle_face_region(device):
    """A needle (angle 1e-12 rad at vertex a; the oracle's normal equations cancel there, so the
    expected answer is worked out by hand): a point 1e-15 above its face is 1e-15 away, not the
    2e-13 of its nearest edge."""
    verts = np.array([[0, 0, 0], [1, 0, 0], [1, 1e-12, 0]], np.float32)
    faces = np.array([[0, 1, 2]], np.int32)
    p = np.array([[0.8, 0.2e-12, 1e-15], [0.8, 0.2e-12, -1e-15]], np.float32)
    bvh = hlbvh_warp.build(verts, faces=faces, device=device)
    closest, distance, prim, u, v = hlbvh_warp.closest_point(bvh, p, return_barycentrics=True)
    h = float(np.float32(1e-15))
    assert prim.tolist() == [0, 0]
    assert np.allclose(distance, h, rtol=1e-6, atol=0)
    # The projection: (1 - u - v) a + u b + v c = (0.8, 0.2e-12, 0): v = y / c_y, u = x - v.
    v_ref = float(np.float32(0.2e-12)) / float(np.float32(1e-12))
    assert np.allclose(v, v_ref, rtol=1e-6) and np.allclose(u, float(np.float32(0.8)) - v_ref, rtol=1e-6)
    assert np.allclose(closest[:, :2], p[:, :2], rtol=1e-6, atol=0) and (np.abs(closest[:, 2]) <= 1e-21).all()




def test_needles_whose_vertices_differ_widely_in_magnitude(device):
    """Needles (c = 2 b, a within 1e-15..1e-10 of the origin): b - a then rounds in float64, and the
    float64 cross product cancels, tilting the normal by up to 1e-5 (a review found distances 13x
    too large, 1.6e-6 of the scale off). The normal is now computed exactly below sin(angle)
    3.6e-6; every distance must match the rational one to 1e-12 of the scale, besides the float32
    rounding of the distance returned."""
    from math import sqrt

    gen = np.random.default_rng(6)
    rows = []
    for _ in range(120):
        b = gen.normal(size=3)
        b /= np.linalg.norm(b)
        side = np.cross(b, gen.normal(size=3))
        side /= np.linalg.norm(side)
        up = np.cross(b, side)
        a = 10.0 ** gen.uniform(-15, -10) * (up + gen.normal() * 10.0 ** gen.uniform(-8, 0) * side)
        p = gen.uniform(1.05, 1.95) * b + 10.0 ** gen.uniform(-8, 0) * side
        rows.append((p, a, b, 2 * b))
    # The review's case first.
    rows.insert(0, ([0.95570445, 0.6443991, -0.66360235], [1.3326483e-11, -2.6009016e-11, -6.0638838e-12],
                    [0.7185566, 0.48449838, -0.49893668], [1.4371132, 0.96899676, -0.99787337]))
    for p, a, b, c in rows:
        tri = np.array([a, b, c], np.float32)
        bvh = hlbvh_warp.build(tri, faces=np.array([[0, 1, 2]], np.int32), device=device)
        distance = float(hlbvh_warp.closest_point(bvh, np.float32(p))[1][0])
        expected = sqrt(exact_distance_sq(p, *tri))
        assert abs(distance - expected) <= 2.0**-24 * expected + 1e-12 * 2.0, (p, tri.tolist(), distance, expected)


# ----------------------------------------------------------------------------- bounds, NaN, empty, errors
@pytest.mark.parametrize("method", ["hlbvh", "median", "sbvh"])
def test_max_dist_bounds_the_search(device, rng, method):
    verts, faces = random_soup(rng, 300)
    bvh = hlbvh_warp.build(verts, faces=faces, method=method, device=device)
    points = all_points(query_points(rng, verts, faces, n=40))
    full = hlbvh_warp.closest_point(bvh, points, stats=True)
    d_ref, _ = check_answers(verts, faces, points, *full[:3])
    for bound in (0.0, float(np.quantile(d_ref, 0.3)), float(np.quantile(d_ref, 0.8))):
        closest, distance, prim, stats = hlbvh_warp.closest_point(bvh, points, max_dist=bound, stats=True)
        check_answers(verts, faces, points, closest, distance, prim, max_dist=bound)
        found = prim >= 0
        assert 0 < found.sum() < len(points)
        # What a bounded search finds is the unbounded answer, bit for bit.
        assert np.array_equal(prim[found], full[2][found]) and np.array_equal(distance[found], full[1][found])
        assert np.array_equal(closest[found], full[0][found])
        # A tighter bound never opens a box the unbounded search would not.
        assert (stats.nodes_visited <= full[3].nodes_visited).all()
        assert (stats.prims_tested <= full[3].prims_tested).all()
        assert (stats.nodes_visited[found] >= 1).all() and (stats.prims_tested[found] >= 1).all()
    # Points far outside with a small bound: the root box is beyond it, nothing is opened.
    far = (verts.max(0) + 10.0 + rng.random((20, 3))).astype(np.float32)
    _, distance, prim, stats = hlbvh_warp.closest_point(bvh, far, max_dist=1.0, stats=True)
    assert (prim == -1).all() and np.isinf(distance).all()
    assert (stats.nodes_visited == 0).all() and (stats.prims_tested == 0).all()


@pytest.mark.parametrize("method", METHODS)
def test_boxes_farther_than_the_best_are_not_opened(device, method):
    """Two triangles in the planes z = 0 and z = 2 + gap above the same square; a point at height 1
    over the lower one, 1 + gap below the upper one. Nearest first, the lower triangle (box
    distance 1) is tested first; the upper one's box lies gap farther and must then be skipped,
    down to gaps the 1e-6 float32 margin of the box test cannot tell from a tie (where it is
    opened: `offer` decides)."""
    for gap in (1.0, 0.2, 1e-3, 1e-5):  # float32(2 + 1e-5) is 2 + 1.0014e-5
        tri = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0]], np.float32)
        verts = np.concatenate([tri, tri + np.array([0, 0, 2 + gap], np.float32)])
        faces = np.arange(6, dtype=np.int32).reshape(2, 3)
        bvh = hlbvh_warp.build(verts, faces=faces, method=method, device=device)
        point = np.array([[0.5, 0.5, 1.0]], np.float32)
        out = hlbvh_warp.closest_point(bvh, point, stats=True)
        check_answers(verts, faces, point, *out[:3])
        assert out[2][0] == 0 and out[1][0] == 1.0
        assert out[3].prims_tested[0] == 1, f"gap {gap}: the farther box was opened"
    # At a tie the farther-or-equal box is opened and the lower id wins (here: the upper one).
    verts = np.concatenate([tri + np.array([0, 0, 2], np.float32), tri])
    bvh = hlbvh_warp.build(verts, faces=faces, method=method, device=device)
    out = hlbvh_warp.closest_point(bvh, point, stats=True)
    assert out[2][0] == 0 and out[1][0] == 1.0 and out[3].prims_tested[0] == 2


def test_nan_and_inf_points_find_nothing(device, rng):
    verts, faces = random_soup(rng, 50)
    bvh = hlbvh_warp.build(verts, faces=faces, device=device)
    good = rng.random((6, 3)).astype(np.float32)
    bad = np.array([[np.nan, 0, 0], [0, np.inf, 0], [0, 0, -np.inf], [np.nan] * 3, [np.inf, -np.inf, 0]], np.float32)
    points = np.concatenate([good[:3], bad, good[3:]])
    closest, distance, prim, u, v, stats = hlbvh_warp.closest_point(bvh, points, return_barycentrics=True,
                                                                    stats=True)
    check_answers(verts, faces, points, closest, distance, prim, u, v)
    is_bad = np.zeros(len(points), bool)
    is_bad[3:8] = True
    assert (prim[is_bad] == -1).all() and (prim[~is_bad] >= 0).all()
    assert (stats.nodes_visited[is_bad] == 0).all() and (stats.prims_tested[is_bad] == 0).all()
    # The user-kernel function: a NaN bound finds nothing as well (the batched call refuses one).
    out = run_user_kernel(query.view(bvh), good, np.nan, device)
    assert (out[2] == -1).all() and np.isinf(out[1]).all()


def test_empty_and_single_points(device, rng):
    verts, faces = random_soup(rng, 20)
    bvh = hlbvh_warp.build(verts, faces=faces, device=device)
    closest, distance, prim, u, v, stats = hlbvh_warp.closest_point(bvh, np.zeros((0, 3)),
                                                                    return_barycentrics=True, stats=True)
    assert closest.shape == (0, 3) and distance.shape == (0,) and prim.shape == (0,)
    assert u.shape == v.shape == (0,) and stats.nodes_visited.shape == stats.prims_tested.shape == (0,)
    assert closest.dtype == np.float32 and distance.dtype == np.float32 and prim.dtype == np.int32
    # One (3,) point, a list, float64, integers and a Warp array: the same answers.
    p = np.array([0.25, 0.5, 2.0], np.float32)
    ref = hlbvh_warp.closest_point(bvh, p[None])
    check_answers(verts, faces, p[None], *ref)
    for same in (p, p.tolist(), p.astype(np.float64)[None], wp.array(p[None], dtype=wp.vec3, device=device)):
        out = hlbvh_warp.closest_point(bvh, same)
        for x, y in zip(out, ref):
            assert np.array_equal(x, y)
    ints = np.array([[0, 1, 2]], np.int64)
    check_answers(verts, faces, ints, *hlbvh_warp.closest_point(bvh, ints))


def test_invalid_inputs_raise(device, rng):
    verts, faces = random_soup(rng, 20)
    bvh = hlbvh_warp.build(verts, faces=faces, device=device)
    boxes = hlbvh_warp.build_from_bounds(verts[faces].min(1), verts[faces].max(1), device=device)
    with pytest.raises(ValueError, match="over a mesh"):
        hlbvh_warp.closest_point(boxes, np.zeros((1, 3)))
    with pytest.raises(ValueError, match="takes a Bvh"):
        hlbvh_warp.closest_point(trimesh.creation.box(), np.zeros((1, 3)))
    for shape in [(4, 2), (2, 3, 3), (4,), (3, 1)]:
        with pytest.raises(ValueError, match="shape"):
            hlbvh_warp.closest_point(bvh, np.zeros(shape))
    for points in (np.array([["a", "b", "c"]]), np.zeros((2, 3), complex), np.array([[None, 1, 2]], object)):
        with pytest.raises(ValueError, match="real numbers"):
            hlbvh_warp.closest_point(bvh, points)
    for bound in (-1.0, -1e-30, float("nan"), float("-inf")):
        with pytest.raises(ValueError, match="max_dist must be >= 0"):
            hlbvh_warp.closest_point(bvh, np.zeros((1, 3)), max_dist=bound)
    for bound in ("far", None, [1.0, 2.0]):
        with pytest.raises(ValueError, match="max_dist must be a number"):
            hlbvh_warp.closest_point(bvh, np.zeros((1, 3)), max_dist=bound)
    # Still usable afterwards, and numeric bounds of any type are fine.
    for bound in (np.float32(10.0), 10, np.int64(10)):
        check_answers(verts, faces, np.zeros((1, 3)), *hlbvh_warp.closest_point(bvh, np.zeros((1, 3)), max_dist=bound),
                      max_dist=10.0)


# ----------------------------------------------------------------------------- trees and views
@pytest.mark.parametrize("deep", ["left", "right"])
def test_chain_deeper_than_the_stack(device, rng, deep):
    """A caterpillar tree of depth 299: the full-stack fallback keeps the answers exact, in the
    packed layout and on the canonical arrays."""
    n = 300
    verts = stress_report.scene_soup(rng)[0][: 3 * n]
    faces = np.arange(3 * n, dtype=np.int32).reshape(-1, 3)
    bvh = caterpillar(verts, faces, device, deep=deep)
    assert bvh.depth == n - 1 > TRAVERSAL_STACK_SIZE
    points = all_points(query_points(rng, verts, faces, n=20))
    # And from 1e7 sizes away, where the walk is in float64 (`packed_far_point_query`).
    extent = float(np.ptp(verts, axis=0).max())
    far = (verts.mean(0) + 1e7 * extent * _far_directions(rng, 4)).astype(np.float32)
    points = np.concatenate([points, far])
    out = hlbvh_warp.closest_point(bvh, points, return_barycentrics=True)
    check_answers(verts, faces, points, *out)
    _check_far_answers(verts, faces, far, *(x[-len(far):] for x in out[:3]))
    canonical = run_user_kernel(canonical_view(bvh), points, np.inf, device)
    check_answers(verts, faces, points, *canonical[:5])


def test_spatial_split_tree_is_exact(device, rng):
    """SBVH leaves bound parts of triangles and list a triangle in several leaves: the answers,
    the lowest-id rule among duplicates and the canonical walk stay exact."""
    small, _ = random_soup(rng, 150, scale=1.0)
    # Long thin triangles across the cluster (x from -1 to 2) make spatial splits pay.
    a = rng.random((40, 3))
    a[:, 0] = -1.0
    b = a.copy()
    b[:, 0] = 2.0
    c = b + [0.0, 0.05, 0.0]
    verts = np.concatenate([small, np.stack([a, b, c], axis=1).reshape(-1, 3).astype(np.float32)])
    faces = np.arange(len(verts), dtype=np.int32).reshape(-1, 3)
    faces = np.concatenate([faces, faces[::7]])  # duplicated triangles, higher ids
    bvh = hlbvh_warp.build(verts, faces=faces, method="sbvh", device=device)
    assert bvh.has_duplicates, "the scene should make the SBVH split triangles"
    points = all_points(query_points(rng, verts, faces, n=40))
    out = hlbvh_warp.closest_point(bvh, points, return_barycentrics=True, stats=True)
    check_answers(verts, faces, points, *out[:5])
    canonical = run_user_kernel(canonical_view(bvh), points, np.inf, device)
    check_answers(verts, faces, points, *canonical[:5])
    assert np.array_equal(canonical[2], out[2]) and np.array_equal(canonical[1], out[1])


@pytest.mark.parametrize("max_leaf_size", [1, 4])
def test_user_kernel_packed_and_canonical_views_agree(device, rng, max_leaf_size):
    """`bvh_closest_point` from a user kernel: the packed view gives the batched call's answers bit
    for bit (same function), the canonical walk the same answers, all matching the oracle."""
    mesh = trimesh.util.concatenate([trimesh.creation.icosphere(subdivisions=3),
                                     trimesh.creation.box(extents=(0.5, 0.5, 0.5)).apply_translation((2, 0, 0))])
    verts, faces = np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)
    bvh = hlbvh_warp.build(verts, faces=faces, device=device, config=BuildConfig(max_leaf_size=max_leaf_size))
    points = all_points(query_points(rng, verts, faces, n=40))
    bound = 0.3
    batched = hlbvh_warp.closest_point(bvh, points, max_dist=bound, return_barycentrics=True, stats=True)
    packed = run_user_kernel(hlbvh_warp.view(bvh), points, bound, device)
    canonical = run_user_kernel(canonical_view(bvh), points, bound, device)
    for name, out in (("packed", packed), ("canonical", canonical)):
        check_answers(verts, faces, points, *out[:5], max_dist=bound)
        for x, y in zip(out[:5], batched[:5]):
            assert np.array_equal(x, y, equal_nan=True), name
    assert np.array_equal(packed[5], batched[5].nodes_visited)
    assert np.array_equal(packed[6], batched[5].prims_tested)
    # Per-point bounds: each point gets its own.
    bounds = np.where(np.arange(len(points)) % 2 == 0, np.inf, 0.0).astype(np.float32)
    out = run_user_kernel(hlbvh_warp.view(bvh), points, bounds, device)
    even = np.arange(len(points)) % 2 == 0
    assert np.array_equal(out[2][even], hlbvh_warp.closest_point(bvh, points[even])[2])
    assert np.array_equal(out[2][~even], hlbvh_warp.closest_point(bvh, points[~even], max_dist=0.0)[2])


@pytest.mark.parametrize("method", DYNAMIC_METHODS)
def test_view_follows_refit_and_rebuild(device, rng, method):
    """A view taken once keeps answering for the moved vertices after a refit and a rebuild."""
    verts, faces = random_soup(rng, 200)
    builder = Builder(len(faces), device=device, method=method)
    bvh = builder.build(verts, faces)
    view = hlbvh_warp.view(bvh)
    points = all_points(query_points(rng, verts, faces, n=30))
    frames = [verts, (verts * np.float32(1.5) + np.float32(0.2)).astype(np.float32),
              (verts + 0.3 * rng.standard_normal(verts.shape)).astype(np.float32)[:, [2, 0, 1]]]
    previous = None
    for k, frame in enumerate(frames):
        if k == 1:
            builder.refit(frame)
        elif k == 2:
            builder.rebuild(frame)
        out = run_user_kernel(view, points, np.inf, device)
        check_answers(frame, faces, points, *out[:5])
        check_answers(frame, faces, points, *hlbvh_warp.closest_point(builder.bvh, points, return_barycentrics=True))
        if previous is not None:
            assert not np.array_equal(previous, out[1]), "the answers did not move with the vertices"
        previous = out[1]


# ----------------------------------------------------------------------------- trimesh drop-in
def test_proximity_query_on_surface(device, rng):
    mesh = trimesh.creation.icosphere(subdivisions=3)
    pq = hlbvh_warp.ProximityQuery(mesh, device=device)
    points = rng.normal(size=(200, 3)) * 1.2
    closest, distance, triangle_id = pq.on_surface(points)
    # trimesh's conventions: float64 points and distances, int64 triangle ids.
    assert closest.shape == (200, 3) and distance.shape == (200,) and triangle_id.shape == (200,)
    assert closest.dtype == np.float64 and distance.dtype == np.float64 and triangle_id.dtype == np.int64
    verts = np.asarray(mesh.vertices, np.float32)
    check_answers(verts, mesh.faces, points, closest.astype(np.float32), distance.astype(np.float32),
                  triangle_id.astype(np.int32))
    # The mesh changes: the BVH is rebuilt for the new vertices.
    mesh.vertices = mesh.vertices * 2.0 + 0.5
    closest, distance, triangle_id = pq.on_surface(points)
    check_answers(np.asarray(mesh.vertices, np.float32), mesh.faces, points, closest.astype(np.float32),
                  distance.astype(np.float32), triangle_id.astype(np.int32))


def test_proximity_query_signed_distance(device, rng):
    """trimesh's sign: positive inside (and on) the closed surface, negative outside."""
    mesh = trimesh.creation.icosphere(subdivisions=3)
    pq = hlbvh_warp.ProximityQuery(mesh, device=device)
    dirs = rng.normal(size=(120, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    radii = np.concatenate([rng.uniform(0.0, 0.9, 60), rng.uniform(1.1, 3.0, 60)])
    points = dirs * radii[:, None]
    sd = pq.signed_distance(points)
    assert sd.shape == (120,) and sd.dtype == np.float64
    d_ref, _, _ = oracle_closest(mesh.vertices.astype(np.float32), mesh.faces, points.astype(np.float32))
    assert (sd[:60] > 0).all() and (sd[60:] < 0).all()
    assert np.allclose(np.abs(sd), d_ref, rtol=0, atol=REL_TOL * 3.0)
    on = pq.signed_distance(np.asarray(mesh.vertices, np.float32).astype(np.float64)[:30])
    assert (on == 0).all() and not np.signbit(on).any()


def test_proximity_query_signed_distance_follows_trimesh_on_open_meshes(device, rng, monkeypatch):
    """On a mesh that is not closed the sign is trimesh's: the closest triangle's normal where the
    point projects into it, ray parity elsewhere (a review found ray parity used everywhere, so
    both sides of an open square came out negative). The oracle is trimesh 5.2's own
    `signed_distance`, with the two parts that need `rtree` (its closest point and its ray
    queries) served by this package."""
    import trimesh.proximity

    square = trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], faces=[[0, 1, 2], [0, 2, 3]])
    points = np.array([[0.5, 0.5, 1.0], [0.5, 0.5, -1.0], [0.3, 0.6, 0.2], [0.3, 0.6, -0.2]])
    # Normals +z: the side they face is outside (negative), the other inside.
    np.testing.assert_allclose(hlbvh_warp.ProximityQuery(square, device=device).signed_distance(points),
                               [-1.0, 1.0, -0.2, 0.2], rtol=1e-6)
    sphere = trimesh.creation.icosphere(subdivisions=3)
    holed = trimesh.Trimesh(sphere.vertices, sphere.faces[5:])
    dirs = rng.normal(size=(400, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    points = np.concatenate([dirs * rng.uniform(0.2, 1.8, (400, 1)), [[0.5, 0.5, np.nan]]])
    ours = hlbvh_warp.ProximityQuery(holed, device=device).signed_distance(points)
    assert np.isnan(ours[-1])
    helper = hlbvh_warp.ProximityQuery(holed, device=device)
    monkeypatch.setattr(trimesh.proximity, "closest_point", lambda mesh, pts: helper.on_surface(pts))
    holed.ray = hlbvh_warp.RayMeshIntersector(holed, device=device)
    expected = trimesh.proximity.signed_distance(holed, points[:-1])
    np.testing.assert_array_equal(np.sign(ours[:-1]), np.sign(expected))
    np.testing.assert_allclose(ours[:-1], expected, rtol=1e-12)


# ----------------------------------------------------------------------------- fuzz
@settings(max_examples=25, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    seed=st.integers(0, 2**32 - 1),
    num_tris=st.integers(1, 40),
    exponent=st.integers(-15, 15),
    duplicate=st.booleans(),
    flat_axis=st.sampled_from([None, 0, 1, 2]),
    method=st.sampled_from(METHODS),
    bounded=st.booleans(),
)
def test_fuzzed_small_soups(device, seed, num_tris, exponent, duplicate, flat_axis, method, bounded):
    rng = np.random.default_rng(seed)
    scale = 10.0**exponent
    verts, faces = stress_report._soup(rng, num_tris, scale=scale, offset=rng.normal() * scale)
    if duplicate:
        faces = np.concatenate([faces, faces[: max(1, num_tris // 2)]])
        faces = faces[rng.permutation(len(faces))]
    if flat_axis is not None:
        verts[:, flat_axis] = verts[0, flat_axis]
    bvh = hlbvh_warp.build(verts, faces=faces, method=method, device=device)
    points = all_points(query_points(rng, verts, faces, n=8))
    max_dist = float(np.float32(0.1 * scale)) if bounded else np.inf
    out = hlbvh_warp.closest_point(bvh, points, max_dist=max_dist, return_barycentrics=True)
    check_answers(verts, faces, points, *out, max_dist=max_dist)


# ----------------------------------------------------------------------------- query order
def test_points_in_morton_order_give_the_callers_answers(device, rng, monkeypatch):
    """`closest_point` may query a batch in Morton order (on the CPU, for incoherent batches):
    every output, statistics included, comes back in the caller's order, equal to a batch
    queried as given, NaN points included."""
    verts, faces = random_soup(rng, 400)
    bvh = hlbvh_warp.build(verts, faces=faces, device=device)
    points = rng.uniform(-0.5, 1.5, (3000, 3)).astype(np.float32)
    points[[5, 77, 2999]] = np.nan
    monkeypatch.setattr(query, "SORT_QUERIES_FROM", 10**9)
    as_given = hlbvh_warp.closest_point(bvh, points, return_barycentrics=True, stats=True)
    monkeypatch.setattr(query, "SORT_QUERIES_FROM", 16)
    order = query._point_order(points, wp.get_device(device))
    if wp.get_device(device).is_cpu:
        assert order is not None and np.array_equal(np.sort(order), np.arange(len(points)))
        assert set(order[-3:].tolist()) == {5, 77, 2999}  # points with NaN last
    sorted_run = hlbvh_warp.closest_point(bvh, points, return_barycentrics=True, stats=True)
    for a, b in zip(as_given[:5], sorted_run[:5]):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(as_given[5].nodes_visited, sorted_run[5].nodes_visited)
    np.testing.assert_array_equal(as_given[5].prims_tested, sorted_run[5].prims_tested)
    check_answers(verts, faces, points, *sorted_run[:5])


def test_a_batch_whose_sampled_steps_all_meet_a_nan_point_answers_quietly(device, rng):
    """NaN points are valid queries (they find nothing). In a large batch where every other point
    is NaN, every consecutive step the query order samples meets one: the median of those steps
    raised NumPy's 'All-NaN slice' RuntimeWarning before the batch was answered (as given)."""
    import warnings

    verts, faces = random_soup(rng, 50)
    bvh = hlbvh_warp.build(verts, faces=faces, device=device)
    points = rng.uniform(-0.5, 1.5, (query.SORT_QUERIES_FROM + 2, 3)).astype(np.float32)
    points[::2] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, distance, prim = hlbvh_warp.closest_point(bvh, points)
    assert (prim[::2] == -1).all() and np.isinf(distance[::2]).all()
    assert np.array_equal(prim[1::2], hlbvh_warp.closest_point(bvh, points[1::2])[2])


def test_query_order_leaves_coherent_or_small_batches_alone(rng):
    cpu = wp.get_device("cpu")
    sphere = trimesh.creation.icosphere(subdivisions=5)  # 10242 vertices, listed coherently
    vertices = np.asarray(sphere.vertices, np.float32)
    # Consecutive icosphere vertices lie 2.3% of the extent apart (median): left as they are.
    assert query._point_order(vertices, cpu) is None
    shuffled = vertices[rng.permutation(len(vertices))]
    order = query._point_order(shuffled, cpu)
    assert order is not None
    # Morton order: consecutive points much closer than in the shuffled order.
    def median_step(p):
        return np.median(np.linalg.norm(np.diff(p, axis=0), axis=1))
    assert median_step(shuffled[order]) < 0.1 * median_step(shuffled)
    assert query._point_order(shuffled[: query.SORT_QUERIES_FROM - 1], cpu) is None


def test_morton_codes_interleave_bits():
    """The codes against a bit-by-bit interleave: bit i of x, y, z lands at 3i + 2, 3i + 1, 3i."""
    cells = np.random.default_rng(3).integers(0, 1024, (200, 3))
    spread = [host_morton.spread_bits(cells[:, k]) for k in range(3)]
    for row, (x, y, z) in enumerate(cells):
        expected = sum(((int(x) >> i) & 1) << (3 * i + 2) | ((int(y) >> i) & 1) << (3 * i + 1)
                       | ((int(z) >> i) & 1) << (3 * i) for i in range(10))
        assert (spread[0][row] << 2 | spread[1][row] << 1 | spread[2][row]) == expected
    # Points at the corners of their box take the extreme codes; a NaN point the sentinel after all.
    pts = np.array([[0, 0, 0], [1, 1, 1], [np.nan, 0, 0], [0.5, 0.5, 0.5]], np.float32)
    codes = host_morton.morton_codes(pts)
    assert codes[0] == 0 and codes[1] == (1 << 30) - 1 and codes[2] > codes[1] and 0 < codes[3] < codes[1]


# ----------------------------------------------------------------- pinned by the second mutation audit
@wp.kernel
def _exact_normals_kernel(a: wp.array(dtype=wp.vec3), b: wp.array(dtype=wp.vec3), c: wp.array(dtype=wp.vec3),
                          out: wp.array(dtype=wp.vec3d)):
    i = wp.tid()
    out[i] = proximity.exact_normal(a[i], b[i], c[i])


def test_exact_normal_is_within_an_ulp_of_the_rational_cross_product(device):
    """Needles whose vertices differ widely in magnitude, where the float64 cross product cancels
    badly: each component of `proximity.exact_normal` within about an ulp of the exact one."""
    from fractions import Fraction

    rng = np.random.default_rng(3)
    n = 400
    a = (rng.standard_normal((n, 3)) * 10.0 ** rng.uniform(-3, 7, (n, 1))).astype(np.float32)
    direction = rng.standard_normal((n, 3))
    b = (a + direction * 10.0 ** rng.uniform(-3, 3, (n, 1))).astype(np.float32)
    c = (a + (direction + 1e-5 * rng.standard_normal((n, 3))) * 10.0 ** rng.uniform(-3, 3, (n, 1))).astype(np.float32)
    out = wp.zeros(n, dtype=wp.vec3d, device=device)
    wp.launch(_exact_normals_kernel, dim=n, device=device,
              inputs=[wp.array(x, dtype=wp.vec3, device=device) for x in (a, b, c)] + [out])
    got = out.numpy()
    worst = 0.0
    for i in range(n):
        pa, pb, pc = ([Fraction(float(x)) for x in p[i]] for p in (a, b, c))
        u = [pb[k] - pa[k] for k in range(3)]
        w = [pc[k] - pa[k] for k in range(3)]
        exact = [u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0]]
        for k in range(3):
            if exact[k] != 0:
                worst = max(worst, float(abs(Fraction(float(got[i][k])) - exact[k]) / abs(exact[k])))
    assert worst <= 2.0**-51


@pytest.mark.parametrize("where", ["far", "huge scale"])
def test_far_points_prune_with_float64_box_distances(device, rng, where):
    """Far from the mesh (1e7 of its sizes) every box's float32 squared distance lies within the
    float32 margin of the best triangle's, and on a mesh at 1e30 the squares overflow float32:
    with float32 box tests alone the search entered every node and tested every triangle (575 ms
    for 100 points on an 82k-triangle sphere, against 0.6 ms for wp.Mesh). The boxes float32
    cannot decide are measured again in float64, so such a search prunes as a near one does, and
    still gives the oracle's triangle (lowest id among equal distances)."""
    sphere = trimesh.creation.icosphere(subdivisions=3)
    verts = np.asarray(sphere.vertices, np.float32)
    faces = np.asarray(sphere.faces, np.int32)
    directions = rng.normal(size=(24, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    if where == "far":
        points = (directions * 1e7).astype(np.float32)
    else:
        verts = verts * np.float32(1e30)
        points = (directions * 3e30).astype(np.float32)
    bvh = hlbvh_warp.build(verts, faces=faces, device=device)
    closest, distance, prim, stats = hlbvh_warp.closest_point(bvh, points, stats=True)
    check_answers(verts, faces, points, closest, distance, prim)
    assert (prim >= 0).all()
    # A near search of this sphere visits tens of nodes; every node is 2N - 1 = 2559.
    assert stats.nodes_visited.mean() < 0.2 * bvh.num_nodes, stats.nodes_visited.mean()
    assert stats.prims_tested.mean() < 0.1 * len(faces), stats.prims_tested.mean()


def _ball_and_box():
    """An icosphere and a box beside it (1,292 triangles): curved and flat parts, boxes of every
    size. ``(vertices, faces, centre, size)``, size the largest extent of the bounding box."""
    mesh = trimesh.util.concatenate([trimesh.creation.icosphere(subdivisions=3),
                                     trimesh.creation.box(extents=(0.5, 0.5, 0.5)).apply_translation((2, 0, 0))])
    verts, faces = np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)
    lo, hi = verts.astype(np.float64).min(0), verts.astype(np.float64).max(0)
    return verts, faces, 0.5 * (lo + hi), float((hi - lo).max())


def _far_directions(rng, n=16):
    """Unit directions: ``n`` random ones, the six axes and the eight diagonals (a point on an axis
    lies in the slabs of most boxes, where only one coordinate's gap counts)."""
    diagonals = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
    dirs = np.concatenate([rng.normal(size=(n, 3)), np.eye(3), -np.eye(3), diagonals])
    return dirs / np.linalg.norm(dirs, axis=1, keepdims=True)


def _far_node_counts(bvh, center, size, dirs, distances):
    """Mean nodes visited per point by the points ``distance * size`` from ``center`` along
    ``dirs``, for each distance; every point must find a triangle."""
    nodes = {}
    for distance in distances:
        points = (center + distance * size * dirs).astype(np.float32)
        _, _, prim, stats = hlbvh_warp.closest_point(bvh, points, stats=True)
        assert (prim >= 0).all()
        nodes[distance] = stats.nodes_visited.mean()
    return nodes


@pytest.mark.parametrize("method", ["hlbvh", "sweep_sah", "sbvh"])
def test_far_points_visit_as_many_nodes_as_points_a_thousand_sizes_away(device, rng, method):
    """From afar the search stays as selective as from 1e3 mesh sizes: the same directions at 1e5,
    1e7 and 1e9 sizes visit at most 10% more nodes on average. Where float32 cannot tell the
    boxes' squared distances apart, the float32 walk ordered children by rounding noise and
    entered every deferred node it popped: 1.75 times the nodes at 1e7, 2.6 at 1e9 on this
    scene (`hlbvh`), 3.2 at 1e7 on the bunny. Past 256 extents the walk is in float64
    (`proximity.packed_far_point_query`)."""
    verts, faces, center, size = _ball_and_box()
    bvh = hlbvh_warp.build(verts, faces=faces, method=method, device=device)
    nodes = _far_node_counts(bvh, center, size, _far_directions(rng), (1e3, 1e5, 1e7, 1e9))
    for distance in (1e5, 1e7, 1e9):
        assert nodes[distance] <= 1.1 * nodes[1e3], nodes


def _check_far_answers(verts, faces, points, closest, distance, prim):
    """Exactness far from the mesh, beyond `check_answers` (whose tolerance, 1e-6 of the point's
    coordinates, is ten mesh sizes at 1e7): the triangle returned is a nearest one to 1e-12 of
    the scale, and the distance is the float64 one rounded to float32 (one float32 ulp).

    Why 1e-12: the kernel takes the float32 coordinates as exact and decides in float64, within a
    few 1e-16 of the scale (the largest coordinate of the point and the triangles); the oracle's
    Gram equations are as accurate here, where the point lies far from every triangle. Four
    orders of margin, and still far below the 0.18 mesh diagonals (median) by which a search
    deciding in float32 misses the nearest triangle at 1e7 (measured with wp.Mesh on the bunny)."""
    d_ref, prim_ref, _ = oracle_closest(verts, faces, points)
    assert (prim >= 0).all() and (prim_ref >= 0).all()
    pts = points.astype(np.float64)
    scale = np.maximum(np.abs(pts).max(axis=1), np.abs(verts.astype(np.float64)).max())
    own = oracle_distance_to(verts, faces, pts, prim)
    excess = (own - d_ref) / scale
    assert (np.abs(excess) <= 1e-12).all(), f"a triangle {excess.max():.3g} of the scale farther than the nearest"
    ulp = np.spacing(d_ref.astype(np.float32)).astype(np.float64)
    assert (np.abs(distance.astype(np.float64) - d_ref) <= ulp).all(), "distance off by more than a float32 ulp"
    assert np.array_equal(prim, lowest_duplicate(verts, faces)[prim])
    return d_ref


@pytest.mark.parametrize("method", ["hlbvh", "sweep_sah", "sbvh"])
def test_far_points_are_exact(device, rng, method):
    """Points on the surface, near it, at 200 and 300 mesh sizes (either side of where the float64
    walk takes over) and at 1e3, 1e5 and 1e7, along the axes, the diagonals and at random: the
    oracle's distance and a nearest triangle, `_check_far_answers`' tolerance where far; the
    float32 walk over the canonical arrays (which has no far walk) gives the same answers bit for
    bit; and a ``max_dist`` just below a far point's distance finds nothing, just above it the
    unbounded answer."""
    verts, faces, center, size = _ball_and_box()
    bvh = hlbvh_warp.build(verts, faces=faces, method=method, device=device)
    dirs = _far_directions(rng)
    near = all_points(query_points(rng, verts, faces, n=20))
    far = {distance: (center + distance * size * dirs).astype(np.float32)
           for distance in (200.0, 300.0, 1e3, 1e5, 1e7)}
    points = np.concatenate([near, *far.values()])
    out = hlbvh_warp.closest_point(bvh, points, return_barycentrics=True)
    check_answers(verts, faces, points, *out)
    canonical = run_user_kernel(canonical_view(bvh), points, np.inf, device)
    for x, y in zip(canonical[:5], out):
        assert np.array_equal(x, y, equal_nan=True)
    start = len(near)
    for distance, pts in far.items():
        rows = slice(start, start + len(pts))
        start += len(pts)
        closest, dist, prim = (x[rows] for x in out[:3])
        d_ref = _check_far_answers(verts, faces, pts, closest, dist, prim)
        # Bounds 1e-6 below and above the distance, 16 float32 ulps and more: decided either way.
        below = hlbvh_warp.closest_point(bvh, pts, max_dist=d_ref * (1.0 - 1e-6))
        assert (below[2] == -1).all() and np.isposinf(below[1]).all(), distance
        above = hlbvh_warp.closest_point(bvh, pts, max_dist=d_ref * (1.0 + 1e-6))
        for x, y in zip(above, (closest, dist, prim)):
            assert np.array_equal(x, y), distance


# ------------------------------------------------- the far walk's margin, 1e3 to 1e14 sizes away
FAR_SIZES = (1e3, 1e6, 1e9, 1e11, 1e12, 1e13, 1e14)


@wp.kernel
def _float64_brute_force_kernel(points: wp.array(dtype=wp.vec3), a: wp.array(dtype=wp.vec3),
                                b: wp.array(dtype=wp.vec3), c: wp.array(dtype=wp.vec3),
                                out_prim: wp.array(dtype=wp.int32), out_d2: wp.array(dtype=wp.float64)):
    tid = wp.tid()
    best = wp.float64(wp.inf)
    prim = int(-1)
    for k in range(a.shape[0]):
        d2 = proximity.closest_point_on_triangle(points[tid], a[k], b[k], c[k]).d2
        if d2 < best:  # strictly: the first, lowest id, of equal distances stays
            best = d2
            prim = k
    out_prim[tid] = prim
    out_d2[tid] = best


def _float64_brute_force(verts, faces, points):
    """Every triangle measured, nothing pruned: the lowest id among the nearest in the float64
    distance the kernel computes per triangle. The oracle of the walk's pruning alone: its margin
    must never skip a box holding such a triangle, whatever the rounding of the distances."""
    tri = np.asarray(verts, np.float32)[np.asarray(faces)]
    prim, d2 = wp.zeros(len(points), dtype=wp.int32), wp.zeros(len(points), dtype=wp.float64)
    wp.launch(_float64_brute_force_kernel, dim=len(points),
              inputs=[wp.array(np.asarray(points, np.float32), dtype=wp.vec3),
                      *(wp.array(np.ascontiguousarray(tri[:, j]), dtype=wp.vec3) for j in range(3)), prim, d2])
    return prim.numpy(), d2.numpy()


def _mirror_tie_mesh(pair_first):
    """A tilted icosphere (80 triangles) and, above it in +y, a pair of triangles that are each
    other's mirror images in the plane x = 0, vertex for vertex. A point with x = 0 above them is
    at exactly the same distance from both, in rational arithmetic and in float64 (the kernel
    applies the same operations to coordinates equal up to sign, and rounding commutes with
    negation): the lower id of the two must win, whichever side of the tree holds it. The pair
    comes first or last among the faces. ``(vertices, faces, pair ids)``."""
    ball = trimesh.creation.icosphere(subdivisions=1)
    ball.apply_transform(trimesh.transformations.rotation_matrix(0.3, [1.0, 2.0, 3.0]))
    ball.apply_translation((0.1, 0.0, 0.2))
    half = np.array([[0.25, 2.0, 0.0], [1.0, 1.5, 0.5], [1.0, 1.5, -0.5]])
    pair_verts = np.concatenate([half, half * [-1.0, 1.0, 1.0]])
    ball_faces = np.asarray(ball.faces)
    if pair_first:
        verts = np.concatenate([pair_verts, ball.vertices])
        faces = np.concatenate([[[0, 1, 2], [3, 4, 5]], ball_faces + 6])
        pair = (0, 1)
    else:
        verts = np.concatenate([ball.vertices, pair_verts])
        n = len(ball.vertices)
        faces = np.concatenate([ball_faces, [[n, n + 1, n + 2], [n + 3, n + 4, n + 5]]])
        pair = (len(ball_faces), len(ball_faces) + 1)
    return verts.astype(np.float32), faces.astype(np.int32), pair


def _far_points(center, size, dirs):
    """``dirs`` at each of FAR_SIZES mesh sizes from ``center``, float32, distance-major."""
    return np.concatenate([(center + d * size * dirs).astype(np.float32) for d in FAR_SIZES])


@pytest.mark.parametrize("pair_first", [True, False])
@pytest.mark.parametrize("method", ["hlbvh", "sweep_sah", "sbvh"])
def test_far_walk_against_rational_brute_force_with_exact_ties(device, rng, method, pair_first):
    """From 1e3 to 1e14 sizes (the float64 walk, `proximity.packed_far_point_query`), every
    triangle's squared distance in rational arithmetic (`_exact_point_triangle_d2`): the answer is
    at the minimum up to the float64 rounding the walk allows (64 units of it, relative), on its
    triangle, at the exact distance to a float32 ulp; where the minimum is apart from the next
    distance by more than that, it is a triangle at the minimum; above the mirror pair it is the
    lower id of the two; and it is the unpruned float64 brute force's triangle, bit for bit."""
    from fractions import Fraction

    verts, faces, pair = _mirror_tie_mesh(pair_first)
    bvh = hlbvh_warp.build(verts, faces=faces, method=method, device=device)
    lo, hi = verts.astype(np.float64).min(0), verts.astype(np.float64).max(0)
    size = float((hi - lo).max())
    tie_dirs = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.3], [0.0, 1.0, -0.2], [0.0, 2.0, 1.0]])
    tie_dirs /= np.linalg.norm(tie_dirs, axis=1, keepdims=True)
    dirs = np.concatenate([tie_dirs, _far_directions(rng, 4)])
    # Points from the origin, so that x = 0 stays exactly 0 on the tie directions.
    points = _far_points(np.zeros(3), size, dirs)
    closest, distance, prim = hlbvh_warp.closest_point(bvh, points)
    tol = Fraction(2 * 64 * 2**-53)
    tri = verts[faces]
    for i, p in enumerate(points):
        exact = [_exact_point_triangle_d2(p, *t) for t in tri]
        best = min(exact)
        assert exact[prim[i]] <= best * (1 + tol), (i, float(exact[prim[i]] / best - 1))
        apart = [k for k, e in enumerate(exact) if e <= best * (1 + tol)]
        if all(e == best for e in (exact[k] for k in apart)):
            assert exact[prim[i]] == best, i
        ulp = float(np.spacing(np.float32(float(best) ** 0.5)))
        assert abs(float(distance[i]) - float(best) ** 0.5) <= ulp, i
        if i % len(dirs) < len(tie_dirs):
            assert prim[i] == pair[0], (i, prim[i], pair)
    # The point is on the answer's triangle (to float32's rounding of it).
    on_triangle = oracle_distance_to(verts, faces, closest.astype(np.float64), prim)
    assert (on_triangle <= 1e-6 * np.abs(verts).max()).all()
    brute, _ = _float64_brute_force(verts, faces, points)
    assert np.array_equal(prim, brute)


@pytest.mark.parametrize("method", ["hlbvh", "sweep_sah"])
def test_far_walk_on_the_bunny_against_brute_force(device, rng, method):
    """The bunny at 1e3 to 1e14 sizes: the unpruned float64 brute force's triangle bit for bit
    (the walk's margin never skips a box that holds it), a nearest triangle and the distance of
    the NumPy oracle (`_check_far_answers`), and the distance within a float32 ulp of the answer's
    exact one (rational arithmetic)."""
    mesh = shared_mesh("bunny")
    verts, faces = np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)
    bvh = hlbvh_warp.build(verts, faces=faces, method=method, device=device)
    lo, hi = verts.astype(np.float64).min(0), verts.astype(np.float64).max(0)
    points = _far_points(0.5 * (lo + hi), float((hi - lo).max()), _far_directions(rng, 4))
    closest, distance, prim = hlbvh_warp.closest_point(bvh, points)
    brute, _ = _float64_brute_force(verts, faces, points)
    assert np.array_equal(prim, brute)
    _check_far_answers(verts, faces, points, closest, distance, prim)
    for i in range(len(points)):
        exact = float(_exact_point_triangle_d2(points[i], *verts[faces[prim[i]]])) ** 0.5
        assert abs(float(distance[i]) - exact) <= float(np.spacing(np.float32(exact))), i


def test_far_walk_stays_selective_to_1e13_sizes(device, rng):
    """Nodes per point stay near those of 1e3 sizes up to 1e13 (1.01, 1.12 and 2.2 times at
    1e11, 1e12 and 1e13 on the ball and box, every builder; 1.75 at 1e12 on the bunny). The far
    walk's margin was a relative 1e-12, which entered every box within that fraction of the best
    triangle's squared distance, while boxes differ by about 2 S / d at d from a mesh of size S:
    2.6, 20 and 27 times (the whole tree) on the ball and box (`hlbvh`), about 260 at 1e12 on
    the bunny."""
    verts, faces, center, size = _ball_and_box()
    dirs = _far_directions(rng)
    for method in ("hlbvh", "sweep_sah", "sbvh"):
        bvh = hlbvh_warp.build(verts, faces=faces, method=method, device=device)
        nodes = _far_node_counts(bvh, center, size, dirs, (1e3, 1e11, 1e12, 1e13))
        assert nodes[1e11] <= 1.1 * nodes[1e3] and nodes[1e12] <= 1.5 * nodes[1e3], (method, nodes)
        assert nodes[1e13] <= 4.0 * nodes[1e3], (method, nodes)
    mesh = shared_mesh("bunny")
    verts, faces = np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)
    bvh = hlbvh_warp.build(verts, faces=faces, device=device)
    lo, hi = verts.astype(np.float64).min(0), verts.astype(np.float64).max(0)
    nodes = _far_node_counts(bvh, 0.5 * (lo + hi), float((hi - lo).max()), dirs, (1e3, 1e12))
    assert nodes[1e12] <= 2.5 * nodes[1e3], nodes


@pytest.mark.parametrize("height", [1e7, 1e30, 3.0e38])
def test_a_point_far_above_a_face_gets_a_point_on_the_triangle(device, height):
    """The face's closest point is the projection p - n (n . ap) / |n|^2, which subtracts two
    nearly equal vectors when p lies far above the plane: at 3e38 its rounding put the returned
    point 6.5e22 off the triangle (a face whose normal points at p, as on an icosphere). Far off
    the plane the point comes from the weights instead, clamped onto the triangle."""
    tri = np.float32([[1, 0, 0], [0, 1, 0], [0, 0, 1]])
    bvh = hlbvh_warp.build(tri, faces=np.int32([[0, 1, 2]]), device=device)
    point = np.full((1, 3), height, np.float32)
    closest, distance, prim, u, v = hlbvh_warp.closest_point(bvh, point, return_barycentrics=True)
    assert prim.tolist() == [0]
    q = closest[0].astype(np.float64)
    # On the triangle: in its plane x + y + z = 1, with weights in [0, 1] that give the point.
    assert abs(q.sum() - 1.0) < 1e-6 and (q >= -1e-7).all(), q
    assert u[0] >= 0 and v[0] >= 0 and u[0] + v[0] <= 1 + 1e-7
    assert np.allclose(q, [1.0 - u[0] - v[0], u[0], v[0]], atol=1e-6)
    if height < 1e10:
        # The float32 point lies exactly on the normal through the face's centre, its foot. Far
        # beyond, every point of the triangle is as near in float64, and any is a right answer.
        assert np.allclose(q, 1.0 / 3.0, atol=1e-6), q
    with np.errstate(over="ignore"):  # inf past float32's range, as the query reports it
        expected = np.float32(np.sqrt(3.0) * (float(point[0, 0]) - 1.0 / 3.0))
    assert distance[0] == expected or np.isclose(distance[0], expected, rtol=1e-6)


# ------------------------------------------------- the far walk's margin under adversarial soups
def _adversarial_triangle(rng, kind):
    """One triangle of unit size, of a shape that stresses `closest_point_on_triangle`'s rounding:
    a sliver (the third vertex within 1e-9..1e-3 of the line through the others), a triangle whose
    angle sits near NORMAL_RECHECK's threshold (sin 1e-6..1e-5, the float64 normal kept with its
    largest tilt), a needle, a degenerate one (collinear, a segment, a point), or a random one."""
    a = rng.normal(size=3)
    b = a + rng.normal(size=3)
    if kind == "sliver":
        c = a + rng.uniform(-0.5, 1.5) * (b - a) + rng.normal(size=3) * 10.0 ** rng.uniform(-9, -3)
    elif kind == "threshold":
        side = np.cross(b - a, rng.normal(size=3))
        side *= np.linalg.norm(b - a) / np.linalg.norm(side)
        c = a + rng.uniform(0.3, 0.9) * (b - a) + side * 10.0 ** rng.uniform(-6, -5)
    elif kind == "needle":
        c = b + rng.normal(size=3) * 10.0 ** rng.uniform(-8, -3)
    elif kind == "collinear":
        c = a + rng.uniform(-1.0, 2.0) * (b - a)
    elif kind == "segment":
        a, b, c = a, a, b
    elif kind == "point":
        b, c = a, a
    else:
        c = rng.normal(size=3)
    return np.stack([a, b, c])


_FAR_KINDS = ("sliver", "threshold", "needle", "collinear", "segment", "point", "random")


@settings(max_examples=120, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    seed=st.integers(0, 2**32 - 1),
    kinds=st.lists(st.sampled_from(_FAR_KINDS), min_size=1, max_size=16),
    scale_exp=st.integers(-15, 15),
    offset_exp=st.sampled_from([None, 0, 3, 6, 8]),
    far_exp=st.one_of(st.floats(2.7, 20.0), st.floats(14.0, 20.0)),
    copies=st.sampled_from(["none", "same", "rotated", "mirrored"]),
    method=st.sampled_from(["hlbvh", "lbvh", "hlbvh_sah", "sweep_sah", "binned_sah", "median", "recursive_sah",
                            "sbvh"]),
)
def test_far_walk_margin_on_adversarial_soups(device, seed, kinds, scale_exp, offset_exp, far_exp, copies, method):
    """Slivers, needles, triangles at NORMAL_RECHECK's threshold and degenerate ones, of size 1e-15
    to 1e15, up to 1e8 of their size from the origin (M >> L, where the coordinates' rounding
    dominates the distance's), with duplicates (the same vertices, rotated, or a mirror image:
    exact ties in float64), seen from 10^2.7 sizes (past the far walk's 256 extents on every axis)
    to 1e20, along axes, diagonals and at random, every builder. The far walk's margin (FAR_LOW and
    `far_slack`) must never skip a box that holds the unpruned float64 brute force's triangle
    (`_float64_brute_force`: its minimum computed distance, the lowest id among equal ones); a
    max_dist a float32 ulp above that distance finds the same triangle and two below finds none;
    and in rational arithmetic the answer is a nearest triangle up to the rounding the margin
    allows (64 units relative plus `far_slack`, twice over). Fails with FAR_LOW at 1 (no relative
    margin: near-ties past 1e14 sizes) or at 1 + 1e-12; `far_slack` never binds on these soups."""
    rng = np.random.default_rng(seed)
    scale = 10.0**scale_exp
    tris = np.stack([_adversarial_triangle(rng, kind) for kind in kinds])
    if copies != "none":
        k = int(rng.integers(len(tris)))
        twin = tris[k][[1, 2, 0]] if copies == "rotated" else tris[k].copy()
        if copies == "mirrored":
            twin[:, 0] = -twin[:, 0]
        tris = np.concatenate([tris, twin[None]])
    tris = tris[rng.permutation(len(tris))] * scale
    if offset_exp is not None:
        direction = rng.normal(size=3)
        tris = tris + direction / np.linalg.norm(direction) * scale * 10.0**offset_exp
    verts = tris.reshape(-1, 3).astype(np.float32)
    faces = np.arange(len(verts), dtype=np.int32).reshape(-1, 3)
    bvh = hlbvh_warp.build(verts, faces=faces, method=method, device=device)
    lo, hi = verts.astype(np.float64).min(0), verts.astype(np.float64).max(0)
    # Far from the origin float32 may collapse the soup to a point: sizes are then its ulps.
    size = max(float((hi - lo).max()), 4.0 * float(np.spacing(np.abs(verts).max())), 1e-30)
    dirs = _far_directions(rng, 4)
    if copies == "mirrored":
        # On the mirror plane x = 0 both twins are exactly as far in float64: a tie for the lowest id.
        dirs = np.concatenate([dirs, [[0.0, 0.6, 0.8], [0.0, -1.0, 0.0]]])
    center = 0.5 * (lo + hi)
    if copies == "mirrored" and offset_exp is None:
        center[0] = 0.0
    points = np.clip(center + 10.0**far_exp * size * dirs, -3.3e38, 3.3e38).astype(np.float32)
    assert traversal_is_far(points, lo, hi).all()
    _, distance, prim = hlbvh_warp.closest_point(bvh, points)
    brute, d2 = _float64_brute_force(verts, faces, points)
    assert np.array_equal(prim, brute), (np.nonzero(prim != brute)[0], prim, brute)
    bound = np.sqrt(d2).astype(np.float32)
    finite = np.isfinite(bound) & (bound > 0)
    if finite.any():
        up, down = np.nextafter(bound, np.float32(np.inf)), np.nextafter(np.nextafter(bound, 0), 0)
        assert np.array_equal(hlbvh_warp.closest_point(bvh, points[finite], max_dist=up[finite])[2], brute[finite])
        assert (hlbvh_warp.closest_point(bvh, points[finite], max_dist=down[finite])[2] == -1).all()
    from fractions import Fraction

    u = 2.0**-53
    tri = verts[faces]
    diagonal = float(np.linalg.norm(hi - lo))
    tau = 2e-9 * diagonal + 8 * u * (np.sqrt(3.0) * np.abs(verts.astype(np.float64)).max() + diagonal)
    for i, p in enumerate(points):
        exact = [_exact_point_triangle_d2(p, *t) for t in tri]
        best = min(exact)
        reach = float(best) ** 0.5 + diagonal
        allowed = best * Fraction(2 * 64 * u) + Fraction(2 * 4 * reach * tau)
        assert exact[prim[i]] - best <= allowed, (i, float(exact[prim[i]] - best), float(allowed))


def traversal_is_far(points, lo, hi):
    """The points the far walk takes (`proximity.point_is_far`, in NumPy): farther outside the box
    than FAR_POINT times its largest extent."""
    p = points.astype(np.float64)
    gap = np.maximum(lo - p, p - hi).max(axis=1)
    return gap > 256.0 * (hi - lo).max()


# ------------------------------------------- the near walk's slack: distances measured short
#: A triangle of size 1 sloping down (1e-3) away from its top edge, which lies near the origin
#: (id 1), and a small level triangle just above that edge (id 0); the point is 1e-16 above the
#: sloping face, a few 1e-15 inside the edge. The far vertex makes p - a and the normal's terms
#: round by about 1e-16 of 1, a third of the point's distance: the computed squared distance of
#: triangle 1 is 8.2e-33 for an exact 2.5e-32, below its own box distance, 1.0e-32, and below
#: triangle 0's, 9.1e-33 (exact in float64: its plane is level).
SHORT_TRIANGLES = np.array([[-0.000127545, -6.955804e-05, 4.7928995e-18],
                            [-0.00012554502, -6.955804e-05, 4.7928995e-18],
                            [-0.00012654501, -6.755804e-05, 4.7928995e-18],
                            [-0.076035984, -0.99710506, -0.0031956849],
                            [3.9988125e-05, 2.6030966e-05, 0.0],
                            [-0.00029307368, -0.0001631445, 0.0]], np.float32)
SHORT_POINT = np.array([[-0.00012654501, -6.855804e-05, 1e-16]], np.float32)


@pytest.mark.parametrize("max_leaf_size", [1, 2])
def test_near_walk_keeps_boxes_beyond_a_triangle_measured_short(device, max_leaf_size):
    """The float64 brute force's answer, whatever the tree. Triangle 1's computed distance lies
    below its box's by 18% (the error of `closest_point_on_triangle` is absolute, about d tau: see
    EXACT_LOW): the walk, with a relative margin alone, found triangle 0 first and pruned the
    box of triangle 1, so trees with one triangle per leaf answered 0 and those with both in one
    leaf 1. `near_bound`'s slack enters that box."""
    faces = np.array([[0, 1, 2], [3, 4, 5]], np.int32)
    tri = SHORT_TRIANGLES[faces]
    # The premise, in rational arithmetic: triangle 1 is measured below its box distance, and
    # its computed distance is the least.
    brute, d2 = _float64_brute_force(SHORT_TRIANGLES, faces, SHORT_POINT)
    assert brute.tolist() == [1]
    from fractions import Fraction

    p = [Fraction(float(x)) for x in SHORT_POINT[0]]
    lo, hi = tri[1].min(0), tri[1].max(0)
    box = sum(max(Fraction(float(lo[i])) - p[i], p[i] - Fraction(float(hi[i])), Fraction(0)) ** 2 for i in range(3))
    assert Fraction(float(d2[0])) < box / Fraction(1.1)
    exact = [_exact_point_triangle_d2(SHORT_POINT[0], *t) for t in tri]
    assert exact[1] > box > exact[0]  # triangle 0 is the nearer one in exact terms
    config = BuildConfig(max_leaf_size=max_leaf_size)
    for method in METHODS:
        bvh = hlbvh_warp.build(SHORT_TRIANGLES, faces=faces, method=method, device=device, config=config)
        assert hlbvh_warp.closest_point(bvh, SHORT_POINT)[2].tolist() == [1], method
        assert run_user_kernel(canonical_view(bvh), SHORT_POINT, np.inf, device)[2].tolist() == [1], method
    mesh = trimesh.Trimesh(SHORT_TRIANGLES.astype(np.float64), faces, process=False)
    assert hlbvh_warp.ProximityQuery(mesh, device=device).on_surface(SHORT_POINT)[2].tolist() == [1]


def _just_inside(tri, reach=200):
    """The float32 (x, y) nearest to the top edge tri[1] tri[2] of a triangle's xy shadow on its
    inner side, among the float32 grid around the edge's midpoint (reach steps each way): the
    distance from the edge is linear in the grid steps, so each x step gets its best y step."""
    b, c = tri[1], tri[2]
    bc = c - b
    length = float(np.hypot(bc[0], bc[1]))
    side = np.sign((tri[0, 0] - b[0]) * bc[1] - (tri[0, 1] - b[1]) * bc[0])
    mid = (0.5 * (b + c)).astype(np.float32)
    step = np.spacing(np.abs(mid[:2]))
    i = np.arange(-reach, reach + 1)
    x = mid[0] + i * step[0]

    def offset(x, y):
        return side * ((x - b[0]) * bc[1] - (y - b[1]) * bc[0]) / length

    per_y = offset(0.0, step[1]) - offset(0.0, 0.0)
    j = np.ceil(-offset(x, mid[1]) / per_y) if per_y > 0 else np.floor(-offset(x, mid[1]) / per_y)
    y = mid[1] + j * step[1]
    s = offset(x, y)
    k = int(np.argmin(np.where(s > 0, s, np.inf)))
    return np.float32(x[k]), np.float32(y[k])


@settings(max_examples=30, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1), slope=st.floats(-4.0, -1.0), edge=st.floats(-5.0, -2.0),
       height=st.floats(-18.0, -13.0), method=st.sampled_from(["hlbvh", "sweep_sah", "median"]))
def test_near_walk_matches_the_brute_force_on_slivers_measured_short(device, seed, slope, edge, height, method):
    """Triangles like `SHORT_TRIANGLES`' (size 1, slope 10^slope, the top edge 10^edge long at the
    origin), each with a level sliver just above its top edge, and points 10^height above the
    face just inside that edge, at the float32 points nearest to it: the walk (one triangle per
    leaf, so that every box is a chance to prune) answers the float64 brute force's triangle.
    (About one point in thirty has the distance of its sloping triangle measured below the level
    sliver's and its own box's, the case `near_bound` covers.)"""
    rng = np.random.default_rng(seed)
    rows, points = [], []
    for _ in range(6):
        size = 10.0**edge
        b, c = size * rng.normal(size=3), size * rng.normal(size=3)
        b[2] = c[2] = 0.0
        far = rng.normal(size=3)
        far *= 1.0 / np.linalg.norm(far[:2])
        side = np.cross(c - b, [0.0, 0.0, 1.0])
        far[2] = -(10.0**slope) * abs(np.dot(far - b, side / np.linalg.norm(side)))
        top = np.float32([far, b, c]).astype(np.float64)
        p = np.float32([*_just_inside(top), 10.0**height])
        gap = np.float32(10.0**height * rng.uniform(0.05, 0.95))
        h = np.float32(1e-3 * size)
        level = np.float32([[p[0] - h, p[1] - h, gap], [p[0] + h, p[1] - h, gap], [p[0], p[1] + h, gap]])
        rows += [level, top]
        points.append(p)
    verts = np.concatenate(rows).astype(np.float32)
    faces = np.arange(len(verts), dtype=np.int32).reshape(-1, 3)
    points = np.array(points, np.float32)
    bvh = hlbvh_warp.build(verts, faces=faces, method=method, device=device)
    brute, _ = _float64_brute_force(verts, faces, points)
    assert np.array_equal(hlbvh_warp.closest_point(bvh, points)[2], brute)
