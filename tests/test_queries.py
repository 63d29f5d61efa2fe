"""Batched queries (intersect, occluded, intersect_all, query_aabb) and queries from user kernels."""

from __future__ import annotations

import importlib.util

import warnings

import numpy as np
import pytest
import trimesh
import warp as wp
from conftest import REPO_ROOT, TEST_KERNEL_OPTIONS
from oracles import (assert_hits_match, brute_force_closest_hit, brute_overlaps, numpy_all_hits, random_rays,
                     random_soup)

import hlbvh_warp
from hlbvh_warp import query, wide
from hlbvh_warp.builder import Builder
from hlbvh_warp.config import BuildConfig
from hlbvh_warp.kernels import traversal

wp.set_module_options(TEST_KERNEL_OPTIONS)  # quick CPU compiles of this file's kernels (conftest)


@pytest.fixture
def scene(rng):
    mesh = trimesh.creation.icosphere(subdivisions=3)
    mesh = trimesh.util.concatenate([mesh, trimesh.creation.box(extents=(0.5, 0.5, 0.5)).apply_translation((2, 0, 0))])
    return np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)


def test_intersect_barycentrics_and_stats(device, rng, scene):
    verts, faces = scene
    bvh = hlbvh_warp.build(verts, faces, device=device)
    o, d = random_rays(rng, verts, 500)
    t, prim, u, v, stats = query.intersect(bvh, o, d, return_barycentrics=True, stats=True)
    t_ref, prim_ref = brute_force_closest_hit(verts, faces, o, d)
    assert_hits_match(t, prim, t_ref, prim_ref)
    hit = prim >= 0
    tri = verts[faces[prim[hit]]].astype(np.float64)
    on_tri = (1 - u[hit] - v[hit])[:, None] * tri[:, 0] + u[hit, None] * tri[:, 1] + v[hit, None] * tri[:, 2]
    on_ray = o[hit] + t[hit, None] * d[hit]
    assert np.allclose(on_tri, on_ray, atol=1e-5)
    assert (u[hit] >= 0).all() and (v[hit] >= 0).all() and (u[hit] + v[hit] <= 1 + 1e-6).all()
    # Statistics: every ray that enters the root visits it; hits tested at least one triangle.
    assert stats.nodes_visited.shape == (500,) and (stats.prims_tested[hit] >= 1).all()
    assert stats.measured_cost(1.2, 1.0) == pytest.approx(1.2 * stats.nodes_visited.mean() + stats.prims_tested.mean())
    # The old two-value call still works, and t_max cuts hits.
    t2, prim2 = query.intersect(bvh, o, d, t_max=float(np.median(t[hit])))
    assert ((prim2 >= 0) == (hit & (t < np.median(t[hit])))).all()


