"""Resorted rebuilds (Pantaleoni & Luebke 2010, 2.2): what a `Bvh` exposes after one.

A resorted rebuild feeds the pipeline the primitives in the previous tree's order and maps the
tree back to the user's face indices. The per-face boxes (`Bvh.prim_lowers/prim_uppers`, read by
box queries, `to_numpy` and refits) are computed in the user's order and gathered for the build:
these tests check that they are current after every rebuild, equal to a build from scratch and to
a float64 NumPy reference, and that what the skips of the top-level sort rely on is detected.
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import hlbvh_warp as hw
from hlbvh_warp import query
from hlbvh_warp.builder import Builder
from hlbvh_warp.config import BuildConfig
from hlbvh_warp.dynamic import BendingMesh, ExplodingMesh
from hlbvh_warp.kernels import compress
from hlbvh_warp.scenes import default_scene

from oracles import brute_overlaps, check_tree_invariants, morton_reference, numpy_node_boxes, numpy_sah

TOPOLOGY = ("node_left", "node_right", "node_begin", "node_end")


@pytest.fixture(scope="module")
def small_scene():
    return default_scene(3000)


def numpy_boxes(vertices: np.ndarray, faces: np.ndarray):
    """Per-face boxes in float64 (min and max are exact, so float32 results must equal them)."""
    corners = vertices.astype(np.float64)[faces]
    return corners.min(axis=1), corners.max(axis=1)


def make_scene(kind, v, f, device):
    if kind == "explode":
        return ExplodingMesh(v, f, device=device, seed=2), (lambda k: k / 24.0)
    return BendingMesh(v, f, device=device), (lambda k: k / 6.0)


@wp.kernel
def _aabb_count_kernel(bvh: query.BvhView, lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3),
                       counts: wp.array(dtype=wp.int32)):
    tid = wp.tid()
    counts[tid] = query.bvh_aabb_count(bvh, lowers[tid], uppers[tid])


@pytest.mark.parametrize("method,kind", [("hlbvh", "explode"), ("hlbvh", "bend"), ("hlbvh_sah", "explode")])
def test_resorted_prim_boxes_are_current_after_every_rebuild(device, small_scene, method, kind):
    """Per-face boxes, node boxes and the tree equal a scratch build's and the float64 reference."""
    v, f = small_scene
    mesh, param = make_scene(kind, v, f, device)
    faces = np.asarray(mesh.faces)
    scratch = Builder(len(f), device=device, method=method, resort=False)
    resorted = Builder(len(f), device=device, method=method, resort=True)
    scratch.build(mesh.vertices, faces)
    resorted.build(mesh.vertices, faces)
    for frame in range(1, 5):
        vertices = mesh.update(param(frame))
        a = scratch.rebuild(vertices).to_numpy()
        b = resorted.rebuild(vertices).to_numpy()
        ref_lo, ref_hi = numpy_boxes(vertices.numpy(), faces)
        # Indexed by the user's face id, and exact: the boxes are min/max of the same floats.
        np.testing.assert_array_equal(b["prim_lowers"], ref_lo.astype(np.float32))
        np.testing.assert_array_equal(b["prim_uppers"], ref_hi.astype(np.float32))
        np.testing.assert_array_equal(b["prim_lowers"], a["prim_lowers"])
        np.testing.assert_array_equal(b["prim_uppers"], a["prim_uppers"])
        for name in TOPOLOGY:
            np.testing.assert_array_equal(a[name], b[name], err_msg=name)
        # prim_order names user faces: a permutation whose node boxes are the float64 unions.
        assert np.array_equal(np.sort(b["prim_order"]), np.arange(len(f)))
        node_lo, node_hi = numpy_node_boxes(b, ref_lo, ref_hi)
        np.testing.assert_array_equal(b["node_lowers"], node_lo.astype(np.float32))
        np.testing.assert_array_equal(b["node_uppers"], node_hi.astype(np.float32))
        check_tree_invariants(b, len(f))


