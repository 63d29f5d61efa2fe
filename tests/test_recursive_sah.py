"""The recursive-SAH builder (Wodniok & Goesele 2016) against a plain-Python build of the same
rule: temporary greedy binned-SAH BVHs priced by their recursive SAH cost."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import warp as wp

import hlbvh_warp as hw
from hlbvh_warp import metrics
from hlbvh_warp.recursive_sah import _side_costs
from oracles import (brute_force_closest_hit, check_tree_invariants, random_rays, random_soup,
                     sphere_past_float32_extent)


def boxes(v, f):
    tri = v[f]
    return tri.min(axis=1).astype(np.float32), tri.max(axis=1).astype(np.float32)


def area(lo, hi):
    d = np.asarray(hi, np.float64) - np.asarray(lo, np.float64)
    return 2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0])


def bins_of(c, lo, ext, num_bins):
    if ext <= 0:
        return np.zeros(len(c), np.int64)
    return np.clip(((np.float32(num_bins) * (c - lo)) / ext).astype(np.int64), 0, num_bins - 1)


def best_binned_split(ids, lo, hi, num_bins, score):
    """(axis, boundary, left ids, right ids) of least score(left, right), first in (axis,
    boundary) order among equals, or None when every centroid coincides."""
    c = np.float32(0.5) * (lo[ids] + hi[ids])
    c_lo, c_hi = c.min(0), c.max(0)
    best = None
    for axis in range(3):
        ext = np.float32(c_hi[axis] - c_lo[axis])
        if ext <= 0:
            continue
        b = bins_of(c[:, axis], c_lo[axis], ext, num_bins)
        for j in range(1, num_bins):
            left, right = ids[b < j], ids[b >= j]
            if len(left) and len(right):
                cost = score(left, right)
                if best is None or cost < best[0]:
                    best = (cost, left, right)
    return None if best is None else best[1:]


def temp_cost(ids, lo, hi, num_bins, max_leaf, t1, t2):
    """sum of term(n) * area(n) over a greedy binned-SAH BVH of `ids`, by recursion."""
    a = area(lo[ids].min(0), hi[ids].max(0))
    if len(ids) <= max_leaf:
        return t2 * len(ids) * a

    def sah(left, right):
        return (area(lo[left].min(0), hi[left].max(0)) * len(left)
                + area(lo[right].min(0), hi[right].max(0)) * len(right))

    split = best_binned_split(ids, lo, hi, num_bins, sah)
    if split is None:
        split = ids[: len(ids) // 2], ids[len(ids) // 2:]
    return 2 * t1 * a + sum(temp_cost(s, lo, hi, num_bins, max_leaf, t1, t2) for s in split)


def numpy_recursive_sah(lo, hi, bins=64, temp_bins=32, max_leaf=1, t1=1.0, t2=1.0):
    """The set of primitive sets of every node of the recursive-SAH tree."""
    nodes = []
    memo = {}

    def cached_cost(ids):
        # Empty bins give candidates the same sides: price each side once.
        key = ids.tobytes()
        if key not in memo:
            memo[key] = temp_cost(ids, lo, hi, temp_bins, max_leaf, t1, t2)
        return memo[key]

    def build(ids):
        nodes.append(frozenset(ids.tolist()))
        if len(ids) <= max_leaf:
            return

        def rated(left, right):
            return sum(cached_cost(s) for s in (left, right))

        split = best_binned_split(ids, lo, hi, bins, rated)
        if split is None:
            split = ids[: len(ids) // 2], ids[len(ids) // 2:]
        for s in split:
            build(s)

    build(np.arange(len(lo)))
    return sorted(nodes, key=sorted)


def tree_sets(bvh):
    t = bvh.to_numpy()
    order = t["prim_order"]
    return sorted((frozenset(order[t["node_begin"][n]:t["node_end"][n]].tolist()) for n in range(bvh.num_nodes)),
                  key=sorted)


# T1 > 0: with T1 = 0 trees of different shapes over the same leaves tie exactly, and the two
# builds' sums, taken in different orders, break such ties differently.
@pytest.mark.parametrize("bins, temp_bins, leaf, t1, t2", [(64, 32, 1, 1.0, 1.0), (8, 4, 3, 1.2, 1.0),
                                                           (16, 32, 2, 0.5, 2.0)])
def test_tree_equals_a_python_build_of_the_same_rule(device, rng, bins, temp_bins, leaf, t1, t2):
    v, f = random_soup(rng, 22, scale=0.3)
    config = hw.BuildConfig(recursive_sah_bins=bins, recursive_sah_temp_bins=temp_bins, max_leaf_size=leaf,
                            sah_traversal_cost=t1, sah_intersection_cost=t2)
    bvh = hw.build(v, f, method="recursive_sah", device=device, config=config)
    check_tree_invariants(bvh.to_numpy(), len(f), max_leaf_size=leaf)
    lo, hi = boxes(v, f)
    assert tree_sets(bvh) == numpy_recursive_sah(lo, hi, bins, temp_bins, leaf, t1, t2)


def test_temporary_bvh_costs_against_a_recursion(device, rng):
    v, f = random_soup(rng, 60, scale=0.4)
    lo, hi = boxes(v, f)
    config = hw.BuildConfig(recursive_sah_temp_bins=8, max_leaf_size=2, sah_traversal_cost=1.2)
    sides = [rng.permutation(60)[: rng.integers(1, 60)] for _ in range(12)]
    scratch = np.concatenate(sides).astype(np.int32)
    lasts = np.cumsum([len(s) for s in sides])
    firsts = lasts - [len(s) for s in sides]
    costs = _side_costs(scratch, firsts, lasts, wp.array(lo, dtype=wp.vec3, device=device),
                        wp.array(hi, dtype=wp.vec3, device=device), config, device)
    expected = [temp_cost(s, lo, hi, 8, 2, 1.2, 1.0) for s in sides]
    np.testing.assert_allclose(costs, expected, rtol=1e-12)


def test_rays_and_quality_against_the_sweep(device, rng):
    v, f = random_soup(rng, 400, scale=0.1)
    bvh = hw.build(v, f, method="recursive_sah", device=device, config=hw.BuildConfig(recursive_sah_bins=16))
    check_tree_invariants(bvh.to_numpy(), len(f))
    o, d = random_rays(rng, v, 300)
    t, prim = hw.intersect(bvh, o, d)
    t_ref, prim_ref = brute_force_closest_hit(v, f, o, d)
    from hlbvh_warp.reference import count_mismatches

    assert count_mismatches(t, prim, t_ref, prim_ref) == 0
    # Rated by real subtrees rather than the linear estimate, the splits beat the greedy sweep here.
    sweep = hw.build(v, f, method="sweep_sah", device=device)
    assert metrics.sah_cost(bvh) < metrics.sah_cost(sweep)


def test_coincident_centroids_are_halved(device):
    # Forty copies of one triangle and one other: no bin boundary separates the copies.
    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    v = np.concatenate([np.repeat(tri[None], 40, axis=0).reshape(-1, 3), tri + 5]).astype(np.float32)
    f = np.arange(len(v), dtype=np.int32).reshape(-1, 3)
    bvh = hw.build(v, f, method="recursive_sah", device=device)
    check_tree_invariants(bvh.to_numpy(), len(f))
    # The odd one out is split off first.
    sets = tree_sets(bvh)
    assert frozenset([40]) in sets and frozenset(range(40)) in sets


def test_recursive_sah_config_is_checked():
    for kwargs in ({"recursive_sah_bins": 1}, {"recursive_sah_bins": 257}, {"recursive_sah_temp_bins": 33}):
        with pytest.raises(ValueError, match="recursive_sah"):
            hw.BuildConfig(**kwargs)


def test_odd_groups_of_coincident_centroids_equal_the_python_build(device, rng):
    # Groups of copies with no bin boundary between them, of odd sizes: halved in their current
    # order, the first floor(n / 2) to the left, as the Python build of the rule does.
    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    copies = [np.repeat(tri[None] + shift, count, axis=0) for shift, count in ((0.0, 7), (3.0, 5), (-2.0, 3))]
    others = rng.random((6, 3, 3)).astype(np.float32) * 4.0 - 2.0
    v = np.concatenate(copies + [others]).reshape(-1, 3)
    f = np.arange(len(v), dtype=np.int32).reshape(-1, 3)
    bvh = hw.build(v, f, method="recursive_sah", device=device,
                   config=hw.BuildConfig(recursive_sah_bins=16, recursive_sah_temp_bins=8))
    check_tree_invariants(bvh.to_numpy(), len(f))
    lo, hi = boxes(v, f)
    assert tree_sets(bvh) == numpy_recursive_sah(lo, hi, 16, 8)


def test_temporary_bvh_of_a_chain_stays_within_its_stack(device):
    # Centroids 0 and 3^k with two temporary bins: every split peels off the largest box alone, a
    # chain of depth N. Building the smaller side first keeps one deferred sibling on the stack;
    # the other way round, the stack (64 entries) overflowed at N > 64.
    num = 81
    x = np.concatenate([[0.0], 3.0 ** np.arange(num - 1)])
    lo = np.stack([x - x / 8, np.zeros(num), np.zeros(num)], 1).astype(np.float32)
    hi = np.stack([x + x / 8, np.ones(num), np.ones(num)], 1).astype(np.float32)
    config = hw.BuildConfig(recursive_sah_temp_bins=2, max_leaf_size=1)
    ids = np.random.default_rng(5).permutation(num).astype(np.int32)
    costs = _side_costs(ids, np.array([0]), np.array([num]), wp.array(lo, dtype=wp.vec3, device=device),
                        wp.array(hi, dtype=wp.vec3, device=device), config, device)
    np.testing.assert_allclose(costs, [temp_cost(ids, lo, hi, 2, 1, 1.0, 1.0)], rtol=1e-12)


def test_temporary_bvh_halves_coincident_centroids_in_order(device, rng):
    # Boxes of one centroid and different sizes: no bin boundary separates them, so the range
    # is halved in its order, the first floor(n / 2) to the left, as the recursion does.
    num = 7
    half = rng.integers(1, 64, (num, 3)) / 16.0  # dyadic: the centroids are exact
    lo, hi = (0.5 - half).astype(np.float32), (0.5 + half).astype(np.float32)
    assert (np.float32(0.5) * (lo + hi) == np.float32(0.5)).all()
    config = hw.BuildConfig(recursive_sah_temp_bins=4, max_leaf_size=1, sah_traversal_cost=1.2)
    sides = [rng.permutation(num)[:k].astype(np.int32) for k in (3, 5, 7)]
    lasts = np.cumsum([len(s) for s in sides])
    costs = _side_costs(np.concatenate(sides), lasts - [len(s) for s in sides], lasts,
                        wp.array(lo, dtype=wp.vec3, device=device), wp.array(hi, dtype=wp.vec3, device=device),
                        config, device)
    np.testing.assert_allclose(costs, [temp_cost(s, lo, hi, 4, 1, 1.2, 1.0) for s in sides], rtol=1e-12)


def test_centroids_near_the_largest_float32(device, rng):
    """Vertices in [2^127, 2^128), finite float32 the input checks accept: lower + upper of every
    centroid overflowed float32 to inf, in the host's binning of the splits and in the
    temporary BVHs, and the tree came out ten times the SAH cost of the same mesh scaled down by
    2^127. Scaled by a power of two (every value normal, 64 and 32 bins) every decision is the
    same: the tree must be that mesh's."""
    n = 120
    unit = (1.0 + 0.9 * rng.random((n, 3))).astype(np.float32)
    corners = np.stack([unit, unit + (0.03 * rng.random((n, 3))).astype(np.float32),
                        unit + (0.03 * rng.random((n, 3))).astype(np.float32)], axis=1)
    v = corners.reshape(-1, 3)
    f = np.arange(3 * n, dtype=np.int32).reshape(n, 3)
    big = (v.astype(np.float64) * 2.0**127).astype(np.float32)
    with np.errstate(over="ignore"):
        assert np.isinf(big[0::3] + big[1::3]).all()  # the scene does what the test means
    tree = hw.build(big, f, method="recursive_sah", device=device).to_numpy()
    expected = hw.build(v, f, method="recursive_sah", device=device).to_numpy()
    for name in ("node_left", "node_right", "node_begin", "node_end", "prim_order"):
        np.testing.assert_array_equal(tree[name], expected[name], err_msg=name)


def test_centroid_extent_past_the_float32_range(device, rng):
    """A sphere of radius 1.7 x 2^127 (2.9e38), finite float32 the input checks accept: the
    centroids span more than float32's largest value, the float32 extent of the root's (and its
    large children's) centroids overflowed to inf, every centroid fell in bin 0, no candidate
    split the node and it was halved in its (shuffled) face order: 6.4 times the SAH cost of the
    same sphere scaled down by 2^127, with NumPy overflow warnings. Scaled down, every extent is
    finite; the splits must cost what that sphere's do."""
    small, big, f = sphere_past_float32_extent(rng)
    config = hw.BuildConfig(recursive_sah_bins=16, recursive_sah_temp_bins=8)
    expected = metrics.sah_cost(hw.build(small, f, method="recursive_sah", device=device, config=config))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        bvh = hw.build(big, f, method="recursive_sah", device=device, config=config)
    check_tree_invariants(bvh.to_numpy(), len(f))
    assert metrics.sah_cost(bvh) == pytest.approx(expected, rel=0.01)
