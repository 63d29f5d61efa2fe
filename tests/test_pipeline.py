"""Each HLBVH stage against an independent NumPy reference, and the whole build's invariants."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import trimesh
import warp as wp
from oracles import (
    assert_hits_match,
    brute_force_closest_hit,
    check_tree_invariants,
    morton_reference,
    random_rays,
    random_soup,
)

import hlbvh_warp as hb
from hlbvh_warp.hlbvh import HlbvhPipeline, StageTimer

from conftest import shared_mesh


# --------------------------------------------------------------------------- references
def radix_tree_reference(codes, max_leaf_size=1):
    """Top-down: split at the highest differing bit; equal codes split at the index median.

    Returns the set of (begin, end, is_leaf) over every node: the tree up to node numbering.
    """
    nodes = set()
    stack = [(0, len(codes))]
    while stack:
        b, e = stack.pop()
        if e - b <= max_leaf_size:
            nodes.add((b, e, True))
            continue
        nodes.add((b, e, False))
        if codes[b] == codes[e - 1]:
            m = (b + e + 1) // 2
        else:
            hb = int(codes[b] ^ codes[e - 1]).bit_length() - 1
            m = b + int(np.searchsorted((codes[b:e] >> hb) & 1, 1))
        stack += [(b, m), (m, e)]
    return nodes


def node_set(tree):
    leaf = tree["node_left"] < 0
    return {(int(b), int(e), bool(is_leaf)) for b, e, is_leaf in zip(tree["node_begin"], tree["node_end"], leaf)}


def sah_reference(tree):
    """The paper's eq. (1) with T1 = T2 = 1, float64, evaluated bottom-up."""
    lo = tree["node_lowers"].astype(np.float64)
    hi = tree["node_uppers"].astype(np.float64)
    d = hi - lo
    area = 2 * (d[:, 0] * d[:, 1] + d[:, 1] * d[:, 2] + d[:, 2] * d[:, 0])
    left, right = tree["node_left"], tree["node_right"]
    cost = np.zeros(len(left))
    for i in range(len(left) - 1, -1, -1):
        if left[i] < 0:
            cost[i] = tree["node_end"][i] - tree["node_begin"][i]
        else:
            p = area[i] if area[i] > 0 else 1.0
            cost[i] = 2 + (cost[left[i]] * area[left[i]] + cost[right[i]] * area[right[i]]) / p
    return cost[0]


def make_pipeline(lowers, uppers, device, **config):
    pipe = HlbvhPipeline(len(lowers), hb.BuildConfig(**config), device)
    pipe.prim_lowers.assign(wp.array(lowers, dtype=wp.vec3, device=device))
    pipe.prim_uppers.assign(wp.array(uppers, dtype=wp.vec3, device=device))
    return pipe


def soup_bounds(rng, n, clusters=False):
    if clusters:  # a few tight clusters: long runs, big voxels
        centers = rng.random((5, 3))
        pts = centers[rng.integers(0, 5, n)] + 1e-3 * rng.random((n, 3))
    else:
        pts = rng.random((n, 3))
    lo = pts.astype(np.float32)
    hi = (pts + 0.01 * rng.random((n, 3))).astype(np.float32)
    return lo, hi


# --------------------------------------------------------------------------- stages
@pytest.mark.parametrize("bits", [10, 4])
def test_morton_codes(device, rng, bits):
    lo, hi = soup_bounds(rng, 3000)
    pipe = make_pipeline(lo, hi, device, bits_per_axis=bits, coarse_bits=min(bits, 6))
    pipe.compute_morton_codes()
    np.testing.assert_array_equal(pipe.morton_codes.numpy(), morton_reference(lo, hi, bits))


def test_triangle_bounds_reduce_centroids_in_the_same_pass(device, rng):
    """The fused box + centroid-bounds pass of per-frame builds, against NumPy; 10,001 triangles
    so that the CPU's last chunk is partial, and codes from it equal the two-pass codes."""
    n = 10_001
    verts = (rng.standard_normal((3 * n, 3)) * [3.0, 1.0, 0.5]).astype(np.float32)
    faces = rng.integers(0, 3 * n, size=(n, 3)).astype(np.int32)
    lo, hi = verts[faces].min(axis=1), verts[faces].max(axis=1)
    pipe = make_pipeline(np.zeros_like(lo), np.zeros_like(hi), device)
    pipe.compute_triangle_bounds(wp.array(verts, dtype=wp.vec3, device=device),
                                 wp.array(faces, dtype=wp.int32, device=device))
    np.testing.assert_array_equal(pipe.prim_lowers.numpy(), lo)
    np.testing.assert_array_equal(pipe.prim_uppers.numpy(), hi)
    centroids = np.float32(0.5) * (lo + hi)
    bounds = pipe.scene_bounds.numpy()
    np.testing.assert_array_equal(bounds[0], centroids.min(axis=0))
    np.testing.assert_array_equal(bounds[1], centroids.max(axis=0))
    pipe.compute_morton_codes(bounds_ready=True)
    np.testing.assert_array_equal(pipe.morton_codes.numpy(), morton_reference(lo, hi, 10))


def test_run_length_encoding_and_csd(device, rng):
    lo, hi = soup_bounds(rng, 4000)
    # Coherent input: sort half of it so that runs are long, keep the rest shuffled.
    pipe = make_pipeline(lo, hi, device, coarse_bits=3)
    pipe.compute_morton_codes()
    codes = pipe.morton_codes.numpy().astype(np.int64)
    coarse = codes >> (3 * (10 - 3))
    m = pipe.run_length_encode()
    heads = np.flatnonzero(np.r_[True, coarse[1:] != coarse[:-1]])
    assert m == len(heads)
    np.testing.assert_array_equal(pipe.run_codes.numpy()[:m], coarse[heads])
    np.testing.assert_array_equal(pipe.run_lengths.numpy()[:m], np.diff(np.r_[heads, len(codes)]))
    np.testing.assert_array_equal(pipe.run_starts.numpy()[:m], heads)
    # Compress-sort-decompress: primitives grouped by coarse voxel, input order within one.
    pipe.top_level_sort(m)
    pipe.run_length_decode(m)
    order = np.argsort(coarse, kind="stable")
    np.testing.assert_array_equal(pipe.sorted_prim_ids.numpy()[: len(codes)], order)
    np.testing.assert_array_equal(pipe.sorted_codes.numpy()[: len(codes)], codes[order])