def test_resorted_aabb_queries_match_scratch_and_numpy(device, small_scene, rng):
    """Box queries (batched and from a view taken before the rebuilds) read the current boxes."""
    v, f = small_scene
    mesh, param = make_scene("explode", v, f, device)
    faces = np.asarray(mesh.faces)
    scratch = Builder(len(f), device=device, resort=False)
    resorted = Builder(len(f), device=device, resort=True)
    scratch.build(mesh.vertices, faces)
    resorted.build(mesh.vertices, faces)
    # A user kernel's view, taken once: views handed out stay valid across rebuilds.
    view = query.view(resorted.bvh)
    for frame in range(1, 4):
        vertices = mesh.update(param(frame))
        scratch.rebuild(vertices)
        resorted.rebuild(vertices)
        verts = vertices.numpy()
        ref_lo, ref_hi = numpy_boxes(verts, faces)
        q_lo = (verts[rng.integers(0, len(verts), 200)] - 0.03).astype(np.float32)
        q_hi = q_lo + np.float32(0.06)
        counts, pairs = query.query_aabb(resorted.bvh, q_lo, q_hi, return_pairs=True)
        ref = brute_overlaps(ref_lo.astype(np.float32), ref_hi.astype(np.float32), q_lo, q_hi)
        assert counts.sum() > 0
        np.testing.assert_array_equal(counts, ref.sum(1))
        np.testing.assert_array_equal(pairs, np.argwhere(ref))
        s_counts, s_pairs = query.query_aabb(scratch.bvh, q_lo, q_hi, return_pairs=True)
        np.testing.assert_array_equal(counts, s_counts)
        np.testing.assert_array_equal(pairs, s_pairs)
        user = wp.zeros(len(q_lo), dtype=wp.int32, device=device)
        wp.launch(_aabb_count_kernel, dim=len(q_lo), device=device,
                  inputs=[view, wp.array(q_lo, dtype=wp.vec3, device=device),
                          wp.array(q_hi, dtype=wp.vec3, device=device), user])
        np.testing.assert_array_equal(user.numpy(), counts)


def test_refit_after_resorted_rebuilds(device, small_scene):
    """A refit keeps the resorted tree's topology and matches the float64 unions of the new boxes."""
    v, f = small_scene
    mesh, param = make_scene("bend", v, f, device)
    faces = np.asarray(mesh.faces)
    builder = Builder(len(f), device=device, resort=True)
    builder.build(mesh.vertices, faces)
    for frame in range(1, 3):
        builder.rebuild(mesh.update(param(frame)))
    before = {k: a.copy() for k, a in builder.bvh.to_numpy().items()}
    vertices = mesh.update(param(3))
    tree = builder.refit(vertices).to_numpy()
    for name in TOPOLOGY + ("prim_order",):
        np.testing.assert_array_equal(tree[name], before[name], err_msg=name)
    ref_lo, ref_hi = numpy_boxes(vertices.numpy(), faces)
    np.testing.assert_array_equal(tree["prim_lowers"], ref_lo.astype(np.float32))
    node_lo, node_hi = numpy_node_boxes(tree, ref_lo, ref_hi)
    np.testing.assert_array_equal(tree["node_lowers"], node_lo.astype(np.float32))
    np.testing.assert_array_equal(tree["node_uppers"], node_hi.astype(np.float32))
    # The next resorted rebuild starts from the refit tree's order and still equals scratch.
    tree = builder.rebuild(mesh.update(param(4))).to_numpy()
    scratch = Builder(len(f), device=device, resort=False)
    ref = scratch.build(mesh.vertices, faces).to_numpy()
    for name in TOPOLOGY:
        np.testing.assert_array_equal(tree[name], ref[name], err_msg=name)


