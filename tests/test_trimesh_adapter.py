"""hlbvh_warp.trimesh_adapter.RayMeshIntersector against trimesh's own RayMeshIntersector."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from oracles import random_rays
from trimesh.ray import ray_triangle

from hlbvh_warp.trimesh_adapter import ProximityQuery, RayMeshIntersector


class _BoxTree:
    """The two calls trimesh makes on its r-tree, by brute force, when rtree is not installed."""

    def __init__(self, triangles):
        self.lo, self.hi = triangles.min(axis=1), triangles.max(axis=1)
        self.bounds = np.concatenate([self.lo.min(0), self.hi.max(0)])

    def intersection(self, box):
        box = np.asarray(box, dtype=np.float64)
        ok = (self.lo <= box[3:]).all(1) & (self.hi >= box[:3]).all(1)
        return np.nonzero(ok)[0].tolist()


@pytest.fixture
def reference(monkeypatch):
    """trimesh's intersector, with a brute-force stand-in for the optional rtree dependency."""
    try:
        import rtree  # noqa: F401
    except ImportError:
        monkeypatch.setattr(trimesh.Trimesh, "triangles_tree", property(lambda m: _BoxTree(m.triangles)))
    return ray_triangle.RayMeshIntersector


def _scene(rng):
    mesh = trimesh.creation.icosphere(subdivisions=2)
    mesh = trimesh.util.concatenate([mesh, trimesh.creation.box(extents=(0.5, 0.5, 0.5)).apply_translation((2, 0, 0))])
    o, d = random_rays(rng, mesh.vertices, 300)
    # Unnormalized directions too: t is parametric in trimesh and here.
    d = d * rng.uniform(0.5, 3.0, size=(len(d), 1)).astype(np.float32)
    return mesh, o.astype(np.float64), d.astype(np.float64)


def test_intersects_first_and_any(device, rng, reference):
    mesh, o, d = _scene(rng)
    ours, ref = RayMeshIntersector(mesh, device=device), reference(mesh)
    first, first_ref = ours.intersects_first(o, d), ref.intersects_first(o, d)
    assert first.dtype == first_ref.dtype and first.shape == first_ref.shape
    assert np.array_equal(first, first_ref)
    anyhit, anyhit_ref = ours.intersects_any(o, d), ref.intersects_any(o, d)
    assert anyhit.dtype == bool and np.array_equal(anyhit, anyhit_ref)


def test_intersects_id_and_location(device, rng, reference):
    mesh, o, d = _scene(rng)
    ours, ref = RayMeshIntersector(mesh, device=device), reference(mesh)
    # All hits: same (ray, triangle) pairs.
    tri, ray = ours.intersects_id(o, d)
    tri_ref, ray_ref = ref.intersects_id(o, d)
    assert set(zip(ray.tolist(), tri.tolist())) == set(zip(ray_ref.tolist(), tri_ref.tolist()))
    # First hits only.
    tri, ray, loc = ours.intersects_id(o, d, multiple_hits=False, return_locations=True)
    tri_ref, ray_ref, loc_ref = ref.intersects_id(o, d, multiple_hits=False, return_locations=True)
    order, order_ref = np.argsort(ray), np.argsort(ray_ref)
    assert np.array_equal(ray[order], ray_ref[order_ref]) and np.array_equal(tri[order], tri_ref[order_ref])
    assert np.allclose(loc[order], loc_ref[order_ref], atol=1e-5)
    # Unique locations.
    loc, ray, tri = ours.intersects_location(o, d)
    loc_ref, ray_ref, tri_ref = ref.intersects_location(o, d)
    assert loc.shape == loc_ref.shape and ray.shape == ray_ref.shape
    key = np.lexsort((loc[:, 2], loc[:, 1], loc[:, 0], ray))
    key_ref = np.lexsort((loc_ref[:, 2], loc_ref[:, 1], loc_ref[:, 0], ray_ref))
    assert np.array_equal(ray[key], ray_ref[key_ref])
    assert np.allclose(loc[key], loc_ref[key_ref], atol=1e-5)


