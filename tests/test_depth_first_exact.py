"""The depth-first emission (`treelets.emit_depth_first_kernel`) against independent NumPy oracles,
the whole tree bit for bit: the node numbering of a top-down walk that takes its node pairs in
depth-first order, and every node box as the CPU's NaN-skipping min/max folds it (the leftmost
extreme of the range's non-NaN values, else its first value), on meshes, random soups, ranges of
equal codes and boxes with NaN (of several payloads), signed zeros, infinities and zero size."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
import warp as wp
from oracles import check_tree_invariants

import hlbvh_warp as hb
from hlbvh_warp.hlbvh import PARALLEL_MIN_PRIMS, HlbvhPipeline


# --------------------------------------------------------------------------- oracles
def oracle_split(codes, a, b):
    """The radix split of the sorted range [a, b): the first code with the highest differing bit set,
    the index median when all codes are equal (Pantaleoni & Luebke 2010, section 3.2)."""
    if codes[a] == codes[b - 1]:
        return (a + b + 1) // 2
    bit = int(codes[a] ^ codes[b - 1]).bit_length() - 1
    return a + int(np.searchsorted((codes[a:b] >> bit) & 1, 1))


def oracle_topology(codes, max_leaf_size):
    """Children, parents and ranges of the walk that pops a node, takes the next two ids for its
    children, and goes on with the left one (ids 1, 2 for the root's children)."""
    n = len(codes)
    left = np.full(2 * n - 1, -1, np.int64)
    right = np.full(2 * n - 1, -1, np.int64)
    parent = np.full(2 * n - 1, -1, np.int64)
    begin = np.zeros(2 * n - 1, np.int64)
    end = np.zeros(2 * n - 1, np.int64)
    end[0] = n
    next_id = 1
    stack = [0]
    while stack:
        node = stack.pop()
        a, b = begin[node], end[node]
        if b - a <= max_leaf_size:
            continue
        split = oracle_split(codes, a, b)
        lo, hi = next_id, next_id + 1
        next_id += 2
        left[node], right[node] = lo, hi
        parent[lo] = parent[hi] = node
        begin[lo], end[lo], begin[hi], end[hi] = a, split, split, b
        stack += [hi, lo]
    return {"node_left": left[:next_id], "node_right": right[:next_id], "node_parent": parent[:next_id],
            "node_begin": begin[:next_id], "node_end": end[:next_id]}


def fold_extreme(values, smallest):
    """Per column, the float32 a left-to-right fold of C's fmin (fmax) with ties kept gives: the
    first value equal to the extreme of the non-NaN values, or the first value if all are NaN."""
    out = values[0].copy()
    for c in range(values.shape[1]):
        col = values[:, c]
        finite = ~np.isnan(col)
        if finite.any():
            target = col[finite].min() if smallest else col[finite].max()
            out[c] = col[np.flatnonzero(finite & (col == target))[0]]
    return out


def oracle_boxes(tree, lowers, uppers):
    order = tree["prim_order"]
    lo = np.array([fold_extreme(lowers[order[b:e]], True) for b, e in zip(tree["node_begin"], tree["node_end"])])
    hi = np.array([fold_extreme(uppers[order[b:e]], False) for b, e in zip(tree["node_begin"], tree["node_end"])])
    return lo.astype(np.float32), hi.astype(np.float32)


def oracle_costs(tree, t_traversal, t_intersect):
    """Eq. (1) of Pantaleoni & Luebke 2010 in float64, children first; a parent of zero area
    passes its children's costs through unweighted."""
    lo = tree["node_lowers"].astype(np.float64)
    hi = tree["node_uppers"].astype(np.float64)
    d = hi - lo
    area = 2.0 * (d[:, 0] * d[:, 1] + d[:, 1] * d[:, 2] + d[:, 2] * d[:, 0])
    left, right = tree["node_left"], tree["node_right"]
    cost = np.zeros(len(left))
    for i in range(len(left) - 1, -1, -1):
        if left[i] < 0:
            cost[i] = t_intersect * (tree["node_end"][i] - tree["node_begin"][i])
            continue
        c = 2.0 * t_traversal
        for child in (left[i], right[i]):
            c += cost[child] * (area[child] / area[i]) if area[i] > 0 else cost[child]
        cost[i] = c
    return cost


# --------------------------------------------------------------------------- inputs
def nan_with_payload(payload):
    return np.array([0x7FC00000 | payload], np.uint32).view(np.float32)[0]


def scene_boxes(rng, case, n):
    """Primitive boxes (lowers, uppers) of one adversarial case, float32."""
    if case == "mesh":
        mesh = trimesh.creation.icosphere(subdivisions=4)
        tri = np.asarray(mesh.vertices, np.float32)[np.asarray(mesh.faces)]
        return tri.min(1), tri.max(1)
    if case == "degenerate":
        # Zero-area triangles: points, and segments along an axis, many of them repeated.
        pts = rng.integers(0, 6, size=(n, 3)).astype(np.float32)
        hi = pts.copy()
        seg = rng.random(n) < 0.5
        hi[seg, 0] += rng.integers(0, 2, size=seg.sum())
        return pts, hi
    if case == "equal_runs":
        # Runs of 1 to 5 boxes with the same centroid: equal codes, split at index medians.
        run = np.repeat(np.arange(n), rng.integers(1, 6, n))[:n]
        centers = rng.random((n, 3)).astype(np.float32)[run]
        size = (0.01 * rng.random((n, 3))).astype(np.float32)
        return centers - size, centers + size
    lo = rng.random((n, 3)).astype(np.float32)
    hi = (lo + 0.05 * rng.random((n, 3))).astype(np.float32)
    if case == "soup":
        return lo, hi
    if case == "signed_zeros":
        # Coordinates of 0 and -0 in both corners, so that unions compare equal values of two signs.
        zeros = np.where(rng.random((n, 3)) < 0.5, np.float32(0.0), np.float32(-0.0))
        pick = rng.random((n, 3)) < 0.6
        lo = np.where(pick, zeros, -lo).astype(np.float32)
        hi = np.where(rng.random((n, 3)) < 0.6, -zeros, hi).astype(np.float32)
        return lo, hi
    if case == "infinities":
        for arr, sign in ((lo, -1), (hi, 1)):
            rows = rng.integers(0, n, n // 20)
            arr[rows, rng.integers(0, 3, rows.size)] = sign * np.inf
        rows = rng.integers(0, n, n // 50)
        lo[rows] = np.inf  # inverted boxes, as an empty input may give
        hi[rows] = -np.inf
        return lo, hi
    if case == "nan":
        # NaN of several payloads: in single coordinates, in whole boxes, and in a run of
        # neighbours (NaN centroids share cell 0), so that some subtrees are NaN throughout.
        for k, arr in enumerate((lo, hi)):
            rows = rng.integers(0, n, n // 10)
            arr[rows, rng.integers(0, 3, rows.size)] = nan_with_payload(1 + k)
        whole = rng.integers(0, n, n // 20)
        lo[whole] = nan_with_payload(3)
        hi[whole] = nan_with_payload(4)
        run = rng.integers(0, n - 40)
        lo[run : run + 40, 1] = nan_with_payload(5)
        hi[run : run + 40, 1] = nan_with_payload(6)
        lo[run : run + 7] = np.array([nan_with_payload(7 + k) for k in range(7)])[:, None]
        return lo, hi
    raise ValueError(case)


CASES = ["mesh", "soup", "degenerate", "equal_runs", "signed_zeros", "infinities", "nan"]


def build(device, lowers, uppers, **config):
    config.setdefault("emission", "depth_first")
    pipe = HlbvhPipeline(len(lowers), hb.BuildConfig(**config), device,
                         wp.array(lowers, dtype=wp.vec3, device=device), wp.array(uppers, dtype=wp.vec3, device=device))
    pipe.build()
    return pipe


def tree_of(pipe):
    count = int(pipe.node_count.numpy()[0])
    tree = {name: getattr(pipe, name).numpy()[:count] for name in
            ("node_left", "node_right", "node_parent", "node_begin", "node_end", "node_lowers", "node_uppers")}
    tree["prim_order"] = pipe.sorted_prim_ids.numpy()[: pipe.num_prims]
    tree["codes"] = pipe.sorted_codes.numpy()[: pipe.num_prims].astype(np.int64)
    return tree


def assert_same_bits(got, want, exact_bits, what):
    if exact_bits:
        bad = np.flatnonzero((got.view(np.uint32) != want.view(np.uint32)).any(axis=1))
    else:
        # CUDA's fminf may pick either zero of a tie and returns its own NaN.
        bad = np.flatnonzero(~((got == want) | (np.isnan(got) & np.isnan(want))).all(axis=1))
    assert bad.size == 0, f"{bad.size} {what} differ, first node {bad[:5]}: {got[bad[:3]]} != {want[bad[:3]]}"


def check_boxes(device, tree, lowers, uppers):
    want_lo, want_hi = oracle_boxes(tree, lowers, uppers)
    exact = wp.get_device(device).is_cpu
    assert_same_bits(tree["node_lowers"], want_lo, exact, "lower corners")
    assert_same_bits(tree["node_uppers"], want_hi, exact, "upper corners")


# --------------------------------------------------------------------------- tests
@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("leaf", [1, 2, 3])
def test_one_walk_matches_the_oracle_tree(device, rng, case, leaf):
    # One thread: the numbering too is the oracle's, node for node.
    lowers, uppers = scene_boxes(rng, case, 3001)
    pipe = build(device, lowers, uppers, max_leaf_size=leaf, cpu_threads=1)
    tree = tree_of(pipe)
    want = oracle_topology(tree["codes"], leaf)
    if wp.get_device(device).is_cpu:
        for name, value in want.items():
            np.testing.assert_array_equal(tree[name], value, err_msg=name)
    else:
        # CUDA allocates node pairs by atomics: the same nodes, numbered in another order.
        got = set(zip(tree["node_begin"], tree["node_end"], tree["node_left"] < 0))
        assert got == set(zip(want["node_begin"], want["node_end"], want["node_left"] < 0))
    check_boxes(device, tree, lowers, uppers)
    if case in ("mesh", "soup", "degenerate", "equal_runs"):
        check_tree_invariants({**tree, "prim_lowers": lowers, "prim_uppers": uppers}, len(lowers), leaf,
                              exact_node_count=len(want["node_left"]))


@pytest.mark.parametrize("case", ["soup", "equal_runs", "signed_zeros", "nan"])
def test_runs_side_by_side_match_the_oracle(device, rng, case):
    # Two threads: the top split into seeds, each run numbering from its own counter. The nodes
    # (ranges, parents, boxes) are the oracle's; only the numbering is the schedule's.
    lowers, uppers = scene_boxes(rng, case, PARALLEL_MIN_PRIMS + 1234)
    pipe = build(device, lowers, uppers, cpu_threads=2)
    tree = tree_of(pipe)
    want = oracle_topology(tree["codes"], 1)
    key = lambda t: set(zip(t["node_begin"], t["node_end"], t["node_left"] < 0))  # noqa: E731
    assert key(tree) == key(want)
    interior = np.flatnonzero(tree["node_left"] >= 0)
    for side in ("node_left", "node_right"):
        np.testing.assert_array_equal(tree["node_parent"][tree[side][interior]], interior)
    assert tree["node_parent"][0] == -1
    check_boxes(device, tree, lowers, uppers)


@pytest.mark.parametrize("n", [PARALLEL_MIN_PRIMS - 1, PARALLEL_MIN_PRIMS, PARALLEL_MIN_PRIMS + 1,
                               PARALLEL_MIN_PRIMS + 1234])
@pytest.mark.parametrize("threads", [1, 2, 3])
def test_each_walk_gathers_the_boxes_of_this_build(device, rng, n, threads):
    # On the CPU every seed gathers its own primitive boxes in tree order: refilled boxes in the
    # same arrays, and a gather buffer left holding NaN, must give this build's boxes at every
    # node, the one-thread tree's nodes, and runs cut where a search of the seed starts cuts them.
    lowers, uppers = scene_boxes(rng, "soup", n)
    pipe = build(device, lowers, uppers, cpu_threads=threads)
    lowers, uppers = scene_boxes(rng, "equal_runs", n)
    pipe.prim_lowers.assign(lowers)
    pipe.prim_uppers.assign(uppers)
    pipe.leaf_lowers.fill_(wp.vec3(np.nan, np.nan, np.nan))
    pipe.leaf_uppers.fill_(wp.vec3(np.nan, np.nan, np.nan))
    pipe.build()
    tree = tree_of(pipe)
    check_boxes(device, tree, lowers, uppers)
    one = tree_of(build(device, lowers, uppers, cpu_threads=1))
    np.testing.assert_array_equal(tree["prim_order"], one["prim_order"])
    key = lambda t: sorted(zip(t["node_begin"], t["node_end"], t["node_left"] < 0))  # noqa: E731
    assert key(tree) == key(one)
    parallel = wp.get_device(device).is_cpu and threads > 1 and n >= PARALLEL_MIN_PRIMS
    assert (pipe.sweep_parts is not None) == parallel
    if not parallel:
        for name in ("node_left", "node_right", "node_parent", "node_begin", "node_end"):
            np.testing.assert_array_equal(tree[name], one[name], err_msg=name)
        return
    seeds = int(pipe.top_seed_count.numpy()[0])
    starts = pipe.top_seed_starts.numpy()[:seeds].astype(np.int64)
    cuts = np.unique(np.concatenate([[0], np.searchsorted(starts, np.arange(1, threads) * (n / threads)), [seeds]]))
    first_free = 2 * seeds - 1
    lows = [first_free + 2 * int(starts[s]) - 2 * int(s) for s in cuts[:-1]]
    assert pipe.sweep_parts == (first_free, list(zip(lows, lows[1:] + [len(tree["node_left"])])))


@pytest.mark.parametrize("case", ["mesh", "degenerate", "equal_runs"])
@pytest.mark.parametrize("leaf", [1, 2])
def test_node_costs_of_the_walk(device, rng, case, leaf):
    # The SAH costs (hlbvh_sah's cluster weights) come out of the same walk, on the same tree.
    lowers, uppers = scene_boxes(rng, case, 2000)
    pipe = build(device, lowers, uppers, max_leaf_size=leaf, cpu_threads=1)
    before = tree_of(pipe)
    cost = wp.zeros(2 * len(lowers) - 1, dtype=wp.float64, device=device)
    pipe.emit_depth_first(node_cost=cost)
    tree = tree_of(pipe)
    for name in ("node_left", "node_right", "node_parent", "node_begin", "node_end"):
        np.testing.assert_array_equal(tree[name], before[name], err_msg=name)
    for name in ("node_lowers", "node_uppers"):
        np.testing.assert_array_equal(tree[name].view(np.uint32), before[name].view(np.uint32), err_msg=name)
    cfg = pipe.config
    want = oracle_costs(tree, cfg.sah_traversal_cost, cfg.sah_intersection_cost)
    np.testing.assert_allclose(cost.numpy()[: len(want)], want, rtol=1e-12)


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 7, 8])
@pytest.mark.parametrize("pattern", ["distinct", "equal", "pairs"])
def test_tiny_ranges(device, rng, n, pattern):
    # Every small range the walk emits whole (2 to 4 primitives), as the root and below it.
    if pattern == "distinct":
        lowers = rng.random((n, 3)).astype(np.float32)
    elif pattern == "equal":
        lowers = np.zeros((n, 3), np.float32)
    else:
        lowers = np.repeat(rng.random(((n + 1) // 2, 3)).astype(np.float32), 2, axis=0)[:n]
    uppers = lowers + np.float32(0.5)
    lowers[rng.random((n, 3)) < 0.3] = -0.0
    pipe = build(device, lowers, uppers, cpu_threads=1)
    tree = tree_of(pipe)
    want = oracle_topology(tree["codes"], 1)
    if wp.get_device(device).is_cpu:
        for name, value in want.items():
            np.testing.assert_array_equal(tree[name], value, err_msg=name)
    check_boxes(device, tree, lowers, uppers)
