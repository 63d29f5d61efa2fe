"""Kept topology and the refit's sweep side by side, pushed at their edges.

A resorted ``hlbvh`` `Builder` frame whose gathered Morton codes all equal the last tree's keeps
that tree's topology and recomputes only its boxes (`Builder._keep_topology`); a tree whose
emission ran its seeds in runs side by side is refit run by run, then the nodes above
(`Builder._sweep_boxes`). Both claim to change nothing but the time a frame takes, so every
check here compares with a second builder that has the feature off (``keeps_topology = False``,
``pipeline.sweep_parts = None``), with a build from scratch (``resort=False``), with float64 NumPy
node boxes and with NumPy's SAH: a mesh's first build (no last tree: the codes buffer is
uninitialized memory), a second mesh set up on the same builder, frames collapsed to a point or
flattened, triangles with equal codes trading places, refits priced by ``auto`` on 1 to 8 threads
just below and above the size from which the emission runs side by side.
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from hlbvh_warp.builder import Builder
from hlbvh_warp.config import BuildConfig
from hlbvh_warp.hlbvh import PARALLEL_MIN_PRIMS
from hlbvh_warp.scenes import default_scene

from oracles import check_tree_invariants, morton_reference, numpy_node_boxes, numpy_sah

TOPOLOGY = ("node_left", "node_right", "node_begin", "node_end")
ALL = TOPOLOGY + ("node_parent", "prim_order", "node_lowers", "node_uppers", "prim_lowers", "prim_uppers")


def numpy_boxes(vertices, faces):
    corners = np.asarray(vertices, dtype=np.float64)[faces]
    return corners.min(axis=1), corners.max(axis=1)


def soup(num_tris: int):
    """The default scene as a triangle soup (every face its own three vertices), so that two
    triangles can trade places by trading vertices."""
    v, f = default_scene(num_tris)
    f = f[:num_tris] if len(f) >= num_tris else f
    verts = np.asarray(v, dtype=np.float32)[f].reshape(-1, 3)
    return verts, np.arange(verts.shape[0], dtype=np.int32).reshape(-1, 3)


def check_boxes(tree: dict, vertices, faces):
    lo, hi = numpy_boxes(vertices, faces)
    np.testing.assert_array_equal(tree["prim_lowers"], lo.astype(np.float32))
    node_lo, node_hi = numpy_node_boxes(tree, lo, hi)
    np.testing.assert_array_equal(tree["node_lowers"], node_lo.astype(np.float32))
    np.testing.assert_array_equal(tree["node_uppers"], node_hi.astype(np.float32))


def scratch_topology(vertices, faces, config, device):
    return Builder(len(faces), config, device=device, resort=False).build(vertices, faces).to_numpy()


def test_a_meshs_first_build_keeps_no_topology(device):
    """The first build has no last tree: its codes buffer is uninitialized (a recycled block, or
    fresh zeroed pages), and a mesh collapsed to one point has every code 0. Before the fix a
    200k-triangle such mesh, built first in a fresh process, "kept" the zeroed node arrays: a
    tree of 0 nodes. Here the zeroed buffers are written explicitly, as fresh pages hold them."""
    n = 3000
    verts = np.ones((3 * n, 3), dtype=np.float32)
    faces = np.arange(3 * n, dtype=np.int32).reshape(n, 3)
    builder = Builder(n, device=device)
    pipe = builder.pipeline
    for name in ("sorted_codes", "node_count", "node_left", "node_right", "node_begin", "node_end"):
        getattr(pipe, name).zero_()
    tree = builder.build(verts, faces).to_numpy()
    assert not builder.last_report.get("kept_topology", False), builder.last_report
    assert builder.bvh.num_nodes == 2 * n - 1
    ref = scratch_topology(verts, faces, BuildConfig(), device)
    for name in TOPOLOGY:
        np.testing.assert_array_equal(tree[name], ref[name], err_msg=name)
    check_tree_invariants(tree, n)
    # The next frame, at rest, has a last tree: it keeps it (the CPU's host-read path).
    tree = builder.rebuild(verts).to_numpy()
    if builder.keeps_topology:
        assert builder.last_report["kept_topology"]
    for name in TOPOLOGY:
        np.testing.assert_array_equal(tree[name], ref[name], err_msg=name)


@pytest.mark.parametrize("threads", [1, 2])
def test_a_second_mesh_then_the_first_meshs_vertices(device, threads):
    """`build` with a second mesh of the same triangle count (its faces in another order), then
    frames over the first mesh's vertices and back: every tree is the one from scratch."""
    v, f = soup(PARALLEL_MIN_PRIMS + 100)
    n = len(f)
    rng = np.random.default_rng(5)
    perm = rng.permutation(n)
    f2 = f[perm]
    config = BuildConfig(cpu_threads=threads, global_sort_runs=1.0)
    builder = Builder(n, config, device=device, timings=True)
    builder.build(v, f)
    builder.rebuild(v)
    first_kept = builder.last_report.get("kept_topology")
    # The second mesh: its faces in a shuffled order, the same vertices moved a little.
    v2 = (v + np.float32(0.01) * rng.standard_normal(v.shape).astype(np.float32)).astype(np.float32)
    for vertices, faces, call in [(v2, f2, "build"), (v2, None, "rebuild"), (v, None, "rebuild"),
                                  (v, None, "rebuild"), (v2, None, "refit"), (v, None, "rebuild")]:
        if call == "build":
            tree = builder.build(vertices, faces).to_numpy()
            mesh_faces = faces
        else:
            tree = getattr(builder, call)(vertices).to_numpy()
        check_boxes(tree, vertices, mesh_faces)
        if call != "refit":
            ref = scratch_topology(vertices, mesh_faces, config, device)
            for name in TOPOLOGY:
                np.testing.assert_array_equal(tree[name], ref[name], err_msg=f"{call} {name}")
    if builder.keeps_topology:
        assert first_kept is True