def test_axis_parallel_rays_from_slab_faces(device):
    """Directions with zero components, origins exactly on box faces: no 0 * inf = NaN misses."""
    mesh = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    bvh = hlbvh_warp.build(mesh, device=device)
    v = np.asarray(mesh.vertices, np.float32)
    o, d = [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            for p in v:
                direction = np.zeros(3, np.float32)
                direction[axis] = sign
                o.append(p - 3 * direction)  # through a corner, along an edge of the box
                d.append(direction)
            # Along the box's face plane, through its middle.
            origin = np.zeros(3, np.float32)
            origin[(axis + 1) % 3] = 1.0
            origin[axis] = -3.0 * sign
            direction = np.zeros(3, np.float32)
            direction[axis] = sign
            o.append(origin)
            d.append(direction)
    t, prim = query.intersect(bvh, np.array(o), np.array(d))
    t_ref, prim_ref = brute_force_closest_hit(v, mesh.faces, np.array(o), np.array(d))
    # Corner rays hit the box (the triangles perpendicular to the ray at the corner).
    corner = np.ones(len(o), bool)
    corner[8::9] = False
    assert (prim[corner] >= 0).all()
    assert np.allclose(t[corner], t_ref[corner])
    assert np.isfinite(t[prim >= 0]).all()
    assert ((prim >= 0) | (prim_ref < 0)).all()


def test_occluded_matches_closest_hit(device, rng, scene):
    verts, faces = scene
    bvh = hlbvh_warp.build(verts, faces, device=device)
    o, d = random_rays(rng, verts, 400)
    t, prim = query.intersect(bvh, o, d)
    t_max = rng.uniform(0.0, 6.0, 400).astype(np.float32)
    occ, stats = query.occluded(bvh, o, d, t_max=t_max, stats=True)
    expected = (prim >= 0) & (t < t_max)
    near_boundary = np.isclose(t, t_max, rtol=1e-5)
    assert np.array_equal(occ[~near_boundary], expected[~near_boundary])
    assert np.array_equal(query.occluded(bvh, o, d), prim >= 0)
    # Any-hit stops at the first triangle: never more work than the closest hit.
    _, _, closest_stats = query.intersect(bvh, o, d, stats=True)
    assert stats.prims_tested.sum() <= closest_stats.prims_tested.sum()


def test_intersect_all_lists_every_crossing(device, rng, scene):
    verts, faces = scene
    bvh = hlbvh_warp.build(verts, faces, device=device)
    o, d = random_rays(rng, verts, 200)
    ray_id, prim, t = query.intersect_all(bvh, o, d)
    # Closed meshes: every ray that hits crosses an even number of times (edge hits aside).
    _, first = query.intersect(bvh, o, d)
    assert set(np.unique(ray_id)) == set(np.nonzero(first >= 0)[0])
    for r in np.unique(ray_id)[:50]:
        sel = ray_id == r
        assert prim[sel][0] == first[r] or np.isclose(t[sel][0], query.intersect(bvh, o[r], d[r])[0][0])
        assert (np.diff(t[sel]) >= 0).all()


@pytest.mark.parametrize("method", ["hlbvh", "lbvh"])
def test_query_aabb_on_boxes_and_meshes(device, rng, method):
    lo = rng.random((2000, 3)).astype(np.float32)
    hi = lo + rng.random((2000, 3)).astype(np.float32) * 0.05
    bvh = hlbvh_warp.build_from_bounds(lo, hi, device=device, method=method)
    q_lo = rng.random((300, 3)).astype(np.float32)
    q_hi = q_lo + 0.1
    q_hi[0] = q_lo[0] - 1.0  # inverted: overlaps nothing
    q_lo[1], q_hi[1] = -np.inf, np.inf  # everything
    counts, pairs = query.query_aabb(bvh, q_lo, q_hi, return_pairs=True)
    ref = brute_overlaps(lo, hi, q_lo, q_hi)
    assert np.array_equal(counts, ref.sum(1))
    assert np.array_equal(pairs, np.argwhere(ref))
    assert counts[0] == 0 and counts[1] == 2000
    assert np.array_equal(query.query_aabb(bvh, q_lo, q_hi), counts)
    with pytest.raises(ValueError):
        query.intersect(bvh, q_lo, q_hi)


@wp.kernel
def _user_queries_kernel(
    bvh: query.BvhView,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    box_lowers: wp.array(dtype=wp.vec3),
    box_uppers: wp.array(dtype=wp.vec3),
    hit_t: wp.array(dtype=float),
    hit_prim: wp.array(dtype=int),
    occluded: wp.array(dtype=int),
    box_counts: wp.array(dtype=int),
    pairs: wp.array(dtype=wp.vec2i),
    pair_count: wp.array(dtype=wp.int32),
):
    tid = wp.tid()
    h = query.bvh_closest_hit(bvh, origins[tid], directions[tid], 1.0e30)
    hit_t[tid] = h.t
    hit_prim[tid] = h.prim
    occluded[tid] = query.bvh_occluded(bvh, origins[tid], directions[tid], 1.0e30)
    box_counts[tid] = query.bvh_aabb_count(bvh, box_lowers[tid], box_uppers[tid])
    query.bvh_aabb_pairs(bvh, box_lowers[tid], box_uppers[tid], tid, pairs, pair_count)


def test_queries_from_a_user_kernel(device, rng, scene):
    verts, faces = scene
    bvh = hlbvh_warp.build(verts, faces, device=device)
    o, d = random_rays(rng, verts, 300)
    q_lo = (verts[rng.integers(0, len(verts), 300)] - 0.05).astype(np.float32)
    q_hi = q_lo + 0.1
    n = len(o)
    out = [wp.zeros(n, dtype=float, device=device), wp.zeros(n, dtype=int, device=device),
           wp.zeros(n, dtype=int, device=device), wp.zeros(n, dtype=int, device=device)]
    pairs = wp.zeros(100_000, dtype=wp.vec2i, device=device)
    pair_count = wp.zeros(1, dtype=wp.int32, device=device)
    wp.launch(_user_queries_kernel, dim=n, device=device,
              inputs=[query.view(bvh)] + [wp.array(a, dtype=wp.vec3, device=device) for a in (o, d, q_lo, q_hi)]
              + out + [pairs, pair_count])
    t, prim = query.intersect(bvh, o, d)
    assert np.array_equal(out[1].numpy(), prim) and np.array_equal(out[0].numpy(), t)
    assert np.array_equal(out[2].numpy().astype(bool), prim >= 0)
    counts, ref_pairs = query.query_aabb(bvh, q_lo, q_hi, return_pairs=True)
    assert np.array_equal(out[3].numpy(), counts)
    total = int(pair_count.numpy()[0])
    assert total == counts.sum()
    got = pairs.numpy()[:total].astype(np.int64)
    assert np.array_equal(got[np.lexsort((got[:, 1], got[:, 0]))], ref_pairs)


@wp.kernel
def _closest_point_from_view_kernel(bvh: query.BvhView, points: wp.array(dtype=wp.vec3), prim: wp.array(dtype=int)):
    tid = wp.tid()
    prim[tid] = query.bvh_closest_point(bvh, points[tid], 1.0e30).prim


def test_triangle_queries_on_a_box_view_find_nothing(device, rng):
    """A box BVH's view has no triangles: from a user kernel, rays and closest points aimed right
    through its boxes find nothing (they once read its empty faces out of bounds), while its box
    queries still count against the brute force."""
    centers = rng.random((500, 3)).astype(np.float32)
    lo, hi = centers - 0.02, centers + 0.02
    bvh = hlbvh_warp.build_from_bounds(lo, hi, device=device)
    n = 64
    o = np.tile(np.array([[0.5, 0.5, -2.0]], np.float32), (n, 1))
    d = (centers[:n] - o).astype(np.float32)
    out = [wp.full(n, 7.0, dtype=float, device=device), wp.full(n, 7, dtype=int, device=device),
           wp.full(n, 7, dtype=int, device=device), wp.zeros(n, dtype=int, device=device)]
    pairs = wp.zeros(100_000, dtype=wp.vec2i, device=device)
    pair_count = wp.zeros(1, dtype=wp.int32, device=device)
    wp.launch(_user_queries_kernel, dim=n, device=device,
              inputs=[query.view(bvh)] + [wp.array(a, dtype=wp.vec3, device=device) for a in (o, d, lo[:n], hi[:n])]
              + out + [pairs, pair_count])
    assert (out[1].numpy() == -1).all() and np.isinf(out[0].numpy()).all() and (out[2].numpy() == 0).all()
    assert np.array_equal(out[3].numpy(), brute_overlaps(lo, hi, lo[:n], hi[:n]).sum(axis=1))
    prim = wp.full(n, 7, dtype=int, device=device)
    wp.launch(_closest_point_from_view_kernel, dim=n, device=device,
              inputs=[query.view(bvh), wp.array(centers[:n], dtype=wp.vec3, device=device), prim])
    assert (prim.numpy() == -1).all()


def test_example_user_kernel_runs_headless(device):
    path = REPO_ROOT / "examples" / "example_user_kernel.py"
    spec = importlib.util.spec_from_file_location("example_user_kernel", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    with wp.ScopedDevice(device):
        example = module.Example(resolution=24)
        for _ in range(2):
            example.step()
            example.render(None)
    image = example.image.numpy()
    assert np.isfinite(image).all() and image.max() > 0.5 and (example.crowding.numpy() > 0).any()
    # The second frame's shading, from the float64 brute force: camera rays, then shadow rays from
    # each hit point that leave out the triangle they start on (the example's `bvh_occluded` call).
    verts, faces = example.bvh.vertices.numpy(), example.bvh.faces.numpy()
    res, angle = 24, 0.5
    eye = example.center + np.array([0.0, 0.0, 2.5 * example.radius], np.float32)
    light = example.center + example.radius * np.array([2.0 * np.cos(angle), 2.0 * np.sin(angle), 2.0], np.float32)
    jj, ii = np.meshgrid(np.arange(res), np.arange(res))
    x = (2.0 * (jj.ravel() + 0.5) / res - 1.0) * 0.45
    y = (1.0 - 2.0 * (ii.ravel() + 0.5) / res) * 0.45
    d = np.stack([x, y, -np.ones_like(x)], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(eye.astype(np.float64), d.shape)
    hit, t, margin = numpy_all_hits(verts, faces, o, d, np.inf)
    t_first = np.where(hit, t, np.inf)
    prim = np.argmin(t_first, axis=1)
    seen = np.isfinite(t_first[np.arange(len(d)), prim])
    unclear = ((margin > -1e-5) & (margin < 1e-5)).any(axis=1)
    p = o[seen] + t_first[seen, prim[seen], None] * d[seen]
    tri = verts[faces[prim[seen]]].astype(np.float64)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n *= np.where((n * d[seen]).sum(1) > 0, -1.0, 1.0)[:, None]
    to_light = light - p
    dist = np.linalg.norm(to_light, axis=1)
    to_light /= dist[:, None]
    s_hit, s_t, s_margin = numpy_all_hits(verts, faces, p, to_light, np.inf)
    others = np.arange(len(faces))[None] != prim[seen, None]
    blocked = (s_hit & others & (s_t < dist[:, None])).any(axis=1)
    expected = np.full(len(d), 0.0)
    expected[seen] = 0.1 + 0.9 * (~blocked) * np.maximum((n * to_light).sum(1), 0.0)
    # A shadow ray grazing an edge, or meeting a neighbour near its start or a blocker near the light.
    unclear[seen] |= (others & s_hit & ((np.abs(s_margin) < 1e-5) | (s_t < 1e-3) | (np.abs(s_t - dist[:, None]) < 1e-3))
                      ).any(axis=1)
    clear = ~unclear
    assert clear.sum() > 0.9 * len(d) and (clear[seen] & blocked).sum() > 10 and (clear[seen] & ~blocked).sum() > 10
    np.testing.assert_allclose(image.ravel()[clear], expected[clear], atol=2e-3)


@wp.kernel
def _closest_hit_from_view_kernel(
    bvh: query.BvhView,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    hit_t: wp.array(dtype=float),
    hit_prim: wp.array(dtype=int),
):
    tid = wp.tid()
    h = query.bvh_closest_hit(bvh, origins[tid], directions[tid], 1.0e30)
    hit_t[tid] = h.t
    hit_prim[tid] = h.prim


def _trace_view(view, o, d, device):
    n = len(o)
    t, prim = wp.zeros(n, dtype=float, device=device), wp.zeros(n, dtype=int, device=device)
    wp.launch(_closest_hit_from_view_kernel, dim=n, device=device,
              inputs=[view, wp.array(o, dtype=wp.vec3, device=device), wp.array(d, dtype=wp.vec3, device=device),
                      t, prim])
    return t.numpy(), prim.numpy()


_CANONICAL_FIELDS = ("node_lowers", "node_uppers", "node_left", "node_right", "node_begin", "node_end", "prim_order",
                     "prim_lowers", "prim_uppers", "vertices", "faces")


@pytest.mark.parametrize("max_leaf_size", [1, 4])
def test_packed_layout_matches_the_canonical_walk(device, rng, scene, max_leaf_size):
    """The packed traversal layout and a hand-made view without it (canonical arrays) agree."""
    verts, faces = scene
    bvh = hlbvh_warp.build(verts, faces, device=device, config=BuildConfig(max_leaf_size=max_leaf_size))
    packed = query.view(bvh)
    assert packed.packed_nodes.shape[0] == len(faces) - 1
    canonical = query.BvhView()
    for name in _CANONICAL_FIELDS:
        setattr(canonical, name, getattr(packed, name))
    canonical.packed_nodes = wp.zeros(0, dtype=traversal.PackedNode, device=device)
    canonical.packed_triangles = wp.zeros(0, dtype=traversal.PackedTriangle, device=device)
    o, d = random_rays(rng, verts, 400)
    t, prim = _trace_view(packed, o, d, device)
    t_canonical, prim_canonical = _trace_view(canonical, o, d, device)
    t_ref, prim_ref = brute_force_closest_hit(verts, faces, o, d)
    assert_hits_match(t, prim, t_ref, prim_ref)
    assert_hits_match(t_canonical, prim_canonical, t_ref, prim_ref)
    assert_hits_match(t, prim, t_canonical, prim_canonical)


def test_single_triangle_root_leaf(device):
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    bvh = hlbvh_warp.build(verts, np.array([[0, 1, 2]], np.int32), device=device)
    o = np.array([[0.2, 0.2, 1.0], [0.8, 0.8, 1.0]], np.float32)
    d = np.array([[0, 0, -1], [0, 0, -1]], np.float32)
    t, prim = query.intersect(bvh, o, d)
    assert prim.tolist() == [0, -1] and t[0] == pytest.approx(1.0)


def test_view_stays_valid_after_refit_and_rebuild(device, rng, scene):
    """The packed layout is derived from boxes and vertices: refits and rebuilds refresh it in place."""
    verts, faces = scene
    builder = Builder(len(faces), device=device, resort=True)
    bvh = builder.build(verts, faces)
    view = query.view(bvh)
    o, d = random_rays(rng, verts, 300)
    frames = [verts, verts * np.float32(1.2) + np.float32(0.1)]
    wobble = verts + (0.05 * rng.standard_normal(verts.shape)).astype(np.float32)
    frames.append(wobble[:, [1, 2, 0]])
    for k, frame in enumerate(frames):
        if k == 1:
            builder.refit(frame)
        elif k == 2:
            builder.rebuild(frame)
        t, prim = _trace_view(view, o, d, device)
        t_ref, prim_ref = brute_force_closest_hit(frame, faces, o, d)
        assert_hits_match(t, prim, t_ref, prim_ref)
        assert (prim_ref >= 0).sum() > 50


@pytest.mark.parametrize("method, leaf", [("hlbvh", 1), ("sweep_sah", 4), ("sbvh", 1), ("hlbvh_sah", 3)])
def test_traversal_layout_per_node_equals_the_sweep(device, rng, method, leaf):
    """CUDA packs the layout with a thread per node (a climb for each node's depth-first position,
    then one record per interior node), the CPU in one sweep: the same records either way. Run
    both on this device, so that the CUDA way runs where no GPU is."""
    verts, faces = random_soup(rng, 400)
    bvh = hlbvh_warp.build(verts, faces, method=method, device=device, config=BuildConfig(max_leaf_size=leaf))
    layouts = []
    for per_node in (False, True):
        layout = query.TraversalLayout.__new__(query.TraversalLayout)
        layout.first_steps = wp.zeros(bvh.node_left.shape[0], dtype=wp.int32, device=device)
        layout.nodes = wp.zeros(max(bvh.num_refs - 1, 1), dtype=traversal.PackedNode, device=device)
        layout.triangles = wp.zeros(bvh.num_refs, dtype=traversal.PackedTriangle, device=device)
        layout.refresh(bvh, per_node=per_node)
        layouts.append(layout)
    sweep, per_node = (layout.nodes.numpy() for layout in layouts)
    assert sweep.dtype == per_node.dtype
    for field in sweep.dtype.names:
        np.testing.assert_array_equal(sweep[field], per_node[field], err_msg=field)
    interior = int((bvh.to_numpy()["node_left"] >= 0).sum())
    # Records were written at all: one per interior node (their positions are distinct, not dense).
    written = (sweep["upper_a"] - sweep["lower_a"]).sum(axis=1) > 0
    assert interior > 0 and written.sum() == interior


def test_tree_and_view_follow_a_second_build_of_the_builder(device, rng, scene):
    """A second `build` sets the builder up for another mesh of the same face count: the tree
    and views taken before it describe the new mesh (they reported the old mesh's distances
    with the new tree's face ids). After a set-up with another vertex count the tree does, and
    a view taken anew; the old view reads its old arrays, in bounds (its faces were the new
    ones, whose indices ran past the old vertex array)."""
    verts, faces = scene
    builder = Builder(len(faces), device=device)
    bvh = builder.build(verts, faces)
    view = query.view(bvh)
    o, d = random_rays(rng, verts, 300)
    query.intersect(bvh, o, d)  # the traversal layout exists before the second set-up
    moved = (verts[:, [2, 0, 1]] * np.float32(1.3) + np.float32(0.05)).astype(np.float32)
    shuffled = faces[rng.permutation(len(faces))]
    extra = np.concatenate([moved, moved[:7] + np.float32(9.0)])  # more vertices, same faces
    for frame_verts, frame_faces in ((moved, shuffled), (extra, faces)):
        old_view = view
        assert builder.build(frame_verts, frame_faces) is bvh
        if len(frame_verts) != len(verts):
            assert old_view.vertices.shape[0] == len(verts) and int(old_view.faces.numpy().max()) < len(verts)
            view = query.view(bvh)
        t_ref, prim_ref = brute_force_closest_hit(frame_verts, frame_faces, o, d)
        assert (prim_ref >= 0).sum() > 50
        assert_hits_match(*query.intersect(bvh, o, d), t_ref, prim_ref)
        assert_hits_match(*_trace_view(view, o, d, device), t_ref, prim_ref)


# ----------------------------------------------------------------- pinned by the mutation audit
def test_intersect_all_honours_t_max(device, rng, scene):
    verts, faces = scene
    bvh = hlbvh_warp.build(verts, faces, device=device)
    o, d = random_rays(rng, verts, 150)
    hit, t_ref, margin = numpy_all_hits(verts, faces, o, d, np.inf)
    t_max = float(np.median(t_ref[hit]))
    # Leave out crossings within float32 error of t_max or of a triangle's edge (the oracle is
    # not watertight): the rest must be listed exactly when t < t_max.
    near = (np.abs(t_ref - t_max) < 1e-4) | (margin < 1e-6)
    ray_id, prim, t = query.intersect_all(bvh, o, d, t_max=t_max)
    assert (t < t_max).all() and (t > 0).all()
    got = set(zip(ray_id.tolist(), prim.tolist()))
    expected = set(map(tuple, np.argwhere(hit & (t_ref < t_max) & ~near).tolist()))
    beyond = set(map(tuple, np.argwhere(hit & (t_ref > t_max) & ~near).tolist()))
    assert len(expected) > 50 and len(beyond) > 50
    assert expected <= got
    assert not (beyond & got)


def test_a_ray_starting_on_a_triangle_does_not_hit_it(device):
    """Hits need t > 0: a ray leaving a surface (a shadow or bounce ray) skips the triangle it
    starts on, and finds the next one (here the plane z = 1) at its true distance."""
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1]], np.float32)
    faces = np.array([[0, 1, 2], [3, 4, 5]], np.int32)
    bvh = hlbvh_warp.build(verts, faces, device=device)
    o = np.array([[0.25, 0.25, 0.0], [0.2, 0.1, 0.0], [0.25, 0.25, 0.0], [0.2, 0.2, 1.0]], np.float32)
    d = np.array([[0, 0, 1], [0.1, 0.1, 1], [0, 0, -1], [0, 0, 1]], np.float32)
    t, prim = query.intersect(bvh, o, d)
    assert prim.tolist() == [1, 1, -1, -1]
    assert t[:2] == pytest.approx([1.0, 1.0])
    assert query.occluded(bvh, o, d).tolist() == [True, True, False, False]
    ray_id, prim_all, _ = query.intersect_all(bvh, o, d)
    assert list(zip(ray_id.tolist(), prim_all.tolist())) == [(0, 1), (1, 1)]


