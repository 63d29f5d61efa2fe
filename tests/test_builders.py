"""The reference builders (sweep_sah, binned_sah, median, hlbvh_sah): tree invariants, the
brute-force ray oracle, and the greedy sweep against an exhaustive NumPy evaluation."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import hlbvh_warp as hw
from hlbvh_warp.builders import build_top_down
from hlbvh_warp.hlbvh import StageTimer
from hlbvh_warp.metrics import sah_cost
from conftest import shared_mesh
from oracles import assert_hits_match, brute_force_closest_hit, check_tree_invariants, random_rays, random_soup

NEW_METHODS = ["sweep_sah", "binned_sah", "median", "hlbvh_sah"]


def check_rays(bvh, vertices, faces, rng, num_rays=96):
    origins, directions = random_rays(rng, vertices, num_rays)
    t, prim = hw.intersect(bvh, origins, directions)
    t_ref, prim_ref = brute_force_closest_hit(vertices, faces, origins, directions)
    assert_hits_match(t, prim, t_ref, prim_ref)


@pytest.mark.parametrize("method", NEW_METHODS)
@pytest.mark.parametrize("leaf", [1, 4])
def test_random_soup(device, rng, method, leaf):
    v, f = random_soup(rng, 300)
    bvh = hw.build(v, f, method=method, device=device, config=hw.BuildConfig(max_leaf_size=leaf))
    exact = 2 * 300 - 1 if leaf == 1 else None
    check_tree_invariants(bvh.to_numpy(), 300, leaf, exact_node_count=exact)
    check_rays(bvh, v, f, rng)


@pytest.mark.parametrize("method", NEW_METHODS)
def test_shared_mesh(device, rng, method):
    mesh = shared_mesh("suzanne")
    v, f = np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)
    bvh = hw.build(v, f, method=method, device=device, config=hw.BuildConfig(sah_bins=8))
    check_tree_invariants(bvh.to_numpy(), len(f), 1, exact_node_count=2 * len(f) - 1)
    check_rays(bvh, v, f, rng)


@pytest.mark.parametrize("emission", ["treelets", "depth_first"])
@pytest.mark.parametrize("coarse_bits", [0, 1, 3, 10])
def test_hlbvh_sah_cluster_counts(device, rng, coarse_bits, emission):
    # m = 0: one cluster (no top tree); m = n: clusters are whole Morton cells, no treelets.
    v, f = random_soup(rng, 200)
    cfg = hw.BuildConfig(coarse_bits=coarse_bits, max_leaf_size=2, emission=emission)
    bvh = hw.build(v, f, method="hlbvh_sah", device=device, config=cfg)
    check_tree_invariants(bvh.to_numpy(), 200, 2)
    check_rays(bvh, v, f, rng, num_rays=48)


def test_hlbvh_sah_emissions_agree(device, rng):
    # Both schedules emit the same cluster subtrees, so the trees have the same SAH cost.
    v, f = random_soup(rng, 2000)
    costs = [hw.metrics.sah_cost(hw.build(v, f, method="hlbvh_sah", device=device,
                                          config=hw.BuildConfig(emission=e)))
             for e in ("treelets", "depth_first")]
    assert costs[0] == pytest.approx(costs[1], rel=1e-9)


@pytest.mark.parametrize("method", ["sweep_sah", "binned_sah", "median"])
@pytest.mark.parametrize("leaf", [1, 3])
def test_top_down_schedules_agree(device, rng, method, leaf):
    # Level by level and depth first make the same splits: the same nodes (as primitive sets),
    # the same primitive order, only the numbering differs.
    v, f = random_soup(rng, 700)
    trees = []
    for emission in ("treelets", "depth_first"):
        cfg = hw.BuildConfig(emission=emission, max_leaf_size=leaf)
        bvh = hw.build(v, f, method=method, device=device, config=cfg)
        tree = bvh.to_numpy()
        check_tree_invariants(tree, 700, leaf, exact_node_count=2 * 700 - 1 if leaf == 1 else None)
        trees.append(tree)
    assert np.array_equal(trees[0]["prim_order"], trees[1]["prim_order"])
    ranges = [sorted(zip(t["node_begin"].tolist(), t["node_end"].tolist())) for t in trees]
    assert ranges[0] == ranges[1]
    assert trees[0]["node_left"].shape == trees[1]["node_left"].shape


def numpy_cluster_bits(v, f, m, min_prims):
    """The automatic cluster grid of hlbvh_sah, recomputed in NumPy: from m bits per axis down,
    while the non-empty voxels hold fewer than `min_prims` box centroids on average."""
    tri = v[f].astype(np.float64)
    c = 0.5 * (tri.min(1) + tri.max(1))
    lo, hi = c.min(0), c.max(0)
    q = np.clip(np.floor((c - lo) / (hi - lo) * 1024), 0, 1023).astype(np.int64)
    while m > 1 and len(f) < min_prims * len(np.unique(q >> (10 - m), axis=0)):
        m -= 1
    return m


def test_hlbvh_sah_merges_small_clusters(device, rng):
    # A soup of 6000 triangles gives almost one triangle per voxel at m = 6: the automatic grid
    # coarsens until clusters hold 6 on average. The tree must be the one an explicit build on
    # that grid gives (the primitive order sorted by full codes is the same for any m).
    v, f = random_soup(rng, 6000)
    m = numpy_cluster_bits(v, f, 6, 6.0)
    assert m < 6
    merged = hw.build(v, f, method="hlbvh_sah", device=device)
    explicit = hw.build(v, f, method="hlbvh_sah", device=device, config=hw.BuildConfig(coarse_bits=m))
    unmerged = hw.build(v, f, method="hlbvh_sah", device=device, config=hw.BuildConfig(cluster_min_prims=0))
    check_tree_invariants(merged.to_numpy(), 6000, 1, exact_node_count=2 * 6000 - 1)
    assert np.array_equal(merged.to_numpy()["prim_order"], explicit.to_numpy()["prim_order"])
    assert sah_cost(merged) == pytest.approx(sah_cost(explicit), rel=1e-9)
    # Switched off, the clusters stay the m = 6 voxels: a different (larger) cluster tree.
    assert sah_cost(unmerged) != pytest.approx(sah_cost(merged), rel=1e-6)
    six = hw.build(v, f, method="hlbvh_sah", device=device, config=hw.BuildConfig(coarse_bits=6))
    assert sah_cost(unmerged) == pytest.approx(sah_cost(six), rel=1e-9)


def numpy_cluster_count(v, f, bits):
    """Non-empty voxels of `bits` bits per axis over the box centroids, in NumPy (the centroids
    in float32, as the kernels form them, then quantized in float64)."""
    tri = v[f].astype(np.float32)
    c = (np.float32(0.5) * (tri.min(1) + tri.max(1))).astype(np.float64)
    lo, hi = c.min(0), c.max(0)
    extent = np.where(hi > lo, hi - lo, 1.0)
    q = np.clip(np.floor((c - lo) / extent * 1024), 0, 1023).astype(np.int64)
    return len(np.unique(q >> (10 - bits), axis=0))


@pytest.mark.parametrize("num_tris", [7, 3000])
@pytest.mark.parametrize("coarse_bits,min_prims", [(None, 6.0), (None, 1.0), (None, 0.0), (2, 6.0), (10, 6.0)])
def test_cluster_tree_reserve_bounds_every_build(device, rng, num_tris, coarse_bits, min_prims):
    # A per-frame Builder reserves the cluster tree once, for `max_clusters`; no scene may need more.
    # The cluster count of each build is checked against NumPy's count of non-empty voxels.
    v, f = random_soup(rng, num_tris)
    cfg = hw.BuildConfig(coarse_bits=coarse_bits, cluster_min_prims=min_prims)
    builder = hw.Builder(num_tris, cfg, device=device, method="hlbvh_sah")
    pipe = builder.pipeline
    top = pipe.top
    builder.build(v, f)
    bits = numpy_cluster_bits(v, f, pipe.coarse_bits, min_prims) if coarse_bits is None else coarse_bits
    assert top.num_clusters == numpy_cluster_count(v, f, bits)
    assert pipe.top is top and top.num_clusters <= top.capacity == pipe.max_clusters()
    check_tree_invariants(builder.bvh.to_numpy(), num_tris, 1, exact_node_count=2 * num_tris - 1)


def test_cluster_tree_reserve_holds_a_count_the_quotient_rounds_below(device):
    # 17 primitives and cluster_min_prims = 1.7000000000000002 (17 x 0.1): 17 / 1.7000000000000002
    # rounds to 9.999..., but 1.7000000000000002 x 10 rounds to 17.0, so the coarsening stops at 10
    # clusters. The reserve was int(17 / 1.7000000000000002) = 9, one short: the frame allocated a
    # new cluster tree. Ten points on a diagonal, seven of them twice: 10 voxels at m = 6.
    min_prims = 17 * 0.1
    assert 17 / min_prims < 10 and not 17 < min_prims * 10
    points = np.linspace(0.0, 1.0, 10)[:, None].repeat(3, axis=1)
    centers = np.concatenate([points, points[:7]]).astype(np.float32)
    builder = hw.Builder(17, hw.BuildConfig(cluster_min_prims=min_prims), device=device, method="hlbvh_sah")
    pipe = builder.pipeline
    top = pipe.top
    builder.build_from_bounds(centers, centers)
    assert pipe.top.num_clusters == 10
    assert pipe.top is top and top.num_clusters <= top.capacity == pipe.max_clusters()
    check_tree_invariants(builder.bvh.to_numpy(), 17, 1, exact_node_count=2 * 17 - 1)


def test_cluster_min_prims_validated():
    with pytest.raises(ValueError, match="cluster_min_prims"):
        hw.BuildConfig(cluster_min_prims=-1.0)


@pytest.mark.parametrize("field, value", [("sbvh_bins", 8.0), ("max_leaf_size", 2.5), ("cpu_threads", True),
                                          ("coarse_bits", "3"), ("sbvh_alpha", None), ("sah_bins", None),
                                          ("global_sort_runs", "0.3"), ("emission", 3)])
def test_config_types_are_checked(field, value):
    # A float where a kernel takes an int failed only at launch ("unable to pack kernel
    # parameter"), and None or a string in a numeric field raised a TypeError from a comparison.
    with pytest.raises(ValueError, match=field):
        hw.BuildConfig(**{field: value})


@pytest.mark.parametrize("bounds", [(("0", "0", "0"), ("1", "1", "1")), ((False, False, False), (True, True, True)),
                                    ((0, 0, 0), (1, 1, True)), np.array([["0", "0", "0"], ["1", "1", "1"]]),
                                    np.array([[0, 0, 0], [1, 1, 1]], dtype=bool)])
def test_morton_bounds_refuse_strings_and_booleans(bounds):
    # NumPy read the strings and booleans as the numbers 0 and 1, where every other number field
    # refuses them.
    with pytest.raises(ValueError, match="morton_bounds must hold numbers"):
        hw.BuildConfig(morton_bounds=bounds)


def test_morton_bounds_take_numbers_of_any_kind():
    config = hw.BuildConfig(morton_bounds=np.array([[0, 0, 0], [1, 2, 3]], dtype=np.float32))
    assert config.morton_bounds == ((0.0, 0.0, 0.0), (1.0, 2.0, 3.0))
    assert hw.BuildConfig(morton_bounds=[[np.int64(0), 0.0, 0], [1, np.float64(2), 3]]) == config


@pytest.mark.parametrize("field", ["block_capacity", "cpu_threads", "planes_per_pass"])
@pytest.mark.parametrize("value", [2**31, 2**32, 2**40, -(2**31) - 1])
def test_config_integers_must_fit_the_kernels_int32(field, value):
    # block_capacity = 2^32 wrapped to 0 in the voxel sort's int32 parameter, and the division
    # by it killed the process (SIGFPE).
    with pytest.raises(ValueError, match=f"{field} must fit in int32"):
        hw.BuildConfig(**{field: value})


@pytest.mark.parametrize("field, value", [("sah_traversal_cost", 10**400), ("sbvh_alpha", -(10**400)),
                                          ("cluster_min_prims", 10**400), ("max_leaf_size", 10**5000),
                                          ("block_capacity", -(10**5000))],
                         ids=["float 1e400", "float -1e400", "float 1e400 again", "int 1e5000", "int -1e5000"])
def test_integers_past_every_range_are_refused_by_name(field, value):
    # A float setting took float(10**400), which raised OverflowError; an integer setting's
    # message printed the value, and Python refused to print 5000 digits ("Exceeds the limit
    # (4300 digits) for integer string conversion"), a ValueError that named no setting.
    with pytest.raises(ValueError, match=f"BuildConfig: {field} ") as error:
        hw.BuildConfig(**{field: value})
    assert "4300" not in str(error.value)


def test_config_takes_numpy_scalars_as_plain_numbers(device, rng):
    config = hw.BuildConfig(sah_bins=np.int64(8), max_leaf_size=np.int32(2), sbvh_alpha=0)
    assert type(config.sah_bins) is int and type(config.sbvh_alpha) is float
    assert config == hw.BuildConfig(sah_bins=8, max_leaf_size=2, sbvh_alpha=0.0)
    verts, faces = random_soup(rng, 200)
    bvh = hw.build(verts, faces, method="binned_sah", device=device, config=config)
    check_tree_invariants(bvh.to_numpy(), len(faces), 2)


def test_hlbvh_sah_binned_top_costs_little(device, rng, monkeypatch):
    # The cluster tree bins its largest nodes; pricing every position instead must not be
    # noticeably better (and the binned tree must still be a valid tree).
    from hlbvh_warp import builders

    v, f = random_soup(rng, 30_000)
    cfg = hw.BuildConfig(coarse_bits=5)
    binned = hw.build(v, f, method="hlbvh_sah", device=device, config=cfg)
    check_tree_invariants(binned.to_numpy(), 30_000, 1, exact_node_count=2 * 30_000 - 1)
    monkeypatch.setattr(builders, "TOP_TREE_BINNED_ABOVE", 0)
    swept = hw.build(v, f, method="hlbvh_sah", device=device, config=cfg)
    assert sah_cost(binned) <= sah_cost(swept) * 1.01


@pytest.mark.parametrize("method", NEW_METHODS)
def test_duplicate_boxes(device, method):
    # Equal centroids everywhere: no plane separates them, the builders must still finish.
    lo = np.tile(np.array([[1.0, 2.0, 3.0]], np.float32), (37, 1))
    bvh = hw.build_from_bounds(lo, lo + 1, method=method, device=device, config=hw.BuildConfig(max_leaf_size=3))
    check_tree_invariants(bvh.to_numpy(), 37, 3)


def test_sah_termination_option(device, rng):
    v, f = random_soup(rng, 200)
    lo, hi = v[f].min(1), v[f].max(1)
    cfg = hw.BuildConfig(max_leaf_size=1)
    wl, wh = wp.array(lo, dtype=wp.vec3, device=device), wp.array(hi, dtype=wp.vec3, device=device)
    bvh = build_top_down(wl, wh, cfg, device, StageTimer(device, False), method="sweep_sah", terminate_leaf_size=8)
    tree = bvh.to_numpy()
    check_tree_invariants(tree, 200, 8)
    full = hw.build_from_bounds(lo, hi, method="sweep_sah", device=device, config=cfg)
    # Terminating only where a leaf is cheaper can only lower the cost of the greedy tree's nodes.
    assert sah_cost(bvh) <= sah_cost(full) * (1 + 1e-9)
    assert bvh.num_nodes < full.num_nodes


def test_sah_builders_beat_morton_on_a_mesh(device):
    mesh = shared_mesh("teapot")
    v, f = np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)
    cost = {m: sah_cost(hw.build(v, f, method=m, device=device)) for m in ["sweep_sah", "hlbvh_sah", "hlbvh"]}
    assert cost["sweep_sah"] < cost["hlbvh"]
    assert cost["hlbvh_sah"] < cost["hlbvh"]


# ----------------------------------------------------------------- exhaustive greedy reference
def area64(lo, hi):
    d = hi.astype(np.float64) - lo.astype(np.float64)
    return 2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0])


def greedy_sweep_reference(lo, hi, t1=None, t2=None):
    """Every node of the greedy SAH tree as a frozenset of primitives. For each node, each axis
    (centroid order, ties by index) and each split position, both boxes are recomputed from
    scratch: O(N^2) per node. Lowest area(L) N(L) + area(R) N(R) wins; ties to the lower axis,
    then the leftmost position. With the SAH constants `t1`, `t2`, a node stays a leaf when its
    best split costs at least as much as a leaf: 2 T1 + T2 * best / area(node) >= T2 * N."""
    cent = np.float32(0.5) * (lo + hi)
    nodes = []

    def rec(ids):
        nodes.append(frozenset(ids))
        if len(ids) <= 1:
            return
        best = None
        for axis in range(3):
            ordered = sorted(ids, key=lambda i: (cent[i, axis], i))
            for k in range(1, len(ordered)):
                left, right = ordered[:k], ordered[k:]
                c = area64(lo[left].min(0), hi[left].max(0)) * k + area64(lo[right].min(0), hi[right].max(0)) * (
                    len(ordered) - k)
                unbalance = abs(2 * k - len(ordered))
                if best is None or c < best[0] or (c == best[0] and unbalance < best[3]):
                    best = (c, left, right, unbalance)
        if t1 is not None and 2 * t1 + t2 * best[0] / area64(lo[ids].min(0), hi[ids].max(0)) >= t2 * len(ids):
            return
        rec(best[1])
        rec(best[2])

    rec(list(range(len(lo))))
    return sorted(nodes, key=sorted)


@pytest.mark.parametrize("emission", ["treelets", "depth_first"])
@pytest.mark.parametrize("seed", range(6))
def test_sweep_sah_equals_exhaustive_greedy(device, seed, emission):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 13))
    lo = (rng.random((n, 3)) * 10).astype(np.float32)
    hi = lo + (rng.random((n, 3)) * rng.choice([0.5, 4.0])).astype(np.float32)
    bvh = hw.build_from_bounds(lo, hi, method="sweep_sah", device=device, config=hw.BuildConfig(emission=emission))
    tree = bvh.to_numpy()
    order, begin, end = tree["prim_order"], tree["node_begin"], tree["node_end"]
    got = sorted((frozenset(order[b:e].tolist()) for b, e in zip(begin, end)), key=sorted)
    assert got == greedy_sweep_reference(lo, hi)


def _lattice_boxes(shape):
    """Equal unit boxes on a lattice of spacing 2: split costs and balances tie exactly."""
    cells = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1).reshape(-1, 3)
    lo = cells.astype(np.float32) * np.float32(2.0)
    return lo, lo + np.float32(1.0)


def assert_root_split(tree, lo, hi, axis, k):
    """The root's left child is exactly the k items first in centroid order on ``axis``."""
    left = tree["node_left"][0]
    left_prims = tree["prim_order"][tree["node_begin"][left]:tree["node_end"][left]]
    assert len(left_prims) == k
    c = np.float32(0.5) * (lo[:, axis] + hi[:, axis])
    assert set(left_prims.tolist()) == set(np.argsort(c, kind="stable")[:k].tolist())