def test_edge_and_vertex_crossings_are_one_location(device, rng, reference):
    # Rays from inside a closed convex mesh through its edges' midpoints and its vertices: one
    # crossing each, where two (or five, six) triangles' float32 t differ by a unit in the last
    # place. trimesh merges a ray's locations within 1e-8, so ours must be that close too.
    mesh = trimesh.creation.icosphere(subdivisions=2)
    ours, ref = RayMeshIntersector(mesh, device=device), reference(mesh)
    targets = np.concatenate([mesh.vertices[mesh.edges_unique].mean(axis=1), mesh.vertices])
    o = rng.uniform(-0.05, 0.05, size=(len(targets), 3))
    d = targets - o
    loc, ray, _ = ours.intersects_location(o, d)
    loc_ref, ray_ref, _ = ref.intersects_location(o, d)
    assert np.array_equal(np.bincount(ray_ref, minlength=len(o)), np.ones(len(o), int))
    assert np.array_equal(np.sort(ray), np.arange(len(o)))
    assert np.allclose(loc[np.argsort(ray)], targets, atol=1e-6)


def test_empty_mesh_raises_on_every_call(device):
    mesh = trimesh.Trimesh(vertices=[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    ours = RayMeshIntersector(mesh, device=device)
    o, d = np.array([[0.2, 0.2, -1.0]]), np.array([[0.0, 0.0, 1.0]])
    for call, args in (("intersects_first", (o, d)), ("intersects_any", (o, d)), ("intersects_id", (o, d)),
                       ("intersects_location", (o, d)), ("contains_points", (o,))):
        with pytest.raises(ValueError, match="empty"):
            getattr(ours, call)(*args)


def test_empty_results_and_contains(device, rng, reference):
    mesh = trimesh.creation.icosphere(subdivisions=2)
    ours, ref = RayMeshIntersector(mesh, device=device), reference(mesh)
    o = np.array([[5.0, 5.0, 5.0]])
    d = np.array([[1.0, 0.0, 0.0]])
    tri, ray = ours.intersects_id(o, d)
    assert tri.shape == (0,) and ray.shape == (0,)
    loc, ray, tri = ours.intersects_location(o, d)
    assert len(loc) == 0
    assert ours.intersects_first(o, d).tolist() == [-1]
    pts = rng.uniform(-1.2, 1.2, size=(200, 3))
    assert np.array_equal(ours.contains_points(pts), ref.contains_points(pts))


def test_rebuilds_after_mesh_change(device):
    mesh = trimesh.creation.icosphere(subdivisions=1)
    ours = RayMeshIntersector(mesh, device=device)
    o, d = np.array([[0.0, 0.0, 5.0]]), np.array([[0.0, 0.0, -1.0]])
    before = ours.intersects_location(o, d)[0][0, 2]
    mesh.apply_translation((0.0, 0.0, 1.0))
    after = ours.intersects_location(o, d)[0][0, 2]
    assert np.isclose(after - before, 1.0, atol=1e-5)


def test_subdivide_keeps_the_surface_and_quadruples_the_faces():
    # `scenes.subdivide` scales a mesh up to the paper's sizes: same surface (bounds and area, in
    # float64), four times the triangles per pass, and bad counts refused.
    import numpy as np

    from hlbvh_warp import scenes

    vertices, faces = scenes.default_scene(200)

    def area(v, f):
        tri = v.astype(np.float64)[f]
        return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()

    v2, f2 = scenes.subdivide(vertices, faces, 2)
    assert v2.dtype == np.float32 and f2.dtype == np.int32
    assert len(f2) == 16 * len(faces)
    np.testing.assert_allclose(v2.min(axis=0), vertices.min(axis=0), rtol=1e-6)
    np.testing.assert_allclose(v2.max(axis=0), vertices.max(axis=0), rtol=1e-6)
    assert area(v2, f2) == pytest.approx(area(vertices, faces), rel=1e-5)
    v0, f0 = scenes.subdivide(vertices, faces, 0)
    np.testing.assert_array_equal(f0, faces)
    with pytest.raises(ValueError, match="times"):
        scenes.subdivide(vertices, faces, -1)


# ----------------------------------------------------------------- pinned by the mutation audit
def test_repeated_rays_and_triangle_zero(device, reference):
    # Rays along the normals of triangles 0..4 (triangle 0 among the first hits), each given
    # twice: equal locations of different rays are different hits, as in trimesh.
    mesh = trimesh.creation.icosphere(subdivisions=2)
    targets = mesh.triangles_center[:5]
    o = np.repeat(targets * 3.0, 2, axis=0)
    d = np.repeat(-targets, 2, axis=0)
    ours, ref = RayMeshIntersector(mesh, device=device), reference(mesh)
    tri, ray, loc = ours.intersects_id(o, d, multiple_hits=False, return_locations=True)
    tri_ref, ray_ref, loc_ref = ref.intersects_id(o, d, multiple_hits=False, return_locations=True)
    assert sorted(zip(ray.tolist(), tri.tolist())) == sorted(zip(ray_ref.tolist(), tri_ref.tolist()))
    assert sorted(zip(ray.tolist(), tri.tolist())) == [(r, r // 2) for r in range(10)]
    loc, ray, tri = ours.intersects_location(o, d)
    loc_ref, ray_ref, tri_ref = ref.intersects_location(o, d)
    assert loc.shape == loc_ref.shape and sorted(ray.tolist()) == sorted(ray_ref.tolist())
    key = np.lexsort((loc[:, 2], loc[:, 1], loc[:, 0], ray))
    key_ref = np.lexsort((loc_ref[:, 2], loc_ref[:, 1], loc_ref[:, 0], ray_ref))
    assert np.allclose(loc[key], loc_ref[key_ref], atol=1e-6)


@pytest.mark.parametrize("method", ["median", "sweep_sah"])
def test_intersector_builds_with_the_chosen_method(device, method):
    mesh = trimesh.creation.icosphere(subdivisions=1)
    assert RayMeshIntersector(mesh, device=device, method=method).bvh.method == method


# ----------------------------------------------------------------- ProximityQuery.signed_distance
def _brute_distance(vertices, faces, points):
    """Float64 distance from each point to the nearest triangle: the nearer of the plane's foot
    (where it falls inside a triangle of nonzero area) and the three edges as segments, which also
    covers zero-area triangles. O(points x faces): for tiny meshes only."""
    tri = np.asarray(vertices, np.float64)[np.asarray(faces)]
    p = np.asarray(points, np.float64)[:, None, :]
    best = np.full(p.shape[:2], np.inf)
    for i in range(3):
        a, b = tri[None, :, i], tri[None, :, (i + 1) % 3]
        ab = b - a
        length2 = np.einsum("...k,...k", ab, ab)
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.clip(np.einsum("...k,...k", p - a, ab) / length2, 0.0, 1.0)
        s = np.where(length2 > 0, s, 0.0)
        best = np.minimum(best, np.linalg.norm(p - (a + s[..., None] * ab), axis=-1))
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm2 = np.einsum("ij,ij->i", normal, normal)
    with np.errstate(invalid="ignore", divide="ignore"):
        offset = np.einsum("pfk,fk->pf", p - tri[None, :, 0], normal) / np.sqrt(norm2)
        foot = p - offset[..., None] * normal / np.sqrt(norm2)[:, None]
        inside = np.ones(best.shape, dtype=bool)
        for i in range(3):
            a, b = tri[None, :, i], tri[None, :, (i + 1) % 3]
            inside &= np.einsum("pfk,fk->pf", np.cross(b - a, foot - a), normal) >= 0
    best = np.where(inside & (norm2 > 0), np.minimum(best, np.abs(offset)), best)
    return best.min(axis=1)


def test_signed_distance_of_a_single_point_is_one_row(device, reference):
    # A (3,) point broadcast against the (1, 3) closest point: the sign came from the wrong axis
    # ([0, 0, 3] read 2 outside, where [[0, 0, 3]] read -2) or NumPy raised ([2, 0, 0]). It is one
    # row now, as on_surface answers it; trimesh itself takes only (n, 3), so its answer for the
    # point as one row is the oracle, with the sphere's own side (radius 1) beside it.
    import trimesh.proximity

    from hlbvh_warp import ProximityQuery

    mesh = trimesh.creation.icosphere(subdivisions=2)
    pq = ProximityQuery(mesh, device=device)
    for point in ([0.0, 0.0, 3.0], [2.0, 0.0, 0.0], [0.1, -0.2, 0.15], (0, 0, 3)):
        single = pq.signed_distance(point)
        expected = trimesh.proximity.signed_distance(mesh, np.array([point], dtype=np.float64))
        assert single.shape == (1,) and single.dtype == np.float64, point
        assert np.sign(single[0]) == np.sign(1.0 - np.linalg.norm(point)), (point, single)
        np.testing.assert_allclose(single, expected, rtol=1e-6)
        np.testing.assert_array_equal(single, pq.signed_distance([point]))


def test_signed_distance_near_zero_area_triangles_keeps_its_magnitude(device, reference):
    # A zero-area closest triangle has a zero normal and NaN barycentrics: the point counted as
    # "on the triangle" and the sign of zero made the distance -0.0. Its sign now comes from the
    # ray-parity test trimesh uses off the triangles. Oracles: a float64 brute force for the
    # magnitude; trimesh's own signed_distance where the closest triangle has an area, and
    # trimesh's own ray parity (mesh.contains) where it has none.
    import trimesh.proximity

    from hlbvh_warp import ProximityQuery

    # The brief's case: a triangle and, beside it, a zero-area one with a repeated vertex.
    flat = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 0, 0], [5, 0, 0], [6, 0, 0]],
                           [[0, 1, 2], [3, 4, 5]], process=False)
    sd = ProximityQuery(flat, device=device).signed_distance([[5.5, 0.3, 0.0]])
    assert sd[0] == pytest.approx(-0.3, rel=1e-6) and np.abs(sd[0]) > 0

    # A closed sphere with zero-area triangles inside it (repeated vertex; three distinct
    # collinear vertices) and outside it.
    sphere = trimesh.creation.icosphere(subdivisions=2)
    n = len(sphere.vertices)
    extra = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.3, 0.0, 0.0],
                      [0.0, -0.3, 0.1], [0.0, -0.1, 0.1], [0.0, 0.3, 0.1],
                      [3.0, 0.0, 0.0], [3.0, 0.0, 0.0], [4.0, 0.0, 0.0]])
    mesh = trimesh.Trimesh(np.concatenate([sphere.vertices, extra]),
                           np.concatenate([sphere.faces, n + np.arange(9).reshape(3, 3)]), process=False)
    degenerate = len(sphere.faces) + np.arange(3)
    points = np.array([[0.15, 0.05, 0.0], [0.1, 0.0, -0.04], [0.02, 0.0, 0.15], [0.0, 0.2, 0.14],
                       [3.5, 0.3, 0.0], [3.5, 0.0, -0.2], [4.2, 0.1, 0.0],     # near a zero-area triangle
                       [0.0, 0.0, 0.6], [0.5, 0.5, 0.5], [0.0, 1.5, 0.0], [2.0, 0.2, 0.1]])
    pq = ProximityQuery(mesh, device=device)
    sd = pq.signed_distance(points)
    _, _, triangle_id = pq.on_surface(points)
    at_degenerate = np.isin(triangle_id, degenerate)
    assert at_degenerate[:7].all() and not at_degenerate[7:].any(), triangle_id
    np.testing.assert_allclose(np.abs(sd), _brute_distance(mesh.vertices, mesh.faces, points), rtol=1e-5)
    inside = mesh.contains(points[at_degenerate])
    assert inside.tolist() == [True] * 4 + [False] * 3
    np.testing.assert_array_equal(np.signbit(sd[at_degenerate]), ~inside)
    expected = trimesh.proximity.signed_distance(mesh, points[~at_degenerate])
    np.testing.assert_allclose(sd[~at_degenerate], expected, rtol=1e-6)


