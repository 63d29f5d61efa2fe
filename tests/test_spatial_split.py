"""The spatial-split builder (``method="sbvh"``, Stich, Friedrich & Dietrich 2009) against float64
oracles: every part of every triangle stays bounded, rays hit what a brute force hits, the root
takes the cheapest candidate of an independent enumeration, and the EPO of its duplicated
references matches the brute force."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
import warp as wp

import hlbvh_warp as hw
from hlbvh_warp import hlbvh, query, spatial_split, wide
from hlbvh_warp.kernels import spatial_split as sk
from hlbvh_warp.metrics import end_point_overlap, sah_cost
from oracles import (assert_hits_match, brute_force_closest_hit, numpy_end_point_overlap, random_rays,
                     sbvh_root_candidates, sphere_past_float32_extent, triangle_slab_bounds)


def slivers(rng, num_tris: int, length: float = 1.0, width: float = 0.01):
    """Long thin triangles in random directions across the unit cube: object splits of such a
    scene overlap everywhere, the case spatial splits are for."""
    a = rng.uniform(0.0, 1.0, (num_tris, 3))
    direction = rng.normal(size=(num_tris, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    side = np.cross(direction, rng.normal(size=(num_tris, 3)))
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    b = a + length * direction
    c = a + 0.5 * length * direction + width * side
    verts = np.stack([a, b, c], axis=1).reshape(-1, 3).astype(np.float32)
    return verts, np.arange(3 * num_tris, dtype=np.int32).reshape(-1, 3)


def large_and_small(rng, num_small: int, num_large: int = 8):
    """Small triangles scattered through the unit cube and a few large ones spanning it: every
    object split that holds a large triangle has a box as large as the scene's (Stich et al.'s
    motivating case); a spatial split cuts the large ones instead."""
    centers = rng.uniform(0.0, 1.0, (num_small, 1, 3))
    small = centers + 0.03 * rng.normal(size=(num_small, 3, 3))
    large = rng.uniform(0.0, 1.0, (num_large, 3, 3))
    tris = np.concatenate([small, large]).astype(np.float32)
    return tris.reshape(-1, 3), np.arange(3 * len(tris), dtype=np.int32).reshape(-1, 3)


def check_parts_bounded(bvh, verts, faces, samples: int = 6):
    """Every point of every triangle lies in the box of a leaf that references the triangle,
    every reference's leaf box lies inside its triangle's box, and every node's box holds its
    children's."""
    tree = bvh.to_numpy()
    left, right = tree["node_left"], tree["node_right"]
    lo, hi = tree["node_lowers"].astype(np.float64), tree["node_uppers"].astype(np.float64)
    interior = np.nonzero(left >= 0)[0]
    for child in (left[interior], right[interior]):
        assert (lo[child] >= lo[interior]).all() and (hi[child] <= hi[interior]).all()
    order = tree["prim_order"]
    assert np.array_equal(np.unique(order), np.arange(len(faces)))  # every triangle referenced
    leaves = np.nonzero(left < 0)[0]
    leaf_of = np.empty(len(order), np.int64)
    for leaf in leaves:
        leaf_of[tree["node_begin"][leaf]:tree["node_end"][leaf]] = leaf
    tris = np.asarray(verts, np.float64)[np.asarray(faces)]
    # Barycentric samples, corners and edges included.
    ij = [(i, j) for i in range(samples + 1) for j in range(samples + 1 - i)]
    bary = np.array([(i / samples, j / samples, 1.0 - (i + j) / samples) for i, j in ij])
    points = np.einsum("sk,tkd->tsd", bary, tris)
    # The float64 sums of the samples may round past a vertex's coordinate by an ulp; far below
    # the size of a missed part.
    eps = 1e-12 * max(np.abs(tris).max(), 1.0)
    for t in range(len(faces)):
        boxes = leaf_of[order == t]
        inside = ((points[t][:, None] >= lo[boxes][None] - eps) & (points[t][:, None] <= hi[boxes][None] + eps)).all(-1)
        assert inside.any(axis=1).all(), f"a part of triangle {t} is in none of its leaves' boxes"
    single = leaves[tree["node_end"][leaves] - tree["node_begin"][leaves] == 1]
    t_single = order[tree["node_begin"][single]]
    assert (lo[single] >= tris[t_single].min(1)).all() and (hi[single] <= tris[t_single].max(1)).all()