def _frames(v):
    """Frames that reach the comparison in every way: at rest, scaled (same codes), bent (new
    codes), collapsed to a point twice (every code 0, twice), flattened twice, at rest again."""
    c = v.mean(axis=0)
    bent = v.copy()
    bent[:, 1] += np.float32(0.3) * (v[:, 0] - c[0]) ** 2
    flat = v.copy()
    flat[:, 2] = 0.0
    return [("rest", v), ("scaled", np.float32(2.0) * v), ("bent", bent.astype(np.float32)),
            ("point", np.zeros_like(v) + np.float32(3.0)), ("point2", np.zeros_like(v) - np.float32(1.0)),
            ("flat", flat), ("flat2", np.float32(4.0) * flat), ("rest", v)]


def _trade_equal_codes(builder, v):
    """Two triangles with equal codes, adjacent in the tree's order, trade vertices: every
    gathered code stays the last tree's, while the boxes at those positions change."""
    order = builder.bvh.prim_order.numpy()
    lo, hi = builder.bvh.prim_lowers.numpy(), builder.bvh.prim_uppers.numpy()
    codes = morton_reference(lo, hi, builder.config.bits_per_axis)[order]
    same = np.flatnonzero((codes[1:] == codes[:-1]))
    for i in same:
        a, b = order[i], order[i + 1]
        if not np.array_equal(v[3 * a:3 * a + 3], v[3 * b:3 * b + 3]):
            out = v.copy()
            out[3 * a:3 * a + 3], out[3 * b:3 * b + 3] = v[3 * b:3 * b + 3], v[3 * a:3 * a + 3]
            return out
    return None


@pytest.mark.parametrize("num_tris,threads,policy", [(3000, 1, "rebuild"), (PARALLEL_MIN_PRIMS + 400, 2, "rebuild"),
                                                     (PARALLEL_MIN_PRIMS + 400, 3, "auto")])