@pytest.mark.parametrize("capacity", [2000, 7])
def test_voxel_sort_equals_stable_argsort(device, rng, capacity):
    # Clustered input makes voxels far larger than a block of 7: the oversized-voxel path.
    lo, hi = soup_bounds(rng, 5000, clusters=True)
    pipe = make_pipeline(lo, hi, device, block_capacity=capacity)
    pipe.build("hlbvh")
    codes = pipe.morton_codes.numpy()
    order = np.argsort(codes, kind="stable")
    np.testing.assert_array_equal(pipe.sorted_prim_ids.numpy()[: len(codes)], order)
    assert pipe.sorted_prim_ids.numpy()[: len(codes)].shape == order.shape


@pytest.mark.parametrize("method", ["hlbvh", "lbvh"])
def test_sort_carries_input_ids(device, rng, method):
    """With input ids (a resorted frame: position i holds user face ids[i]), the sorted ids are
    those faces in code order, equal codes in face id order (as a build from scratch has them,
    not in the input's), and the boxes are read by face id."""
    lo, hi = soup_bounds(rng, 3000, clusters=True)
    ids = rng.permutation(len(lo)).astype(np.int32)
    # The pipeline's boxes are in the user's order; its Morton codes are in input order.
    pipe = make_pipeline(lo, hi, device)
    codes = morton_reference(lo[ids], hi[ids], 10).astype(np.int32)
    pipe.morton_codes.assign(wp.array(codes, dtype=wp.int32, device=device))
    pipe.set_input_ids(wp.array(ids, dtype=wp.int32, device=device))
    pipe.build(method, inputs_ready="codes")
    expected = ids[np.lexsort((ids, codes))]
    assert not np.array_equal(expected, ids[np.argsort(codes, kind="stable")]), "no tie out of face order"
    np.testing.assert_array_equal(pipe.sorted_prim_ids.numpy()[: len(lo)], expected)
    # Every leaf's box is its face's own box, so the boxes were read by face id.
    tree = {name: arr.numpy() for name, arr in (("left", pipe.node_left), ("begin", pipe.node_begin),
                                                 ("lowers", pipe.node_lowers), ("uppers", pipe.node_uppers))}
    count = int(pipe.node_count.numpy()[0])
    leaves = np.flatnonzero(tree["left"][:count] < 0)
    faces = expected[tree["begin"][leaves]]
    np.testing.assert_array_equal(tree["lowers"][leaves], lo[faces])
    np.testing.assert_array_equal(tree["uppers"][leaves], hi[faces])
    # Set back to positions, the same pipeline sorts plain input again.
    pipe.set_input_ids(None)
    pipe.morton_codes.assign(wp.array(morton_reference(lo, hi, 10).astype(np.int32), dtype=wp.int32, device=device))
    pipe.build(method, inputs_ready="codes")
    np.testing.assert_array_equal(pipe.sorted_prim_ids.numpy()[: len(lo)],
                                  np.argsort(morton_reference(lo, hi, 10), kind="stable"))


def test_input_ids_are_checked(device):
    pipe = make_pipeline(np.zeros((4, 3), np.float32), np.ones((4, 3), np.float32), device)
    for bad in (wp.zeros(3, dtype=wp.int32, device=device), wp.zeros(4, dtype=wp.float32, device=device)):
        with pytest.raises(ValueError, match="input_ids"):
            pipe.set_input_ids(bad)
    assert pipe.input_ids.shape[0] == 0


EMISSIONS = ["treelets", "depth_first"]


@pytest.mark.parametrize("emission", EMISSIONS)
@pytest.mark.parametrize("planes", [1, 2, 3, 4])
@pytest.mark.parametrize("leaf", [1, 3])
def test_emitted_topology_matches_radix_tree(device, rng, planes, leaf, emission):
    if emission == "depth_first" and planes != 3:
        pytest.skip("the depth-first schedule has no passes: p does not apply")
    lo, hi = soup_bounds(rng, 3000, clusters=True)
    # Duplicated boxes force equal codes: those segments must be split at the index median.
    lo = np.concatenate([lo, np.repeat(lo[:5], 40, axis=0)])
    hi = np.concatenate([hi, np.repeat(hi[:5], 40, axis=0)])
    pipe = make_pipeline(lo, hi, device, planes_per_pass=planes, max_leaf_size=leaf, emission=emission)
    pipe.build("hlbvh")
    bvh = hb.api.bvh_from_pipeline(pipe, "hlbvh", {})
    tree = bvh.to_numpy()
    sorted_codes = pipe.sorted_codes.numpy()[: len(lo)].astype(np.int64)
    assert node_set(tree) == radix_tree_reference(sorted_codes, leaf)
    check_tree_invariants(tree, len(lo), max_leaf_size=leaf)


@pytest.mark.parametrize("emission", EMISSIONS)
@pytest.mark.parametrize("method", ["hlbvh", "lbvh"])
def test_distinct_codes_give_2n_minus_1_nodes(device, method, emission):
    # A 3D grid of points: every centroid in its own Morton cell.
    g = np.stack(np.meshgrid(*[np.arange(12)] * 3, indexing="ij"), -1).reshape(-1, 3).astype(np.float32)
    bvh = hb.build_from_bounds(g, g + 0.5, method=method, device=device, config=hb.BuildConfig(emission=emission))
    check_tree_invariants(bvh.to_numpy(), len(g), exact_node_count=2 * len(g) - 1)
    assert bvh.num_nodes == 2 * len(g) - 1
    assert bvh.num_leaves == len(g)


@pytest.mark.parametrize("emission", EMISSIONS)
@pytest.mark.parametrize("n", [1, 2, 3, 1000])
def test_all_identical_boxes(device, n, emission):
    lo = np.zeros((n, 3), np.float32)
    bvh = hb.build_from_bounds(lo, lo + 1, device=device, config=hb.BuildConfig(emission=emission))
    check_tree_invariants(bvh.to_numpy(), n, exact_node_count=2 * n - 1)
    # Index-median splits of equal codes give a balanced tree.
    assert bvh.depth == int(np.ceil(np.log2(n)))