def binned_root_split_reference(lo, hi, num_bins):
    """Root split of binned SAH (Wald 2007) in float64: bins of equal width over the centroid
    extent per axis, every non-trivial bin boundary priced as area(L) * |L| + area(R) * |R|;
    equal costs go to the most balanced boundary, then to the lower axis."""
    c = (np.float32(0.5) * (lo + hi)).astype(np.float32)
    best = None
    for axis in range(3):
        cmin, cmax = c[:, axis].min(), c[:, axis].max()
        if not cmax > cmin:
            continue
        scale = np.float64(num_bins) / (np.float64(cmax) - np.float64(cmin))
        bins = np.clip(((c[:, axis].astype(np.float64) - cmin) * scale).astype(np.int64), 0, num_bins - 1)
        for j in range(1, num_bins):
            left = bins < j
            k = int(left.sum())
            if k == 0 or k == len(lo):
                continue

            def area(mask):
                d = hi[mask].max(0).astype(np.float64) - lo[mask].min(0).astype(np.float64)
                return 2 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0])

            cost = area(left) * k + area(~left) * (len(lo) - k)
            unbalance = abs(2 * k - len(lo))
            # Costs within rounding tie; a tie goes to the more balanced position, then to the
            # earlier axis and position (the order priced here).
            if (best is None or cost < best[0] * (1 - 1e-12)
                    or (cost <= best[0] * (1 + 1e-12) and unbalance < abs(2 * best[2] - len(lo)))):
                best = (cost, axis, k)
    return best