def test_kept_frames_equal_a_builder_that_never_keeps(device, num_tris, threads, policy):
    """The same frames through a builder that keeps topology and one that never does: every
    array identical (the order within equal codes included), the boxes NumPy's, the topology
    a build from scratch's, and `kept_topology` true exactly when the codes (NumPy's) are the
    last tree's."""
    v, f = soup(num_tris)
    config = BuildConfig(cpu_threads=threads, global_sort_runs=1.0)
    keep = Builder(len(f), config, device=device, policy=policy, timings=True)
    never = Builder(len(f), config, device=device, policy=policy)
    never.keeps_topology = False
    keep.build(v, f)
    never.build(v, f)
    frames = _frames(v)
    kept_any = []
    last_codes = morton_reference(*numpy_boxes(v, f), config.bits_per_axis)
    step = 0
    while frames:
        name, vertices = frames.pop(0)
        last_order = keep.bvh.prim_order.numpy().copy()
        keep.rebuild(vertices)
        never.rebuild(vertices)
        report = keep.last_report
        a, b = keep.bvh.to_numpy(), never.bvh.to_numpy()
        for field in ALL:
            np.testing.assert_array_equal(a[field], b[field], err_msg=f"{name} {field}")
        check_boxes(a, vertices, f)
        ref = scratch_topology(vertices, f, config, device)
        for field in TOPOLOGY:
            np.testing.assert_array_equal(a[field], ref[field], err_msg=f"{name} {field}")
        lo, hi = numpy_boxes(vertices, f)
        codes = morton_reference(lo.astype(np.float32), hi.astype(np.float32), config.bits_per_axis)
        if keep.keeps_topology:
            same = bool(np.array_equal(codes[last_order], last_codes[last_order]))
            assert report.get("kept_topology", False) == same, (name, report)
            if report.get("kept_topology"):
                assert "hierarchy" in report["stages_skipped"] and "hierarchy" not in report["stages_ms"]
                kept_any.append(name)
            else:
                assert "hierarchy" in report["stages_ms"], (name, report)
        last_codes = codes
        if name == "rest" and step == 0:
            traded = _trade_equal_codes(keep, vertices)
            if traded is not None:
                frames.insert(0, ("traded", traded))
        # A refit, then an update, in between: neither changes the last tree's codes.
        keep.refit(vertices)
        never.refit(vertices)
        keep.update(vertices)
        never.update(vertices)
        step += 1
    if keep.keeps_topology:
        assert {"scaled", "point2", "flat2", "traded"} <= set(kept_any), kept_any