@pytest.mark.parametrize("method", ["hlbvh", "lbvh"])
def test_methods_agree_on_tree(device, rng, method):
    lo, hi = soup_bounds(rng, 2000)
    ref = hb.build_from_bounds(lo, hi, method="lbvh", device=device).to_numpy()
    other = hb.build_from_bounds(lo, hi, method=method, device=device).to_numpy()
    assert node_set(ref) == node_set(other)
    assert sah_reference(ref) == pytest.approx(sah_reference(other), rel=1e-6)


def test_resorted_input_gives_equivalent_tree_and_skips_sort(device):
    mesh = _bumpy_mesh()
    first = hb.build(mesh, device=device)
    order = first.to_numpy()["prim_order"]
    again = hb.build(mesh.vertices, mesh.faces[order], device=device, timings=True)
    assert sah_reference(again.to_numpy()) == pytest.approx(sah_reference(first.to_numpy()), rel=1e-6)
    assert "top_level_sort" in again.timings["skipped"]
    assert "voxel_sort" in again.timings["skipped"]
    # The tree holds the same primitives in each leaf, up to the face permutation.
    np.testing.assert_array_equal(order[again.to_numpy()["prim_order"]], order)


@pytest.mark.parametrize("emission", ["treelets", "depth_first"])
def test_timings_report_stages(device, rng, emission):
    lo, hi = soup_bounds(rng, 500)
    # The paper's sort for every build (a random soup has about one run per primitive).
    config = hb.BuildConfig(emission=emission, global_sort_runs=1.0)
    bvh = hb.build_from_bounds(lo, hi, device=device, timings=True, config=config)
    for stage in ("morton", "run_length_encode", "top_level_sort", "run_length_decode", "voxel_sort", "hierarchy"):
        assert bvh.timings[stage] >= 0.0
    if emission == "treelets":
        assert bvh.timings["bbox"] >= 0.0
    else:
        # The depth-first emission writes every box as it goes: no separate pass.
        assert "bbox" in bvh.timings["skipped"] and "bbox" not in bvh.timings
    assert hb.build_from_bounds(lo, hi, device=device).timings == {}