def test_a_single_ray_is_one_row_in_every_ray_call(device, rng, reference):
    # intersects_first / intersects_any answered a (3,) ray as one row, intersects_id and
    # intersects_location failed with a NumPy broadcast error from the hit locations. Oracle:
    # trimesh's answer for the same ray given as one row (trimesh itself takes only (n, 3)).
    mesh, o, d = _scene(rng)
    ours, ref = RayMeshIntersector(mesh, device=device), reference(mesh)
    hit = int(np.nonzero(ref.intersects_first(o, d) >= 0)[0][0])
    miss = int(np.nonzero(ref.intersects_first(o, d) < 0)[0][0])
    for k in (hit, miss):
        tri, ray = ours.intersects_id(o[k], d[k])
        tri_ref, ray_ref = ref.intersects_id(o[k:k + 1], d[k:k + 1])
        assert sorted(zip(ray.tolist(), tri.tolist())) == sorted(zip(ray_ref.tolist(), tri_ref.tolist())), k
        locations, ray, tri = ours.intersects_location(o[k], d[k], multiple_hits=False)
        locations_ref, _, tri_ref = ref.intersects_location(o[k:k + 1], d[k:k + 1], multiple_hits=False)
        assert tri.tolist() == tri_ref.tolist(), k
        np.testing.assert_allclose(locations.reshape(-1, 3), locations_ref.reshape(-1, 3), atol=1e-6)
        assert ours.intersects_first(o[k], d[k]).tolist() == ref.intersects_first(o[k:k + 1], d[k:k + 1]).tolist()


