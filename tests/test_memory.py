"""The host buffer pool: recycled blocks never alias a live array, and builds on recycled memory
equal builds on fresh memory."""

from __future__ import annotations

import gc

import numpy as np
import pytest
import warp as wp

import hlbvh_warp as hw
from hlbvh_warp import memory
from oracles import random_soup


@pytest.fixture
def pool():
    memory.clear_host_cache()
    old = memory._POOL.limit
    yield memory._POOL
    memory.set_host_cache_limit(old)
    memory.clear_host_cache()


def test_block_is_recycled_only_after_its_last_view_dies(pool):
    a = memory.empty(100_000, dtype=wp.int32, device="cpu")
    first_ptr = a.ptr
    sliced = a[10:20]
    as_numpy = a.numpy()
    del a
    gc.collect()
    assert pool.idle_bytes == 0, "a slice and a NumPy view still hold the block"
    b = memory.empty(100_000, dtype=wp.int32, device="cpu")
    assert b.ptr != first_ptr
    del sliced, as_numpy
    gc.collect()
    assert pool.idle_bytes >= 400_000
    c = memory.empty(100_000, dtype=wp.int32, device="cpu")
    assert c.ptr == first_ptr
    assert pool.idle_bytes == 0


def test_small_and_disabled_allocations_bypass_the_pool(pool):
    small = memory.empty(100, dtype=wp.int32, device="cpu")
    del small
    gc.collect()
    assert pool.idle_bytes == 0
    memory.set_host_cache_limit(0)
    big = memory.empty(100_000, dtype=wp.vec3, device="cpu")
    del big
    gc.collect()
    assert pool.idle_bytes == 0


@pytest.mark.parametrize("method", ["hlbvh", "hlbvh_sah", "sweep_sah"])
def test_builds_on_recycled_memory_match_fresh_ones(pool, device, rng, method):
    v, f = random_soup(rng, 20_000)
    memory.set_host_cache_limit(0)
    fresh = hw.build(v, f, method=method, device=device).to_numpy()
    memory.set_host_cache_limit(1 << 30)
    # Fill the pool with blocks that hold another scene's tree, then build on them.
    other_v, other_f = random_soup(rng, 20_000)
    kept = hw.build(v, f, method=method, device=device)
    kept_before = kept.to_numpy()
    scratch = hw.build(other_v, other_f, method=method, device=device)
    del scratch
    gc.collect()
    if wp.get_device(device).is_cpu:
        assert pool.idle_bytes > 0, "the dropped build gave nothing back"
    again = hw.build(v, f, method=method, device=device)
    for key, value in fresh.items():
        assert np.array_equal(again.to_numpy()[key], value), key
    # A live tree is never handed out: the kept build is unchanged by the builds after it.
    for key, value in kept_before.items():
        assert np.array_equal(kept.to_numpy()[key], value), key