@pytest.mark.parametrize("clusters", [False, True])
def test_global_sort_when_runs_do_not_compress(device, rng, clusters):
    """About one run per primitive (a random soup): one radix sort of the full codes replaces
    compress-sort-decompress and the voxel sort, for the same order; clustered input keeps the
    paper's stages. Either way the order is NumPy's stable argsort of the codes."""
    lo, hi = soup_bounds(rng, 4000, clusters=clusters)
    if clusters:
        # Grouped by cluster, as a mesh's coherent face order is: long runs.
        by_cluster = np.argsort(morton_reference(lo, hi, 10) >> 12, kind="stable")
        lo, hi = lo[by_cluster], hi[by_cluster]
    codes = morton_reference(lo, hi, 10)
    runs = 1 + int(np.count_nonzero(np.diff(codes >> 12)))  # m = 6: the high 18 bits
    orders = {}
    for fraction in (0.5, 1.0):
        pipe = make_pipeline(lo, hi, device, global_sort_runs=fraction)
        timer = StageTimer(pipe.device, True)
        pipe.build("hlbvh", timer)
        global_path = "global_sort" in timer.timings
        assert global_path == (fraction < 1.0 and runs > fraction * len(lo)), (fraction, runs)
        skipped = timer.timings.get("skipped", [])
        if global_path:
            assert {"top_level_sort", "run_length_decode", "voxel_sort"} <= set(skipped), skipped
            # The CPU's sample saw the runs would not compress: no encoding either.
            assert ("run_length_encode" in skipped) == pipe.device.is_cpu, skipped
        else:
            assert "run_length_decode" in timer.timings and "run_length_decode" not in skipped
        orders[fraction] = pipe.sorted_prim_ids.numpy()[: len(lo)].copy()
        np.testing.assert_array_equal(orders[fraction], np.argsort(codes, kind="stable"))
    assert (runs > len(lo) // 2) != clusters


def sampled_pair_ends(n: int, samples: int = 1024) -> np.ndarray:
    """The second position of each adjacent pair the CPU build samples before encoding the runs
    (`HlbvhPipeline.sampled_run_fraction`): evenly spaced over [1, n)."""
    samples = min(n - 1, samples)
    return 1 + np.arange(samples, dtype=np.int64) * (n - 1) // samples


@pytest.mark.parametrize("breaks_at", ["sampled_pairs_only", "all_but_sampled_pairs"])
def test_run_sample_decides_before_encoding(device, rng, breaks_at):
    """On the CPU a sample of adjacent pairs decides whether the runs compress before any pass
    over all the codes. Inputs whose coarse voxel changes exactly at the sampled pairs (few
    runs, but a sample of all breaks) or everywhere else (many runs, a sample of none) fool it
    both ways: the first takes the global sort without encoding, the second encodes, finds the
    runs do not compress and takes the global sort after all. The order is NumPy's stable
    argsort of the codes either way. CUDA always encodes and decides on the exact count."""
    n = 4096
    ends = sampled_pair_ends(n)
    change = np.zeros(n, dtype=bool)
    change[ends] = True
    if breaks_at == "all_but_sampled_pairs":
        change[1:] = ~change[1:]
    # Alternate between two coarse voxels of a fixed unit grid (m = 6: cells of 1/64) at each
    # change, with a different fine cell for every point.
    voxel = np.cumsum(change) % 2
    corner = np.where(voxel[:, None] == 1, 0.75, 0.25)
    pts = corner + rng.integers(0, 16, (n, 3)) / 1024.0 + 0.5 / 1024.0
    lo = hi = pts.astype(np.float32)
    config = dict(coarse_bits=6, morton_bounds=((0, 0, 0), (1, 1, 1)), global_sort_runs=0.3)
    pipe = make_pipeline(lo, hi, device, **config)
    timer = StageTimer(pipe.device, True)
    pipe.build("hlbvh", timer)
    codes = pipe.morton_codes.numpy().astype(np.int64)
    coarse = codes >> 12
    # The input is what the test meant: the coarse voxel changes exactly where planned.
    np.testing.assert_array_equal(coarse[1:] != coarse[:-1], change[1:])
    runs = 1 + int(np.count_nonzero(change[1:]))
    sampled = float(np.mean(coarse[ends] != coarse[ends - 1]))
    assert (sampled, runs > 0.3 * n) == ((1.0, False) if breaks_at == "sampled_pairs_only" else (0.0, True))
    skipped = set(timer.timings.get("skipped", []))
    encoded = "run_length_encode" not in skipped
    assert encoded == (not pipe.device.is_cpu or breaks_at == "all_but_sampled_pairs"), skipped
    # The sample (CPU), or the encoding's exact count, chose the global sort.
    assert ("global_sort" in timer.timings) == (pipe.device.is_cpu or runs > 0.3 * n), timer.timings
    if pipe.device.is_cpu:
        assert pipe.sampled_run_fraction() == sampled
    np.testing.assert_array_equal(pipe.sorted_prim_ids.numpy()[:n], np.argsort(codes, kind="stable"))


@pytest.mark.parametrize("case", ["sorted", "last_pair_swapped", "first_pair_swapped"])
def test_codes_already_in_order_skip_every_sort(device, rng, case):
    """Input whose codes already ascend (a resorted frame in which nothing changed order) skips
    the run-length encoding, both sorts and the decode on the CPU, and its order is the input's. One pair
    out of order anywhere, the first or the last, and the paper's stages run as before. Either
    way the order is NumPy's stable argsort of the codes and the tree the radix tree over them."""
    lo, hi = soup_bounds(rng, 3000, clusters=True)
    ascending = np.argsort(morton_reference(lo, hi, 10), kind="stable")
    lo, hi = lo[ascending], hi[ascending]
    codes = morton_reference(lo, hi, 10)
    distinct = np.flatnonzero(np.diff(codes) != 0)
    if case != "sorted":
        # Swap the first (or last) two neighbours whose codes differ: one descent, at that end.
        i = int(distinct[0] if case == "first_pair_swapped" else distinct[-1])
        swap = np.arange(len(lo))
        swap[[i, i + 1]] = swap[[i + 1, i]]
        lo, hi = lo[swap], hi[swap]
        codes = codes[swap]
    # The paper's sort for every build that sorts (no global-sort shortcut).
    pipe = make_pipeline(lo, hi, device, global_sort_runs=1.0)
    timer = StageTimer(pipe.device, True)
    pipe.build("hlbvh", timer)
    skipped = set(timer.timings.get("skipped", []))
    sort_stages = {"run_length_encode", "top_level_sort", "run_length_decode", "voxel_sort"}
    if case == "sorted":
        # On CUDA the check is left out (a pass and a host read per build); the older skips fire.
        expected = sort_stages if pipe.device.is_cpu else {"top_level_sort", "voxel_sort"}
        assert expected <= skipped, skipped
    else:
        # The paper's stages run; the swap is undone by one of the two sorts (the top-level one
        # when it crosses voxels, the voxel sort when it does not).
        assert not ({"run_length_encode", "run_length_decode"} & skipped), skipped
        assert not {"top_level_sort", "voxel_sort"} <= skipped, skipped
    order = pipe.sorted_prim_ids.numpy()[: len(lo)]
    np.testing.assert_array_equal(order, np.argsort(codes, kind="stable"))
    tree = hb.build_from_bounds(lo, hi, device=device).to_numpy()
    check_tree_invariants(tree, len(lo))
    leaves = tree["node_left"] < 0
    spans = {(int(b), int(e), bool(is_leaf)) for b, e, is_leaf in zip(tree["node_begin"], tree["node_end"], leaves)}
    assert spans == radix_tree_reference(codes[tree["prim_order"]])


def test_sync_free_build_matches(device, rng):
    lo, hi = soup_bounds(rng, 3000, clusters=True)
    pipe = make_pipeline(lo, hi, device)
    pipe.build("hlbvh")
    ref = hb.api.bvh_from_pipeline(pipe, "hlbvh", {}).to_numpy()
    pipe2 = make_pipeline(lo, hi, device)
    pipe2.build("hlbvh", StageTimer(device, False), sync_free=True)
    got = hb.api.bvh_from_pipeline(pipe2, "hlbvh", {}).to_numpy()
    assert node_set(got) == node_set(ref)
    np.testing.assert_array_equal(got["prim_order"], ref["prim_order"])


def numpy_bottom_up_boxes(tree, lo, hi):
    # Children are numbered after parents: a reverse sweep is an independent bottom-up.
    nlo = np.zeros_like(tree["node_lowers"])
    nhi = np.zeros_like(tree["node_uppers"])
    for i in range(len(nlo) - 1, -1, -1):
        left, right = tree["node_left"][i], tree["node_right"][i]
        if left < 0:
            prims = tree["prim_order"][tree["node_begin"][i] : tree["node_end"][i]]
            nlo[i], nhi[i] = lo[prims].min(0), hi[prims].max(0)
        else:
            assert left > i and right > i
            nlo[i], nhi[i] = np.minimum(nlo[left], nlo[right]), np.maximum(nhi[left], nhi[right])
    return nlo, nhi


@pytest.mark.parametrize("method, leaf", [("hlbvh", 1), ("sweep_sah", 4), ("hlbvh_sah", 2), ("median", 1)])
@pytest.mark.parametrize("strategy", ["climb", "sweep"])
def test_node_bounds_match_numpy_bottom_up(device, rng, strategy, method, leaf):
    # Every builder's tree, so that the climb (CUDA's bounds) runs on each shape of tree here too.
    lo, hi = soup_bounds(rng, 2000)
    bvh = hb.build_from_bounds(lo, hi, method=method, device=device, config=hb.BuildConfig(max_leaf_size=leaf))
    bvh.node_lowers.zero_()
    bvh.node_uppers.zero_()
    hb.hlbvh.refit_bounds(bvh, strategy=strategy)
    tree = bvh.to_numpy()
    nlo, nhi = numpy_bottom_up_boxes(tree, lo, hi)
    np.testing.assert_array_equal(tree["node_lowers"], nlo)
    np.testing.assert_array_equal(tree["node_uppers"], nhi)


@pytest.mark.parametrize("emission", EMISSIONS)
@pytest.mark.parametrize("leaf", [1, 4])
def test_built_boxes_match_numpy_bottom_up(device, rng, emission, leaf):
    # The depth-first schedule writes leaf boxes during emission: check the build's own boxes.
    lo, hi = soup_bounds(rng, 2000, clusters=True)
    config = hb.BuildConfig(emission=emission, max_leaf_size=leaf)
    tree = hb.build_from_bounds(lo, hi, device=device, config=config).to_numpy()
    nlo, nhi = numpy_bottom_up_boxes(tree, lo, hi)
    np.testing.assert_array_equal(tree["node_lowers"], nlo)
    np.testing.assert_array_equal(tree["node_uppers"], nhi)
    assert tree["node_parent"][0] == -1
    children = np.flatnonzero(tree["node_left"] >= 0)
    np.testing.assert_array_equal(tree["node_parent"][tree["node_left"][children]], children)
    np.testing.assert_array_equal(tree["node_parent"][tree["node_right"][children]], children)


@pytest.mark.parametrize("emission", EMISSIONS)
def test_sync_free_matches_across_emissions(device, rng, emission):
    lo, hi = soup_bounds(rng, 3000, clusters=True)
    ref = make_pipeline(lo, hi, device, emission="treelets")
    ref.build("hlbvh")
    pipe = make_pipeline(lo, hi, device, emission=emission)
    pipe.build("hlbvh", StageTimer(device, False), sync_free=True)
    a = hb.api.bvh_from_pipeline(ref, "hlbvh", {}).to_numpy()
    b = hb.api.bvh_from_pipeline(pipe, "hlbvh", {}).to_numpy()
    assert node_set(a) == node_set(b)
    assert sah_reference(a) == pytest.approx(sah_reference(b), rel=1e-9)


# --------------------------------------------------------------------------- crafted codes and boxes
def sort_crafted_codes(pipe, codes):
    """Sort given Morton codes with the pipeline (no boxes needed) and return the order."""
    pipe.morton_codes.assign(wp.array(np.asarray(codes, np.int32), dtype=wp.int32, device=pipe.device))
    pipe.build("hlbvh", inputs_ready="codes")
    return pipe.sorted_prim_ids.numpy()[: pipe.num_prims].copy()


def crafted_voxel_codes(case, rng):
    # 10 bits per axis with coarse_bits=6: a code's coarse voxel is code >> 12.
    def fine(k):  # distinct low bits
        return rng.permutation(1 << 12)[:k]

    if case == "budget_runs_out_at_a_voxel_end":
        # A reversed voxel of 30 in a block of 100: the insertion sort's budget (4 moves per
        # element, 400) runs out inserting its 29th element (1 + 2 + ... + 28 = 406 moves), one
        # before the voxel's end.
        a = (5 << 12) | np.sort(fine(30))[::-1]
        b = (9 << 12) | np.sort(fine(70))
        return np.concatenate([a, b])
    if case == "two_element_voxel_after_the_budget":
        # The budget runs out in a reversed voxel of 40; a later voxel holds just two, descending.
        a = (5 << 12) | np.sort(fine(40))[::-1]
        b = (7 << 12) | np.sort(fine(2))[::-1]
        c = (9 << 12) | np.sort(fine(58))
        return np.concatenate([a, b, c])
    raise ValueError(case)


@pytest.mark.parametrize("case", ["budget_runs_out_at_a_voxel_end", "two_element_voxel_after_the_budget"])
def test_voxel_sort_when_the_insertion_budget_runs_out(device, rng, case):
    codes = crafted_voxel_codes(case, rng)
    pipe = HlbvhPipeline(len(codes), hb.BuildConfig(coarse_bits=6, global_sort_runs=1.0), device)
    assert pipe.num_prims == 100
    np.testing.assert_array_equal(sort_crafted_codes(pipe, codes), np.argsort(codes, kind="stable"))


def test_voxel_sort_of_one_coarse_voxel_after_many(device, rng):
    # A pipeline reused: first many voxels in small blocks, then every code in one coarse voxel
    # (possible over a fixed grid, BuildConfig.morton_bounds): nothing of the first build's voxel
    # and block counts may leak into the second.
    n = 200
    pipe = HlbvhPipeline(n, hb.BuildConfig(coarse_bits=6, global_sort_runs=1.0, block_capacity=7), device)
    many = rng.integers(0, 1 << 30, n)
    np.testing.assert_array_equal(sort_crafted_codes(pipe, many), np.argsort(many, kind="stable"))
    one = (3 << 12) | rng.integers(0, 1 << 12, n)
    np.testing.assert_array_equal(sort_crafted_codes(pipe, one), np.argsort(one, kind="stable"))


@pytest.mark.parametrize("emission", ["treelets", "depth_first"])
@pytest.mark.parametrize("planes", [1, 2, 3, 4])
@pytest.mark.parametrize("leaf", [1, 2])
def test_reused_pipeline_topology_of_sparse_codes_matches_radix_tree(device, rng, emission, planes, leaf):
    """One pipeline (as a Builder keeps it) over many small sets of codes made of a few bit
    planes anywhere in the 30: neighbours whose highest differing bit lies far above the next
    one, runs of duplicates, and split slots left over from the previous builds."""
    if emission == "depth_first" and planes != 3:
        pytest.skip("the depth-first schedule has no passes: p does not apply")
    n = 32
    pipe = HlbvhPipeline(n, hb.BuildConfig(planes_per_pass=planes, max_leaf_size=leaf, emission=emission), device)
    pipe.prim_lowers.assign(np.zeros((n, 3), np.float32))
    pipe.prim_uppers.assign(np.ones((n, 3), np.float32))
    for _ in range(40):
        planes_used = rng.choice(30, size=int(rng.integers(2, 8)), replace=False)
        codes = np.zeros(n, np.int64)
        for bit in planes_used:
            codes |= (rng.random(n) < 0.5).astype(np.int64) << int(bit)
        order = sort_crafted_codes(pipe, codes)
        np.testing.assert_array_equal(order, np.argsort(codes, kind="stable"))
        tree = hb.api.bvh_from_pipeline(pipe, "hlbvh", {}).to_numpy()
        assert node_set(tree) == radix_tree_reference(codes[order], leaf), sorted(planes_used)


@pytest.mark.parametrize("offset", [-10.0, 0.0, 10.0])
def test_centroid_bounds_see_every_position_of_a_chunk(device, rng, offset):
    """The chunked centroid reduction against NumPy, with the extreme centroids placed at the
    first, second and last positions of the CPU's chunks (4096 primitives) and of the whole
    array, in a scene that lies wholly below, across or above zero on every axis."""
    n = 2 * 4096 + 3
    base_lo = (rng.random((n, 3)) + offset).astype(np.float32)
    base_hi = (base_lo + 0.01 * rng.random((n, 3))).astype(np.float32)
    pipe = make_pipeline(base_lo, base_hi, device)
    for low_at, high_at in ((0, 1), (1, 4097), (4095, 4096), (4097, n - 1), (n - 1, 2), (8192, 4095)):
        lo, hi = base_lo.copy(), base_hi.copy()
        lo[low_at], hi[low_at] = offset - 1.0, offset - 0.5
        lo[high_at], hi[high_at] = offset + 2.0, offset + 2.5
        pipe.prim_lowers.assign(lo)
        pipe.prim_uppers.assign(hi)
        pipe.compute_centroid_bounds()
        c = np.float32(0.5) * (lo + hi)
        bounds = pipe.scene_bounds.numpy()
        np.testing.assert_array_equal(bounds[0], c.min(axis=0), err_msg=f"lowest centroid at {low_at}")
        np.testing.assert_array_equal(bounds[1], c.max(axis=0), err_msg=f"highest centroid at {high_at}")


def test_repeated_climb_refits_match_numpy(device, rng):
    """Climbing refits, one after another with one visit-counter array (as a CUDA Builder
    keeps it), box the moved primitives exactly, and the host copies follow each refit."""
    lo = rng.random((1500, 3)).astype(np.float32)
    hi = (lo + 0.01).astype(np.float32)
    bvh = hb.build_from_bounds(lo, hi, device=device)
    visits = wp.zeros(bvh.node_left.shape[0], dtype=wp.int32, device=device)
    for step in range(3):
        moved = (lo + np.float32(0.1 * step) * rng.random((1500, 3)).astype(np.float32)).astype(np.float32)
        bvh.prim_lowers.assign(moved)
        bvh.prim_uppers.assign(moved + np.float32(0.01))
        hb.hlbvh.refit_bounds(bvh, node_visits=visits, strategy="climb")
        tree = bvh.to_numpy()
        nlo, nhi = numpy_bottom_up_boxes(tree, moved, moved + np.float32(0.01))
        np.testing.assert_array_equal(tree["node_lowers"], nlo)
        np.testing.assert_array_equal(tree["node_uppers"], nhi)


def test_hlbvh_sah_of_input_already_in_code_order(device, rng):
    """Input whose codes already ascend (a static frame fed in tree order) must still get the
    voxel sort's clusters: the one-shot pipeline reused from a build over other boxes keeps
    none of that build's clusters."""

    n = 3000
    lo, hi = (x.astype(np.float32) for x in (rng.random((n, 3)), rng.random((n, 3)) * 0.01))
    hi = lo + hi
    cfg = hb.BuildConfig(coarse_bits=3, sah_bins=13)
    other = rng.random((n, 3)).astype(np.float32) ** 3
    hb.build_from_bounds(other, other + np.float32(0.01), method="hlbvh_sah", device=device, config=cfg)
    order = np.argsort(morton_reference(lo, hi, 10), kind="stable")
    s_lo, s_hi = lo[order], hi[order]
    tree = hb.build_from_bounds(s_lo, s_hi, method="hlbvh_sah", device=device, config=cfg).to_numpy()
    check_tree_invariants(tree, n)
    nlo, nhi = numpy_bottom_up_boxes(tree, s_lo, s_hi)
    np.testing.assert_array_equal(tree["node_lowers"], nlo)
    np.testing.assert_array_equal(tree["node_uppers"], nhi)
    shuffled = hb.build_from_bounds(lo, hi, method="hlbvh_sah", device=device, config=cfg).to_numpy()
    assert sah_reference(tree) == pytest.approx(sah_reference(shuffled), rel=1e-6)



# --------------------------------------------------------------------------- rays
def _bumpy_mesh():
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=4)
    v = m.vertices * (1 + 0.1 * np.sin(7 * m.vertices[:, :1]))
    return trimesh.Trimesh(v, m.faces, process=False)