def test_barycentrics_on_edges_and_vertices(device):
    """Rays exactly through an edge or a vertex take the exact float64 branch of the watertight
    test: the reported (u, v) must still weigh b and c, (1 - u - v) a + u b + v c the hit point."""
    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    bvh = hlbvh_warp.build(tri, np.array([[0, 1, 2]], np.int32), device=device)
    points = np.array([[0.25, 0.0], [0.0, 0.75], [0.25, 0.75], [0.5, 0.5], [1.0, 0.0], [0.0, 1.0], [0.0, 0.0]])
    o = np.column_stack([points, np.full(len(points), 2.0)]).astype(np.float32)
    for sign in (-1.0, 1.0):
        origins = o.copy()
        origins[:, 2] *= -sign
        d = np.tile(np.array([[0.0, 0.0, sign]], np.float32), (len(o), 1))
        t, prim, u, v = query.intersect(bvh, origins, d, return_barycentrics=True)
        assert (prim == 0).all() and t == pytest.approx(np.full(len(o), 2.0))
        # For this triangle the weights of b and c are the x and y of the hit point.
        np.testing.assert_allclose(u, points[:, 0], atol=1e-7)
        np.testing.assert_allclose(v, points[:, 1], atol=1e-7)


def _stacked_triangles(heights):
    base = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    verts = np.concatenate([base + np.float32([0, 0, z]) for z in heights])
    return verts, np.arange(len(verts), dtype=np.int32).reshape(-1, 3)