@pytest.mark.parametrize("num_bins", [4, 16, 32])
@pytest.mark.parametrize("seed", range(4))
def test_binned_root_split_matches_numpy(device, num_bins, seed):
    rng = np.random.default_rng(100 + seed)
    n = 400
    lo = (rng.random((n, 3)) * [10, 3, 6]).astype(np.float32)
    hi = lo + (rng.random((n, 3)) * 0.5).astype(np.float32)
    tree = hw.build_from_bounds(lo, hi, method="binned_sah", device=device,
                                config=hw.BuildConfig(sah_bins=num_bins)).to_numpy()
    assert_root_split(tree, lo, hi, *binned_root_split_reference(lo, hi, num_bins)[1:])


@pytest.mark.parametrize("num_bins", [16, 64])
def test_binned_sah_near_the_smallest_normal(device, num_bins):
    """Centroids spread over about 2e-38, near float32's smallest normal: num_bins / extent is past
    float32's range (a float32 scale put every item in one bin). The root split is NumPy's in
    float64, and the whole tree is the one over the same boxes scaled up by 2^125 (exact: a power
    of two, every value normal)."""
    rng = np.random.default_rng(7)
    n = 300
    # In [1, 2): a power-of-two scale is exact.
    unit_lo = (1.0 + 0.9 * rng.random((n, 3))).astype(np.float32)
    unit_hi = unit_lo + (rng.random((n, 3)) * 0.05).astype(np.float32)
    tiny = np.float32(2.0**-125)
    lo, hi = unit_lo * tiny, unit_hi * tiny
    centroids = np.float32(0.5) * (lo + hi)
    extents = centroids.max(axis=0) - centroids.min(axis=0)
    with np.errstate(over="ignore"):
        assert np.isinf(np.float32(num_bins) / extents).all()  # the scene does what the test means
    config = hw.BuildConfig(sah_bins=num_bins)
    tree = hw.build_from_bounds(lo, hi, method="binned_sah", device=device, config=config).to_numpy()
    assert_root_split(tree, lo, hi, *binned_root_split_reference(lo, hi, num_bins)[1:])
    unit = hw.build_from_bounds(unit_lo, unit_hi, method="binned_sah", device=device, config=config).to_numpy()
    for name in ("node_left", "node_right", "node_begin", "node_end", "prim_order"):
        np.testing.assert_array_equal(tree[name], unit[name], err_msg=name)
    check_tree_invariants(tree, n)