@pytest.mark.parametrize("method", ["hlbvh", "lbvh"])
def test_intersect_generated_mesh(device, rng, method):
    mesh = _bumpy_mesh()
    bvh = hb.build(mesh, method=method, device=device)
    o, d = random_rays(rng, mesh.vertices, 400)
    t, p = hb.intersect(bvh, o, d)
    assert_hits_match(t, p, *brute_force_closest_hit(mesh.vertices, mesh.faces, o, d))
    assert (p >= 0).sum() > 100


@pytest.mark.parametrize("leaf", [1, 4])
def test_intersect_random_soup(device, rng, leaf):
    v, f = random_soup(rng, 3000)
    bvh = hb.build(v, f, device=device, config=hb.BuildConfig(max_leaf_size=leaf, planes_per_pass=2))
    o, d = random_rays(rng, v, 400)
    t, p = hb.intersect(bvh, o, d)
    assert_hits_match(t, p, *brute_force_closest_hit(v, f, o, d))


def test_intersect_t_max(device, rng):
    mesh = _bumpy_mesh()
    bvh = hb.build(mesh, device=device)
    o, d = random_rays(rng, mesh.vertices, 300)
    t_ref, p_ref = brute_force_closest_hit(mesh.vertices, mesh.faces, o, d, t_max=2.0)
    t, p = hb.intersect(bvh, o, d, t_max=2.0)
    assert_hits_match(t, p, t_ref, p_ref)


