"""The public calls as users misuse them and as ray tracers stress them, against float64 oracles."""

import numpy as np
import pytest
import trimesh
import warp as wp
from conftest import TEST_KERNEL_OPTIONS

import hlbvh_warp
from hlbvh_warp import query

from oracles import numpy_all_hits

wp.set_module_options(TEST_KERNEL_OPTIONS)  # quick CPU compiles of this file's kernels (conftest)


def _big_sphere(subdivisions=2):
    """An icosphere of radius 1.7 * 2^127 (2.9e38): every coordinate a finite float32, but a box
    coordinate minus an origin on the far side of the sphere is past float32's range."""
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions)
    vertices = (np.asarray(mesh.vertices, np.float64) * 1.7 * 2.0**127).astype(np.float32)
    return vertices, np.asarray(mesh.faces, np.int32)


def _rays_across_the_big_sphere(rng, n=64):
    """The big sphere and n rays from inside it near one side towards the other, with long
    directions: the hits lie at t of about 1, not past float32 as for unit ones."""
    vertices, faces = _big_sphere()
    scale = 1.7 * 2.0**127
    origins = (np.c_[rng.uniform(-0.9, -0.7, n), rng.uniform(-0.2, 0.2, (n, 2))] * scale).astype(np.float32)
    directions = (np.c_[np.ones(n), rng.uniform(-0.4, 0.4, (n, 2))] * 2.0**120).astype(np.float32)
    return vertices, faces, origins, directions


@wp.kernel
def _canonical_closest_hit_kernel(view: hlbvh_warp.BvhView, origins: wp.array(dtype=wp.vec3),
                                  directions: wp.array(dtype=wp.vec3), prims: wp.array(dtype=wp.int32)):
    tid = wp.tid()
    prims[tid] = hlbvh_warp.bvh_closest_hit(view, origins[tid], directions[tid], 1.0e30).prim


def test_rays_across_a_mesh_spanning_float32_do_not_leak(device, rng):
    """A box coordinate minus the origin past float32's range (a sphere of radius 2.9e38, rays from
    inside it near one side to the other) overflowed the slab distances of the box test to
    infinity: the walk dropped every box on the far side, and 499 of 500 rays from inside the
    closed sphere escaped, though the triangle test (which shears in float64 there) hits them.
    Every ray from inside must hit, each query must agree with the float64 brute force."""
    vertices, faces, origins, directions = _rays_across_the_big_sphere(rng)
    n = len(origins)
    bvh = hlbvh_warp.build(vertices, faces, device=device)
    hit, t_ref, margin = numpy_all_hits(vertices, faces, origins, directions, np.inf)
    clear = hit & (margin > 1e-4)
    assert clear.any(axis=1).all()  # the oracle: every ray crosses the sphere away from its edges
    best = np.where(hit, t_ref, np.inf).min(axis=1)

    t, prim = query.intersect(bvh, origins, directions)
    assert (prim >= 0).all(), f"{int((prim < 0).sum())} of {n} rays escaped the closed sphere"
    np.testing.assert_allclose(t, best, rtol=1e-5)
    assert query.occluded(bvh, origins, directions).all()
    ray_id, all_prim, _ = query.intersect_all(bvh, origins, directions)
    listed = set(zip(ray_id.tolist(), all_prim.tolist()))
    assert set(map(tuple, np.argwhere(clear).tolist())) <= listed

    # A user's view without the traversal layout walks the canonical arrays: the same hits.
    bare = query.view(bvh)
    view = hlbvh_warp.BvhView()
    for name in ("node_lowers", "node_uppers", "node_left", "node_right", "node_begin", "node_end", "prim_order",
                 "prim_lowers", "prim_uppers", "vertices", "faces"):
        setattr(view, name, getattr(bare, name))
    view.packed_nodes = wp.zeros(0, dtype=bare.packed_nodes.dtype, device=device)
    view.packed_triangles = wp.zeros(0, dtype=bare.packed_triangles.dtype, device=device)
    out = wp.zeros(n, dtype=wp.int32, device=device)
    wp.launch(_canonical_closest_hit_kernel, dim=n, device=device,
              inputs=[view, wp.array(origins, dtype=wp.vec3, device=device),
                      wp.array(directions, dtype=wp.vec3, device=device), out])
    np.testing.assert_array_equal(out.numpy(), prim)