@pytest.mark.parametrize("max_leaf_size", [1, 4])
def test_a_frame_with_the_last_trees_codes_keeps_its_topology(device, small_scene, max_leaf_size):
    """A resorted frame whose Morton codes all equal the last tree's keeps its topology and
    recomputes only the boxes: the same tree as from scratch, every box current. The codes are
    judged here by the float64 NumPy reference: at rest and scaled by two (exact in float32, the
    grid scales with the scene) they are the last tree's; bent, they are not, and the frame
    takes the whole build."""
    v, f = small_scene
    # The paper's sort for every build: every resorted frame is fed the previous tree's order, so
    # the frames whose codes changed are compared too (with the sampled choice, the bent frames
    # would take the faces' order and never reach the comparison).
    config = BuildConfig(max_leaf_size=max_leaf_size, global_sort_runs=1.0)
    scratch = Builder(len(f), config, device=device, resort=False)
    resorted = Builder(len(f), config, device=device, resort=True, timings=True)
    scratch.build(v, f)
    resorted.build(v, f)
    bent = BendingMesh(v, f, device=device).update(0.3).numpy()
    kept = []
    last_codes = morton_reference(*(b.astype(np.float32) for b in numpy_boxes(v, f)), config.bits_per_axis)
    for vertices in (v, 2.0 * v, bent, bent, v):
        vertices = np.asarray(vertices, dtype=np.float32)
        a = scratch.rebuild(vertices).to_numpy()
        b = resorted.rebuild(vertices).to_numpy()
        report = resorted.last_report
        ref_lo, ref_hi = numpy_boxes(vertices, f)
        codes = morton_reference(ref_lo.astype(np.float32), ref_hi.astype(np.float32), config.bits_per_axis)
        same = bool(np.array_equal(codes, last_codes))
        kept.append(report.get("kept_topology", False))
        assert report["input_order"] == "previous tree"
        assert kept[-1] == same, (len(kept), report)
        if same:
            assert "hierarchy" in report["stages_skipped"] and "hierarchy" not in report["stages_ms"]
        last_codes = codes
        for name in TOPOLOGY:
            np.testing.assert_array_equal(b[name], a[name], err_msg=name)
        np.testing.assert_array_equal(b["prim_lowers"], ref_lo.astype(np.float32))
        node_lo, node_hi = numpy_node_boxes(b, ref_lo, ref_hi)
        np.testing.assert_array_equal(b["node_lowers"], node_lo.astype(np.float32))
        np.testing.assert_array_equal(b["node_uppers"], node_hi.astype(np.float32))
        check_tree_invariants(b, len(f), max_leaf_size)
    # At rest, scaled, bent, bent again, back at rest: the two bent frames share their codes too.
    assert kept == [True, True, False, True, False]
    # hlbvh_sah's cluster tree prices the boxes: its topology is never kept.
    sah = Builder(len(f), device=device, method="hlbvh_sah")
    sah.build(v, f)
    sah.rebuild(v)
    assert "kept_topology" not in sah.last_report


def test_resorted_input_is_the_previous_tree_order(small_scene):
    """The build's input order is the previous tree's, and with nothing moved the sorts are skipped."""
    v, f = small_scene
    mesh, param = make_scene("bend", v, f, "cpu")
    # The paper's sort for every build: this small scene has about one run per face.
    paper = BuildConfig(global_sort_runs=1.0)
    builder = Builder(len(f), paper, device="cpu", resort=True, timings=True)
    builder.build(mesh.vertices, mesh.faces)
    previous = builder.bvh.prim_order.numpy().copy()
    builder.rebuild(mesh.update(param(1)))
    np.testing.assert_array_equal(builder.input_order.numpy(), previous)
    # With the paper's sort for every build nothing needs sampling: it always resorts.
    assert builder.last_report["input_order"] == "previous tree"
    assert builder.last_report["sampled_run_fraction"] is None
    assert "resort_check" not in builder.last_report["stages_ms"]
    # The same vertices again: the input is the sorted order, so the runs ascend and every block
    # is in order (Pantaleoni & Luebke 2010, 2.2: the resorted input is already sorted).
    builder.rebuild()
    skipped = builder.last_report["stages_skipped"]
    assert "top_level_sort" in skipped and "voxel_sort" in skipped, skipped
    assert "resort_gather" in builder.last_report["stages_ms"]
    # A build from scratch over the mesh's own face order has to sort.
    scratch = Builder(len(f), paper, device="cpu", resort=False, timings=True)
    scratch.build(mesh.vertices, mesh.faces)
    assert "top_level_sort" not in scratch.last_report["stages_skipped"]
    assert "global_sort" not in scratch.last_report["stages_ms"]


@pytest.mark.parametrize("case", ["sorted", "one_descent_last", "random", "stale_tail", "single"])
def test_descent_checks_agree_with_numpy(device, rng, case):
    """Both forms of the top-level sort's check (one scan on the CPU, a parallel flag elsewhere)."""
    n = 5000
    codes = np.sort(rng.integers(0, 1 << 18, n)).astype(np.int32)
    count = n
    if case == "one_descent_last":
        codes[-1] = codes[-2] - 1
    elif case == "random":
        rng.shuffle(codes)
    elif case == "stale_tail":
        # Entries past the device-side run count are stale and must be ignored.
        count = n // 2
        codes[count:] = 0
    elif case == "single":
        count = 1
    expected = bool((codes[1:count] < codes[: count - 1]).any())
    run_codes = wp.array(codes, dtype=wp.int32, device=device)
    run_count = wp.array([count], dtype=wp.int32, device=device)
    found = wp.full(1, 7, dtype=wp.int32, device=device)
    wp.launch(compress.find_descent_kernel, dim=1, inputs=[run_count, run_codes, found], device=device)
    flagged = wp.zeros(1, dtype=wp.int32, device=device)
    wp.launch(compress.flag_descents_kernel, dim=n, inputs=[run_count, run_codes, flagged], device=device)
    assert int(found.numpy()[0]) == int(expected)
    assert int(flagged.numpy()[0]) == int(expected)