@pytest.mark.parametrize("name", ["suzanne", "teapot", "bunny", "armadillo"])
def test_intersect_shared_meshes(device, rng, name):
    mesh = shared_mesh(name)
    bvh = hb.build(mesh, device=device)
    check_tree_invariants(bvh.to_numpy(), len(mesh.faces), exact_node_count=None)
    o, d = random_rays(rng, mesh.vertices, 150)
    t, p = hb.intersect(bvh, o, d)
    assert_hits_match(t, p, *brute_force_closest_hit(mesh.vertices, mesh.faces, o, d))


def test_degenerate_triangles_are_valid(device, rng):
    v, f = random_soup(rng, 200)
    f[:50, 2] = f[:50, 1]  # segments
    f[50:80, 1:] = f[50:80, :1]  # points
    bvh = hb.build(v, f, device=device)
    check_tree_invariants(bvh.to_numpy(), 200)
    o, d = random_rays(rng, v, 200)
    t, p = hb.intersect(bvh, o, d)
    assert_hits_match(t, p, *brute_force_closest_hit(v, f, o, d))


# --------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "vertices, faces, message",
    [
        (np.array([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]], np.float32), [[0, 1, 2]], "NaN or Inf"),
        (np.array([[0, 0, 0], [1, 0, 0], [0, np.inf, 0]]), [[0, 1, 2]], "NaN or Inf"),
        (np.array([[0, 0, 0], [1, 0, 0], [0, 1e39, 0]]), [[0, 1, 2]], "float32 range"),
        (np.eye(3), [[0, 1, 3]], "out of range"),
        (np.eye(3), [[0, -1, 2]], "out of range"),
        (np.eye(3)[:, :2], [[0, 1, 2]], "shape"),
        (np.eye(3), [[0, 1]], "shape"),
        (np.eye(3), np.array([[0.0, 1.0, 2.0]]), "integers"),
        (np.zeros((0, 3)), np.zeros((0, 3), np.int32), "empty"),
        (np.eye(3), np.zeros((0, 3), np.int32), "empty"),
        (np.array([["a", "b", "c"]]), [[0, 0, 0]], "real numbers"),
        # Empty lists read as float arrays of shape (0,): the message names the empty mesh.
        (np.eye(3), [], "empty: faces"),
        ([], [], "empty: vertices"),
        ([], [[0, 1, 2]], "empty: vertices"),
    ],
)
def test_bad_input_raises(device, vertices, faces, message):
    with pytest.raises(ValueError, match=message):
        hb.build(vertices, faces, device=device)