@pytest.mark.parametrize("scene", ["slivers", "large_and_small", "sphere"])
def test_rays_and_parts_against_brute_force(device, rng, scene):
    if scene == "slivers":
        verts, faces = slivers(rng, 150)
    elif scene == "large_and_small":
        verts, faces = large_and_small(rng, 150)
    else:
        mesh = trimesh.creation.icosphere(subdivisions=2)
        verts, faces = mesh.vertices.astype(np.float32), mesh.faces.astype(np.int32)
    bvh = hw.build(verts, faces, method="sbvh", device=device, config=hw.BuildConfig(sbvh_alpha=0.0))
    if scene != "sphere":
        assert bvh.has_duplicates and bvh.num_refs > bvh.num_prims == len(faces)
    check_parts_bounded(bvh, verts, faces)
    o, d = random_rays(rng, verts, 1500)
    t_ref, prim_ref = brute_force_closest_hit(verts, faces, o, d)
    assert_hits_match(*query.intersect(bvh, o, d), t_ref, prim_ref)
    assert np.array_equal(query.occluded(bvh, o, d), prim_ref >= 0)
    # All hits: each triangle once per ray, however many leaves hold a part of it.
    ray_id, prim_id, _ = query.intersect_all(bvh, o, d)
    pairs = ray_id * len(faces) + prim_id
    assert len(np.unique(pairs)) == len(pairs)
    sweep_ids, sweep_prims, _ = query.intersect_all(hw.build(verts, faces, method="sweep_sah", device=device), o, d)
    assert np.array_equal(np.sort(pairs), np.sort(sweep_ids * len(faces) + sweep_prims))


def test_root_takes_the_cheapest_candidate(device, rng):
    verts, faces = large_and_small(rng, 60, 4)
    bins = 8
    candidates = sbvh_root_candidates(verts, faces, bins)
    assert candidates["object_overlap"] > 0.0  # alpha = 0 lets spatial splits compete
    bvh = hw.build(verts, faces, method="sbvh", device=device, config=hw.BuildConfig(sbvh_bins=bins, sbvh_alpha=0.0))
    tree = bvh.to_numpy()
    lo, hi = tree["node_lowers"].astype(np.float64), tree["node_uppers"].astype(np.float64)
    children = [tree["node_left"][0], tree["node_right"][0]]
    # The root's split as the tree holds it: A(L) N(L) + A(R) N(R) of its children, N the
    # triangles each child held when the root was split (its subtree's distinct triangles: deeper
    # spatial splits add references, never triangles).
    held = [len(np.unique(tree["prim_order"][tree["node_begin"][c]:tree["node_end"][c]])) for c in children]
    cost = sum(_area(lo[c], hi[c]) * k for c, k in zip(children, held))
    best = min(candidates["object"], candidates["spatial"])
    assert cost == pytest.approx(best, rel=1e-5)
    # The scene is built so that the spatial split wins at the root: the test sees that path.
    assert candidates["spatial"] < candidates["object"]
    assert sum(held) > len(faces)


@pytest.mark.parametrize("bins", [2, 5, 16])
@pytest.mark.parametrize("scene", ["slivers", "large_and_small"])
def test_split_search_prices_like_the_enumeration(device, rng, bins, scene):
    verts, faces = slivers(rng, 50, length=0.5) if scene == "slivers" else large_and_small(rng, 50, 5)
    candidates = sbvh_root_candidates(verts, faces, bins)
    found = spatial_split.root_split_costs(verts, faces, hw.BuildConfig(sbvh_bins=bins, sbvh_alpha=0.0), device)
    assert found["object"] == pytest.approx(candidates["object"], rel=1e-12)
    # Spatial parts are rounded outward to float32 (a few units in the last place).
    assert found["spatial"] == pytest.approx(candidates["spatial"], rel=1e-5)


def _area(lo, hi) -> float:
    d = hi - lo
    return float(2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0]))


def test_slab_bounds_oracle_by_hand():
    tri = np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0], [0.0, 2.0, 1.0]])
    lo, hi = triangle_slab_bounds(tri, 0, 1.0, 2.0)
    # x in [1, 2]: the edge (0,0,0)-(4,0,0) gives y = z = 0; the edge (4,0,0)-(0,2,1) at x = 2 gives
    # y = 1, z = 0.5, and at x = 1 gives y = 1.5, z = 0.75.
    np.testing.assert_allclose(lo, [1.0, 0.0, 0.0])
    np.testing.assert_allclose(hi, [2.0, 1.5, 0.75])
    assert triangle_slab_bounds(tri, 0, 5.0, 6.0) is None


def test_spatial_splits_pay_where_large_triangles_overlap_small_ones(device, rng):
    """Stich et al.'s claim, on their kind of scene: lower SAH and far lower EPO than the same
    builder without spatial splits and than the full-sweep SAH build (measured: 0.89 and 0.14)."""
    verts, faces = large_and_small(rng, 400)
    sbvh = hw.build(verts, faces, method="sbvh", device=device)
    objects_only = hw.build(verts, faces, method="sbvh", device=device, config=hw.BuildConfig(sbvh_alpha=np.inf))
    sweep = hw.build(verts, faces, method="sweep_sah", device=device)
    assert not objects_only.has_duplicates
    assert np.array_equal(np.sort(objects_only.to_numpy()["prim_order"]), np.arange(len(faces)))
    assert sah_cost(sbvh) < 0.95 * min(sah_cost(objects_only), sah_cost(sweep))
    assert end_point_overlap(sbvh) < 0.5 * min(end_point_overlap(objects_only), end_point_overlap(sweep))