def test_one_origin_serves_every_ray_in_every_ray_call(device, rng, reference):
    # The queries take one origin for many directions; intersects_id then indexed the hit
    # locations by ray ids past the one origin row (an IndexError). Oracle: trimesh's answers for
    # the origin repeated on every row (trimesh itself takes only equal shapes).
    mesh, o, d = _scene(rng)
    ours, ref = RayMeshIntersector(mesh, device=device), reference(mesh)
    eye = np.array([[0.3, -0.2, -4.0]])
    tiled = np.repeat(eye, len(o), axis=0)
    d = rng.normal(scale=0.3, size=o.shape) - eye  # from one eye toward points inside the sphere
    tri, ray = ours.intersects_id(eye, d)
    tri_ref, ray_ref = ref.intersects_id(tiled, d)
    assert len(tri_ref) > 50
    assert sorted(zip(ray.tolist(), tri.tolist())) == sorted(zip(ray_ref.tolist(), tri_ref.tolist()))
    locations, ray, tri = ours.intersects_location(eye, d)
    assert np.array_equal(ray, ours.intersects_location(tiled, d)[1])
    np.testing.assert_allclose(locations, ours.intersects_location(tiled, d)[0])
    assert np.array_equal(ours.intersects_first(eye, d), ref.intersects_first(tiled, d))
    assert np.array_equal(ours.intersects_any(o, d[:1]), ref.intersects_any(o, np.repeat(d[:1], len(o), axis=0)))
    with pytest.raises(ValueError, match="differ in shape"):
        ours.intersects_id(o[:2], d[:3])


