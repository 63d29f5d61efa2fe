"""Ray ranges for secondary rays: a near end ``t_min`` and a triangle each ray ignores, in the batched
calls (`intersect`, `occluded`, `intersect_all`) and in user kernels on packed and canonical views,
against a float64 brute force; and rays from far origins, whose walk starts nearer with the range
shifted to match."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
import warp as wp
from conftest import TEST_KERNEL_OPTIONS
from handmade_trees import canonical_view
from oracles import (assert_range_hits_match, crossings, crossings_prim, directions_off_surface, expected_range_hits,
                     nested_shells, numpy_all_hits, random_rays)

import hlbvh_warp
from hlbvh_warp import query, wide

wp.set_module_options(TEST_KERNEL_OPTIONS)  # quick CPU compiles of this file's kernels (conftest)


@pytest.fixture
def scene():
    return nested_shells()


def test_t_min_per_ray_and_for_every_ray(device, rng, scene):
    verts, faces = scene
    bvh = hlbvh_warp.build(verts, faces, device=device)
    o, d = random_rays(rng, verts, 400)
    first, second = crossings(verts, faces, o, d)
    # Per ray: a near end between the first and the second crossing, so the answer is the second.
    lows = np.where(np.isfinite(second), 0.5 * (first + second), np.where(np.isfinite(first), first * 0.5, 1.0))
    t, prim = query.intersect(bvh, o, d, t_min=lows)
    best, prim_ref, ambiguous = expected_range_hits(verts, faces, o, d, lows, -1)
    assert (prim_ref >= 0).sum() > 100 and (prim_ref != crossings_prim(verts, faces, o, d)).sum() > 100
    assert_range_hits_match(t, prim, best, prim_ref, ambiguous)
    # One near end for every ray, as a Warp array and as a number.
    low = float(np.median(first[np.isfinite(first)]))
    best, prim_ref, ambiguous = expected_range_hits(verts, faces, o, d, low, -1)
    for arg in (low, wp.array([low], dtype=wp.float32, device=device)):
        t, prim = query.intersect(bvh, o, d, t_min=arg)
        assert_range_hits_match(t, prim, best, prim_ref, ambiguous)
    assert (t[prim >= 0] > np.float32(low)).all()


def test_ignore_prim_finds_the_next_crossing(device, rng, scene):
    verts, faces = scene
    bvh = hlbvh_warp.build(verts, faces, device=device)
    o, d = random_rays(rng, verts, 400)
    first = crossings_prim(verts, faces, o, d)
    # Every other ray ignores the triangle it would hit first; the rest ignore nothing (-1).
    ignore = np.where(np.arange(len(o)) % 2 == 0, first, -1).astype(np.int64)
    t, prim, u, v = query.intersect(bvh, o, d, ignore_prim=ignore, return_barycentrics=True)
    best, prim_ref, ambiguous = expected_range_hits(verts, faces, o, d, 0.0, ignore)
    assert ((ignore >= 0) & (prim_ref >= 0) & ~ambiguous).sum() > 100
    assert_range_hits_match(t, prim, best, prim_ref, ambiguous)
    assert not ((prim == ignore) & (ignore >= 0)).any()
    # The weights belong to the triangle reported, not to the one ignored.
    hit = prim >= 0
    tri = verts[faces[prim[hit]]].astype(np.float64)
    on_tri = (1 - u[hit] - v[hit])[:, None] * tri[:, 0] + u[hit, None] * tri[:, 1] + v[hit, None] * tri[:, 2]
    np.testing.assert_allclose(on_tri, o[hit] + t[hit, None] * d[hit], atol=1e-5)


def test_secondary_rays_leave_their_surface(device, rng, scene):
    """What the range is for: rays from the hit points of camera rays, each ignoring its triangle,
    find the next surface at its float64 distance and never their own triangle."""
    verts, faces = scene
    bvh = hlbvh_warp.build(verts, faces, device=device)
    o, d = random_rays(rng, verts, 600)
    t, prim = query.intersect(bvh, o, d)
    keep = prim >= 0
    points = (o[keep] + t[keep, None] * d[keep]).astype(np.float32)
    dirs = directions_off_surface(rng, verts, faces, prim[keep])
    ignore = prim[keep]
    t2, prim2 = query.intersect(bvh, points, dirs, ignore_prim=ignore)
    assert not (prim2 == ignore).any()
    best, prim_ref, ambiguous = expected_range_hits(verts, faces, points, dirs, 0.0, ignore)
    # A neighbour sharing the edge or vertex the point lies near is crossed at t near 0: ambiguous.
    ambiguous |= (best < 1e-3)
    assert_range_hits_match(t2, prim2, best, prim_ref, ambiguous)
    occ = query.occluded(bvh, points, dirs, ignore_prim=ignore)
    assert np.array_equal(occ[~ambiguous], prim_ref[~ambiguous] >= 0)


def test_occluded_and_intersect_all_honour_the_range(device, rng, scene):
    """`intersect_all` under a range lists exactly the unrestricted list's crossings inside it (the
    same watertight test, so the same float32 t), `occluded` says whether it is non-empty, and
    `intersect`'s answer is its nearest."""
    verts, faces = scene
    bvh = hlbvh_warp.build(verts, faces, device=device)
    o, d = random_rays(rng, verts, 300)
    first, second = crossings(verts, faces, o, d)
    lows = np.where(np.isfinite(first), first * rng.uniform(0.5, 1.5, len(o)), 0.0)
    highs = lows + rng.uniform(0.0, 2.0, len(o))
    ignore = np.where(rng.random(len(o)) < 0.5, crossings_prim(verts, faces, o, d), -1)
    ray_all, prim_all, t_all = query.intersect_all(bvh, o, d)
    # Compared in float64: t_min and t_max bound the float32 t as the exact values they are.
    t64 = t_all.astype(np.float64)
    inside = (t64 > lows[ray_all]) & (t64 < highs[ray_all]) & (prim_all != ignore[ray_all])
    ray_id, prim, t = query.intersect_all(bvh, o, d, t_max=highs, t_min=lows, ignore_prim=ignore)
    assert inside.sum() > 50 and (~inside).sum() > 50
    assert np.array_equal(ray_id, ray_all[inside]) and np.array_equal(prim, prim_all[inside])
    assert np.array_equal(t, t_all[inside])
    occ = query.occluded(bvh, o, d, t_max=highs, t_min=lows, ignore_prim=ignore)
    assert np.array_equal(occ, np.isin(np.arange(len(o)), ray_id))
    t_near, prim_near = query.intersect(bvh, o, d, t_max=highs, t_min=lows, ignore_prim=ignore)
    nearest = np.full(len(o), np.inf, np.float32)
    np.minimum.at(nearest, ray_id, t)
    assert np.array_equal(t_near, nearest)
    assert np.array_equal(prim_near >= 0, occ)