@pytest.mark.parametrize("scene", ["slivers", "large_and_small"])
def test_epo_with_duplicated_references_matches_the_brute_force(device, rng, scene):
    verts, faces = slivers(rng, 40, length=0.6) if scene == "slivers" else large_and_small(rng, 40, 4)
    bvh = hw.build(verts, faces, method="sbvh", device=device, config=hw.BuildConfig(sbvh_alpha=0.0))
    assert bvh.has_duplicates
    tree = bvh.to_numpy()
    epo, per_node = end_point_overlap(bvh, per_node=True)
    expected, expected_nodes = numpy_end_point_overlap(tree, verts, faces,
                                                       node_boxes=(tree["node_lowers"], tree["node_uppers"]))
    assert expected > 0.0
    assert epo == pytest.approx(expected, rel=1e-9)
    np.testing.assert_allclose(per_node, expected_nodes, rtol=1e-9, atol=1e-12)


@wp.kernel
def _user_box_queries(bvh: hw.BvhView, lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3),
                      counts: wp.array(dtype=int), pairs: wp.array(dtype=wp.vec2i),
                      pair_count: wp.array(dtype=wp.int32)):
    tid = wp.tid()
    counts[tid] = hw.bvh_aabb_count(bvh, lowers[tid], uppers[tid])
    hw.bvh_aabb_pairs(bvh, lowers[tid], uppers[tid], tid, pairs, pair_count)


def test_box_queries_in_a_user_kernel_count_each_triangle_once(device, rng):
    # A spatial-split leaf's box bounds its part of a triangle: a walk pruned by those boxes
    # missed 76 of 100 queries' triangles here and counted some twice. The view of such a tree
    # has its box calls test every triangle's whole box, against a NumPy brute force.
    verts, faces = large_and_small(rng, 150, 8)
    bvh = hw.build(verts, faces, method="sbvh", device=device, config=hw.BuildConfig(sbvh_alpha=0.0))
    assert bvh.has_duplicates
    tri = verts[faces]
    q_lo = rng.uniform(-0.1, 1.0, (100, 3)).astype(np.float32)
    q_hi = q_lo + np.float32(0.2)
    hits = ((q_lo[:, None] <= tri.max(axis=1)[None]) & (tri.min(axis=1)[None] <= q_hi[:, None])).all(axis=-1)
    counts = wp.zeros(100, dtype=int, device=device)
    pairs = wp.zeros(int(hits.sum()) + 10, dtype=wp.vec2i, device=device)
    pair_count = wp.zeros(1, dtype=wp.int32, device=device)
    wp.launch(_user_box_queries, dim=100, device=device,
              inputs=[hw.view(bvh), wp.array(q_lo, dtype=wp.vec3, device=device),
                      wp.array(q_hi, dtype=wp.vec3, device=device), counts, pairs, pair_count])
    np.testing.assert_array_equal(counts.numpy(), hits.sum(axis=1))
    assert int(pair_count.numpy()[0]) == int(hits.sum())
    found = pairs.numpy()[: int(hits.sum())]
    assert sorted(map(tuple, found.tolist())) == sorted(map(tuple, np.argwhere(hits).tolist()))


@pytest.mark.parametrize("budget", [0.0, 0.05])
def test_reference_budget(device, rng, budget):
    verts, faces = large_and_small(rng, 300, 30)
    bvh = hw.build(verts, faces, method="sbvh", device=device,
                   config=hw.BuildConfig(sbvh_alpha=0.0, sbvh_max_duplication=budget))
    assert bvh.num_refs <= int(np.floor((1.0 + budget) * len(faces)))
    if budget > 0:
        assert bvh.has_duplicates
    o, d = random_rays(rng, verts, 500)
    assert_hits_match(*query.intersect(bvh, o, d), *brute_force_closest_hit(verts, faces, o, d))


def test_a_budget_meant_as_no_limit_allocates_only_the_tree(device, rng):
    # Node storage grows with the tree: a budget of 1e12 references per triangle once asked for
    # terabytes up front. Where neither budget is spent, both give the same tree.
    verts, faces = large_and_small(rng, 200, 8)
    trees = [hw.build(verts, faces, method="sbvh", device=device,
                      config=hw.BuildConfig(sbvh_alpha=0.0, sbvh_max_duplication=budget)).to_numpy()
             for budget in (3.0, 1e12)]
    assert len(trees[0]["prim_order"]) < 4 * len(faces)
    for name in ("node_left", "node_right", "node_begin", "node_end", "prim_order", "node_lowers", "node_uppers"):
        np.testing.assert_array_equal(trees[0][name], trees[1][name], err_msg=name)


