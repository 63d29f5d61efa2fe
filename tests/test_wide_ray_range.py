"""Ray ranges on wide trees (k = 4, 8, 16): ``t_min`` and ``ignore_prim`` through `wide.intersect` and
the six-argument `bvh_wide_closest_hit`, against the binary tree's `query.intersect` of the same
arguments (the same watertight test, so the same t and triangle) and a float64 brute force."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from oracles import (assert_range_hits_match, crossings, crossings_prim, directions_off_surface, expected_range_hits,
                     nested_shells, random_rays)

import hlbvh_warp
from hlbvh_warp import query, wide

WIDTHS = [4, 8, 16]


@pytest.fixture
def scene():
    return nested_shells()


def trees(device, verts, faces, width):
    bvh = hlbvh_warp.build(verts, faces, device=device)
    return bvh, wide.collapse(bvh, width)


def assert_same_hits(got, expected):
    """The wide tree's ``(t, prim)`` are the binary tree's, bit for bit."""
    assert np.array_equal(got[1], expected[1]), f"{int((got[1] != expected[1]).sum())} rays name another triangle"
    assert np.array_equal(got[0], expected[0])


@pytest.mark.parametrize("width", WIDTHS)
def test_wide_range_is_the_binary_trees(device, rng, scene, width):
    """Per ray a near end and an ignored triangle (each chosen to change the answer for many rays),
    then one of each for every ray with a far end per ray: the binary tree's hits exactly, and the
    float64 brute force's where it is not ambiguous."""
    verts, faces = scene
    bvh, w = trees(device, verts, faces, width)
    o, d = random_rays(rng, verts, 400)
    first, second = crossings(verts, faces, o, d)
    # A quarter of the rays each: past the first crossing, ignoring it, both, neither.
    kind = np.arange(len(o)) % 4
    lows = np.where((kind % 2 == 1) & np.isfinite(second), 0.5 * (first + second), 0.0)
    ignore = np.where(kind >= 2, crossings_prim(verts, faces, o, d), -1)
    got = wide.intersect(w, o, d, t_min=lows, ignore_prim=ignore)
    assert_same_hits(got, query.intersect(bvh, o, d, t_min=lows, ignore_prim=ignore))
    best, prim_ref, ambiguous = expected_range_hits(verts, faces, o, d, lows, ignore)
    assert (prim_ref != crossings_prim(verts, faces, o, d)).sum() > 100
    assert_range_hits_match(*got, best, prim_ref, ambiguous)
    assert not ((got[1] == ignore) & (ignore >= 0)).any()
    # The counters come from the same walk.
    t, prim, stats = wide.intersect(w, o, d, t_min=lows, ignore_prim=ignore, stats=True)
    assert_same_hits((t, prim), got)
    assert (stats.prims_tested[prim >= 0] >= 1).all()
    # One near end and one ignored triangle for every ray, with a far end per ray.
    low = float(np.median(first[np.isfinite(first)]))
    skip = int(np.bincount(crossings_prim(verts, faces, o, d) + 1)[1:].argmax())  # the one most rays cross first
    highs = np.where(kind < 2, np.inf, low + rng.uniform(0.0, 1.0, len(o)))
    got = wide.intersect(w, o, d, t_max=highs, t_min=low, ignore_prim=skip)
    assert_same_hits(got, query.intersect(bvh, o, d, t_max=highs, t_min=low, ignore_prim=skip))
    assert_range_hits_match(*got, *expected_range_hits(verts, faces, o, d, low, skip, highs))
    # Compared in float64: t_min bounds the float32 t as the exact value it is.
    assert (got[0][got[1] >= 0].astype(np.float64) > low).all() and not (got[1] == skip).any()
    assert ((got[1] >= 0) & np.isfinite(highs)).sum() > 20 and ((got[1] < 0) & np.isfinite(highs)).sum() > 20