def test_an_out_of_range_index_is_named_with_the_face_that_holds_it(device):
    # Face 0 holds 5 and face 2 holds 7: the message said "face index 7 ... (first at face 0)",
    # naming a face that does not hold 7.
    faces = [[0, 1, 5], [0, 1, 2], [7, 1, 2]]
    with pytest.raises(ValueError, match=r"face index 5 out of range \[0, 3\) \(first at face 0\)"):
        hb.build(np.eye(3), faces, device=device)
    with pytest.raises(ValueError, match=r"face index -2 out of range \[0, 3\) \(first at face 1\)"):
        hb.build(np.eye(3), [[0, 1, 2], [0, -2, 9], [-3, 1, 2]], device=device)


def test_bad_bounds_and_options(device):
    with pytest.raises(ValueError, match="lowers > uppers"):
        hb.build_from_bounds(np.ones((2, 3)), np.zeros((2, 3)), device=device)
    with pytest.raises(ValueError, match="unknown method"):
        hb.build(np.eye(3), [[0, 1, 2]], method="nope", device=device)
    with pytest.raises(ValueError, match="unknown method"):
        hb.build(np.eye(3), [[0, 1, 2]], method=["hlbvh"], device=device)
    with pytest.raises(ValueError, match="alone, or vertices with faces="):
        hb.build(trimesh.creation.box(), faces=[[0, 1, 2]], device=device)
    with pytest.raises(ValueError, match="planes_per_pass"):
        hb.BuildConfig(planes_per_pass=9)
    with pytest.raises(ValueError, match="global_sort_runs"):
        hb.BuildConfig(global_sort_runs=-0.1)
    with pytest.raises(ValueError, match="differ in shape"):
        hb.intersect(hb.build(np.eye(3), [[0, 1, 2]], device=device), np.zeros((2, 3)), np.zeros((3, 3)))


def test_float64_and_wide_int_input(device):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
    f = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint64)
    bvh = hb.build(v, f, device=device)
    t, p = hb.intersect(bvh, [[0.2, 0.2, 1.0]], [[0, 0, -1]])
    assert p[0] == 0 and t[0] == pytest.approx(1.0)
    bvh2 = hb.build(wp.array(v.astype(np.float32), dtype=wp.vec3, device=device),
                    wp.array(f.astype(np.int32), dtype=wp.int32, device=device), device=device)
    assert bvh2.num_nodes == 3


def test_voxel_sort_of_nearly_sorted_input(device, rng):
    # The previous frame's order with a few primitives moved: blocks take the insertion path.
    lo, hi = soup_bounds(rng, 6000, clusters=True)
    pipe = make_pipeline(lo, hi, device)
    pipe.compute_morton_codes()
    order = np.argsort(pipe.morton_codes.numpy(), kind="stable")
    lo, hi = lo[order].copy(), hi[order].copy()
    swap = rng.choice(len(lo), size=(6, 2), replace=False)
    for a, b in swap:
        lo[[a, b]], hi[[a, b]] = lo[[b, a]], hi[[b, a]]
    pipe = make_pipeline(lo, hi, device)
    pipe.build("hlbvh")
    np.testing.assert_array_equal(
        pipe.sorted_prim_ids.numpy()[: len(lo)], np.argsort(pipe.morton_codes.numpy(), kind="stable")
    )