def test_a_far_origin_past_half_of_float32_keeps_the_exit_hit(device):
    """An origin at 3.4e38 and a sphere of radius 1e37: the exit crossing's box lies more than
    float32's largest value away on one axis, and intersect_all listed only the entry."""
    mesh = trimesh.creation.icosphere(subdivisions=2)
    vertices = (np.asarray(mesh.vertices) * 1e37).astype(np.float32)
    faces = np.asarray(mesh.faces, np.int32)
    bvh = hlbvh_warp.build(vertices, faces, device=device)
    origin = np.array([[-1.517852376857916e38, 1.476300818423395e38, 3.398543675134822e38]], np.float32)
    direction = np.array([[1.585236626284128e38, -1.4348287670345204e38, -3.3681975395340305e38]], np.float32)
    hit, t_ref, margin = numpy_all_hits(vertices, faces, origin, direction, np.inf)
    expected = np.flatnonzero(hit[0])
    assert len(expected) == 2 and (margin[0, expected] > 0.1).all()  # entry and exit, both clear
    _, prims, t = query.intersect_all(bvh, origin, direction)
    assert sorted(prims.tolist()) == sorted(expected.tolist())
    np.testing.assert_allclose(np.sort(t), np.sort(t_ref[0, expected]), rtol=1e-5)
    exit_prim = expected[np.argmax(t_ref[0, expected])]
    entry_prim = expected[np.argmin(t_ref[0, expected])]
    assert query.intersect(bvh, origin, direction, ignore_prim=int(entry_prim))[1][0] == exit_prim


def test_per_query_limits_take_any_warp_array(device):
    """t_max, t_min, max_dist and ignore_prim take one value per query "NumPy or Warp", as the
    rays and points do; a wp.indexedarray (a gather of another array) was refused as "must be a
    number" or as "dtype object", though the origins beside it were taken."""
    bvh = hlbvh_warp.build(trimesh.creation.box(), device=device)
    origins = np.array([[0.1, 0.2, -5.0], [0.1, 0.2, -5.0]])
    directions = np.array([0.0, 0.0, 1.0])
    base = wp.array([1.0, 10.0, 4.49], dtype=float, device=device)
    which = wp.array([2, 1], dtype=int, device=device)  # t = 4.49 and 10, through the box's bottom face
    gathered = wp.indexedarray(base, [which])
    t, prim = query.intersect(bvh, origins, directions, t_max=gathered)
    # The bottom face (z = -0.5) is at t = 4.5: beyond 4.49, within 10.
    assert prim.tolist()[0] == -1 and prim[1] >= 0 and t[1] == 4.5
    np.testing.assert_array_equal(query.occluded(bvh, origins, directions, t_max=gathered), [False, True])
    t, prim = query.intersect(bvh, origins, directions, t_min=gathered)
    assert t.tolist() == [4.5, np.inf]  # the bottom face lies past 4.49; nothing lies past 10
    _, distance, found = query.closest_point(bvh, origins, max_dist=gathered)
    assert found[0] == -1 and found[1] >= 0 and distance.tolist() == [np.inf, 4.5]  # the box is 4.5 away
    first = query.intersect(bvh, origins, directions)[1]
    ignored = wp.indexedarray(wp.array([-1, -1, first[0]], dtype=wp.int32, device=device), [which])
    t, _ = query.intersect(bvh, origins, directions, ignore_prim=ignored)
    assert t.tolist() == [5.5, 4.5]  # ray 0 ignores the bottom face's triangle: the top face next


def test_a_flag_passed_where_a_distance_goes_is_refused(device):
    """``intersect(bvh, o, d, True)`` (return_barycentrics meant, t_max given) and
    ``closest_point(bvh, p, True)`` read True as the number 1 and silently dropped every hit past
    t = 1 or every triangle past distance 1; a boolean array was refused as "dtype bool" already.
    A scalar boolean is refused the same way, and the next good call answers as before."""
    bvh = hlbvh_warp.build(trimesh.creation.box(), device=device)
    o, d = np.array([[0.1, 0.2, -5.0]]), np.array([[0.0, 0.0, 1.0]])
    for flag in (True, np.True_, False):
        for call, kwargs in ((query.intersect, {}), (query.occluded, {}), (query.intersect_all, {})):
            with pytest.raises(ValueError, match="t_max must be a number, got bool"):
                call(bvh, o, d, flag, **kwargs)
            with pytest.raises(ValueError, match="t_min must be a number, got bool"):
                call(bvh, o, d, t_min=flag)
        with pytest.raises(ValueError, match="max_dist must be a number, got bool"):
            query.closest_point(bvh, o, flag)
    t, prim = query.intersect(bvh, o, d)
    assert t.tolist() == [4.5] and prim[0] >= 0  # the box's bottom face, z = -0.5
    assert query.closest_point(bvh, o)[1].tolist() == [4.5]