def test_a_budget_past_float64_once_multiplied_is_no_limit(device, rng):
    # sbvh_max_duplication = 1e308 is finite, so the config takes it, but (1 + 1e308) N is inf
    # in float64: the build raised OverflowError from int(). It is a budget no tree can spend.
    verts, faces = large_and_small(rng, 200, 8)
    trees = [hw.build(verts, faces, method="sbvh", device=device,
                      config=hw.BuildConfig(sbvh_alpha=0.0, sbvh_max_duplication=budget)).to_numpy()
             for budget in (1e12, 1e308)]
    for name in ("node_left", "node_right", "node_begin", "node_end", "prim_order", "node_lowers", "node_uppers"):
        np.testing.assert_array_equal(trees[0][name], trees[1][name], err_msg=name)


def test_degenerate_and_coincident_triangles(device, rng):
    verts, faces = slivers(rng, 60)
    tris = verts.reshape(-1, 3, 3).copy()
    tris[:10, 2] = tris[:10, 0]                      # segments
    tris[10:15] = tris[10:15, :1]                    # points
    tris[15:30] = tris[30:45]                        # duplicated triangles
    tris[45:50, :, 0] = 0.5                          # flat in a plane x = 0.5
    verts = tris.reshape(-1, 3)
    bvh = hw.build(verts, faces, method="sbvh", device=device, config=hw.BuildConfig(sbvh_alpha=0.0, sbvh_bins=4))
    check_parts_bounded(bvh, verts, faces)
    o, d = random_rays(rng, verts, 800)
    assert_hits_match(*query.intersect(bvh, o, d), *brute_force_closest_hit(verts, faces, o, d))


def test_refit_and_wide_trees_stay_exact(device, rng):
    verts, faces = slivers(rng, 120)
    bvh = hw.build(verts, faces, method="sbvh", device=device, config=hw.BuildConfig(sbvh_alpha=0.0))
    o, d = random_rays(rng, verts, 600)
    reference = brute_force_closest_hit(verts, faces, o, d)
    for k in (4, 8):
        assert_hits_match(*wide.intersect(wide.collapse(bvh, k), o, d), *reference)
    # A refit bounds every reference by its whole triangle: looser boxes, the same hits.
    before = sah_cost(bvh)
    hlbvh.refit_bounds(bvh)
    bvh.invalidate()
    assert sah_cost(bvh) >= before
    assert_hits_match(*query.intersect(bvh, o, d), *reference)