@pytest.mark.parametrize("method", ["hlbvh", "lbvh", "hlbvh_sah", "sweep_sah", "binned_sah", "median"])
@pytest.mark.parametrize("mesh", [False, True])
@pytest.mark.parametrize("signs", ["positive", "both"])
def test_centroids_near_the_largest_float32(device, method, mesh, signs):
    """Coordinates up to 2^128, all finite float32 (the input checks accept them): the sum
    lower + upper of a centroid ("positive": [2^127, 2^128)) or the centroids' extent ("both":
    (-2^128, 2^128)) is past float32's range. The tree must be the one over the same geometry
    scaled down by 2^127 (exact: a power of two, every value normal), where an overflowed centroid
    (inf) put every primitive in one Morton cell or at one sweep position and left the input
    order (an SAH cost 20x the unit scene's), and an overflowed extent made the median split
    the first axis whatever its extent."""
    rng = np.random.default_rng(8)
    n = 400

    def unit_coords(shape):
        if signs == "positive":
            return (1.0 + 0.9 * rng.random(shape)).astype(np.float32)
        return (1.9 * (2.0 * rng.random(shape) - 1.0)).astype(np.float32)

    def scaled(x):
        big = x.astype(np.float64) * 2.0**127
        return big.astype(np.float32)

    if mesh:
        unit_v = unit_coords((3 * n, 3))
        # Long thin triangles along y on one half, along z on the other: the median's axis matters.
        unit_v[1::3] = unit_v[0::3]
        unit_v[2::3] = unit_v[0::3]
        unit_v[1::3, 1] += np.float32(0.05)
        unit_v[2::3, 2] += np.float32(0.05)
        faces = np.arange(3 * n, dtype=np.int32).reshape(n, 3)
        tree = hw.build(scaled(unit_v), faces, method=method, device=device).to_numpy()
        unit = hw.build(unit_v, faces, method=method, device=device).to_numpy()
        unit_lo = unit_v.reshape(n, 3, 3).min(axis=1)
        unit_hi = unit_v.reshape(n, 3, 3).max(axis=1)
    else:
        unit_lo = unit_coords((n, 3))
        unit_hi = unit_lo + (rng.random((n, 3)) * 0.05).astype(np.float32)
        tree = hw.build_from_bounds(scaled(unit_lo), scaled(unit_hi), method=method, device=device).to_numpy()
        unit = hw.build_from_bounds(unit_lo, unit_hi, method=method, device=device).to_numpy()
    with np.errstate(over="ignore"):  # the scene does what the test means
        sums = scaled(unit_lo) + scaled(unit_hi)
        if signs == "positive":
            assert np.isinf(sums).all()
        else:
            centroids = (unit_lo.astype(np.float64) + unit_hi) * 2.0**126
            assert np.isinf((centroids.max(axis=0) - centroids.min(axis=0)).astype(np.float32)).all()
    for name in ("node_left", "node_right", "node_begin", "node_end", "prim_order"):
        np.testing.assert_array_equal(tree[name], unit[name], err_msg=name)


