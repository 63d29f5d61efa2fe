"""The host buffer pool: recycled blocks never alias a live array, and builds on recycled memory
equal builds on fresh memory."""

from __future__ import annotations

import gc

import numpy as np
import pytest
import warp as wp

import hlbvh_warp as hw
from hlbvh_warp import api, memory
from hlbvh_warp.hlbvh import PARALLEL_MIN_PRIMS, StageTimer
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


@pytest.mark.parametrize("method", ["hlbvh", "lbvh", "hlbvh_sah"])
def test_one_shot_builds_reuse_the_pipeline_but_never_its_outputs(pool, device, rng, method):
    v, f = random_soup(rng, 5_000)
    other_v, other_f = random_soup(rng, 5_000)
    memory.set_host_cache_limit(0)
    expected = hw.build(other_v, other_f, method=method, device=device).to_numpy()
    assert not memory._SCRATCH._entries, "a disabled pool keeps no scratch"
    memory.set_host_cache_limit(1 << 30)
    first = hw.build(v, f, method=method, device=device)
    first_arrays = first.to_numpy()
    ((kept, _),) = memory._SCRATCH._entries.values()
    second = hw.build(other_v, other_f, method=method, device=device)
    reused = next(iter(memory._SCRATCH._entries.values()))[0]
    assert reused is kept, "the second build did not reuse the first's pipeline"
    for name in ("node_left", "node_lowers", "prim_order"):
        assert getattr(first, name).ptr != getattr(second, name).ptr, name
    for key, value in first_arrays.items():
        assert np.array_equal(first.to_numpy()[key], value), key
    for key, value in expected.items():
        assert np.array_equal(second.to_numpy()[key], value), key
    memory.clear_host_cache()
    assert not memory._SCRATCH._entries


@pytest.mark.parametrize("method", ["hlbvh", "lbvh", "hlbvh_sah"])
def test_one_shot_build_over_refilled_box_arrays(pool, device, rng, method):
    """A caller may refill the same box arrays between one-shot builds, which share a kept
    pipeline: the second tree must be the one a build with nothing kept gives. (The leaf-box
    gather once kept its views over the first build's ids, keyed by the boxes' addresses only,
    and gathered the second build's boxes in the first build's order.)"""
    # Enough primitives, and two threads, for the CPU's sliced launches.
    n = 3 * PARALLEL_MIN_PRIMS
    config = hw.BuildConfig(cpu_threads=2)
    timer = StageTimer(device, False)
    centers = rng.random((2, n, 3)).astype(np.float32)
    sizes = (0.01 * rng.random((2, n, 3))).astype(np.float32)
    lowers = wp.array(centers[0] - sizes[0], dtype=wp.vec3, device=device)
    uppers = wp.array(centers[0] + sizes[0], dtype=wp.vec3, device=device)
    api.BUILDERS[method](lowers, uppers, config, device, timer)
    lowers.assign(centers[1] - sizes[1])
    uppers.assign(centers[1] + sizes[1])
    second = api.BUILDERS[method](lowers, uppers, config, device, timer).to_numpy()

    memory.set_host_cache_limit(0)
    expected = hw.build_from_bounds(centers[1] - sizes[1], centers[1] + sizes[1], method=method, device=device,
                                    config=config).to_numpy()
    for key in ("prim_order", "node_left", "node_right", "node_lowers", "node_uppers"):
        np.testing.assert_array_equal(second[key], expected[key], err_msg=key)
    # And against the boxes themselves: every leaf's box is its primitive's.
    leaves = np.flatnonzero(second["node_end"] - second["node_begin"] == 1)
    prims = second["prim_order"][second["node_begin"][leaves]]
    np.testing.assert_array_equal(second["node_lowers"][leaves], centers[1][prims] - sizes[1][prims])


def _kept_by_size():
    return {key[1]: scratch for key, (scratch, _) in memory._SCRATCH._entries.items()}


def test_one_shot_builds_of_several_meshes_each_keep_their_pipeline(pool, device, rng):
    """A scene of several meshes built one-shot in turn gets every mesh's pipeline back (with
    room for only two sets, the third mesh evicted the first every time)."""
    meshes = [random_soup(rng, n) for n in (3000, 4000, 5000, 6000)]
    for v, f in meshes:
        hw.build(v, f, device=device)
    first = _kept_by_size()
    assert sorted(first) == [3000, 4000, 5000, 6000]
    for v, f in meshes:
        hw.build(v, f, device=device)
    again = _kept_by_size()
    for n, scratch in first.items():
        assert again[n] is scratch, f"the {n}-triangle mesh got a new pipeline"
    assert memory._SCRATCH.held_bytes == sum(nbytes for _, nbytes in memory._SCRATCH._entries.values())