@wp.kernel
def _range_user_kernel(
    bvh: hlbvh_warp.BvhView,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    t_min: wp.array(dtype=float),
    ignore: wp.array(dtype=wp.int32),
    out_t: wp.array(dtype=float),
    out_prim: wp.array(dtype=wp.int32),
    out_any: wp.array(dtype=wp.int32),
    out_occluded: wp.array(dtype=wp.int32),
):
    # What a user writes for a secondary ray: the range and the triangle it leaves from.
    tid = wp.tid()
    h = hlbvh_warp.bvh_closest_hit(bvh, origins[tid], directions[tid], t_min[tid], 1.0e30, ignore[tid])
    out_t[tid] = h.t
    out_prim[tid] = h.prim
    out_any[tid] = hlbvh_warp.bvh_any_hit(bvh, origins[tid], directions[tid], t_min[tid], 1.0e30, ignore[tid]).prim
    out_occluded[tid] = hlbvh_warp.bvh_occluded(bvh, origins[tid], directions[tid], t_min[tid], 1.0e30, ignore[tid])


@pytest.mark.parametrize("layout", ["packed", "canonical"])
def test_user_kernel_range_overloads(device, rng, scene, layout):
    verts, faces = scene
    bvh = hlbvh_warp.build(verts, faces, device=device)
    o, d = random_rays(rng, verts, 300)
    first, _ = crossings(verts, faces, o, d)
    lows = np.where(np.isfinite(first) & (rng.random(len(o)) < 0.5), first * 1.2, 0.0).astype(np.float32)
    ignore = np.where(rng.random(len(o)) < 0.5, crossings_prim(verts, faces, o, d), -1).astype(np.int32)
    view = query.view(bvh) if layout == "packed" else canonical_view(bvh)
    outs = [wp.empty(len(o), dtype=dt, device=device) for dt in (float, wp.int32, wp.int32, wp.int32)]
    wp.launch(_range_user_kernel, dim=len(o), device=device,
              inputs=[view, wp.array(o, dtype=wp.vec3, device=device), wp.array(d, dtype=wp.vec3, device=device),
                      wp.array(lows, dtype=float, device=device), wp.array(ignore, dtype=wp.int32, device=device)]
              + outs)
    t_k, prim_k, any_k, occ_k = (a.numpy() for a in outs)
    t, prim = query.intersect(bvh, o, d, t_min=lows, ignore_prim=ignore)
    assert np.array_equal(prim_k, prim) and np.array_equal(t_k, t)
    assert np.array_equal(any_k >= 0, prim >= 0) and np.array_equal(occ_k, (prim >= 0).astype(np.int32))
    assert not ((any_k == ignore) & (ignore >= 0)).any()
    best, prim_ref, ambiguous = expected_range_hits(verts, faces, o, d, lows, ignore)
    assert_range_hits_match(t_k, prim_k, best, prim_ref, ambiguous)


