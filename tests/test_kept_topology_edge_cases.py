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

from oracles import check_tree_invariants, morton_reference, numpy_node_boxes

TOPOLOGY = ("node_left", "node_right", "node_begin", "node_end")
ALL = TOPOLOGY + ("node_parent", "prim_order", "node_lowers", "node_uppers", "prim_lowers", "prim_uppers")


def numpy_boxes(vertices, faces):
    corners = np.asarray(vertices, dtype=np.float64)[faces]
    return corners.min(axis=1), corners.max(axis=1)


def numpy_sah(tree: dict, t1: float = 1.0, t2: float = 1.0) -> float:
    lo = tree["node_lowers"].astype(np.float64)
    hi = tree["node_uppers"].astype(np.float64)
    d = np.maximum(hi - lo, 0.0)
    area = 2.0 * (d[:, 0] * d[:, 1] + d[:, 1] * d[:, 2] + d[:, 2] * d[:, 0])
    leaf = tree["node_left"] < 0
    cost = np.where(leaf, t2 * (tree["node_end"] - tree["node_begin"]), 2.0 * t1)
    return float((cost * area).sum() / area[0])


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