@pytest.mark.parametrize("num_bins", [4, 32])
@pytest.mark.parametrize("shape", [(4, 4, 4), (3, 5, 5), (6, 6, 2)])
def test_binned_root_split_ties_on_a_lattice(device, num_bins, shape):
    # Equal boxes on a lattice: boundaries on different axes cost exactly the same, and mirror
    # positions tie in balance too; the documented rule picks the most balanced, then the lower
    # axis. (A mutation audit found the lattice tie covered for the sweep only.)
    lo, hi = _lattice_boxes(shape)
    tree = hw.build_from_bounds(lo, hi, method="binned_sah", device=device,
                                config=hw.BuildConfig(sah_bins=num_bins)).to_numpy()
    assert_root_split(tree, lo, hi, *binned_root_split_reference(lo, hi, num_bins)[1:])


def test_presort_keys_order_like_the_floats(device, rng):
    """The top-down presort sorts centroid bits as int32 (`sah.ordered_bits`): the same order as a
    stable float sort, across signs, 40 decades of magnitude, +-0 and ties."""
    from hlbvh_warp.builders import TopDownBuilder

    n = 3000
    centers = rng.standard_normal((n, 3)) * 10.0 ** rng.integers(-20, 20, (n, 3))
    centers[:8] = [[0.0, -0.0, 1e-40], [-0.0, 0.0, -1e-40], [3.0, 3.0, 3.0], [3.0, -3.0, 3.0],
                   [-3.0, 3.0, -3.0], [0.0, 0.0, 0.0], [-5e30, 5e30, 1.0], [5e30, -5e30, 1.0]]
    lowers = centers.astype(np.float32)
    builder = TopDownBuilder(n, device)
    box = wp.array(lowers, dtype=wp.vec3, device=device)
    builder.sort_axes(box, box)
    order = builder.order.numpy().reshape(3, n)
    for axis in range(3):
        keys = np.float32(0.5) * (lowers[:, axis] + lowers[:, axis]) + np.float32(0.0)
        np.testing.assert_array_equal(order[axis], np.argsort(keys, kind="stable"), err_msg=f"axis {axis}")