def test_bad_use_raises(device, rng):
    verts, faces = large_and_small(rng, 30)
    tris = verts.reshape(-1, 3, 3)
    with pytest.raises(ValueError, match="needs a mesh"):
        hw.build_from_bounds(tris.min(1), tris.max(1), method="sbvh", device=device)
    bvh = hw.build(verts, faces, method="sbvh", device=device, config=hw.BuildConfig(sbvh_alpha=0.0))
    assert bvh.has_duplicates
    with pytest.raises(ValueError, match="spatial splits"):
        query.query_aabb(bvh, tris.min(1), tris.max(1))
    for bad in ({"sbvh_bins": 1}, {"sbvh_bins": 65}, {"sbvh_alpha": float("nan")}, {"sbvh_alpha": -1.0},
                {"sbvh_max_duplication": -0.5}, {"sbvh_max_duplication": float("inf")}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            hw.BuildConfig(**bad)
    bad_verts = verts.copy()
    bad_verts[4, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        hw.build(bad_verts, faces, method="sbvh", device=device)


@pytest.mark.parametrize("num_small, max_leaf", [(0, 1), (1, 1), (40, 4)])
def test_tiny_scenes_and_larger_leaves(device, rng, num_small, max_leaf):
    verts, faces = large_and_small(rng, num_small, 1 if num_small < 2 else 6)
    bvh = hw.build(verts, faces, method="sbvh", device=device,
                   config=hw.BuildConfig(sbvh_alpha=0.0, max_leaf_size=max_leaf))
    tree = bvh.to_numpy()
    leaves = tree["node_left"] < 0
    assert (tree["node_end"] - tree["node_begin"])[leaves].max() <= max_leaf
    check_parts_bounded(bvh, verts, faces)
    o, d = random_rays(rng, verts, 300)
    assert_hits_match(*query.intersect(bvh, o, d), *brute_force_closest_hit(verts, faces, o, d))


def test_parts_cut_far_from_their_triangles_vertices_keep_every_point(device, rng):
    # Long triangles spanning +-1e6 in the plane y = -x, cut by spatial splits down to parts near
    # the origin among small triangles along the same line. The float64 clip is accurate to the
    # triangle's coordinates (about 1e-10 here), not to the part's (1e-5): rounded outward by the
    # part's own float32 unit, two parts of a triangle left gaps of about 4e-11 between their
    # boxes, and rays through them missed a triangle they hit 0.2 inside its edges.
    radius, num_long, num_small = 1e6, 12, 4000
    z = np.arange(num_long) * 2.0
    long_tris = np.stack([np.stack([np.full(num_long, -radius), np.full(num_long, radius), z], 1),
                          np.stack([np.full(num_long, radius), np.full(num_long, -radius), z], 1),
                          np.stack([np.full(num_long, -radius), np.full(num_long, radius), z + 1.0], 1)], 1)
    size = 10.0 ** rng.uniform(-5, 6, num_small) * rng.choice([-1.0, 1.0], num_small)
    centers = np.stack([size, -size, rng.uniform(0, 2 * num_long, num_small)], 1)
    small = centers[:, None] + (np.abs(size)[:, None, None] * 0.05 + 1e-7) * rng.normal(size=(num_small, 3, 3))
    verts = np.concatenate([long_tris, small]).astype(np.float32).reshape(-1, 3)
    faces = np.arange(len(verts), dtype=np.int32).reshape(-1, 3)
    bvh = hw.build(verts, faces, method="sbvh", device=device,
                   config=hw.BuildConfig(sbvh_alpha=0.0, sbvh_max_duplication=3.0))
    assert bvh.has_duplicates
    # Points (x, -x, z) of each long triangle (exactly on it) a few float32 units either side of
    # every edge of its leaves' boxes near the origin, at heights inside the box and the triangle:
    # each must lie in some leaf box that references the triangle, compared exactly.
    tree = bvh.to_numpy()
    leaves = np.nonzero(tree["node_left"] < 0)[0]
    order, begin, end = tree["prim_order"], tree["node_begin"], tree["node_end"]
    leaf_of = np.repeat(leaves, end[leaves] - begin[leaves])
    ref_tri = np.concatenate([order[begin[leaf]:end[leaf]] for leaf in leaves])
    steps = np.array([-32, -16, -8, -4, -2, -1, 1, 2, 4, 8, 16, 32], np.float64)
    for k in range(num_long):
        holding = leaf_of[ref_tri == k]
        lo, hi = tree["node_lowers"][holding].astype(np.float64), tree["node_uppers"][holding].astype(np.float64)
        edges = np.concatenate([lo[:, 0], hi[:, 0], -lo[:, 1], -hi[:, 1]])
        z_lo = np.tile(np.maximum(lo[:, 2], z[k] + 0.01), 4)  # the triangle's height at |x| << 1e6:
        z_hi = np.tile(np.minimum(hi[:, 2], z[k] + 0.49), 4)  # from z to z + 0.5
        keep = (np.abs(edges) < 100.0) & (z_lo < z_hi)
        edges, z_lo, z_hi = edges[keep], z_lo[keep], z_hi[keep]
        unit = np.spacing(np.abs(edges).astype(np.float32)).astype(np.float64)
        xs = (edges[:, None] + steps[None] * unit[:, None]).ravel()
        zs = (z_lo[:, None] + (z_hi - z_lo)[:, None] * rng.random((len(edges), len(steps)))).ravel()
        points = np.stack([xs, -xs, zs], 1)
        inside = ((points[:, None] >= lo[None]) & (points[:, None] <= hi[None])).all(-1).any(1)
        assert inside.all(), f"{int((~inside).sum())} points of triangle {k} lie in none of its leaves"
    # And random rays against the brute force.
    o, d = random_rays(rng, verts, 500)
    assert_hits_match(*query.intersect(bvh, o, d), *brute_force_closest_hit(verts, faces, o, d))


def test_a_budget_spent_exactly_gives_the_unlimited_tree(device, rng):
    # A budget that the unlimited build's references fill exactly: every spatial split fits, the
    # last one included, so the tree is the unlimited one.
    verts, faces = large_and_small(rng, 200, 12)
    config = dict(sbvh_alpha=0.0)
    free = hw.build(verts, faces, method="sbvh", device=device,
                    config=hw.BuildConfig(sbvh_max_duplication=1e12, **config)).to_numpy()
    n, refs = len(faces), len(free["prim_order"])
    assert refs > n
    budget = (refs - n + 0.5) / n
    assert int(np.floor((1.0 + budget) * n)) == refs
    tight = hw.build(verts, faces, method="sbvh", device=device,
                     config=hw.BuildConfig(sbvh_max_duplication=budget, **config)).to_numpy()
    for name in ("node_left", "node_begin", "node_end", "prim_order", "node_lowers", "node_uppers"):
        np.testing.assert_array_equal(tight[name], free[name], err_msg=name)


@pytest.mark.parametrize("bins", [4, 8])
def test_boxes_ending_on_a_plane_price_like_the_enumeration(device, rng, bins):
    # Every coordinate on the grid of the root's bin planes: a box ending exactly on a plane
    # stays left whole (it does not exit in the slab above), one starting on it goes right.
    grid = rng.integers(0, bins + 1, size=(60, 3, 3)).astype(np.float32) / np.float32(bins)
    grid[0] = [[0, 0, 0], [1, 1, 0], [0, 1, 1]]
    grid[1] = [[1, 1, 1], [1, 0, 1], [0, 1, 0]]
    verts = grid.reshape(-1, 3)
    faces = np.arange(len(verts), dtype=np.int32).reshape(-1, 3)
    candidates = sbvh_root_candidates(verts, faces, bins)
    found = spatial_split.root_split_costs(verts, faces, hw.BuildConfig(sbvh_bins=bins, sbvh_alpha=0.0), device)
    assert np.isfinite(candidates["spatial"])
    assert found["object"] == pytest.approx(candidates["object"], rel=1e-12)
    assert found["spatial"] == pytest.approx(candidates["spatial"], rel=1e-5)
    bvh = hw.build(verts, faces, method="sbvh", device=device,
                   config=hw.BuildConfig(sbvh_bins=bins, sbvh_alpha=0.0))
    check_parts_bounded(bvh, verts, faces)


@wp.kernel
def _part_boxes_kernel(a: wp.array(dtype=wp.vec3), b: wp.array(dtype=wp.vec3), c: wp.array(dtype=wp.vec3),
                       slab: wp.array(dtype=wp.vec2), out_lo: wp.array(dtype=wp.vec3), out_hi: wp.array(dtype=wp.vec3)):
    """The box of the part of each triangle within its x slab, as the spatial-split search clips it."""
    i = wp.tid()
    lo = wp.min(wp.min(a[i], b[i]), c[i])
    hi = wp.max(wp.max(a[i], b[i]), c[i])
    polygon, count = sk.triangle_in_box(a[i], b[i], c[i], lo, hi)
    margin = sk.clip_margin(a[i], b[i], c[i])
    part_lo, part_hi = sk.slab_part_box(polygon, count, 0, lo, hi, slab[i][0], slab[i][1], margin)
    out_lo[i] = part_lo
    out_hi[i] = part_hi


def test_clipped_part_boxes_hold_the_exact_parts(device, rng):
    # The kernels' slab_part_box on long triangles in the plane y = -x spanning +-1e6, cut into
    # slabs near the origin: each box must hold the exact part (x in [p0, p1], y = -x, z from
    # z0 up to the slanted edge), computed here in rationals. The float64 clip is off by about
    # 1e-10 there, far more than a float32 unit of the part's coordinates.
    from fractions import Fraction

    radius = np.float32(1e6)
    num = 400
    z0 = rng.integers(0, 8, num).astype(np.float32)
    a = np.stack([np.full(num, -radius), np.full(num, radius), z0], 1)
    b = np.stack([np.full(num, radius), np.full(num, -radius), z0], 1)
    c = np.stack([np.full(num, -radius), np.full(num, radius), z0 + 1], 1)
    p0 = (10.0 ** rng.uniform(-6, 0, num) * rng.choice([-1.0, 1.0], num)).astype(np.float32)
    p1 = (p0 + np.abs(p0) * rng.uniform(1e-3, 1.0, num)).astype(np.float32)
    arrays = [wp.array(x.astype(np.float32), dtype=wp.vec3, device=device) for x in (a, b, c)]
    slab = wp.array(np.stack([p0, p1], 1), dtype=wp.vec2, device=device)
    out_lo = wp.zeros(num, dtype=wp.vec3, device=device)
    out_hi = wp.zeros(num, dtype=wp.vec3, device=device)
    wp.launch(_part_boxes_kernel, dim=num, inputs=[*arrays, slab, out_lo, out_hi], device=device)
    lo, hi = out_lo.numpy(), out_hi.numpy()
    r = Fraction(float(radius))
    for i in range(num):
        x0, x1 = Fraction(float(p0[i])), Fraction(float(p1[i]))
        z_top = Fraction(float(z0[i])) + (r - x0) / (2 * r)
        exact_lo = (x0, -x1, Fraction(float(z0[i])))
        exact_hi = (x1, -x0, z_top)
        for d in range(3):
            assert Fraction(float(lo[i, d])) <= exact_lo[d], (i, d, "lower")
            assert Fraction(float(hi[i, d])) >= exact_hi[d], (i, d, "upper")


def _clip_exact(polygon, axis, bound, sign):
    """Sutherland-Hodgman against one plane, in rationals: the part with sign * (p - bound) >= 0."""
    out = []
    for i in range(len(polygon)):
        p, q = polygon[i], polygon[(i + 1) % len(polygon)]
        dp, dq = sign * (p[axis] - bound), sign * (q[axis] - bound)
        if dp >= 0:
            out.append(p)
        if (dp >= 0) != (dq >= 0):
            t = dp / (dp - dq)
            out.append(tuple(p[k] + t * (q[k] - p[k]) for k in range(3)))
    return out


def test_clipped_part_boxes_hold_the_exact_parts_when_z_is_large(device, rng):
    # Triangles in the plane z = -1e6 x, x in [-1, 1]: only z carries large coordinates, so the
    # clip's margin must look at z too (a mutation audit found a margin of x and y alone passing
    # the test above, whose large coordinates are in x and y). Oracle: the part clipped in rationals.
    from fractions import Fraction

    num, big = 400, 1.0e6
    y0 = rng.integers(0, 8, num).astype(np.float64)
    a = np.stack([np.full(num, -1.0), y0, np.full(num, big)], 1).astype(np.float32)
    b = np.stack([np.full(num, 1.0), y0, np.full(num, -big)], 1).astype(np.float32)
    c = np.stack([np.full(num, -1.0), y0 + 1.0, np.full(num, big)], 1).astype(np.float32)
    s0 = (10.0 ** rng.uniform(-12, -6, num) * rng.choice([-1.0, 1.0], num)).astype(np.float32)
    s1 = (s0 + np.abs(s0) * rng.uniform(1e-3, 1.0, num)).astype(np.float32)
    out_lo, out_hi = wp.zeros(num, dtype=wp.vec3, device=device), wp.zeros(num, dtype=wp.vec3, device=device)
    wp.launch(_part_boxes_kernel, dim=num, device=device,
              inputs=[*(wp.array(x, dtype=wp.vec3, device=device) for x in (a, b, c)),
                      wp.array(np.stack([s0, s1], 1), dtype=wp.vec2, device=device), out_lo, out_hi])
    lo, hi = out_lo.numpy(), out_hi.numpy()
    checked = 0
    for i in range(num):
        tri = [tuple(Fraction(float(v)) for v in p) for p in (a[i], b[i], c[i])]
        part = _clip_exact(_clip_exact(tri, 0, Fraction(float(s0[i])), 1), 0, Fraction(float(s1[i])), -1)
        if not part:
            continue
        checked += 1
        for k in range(3):
            assert Fraction(float(lo[i][k])) <= min(p[k] for p in part), (i, k, "lower")
            assert Fraction(float(hi[i][k])) >= max(p[k] for p in part), (i, k, "upper")
    assert checked > 300


def test_boxes_past_3e38_are_their_triangles_boxes(device, rng):
    """Vertices beyond 3.0e38 on x and below -3.0e38 on y, finite float32 the input checks accept:
    the reductions' empty box, at +-3.0e38, stayed a corner of every node and bin box there (the
    root's lower x 3.0e38 below every vertex), so the sweeps priced boxes larger than the parts."""
    top = np.float64(np.finfo(np.float32).max)
    verts, faces = slivers(rng, 60, length=0.3)
    verts = verts.astype(np.float64)
    verts[:, 0] = top * (0.9 + 0.08 * verts[:, 0] / verts[:, 0].max())
    verts[:, 1] = -top * (0.9 + 0.08 * verts[:, 1] / verts[:, 1].max())
    verts = verts.astype(np.float32)
    assert verts[:, 0].min() > 3.0e38 and verts[:, 1].max() < -3.0e38  # the scene does what the test means
    bvh = hw.build(verts, faces, method="sbvh", device=device, config=hw.BuildConfig(sbvh_alpha=0.0))
    tree = bvh.to_numpy()
    np.testing.assert_array_equal(tree["node_lowers"][0], verts.min(axis=0))
    np.testing.assert_array_equal(tree["node_uppers"][0], verts.max(axis=0))
    check_parts_bounded(bvh, verts, faces)
    # Every leaf's box within the boxes of the triangles it references.
    tris = verts[faces]
    leaves = np.nonzero(tree["node_left"] < 0)[0]
    for leaf in leaves:
        refs = tree["prim_order"][tree["node_begin"][leaf]:tree["node_end"][leaf]]
        assert (tree["node_lowers"][leaf] >= tris[refs].min(axis=(0, 1))).all()
        assert (tree["node_uppers"][leaf] <= tris[refs].max(axis=(0, 1))).all()


def test_centroids_near_the_largest_float32(device, rng):
    """Slivers at [2^127, 2^128), finite float32 the input checks accept: lower + upper of every
    reference's centroid overflowed float32 to inf, every object split binned them all in one
    bin, and the tree priced worse than the same mesh scaled down by 2^127. Scaled by a power of
    two (every value normal) every decision is the same: the tree must be that mesh's."""
    verts, faces = slivers(rng, 80, length=0.3)
    verts = (1.0 + 0.75 * (verts - verts.min()) / (verts.max() - verts.min())).astype(np.float32)
    big = (verts.astype(np.float64) * 2.0**127).astype(np.float32)
    with np.errstate(over="ignore"):
        assert np.isinf(big[0::3] + big[1::3]).all()  # the scene does what the test means
    config = hw.BuildConfig(sbvh_alpha=0.0)
    tree = hw.build(big, faces, method="sbvh", device=device, config=config).to_numpy()
    expected = hw.build(verts, faces, method="sbvh", device=device, config=config).to_numpy()
    for name in ("node_left", "node_right", "node_begin", "node_end", "prim_order"):
        np.testing.assert_array_equal(tree[name], expected[name], err_msg=name)


def test_no_spatial_search_where_the_object_split_does_not_overlap(device, rng):
    # Two clusters far apart: the best object split's boxes are disjoint, an overlap of 0, which
    # is not more than alpha = 0 of the root's area: the spatial search is not tried.
    centers = np.concatenate([rng.uniform(0.0, 0.3, (30, 1, 3)), rng.uniform(0.7, 1.0, (30, 1, 3))])
    verts = (centers + 0.02 * rng.normal(size=(60, 3, 3))).astype(np.float32).reshape(-1, 3)
    faces = np.arange(len(verts), dtype=np.int32).reshape(-1, 3)
    candidates = sbvh_root_candidates(verts, faces, 8)
    assert candidates["object_overlap"] == 0.0
    found = spatial_split.root_split_costs(verts, faces, hw.BuildConfig(sbvh_bins=8, sbvh_alpha=0.0), device)
    assert found["object"] == pytest.approx(candidates["object"], rel=1e-12)
    assert found["spatial"] == np.inf and found["spatial_axis"] == -1


def test_centroid_extent_past_the_float32_range(device, rng):
    """A sphere of radius 1.7 x 2^127 (2.9e38): its centroids span more than float32's largest
    value, so the float32 extent of a large node's centroids was inf, every object split binned
    them all in bin 0 and the node was halved in its (shuffled) order: 6.3 times the SAH cost of
    the same sphere scaled down by 2^127. Object splits only (alpha = inf), as cheap as that
    sphere's."""
    small, big, f = sphere_past_float32_extent(rng)
    config = hw.BuildConfig(sbvh_alpha=np.inf)
    expected = sah_cost(hw.build(small, f, method="sbvh", device=device, config=config))
    bvh = hw.build(big, f, method="sbvh", device=device, config=config)
    check_parts_bounded(bvh, big, f)
    assert sah_cost(bvh) == pytest.approx(expected, rel=0.01)


def test_spatial_splits_of_a_box_past_the_float32_range(device, rng):
    """Large and small triangles in [-1.7, 1.7] x 2^127: the root's box is wider than float32's
    largest value, so its float32 extent was inf, every slab plane lower + inf * j / B was inf,
    every reference fell in slab 0 and no spatial split was found where the same scene scaled
    down by 2^127 takes one (its SAH 16% below the big scene's tree). The root's spatial split
    must cost what the scaled-down scene's does (areas scaled by 2^254), and the tree as much."""
    v, f = large_and_small(rng, 200)
    v = (v.astype(np.float64) * 2.0 - 1.0) * 1.7
    small = v.astype(np.float32)
    big = (v * 2.0**127).astype(np.float32)
    assert (big.max(0).astype(np.float64) - big.min(0) > np.finfo(np.float32).max).all()
    config = hw.BuildConfig(sbvh_alpha=0.0)
    root = spatial_split.root_split_costs(small, f, config, device)
    assert root["spatial"] < root["object"]  # the scene does what the test means
    found = spatial_split.root_split_costs(big, f, config, device)
    assert found["spatial_axis"] == root["spatial_axis"]
    assert found["spatial"] == pytest.approx(root["spatial"] * 2.0**254, rel=1e-3)
    expected = hw.build(small, f, method="sbvh", device=device, config=config)
    bvh = hw.build(big, f, method="sbvh", device=device, config=config)
    check_parts_bounded(bvh, big, f)
    assert sah_cost(bvh) == pytest.approx(sah_cost(expected), rel=0.01)


@pytest.mark.parametrize("bins", [4, 16])
@pytest.mark.parametrize("scene", ["diagonals", "fan"])
def test_no_spatial_split_that_keeps_every_reference_on_one_side(device, bins, scene):
    """Slivers along the cube's diagonal, every one starting in the first slab of every axis:
    each spatial boundary has all N references on its left ("fan": the slivers end at different
    lengths), or on both sides ("diagonals": each spans the whole box). Such a split duplicates
    without making a side smaller, and the sweep's rule (both sides below N, Stich et al. 2009
    split only what shrinks) leaves no spatial candidate; the object splits stay valid (the
    centroids differ), so the tree is built from object splits alone, with no duplicates."""
    n = 24
    k = np.arange(n, dtype=np.float64)[:, None]
    start = 1e-3 * k * np.ones(3)  # well inside the first slab of 16 on every axis
    length = 1.0 if scene == "diagonals" else 0.4 + 0.6 * k / n
    end = start + length * np.ones(3)
    middle = 0.5 * (start + end) + 0.01 * np.array([1.0, -1.0, 0.0])  # inside the sliver's box
    verts = np.stack([start, end, middle], axis=1).reshape(-1, 3).astype(np.float32)
    faces = np.arange(3 * n, dtype=np.int32).reshape(-1, 3)
    candidates = sbvh_root_candidates(verts, faces, bins)
    assert candidates["spatial"] == np.inf and candidates["object"] < np.inf  # the scene does what it means
    assert candidates["object_overlap"] > 0.0  # alpha = 0 lets the spatial search run
    config = hw.BuildConfig(sbvh_bins=bins, sbvh_alpha=0.0)
    found = spatial_split.root_split_costs(verts, faces, config, device)
    assert found["object"] == pytest.approx(candidates["object"], rel=1e-12)
    assert found["spatial"] == np.inf and found["spatial_axis"] == -1
    bvh = hw.build(verts, faces, method="sbvh", device=device, config=config)
    assert not bvh.has_duplicates and bvh.num_refs == n
    check_parts_bounded(bvh, verts, faces)
