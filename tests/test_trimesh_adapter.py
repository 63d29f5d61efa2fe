"""hlbvh_warp.trimesh_adapter.RayMeshIntersector against trimesh's own RayMeshIntersector."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from oracles import random_rays
from trimesh.ray import ray_triangle

from hlbvh_warp.trimesh_adapter import RayMeshIntersector


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