def test_hlbvh_sah_max_leaf_size_applies_inside_clusters_only(device, rng):
    # Documented (BuildConfig.max_leaf_size): the cluster tree splits down to single clusters,
    # so with one primitive per cluster the leaf size has no effect, while the top-down builders
    # keep a node of at most max_leaf_size primitives as a leaf.
    lo = rng.random((64, 3)).astype(np.float32)
    cfg = hw.BuildConfig(max_leaf_size=64, coarse_bits=10)
    assert hw.build_from_bounds(lo, lo + 0.01, method="sweep_sah", device=device, config=cfg).num_nodes == 1
    tree = hw.build_from_bounds(lo, lo + 0.01, method="hlbvh_sah", device=device, config=cfg).to_numpy()
    check_tree_invariants(tree, 64, 64, exact_node_count=2 * 64 - 1)


@pytest.mark.parametrize("emission", ["treelets", "depth_first"])
@pytest.mark.parametrize("leaf", [1, 4])
def test_hlbvh_sah_subtree_costs_match_numpy(device, rng, emission, leaf):
    """The SAH costs the cluster subtrees are weighted by (eq. 1: T2 N at a leaf of N
    primitives, 2 T1 + the children's costs x area ratios at an interior node), against a
    float64 NumPy evaluation over the finished tree, with T1 != T2 and leaves of several."""
    from hlbvh_warp.builder import Builder

    v, f = random_soup(rng, 2000)
    cfg = hw.BuildConfig(coarse_bits=2, max_leaf_size=leaf, emission=emission, sah_traversal_cost=0.7,
                         sah_intersection_cost=1.3)
    builder = Builder(len(f), cfg, device=device, method="hlbvh_sah", resort=False)
    tree = builder.build(v, f).to_numpy()
    pipe = builder.pipeline
    num_clusters = pipe.top.num_clusters
    assert 1 < num_clusters <= 64
    cost = pipe.node_cost.numpy()
    lo, hi = tree["node_lowers"].astype(np.float64), tree["node_uppers"].astype(np.float64)
    d = hi - lo
    area = 2.0 * (d[:, 0] * d[:, 1] + d[:, 1] * d[:, 2] + d[:, 2] * d[:, 0])
    left, right = tree["node_left"], tree["node_right"]
    expected = np.zeros(len(left))
    # Below the cluster roots the nodes keep their ids, children after parents.
    for i in range(len(left) - 1, 2 * num_clusters - 2, -1):
        if left[i] < 0:
            expected[i] = 1.3 * (tree["node_end"][i] - tree["node_begin"][i])
        else:
            ratio = (lambda c: area[c] / area[i]) if area[i] > 0 else (lambda c: 1.0)
            expected[i] = 2 * 0.7 + expected[left[i]] * ratio(left[i]) + expected[right[i]] * ratio(right[i])
    below = np.arange(2 * num_clusters - 1, len(left))
    assert (left[below] < 0).sum() > 100
    np.testing.assert_allclose(cost[below], expected[below], rtol=1e-9)