def test_closest_hit_skips_a_deferred_node_behind_its_hit(device):
    """Two leaves on one ray: front to back, the near leaf is entered first and its hit at t = 1
    drops the far leaf (entered at t = 2) unvisited: 2 nodes visited, 1 triangle tested
    (Wodniok & Goesele's n_s and n_t), whichever way the ray runs."""
    verts, faces = _stacked_triangles([1.0, 2.0])
    bvh = hlbvh_warp.build(verts, faces, device=device)
    assert bvh.num_nodes == 3
    for direction, first in ((1.0, 0), (-1.0, 1)):
        o = np.array([[0.2, 0.2, 1.5 - 1.5 * direction]], np.float32)
        t, prim, stats = query.intersect(bvh, o, np.array([[0, 0, direction]], np.float32), stats=True)
        assert prim.tolist() == [first] and t[0] == pytest.approx(1.0)
        assert stats.nodes_visited.tolist() == [2] and stats.prims_tested.tolist() == [1]


def _slab_entry(o, d, lo, hi):
    """Float64 entry distance of the ray into a box (inf for a miss)."""
    o, d = np.float64(o), np.float64(d)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (np.float64(lo) - o) / d, (np.float64(hi) - o) / d
    near = np.nanmax(np.minimum(t1, t2))
    far = np.nanmin(np.maximum(t1, t2))
    return max(near, 0.0) if near <= far else np.inf


def test_closest_hit_skips_a_deferred_node_hit_inside_the_near_box(device):
    """Tilted triangles: the hit lies strictly inside the near leaf's box, after its entry, so a
    walk that deferred the far child with the near child's entry distance would open the far leaf
    too. (A mutation audit found the flat case above blind to that: its hit is at the entry.)"""
    base = np.array([[0, 0, 0], [1, 0, 0.5], [0, 1, 0.5]], np.float32)
    verts = np.concatenate([base + np.float32([0, 0, z]) for z in (1.0, 3.0)])
    faces = np.arange(6, dtype=np.int32).reshape(-1, 3)
    bvh = hlbvh_warp.build(verts, faces, device=device)
    tri = verts[faces]
    for z0, direction in ((6.0, -1.0), (-2.0, 1.0)):
        o, d = np.float32([[0.2, 0.2, z0]]), np.float32([[0, 0, direction]])
        t_ref, prim_ref = brute_force_closest_hit(verts, faces, o, d)
        near, far = prim_ref[0], 1 - prim_ref[0]
        # The premise, in float64: entered the near box before its hit, the far box after it.
        assert _slab_entry(o[0], d[0], tri[near].min(0), tri[near].max(0)) < t_ref[0]
        assert _slab_entry(o[0], d[0], tri[far].min(0), tri[far].max(0)) > t_ref[0]
        t, prim, stats = query.intersect(bvh, o, d, stats=True)
        assert prim.tolist() == [near] and t[0] == pytest.approx(t_ref[0], rel=1e-6)
        assert stats.nodes_visited.tolist() == [2] and stats.prims_tested.tolist() == [1]


def _rays_at_a_cube_edge():
    """A unit cube's vertices and faces, and 30 rays each reaching a point of its edge x = 0,
    y = 1 at t = 1 exactly, tilted so that float32 distances to the two faces there round apart."""
    mesh = trimesh.creation.box(extents=(1, 1, 1))
    verts = (np.asarray(mesh.vertices) + 0.5).astype(np.float32)
    faces = np.asarray(mesh.faces, np.int32)
    o, d = [], []
    for dy in (41, 47, 55, 61, 82, 83, 94, 97, 107, 109):
        for z0 in (0.25, 0.5, 0.625):
            o.append([-3, 1 - dy, z0])
            d.append([3, dy, 0])  # reaches (0, 1, z0) at t = 1 exactly
    return verts, faces, np.float32(o), np.float32(d)