def test_nearest_vertex_is_trimeshs(device, rng):
    pytest.importorskip("scipy")  # trimesh's KD-tree
    from hlbvh_warp import ProximityQuery

    mesh = trimesh.creation.icosphere(subdivisions=2)
    points = rng.normal(size=(50, 3)) * 2
    distance, vertex = ProximityQuery(mesh, device=device).vertex(points)
    all_distances = np.linalg.norm(points[:, None] - mesh.vertices[None], axis=2)
    np.testing.assert_allclose(distance, all_distances.min(axis=1), rtol=1e-12)
    np.testing.assert_array_equal(vertex, all_distances.argmin(axis=1))


def test_nearest_vertex_of_a_single_point_is_one_row(device):
    # The README: a single (3,) point is answered as one row. on_surface and signed_distance did;
    # vertex handed the point to SciPy's KD-tree, which gave two scalars. The nearest vertex by
    # brute force is the oracle.
    pytest.importorskip("scipy")  # trimesh's KD-tree
    from hlbvh_warp import ProximityQuery

    mesh = trimesh.creation.icosphere(subdivisions=2)
    pq = ProximityQuery(mesh, device=device)
    for point in ([0.0, 0.0, 3.0], [0.3, -0.2, 0.1], (2, 1, 0)):
        distance, vertex = pq.vertex(point)
        all_distances = np.linalg.norm(mesh.vertices - np.asarray(point, dtype=np.float64), axis=1)
        assert distance.shape == (1,) and vertex.shape == (1,), point
        np.testing.assert_allclose(distance, [all_distances.min()], rtol=1e-12)
        np.testing.assert_array_equal(vertex, [all_distances.argmin()])