def face_codes(builder) -> np.ndarray:
    """The latest build's Morton code of every face (the pipeline keeps them in tree order)."""
    n = builder.num_prims
    codes = np.empty(n, dtype=np.int64)
    codes[builder.bvh.prim_order.numpy()] = builder.pipeline.sorted_codes.numpy()[:n]
    return codes


def numpy_run_fraction(codes: np.ndarray, order: np.ndarray, shift: int) -> float:
    """M / N of the run-length encoding of ``codes`` fed in ``order``, over every pair."""
    coarse = codes[order] >> shift
    return (1 + np.count_nonzero(coarse[1:] != coarse[:-1])) / len(order)


@pytest.mark.parametrize("kind", ["explode", "bend"])
def test_resorting_is_used_where_it_pays(device, kind):
    """A rebuild whose previous order would leave more runs than `global_sort_runs` allows takes
    one radix sort anyway, which costs the same in any order: it is fed in the faces' order and
    skips the gather. Where the runs compress it resorts. The sampled M / N is checked against
    the full count in NumPy, and the tree against a build from scratch either way."""
    v, f = default_scene(20000)
    mesh, _ = make_scene(kind, v, f, device)
    # A coarse grid of 16^3 voxels, so that the bent mesh's runs compress at this size, and a
    # limit between the two scenes' run counts (the mechanism, not the default's tuning).
    config = BuildConfig(coarse_bits=4, global_sort_runs=0.3)
    num_prims = mesh.num_tris if kind == "explode" else len(f)
    builder = Builder(num_prims, config, device=device, resort=True, timings=True)
    scratch = Builder(num_prims, config, device=device, resort=False)
    builder.build(mesh.vertices, mesh.faces)
    scratch.build(mesh.vertices, mesh.faces)
    shift = 3 * (builder.config.bits_per_axis - builder.pipeline.coarse_bits)
    # Late in the explosion the fragments are scattered; the bend keeps its neighbourhoods.
    times = [0.5, 0.75] if kind == "explode" else [0.1, 0.2]
    for t in times:
        previous = builder.bvh.prim_order.numpy().copy()
        vertices = mesh.update(t)
        builder.rebuild(vertices)
        scratch.rebuild(vertices)
        report = builder.last_report
        if builder.sync_free:
            # Sync-free CUDA builds always compress-sort-decompress, so they always resort.
            assert report["input_order"] == "previous tree" and report["sampled_run_fraction"] is None
            continue
        exact = numpy_run_fraction(face_codes(scratch), previous, shift)
        sampled = report["sampled_run_fraction"]
        assert abs(sampled - exact) < 0.1, (sampled, exact)  # 256 samples: one standard error 0.03
        pays = exact <= builder.config.global_sort_runs
        assert pays == (kind == "bend"), exact  # the scenes do what the test means them to
        if pays:
            assert report["input_order"] == "previous tree"
            assert "resort_gather" in report["stages_ms"]
            np.testing.assert_array_equal(builder.input_order.numpy(), previous)
        else:
            assert report["input_order"] == "faces"
            assert "resort_gather" in report["stages_skipped"]
            assert builder.pipeline.input_ids.shape[0] == 0  # the sort carries positions: face ids
        # The scratch build's tree either way: the same codes in tree order, so the same
        # topology (faces with equal codes may trade places), and every box the union of its
        # faces' boxes in float64.
        tree, ref = builder.bvh.to_numpy(), scratch.bvh.to_numpy()
        codes = face_codes(scratch)
        np.testing.assert_array_equal(codes[tree["prim_order"]], codes[ref["prim_order"]])
        for name in TOPOLOGY:
            np.testing.assert_array_equal(tree[name], ref[name], err_msg=name)
        check_tree_invariants(tree, builder.num_prims)
        lowers, uppers = numpy_boxes(vertices.numpy(), mesh.faces)
        node_lo, node_hi = numpy_node_boxes(tree, lowers, uppers)
        np.testing.assert_array_equal(tree["node_lowers"], node_lo.astype(np.float32))
        np.testing.assert_array_equal(tree["node_uppers"], node_hi.astype(np.float32))