# ----------------------------------------------------------------- pinned by the mutation audit
def test_input_forms_and_their_checks(device):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    f = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    # Faces as one flat run of indices are the same mesh.
    flat = hb.build(v, f.ravel(), device=device)
    assert flat.num_prims == 2 and np.array_equal(flat.faces.numpy(), f)
    # One ray as a (3,) origin and direction.
    t, p = hb.intersect(flat, [0.2, 0.2, 1.0], [0.0, 0.0, -1.0])
    assert p.tolist() == [0] and t[0] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="differ in shape"):
        hb.build_from_bounds(np.zeros((4, 3)), np.ones((5, 3)), device=device)
    with pytest.raises(ValueError, match="no primitives"):
        hb.build_from_bounds(np.zeros((0, 3)), np.zeros((0, 3)), device=device)




def test_indexed_warp_arrays_are_read_as_the_rows_they_select(device, rng):
    # A wp.indexedarray (rows of a Warp array picked by an index array) is no wp.array subclass:
    # NumPy wrapped it as one object and the build refused it as "must hold real numbers, got
    # dtype object", though it holds vec3 floats as any Warp array.
    pool = rng.random((40, 3)).astype(np.float32)
    picked = rng.permutation(40)[:24].astype(np.int32)
    selected = pool[picked]
    faces = np.arange(24, dtype=np.int32).reshape(8, 3)

    def indexed(rows):
        return wp.indexedarray(wp.array(rows, dtype=wp.vec3, device=device),
                               [wp.array(picked, dtype=wp.int32, device=device)])

    bvh = hb.build(indexed(pool), faces, device=device)
    np.testing.assert_array_equal(bvh.vertices.numpy(), selected)
    o, d = random_rays(rng, selected, 50)
    assert_hits_match(*hb.intersect(bvh, o, d), *brute_force_closest_hit(selected, faces, o, d))
    # A lowers / uppers pair, one indexed and one NumPy.
    boxes = hb.build_from_bounds(indexed(pool), selected + np.float32(0.1), device=device)
    np.testing.assert_array_equal(boxes.prim_lowers.numpy(), selected)
    np.testing.assert_array_equal(boxes.prim_uppers.numpy(), selected + np.float32(0.1))


def test_wide_integer_vertices_are_rounded_once(device):
    # Through float64, 2^54 + 2^30 + 1 rounded to 2^54 + 2^30 and then (a tie) to 2^54; the
    # float32 nearest to it is 2^54 + 2^31.
    x = 2**54 + 2**30 + 1
    for dtype in (np.int64, np.uint64):
        v = np.array([[x, 0, 0], [x, 1, 0], [x, 0, 1]], dtype=dtype)
        bvh = hb.build(v, faces=[[0, 1, 2]], device=device)
        assert bvh.vertices.numpy()[0, 0] == np.float32(2**54 + 2**31)

def test_empty_query_arrays_of_no_numbers_are_refused(device):
    # Only an empty array of numbers is no queries; an empty object, string or bool array is the
    # same dtype error as a full one.
    bvh = hb.build(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32), faces=[[0, 1, 2]], device=device)
    assert hb.closest_point(bvh, [])[2].shape == (0,)
    for empty in (np.array([], dtype=object), np.array([], dtype=str), np.array([], dtype=bool)):
        with pytest.raises(ValueError, match="points must hold real numbers"):
            hb.closest_point(bvh, empty)


def test_several_meshes_are_refused_with_the_way_to_join_them(device):
    # A scene or a list of meshes is the natural thing to pass; the error says how to make one
    # mesh of it, and the joined mesh builds (face ids running through the meshes in order).
    meshes = [trimesh.creation.box(), trimesh.creation.icosphere(subdivisions=1)]
    with pytest.raises(ValueError, match=r"trimesh\.Scene.*to_mesh\(\)"):
        hb.build(trimesh.Scene(meshes), device=device)
    for given in (meshes, tuple(meshes)):
        with pytest.raises(ValueError, match=r"of 2: .*trimesh\.util\.concatenate"):
            hb.build(given, device=device)
    with pytest.raises(ValueError, match="trimesh.Scene"):
        hb.Builder(92, device=device).build(trimesh.Scene(meshes))
    joined = trimesh.util.concatenate(meshes)
    # A ray down onto the sphere (moved aside: its vertices follow the box's 8) hits a face past
    # the box's 12.
    joined.vertices[8:] += (3.0, 0.0, 0.0)
    bvh = hb.build(joined, device=device)
    t, prim = hb.intersect(bvh, [[3.0, 0.0, 5.0], [0.0, 0.0, 5.0]], [0.0, 0.0, -1.0])
    assert prim[0] >= 12 and 0 <= prim[1] < 12


# ----------------------------------------------------------------- pinned by the second mutation audit
def test_vertex_input_edges(device):
    faces = [[0, 1, 2]]
    # float32's largest value, given as float64, fits exactly: accepted (only beyond it is refused).
    big = float(np.finfo(np.float32).max)
    bvh = hb.build(np.array([[0, 0, 0], [1, 0, 0], [0, big, 0]], np.float64), faces, device=device)
    assert bvh.to_numpy()["node_uppers"][0][1] == np.float32(big)
    with pytest.raises(ValueError, match="beyond the float32 range"):
        hb.build(np.array([[0, 0, 0], [1, 0, 0], [0, 2 * big, 0]], np.float64), faces, device=device)
    # A long double past float64's range was rounded to float64 first: it became inf and was
    # refused as a NaN or Inf coordinate (with NumPy's overflow warning), though it is finite.
    if np.finfo(np.longdouble).max > np.finfo(np.float64).max:
        huge = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.longdouble)
        huge[2, 1] = np.longdouble("1e400")
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with pytest.raises(ValueError, match="beyond the float32 range"):
                hb.build(huge, faces, device=device)
            with pytest.raises(ValueError, match="lowers has a coordinate beyond the float32 range"):
                hb.build_from_bounds(huge, huge + 1, device=device)
    # A flat NumPy array is not (n, 3) vertices (only a flat wp.array of floats is read as rows).
    with pytest.raises(ValueError, match=r"must have shape \(n, 3\)"):
        hb.build(np.array([0, 0, 0, 1, 0, 0, 0, 1, 0], np.float32), faces, device=device)
    with pytest.raises(ValueError, match="real numbers"):
        hb.build(np.eye(3, dtype=bool), faces, device=device)