def test_signed_distance_of_a_point_in_a_face_plane_outside_the_mesh(device):
    # A point in the plane of its closest triangle, just outside that triangle's edge: the normal
    # cannot side it, and the answer must still say outside (negative, trimesh's sign).
    from hlbvh_warp import ProximityQuery

    size = 1.0e4
    box = trimesh.creation.box(extents=(size, size, size))
    box.apply_translation((size / 2, size / 2, size / 2))  # [0, size]^3
    faces = np.asarray(box.faces)
    bottom = (np.asarray(box.vertices)[faces][:, :, 2] == 0).all(axis=1)
    # The bottom face's triangles first, so that they win the distance tie at the edge.
    mesh = trimesh.Trimesh(box.vertices, np.concatenate([faces[bottom], faces[~bottom]]), process=False)
    points = np.array([[0.3 * size, -1.0e-5, 0.0], [0.3 * size, 1.0e-5, 0.0]])  # out of and on the box
    sd = ProximityQuery(mesh, device=device).signed_distance(points)
    assert sd[0] < 0 and sd[1] == pytest.approx(0.0, abs=1e-3), sd


@pytest.mark.parametrize("cls", [RayMeshIntersector, ProximityQuery])
def test_drop_ins_refuse_several_meshes_when_made(cls):
    # A list reached the first query and failed there hashing itself ("unhashable type").
    meshes = [trimesh.creation.box(), trimesh.creation.icosphere(subdivisions=1)]
    for given in (meshes, trimesh.Scene(meshes)):
        with pytest.raises(ValueError, match=f"{cls.__name__} takes one mesh.*concatenate"):
            cls(given)
    with pytest.raises(ValueError, match=f"{cls.__name__} takes a trimesh.Trimesh, got ndarray"):
        cls(np.zeros((3, 3)))