def test_sorted_previous_order_is_resorted_whatever_its_runs():
    """A static frame's previous order is sorted: resorting skips every sort even when the runs
    do not compress (about one per face here), so no sampled descent keeps the gather."""
    v, f = default_scene(1000)
    builder = Builder(len(f), device="cpu", resort=True, timings=True)
    builder.build(v, f)
    builder.rebuild(v)
    report = builder.last_report
    assert report["sampled_run_fraction"] > builder.config.global_sort_runs
    assert report["input_order"] == "previous tree"
    assert "run_length_encode" in report["stages_skipped"]


@pytest.mark.parametrize("method,kind", [("lbvh", "bend"), ("hlbvh_sah", "explode")])
def test_resorting_by_method(device, method, kind, small_scene):
    """lbvh's one radix sort costs the same in any order: never resorted, even where the runs
    would compress (a bend over a coarse grid). hlbvh_sah always compresses (its clusters are
    the voxels): always resorted, even where they do not (an explosion). Trees equal scratch
    builds'."""
    v, f = small_scene
    mesh, param = make_scene(kind, v, f, device)
    # A limit the bend's runs fall under, so that only the method decides.
    config = BuildConfig(coarse_bits=3, global_sort_runs=0.3)
    num_prims = mesh.num_tris if kind == "explode" else len(f)
    builder = Builder(num_prims, config, method=method, device=device, resort=True, timings=True)
    scratch = Builder(num_prims, config, method=method, device=device, resort=False)
    builder.build(mesh.vertices, mesh.faces)
    scratch.build(mesh.vertices, mesh.faces)
    previous = builder.bvh.prim_order.numpy().copy()
    vertices = mesh.update(param(1 if kind == "bend" else 12))
    builder.rebuild(vertices)
    scratch.rebuild(vertices)
    report = builder.last_report
    if kind == "bend" and not builder.sync_free:
        # The runs of the previous order do compress: only the method decides.
        shift = 3 * (config.bits_per_axis - builder.pipeline.coarse_bits)
        assert numpy_run_fraction(face_codes(scratch), previous, shift) < config.global_sort_runs
    cuda_lbvh = method == "lbvh" and builder.sync_free
    expected = "previous tree" if method == "hlbvh_sah" or cuda_lbvh else "faces"
    assert report["input_order"] == expected
    assert ("resort_gather" in report["stages_ms"]) == (expected == "previous tree")
    tree, ref = builder.bvh.to_numpy(), scratch.bvh.to_numpy()
    for name in TOPOLOGY:
        np.testing.assert_array_equal(tree[name], ref[name], err_msg=name)


def test_resort_sample_spans_the_whole_previous_order(device, rng):
    """The sampled M / N reads pairs from every part of the previous order: one whose first half is
    in tree order and whose second half is scattered samples about half of its pairs as breaks,
    as NumPy's count over every pair says (a sample of the first half alone would read almost
    none)."""
    v, f = default_scene(20000)
    config = BuildConfig(coarse_bits=4)
    builder = Builder(len(f), config, device=device, resort=True)
    scratch = Builder(len(f), config, device=device, resort=False)
    builder.build(v, f)
    scratch.build(v, f)
    if builder.sync_free:
        pytest.skip("sync-free builds always resort and take no sample")
    order = builder.bvh.prim_order.numpy().copy()
    half = len(order) // 2
    order[half:] = rng.permutation(order[half:])
    builder.prim_order.assign(order)
    builder.rebuild(v)
    shift = 3 * (config.bits_per_axis - builder.pipeline.coarse_bits)
    codes = face_codes(scratch)
    exact = numpy_run_fraction(codes, order, shift)
    first_half = numpy_run_fraction(codes, order[:half], shift)
    assert exact - first_half > 0.3, (exact, first_half)  # the scene does what the test means
    sampled = builder.last_report["sampled_run_fraction"]
    assert abs(sampled - exact) < 0.1, (sampled, exact)  # 256 samples: one standard error 0.03