def _torus_inside(points, major, minor):
    """Analytic inside test of a torus around z (float64)."""
    radial = np.hypot(points[:, 0], points[:, 1]) - major
    return radial**2 + points[:, 2] ** 2 < minor**2


@pytest.mark.parametrize("scale", [1.0, 1e12, 1e-12])
def test_drop_in_locations_and_inside_tests_at_every_scale(device, rng, scale):
    """trimesh merges a ray's hit locations by rounding them to multiples of 1e-8 as int64: past
    about 9e10 the products overflow, every location of a ray becomes one row, and the drop-in
    listed one crossing where there are two. Points in a torus's hole then read inside
    (contains_points) with a positive signed distance, since each of their two parity rays met the
    ring once. The locations are merged within 1e-8 of their magnitude (absolute below 1)."""
    major, minor = 1.0, 0.8
    mesh = trimesh.creation.torus(major_radius=major, minor_radius=minor, major_sections=48, minor_sections=24)
    mesh.vertices *= scale
    points = rng.uniform(-2.0, 2.0, (300, 3)) * [1, 1, 0.9]
    angle = rng.uniform(0, 2 * np.pi, 20)
    hole = np.c_[0.1 * np.cos(angle), 0.1 * np.sin(angle), rng.uniform(-0.3, 0.3, 20)]  # outside, rays meet the ring
    points = np.concatenate([hole, points])
    # Away from the polygonal surface (its chords cut 0.3% of the radii), where inside is clear.
    radial = np.hypot(np.hypot(points[:, 0], points[:, 1]) - major, points[:, 2])
    points = points[np.abs(radial - minor) > 0.05]
    points = points[np.abs(points[:, 2]) < 0.85]  # inside the mesh's bounding box: rays are cast
    inside = _torus_inside(points, major, minor)
    assert inside.any() and (~inside).any()
    ours = hlbvh_warp.RayMeshIntersector(mesh, device=device)
    np.testing.assert_array_equal(ours.contains_points(points * scale), inside)
    signed = hlbvh_warp.ProximityQuery(mesh, device=device).signed_distance(points * scale)
    # Within trimesh's tol.merge (1e-8, absolute) of the surface a point reads inside, as in trimesh.
    np.testing.assert_array_equal(signed > 0, inside | (np.abs(signed) <= 1e-8))

    # Every ray lists each crossing the float64 brute force finds once: no two merged.
    o = points[:40] * scale
    d = np.tile([0.3, -0.2, 0.9], (len(o), 1))
    hit, _, margin = numpy_all_hits(mesh.vertices, mesh.faces, o, d, np.inf)
    assert (margin[hit] > 1e-6).all()  # no ray passes near an edge: each hit is one crossing
    _, ray, _ = ours.intersects_location(o, d)
    np.testing.assert_array_equal(np.bincount(ray, minlength=len(o)), hit.sum(axis=1))


@pytest.mark.parametrize("width", [4, 16])
def test_wide_rays_across_a_mesh_spanning_float32_do_not_leak(device, rng, width):
    """The wide walk had the binary walk's overflow: on the sphere of radius 2.9e38 a box
    coordinate minus an origin on the far side is past float32's range, its slab distance came
    out infinite, and `wide.intersect` missed every one of 64 rays from inside the closed sphere.
    It now decides those boxes again in float64, as the binary walk does: the float64 brute
    force's hits."""
    from hlbvh_warp import wide

    vertices, faces, origins, directions = _rays_across_the_big_sphere(rng)
    n = len(origins)
    bvh = hlbvh_warp.build(vertices, faces, device=device)
    hit, t_ref, margin = numpy_all_hits(vertices, faces, origins, directions, np.inf)
    assert (hit & (margin > 1e-4)).any(axis=1).all()
    best = np.where(hit, t_ref, np.inf).min(axis=1)
    t, prim = wide.intersect(wide.collapse(bvh, width), origins, directions)
    assert (prim >= 0).all(), f"{int((prim < 0).sum())} of {n} rays escaped the closed sphere"
    np.testing.assert_allclose(t, best, rtol=1e-5)