def test_rays_grazing_an_edge_of_a_box_mesh_hit_it(device):
    """Rays through the edge x = 0, y = 1 of a unit cube, tilted so the slab test's float32
    distances to the two faces meeting there round apart: the far-distance pad of Ize's robust
    slab test (traversal.FAR_PAD) keeps the box entered. Without it every one missed."""
    verts, faces, o, d = _rays_at_a_cube_edge()
    t_ref, prim_ref = brute_force_closest_hit(verts, faces, o, d)
    assert (prim_ref >= 0).all()
    for method in ("hlbvh", "sweep_sah"):
        bvh = hlbvh_warp.build(verts, faces, method=method, device=device)
        t, prim = query.intersect(bvh, o, d)
        assert (prim >= 0).all(), f"{method}: {(prim < 0).sum()} of {len(o)} grazing rays missed"
        np.testing.assert_allclose(t, t_ref, rtol=1e-5)
        assert query.occluded(bvh, o, d).all()


# A user kernel compiled as CUDA compiles by default (NVRTC's --fmad=true): free to fuse a product
# and a sum into one multiply-add. On the CPU, -ffp-contract=fast gives clang the same freedom.
@wp.kernel(module="unique", module_options={"cpu_compiler_flags": f"{wp.config.cpu_compiler_flags or ''} "
                                                                  "-ffp-contract=fast"})
def _fused_closest_hit_kernel(bvh: query.BvhView, origins: wp.array(dtype=wp.vec3),
                              directions: wp.array(dtype=wp.vec3), prims: wp.array(dtype=wp.int32)):
    i = wp.tid()
    prims[i] = query.bvh_closest_hit(bvh, origins[i], directions[i], wp.inf).prim


def test_rays_through_shared_edges_stay_watertight_where_multiply_adds_fuse(device):
    """Rays from inside a closed sphere, each aimed at a point of one of its edges, must all hit
    (Woop et al. 2013: one of the two triangles there). The two triangles compute that edge's
    function as exact negatives of each other only while neither product is fused into a
    multiply-add; fused, 538 of 200k such rays escaped through the edges (CUDA's default, and
    the CPU with contraction allowed)."""
    mesh = trimesh.creation.icosphere(subdivisions=4)
    verts, faces = np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)
    bvh = hlbvh_warp.build(verts, faces, device=device)
    rng = np.random.default_rng(0)
    count = 50_000
    edges = mesh.edges_unique[rng.integers(0, len(mesh.edges_unique), count)]
    s = rng.random((count, 1)).astype(np.float32)
    target = verts[edges[:, 0]] * (1 - s) + verts[edges[:, 1]] * s
    o = (rng.normal(size=(count, 3)) * 0.2).astype(np.float32)
    d = (target - o).astype(np.float32)
    prims = wp.empty(count, dtype=wp.int32, device=device)
    wp.launch(_fused_closest_hit_kernel, dim=count, device=device,
              inputs=[query.view(bvh), wp.array(o, dtype=wp.vec3, device=device),
                      wp.array(d, dtype=wp.vec3, device=device), prims])
    escaped = int((prims.numpy() < 0).sum())
    assert escaped == 0, f"{escaped} of {count} rays escaped the closed sphere through its edges"
    assert (query.intersect(bvh, o, d)[1] >= 0).all()


def test_rays_aimed_at_a_silhouette_edge_hit_it_where_multiply_adds_fuse(device):
    """Rays aimed exactly at points of a cube's edge x = 0, y = 1 (the grazing rays above) must hit
    it. The shear of Woop et al. 2013 gives such a point a zero edge function only while
    ``sx * p[kz]`` is rounded before it is subtracted: rounded, it gives ``p[kx]`` back exactly;
    fused into a multiply-add (CUDA's default, and the CPU with contraction allowed), the
    difference keeps the rounding error of ``sx`` and 21 of the 30 rays missed the cube."""
    verts, faces, o, d = _rays_at_a_cube_edge()
    bvh = hlbvh_warp.build(verts, faces, device=device)
    prims = wp.empty(len(o), dtype=wp.int32, device=device)
    wp.launch(_fused_closest_hit_kernel, dim=len(o), device=device,
              inputs=[query.view(bvh), wp.array(o, dtype=wp.vec3, device=device),
                      wp.array(d, dtype=wp.vec3, device=device), prims])
    missed = int((prims.numpy() < 0).sum())
    assert missed == 0, f"{missed} of {len(o)} rays aimed at the cube's edge missed it"


def test_any_hit_stops_at_the_first_hit_in_a_leaf(device):
    """Four triangles on one ray in one leaf: the any-hit query stops at the first one it finds,
    the closest-hit query tests all four."""
    verts, faces = _stacked_triangles([1.0, 2.0, 3.0, 4.0])
    bvh = hlbvh_warp.build(verts, faces, device=device, config=BuildConfig(max_leaf_size=4))
    assert bvh.num_nodes == 1
    o, d = np.array([[0.2, 0.2, 0.0]], np.float32), np.array([[0, 0, 1]], np.float32)
    occ, any_stats = query.occluded(bvh, o, d, stats=True)
    _, prim, closest_stats = query.intersect(bvh, o, d, stats=True)
    assert occ.tolist() == [True] and prim.tolist() == [0]
    assert any_stats.prims_tested.tolist() == [1] and closest_stats.prims_tested.tolist() == [4]


@wp.kernel
def _box_count_kernel(bvh: query.BvhView, lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3),
                      counts: wp.array(dtype=int)):
    tid = wp.tid()
    counts[tid] = query.bvh_aabb_count(bvh, lowers[tid], uppers[tid])


def _assert_box_queries(bvh, q_lo, q_hi, ref, device):
    """`query_aabb` (counts and pairs) and `bvh_aabb_count` in a user kernel against the
    reference overlaps ``ref`` (queries x primitives)."""
    counts, pairs = query.query_aabb(bvh, q_lo, q_hi, return_pairs=True)
    assert np.array_equal(counts, ref.sum(1))
    assert np.array_equal(pairs, np.argwhere(ref))
    out = wp.zeros(len(q_lo), dtype=int, device=device)
    wp.launch(_box_count_kernel, dim=len(q_lo), device=device,
              inputs=[query.view(bvh), wp.array(q_lo, dtype=wp.vec3, device=device),
                      wp.array(q_hi, dtype=wp.vec3, device=device), out])
    assert np.array_equal(out.numpy(), ref.sum(1))


@pytest.mark.parametrize("max_leaf_size", [1, 4])
def test_box_queries_count_touching_boxes(device, rng, max_leaf_size):
    """Closed boxes: a query that only touches a box (a shared face, edge or corner, from below
    or from above) overlaps it, in `query_aabb` and in `bvh_aabb_count` from a user kernel, at
    one primitive per leaf and at several (where a leaf's box is not its primitives' boxes)."""
    cells = np.stack(np.meshgrid(np.arange(5), np.arange(5), np.arange(5), indexing="ij"), -1).reshape(-1, 3)
    lo = cells.astype(np.float32)
    hi = lo + np.float32(0.5)  # gaps between the boxes: integer corners touch from below, .5 from above
    bvh = hlbvh_warp.build_from_bounds(lo, hi, device=device, config=BuildConfig(max_leaf_size=max_leaf_size))
    q_lo = rng.integers(-1, 5, (300, 3)).astype(np.float32) + rng.choice([0.5, 1.0], (300, 3)).astype(np.float32)
    q_hi = q_lo + rng.integers(0, 3, (300, 3)).astype(np.float32) * np.float32(0.5)
    ref = brute_overlaps(lo, hi, q_lo, q_hi)
    # Many queries meet their boxes only on a boundary.
    inner = ((lo[None] < q_hi[:, None]) & (hi[None] > q_lo[:, None])).all(-1)
    assert (ref & ~inner).sum() > 100
    _assert_box_queries(bvh, q_lo, q_hi, ref, device)