@pytest.mark.parametrize("width", WIDTHS)
def test_wide_secondary_rays_leave_their_surface(device, rng, scene, width):
    """Rays from the hit points of camera rays, each ignoring the triangle it starts on: never
    that triangle, the binary tree's answer, the float64 one away from the start point."""
    verts, faces = scene
    bvh, w = trees(device, verts, faces, width)
    o, d = random_rays(rng, verts, 400)
    t, prim = wide.intersect(w, o, d)
    keep = prim >= 0
    points = (o[keep] + t[keep, None] * d[keep]).astype(np.float32)
    dirs = directions_off_surface(rng, verts, faces, prim[keep])
    ignore = prim[keep]
    got = wide.intersect(w, points, dirs, ignore_prim=ignore)
    assert not (got[1] == ignore).any()
    assert_same_hits(got, query.intersect(bvh, points, dirs, ignore_prim=ignore))
    best, prim_ref, ambiguous = expected_range_hits(verts, faces, points, dirs, 0.0, ignore)
    # A neighbour sharing the edge or vertex the point lies near is crossed at t near 0: ambiguous.
    ambiguous |= best < 1e-3
    assert_range_hits_match(*got, best, prim_ref, ambiguous)


@pytest.mark.parametrize("width", WIDTHS)
def test_wide_boxes_behind_t_min_are_not_entered(device, rng, scene, width):
    """Rays along +x through both shells to the box beside them, starting their range past the
    outer shell (x = 1.2, the box begins at x = 1.35): the walk enters no box that ends before
    t_min, so it tests the triangles of the box's near face (two, whose boxes are that face) and
    at most those of its far face, where boxes entered from 0 would add the triangles of the four
    shell crossings."""
    verts, faces = scene
    bvh, w = trees(device, verts, faces, width)
    n = 64
    o = np.column_stack([np.full(n, -3.0), rng.uniform(-0.2, 0.2, (n, 2))]).astype(np.float32)
    d = np.tile(np.float32([1.0, 0.0, 0.0]), (n, 1))
    box_tris = np.flatnonzero(verts[faces].min(axis=1)[:, 0] > 1.2)
    t, prim, stats = wide.intersect(w, o, d, t_min=4.2, stats=True)
    assert np.isin(prim, box_tris).all() and np.allclose(t, 4.35, rtol=1e-6)
    assert (stats.prims_tested <= 4).all(), stats.prims_tested.max()
    assert_same_hits((t, prim), query.intersect(bvh, o, d, t_min=4.2))
    # Past everything: not even the root is entered.
    t, prim, stats = wide.intersect(w, o, d, t_min=5.0, stats=True)
    assert (prim == -1).all() and (stats.nodes_visited == 0).all()


@wp.kernel
def _wide_range_user_kernel(
    view: wide.WideView,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    t_min: wp.array(dtype=float),
    t_max: wp.array(dtype=float),
    ignore: wp.array(dtype=wp.int32),
    out_t: wp.array(dtype=float),
    out_prim: wp.array(dtype=wp.int32),
):
    # What a user writes for a secondary ray: the range and the triangle it leaves from.
    i = wp.tid()
    h = wide.bvh_wide_closest_hit(view, origins[i], directions[i], t_min[i], t_max[i], ignore[i])
    out_t[i] = h.t
    out_prim[i] = h.prim