@pytest.mark.parametrize("method,num_tris,threads", [
    *[("hlbvh", n, t) for n in (PARALLEL_MIN_PRIMS - 1, PARALLEL_MIN_PRIMS, PARALLEL_MIN_PRIMS + 1, 12000)
      for t in (2, 3, 8)],
    # hlbvh_sah's emission runs its clusters' treelets side by side under its cluster tree.
    *[("hlbvh_sah", n, t) for n in (PARALLEL_MIN_PRIMS, 12000) for t in (2, 3)],
])
def test_the_sweep_side_by_side_equals_the_one_sweep(device, method, num_tris, threads):
    """auto's priced refits, forced refits and kept frames of a tree whose emission ran side by
    side against a builder whose every sweep is the one serial sweep: equal boxes (NumPy's),
    equal SAH (NumPy's), equal decisions."""
    v, f = soup(num_tris)
    n = len(f)
    config = BuildConfig(cpu_threads=threads)
    side = Builder(n, config, device=device, method=method, policy="auto")
    one = Builder(n, config, device=device, method=method, policy="auto")
    side.build(v, f)
    one.build(v, f)
    parallel = wp.get_device(device).is_cpu and n >= PARALLEL_MIN_PRIMS
    assert (side.pipeline.sweep_parts is not None) == parallel, side.pipeline.sweep_parts
    rng = np.random.default_rng(threads * 100003 + n)
    c = v.mean(axis=0)
    frames = []
    for k in range(1, 5):
        moved = v.copy()
        moved[:, 1] += np.float32(0.002 * k) * (v[:, 0] - c[0]) ** 2
        frames.append(("update", moved.astype(np.float32)))
    frames += [("refit", (v + np.float32(0.001) * rng.standard_normal(v.shape)).astype(np.float32)),
               ("rebuild", np.float32(2.0) * v), ("update", np.float32(2.0) * v + np.float32(0.01)),
               ("refit", np.float32(0.5) * v)]
    for call, vertices in frames:
        one.pipeline.sweep_parts = None
        getattr(side, call)(vertices)
        getattr(one, call)(vertices)
        a, b = side.bvh.to_numpy(), one.bvh.to_numpy()
        for field in ALL:
            np.testing.assert_array_equal(a[field], b[field], err_msg=f"{call} {field}")
        check_boxes(a, vertices, f)
        ra, rb = side.last_report, one.last_report
        assert ra["decision"] == rb["decision"], (ra, rb)
        if "sah_refit" in ra:
            assert ra["sah_refit"] == pytest.approx(rb["sah_refit"], rel=1e-12)
            if ra["decision"] == "refit":
                assert ra["sah_refit"] == pytest.approx(numpy_sah(a), rel=1e-9)
        # A rebuild (or a kept frame) leaves the parts of its own emission.
        assert (side.pipeline.sweep_parts is not None) == parallel


@pytest.mark.parametrize("method", ["lbvh", "hlbvh_sah"])
def test_other_methods_keep_no_topology_and_sweep_their_own_way(device, method):
    """lbvh and hlbvh_sah frames never keep a topology; their parallel emissions (refit side by
    side on the CPU) refit to NumPy's boxes."""
    v, f = soup(PARALLEL_MIN_PRIMS + 400)
    config = BuildConfig(cpu_threads=2, global_sort_runs=1.0)
    builder = Builder(len(f), config, device=device, method=method, policy="auto")
    builder.build(v, f)
    assert not builder.keeps_topology
    assert (builder.pipeline.sweep_parts is not None) == wp.get_device(device).is_cpu
    for vertices in (v, np.float32(2.0) * v, np.float32(2.0) * v + np.float32(0.001)):
        builder.rebuild(vertices)
        assert "kept_topology" not in builder.last_report
        builder.refit(vertices)
        check_boxes(builder.bvh.to_numpy(), vertices, f)


def test_boxes_builder_keeps_topology_of_scaled_boxes(device):
    """`build_from_bounds`: boxes scaled by two keep the topology; the tree equals a builder's
    that never keeps, and the boxes NumPy's."""
    v, f = soup(PARALLEL_MIN_PRIMS + 400)
    lo, hi = (x.astype(np.float32) for x in numpy_boxes(v, f))
    config = BuildConfig(cpu_threads=2, global_sort_runs=1.0)
    keep = Builder(len(f), config, device=device)
    never = Builder(len(f), config, device=device)
    never.keeps_topology = False
    keep.build_from_bounds(lo, hi)
    never.build_from_bounds(lo, hi)
    for scale in (2.0, 4.0, 0.5):
        bounds = (np.float32(scale) * lo, np.float32(scale) * hi)
        keep.rebuild(bounds=bounds)
        never.rebuild(bounds=bounds)
        if keep.keeps_topology:
            assert keep.last_report["kept_topology"], keep.last_report
        a, b = keep.bvh.to_numpy(), never.bvh.to_numpy()
        for field in ALL:
            np.testing.assert_array_equal(a[field], b[field], err_msg=field)
        node_lo, node_hi = numpy_node_boxes(a, bounds[0].astype(np.float64), bounds[1].astype(np.float64))
        np.testing.assert_array_equal(a["node_lowers"], node_lo.astype(np.float32))
        np.testing.assert_array_equal(a["node_uppers"], node_hi.astype(np.float32))
