"""The HLBVH build pushed to the corners of its configuration space and of its input: settings
that must be refused with a ValueError naming them, and builds whose order, topology and boxes
are checked against independent NumPy references."""

from __future__ import annotations

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
@pytest.mark.parametrize("exponent", [500, 996, 1020])
def test_hlbvh_sah_tree_is_the_same_for_costs_scaled_by_a_power_of_two(device, rng, emission, exponent):
    # Eq. (1) is linear in (T1, T2): scaling both by 2^k scales every cluster cost, and every
    # price of the cluster tree's sweep, exactly, so the splits must not change. Costs past 1e300
    # lost to the sweep's "no split yet" mark (1e300), and past float64's range became inf: every
    # cluster split fell back to the index median (an SAH cost 1.27x the unit costs' tree here).
    lowers = rng.random((3000, 3)).astype(np.float32)
    uppers = lowers + np.float32(0.01)
    unit = hb.BuildConfig(emission=emission)
    scaled = unit.replace(sah_traversal_cost=2.0**exponent, sah_intersection_cost=2.0**exponent)
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