def _plane_at_z1(device):
    verts = np.array([[-1, -1, 1], [3, -1, 1], [-1, 3, 1]], np.float32)
    return hlbvh_warp.build(verts, np.array([[0, 1, 2]], np.int32), device=device)


def test_t_min_bounds_exactly(device):
    """The range is open at t_min, which is rounded down to float32 (as t_max is rounded up), so a
    float64 t_min just under a float32 hit keeps it: rounded to nearest, 1 - 1e-12 read as 1.0 and
    dropped the hit at t = 1."""
    bvh = _plane_at_z1(device)
    o, d = np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32)
    cases = {0.0: True, 1.0 - 1e-12: True, float(np.nextafter(1.0, 0.0)): True, 1.0: False, 1.0 + 1e-12: False,
             1e39: False, float("inf"): False}
    for low, hit in cases.items():
        t, prim = query.intersect(bvh, o, d, t_min=low)
        assert (prim[0] == 0) == hit, low
        if hit:
            assert t[0] == 1.0
        assert query.occluded(bvh, o, d, t_min=low)[0] == hit
    # An empty range misses, whichever end is given per ray.
    assert query.intersect(bvh, np.zeros((2, 3)), [0, 0, 1], t_min=[0.5, 2.0], t_max=[2.0, 0.5])[1].tolist() == [0, -1]
    # A tiny direction is scaled into range; t_min is in the caller's units all the same.
    tiny = np.array([[0, 0, 1e-30]], np.float32)
    assert query.intersect(bvh, o, tiny, t_min=0.5e30)[1][0] == 0
    assert query.intersect(bvh, o, tiny, t_min=2e30)[1][0] == -1


def test_ray_range_errors_name_the_problem(device):
    bvh = _plane_at_z1(device)
    o, d = np.zeros((2, 3), np.float32), np.array([[0, 0, 1]] * 2, np.float32)
    bad = {
        "t_min must be >= 0, got -1.0": {"t_min": -1.0},
        r"t_min must be >= 0, got nan \(ray 1\)": {"t_min": [0.0, np.nan]},
        r"t_min must be a number or have shape \(2,\)": {"t_min": np.zeros(3)},
        r"ignore_prim must be -1 \(none\) or a triangle index in \[0, 1\), got 1": {"ignore_prim": 1},
        r"got -2 \(ray 0\)": {"ignore_prim": [-2, 0]},
        "ignore_prim must hold integer triangle indices": {"ignore_prim": np.array([0.0, 0.0])},
        "must hold integer triangle indices.*bool": {"ignore_prim": np.array([True, False])},
        r"ignore_prim must be one index or have shape \(2,\)": {"ignore_prim": np.zeros(3, np.int32)},
    }
    for message, kwargs in bad.items():
        for call in (query.intersect, query.occluded, query.intersect_all):
            with pytest.raises(ValueError, match=message):
                call(bvh, o, d, **kwargs)
    # A Warp array of indices is read like a NumPy one.
    ignore = wp.array([0, -1], dtype=wp.int32, device=device)
    assert query.intersect(bvh, o, d, ignore_prim=ignore)[1].tolist() == [-1, 0]