@pytest.mark.parametrize("boxes_only", [False, True])
def test_an_inverted_query_box_overlaps_nothing(device, boxes_only):
    """A query box with lowers > uppers on one axis is empty (query_aabb's contract): it overlaps
    nothing, even where its bounds both lie inside a primitive's box on that axis. The closed-box
    test compared each query bound only with the other box's opposite bound, so a box inverted by
    less than a primitive's width met it: a triangle spanning x in [0, 1] overlapped x in [0.5, 0.4]."""
    verts = np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1], [2, 2, 2], [3, 2, 2],
                        [2, 3, 3]])
    faces = np.int32([[0, 1, 2], [3, 4, 5], [6, 7, 8]])
    tri = verts[faces]
    if boxes_only:
        bvh = hlbvh_warp.build_from_bounds(tri.min(1), tri.max(1), device=device)
    else:
        bvh = hlbvh_warp.build(verts, faces, device=device)
    q_lo = np.float32([[0.5, 0.2, -1.0], [-1.0, 0.5, -1.0], [-1.0, -1.0, 0.7], [0.1, 0.1, -0.1], [2.5, 2.5, 2.5]])
    q_hi = np.float32([[0.4, 0.3, 2.0], [2.0, 0.4, 2.0], [2.0, 2.0, 0.6], [0.2, 0.2, 0.1], [2.4, 2.6, 2.6]])
    ref = brute_overlaps(tri.min(1), tri.max(1), q_lo, q_hi) & (q_lo <= q_hi).all(-1)[:, None]
    assert ref.sum(1).tolist() == [0, 0, 0, 1, 0]  # every box but the fourth is inverted on one axis
    _assert_box_queries(bvh, q_lo, q_hi, ref, device)


def test_occluded_takes_one_t_max_for_every_ray(device):
    verts, faces = _stacked_triangles([1.0, 2.0])
    bvh = hlbvh_warp.build(verts, faces, device=device)
    o = np.tile(np.float32([[0.2, 0.2, 0.0]]), (3, 1))
    d = np.float32([[0, 0, 1], [0, 0, 2], [0, 0, 0.5]])  # hits at t = 1, 0.5 and 2
    assert query.occluded(bvh, o, d, t_max=1.5).tolist() == [True, True, False]
    assert query.occluded(bvh, o, d, t_max=np.float32(0.75)).tolist() == [False, True, False]
    assert query.occluded(bvh, o, d, t_max=np.array(2.5)).tolist() == [True, True, True]