@pytest.mark.parametrize("width", WIDTHS)
def test_wide_user_kernel_range_overload(device, rng, scene, width):
    verts, faces = scene
    bvh, w = trees(device, verts, faces, width)
    o, d = random_rays(rng, verts, 300)
    first, _ = crossings(verts, faces, o, d)
    lows = np.where(np.isfinite(first) & (rng.random(len(o)) < 0.5), first * 1.2, 0.0).astype(np.float32)
    highs = np.where(rng.random(len(o)) < 0.25, lows + 0.5, np.inf).astype(np.float32)
    ignore = np.where(rng.random(len(o)) < 0.5, crossings_prim(verts, faces, o, d), -1).astype(np.int32)
    outs = [wp.empty(len(o), dtype=float, device=device), wp.empty(len(o), dtype=wp.int32, device=device)]
    wp.launch(_wide_range_user_kernel, dim=len(o), device=device,
              inputs=[wide.view(w)] + [wp.array(a, dtype=dt, device=device) for a, dt in
                                       ((o, wp.vec3), (d, wp.vec3), (lows, float), (highs, float),
                                        (ignore, wp.int32))] + outs)
    got = (outs[0].numpy(), outs[1].numpy())
    assert_same_hits(got, wide.intersect(w, o, d, t_max=highs, t_min=lows, ignore_prim=ignore))
    assert_same_hits(got, query.intersect(bvh, o, d, t_max=highs, t_min=lows, ignore_prim=ignore))
    assert not ((got[1] == ignore) & (ignore >= 0)).any()
    best, prim_ref, ambiguous = expected_range_hits(verts, faces, o, d, lows, ignore, highs)
    assert_range_hits_match(*got, best, prim_ref, ambiguous)


def _plane_at_z1(device):
    verts = np.array([[-1, -1, 1], [3, -1, 1], [-1, 3, 1]], np.float32)
    return hlbvh_warp.build(verts, np.array([[0, 1, 2]], np.int32), device=device)


@pytest.mark.parametrize("width", WIDTHS)
def test_wide_t_min_bounds_exactly(device, width):
    """As on the binary tree: the range is open at t_min, rounded down to float32, and in the
    caller's units for a tiny direction the walk scales."""
    w = wide.collapse(_plane_at_z1(device), width)
    o, d = np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32)
    cases = {0.0: True, 1.0 - 1e-12: True, float(np.nextafter(1.0, 0.0)): True, 1.0: False, 1.0 + 1e-12: False,
             float("inf"): False}
    for low, hit in cases.items():
        t, prim = wide.intersect(w, o, d, t_min=low)
        assert (prim[0] == 0) == hit, low
        assert t[0] == (1.0 if hit else np.inf)
    assert wide.intersect(w, np.zeros((2, 3)), [0, 0, 1], t_min=[0.5, 2.0], t_max=[2.0, 0.5])[1].tolist() == [0, -1]
    assert wide.intersect(w, o, d, ignore_prim=0)[1][0] == -1
    tiny = np.array([[0, 0, 1e-30]], np.float32)
    assert wide.intersect(w, o, tiny, t_min=0.5e30)[1][0] == 0
    assert wide.intersect(w, o, tiny, t_min=2e30)[1][0] == -1


def test_wide_ray_range_errors_are_the_binary_trees(device):
    """`wide.intersect` checks a range as `query.intersect` does (the same host checks): the same
    ValueError, word for word."""
    bvh = _plane_at_z1(device)
    w = wide.collapse(bvh, 4)
    o, d = np.zeros((2, 3), np.float32), np.array([[0, 0, 1]] * 2, np.float32)
    bad = [{"t_min": -1.0}, {"t_min": [0.0, np.nan]}, {"t_min": np.zeros(3)}, {"t_min": "near"},
           {"ignore_prim": 1}, {"ignore_prim": [-2, 0]}, {"ignore_prim": np.array([0.0, 0.0])},
           {"ignore_prim": np.array([True, False])}, {"ignore_prim": np.zeros(3, np.int32)},
           {"t_max": [1.0, 2.0, 3.0], "t_min": 0.5}]
    for kwargs in bad:
        with pytest.raises(ValueError) as binary:
            query.intersect(bvh, o, d, **kwargs)
        with pytest.raises(ValueError) as wide_error:
            wide.intersect(w, o, d, **kwargs)
        assert str(wide_error.value) == str(binary.value), kwargs
    # A Warp array of indices is read like a NumPy one.
    ignore = wp.array([0, -1], dtype=wp.int32, device=device)
    assert wide.intersect(w, o, d, ignore_prim=ignore)[1].tolist() == [-1, 0]