@pytest.mark.parametrize("distance", [200.0, 1e3, 1e4, 1e6, 1e8])
def test_rays_from_far_origins(device, rng, scene, distance):
    """Origins ``distance`` mesh sizes away: float32 coordinates relative to such an origin keep
    nothing of a triangle's size, so the walk starts from the origin moved along its ray, in
    float64, to the mesh's box. Hits then agree with the float64 brute force (at 1e6, 32 of 300
    had disagreed, and at 1e8 most hits were lost), the walk opens as few nodes as from nearby
    (at 1e8 it had opened the whole tree), and the range bounds the true distance."""
    verts, faces = scene
    bvh = hlbvh_warp.build(verts, faces, device=device)
    lo, hi = verts.min(0).astype(np.float64), verts.max(0).astype(np.float64)
    size = np.linalg.norm(hi - lo)
    dirs = rng.normal(size=(300, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    near_o = (0.5 * (lo + hi) - 2.0 * size * dirs).astype(np.float32)
    far_o = (0.5 * (lo + hi) - distance * size * dirs).astype(np.float32)
    targets = lo + rng.random((300, 3)) * (hi - lo)
    rays = {}
    for name, o in (("near", near_o), ("far", far_o)):
        d = targets - o.astype(np.float64)
        rays[name] = (o, (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32))
    _, _, near_stats = query.intersect(bvh, *rays["near"], stats=True)
    o, d = rays["far"]
    t, prim, stats = query.intersect(bvh, o, d, stats=True)
    # Which triangle is first is decided near the mesh, to the mesh's float32 resolution.
    best, prim_ref, ambiguous = expected_range_hits(verts, faces, o, d, 0.0, -1, scale=size)
    # At 1e8 a float32 direction's rounding alone turns a ray by more than the mesh: few still hit.
    assert (prim_ref >= 0).sum() > (100 if distance < 1e8 else 10)
    assert_range_hits_match(t, prim, best, prim_ref, ambiguous)
    assert stats.nodes_visited.mean() <= 1.5 * near_stats.nodes_visited.mean()
    # The range bounds the distance from the caller's origin, wherever the walk started.
    hit = np.flatnonzero((prim_ref >= 0) & ~ambiguous)
    below, _ = query.intersect(bvh, o[hit], d[hit], t_max=best[hit] * (1 - 1e-6))
    above, _ = query.intersect(bvh, o[hit], d[hit], t_max=best[hit] * (1 + 1e-6))
    assert np.isinf(below).all() and np.isfinite(above).all()
    ray_id, all_prim, all_t = query.intersect_all(bvh, o[hit], d[hit])
    first = np.full(len(hit), np.inf)
    np.minimum.at(first, ray_id, all_t.astype(np.float64))
    np.testing.assert_allclose(first, best[hit], rtol=1e-5)
    # A far ray that misses the mesh's box is refused before the walk.
    away = query.intersect(bvh, o[:50], -d[:50], stats=True)
    assert (away[1] == -1).all() and (away[2].nodes_visited == 0).all()
    # Wide trees start their walk the same way, so they find the same hits at the same t.
    for width in (4, 16):
        t_wide, prim_wide = wide.intersect(wide.collapse(bvh, width), o, d)
        assert np.array_equal(prim_wide, prim) and np.array_equal(t_wide, t)


@pytest.mark.parametrize("z", [-1e5, -1e16, -2e16, -1e20])
def test_far_axis_rays_keep_the_front_face(device, z):
    """Rays along z have exact answers at any distance (x and y never round): the first face is
    the front one, and every crossing is listed. From 2e16 sphere sizes the float64 entry distance
    is off by more than the sphere, and a walk started one extent before the box began inside it:
    the back face came first and the front one was lost from `intersect_all`."""
    sphere = trimesh.creation.icosphere(subdivisions=2)
    verts, faces = np.asarray(sphere.vertices, np.float32), np.asarray(sphere.faces, np.int32)
    bvh = hlbvh_warp.build(verts, faces, device=device)
    xy = np.random.default_rng(1).uniform(-0.6, 0.6, (40, 2))
    o = np.c_[xy, np.full(len(xy), z)].astype(np.float32)
    d = np.array([0, 0, 1], np.float32)
    # The same lines from nearby: only t differs, by the origin's offset.
    near = np.c_[xy, np.full(len(xy), -3.0)].astype(np.float32)
    hit, t_ref, margin = numpy_all_hits(verts, faces, near, np.tile(d, (len(xy), 1)), np.inf)
    clear = ~((np.abs(margin) < 1e-6) & hit).any(axis=1)
    first = np.where(hit.any(axis=1), np.argmin(np.where(hit, t_ref, np.inf), axis=1), -1)
    assert (first[clear] >= 0).sum() > 20
    t, prim = query.intersect(bvh, o, d)
    assert np.array_equal(prim[clear], first[clear])
    for width in (4, 16):
        assert np.array_equal(wide.intersect(wide.collapse(bvh, width), o, d)[1][clear], first[clear])
    ray_id, all_prim, _ = query.intersect_all(bvh, o, d)
    listed = set(zip(ray_id.tolist(), all_prim.tolist()))
    expected = set(map(tuple, np.argwhere(hit).tolist()))
    assert {pair for pair in expected if clear[pair[0]]} <= listed


def test_far_hits_honour_the_open_range(device):
    """The range is tested on the t reported, the float32 distance from the caller's origin: a far
    walk compares in its own frame, and adding the shift back had rounded hits onto t_max (half
    of them at 1e5 sphere sizes) or onto t_min with the same triangle, and past float32's range
    to an infinite t with a triangle."""
    sphere = trimesh.creation.icosphere(subdivisions=3)
    bvh = hlbvh_warp.build(sphere, device=device)
    xy = np.random.default_rng(0).uniform(-0.5, 0.5, (64, 2))
    d = np.array([0, 0, 1], np.float32)
    for z in (-1e5, -1e8):
        o = np.c_[xy, np.full(len(xy), z)].astype(np.float32)
        t, prim = query.intersect(bvh, o, d)
        assert (prim >= 0).all()
        t2, prim2 = query.intersect(bvh, o, d, t_min=t)
        assert ((t2 > t) | (prim2 == -1)).all()
        assert not query.occluded(bvh, o, d, t_max=t).any()
        assert query.intersect_all(bvh, o, d, t_max=t)[0].size == 0
        assert (query.intersect_all(bvh, o, d, t_min=t)[2] > t[query.intersect_all(bvh, o, d, t_min=t)[0]]).all()
        w = wide.collapse(bvh, 4)
        assert (wide.intersect(w, o, d, t_max=t)[1] == -1).all()
    # The sphere lies 3e38 / 0.5 = 6e38 along the ray, past float32's range: no hit, as from nearby.
    far = np.array([[0.1, 0.2, -3e38]], np.float32)
    assert query.intersect(bvh, far, [0, 0, 0.5])[1][0] == -1
    assert not query.occluded(bvh, far, [0, 0, 0.5])[0]


@wp.kernel
def _far_empty_range_kernel(view: hlbvh_warp.BvhView, z: float, t_min: float, out: wp.array(dtype=wp.int32)):
    origin = wp.vec3(0.1, 0.2, z)
    direction = wp.vec3(0.0, 0.0, 1.0)
    out[0] = hlbvh_warp.bvh_closest_hit(view, origin, direction, t_min, 1.0e30, -1).prim
    out[1] = hlbvh_warp.bvh_occluded(view, origin, direction, t_min, 1.0e30, -1)


def test_user_kernel_empty_ranges_find_nothing_from_far(device):
    """In a kernel nothing can raise: t_min < 0, NaN or -inf is an empty range and finds nothing,
    from far as from near. Moving a far origin had turned such a t_min into 0 before the check."""
    bvh = hlbvh_warp.build(trimesh.creation.icosphere(subdivisions=2), device=device)
    out = wp.zeros(2, dtype=wp.int32, device=device)
    for z in (-3.0, -1e5):
        wp.launch(_far_empty_range_kernel, dim=1, inputs=[query.view(bvh), z, 0.0, out], device=device)
        assert out.numpy()[0] >= 0 and out.numpy()[1] == 1
        for low in (-1.0, float("nan"), float("-inf")):
            wp.launch(_far_empty_range_kernel, dim=1, inputs=[query.view(bvh), z, low, out], device=device)
            assert out.numpy().tolist() == [-1, 0], (z, low)