def test_per_ray_t_max_and_one_origin_for_every_ray(device, rng, scene):
    """``t_max`` one per ray in `intersect` and `intersect_all` (as `occluded` took it), and one
    origin or one direction for a batch, against the float64 brute force."""
    verts, faces = scene
    bvh = hlbvh_warp.build(verts, faces, device=device)
    o, d = random_rays(rng, verts, 300)
    t_ref, prim_ref = brute_force_closest_hit(verts, faces, o, d)
    hit = prim_ref >= 0
    # Half the rays stop just short of their hit, half just past it; misses get any limit.
    limits = np.where(rng.random(300) < 0.5, 0.99, 1.01) * np.where(hit, t_ref, 1.0)
    t, prim = query.intersect(bvh, o, d, t_max=limits)
    short = hit & (limits < t_ref)
    assert short.sum() > 50 and (hit & ~short).sum() > 50
    # Cut short: the nearest hit before the limit, if any (another triangle of the scene).
    t_cut, prim_cut = brute_force_closest_hit(verts, faces, o[short], d[short], t_max=limits[short])
    assert_hits_match(t[short], prim[short], t_cut, prim_cut)
    assert_hits_match(t[~short], prim[~short], t_ref[~short], prim_ref[~short])
    # The same limits through the details kernel (barycentrics) and the all-hits walk.
    t2, prim2, _, _ = query.intersect(bvh, o, d, t_max=wp.array(limits, dtype=float, device=device),
                                      return_barycentrics=True)
    assert np.array_equal(prim2, prim) and np.array_equal(t2, t)
    ray_id, all_prim, all_t = query.intersect_all(bvh, o, d, t_max=limits)
    assert (all_t < limits[ray_id]).all()
    closest = np.full(300, np.inf, np.float32)
    np.minimum.at(closest, ray_id, all_t)
    np.testing.assert_array_equal(closest, t)
    # One origin for many directions (a camera), one direction for many origins (a light).
    eye = np.float32([0.1, 0.2, -4.0])
    t_eye, p_eye = query.intersect(bvh, eye, d)
    assert_hits_match(t_eye, p_eye, *brute_force_closest_hit(verts, faces, np.tile(eye, (300, 1)), d))
    assert np.array_equal(query.occluded(bvh, o, d[:1]), query.occluded(bvh, o, np.tile(d[:1], (300, 1))))
    # One limit in any form float() takes, a one-element array included, is every ray's.
    ts = np.sort(t_ref[hit])
    cut = float(0.5 * (ts[len(ts) // 2 - 1] + ts[len(ts) // 2]))  # between two hits: no ray ties it
    assert ts[len(ts) // 2] - ts[len(ts) // 2 - 1] > 1e-5 * cut
    t_one, prim_one = query.intersect(bvh, o, d, t_max=cut)
    assert_hits_match(t_one, prim_one, *brute_force_closest_hit(verts, faces, o, d, t_max=cut))
    for same in (np.array([cut]), wp.array([cut], dtype=float, device=device), np.float64(cut)):
        assert np.array_equal(query.intersect(bvh, o, d, t_max=same)[1], prim_one)
        assert np.array_equal(query.occluded(bvh, o, d, t_max=same), prim_one >= 0)
    for unbounded in (10**40, "inf", np.inf, 1e39):
        assert np.array_equal(query.intersect(bvh, o, d, t_max=unbounded)[1], query.intersect(bvh, o, d)[1])
    # A NaN limit finds nothing for its ray only.
    nan_limits = np.where(np.arange(300) % 2 == 0, np.nan, np.inf)
    t_nan, prim_nan = query.intersect(bvh, o, d, t_max=nan_limits)
    assert (prim_nan[::2] == -1).all() and np.array_equal(prim_nan[1::2], query.intersect(bvh, o, d)[1][1::2])
    with pytest.raises(ValueError, match=r"t_max must be a number or have shape \(300,\)"):
        query.intersect(bvh, o, d, t_max=limits[:5])
    with pytest.raises(ValueError, match="t_max must be a number"):
        query.intersect_all(bvh, o, d, t_max="far")
    with pytest.raises(ValueError, match="t_max must hold real numbers"):
        query.occluded(bvh, o, d, t_max=np.full(300, "x"))


def test_empty_batches(device, scene):
    verts, faces = scene
    bvh = hlbvh_warp.build(verts, faces, device=device)
    none = np.zeros((0, 3), np.float32)
    t, prim = query.intersect(bvh, none, none)
    assert t.shape == prim.shape == (0,)
    assert query.occluded(bvh, none, none).shape == (0,)
    ray_id, prim_id, t = query.intersect_all(bvh, none, none)
    assert ray_id.shape == prim_id.shape == t.shape == (0,)
    counts, pairs = query.query_aabb(bvh, none, none, return_pairs=True)
    assert counts.shape == (0,) and pairs.shape == (0, 2)
    assert query.query_aabb(bvh, none, none).shape == (0,)
    # An empty list is an empty batch too, as an empty array is.
    point, dist, prim = hlbvh_warp.closest_point(bvh, [])
    assert point.shape == (0, 3) and dist.shape == prim.shape == (0,)
    t, prim = query.intersect(bvh, [], [])
    assert t.shape == prim.shape == (0,)
    # And so is an empty list of per-ray ranges and ignored triangles (NumPy reads it as float64).
    t, prim = query.intersect(bvh, none, none, t_min=[], t_max=[], ignore_prim=[])
    assert t.shape == prim.shape == (0,)
    assert query.occluded(bvh, none, none, ignore_prim=[]).shape == (0,)
    assert query.intersect_all(bvh, none, none, ignore_prim=[])[0].shape == (0,)
    with pytest.raises(ValueError, match="integer triangle indices"):
        query.intersect(bvh, np.zeros((1, 3)), np.ones((1, 3)), ignore_prim=[0.0])


def test_query_boxes_are_validated(device, scene):
    verts, faces = scene
    bvh = hlbvh_warp.build(verts, faces, device=device)
    lo = np.zeros((4, 3), np.float32)
    with pytest.raises(ValueError, match="differ in shape"):
        query.query_aabb(bvh, lo, np.ones((5, 3), np.float32))
    with pytest.raises(ValueError, match="real numbers"):
        query.query_aabb(bvh, lo.astype(np.complex64), lo + 1)
    with pytest.raises(ValueError, match="real numbers"):
        query.query_aabb(bvh, lo, np.ones((4, 3), bool))


def test_result_totals_past_int32_are_refused_before_any_write(device):
    # The offsets of query_aabb's pairs and intersect_all's hits were an int32 device scan: counts
    # summing past 2^31 wrapped, and the write pass would have written outside the output it sized.
    counts = wp.array(np.array([2**30, 2**30, 7], np.int32), dtype=wp.int32, device=device)
    with pytest.raises(ValueError, match="2147483655 overlapping pairs"):
        query._offsets(counts, "overlapping pairs")
    counts = wp.array(np.array([3, 0, 5, 2], np.int32), dtype=wp.int32, device=device)
    offsets, total = query._offsets(counts, "ray hits")
    assert total == 10 and offsets.numpy().tolist() == [0, 3, 3, 8]


# ----------------------------------------------------------------- pinned by the third mutation audit
def test_two_rays_each_with_its_own_t_max(device):
    # Per-ray limits on a batch of two: one limit per ray must reach the kernel that reads one
    # per ray, not the lean one-limit kernel (which took the first ray's limit for both).
    verts, faces = _stacked_triangles([1.0, 2.0])
    bvh = hlbvh_warp.build(verts, faces, device=device)
    o = np.float32([[0.2, 0.2, 0.0], [0.2, 0.2, 0.0]])
    d = np.float32([[0, 0, 1], [0, 0, 1]])  # both hit triangle 0 at t = 1 and triangle 1 at t = 2
    for limits in ([0.5, 1.5], [1.5, 0.5], [1.5, 2.5]):
        t_ref, prim_ref = brute_force_closest_hit(verts, faces, o, d, t_max=np.array(limits))
        t, prim = query.intersect(bvh, o, d, t_max=np.array(limits))
        assert prim.tolist() == prim_ref.tolist(), limits
        assert_hits_match(t, prim, t_ref, prim_ref)
        assert query.occluded(bvh, o, d, t_max=limits).tolist() == (prim_ref >= 0).tolist()
        ray_id, _, all_t = query.intersect_all(bvh, o, d, t_max=limits)
        assert np.bincount(ray_id, minlength=2).tolist() == [int((np.float32([1, 2]) < lim).sum()) for lim in limits]


@pytest.mark.parametrize("call", ["intersect", "occluded", "intersect_all"])
def test_t_max_shapes_and_dtypes(device, scene, call):
    verts, faces = scene
    bvh = hlbvh_warp.build(verts, faces, device=device)
    fn = getattr(query, call)
    o = np.tile(np.float32([[0.01, 0.02, -3.0]]), (4, 1))
    d = np.tile(np.float32([[0.0, 0.0, 1.0]]), (4, 1))  # each hits the sphere near t = 2
    # One number is a scalar or a one-element vector; a (1, 1) array or a (R, 2) array is neither.
    for bad in (np.array([[5.0]]), np.full((4, 2), 5.0), np.full((4, 1), 5.0)):
        with pytest.raises(ValueError, match=r"t_max must be a number or have shape \(4,\)"):
            fn(bvh, o, d, t_max=bad)
    # Booleans are no distances, per ray or not (True as a Python number is float(True) = 1).
    with pytest.raises(ValueError, match="t_max must hold real numbers, got dtype bool"):
        fn(bvh, o, d, t_max=np.array([True, True, False, True]))
    # Unsigned integers are real numbers like any other.
    unsigned = fn(bvh, o, d, t_max=np.array([1, 5, 1, 5], dtype=np.uint32))
    floats = fn(bvh, o, d, t_max=np.array([1.0, 5.0, 1.0, 5.0]))
    for a, b in zip(unsigned, floats):
        assert np.array_equal(a, b)
    hit = unsigned[1] >= 0 if call == "intersect" else (unsigned if call == "occluded" else None)
    if hit is not None:
        assert hit.tolist() == [False, True, False, True]
    # An empty batch checks its limit like any other.
    with pytest.raises(ValueError, match="t_max must be a number"):
        fn(bvh, [], [], t_max="far")
    with pytest.raises(ValueError, match=r"have shape \(0,\)"):
        fn(bvh, [], [], t_max=np.ones(3))


def test_huge_t_max_is_unbounded_without_a_warning(device, scene, rng):
    # A limit past float32's range rounds to inf, quietly: 1e39 is as unbounded as inf.
    verts, faces = scene
    bvh = hlbvh_warp.build(verts, faces, device=device)
    o, d = random_rays(rng, verts, 50)
    unbounded = query.intersect(bvh, o, d)[1]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for huge in (1e39, 10**40, np.float64(1e300), np.full(50, 1e39), [1e39]):
            assert np.array_equal(query.intersect(bvh, o, d, t_max=huge)[1], unbounded)
            assert np.array_equal(query.occluded(bvh, o, d, t_max=huge), unbounded >= 0)
            assert np.array_equal(np.unique(query.intersect_all(bvh, o, d, t_max=huge)[0]),
                                  np.flatnonzero(unbounded >= 0))


def test_query_coordinates_past_float32_are_infinite_without_a_warning(device, scene):
    """Float64 query coordinates past float32's range are read as the infinities they round to,
    quietly, as a huge t_max or max_dist is: a box bound of -+1e39 is unbounded, a ray or a point
    at 1e39 finds nothing (as one at inf does). The cast to float32 warned of an overflow."""
    verts, faces = scene
    bvh = hlbvh_warp.build(verts, faces, device=device)
    huge = np.array([[-1e39, -1e39, -1e39], [-np.inf, -np.inf, -np.inf]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert query.query_aabb(bvh, huge, -huge).tolist() == [len(faces), len(faces)]
        t, prim = query.intersect(bvh, np.array([[1e39, 0.0, 0.0], [5.0, 0.0, 0.0]]), np.array([-1.0, 0.0, 0.0]))
        assert prim[0] == -1 and prim[1] >= 0
        assert query.occluded(bvh, np.array([[0.0, 0.0, 0.0]]), np.array([[1e39, 1.0, 0.0]])).tolist() == [False]
        assert query.closest_point(bvh, np.array([[0.0, 1e39, 0.0], [0.0, 0.0, 0.0]]))[2][0] == -1


def test_a_ray_with_no_t_range_walks_nothing(device, scene):
    # t_max 0, negative or NaN: no t in (0, t_max), so the ray misses without entering the tree.
    verts, faces = scene
    bvh = hlbvh_warp.build(verts, faces, device=device)
    o = np.zeros((3, 3), np.float32)  # inside the sphere: the root box contains every origin
    d = np.float32([[0, 0, 1], [1, 0, 0], [0, -1, 0]])
    for limit in (0.0, -1.0, np.nan, np.float32([0.0, -0.0, np.nan])):
        t, prim, stats = query.intersect(bvh, o, d, t_max=limit, stats=True)
        assert (prim == -1).all() and np.isinf(t).all()
        assert stats.nodes_visited.tolist() == [0, 0, 0] and stats.prims_tested.tolist() == [0, 0, 0]
        occluded, stats = query.occluded(bvh, o, d, t_max=limit, stats=True)
        assert not occluded.any() and stats.nodes_visited.tolist() == [0, 0, 0]
        assert len(query.intersect_all(bvh, o, d, t_max=limit)[0]) == 0
    assert (query.intersect(bvh, o, d)[1] >= 0).all()  # the same rays hit with a range


def test_one_origin_or_direction_with_an_empty_batch(device, scene):
    verts, faces = scene
    bvh = hlbvh_warp.build(verts, faces, device=device)
    eye, none = np.float32([0.1, 0.2, -4.0]), np.zeros((0, 3), np.float32)
    # One origin (or one direction) for no rays: an empty batch, as for many rays.
    for o, d in ((eye, none), (none, eye), ([eye], none)):
        t, prim = query.intersect(bvh, o, d)
        assert t.shape == prim.shape == (0,)
        assert query.occluded(bvh, o, d).shape == (0,)
        assert len(query.intersect_all(bvh, o, d)[0]) == 0
    # No rows against several is a shape mismatch, not a broadcast.
    for o, d in ((none, np.ones((5, 3))), (np.ones((5, 3)), none)):
        with pytest.raises(ValueError, match="origins and directions differ in shape"):
            query.intersect(bvh, o, d)


def test_an_empty_batch_of_the_wrong_width_is_a_shape_error(device, scene):
    # Only an empty list (shape (0,)) is read as no rows of three: (0, 2) is the caller's mistake.
    verts, faces = scene
    bvh = hlbvh_warp.build(verts, faces, device=device)
    for bad in (np.zeros((0, 2)), np.zeros((0, 4)), np.zeros((2, 0))):
        with pytest.raises(ValueError, match=r"origins must have shape \(n, 3\)"):
            query.intersect(bvh, bad, bad)
        with pytest.raises(ValueError, match=r"points must have shape \(n, 3\)"):
            query.closest_point(bvh, bad)
        with pytest.raises(ValueError, match=r"lowers must have shape \(n, 3\)"):
            query.query_aabb(bvh, bad, bad)


@pytest.mark.parametrize("method", ["hlbvh", "sweep_sah", "sbvh"])
def test_rays_through_collinear_triangles_miss_them(device, rng, method):
    """Three distinct, exactly collinear vertices make a triangle of zero area, which has no
    surface for a ray to hit (the float64 oracle's determinant is exactly zero). Sheared in
    float32, their edge functions could stay tiny and of one sign, and rays aimed at the segment
    reported a hit with meaningless weights (every ray of this test, before the exact area check).
    A proper triangle beside them is still hit where the oracle hits it, by every ray query."""
    steps = rng.integers(1, 64, size=(40, 3)).astype(np.float32)
    starts = rng.integers(-64, 64, size=(40, 3)).astype(np.float32)
    # a, a + s, a + 3s: integers, so exactly collinear in float32.
    verts = np.concatenate([starts, starts + steps, starts + 3 * steps,
                            np.float32([[-200, -200, 300], [200, -200, 300], [0, 200, 300]])])
    n = len(starts)
    faces = np.concatenate([np.stack([np.arange(n), np.arange(n) + n, np.arange(n) + 2 * n], axis=1),
                            [[3 * n, 3 * n + 1, 3 * n + 2]]]).astype(np.int32)
    targets = starts + steps * rng.uniform(0.2, 2.8, size=(n, 1)).astype(np.float32)
    origins = (targets + rng.normal(scale=50.0, size=(n, 3))).astype(np.float32)
    directions = targets - origins
    # Half the rays go on to the proper triangle at z = 300 (those aimed upwards meet it).
    bvh = hlbvh_warp.build(verts, faces, method=method, device=device)
    t, prim = query.intersect(bvh, origins, directions)
    t_ref, prim_ref = brute_force_closest_hit(verts, faces, origins, directions)
    assert set(prim_ref.tolist()) <= {-1, n}  # the oracle hits no collinear triangle
    assert_hits_match(t, prim, t_ref, prim_ref)
    assert np.array_equal(query.occluded(bvh, origins, directions), prim_ref >= 0)
    rays, hit_prims = query.intersect_all(bvh, origins, directions)[:2]
    assert set(hit_prims.tolist()) <= {n}
    assert sorted(rays[hit_prims == n].tolist()) == np.flatnonzero(prim_ref == n).tolist()
    w = wide.collapse(bvh, 4)
    assert np.array_equal(wide.intersect(w, origins, directions)[1], prim)


def test_t_max_just_above_a_hit_keeps_it(device):
    """Hits count for t < t_max. A float32 t is below t_max exactly when it is below the float32
    at or above t_max: rounded to nearest, t_max = 1 + 1e-12 became 1.0 and dropped the hit at
    t = 1 from every ray query. A t_max of exactly 1 still excludes it (an open bound), and an
    integer past float64's range is unbounded, not an OverflowError."""
    verts = np.float32([[-1, -1, 1], [1, -1, 1], [0, 1, 1]])
    bvh = hlbvh_warp.build(verts, np.int32([[0, 1, 2]]), device=device)
    w = wide.collapse(bvh, 4)
    o, d = np.float32([[0, 0, 0]]), np.float32([[0, 0, 1]])
    assert query.intersect(bvh, o, d)[0].tolist() == [1.0]
    for t_max, hit in ((1.0 + 1e-12, True), (np.array([1.0 + 1e-12]), True), (1.0, False),
                       (np.nextafter(1.0, 0.0), False), (10**400, True), (-10**400, False)):
        assert (query.intersect(bvh, o, d, t_max=t_max)[1][0] >= 0) == hit, t_max
        assert query.occluded(bvh, o, d, t_max=t_max)[0] == hit, t_max
        assert len(query.intersect_all(bvh, o, d, t_max=t_max)[0]) == int(hit), t_max
        assert (wide.intersect(w, o, d, t_max=t_max)[1][0] >= 0) == hit, t_max
    with pytest.raises(ValueError, match="max_dist must be >= 0"):
        query.closest_point(bvh, o, max_dist=-10**400)
    assert query.closest_point(bvh, o, max_dist=10**400)[2].tolist() == [0]
