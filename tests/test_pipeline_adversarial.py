"""The HLBVH build pushed to the corners of its configuration space and of its input: settings
that must be refused with a ValueError naming them, and builds whose order, topology and boxes
are checked against independent NumPy references."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

import hlbvh_warp as hb


@pytest.mark.parametrize("bounds", [
    ((0, 0, 0), (10**400, 1, 1)),
    ((-(10**400), 0, 0), (1, 1, 1)),
    # Past Python's 4300-digit limit on printing an integer: the message must still be made.
    ((0, 0, 0), (10**5000, 1, 1)),
    ((0, 0, 0), (10**5000,)),
])
def test_morton_bounds_past_float64_are_refused_with_a_value_error(bounds):
    # NumPy's float64 conversion raised an OverflowError for these, where every other bad
    # setting raises a ValueError naming the field.
    with pytest.raises(ValueError, match="morton_bounds"):
        hb.BuildConfig(morton_bounds=bounds)


def _tree_of(bvh):
    """The tree up to node numbering: its order and the set of (begin, end, is_leaf) nodes."""
    t = bvh.to_numpy()
    nodes = {(int(b), int(e), bool(leaf)) for b, e, leaf in zip(t["node_begin"], t["node_end"], t["node_left"] < 0)}
    return t["prim_order"].tolist(), nodes


@pytest.mark.parametrize("emission", ["depth_first", "treelets"])
@pytest.mark.parametrize("costs", [(2.0**500, 2.0**500), (2.0**996, 2.0**996), (2.0**1020, 2.0**1020), (0.0, 5e-324)])
def test_hlbvh_sah_tree_is_the_same_for_costs_scaled_by_a_power_of_two(device, rng, emission, costs):
    # Eq. (1) is linear in (T1, T2): scaling both by 2^k scales every cluster cost, and every
    # price of the cluster tree's sweep, exactly, so the splits must not change. Costs past 1e300
    # lost to the sweep's "no split yet" mark (1e300), and past float64's range became inf: every
    # cluster split fell back to the index median (an SAH cost 1.27x the unit costs' tree here).
    # The smallest T2 (2^-1074) must not overflow the scale that corrects it.
    lowers = rng.random((3000, 3)).astype(np.float32)
    uppers = lowers + np.float32(0.01)
    unit = hb.BuildConfig(emission=emission, sah_traversal_cost=costs[0] and 1.0)
    scaled = unit.replace(sah_traversal_cost=costs[0], sah_intersection_cost=costs[1])
    expected = _tree_of(hb.build_from_bounds(lowers, uppers, method="hlbvh_sah", config=unit, device=device))
    got = _tree_of(hb.build_from_bounds(lowers, uppers, method="hlbvh_sah", config=scaled, device=device))
    assert got[1] == expected[1] and got[0] == expected[0]


def _top_down_tree(lowers, uppers, weight, mode, emission, device):
    """A `TopDownBuilder` tree over the boxes, every item weighing `weight`."""
    import warp as wp

    from hlbvh_warp.builders import TopDownBuilder, _Arena

    k = len(lowers)
    lo = wp.array(lowers, dtype=wp.vec3, device=device)
    hi = wp.array(uppers, dtype=wp.vec3, device=device)
    weights = wp.full(k, wp.float64(weight), dtype=wp.float64, device=device)
    out = _Arena(wp.get_device(device), k, 2 * k - 1)
    builder = TopDownBuilder(k, device)
    builder.sort_axes(lo, hi)
    builder.build_levels(lo, hi, weights, mode=mode, num_bins=16, max_leaf_size=1, terminate_leaf_size=0,
                         t_traversal=1.0, t_intersect=1.0, node_left=out.node_left, node_right=out.node_right,
                         node_parent=out.node_parent, node_begin=out.node_begin, node_end=out.node_end,
                         node_count=out.node_count, item_order=out.prim_order, emission=emission,
                         binned_above=256)
    return _tree_of(out.to_bvh("sweep_sah", hb.BuildConfig(), lo, hi, {}))


@pytest.mark.parametrize("emission", ["depth_first", "treelets"])
@pytest.mark.parametrize("mode", ["sweep", "binned"])
def test_top_down_splits_are_the_same_for_weights_scaled_by_a_power_of_two(device, rng, mode, emission):
    # The split prices A(L) W(L) + A(R) W(R) scale exactly with the weights. Prices past 1e300
    # (weights of 2^1000 here) never beat the sweep's "no split yet" mark, which was 1e300: every
    # node fell back to the index median.
    from hlbvh_warp.kernels import sah

    lowers = rng.random((1000, 3)).astype(np.float32)
    uppers = lowers + np.float32(0.01)
    rule = {"sweep": sah.MODE_SWEEP, "binned": sah.MODE_BINNED}[mode]
    expected = _top_down_tree(lowers, uppers, 1.0, rule, emission, device)
    got = _top_down_tree(lowers, uppers, 2.0**1000, rule, emission, device)
    assert got[1] == expected[1] and got[0] == expected[0]


def _coincident_reference(lowers, uppers, t1, t2, terminate):
    """The tree a top-down SAH build with termination makes over boxes whose centroids all
    coincide: no plane separates them, so a node of items [b, e) (in index order) can only be
    halved at b + (e - b) // 2; it stays a leaf when that split, priced by eq. (1) in exact
    rational arithmetic, costs at least T2 x its items. Returns the set of (begin, end, is_leaf)."""
    lo = [[Fraction(float(x)) for x in row] for row in lowers]
    hi = [[Fraction(float(x)) for x in row] for row in uppers]

    def area(items):
        d = [max(hi[i][a] for i in items) - min(lo[i][a] for i in items) for a in range(3)]
        return 2 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0])

    nodes = set()
    stack = [(0, len(lowers))]
    while stack:
        b, e = stack.pop()
        size = e - b
        mid = b + size // 2
        if size > 1 and size <= terminate:
            left, right = range(b, mid), range(mid, e)
            price = area(left) * len(left) + area(right) * len(right)
            if 2 * t1 + t2 * price / area(range(b, e)) >= t2 * size:
                size = 1
        if size <= 1:
            nodes.add((b, e, True))
            continue
        nodes.add((b, e, False))
        stack += [(b, mid), (mid, e)]
    return nodes


@pytest.mark.parametrize("emission", ["depth_first", "treelets"])
@pytest.mark.parametrize("case", ["equal boxes", "nested boxes"])
def test_binned_termination_prices_the_split_of_coincident_centroids(device, case, emission):
    # build_top_down's terminate_leaf_size keeps a node a leaf where splitting it costs more under
    # the SAH. Binned SAH finds no bin boundary when every centroid coincides and halves the node
    # by index; that halving was made without the termination test, so eight equal boxes became 15
    # nodes (SAH cost 22) where the leaf costs 8, and sweep_sah keeps the leaf.
    import warp as wp

    from hlbvh_warp.builders import build_top_down
    from hlbvh_warp.hlbvh import StageTimer

    if case == "equal boxes":
        lowers = np.zeros((8, 3), np.float32)
        uppers = np.ones((8, 3), np.float32)
        t1 = 1.0
    else:
        # One centroid, boxes of two sizes: splitting the small pair from the large one pays when
        # a traversal step is cheap.
        half = np.array([1, 1, 1, 1, 64, 64, 64, 64], np.float32)[:, None] * np.ones(3, np.float32)
        lowers, uppers = -half, half
        t1 = 0.125
    config = hb.BuildConfig(sah_traversal_cost=t1, sah_intersection_cost=1.0, emission=emission)
    bvh = build_top_down(wp.array(lowers, dtype=wp.vec3, device=device), wp.array(uppers, dtype=wp.vec3, device=device),
                         config, device, StageTimer(device, False), method="binned_sah", terminate_leaf_size=8)
    expected = _coincident_reference(lowers, uppers, Fraction(t1), Fraction(1), 8)
    assert _tree_of(bvh)[1] == expected


def test_a_bad_setting_beside_an_overlong_morton_bounds_corner_is_named():
    # The message of any other bad setting prints the whole config, morton_bounds (not checked
    # yet) included; a corner of more than 4300 digits made that print raise Python's own
    # ValueError on long integers instead.
    with pytest.raises(ValueError, match="bits_per_axis must be in"):
        hb.BuildConfig(bits_per_axis=11, morton_bounds=((0, 0, 0), (10**5000, 1, 1)))
    # Otherwise the message shows the config as its repr does.
    with pytest.raises(ValueError) as error:
        hb.BuildConfig(bits_per_axis=11)
    assert str(error.value).endswith(f"(got {hb.BuildConfig.__repr__(hb.BuildConfig()).replace('=10,', '=11,', 1)})")


def test_a_stage_timer_finished_twice_totals_its_stages_once():
    """`StageTimer.finish` summed every entry but "skipped" into "total", so a second call counted
    the first call's total in as a stage: twice the stages' sum."""
    from hlbvh_warp.hlbvh import StageTimer

    timer = StageTimer("cpu", True)
    timer.stage("first")
    sum(range(10000))
    timer.stage("second")
    timer.finish()
    timings = timer.finish()
    stages = [v for k, v in timings.items() if k not in ("skipped", "total")]
    assert len(stages) == 2
    assert timings["total"] == pytest.approx(sum(stages), rel=1e-12)