def test_the_resort_sample_reaches_the_last_pair(device):
    # With as many samples as adjacent pairs every pair is sampled, the last one included: here
    # it alone descends (codes ascend with x otherwise).
    from hlbvh_warp.kernels import dynamic as dynamic_kernels

    n = 257
    lo = np.zeros((n, 3), np.float32)
    lo[:, 0] = np.linspace(0.0, 1.0, n, dtype=np.float32)
    order = np.arange(n, dtype=np.int32)
    order[-2:] = order[-2:][::-1]
    bounds = wp.array(np.array([[0, 0, 0], [1, 1, 1]], np.float32), dtype=wp.vec3, device=device)
    breaks = wp.zeros(2, dtype=wp.int32, device=device)
    boxes = wp.array(lo, dtype=wp.vec3, device=device)
    wp.launch(dynamic_kernels.sample_run_breaks_kernel, dim=n - 1, device=device,
              inputs=[wp.array(order, device=device), boxes, boxes, bounds, 10, n, n - 1, 0, breaks])
    assert int(breaks.numpy()[1]) == 1


@pytest.mark.parametrize("method", ["hlbvh", "hlbvh_sah"])
@pytest.mark.parametrize("case", ["coarse_bits", "duplicates", "coarse_bits_two_threads", "one_bit_two_threads",
                                  "treelets", "sparse_ties"])
def test_resorted_rebuild_with_tied_codes_equals_a_fresh_build(device, method, case):
    """Primitives with equal Morton codes (few bits per axis, duplicated triangles) come out of the
    stable sort in their input order: from scratch the face order, resorted the previous tree's,
    where a primitive whose code changed joins its new neighbours in another place. Resorted frames
    of small motion must give a fresh build's tree all the same: its order, its topology and its
    SAH cost. Before, 2 bits per axis gave 0.1-6% apart."""
    rng = np.random.default_rng(7)
    # Two threads: the top of the tree is cut into seeds; with 1 bit per axis (8 codes) the
    # seeds' cuts fall inside runs of equal codes.
    v, f = default_scene(12000 if case.endswith("two_threads") else 3000)
    v, f = np.asarray(v, np.float32), np.asarray(f, np.int32)
    if case == "sparse_ties":
        # Triangles of many sizes about one per Morton cell (4 bits per axis): runs of two to
        # four equal codes, split without a search on the CPU.
        centers = rng.random((3000, 1, 3))
        v = (centers + rng.random((3000, 3, 3)) * rng.random((3000, 1, 1)) * 0.05).reshape(-1, 3).astype(np.float32)
        f = np.arange(9000, dtype=np.int32).reshape(-1, 3)
    cfg = {"coarse_bits": BuildConfig(bits_per_axis=2, cpu_threads=1),
           "coarse_bits_two_threads": BuildConfig(bits_per_axis=2, cpu_threads=2),
           "one_bit_two_threads": BuildConfig(bits_per_axis=1, cpu_threads=2),
           "treelets": BuildConfig(bits_per_axis=2, emission="treelets"),
           "sparse_ties": BuildConfig(bits_per_axis=4, global_sort_runs=1.0),
           "duplicates": BuildConfig(global_sort_runs=1.0)}[case]
    if case == "duplicates":
        f = np.concatenate([f, f[::-1], f[:500]])
    builder = Builder(len(f), cfg, device=device, method=method, resort=True)
    builder.build(v, f)
    resorted = 0
    for _ in range(4):
        v = (v + rng.normal(scale=3e-3, size=v.shape)).astype(np.float32)
        tree = builder.rebuild(v).to_numpy()
        resorted += builder.last_report["input_order"] == "previous tree"
        fresh = hw.build(v, f, method=method, config=cfg, device=device).to_numpy()
        check_tree_invariants(tree, len(f))
        for name in TOPOLOGY + ("prim_order",):
            np.testing.assert_array_equal(tree[name], fresh[name], err_msg=name)
        assert numpy_sah(tree) == pytest.approx(numpy_sah(fresh), rel=1e-9)
        lo, hi = numpy_boxes(v, f)
        node_lo, node_hi = numpy_node_boxes(tree, lo, hi)
        np.testing.assert_array_equal(tree["node_lowers"], node_lo.astype(np.float32))
        np.testing.assert_array_equal(tree["node_uppers"], node_hi.astype(np.float32))
    assert resorted >= 2, "the frames were not fed in the previous tree's order"