def test_scratch_cache_keeps_to_the_byte_limit(pool, device, rng):
    """The kept sets never hold more than the pool's limit; the oldest go first, and lowering
    the limit drops sets at once."""
    v, f = random_soup(rng, 5000)
    hw.build(v, f, device=device)
    ((_, one_set),) = memory._SCRATCH._entries.values()
    assert one_set > 0
    # Room for one set of this size: a second mesh's set replaces the first.
    memory.set_host_cache_limit(one_set + one_set // 2)
    hw.build(v, f, device=device)
    other_v, other_f = random_soup(rng, 5001)
    hw.build(other_v, other_f, device=device)
    assert sorted(_kept_by_size()) == [5001]
    assert memory._SCRATCH.held_bytes <= one_set + one_set // 2
    memory.set_host_cache_limit(one_set // 2)
    assert not memory._SCRATCH._entries and memory._SCRATCH.held_bytes == 0
    # A set larger than the limit is not kept at all.
    hw.build(v, f, device=device)
    assert not memory._SCRATCH._entries


def test_idle_blocks_and_scratch_sets_share_one_limit(pool, device, rng):
    """Each used to be checked against the limit alone, so the two together held up to twice it
    (15.9 MB under an 8 MB limit, over builds of varying sizes)."""
    hw.build(*random_soup(rng, 4000), device=device)
    ((_, one_set),) = memory._SCRATCH._entries.values()
    limit = 3 * one_set
    memory.set_host_cache_limit(limit)
    most = 0
    for n in (4000, 4100, 4200, 4300, 4400, 4500, 4000, 4600, 4700):
        bvh = hw.build(*random_soup(rng, n), device=device)
        del bvh
        gc.collect()
        assert memory.host_cache_bytes() == memory._POOL.idle_bytes + memory._SCRATCH.held_bytes
        most = max(most, memory.host_cache_bytes())
        assert memory.host_cache_bytes() <= limit, n
    assert most > limit // 2  # the cache was in use, near its limit
    memory.set_host_cache_limit(one_set)
    assert memory.host_cache_bytes() <= one_set


def test_scratch_cache_sets_setting(pool, device, rng):
    """`set_scratch_cache_sets` caps the kept sets at once; 0 keeps none; a negative count is an error."""
    old = memory._SCRATCH.max_entries
    try:
        for n in (3000, 4000, 5000):
            hw.build(*random_soup(rng, n), device=device)
        assert len(memory._SCRATCH._entries) == 3
        memory.set_scratch_cache_sets(1)
        assert sorted(_kept_by_size()) == [5000]
        memory.set_scratch_cache_sets(0)
        hw.build(*random_soup(rng, 3000), device=device)
        assert not memory._SCRATCH._entries and memory._SCRATCH.held_bytes == 0
        for bad in (-1, 2.5, True, "3"):
            with pytest.raises(ValueError, match="count"):
                memory.set_scratch_cache_sets(bad)
        assert memory._SCRATCH.max_entries == 0
    finally:
        memory.set_scratch_cache_sets(old)


def test_host_cache_limit_must_be_a_byte_count(pool):
    # -1 and 1.5 were taken as limits (int() of them), "x" failed inside int().
    old = memory._POOL.limit
    for bad in (-1, 1.5, True, "x"):
        with pytest.raises(ValueError, match="limit_bytes"):
            memory.set_host_cache_limit(bad)
    assert memory._POOL.limit == old


GC_REENTRY_SCRIPT = """
import gc
import warp as wp
wp.config.quiet = True
from hlbvh_warp import memory

class Scene:  # a user object in a reference cycle, holding a pooled array
    def __init__(self, size):
        self.buf = memory.empty(size, dtype=wp.uint8, device="cpu")
        self.me = self

gc.set_threshold(1)  # a collection at nearly every allocation, the pool's own included
for i in range(1500):
    a = memory.empty((1 << 16) * (i + 2), dtype=wp.uint8, device="cpu")  # a new size class
    s = Scene((1 << 16) * (5000 + i))
    del s  # cyclic garbage holding a pooled block
    del a  # its finalizer gives a block back; a collection inside may give back the other
    if i % 200 == 0:
        memory.clear_host_cache()
print("done")
"""


def test_a_collection_inside_the_pool_does_not_deadlock():
    # The pool gives blocks back from finalizers. The garbage collector may run one on a thread
    # that holds the pool's lock (an allocation under it collecting a cycle that held a pooled
    # array): with a plain lock the process hung there. In a subprocess, so a regression fails
    # by timeout instead of hanging the suite.
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-c", GC_REENTRY_SCRIPT], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.strip().endswith("done")


def test_pool_keeps_blocks_up_to_its_limit_exactly_and_drops_them_when_lowered(pool):
    # A block whose size class fills the limit exactly is kept (at most `limit` idle bytes);
    # one byte less and it goes back to the system; lowering the limit below what is idle
    # drops the idle blocks at once.
    nbytes = 400_000
    size = memory._size_class(nbytes)
    assert nbytes <= size < nbytes + max(nbytes // 8, memory.MIN_POOLED_BYTES)
    memory.set_host_cache_limit(size)
    a = memory.empty(nbytes // 4, dtype=wp.int32, device="cpu")
    del a
    gc.collect()
    assert memory.host_cache_bytes() == size
    memory.set_host_cache_limit(size - 1)
    assert memory.host_cache_bytes() == 0
    b = memory.empty(nbytes // 4, dtype=wp.int32, device="cpu")
    del b
    gc.collect()
    assert memory.host_cache_bytes() == 0


def test_scratch_cache_counts_a_replaced_set_once():
    # Giving back a set under a key that is still held replaces it: its bytes are counted once.
    cache = memory.ScratchCache(max_entries=4)
    cache.give_back("a", object(), 100)
    cache.give_back("a", object(), 300)
    cache.give_back("b", object(), 50)
    assert cache.held_bytes == 350
    assert cache.take("a") is not None and cache.held_bytes == 50
    cache.trim(0)
    assert cache.held_bytes == 0 and not cache._entries


# ----------------------------------------------------------------- pinned by the second mutation audit
KIB = 1024


@pytest.mark.parametrize("set_first", [True, False])
def test_idle_blocks_and_kept_sets_share_one_cap_either_way_round(pool, set_first):
    limit = 4 * 1024 * KIB
    memory.set_host_cache_limit(limit)
    if set_first:
        memory.give_back_scratch("set", object(), 3 * 1024 * KIB)
    block = memory.empty(2 * 1024 * KIB // 4, wp.float32, "cpu")
    del block
    gc.collect()
    if not set_first:
        memory.give_back_scratch("set", object(), 3 * 1024 * KIB)
    assert 0 < memory.host_cache_bytes() <= limit


def test_trim_drops_the_largest_blocks_first_and_no_more_than_asked():
    pool = memory.HostBufferPool(limit=1 << 30)
    blocks = [pool.empty(n // 4, wp.float32, "cpu") for n in (64 * KIB, 128 * KIB, 1024 * KIB)]
    del blocks
    gc.collect()
    total = pool.idle_bytes
    pool.trim(total)  # already within: nothing goes
    assert pool.idle_bytes == total
    pool.trim(total - 1)  # the largest block goes, and only it
    assert sorted(size for size, idle in pool._idle.items() for _ in idle) == [64 * KIB, 128 * KIB]


def test_a_set_larger_than_the_cap_is_not_kept_and_evicts_nothing(pool):
    memory.set_host_cache_limit(1024 * KIB)
    memory.give_back_scratch("small", object(), 100 * KIB)
    memory.give_back_scratch("huge", object(), 2048 * KIB)
    assert memory.take_scratch("huge") is None
    assert memory.take_scratch("small") is not None


def test_pooling_starts_at_its_documented_size_and_classes_waste_at_most_an_eighth(pool):
    array = memory.empty(memory.MIN_POOLED_BYTES // 4, wp.int32, "cpu")
    del array
    gc.collect()
    assert memory._POOL.idle_bytes == memory.MIN_POOLED_BYTES
    sizes = np.arange(512 * KIB + 4, 4096 * KIB, 36 * KIB + 4)
    assert max(memory._size_class(int(n)) / n - 1.0 for n in sizes) <= 0.125
    assert all(memory._size_class(int(n)) >= n for n in sizes)


@pytest.mark.parametrize("planes", [1, 3, 4])
def test_only_the_treelet_schedule_holds_the_treelet_passes_scratch(device, rng, planes):
    """The treelet passes (Pantaleoni & Luebke 2010, Fig. 4) keep per primitive a head flag, its
    node and end, a segment id, head, end and node, a split count and offset, and 2^p - 1 split
    positions: 8 + 2^p ints, and two counters. The depth-first schedule emits the same splits
    from the sorted codes and reads none of them, so it holds none; it holds the tree-order leaf
    boxes instead (two vec3 per primitive). Both schedules build the same tree."""
    from hlbvh_warp.config import BuildConfig
    from hlbvh_warp.hlbvh import HlbvhPipeline

    n = 3000
    lo = rng.random((n, 3)).astype(np.float32)
    trees = {}
    held = {}
    for emission in ("depth_first", "treelets"):
        config = BuildConfig(planes_per_pass=planes, emission=emission)
        held[emission] = HlbvhPipeline(n, config, device).held_bytes()
        tree = hw.build_from_bounds(lo, lo + 0.01, device=device, config=config).to_numpy()
        # The schedules number the nodes differently: compare the order and the node ranges.
        ranges = {(int(b), int(e), int(left) < 0)
                  for b, e, left in zip(tree["node_begin"], tree["node_end"], tree["node_left"])}
        trees[emission] = (tree["prim_order"].tolist(), ranges)
    treelet_ints = (8 + 2**planes) * n + 2
    assert held["treelets"] - held["depth_first"] == 4 * treelet_ints - 2 * 12 * n
    assert trees["depth_first"] == trees["treelets"]