# ----------------------------------------------------------------- pinned by the third mutation audit
@pytest.mark.parametrize("multiple_hits", [True, False])
def test_one_direction_serves_every_origin_in_intersects_id(device, rng, reference, multiple_hits):
    # A light's one direction for many origins: the hit locations index the directions by ray id
    # too, so the direction row must be spelled out as the origin row is (the one-origin test
    # above never reached this half of the broadcast: an IndexError without it).
    mesh, _, _ = _scene(rng)
    ours, ref = RayMeshIntersector(mesh, device=device), reference(mesh)
    # Origins on a plane below the sphere and the box, one slanted direction up through both.
    o = np.column_stack([rng.uniform(-1.2, 2.4, 200), rng.uniform(-1.2, 1.2, 200), np.full(200, -3.0)])
    light = np.array([[0.05, -0.1, 1.0]])
    tiled = np.repeat(light, len(o), axis=0)
    tri, ray = ours.intersects_id(o, light, multiple_hits=multiple_hits)
    tri_ref, ray_ref = ref.intersects_id(o, tiled, multiple_hits=multiple_hits)
    assert len(set(ray_ref.tolist())) > 50
    assert sorted(zip(ray.tolist(), tri.tolist())) == sorted(zip(ray_ref.tolist(), tri_ref.tolist()))
    tri, ray, locations = ours.intersects_id(o, light, multiple_hits=multiple_hits, return_locations=True)
    # Each location lies on its own ray (float64: o + t d for that ray's origin and the light).
    along = np.einsum("ij,j->i", locations - o[ray], light[0]) / (light[0] @ light[0])
    np.testing.assert_allclose(locations, o[ray] + along[:, None] * light[0], atol=1e-6)
    assert (along > 0).all()
    locations_t, ray_t, tri_t = ours.intersects_location(o, tiled, multiple_hits=multiple_hits)
    np.testing.assert_allclose(ours.intersects_location(o, light, multiple_hits=multiple_hits)[0], locations_t)


def test_empty_lists_are_empty_batches_in_every_ray_call(device):
    # intersects_first / intersects_any take [] as no rays; intersects_id / intersects_location
    # read a 1-D [] as one (3,) ray and reshaped it to (1, 0): "origins must have shape (n, 3),
    # got (1, 0)".
    mesh = trimesh.creation.icosphere(subdivisions=1)
    ours = RayMeshIntersector(mesh, device=device)
    assert ours.intersects_first([], []).shape == (0,)
    assert ours.intersects_any([], []).shape == (0,)
    tri, ray = ours.intersects_id([], [])
    assert tri.shape == ray.shape == (0,)
    locations, ray, tri = ours.intersects_location([], [])
    assert locations.shape == (0, 3) and ray.shape == tri.shape == (0,)


def test_a_row_against_rows_of_another_width_names_the_directions(device):
    # One origin against directions of two columns: the query's own shape error, not NumPy's
    # broadcast message.
    ours = RayMeshIntersector(trimesh.creation.icosphere(subdivisions=1), device=device)
    for call in (ours.intersects_id, ours.intersects_location):
        with pytest.raises(ValueError, match=r"directions must have shape \(n, 3\), got \(5, 2\)"):
            call(np.zeros((1, 3)), np.ones((5, 2)))


def test_every_call_refuses_rows_that_are_not_real_numbers(device):
    """The drop-ins cast their rows to float64 before the library's checks ran: a complex origin
    lost its imaginary part, bool points read as 0 and 1 (`contains_points` answered), and an
    object row holding None became NaN ("found nothing"). Each is refused as the library's own
    queries refuse it, naming the argument, while float, integer and list rows still work."""
    mesh = trimesh.creation.icosphere(subdivisions=1)
    rays, near = RayMeshIntersector(mesh, device=device), ProximityQuery(mesh, device=device)
    good = np.float64([[0.0, 0.0, -5.0]])
    up = np.float64([[0.0, 0.0, 1.0]])
    bad_rows = (np.array([[0, 0, -5 + 3j]]), np.zeros((1, 3), bool), np.array([[None, 1, 2]], dtype=object))
    for bad in bad_rows:
        for call in (lambda x: rays.intersects_first(x, up), lambda x: rays.intersects_any(x, up),
                     lambda x: rays.intersects_id(x, up), lambda x: rays.intersects_location(good, x)):
            with pytest.raises(ValueError, match="(origins|directions) must hold real numbers"):
                call(bad)
        for call in (rays.contains_points, near.on_surface, near.signed_distance):
            with pytest.raises(ValueError, match="points must hold real numbers"):
                call(bad)
    assert rays.intersects_first(good, up).tolist() == rays.intersects_first([[0, 0, -5]], [[0, 0, 1]]).tolist()
    assert rays.intersects_first(good, up)[0] >= 0
    assert rays.contains_points(np.int64([[0, 0, 0], [0, 0, 5]])).tolist() == [True, False]