# ----------------------------------------------------------------- pinned by the mutation audit
def median_reference(lo, hi, max_leaf_size):
    """Every node of the object-median tree as a frozenset: the longest centroid extent (ties to
    the lower axis), items in centroid order (ties by index), the first size // 2 go left."""
    cent = np.float32(0.5) * (lo + hi)
    nodes = []

    def rec(ids):
        nodes.append(frozenset(ids))
        if len(ids) <= max_leaf_size:
            return
        extent = [cent[ids, a].max() - cent[ids, a].min() for a in range(3)]
        axis = int(np.argmax(extent))
        ordered = sorted(ids, key=lambda i: (cent[i, axis], i))
        rec(ordered[: len(ids) // 2])
        rec(ordered[len(ids) // 2:])

    rec(list(range(len(lo))))
    return sorted(nodes, key=sorted)


def _node_sets(tree):
    order, begin, end = tree["prim_order"], tree["node_begin"], tree["node_end"]
    return sorted((frozenset(order[b:e].tolist()) for b, e in zip(begin, end)), key=sorted)


@pytest.mark.parametrize("emission", ["treelets", "depth_first"])
@pytest.mark.parametrize("leaf", [1, 3])
def test_median_equals_the_numpy_median_split(device, rng, emission, leaf):
    n = 101  # odd sizes all the way down: the middle position is pinned
    lo = (rng.random((n, 3)) * [1.0, 7.0, 3.0]).astype(np.float32)
    hi = lo + (rng.random((n, 3)) * 0.3).astype(np.float32)
    cfg = hw.BuildConfig(max_leaf_size=leaf, emission=emission)
    tree = hw.build_from_bounds(lo, hi, method="median", device=device, config=cfg).to_numpy()
    assert _node_sets(tree) == median_reference(lo, hi, leaf)


@pytest.mark.parametrize("shape", [(4, 4, 4), (2, 5, 5), (3, 1, 3)])
def test_median_ties_on_a_lattice_go_to_the_lower_axis(device, shape):
    # Equal centroid extents on several axes at once, down the whole tree.
    lo, hi = _lattice_boxes(shape)
    tree = hw.build_from_bounds(lo, hi, method="median", device=device).to_numpy()
    assert _node_sets(tree) == median_reference(lo, hi, 1)


@pytest.mark.parametrize("emission", ["treelets", "depth_first"])
@pytest.mark.parametrize("shape", [(7, 1, 1), (3, 3, 1), (5, 2, 1)])
def test_sweep_sah_ties_on_a_lattice_equal_the_exhaustive_greedy(device, shape, emission):
    # Equal, evenly spaced boxes: many split positions tie exactly in cost, and the mirror
    # positions k and n - k tie in balance too; the first most balanced one must win.
    lo, hi = _lattice_boxes(shape)
    tree = hw.build_from_bounds(lo, hi, method="sweep_sah", device=device,
                                config=hw.BuildConfig(emission=emission)).to_numpy()
    assert _node_sets(tree) == greedy_sweep_reference(lo, hi)


@pytest.mark.parametrize("emission", ["treelets", "depth_first"])
def test_sweep_sah_prices_every_position_not_bins(device, emission):
    # 40 items in two tight clumps and a spread: more items than `sah_bins`, where pricing only
    # bin boundaries (binned SAH) would give another tree.
    rng = np.random.default_rng(7)
    lo = np.concatenate([rng.random((15, 3)) * 0.05, 5 + rng.random((15, 3)) * 0.05,
                         rng.random((10, 3)) * 5]).astype(np.float32)
    hi = lo + (rng.random((40, 3)) * 0.2).astype(np.float32)
    tree = hw.build_from_bounds(lo, hi, method="sweep_sah", device=device,
                                config=hw.BuildConfig(emission=emission, sah_bins=4)).to_numpy()
    assert _node_sets(tree) == greedy_sweep_reference(lo, hi)


def test_presort_keys_order_neighbouring_floats(device):
    # Adjacent float32 values (one unit in the last place apart), negative and positive.
    values = []
    for x in (-3.0, -1e-30, 1e-30, 2.0):
        x = np.float32(x)
        values += [np.nextafter(x, np.float32(-np.inf)), x, np.nextafter(x, np.float32(np.inf))]
    values = np.array(values, np.float32)
    perm = np.random.default_rng(0).permutation(len(values))
    lowers = np.repeat(values[perm][:, None], 3, axis=1)
    from hlbvh_warp.builders import TopDownBuilder

    builder = TopDownBuilder(len(values), device)
    box = wp.array(lowers, dtype=wp.vec3, device=device)
    builder.sort_axes(box, box)
    order = builder.order.numpy().reshape(3, -1)
    for axis in range(3):
        np.testing.assert_array_equal(order[axis], np.argsort(values[perm], kind="stable"))


def test_sah_termination_keeps_the_leaf_on_an_exact_tie(device):
    # Two touching unit squares, T1 = 0.5, T2 = 1: splitting costs 2 * 0.5 + (2 * 1 + 2 * 1) / 4
    # = 2, exactly the leaf's 1 * 2; the rule (split cost >= leaf cost) keeps the leaf.
    lo = np.array([[0, 0, 0], [1, 0, 0]], np.float32)
    hi = np.array([[1, 1, 0], [2, 1, 0]], np.float32)
    cfg = hw.BuildConfig(sah_traversal_cost=0.5, sah_intersection_cost=1.0)
    wl, wh = wp.array(lo, dtype=wp.vec3, device=device), wp.array(hi, dtype=wp.vec3, device=device)
    bvh = build_top_down(wl, wh, cfg, device, StageTimer(device, False), method="sweep_sah", terminate_leaf_size=2)
    assert _node_sets(bvh.to_numpy()) == greedy_sweep_reference(lo, hi, 0.5, 1.0) == [frozenset({0, 1})]
    # A hair cheaper to split (T1 just below 0.5) and it splits.
    cfg = hw.BuildConfig(sah_traversal_cost=0.499, sah_intersection_cost=1.0)
    bvh = build_top_down(wl, wh, cfg, device, StageTimer(device, False), method="sweep_sah", terminate_leaf_size=2)
    assert bvh.num_nodes == 3


@pytest.mark.parametrize("threads", [1, 2])
def test_sah_termination_on_many_items_and_threads(device, threads):
    # Above the size where CPU subtrees run side by side (builders.PARALLEL_MIN_ITEMS): leaves of
    # several items make node ids unknowable in advance, so the build must stay in one thread.
    from hlbvh_warp.builders import PARALLEL_MIN_ITEMS

    v, f = random_soup(np.random.default_rng(9), PARALLEL_MIN_ITEMS + 904)
    lo, hi = v[f].min(1), v[f].max(1)
    cfg = hw.BuildConfig(max_leaf_size=1, cpu_threads=threads)
    wl, wh = wp.array(lo, dtype=wp.vec3, device=device), wp.array(hi, dtype=wp.vec3, device=device)
    bvh = build_top_down(wl, wh, cfg, device, StageTimer(device, False), method="sweep_sah", terminate_leaf_size=8)
    tree = bvh.to_numpy()
    check_tree_invariants(tree, len(f), 8)
    sizes = tree["node_end"] - tree["node_begin"]
    assert (sizes[tree["node_left"] < 0] > 1).any()  # the rule kept some leaves of several
    # The same tree whatever the thread count (the termination makes it one thread's work).
    one = build_top_down(wl, wh, hw.BuildConfig(max_leaf_size=1, cpu_threads=1), device, StageTimer(device, False),
                         method="sweep_sah", terminate_leaf_size=8)
    assert _node_sets(tree) == _node_sets(one.to_numpy())


@pytest.mark.parametrize("t1", [0.3, 1.0])
@pytest.mark.parametrize("seed", range(3))
def test_sah_termination_equals_the_greedy_rule(device, seed, t1):
    rng = np.random.default_rng(50 + seed)
    n = 12
    lo = (rng.random((n, 3)) * 4).astype(np.float32)
    hi = lo + (rng.random((n, 3)) * 3).astype(np.float32)
    cfg = hw.BuildConfig(sah_traversal_cost=t1, sah_intersection_cost=1.0)
    wl, wh = wp.array(lo, dtype=wp.vec3, device=device), wp.array(hi, dtype=wp.vec3, device=device)
    bvh = build_top_down(wl, wh, cfg, device, StageTimer(device, False), method="sweep_sah", terminate_leaf_size=n)
    expected = greedy_sweep_reference(lo, hi, t1, 1.0)
    assert _node_sets(bvh.to_numpy()) == expected
    if t1 == 1.0:  # the rule keeps some node of several items a leaf
        assert any(len(node) > 1 and not any(other < node for other in expected) for node in expected)


@pytest.mark.parametrize("method", ["sweep_sah", "median"])
def test_large_top_down_builds_with_larger_leaves(device, rng, method):
    # Above PARALLEL_MIN_ITEMS the CPU builds disjoint subtrees side by side, which needs the
    # node count of each in advance: exact only with one item per leaf. Larger leaves must still
    # give a valid tree with exactly the primitives' leaves.
    v, f = random_soup(rng, 5000)
    bvh = hw.build(v, f, method=method, device=device, config=hw.BuildConfig(max_leaf_size=4))
    check_tree_invariants(bvh.to_numpy(), 5000, 4)


def test_hlbvh_sah_top_tree_weighs_clusters_by_their_cost(device):
    """Section 3.3 of Pantaleoni & Luebke: the top levels are a SAH sweep over the clusters with
    each cluster weighted by its subtree's SAH cost, not counted as one item. Clusters (the
    voxels of coarse_bits = 1) recomputed in NumPy, their costs by recursion over the built
    subtrees, the weighted greedy sweep in float64: its nodes must be the tree's top nodes."""
    rng = np.random.default_rng(11)
    n = 600
    centers = rng.random((n, 3)) ** 3  # crowded towards one corner: clusters of very unequal cost
    v = (centers[:, None, :] + 0.02 * rng.random((n, 3, 3))).reshape(-1, 3).astype(np.float32)
    f = np.arange(3 * n, dtype=np.int32).reshape(n, 3)
    bvh = hw.build(v, f, method="hlbvh_sah", device=device, config=hw.BuildConfig(coarse_bits=1))
    tree = bvh.to_numpy()
    tri = v[f]
    plo, phi = tri.min(1), tri.max(1)
    c = (np.float32(0.5) * (plo + phi)).astype(np.float64)
    lo, hi = c.min(0), c.max(0)
    q = np.clip(np.floor((c - lo) / (hi - lo) * 1024), 0, 1023).astype(np.int64) >> 9
    voxel = q[:, 0] * 4 + q[:, 1] * 2 + q[:, 2]
    clusters = [np.nonzero(voxel == k)[0] for k in np.unique(voxel)]
    assert len(clusters) >= 6
    order, begin, end, left, right = (tree[k] for k in ("prim_order", "node_begin", "node_end", "node_left",
                                                         "node_right"))
    node_of = {frozenset(order[b:e].tolist()): i for i, (b, e) in enumerate(zip(begin, end))}

    def cost(node):
        if left[node] < 0:
            return float(end[node] - begin[node])
        ids = order[begin[node]:end[node]]
        parent = area64(plo[ids].min(0), phi[ids].max(0))
        total = 2.0
        for child in (left[node], right[node]):
            kids = order[begin[child]:end[child]]
            total += cost(child) * area64(plo[kids].min(0), phi[kids].max(0)) / parent
        return total

    c_lo = np.array([plo[ids].min(0) for ids in clusters])
    c_hi = np.array([phi[ids].max(0) for ids in clusters])
    weight = np.array([cost(node_of[frozenset(ids.tolist())]) for ids in clusters])
    cent = np.float32(0.5) * (c_lo + c_hi)
    expected = []

    def rec(items):
        expected.append(frozenset(np.concatenate([clusters[i] for i in items]).tolist()))
        if len(items) == 1:
            return
        best = None
        for axis in range(3):
            ordered = sorted(items, key=lambda i: (cent[i, axis], i))
            for k in range(1, len(ordered)):
                a, b = ordered[:k], ordered[k:]
                price = (area64(c_lo[a].min(0), c_hi[a].max(0)) * weight[a].sum()
                         + area64(c_lo[b].min(0), c_hi[b].max(0)) * weight[b].sum())
                if best is None or price < best[0]:
                    best = (price, a, b)
        rec(best[1])
        rec(best[2])

    rec(list(range(len(clusters))))
    assert all(node in node_of for node in expected)
