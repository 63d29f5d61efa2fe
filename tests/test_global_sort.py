"""The global sort, one radix sort or two halves side by side merged (CPU), against NumPy's
stable argsort: codes and ids exactly, ties included."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import hlbvh_warp as hw
from hlbvh_warp import hlbvh
from hlbvh_warp.hlbvh import HlbvhPipeline

BITS = 3 * hw.BuildConfig().bits_per_axis


def sorted_by_pipeline(device, codes, cpu_threads=2, input_ids=None):
    n = len(codes)
    pipe = HlbvhPipeline(n, hw.BuildConfig(cpu_threads=cpu_threads), device)
    pipe.morton_codes.assign(wp.array(codes.astype(np.int32), dtype=wp.int32, device=device))
    if input_ids is not None:
        pipe.set_input_ids(wp.array(input_ids.astype(np.int32), dtype=wp.int32, device=device))
    pipe.global_sort()
    return pipe.sorted_codes.numpy()[:n], pipe.sorted_prim_ids.numpy()[:n]


def assert_stable_sort(device, codes, cpu_threads=2, input_ids=None):
    got_codes, got_ids = sorted_by_pipeline(device, codes, cpu_threads, input_ids)
    order = np.argsort(codes, kind="stable")
    ids = order if input_ids is None else input_ids[order]
    np.testing.assert_array_equal(got_codes, codes[order])
    np.testing.assert_array_equal(got_ids, ids)
    return got_codes, got_ids


def adversarial(case, n, rng):
    """Codes of `case`: ties across the halves' boundary, one code, sorted, reversed, random."""
    if case == "ties across the split":
        # Few distinct codes, each spread over both halves: every merge step meets a tie.
        return rng.integers(0, 4, n) << (BITS - 2)
    if case == "equal around the split":
        # One long run of a code from a quarter to three quarters, the rest smaller and larger.
        codes = rng.integers(0, 1 << BITS, n)
        codes[n // 4 : 3 * n // 4] = 1 << (BITS - 1)
        return codes
    if case == "all equal":
        return np.full(n, 12345)
    if case == "sorted":
        return np.sort(rng.integers(0, 1 << BITS, n))
    if case == "reversed":
        return np.sort(rng.integers(0, 1 << BITS, n))[::-1].copy()
    if case == "first half larger":
        # Every code of the first half above every one of the second, and the top bit used.
        return np.concatenate([rng.integers(1 << (BITS - 1), 1 << BITS, n // 2),
                               rng.integers(0, 1 << (BITS - 1), n - n // 2)])
    return rng.integers(0, 1 << BITS, n)


CASES = ["ties across the split", "equal around the split", "all equal", "sorted", "reversed",
         "first half larger", "random"]


@pytest.fixture
def small_threshold(monkeypatch):
    """The side-by-side sort from 64 codes up, so that small adversarial inputs take it."""
    monkeypatch.setattr(hlbvh, "PARALLEL_SORT_MIN_PRIMS", 64)
    return 64


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("n", [64, 65, 1001, 4096 + 3])
def test_global_sort_equals_stable_argsort(device, rng, small_threshold, case, n):
    assert_stable_sort(device, adversarial(case, n, rng))


@pytest.mark.parametrize("threads", [2, 3, 5])
def test_merge_in_more_parts_than_halves(device, rng, small_threshold, threads):
    # The halves' merge is cut into one part per thread; every cut must land on the stable order.
    assert_stable_sort(device, adversarial("ties across the split", 3001, rng), cpu_threads=threads)


@pytest.mark.parametrize("case", ["ties across the split", "random"])
def test_one_thread_and_two_give_the_same_sort(device, rng, small_threshold, case):
    codes = adversarial(case, 2049, rng)
    one = sorted_by_pipeline(device, codes, cpu_threads=1)
    two = sorted_by_pipeline(device, codes, cpu_threads=2)
    np.testing.assert_array_equal(one[0], two[0])
    np.testing.assert_array_equal(one[1], two[1])


@pytest.mark.parametrize("case", ["ties across the split", "all equal", "random"])
def test_sort_carries_input_ids_across_the_halves(device, rng, small_threshold, case):
    # A resorted frame: the sort carries each position's face id, a permutation, not the position.
    n = 3001
    assert_stable_sort(device, adversarial(case, n, rng), input_ids=rng.permutation(n))


def test_ties_come_from_the_first_half_first(device, small_threshold):
    # One code throughout: the stable order is the input order, so the first half's ids must all
    # come before the second's; a merge that took ties from the second half first fails here.
    n = 200
    _, ids = assert_stable_sort(device, np.full(n, 7))
    assert ids[0] == 0 and ids[-1] == n - 1


@pytest.mark.parametrize("offset", [-1, 0, 1])
def test_sizes_around_the_threshold(device, rng, offset):
    # The real threshold: one radix sort below it, the halves from it up; odd and even sizes.
    n = hlbvh.PARALLEL_SORT_MIN_PRIMS + offset
    codes = rng.integers(0, 1 << 10, n) << (BITS - 10)
    assert_stable_sort(device, codes)


def test_lbvh_tree_the_same_with_one_thread_and_two(device, rng, small_threshold):
    # The whole LBVH build goes through the global sort: the same tree on one core and two.
    from oracles import random_soup

    v, f = random_soup(rng, 3000)
    v[: 3 * 1500] = np.round(v[: 3 * 1500], 1)
    trees = [hw.build(v, f, method="lbvh", device=device, config=hw.BuildConfig(cpu_threads=t)).to_numpy()
             for t in (1, 2)]
    for key in ("prim_order", "node_begin", "node_end", "node_left", "node_right"):
        np.testing.assert_array_equal(trees[0][key], trees[1][key])


def test_merge_parts_of_a_large_merge_cover_it_exactly(device, rng):
    """`merge.merge_halves_kernel` cut into many parts: part p of P starts at total * p / P, a
    product past int32 from total * P >= 2^31 (34M codes on a 64-core CPU, one part per core),
    where the parts' bounds wrapped negative and the end of the output was never written. Here
    1.5M codes in 2048 parts, each part launched as the CPU's cores launch it, against NumPy's
    stable merge."""
    from hlbvh_warp.kernels import merge

    total, parts = 3 * (1 << 19) + 7, 2048
    assert total * parts >= 1 << 31
    a_count = total // 2
    b_count = total - a_count
    halves = [np.sort(rng.integers(0, 1 << 12, count)) for count in (a_count, b_count)]
    # The halves sit where the global sort leaves them: the first at 0, the second at 2 a_count.
    keys = np.zeros(2 * total, dtype=np.int32)
    keys[:a_count] = halves[0]
    keys[2 * a_count:2 * a_count + b_count] = halves[1]
    ids = np.arange(2 * total, dtype=np.int32)
    keys_wp = wp.array(keys, dtype=wp.int32, device=device)
    ids_wp = wp.array(ids, dtype=wp.int32, device=device)
    out_keys = wp.full(total, -1, dtype=wp.int32, device=device)
    out_ids = wp.full(total, -1, dtype=wp.int32, device=device)
    for part in range(parts):
        wp.launch(merge.merge_halves_kernel, dim=1,
                  inputs=[keys_wp, ids_wp, a_count, 2 * a_count, b_count, parts, part, out_keys, out_ids],
                  device=device)
    merged_ids = np.concatenate([np.arange(a_count), 2 * a_count + np.arange(b_count)])
    order = np.argsort(np.concatenate(halves), kind="stable")
    np.testing.assert_array_equal(out_keys.numpy(), np.concatenate(halves)[order])
    np.testing.assert_array_equal(out_ids.numpy(), merged_ids[order])
