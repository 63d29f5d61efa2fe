"""SAH cost and tree statistics against a float64 NumPy evaluation of the same formulas."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import hlbvh_warp as hw
from hlbvh_warp.metrics import sah_cost, tree_stats
from oracles import random_soup


def numpy_area(lo, hi):
    d = np.asarray(hi, dtype=np.float64) - np.asarray(lo, dtype=np.float64)
    return 2.0 * (d[..., 0] * d[..., 1] + d[..., 1] * d[..., 2] + d[..., 2] * d[..., 0])


def numpy_sah(tree, t1=1.0, t2=1.0):
    """Pantaleoni & Luebke 2010 eq. (1) by recursion from the root, boxes rebuilt from the
    primitives (not read from the tree), P_hit = 1 under a zero-area parent."""
    left, right = tree["node_left"], tree["node_right"]
    begin, end, order = tree["node_begin"], tree["node_end"], tree["prim_order"]
    plo, phi = tree["prim_lowers"].astype(np.float64), tree["prim_uppers"].astype(np.float64)

    def box(node):
        ids = order[begin[node]:end[node]]
        return plo[ids].min(0), phi[ids].max(0)

    def cost(node):
        if left[node] < 0:
            return t2 * (end[node] - begin[node])
        parent_area = numpy_area(*box(node))
        total = 2 * t1
        for child in (left[node], right[node]):
            ratio = numpy_area(*box(child)) / parent_area if parent_area > 0 else 1.0
            total += cost(child) * ratio
        return total

    return cost(0)


@pytest.mark.parametrize("method", ["hlbvh", "median", "sweep_sah"])
@pytest.mark.parametrize("t1, t2", [(1.0, 1.0), (1.2, 1.0), (0.0, 2.5)])
def test_sah_cost_matches_numpy(device, rng, method, t1, t2):
    v, f = random_soup(rng, 40)
    bvh = hw.build(v, f, method=method, device=device, config=hw.BuildConfig(max_leaf_size=3))
    expected = numpy_sah(bvh.to_numpy(), t1, t2)
    assert sah_cost(bvh, t1, t2) == pytest.approx(expected, rel=1e-6)


def test_single_leaf_cost(device):
    lo = np.array([[0, 0, 0], [1, 1, 1]], dtype=np.float32)
    bvh = hw.build_from_bounds(lo, lo + 1, method="median", device=device, config=hw.BuildConfig(max_leaf_size=2))
    assert bvh.num_nodes == 1
    assert sah_cost(bvh, 1.0, 3.0) == pytest.approx(6.0)


def test_hand_computed_cost(device):
    # Two unit cubes side by side: root box 2x1x1 (area 10), each child area 6:
    # C = 2 T1 + 2 * (T2 * 1) * 6 / 10 = 2 + 1.2 = 3.2 with T1 = T2 = 1.
    lo = np.array([[0, 0, 0], [1, 0, 0]], dtype=np.float32)
    bvh = hw.build_from_bounds(lo, lo + 1, method="sweep_sah", device=device)
    assert sah_cost(bvh) == pytest.approx(3.2)


def test_zero_area_boxes_pass_costs_through(device):
    # Every primitive is the same point: every box has zero area, so P_hit = 1 throughout and
    # C = 2 T1 (N - 1) + T2 N for any binary tree with single-primitive leaves.
    n = 9
    pts = np.full((n, 3), 0.25, dtype=np.float32)
    bvh = hw.build_from_bounds(pts, pts, method="median", device=device)
    assert bvh.num_nodes == 2 * n - 1
    got = sah_cost(bvh, 1.5, 1.0)
    assert got == pytest.approx(2 * 1.5 * (n - 1) + n)
    assert got == pytest.approx(numpy_sah(bvh.to_numpy(), 1.5, 1.0))


def test_cost_is_scale_invariant_at_huge_coordinates(device, rng):
    # At 1e19 an area term (1e19)^2 * 2 sits at float32's limit (3.4e38) and the ratios of such
    # areas lose their digits; the float64 areas keep the cost equal to the unit-scale tree's.
    lo = rng.random((30, 3)).astype(np.float32)
    hi = lo + 0.1 * rng.random((30, 3)).astype(np.float32)
    small = hw.build_from_bounds(lo, hi, method="sweep_sah", device=device)
    big = hw.build_from_bounds(lo * np.float32(1e19), hi * np.float32(1e19), method="sweep_sah", device=device)
    big_cost = sah_cost(big)
    assert np.isfinite(big_cost)
    assert big_cost == pytest.approx(sah_cost(small), rel=1e-4)
    assert big_cost == pytest.approx(numpy_sah(big.to_numpy()), rel=1e-9)


def test_tree_stats_match_numpy(device, rng):
    v, f = random_soup(rng, 60)
    bvh = hw.build(v, f, method="hlbvh", device=device, config=hw.BuildConfig(max_leaf_size=4))
    tree = bvh.to_numpy()
    stats = tree_stats(bvh)
    left, begin, end, parent = tree["node_left"], tree["node_begin"], tree["node_end"], tree["node_parent"]
    leaves = left < 0
    depth = np.zeros(len(left), dtype=int)
    for node in range(1, len(left)):  # children are numbered after their parents
        depth[node] = depth[parent[node]] + 1
    sizes = (end - begin)[leaves]
    assert stats["num_nodes"] == len(left)
    assert stats["num_leaves"] == int(leaves.sum())
    assert stats["depth"] == int(depth.max())
    assert stats["leaf_size_histogram"] == np.bincount(sizes).tolist()
    assert stats["sah_cost"] == pytest.approx(numpy_sah(tree), rel=1e-6)


def climbed_root_cost(bvh, t1=1.0, t2=1.0):
    """The root of `node_costs`: eq. (1) evaluated bottom-up, the recursive form."""
    from hlbvh_warp.metrics import node_costs

    return float(node_costs(bvh, t1, t2).numpy()[0])


@pytest.mark.parametrize("method", ["hlbvh", "lbvh", "hlbvh_sah", "sweep_sah", "binned_sah", "median"])
def test_one_pass_cost_equals_the_bottom_up_recursion(device, rng, method):
    # `sah_cost` sums term x area over the nodes in one pass; the climb evaluates eq. (1) as written.
    # Zero-area subtrees under a positive root (duplicated points, flat slivers) are where the two
    # forms could part: the sum drops them, the recursion passes their costs through and then
    # scales them by 0.
    v, f = random_soup(rng, 300)
    point = v[f[:40, 0]]
    v = np.concatenate([v, point, point, point]).astype(np.float32)
    k = len(v) - 3 * len(point)
    degenerate = np.stack([np.arange(40), np.arange(40) + 40, np.arange(40) + 80], axis=1) + k
    f = np.concatenate([f, degenerate, degenerate]).astype(np.int32)
    for leaf in (1, 4):
        bvh = hw.build(v, f, method=method, device=device, config=hw.BuildConfig(max_leaf_size=leaf))
        for t1, t2 in ((1.0, 1.0), (1.2, 1.0), (0.0, 2.5)):
            assert sah_cost(bvh, t1, t2) == pytest.approx(climbed_root_cost(bvh, t1, t2), rel=1e-12)
        assert sah_cost(bvh) == pytest.approx(numpy_sah(bvh.to_numpy()), rel=1e-9)


def test_one_pass_cost_takes_scratch_and_rejects_a_short_one(device, rng):
    import warp as wp

    from hlbvh_warp.metrics import sah_scratch_size

    v, f = random_soup(rng, 50)
    bvh = hw.build(v, f, device=device)
    size = sah_scratch_size(bvh.node_left.shape[0], device)
    scratch = wp.empty(size, dtype=wp.float64, device=device)
    assert sah_cost(bvh, scratch=scratch) == pytest.approx(climbed_root_cost(bvh), rel=1e-12)
    with pytest.raises(ValueError, match="scratch"):
        sah_cost(bvh, scratch=wp.empty(size - 1, dtype=wp.float64, device=device))



def test_node_costs_checks_its_scratch(device, rng):
    """`node_costs` writes every node's entry of its scratch pair: short arrays were written past
    their end (the process crashed), other types failed inside Warp. Each is refused by name, and
    the right pair gives the costs of a call without scratch, returned in ``costs``."""
    import warp as wp

    from hlbvh_warp.metrics import node_costs

    v, f = random_soup(rng, 40)
    bvh = hw.build(v, f, device=device)
    capacity = bvh.node_left.shape[0]
    visits = wp.empty(capacity, dtype=wp.int32, device=device)
    costs = wp.empty(capacity, dtype=wp.float64, device=device)
    for bad, name in (((wp.empty(1, dtype=wp.int32, device=device), costs), "visits"),
                      ((visits, wp.empty(capacity - 1, dtype=wp.float64, device=device)), "costs"),
                      ((visits, wp.empty(capacity, dtype=wp.float32, device=device)), "costs"),
                      ((visits.numpy(), costs), "visits"), ((visits,), "pair")):
        with pytest.raises(ValueError, match=name):
            node_costs(bvh, scratch=bad)
    with pytest.raises(ValueError, match="sah_cost scratch"):
        sah_cost(bvh, scratch=np.zeros(capacity))
    used = bvh.num_nodes
    returned = node_costs(bvh, scratch=(visits, costs))
    assert returned is costs
    assert np.array_equal(costs.numpy()[:used], node_costs(bvh).numpy()[:used])

def test_the_cpu_refit_sweep_prices_the_tree_and_only_the_sweep_can(rng):
    import warp as wp

    from hlbvh_warp.hlbvh import compute_bounds
    from hlbvh_warp.metrics import cost_from_sum

    v, f = random_soup(rng, 200)
    bvh = hw.build(v, f, device="cpu", config=hw.BuildConfig(max_leaf_size=2))
    expected = numpy_sah(bvh.to_numpy(), 1.2, 1.0)
    cost_sum = wp.zeros(1, dtype=wp.float64, device="cpu")
    visits = wp.empty(bvh.node_left.shape[0], dtype=wp.int32, device="cpu")
    bvh.node_lowers.zero_()  # the sweep must rebuild every box before it prices it
    args = ["cpu", bvh.node_count, bvh.node_left, bvh.node_right, bvh.node_parent, bvh.node_begin, bvh.node_end,
            bvh.prim_order, bvh.prim_lowers, bvh.prim_uppers, visits, bvh.node_lowers, bvh.node_uppers]
    compute_bounds(*args, "sweep", (1.2, 1.0, cost_sum))
    total = float(cost_sum.numpy()[0])
    assert cost_from_sum(bvh, total, bvh.num_nodes, 1.2, 1.0) == pytest.approx(expected, rel=1e-9)
    with pytest.raises(ValueError, match="sweep"):
        compute_bounds(*args, "climb", (1.2, 1.0, cost_sum))


# ----------------------------------------------------------------- pinned by the mutation audit
@pytest.mark.parametrize("points", ["one point", "one segment"])
def test_bottom_up_costs_pass_through_a_zero_area_root(device, points):
    # `node_costs` (the climb that prices hlbvh_sah's clusters) takes P_hit = 1 under a parent of
    # zero area, as the one-pass `sah_cost` does: C = 2 T1 (N - 1) + T2 N at the root of any
    # binary tree of single-primitive leaves, and each node's cost is that of its own subtree.
    from hlbvh_warp.metrics import node_costs

    n = 11
    pts = np.full((n, 3), 0.25, dtype=np.float32)
    if points == "one segment":
        pts[:, 0] = np.linspace(0.0, 1.0, n, dtype=np.float32)
    bvh = hw.build_from_bounds(pts, pts, method="median", device=device)
    tree = bvh.to_numpy()
    costs = node_costs(bvh, 1.5, 2.0).numpy()[: bvh.num_nodes]
    assert costs[0] == pytest.approx(2 * 1.5 * (n - 1) + 2.0 * n, rel=1e-12)
    sizes = tree["node_end"] - tree["node_begin"]
    np.testing.assert_allclose(costs, 2 * 1.5 * (sizes - 1) + 2.0 * sizes, rtol=1e-12)
    assert costs[0] == pytest.approx(numpy_sah(tree, 1.5, 2.0), rel=1e-12)


def test_tree_stats_counts_and_mean_leaf_size(device, rng):
    v, f = random_soup(rng, 90)
    bvh = hw.build(v, f, method="median", device=device, config=hw.BuildConfig(max_leaf_size=4))
    tree = bvh.to_numpy()
    leaves = tree["node_left"] < 0
    sizes = (tree["node_end"] - tree["node_begin"])[leaves]
    stats = tree_stats(bvh)
    assert (stats["num_prims"], stats["num_refs"]) == (90, 90)
    assert stats["num_interior"] == int((~leaves).sum())
    assert stats["mean_leaf_size"] == pytest.approx(sizes.mean(), rel=1e-12)
    assert stats["mean_leaf_size"] > 1.0


@pytest.mark.parametrize("t1, t2", [(-0.5, 1.0), (1.0, 0.0), (1.0, -1.0), (float("nan"), 1.0), (1.0, float("inf")),
                                    ("1", 1.0), (1.0, None),
                                    # Integers past float's range: float() raised OverflowError.
                                    (10**400, 1.0), (1.0, -(10**400))])
def test_cost_functions_reject_bad_constants(device, t1, t2):
    from hlbvh_warp.metrics import end_point_overlap, node_costs

    lo = np.array([[0, 0, 0], [1, 0, 0]], dtype=np.float32)
    bvh = hw.build_from_bounds(lo, lo + 1, device=device)
    for cost in (sah_cost, node_costs, tree_stats):
        with pytest.raises(ValueError, match="t_intersect|t_traversal"):
            cost(bvh, t1, t2)
    mesh = hw.build(lo[[0, 1, 1]] + np.eye(3, dtype=np.float32), [[0, 1, 2]], device=device)
    with pytest.raises(ValueError, match="t_intersect|t_traversal"):
        end_point_overlap(mesh, t1, t2)


def test_cost_functions_name_a_tree_that_is_not_one(device):
    from hlbvh_warp.metrics import end_point_overlap, node_costs

    lo = np.array([[0, 0, 0], [1, 0, 0]], dtype=np.float32)
    builder = hw.Builder(2, device=device)
    builder.build_from_bounds(lo, lo + 1)
    for cost in (sah_cost, node_costs, tree_stats, end_point_overlap):
        for not_a_tree in (None, builder):
            with pytest.raises(ValueError, match="takes a Bvh"):
                cost(not_a_tree)


# ----------------------------------------------------------------- pinned by the third mutation audit
def test_an_infinite_root_prices_as_nan_without_a_warning(device, rng):
    # A frame that blew up (an infinite vertex written into a Builder's buffer in place): the tree
    # over it is priced as NaN, quietly (`cost_from_sum`), by `auto` as it rebuilds and on request.
    from hlbvh_warp import Builder

    v, f = random_soup(rng, 300)
    bad = v.copy()
    bad[4] = np.inf
    builder = Builder(len(f), device=device, policy="auto")
    builder.build(v, f)
    builder.vertices.assign(bad)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        builder.update()  # no snapshot of the last frame: rebuilt and priced
        assert builder.sah_reference is None
        assert np.isnan(builder.sah_cost()) and np.isnan(sah_cost(builder.bvh))


def test_an_infinite_frame_of_a_flat_scene_prices_as_nan(device, rng):
    # A flat scene (every z = 0) with one infinite x: the root's extent is (inf, y, 0), whose
    # area inf*y + y*0 + 0*inf is NaN, not inf. `root_area > 0` is False for NaN, so the tree was
    # priced by the zero-area formula (a finite 2 T1 (N - 1) + T2 N) with a NumPy warning, and
    # `auto` took that as its reference and refit a tree built over the infinite frame.
    from hlbvh_warp import Builder

    v, f = random_soup(rng, 300)
    v[:, 2] = 0.0
    bad = v.copy()
    bad[4, 0] = np.inf
    builder = Builder(len(f), device=device, policy="auto")
    builder.build(v, f)
    builder.vertices.assign(bad)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        builder.update()
        assert builder.sah_reference is None
        assert np.isnan(builder.sah_cost())
