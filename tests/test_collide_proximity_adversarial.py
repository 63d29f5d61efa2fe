"""Adversarial cases for the closest-point queries (``kernels/proximity.py``) and the triangle
pair tests (``kernels/collide.py``), each checked against exact rational arithmetic on the float32
inputs (`fractions.Fraction`), never against numbers the code printed."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
import warp as wp

import hlbvh_warp
from hlbvh_warp.kernels import collide

from oracles import exact_distance_sq

#: Integer normals whose length is an integer (Pythagorean quadruples): a point k normals off a
#: plane through integer points lies at exactly k times that length, a float32 number.
PYTHAGOREAN_NORMALS = (((1, 2, 2), 3), ((2, 3, 6), 7), ((1, 4, 8), 9), ((4, 4, 7), 9), ((2, 6, 9), 11),
                       ((6, 6, 7), 11), ((3, 4, 12), 13), ((2, 10, 11), 15))




def tilted_triangles_at_exact_distances(rng, n):
    """``n`` (triangle, point, distance): integer triangles in tilted planes whose normal has an
    integer length, and points straight above the face, a vertex or an edge midpoint at an exact
    float32 distance. The float64 distance computed for such a point rounds up past it about one
    time in thirty."""
    out = []
    while len(out) < n:
        normal, length = PYTHAGOREAN_NORMALS[rng.integers(len(PYTHAGOREAN_NORMALS))]
        normal = (np.array(normal, np.int64) * rng.choice([-1, 1], 3))[rng.permutation(3)]
        e1 = np.cross(normal, rng.integers(-3, 4, 3))
        if not e1.any():
            continue
        e2 = np.cross(normal, e1)
        foot = rng.integers(-64, 64, 3)
        tri = np.array([foot - e1 - e2, foot + 2 * e1 - e2, foot - e1 + 2 * e2])
        where = rng.integers(3)  # above the face, a vertex or an edge midpoint (an integer point)
        if where == 2 and ((tri[0] + tri[1]) % 2).any():
            continue
        base = (foot, tri[0], (tri[0] + tri[1]) // 2)[where]
        k = int(rng.integers(1, 6))
        point = base + k * normal
        if max(np.abs(tri).max(), np.abs(point).max()) >= 2**24:
            continue
        out.append((tri.astype(np.float32), point.astype(np.float32), float(k * length)))
    return out


def test_a_triangle_at_exactly_max_dist_counts_in_tilted_planes(device):
    """max_dist is inclusive: a triangle whose exact distance equals it is found, also where the
    float64 distance computed for it rounds above the bound (it rounded 57600 + 7e-12 for an exact
    240^2, and the triangle was dropped); one float32 step below the bound it is not."""
    rng = np.random.default_rng(11)
    cases = tilted_triangles_at_exact_distances(rng, 240)
    faces = np.array([[0, 1, 2]], np.int32)
    missed, wrongly_found = [], []
    for tri, point, dist in cases:
        assert exact_distance_sq(point, *tri) == Fraction(dist) ** 2  # the oracle's word, not the construction's
        bvh = hlbvh_warp.build(tri, faces=faces, device=device)
        _, distance, prim = hlbvh_warp.closest_point(bvh, point, max_dist=dist)
        if prim[0] != 0 or distance[0] != np.float32(dist):
            missed.append((tri.tolist(), point.tolist(), dist))
        below = float(np.nextafter(np.float32(dist), np.float32(0)))
        if hlbvh_warp.closest_point(bvh, point, max_dist=below)[2][0] != -1:
            wrongly_found.append((tri.tolist(), point.tolist(), dist))
    assert not missed, f"{len(missed)} of {len(cases)} triangles at exactly max_dist missed, first {missed[0]}"
    assert not wrongly_found, f"{len(wrongly_found)} found one float32 step inside, first {wrongly_found[0]}"


def edge_region_points(rng, vertices, faces, n):
    """``n`` float32 points off a convex mesh near its edges: an edge point pushed out along the
    mean of its ends (a point in the edge's Voronoi region, at exactly equal distances from the
    two triangles sharing the edge), some at an end (a vertex's region)."""
    v = np.asarray(vertices, np.float64)
    tri = v[faces[rng.integers(len(faces), size=n)]]
    k = rng.integers(3, size=n)
    a, b = tri[np.arange(n), k], tri[np.arange(n), (k + 1) % 3]
    w = rng.choice([0.0, 0.25, 0.5, 0.75], n)[:, None]
    out = (a + b) / np.linalg.norm(a + b, axis=1, keepdims=True)
    return (a + w * (b - a) + rng.choice([0.0, 0.1, 0.3, 0.6], n)[:, None] * out).astype(np.float32)


def exact_ties(vertices, faces, points, gap=1e-9):
    """For each point whose nearest triangles are tied exactly (rational distances equal) while
    every other triangle lies farther by more than ``gap`` relative (beyond float64's resolution,
    where the computed distances cannot swap the order): ``(point index, lowest tied id)``."""
    tri = np.asarray(vertices, np.float32)[faces]
    lo, hi = tri.min(axis=1).astype(np.float64), tri.max(axis=1).astype(np.float64)
    out = []
    for i, p in enumerate(np.asarray(points, np.float32)):
        # The nearest triangle is no farther than the nearest vertex, and none is nearer than its
        # box: the others need no rational work.
        q = p.astype(np.float64)
        reach = np.linalg.norm(tri.astype(np.float64) - q, axis=2).min()
        box = np.linalg.norm(np.maximum(np.maximum(lo - q, q - hi), 0.0), axis=1)
        exact = {int(j): exact_distance_sq(p, *tri[j]) for j in np.nonzero(box <= reach * (1 + 1e-9))[0]}
        best = min(exact.values())
        tied = sorted(j for j, x in exact.items() if x == best)
        if len(tied) >= 2 and all(x > best * Fraction(1 + gap) for x in exact.values() if x != best):
            out.append((i, tied[0]))
    return out


def test_a_point_nearest_a_shared_edge_goes_to_the_lower_id(device):
    """A point in a shared edge's region is at exactly equal distances from the two triangles:
    the lower id must win, whatever order each triangle lists the edge in. The edge was measured
    from its first end in each triangle (ab from a, bc from b), so the two float64 distances
    differed in the last bits and the higher id won 18 of 380 such ties on an icosphere."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=2)
    verts, faces = np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)
    points = edge_region_points(np.random.default_rng(3), verts, faces, 500)
    ties = exact_ties(verts, faces, points)
    assert len(ties) > 300  # the generator is doing its job
    bvh = hlbvh_warp.build(verts, faces=faces, device=device)
    _, _, prim = hlbvh_warp.closest_point(bvh, points)
    wrong = [(points[i].tolist(), int(prim[i]), lowest) for i, lowest in ties if prim[i] != lowest]
    assert not wrong, f"{len(wrong)} of {len(ties)} exact ties went to a higher id, first {wrong[0]}"


def points_exactly_on_triangles(rng, n):
    """``n`` pairs of float32 triangles sharing an edge (listed in opposite directions, the first
    pair's ids 0 and 1, the next 2 and 3, ...), each with a float32 point lying exactly on the
    pair: the shared edge's midpoint, or (a + b + 2 c) / 4 inside the first triangle, kept only
    where those are float32 numbers (checked in rationals). The pairs lie 8 units apart, so each
    point's triangles at distance 0 are its own pair's. Returns ``(vertices, faces, points)``."""
    verts, faces, points = [], [], []
    while len(points) < n:
        a, b, c, d = (rng.uniform(-1, 1, (4, 3)) + [8.0 * len(points), 0, 0]).astype(np.float32)
        ex = [[Fraction(float(x)) for x in v] for v in (a, b, c)]
        if rng.integers(2):
            exact = [(ex[0][i] + ex[1][i]) / 2 for i in range(3)]
        else:
            exact = [(ex[0][i] + ex[1][i] + 2 * ex[2][i]) / 4 for i in range(3)]
        p = np.array([float(x) for x in exact], np.float32)
        if any(Fraction(float(p[i])) != exact[i] for i in range(3)):
            continue
        k = 4 * len(points)
        verts.append([a, b, c, d])
        faces += [[k, k + 1, k + 2], [k + 3, k + 1, k]]  # the edge ab, as ab and as ba
        points.append(p)
    return (np.array(verts, np.float32).reshape(-1, 3), np.array(faces, np.int32),
            np.array(points, np.float32))


def test_points_exactly_on_the_surface_are_at_distance_zero(device):
    """A point exactly on a triangle (a float32 point on a shared edge or inside a face, checked
    in rationals) is at distance 0: the point itself comes back, a max_dist of 0 finds it, and on
    an edge shared by two triangles the lower id wins the exact tie. The float64 projection left a
    residue of about 1e-17 that differed between the two triangles, so the higher id won a
    quarter of the edge points and max_dist = 0 found nothing for some."""
    verts, faces, points = points_exactly_on_triangles(np.random.default_rng(4), 200)
    on_both = np.array([exact_distance_sq(p, *verts[faces[2 * i + 1]]) == 0 for i, p in enumerate(points)])
    assert all(exact_distance_sq(p, *verts[faces[2 * i]]) == 0 for i, p in enumerate(points))
    assert on_both.sum() > 50 and (~on_both).sum() > 20  # edge points (a tie) and face points (inside one)
    lowest = 2 * np.arange(len(points))
    for flip in (False, True):
        # Both id orders: the tie goes to the lower id, not to one triangle's rounding.
        f = faces.reshape(-1, 2, 3)[:, ::-1].reshape(-1, 3) if flip else faces
        expected = np.where(on_both | (not flip), lowest, lowest + 1)
        bvh = hlbvh_warp.build(verts, faces=f, device=device)
        for max_dist in (np.inf, 0.0):
            closest, distance, prim = hlbvh_warp.closest_point(bvh, points, max_dist=max_dist)
            wrong = np.nonzero((prim != expected) | (distance != 0) | (closest != points).any(axis=1))[0]
            assert not len(wrong), (
                f"max_dist={max_dist}, flip={flip}: {len(wrong)} of {len(points)} points on the surface answered "
                f"wrongly, first {points[wrong[0]].tolist()}: prim {prim[wrong[0]]} (expected {expected[wrong[0]]}), "
                f"distance {distance[wrong[0]]}")


@wp.kernel
def _point_on_triangle_kernel(tri: wp.array2d(dtype=wp.vec3), points: wp.array(dtype=wp.vec3),
                              out: wp.array(dtype=wp.int32)):
    i = wp.tid()
    out[i] = collide.point_on_triangle(points[i], tri[i, 0], tri[i, 1], tri[i, 2])


def _nudged(x, rng):
    """Each coordinate moved by -1, 0 or +1 float32 ulp."""
    step = rng.integers(-1, 2, np.shape(x))
    x = np.asarray(x, np.float32)
    return np.where(step > 0, np.nextafter(x, np.float32(np.inf)),
                    np.where(step < 0, np.nextafter(x, np.float32(-np.inf)), x)).astype(np.float32)


def test_point_on_triangle_is_exact(device):
    """`collide.point_on_triangle` (the closest-point walks' test for distance exactly 0) against
    the rational distance: points exactly on faces, edges and vertices of tilted triangles and of
    zero-area ones (segments with a repeated or collinear vertex, points), and the same points
    moved by an ulp, at scales 2^-100 to 2^100."""
    rng = np.random.default_rng(8)
    verts, faces, points = points_exactly_on_triangles(rng, 60)
    tri, pts = [verts[faces[0::2]]], [points]
    # Zero-area triangles: (a, b, b), (a, b, m) with m the exact midpoint, (a, a, a); points on them.
    segs, on = [], []
    while len(segs) < 60:
        a, b = rng.uniform(-1, 1, (2, 3)).astype(np.float32)
        m = ((a.astype(np.float64) + b) / 2).astype(np.float32)
        if (m.astype(np.float64) * 2 != a.astype(np.float64) + b).any():
            continue
        kind = len(segs) % 3
        segs.append([a, b, b] if kind == 0 else [a, b, m] if kind == 1 else [a, a, a])
        on.append(m if kind < 2 else a)
    tri.append(np.array(segs, np.float32))
    pts.append(np.array(on, np.float32))
    tri = np.concatenate(tri)
    pts = np.concatenate(pts)
    tri = np.concatenate([tri, tri, tri[:, [2, 0, 1]]])
    pts = np.concatenate([pts, _nudged(pts, rng), pts])
    for scale in (2.0**-100, 1.0, 2.0**100):  # exact scalings: on stays on
        t, p = (tri * np.float32(scale)).astype(np.float32), (pts * np.float32(scale)).astype(np.float32)
        expected = np.array([exact_distance_sq(q, *x) == 0 for q, x in zip(p, t)])
        assert 0.1 < expected.mean() < 0.9
        out = wp.empty(len(p), dtype=wp.int32, device=device)
        wp.launch(_point_on_triangle_kernel, dim=len(p), device=device,
                  inputs=[wp.array(t, dtype=wp.vec3, device=device), wp.array(p, dtype=wp.vec3, device=device)],
                  outputs=[out])
        got = out.numpy() == 1
        bad = np.nonzero(got != expected)[0]
        assert not len(bad), f"scale {scale}: {len(bad)} wrong, first {t[bad[0]].tolist()}, {p[bad[0]].tolist()}"


def test_a_nan_triangle_is_named_by_triangle_and_vertex(device):
    """A NaN in triangle 1's third vertex is reported there, not as row 5 of the flattened vertices."""
    tri = np.zeros((3, 3, 3), np.float32) + np.eye(3, dtype=np.float32)
    bad = tri.copy()
    bad[1, 2, 0] = np.nan
    with pytest.raises(ValueError, match=r"tri_b has a NaN or Inf coordinate \(first at triangle 1, vertex 2: \[nan"):
        hlbvh_warp.triangles_intersect(tri, bad, device=device)
