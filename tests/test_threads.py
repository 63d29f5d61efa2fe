"""Subtrees built side by side on CPU cores give the same tree as one thread."""

from __future__ import annotations

import numpy as np
import pytest

import hlbvh_warp as hw
from hlbvh_warp import threads
from oracles import check_tree_invariants, random_soup

METHODS = ["hlbvh", "lbvh", "hlbvh_sah", "sweep_sah", "binned_sah", "median"]


def canonical(tree):
    """Nodes as (begin, end, box) rows in a fixed order: the tree up to node numbering."""
    rows = np.column_stack([tree["node_begin"], tree["node_end"], tree["node_lowers"], tree["node_uppers"]])
    return rows[np.lexsort(rows.T[::-1])]


@pytest.mark.parametrize("method", METHODS)
def test_threaded_builds_equal_one_thread(device, rng, method):
    # Large enough for every parallel path (top-down: 4096 items; emission: 8192 primitives).
    n = 12_000
    v, f = random_soup(rng, n)
    trees = []
    for count in (1, 2, 3):
        bvh = hw.build(v, f, method=method, device=device, config=hw.BuildConfig(cpu_threads=count))
        tree = bvh.to_numpy()
        check_tree_invariants(tree, n, 1, exact_node_count=2 * n - 1)
        trees.append(tree)
    for tree in trees[1:]:
        assert np.array_equal(tree["prim_order"], trees[0]["prim_order"])
        assert np.array_equal(canonical(tree), canonical(trees[0]))


def test_threaded_leaf_size_falls_back(device, rng):
    # With several primitives per leaf node counts are not known in advance: one thread, same tree.
    v, f = random_soup(rng, 10_000)
    a = hw.build(v, f, method="sweep_sah", device=device, config=hw.BuildConfig(cpu_threads=1, max_leaf_size=4))
    b = hw.build(v, f, method="sweep_sah", device=device, config=hw.BuildConfig(cpu_threads=2, max_leaf_size=4))
    assert np.array_equal(canonical(a.to_numpy()), canonical(b.to_numpy()))


def test_run_reraises_and_runs_every_job():
    done = []

    def ok(i):
        return lambda: done.append(i)

    def bad():
        raise RuntimeError("job failed")

    with pytest.raises(RuntimeError, match="job failed"):
        threads.run([ok(0), bad, ok(2), ok(3)], 2)
    threads.run([ok(4), ok(5), ok(6)], 3)
    assert sorted(done)[-3:] == [4, 5, 6] and {0, 2, 3} <= set(done)


def test_bad_thread_count():
    with pytest.raises(ValueError, match="cpu_threads"):
        hw.BuildConfig(cpu_threads=-1)
