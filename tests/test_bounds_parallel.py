"""The box and centroid-bounds pass on several CPU cores (`HlbvhPipeline._reduce_centroid_bounds`):
slices side by side, each into its own partial bounds, combined in order, must give the one
thread's boxes and bounds to the bit, and NumPy's values."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import hlbvh_warp as hw
from hlbvh_warp import hlbvh
from hlbvh_warp.hlbvh import HlbvhPipeline


def _scene(n: int, seed: int):
    rng = np.random.default_rng(seed)
    centers = rng.uniform(-1.0, 1.0, (n, 3))
    centers[:, 2] = rng.uniform(0.5, 1.0, n)  # z above zero: the zero centroids below are its lower bound
    vertices = (centers[:, None, :] + 0.01 * rng.standard_normal((n, 3, 3))).reshape(-1, 3).astype(np.float32)
    # Centroids of exactly +0 and -0 on the bounds' faces, in several slices: the combine must
    # keep the sign the serial reduction keeps (the first one met on a tie).
    for k, sign in zip(np.linspace(0, n - 1, 9).astype(int), [1, -1] * 5):
        vertices[3 * k : 3 * k + 3] = np.float32(sign * 0.0)
    vertices[3 * (n // 3) : 3 * (n // 3) + 3, 0] = np.float32(-2.0)  # the lower x in the second slice
    vertices[3 * (n // 3) + 1, 1] = np.nan  # a NaN vertex: its triangle's box keeps the others'
    faces = np.arange(3 * n, dtype=np.int32).reshape(-1, 3)
    return vertices, faces


def _bounds(vertices, faces, threads, device, boxes_given=False):
    n = len(faces)
    pipe = HlbvhPipeline(n, hw.BuildConfig(cpu_threads=threads), device)
    v = wp.array(vertices, dtype=wp.vec3, device=device)
    f = wp.array(faces, dtype=wp.int32, device=device)
    pipe.compute_triangle_bounds(v, f)
    if boxes_given:
        # Boxes given as such: the centroid pass alone.
        pipe.compute_centroid_bounds()
    return pipe.scene_bounds.numpy(), pipe.prim_lowers.numpy(), pipe.prim_uppers.numpy()


@pytest.mark.parametrize("offset", [-1, 0, 1, 4097])
@pytest.mark.parametrize("threads", [2, 3])
@pytest.mark.parametrize("boxes_given", [False, True])
def test_bounds_on_several_cores_equal_one_core_to_the_bit(device, offset, threads, boxes_given):
    n = hlbvh.PARALLEL_BOUNDS_MIN_PRIMS + offset
    vertices, faces = _scene(n, seed=offset + 10)
    one = _bounds(vertices, faces, 1, device, boxes_given)
    several = _bounds(vertices, faces, threads, device, boxes_given)
    for a, b in zip(one, several):
        np.testing.assert_array_equal(a.view(np.uint32), b.view(np.uint32))
    # NumPy: the boxes' centroids' min and max over the triangles, NaN coordinates left out.
    tri = vertices[faces].astype(np.float64)
    with np.errstate(invalid="ignore"):
        lo, hi = np.nanmin(tri, axis=1), np.nanmax(tri, axis=1)
    centroid = (0.5 * (lo.astype(np.float32) + hi.astype(np.float32))).astype(np.float64)
    np.testing.assert_array_equal(several[0][0], np.nanmin(centroid, axis=0).astype(np.float32))
    np.testing.assert_array_equal(several[0][1], np.nanmax(centroid, axis=0).astype(np.float32))


def test_parallel_bounds_give_the_one_thread_tree(device):
    """A whole build over the several-core bounds is the one-thread build (the codes follow the
    bounds bit for bit): the same primitive order and the same nodes, each a span of it with its
    box. (The emission numbers the nodes of its runs side by side from one counter per run, so
    the numbering itself depends on the thread count.)"""
    vertices, faces = _scene(hlbvh.PARALLEL_BOUNDS_MIN_PRIMS + 333, seed=3)
    vertices = np.nan_to_num(vertices)
    trees = [hw.build(vertices, faces, device=device, config=hw.BuildConfig(cpu_threads=t)).to_numpy()
             for t in (1, 2)]
    np.testing.assert_array_equal(trees[0]["prim_order"], trees[1]["prim_order"])

    def nodes(tree):
        count = len(tree["node_begin"])
        return sorted((int(b), int(e), tuple(lo.tolist()), tuple(hi.tolist()))
                      for b, e, lo, hi in zip(tree["node_begin"][:count], tree["node_end"][:count],
                                              tree["node_lowers"][:count], tree["node_uppers"][:count]))

    assert nodes(trees[0]) == nodes(trees[1])


@pytest.mark.parametrize("offset", [-1, 0, 4097])
@pytest.mark.parametrize("threads", [1, 2, 3])
def test_triangle_boxes_alone_equal_the_generic_kernel(device, offset, threads):
    """The boxes-only pass (a refit's, or a fixed grid's: `compute_triangle_boxes`) on any number
    of cores gives `morton.triangle_bounds_kernel`'s boxes to the bit, NaN, infinite and signed-zero
    vertices included."""
    from hlbvh_warp.kernels import morton

    n = hlbvh.PARALLEL_BOUNDS_MIN_PRIMS + offset
    vertices, faces = _scene(n, seed=offset + 20)
    vertices[3 * (n - 1)] = np.float32(np.inf)  # the last triangle, in the last slice
    vertices[3 * (n // 2) + 2] = np.float32(-0.0)
    v = wp.array(vertices, dtype=wp.vec3, device=device)
    f = wp.array(faces, dtype=wp.int32, device=device)
    pipe = HlbvhPipeline(n, hw.BuildConfig(cpu_threads=threads), device)
    pipe.prim_lowers.fill_(np.float32(7.0))  # stale values the pass must overwrite
    pipe.compute_triangle_boxes(v, f)
    lo = wp.empty(n, dtype=wp.vec3, device=device)
    hi = wp.empty(n, dtype=wp.vec3, device=device)
    wp.launch(morton.triangle_bounds_kernel, dim=n, inputs=[v, f, lo, hi], device=device)
    np.testing.assert_array_equal(pipe.prim_lowers.numpy().view(np.uint32), lo.numpy().view(np.uint32))
    np.testing.assert_array_equal(pipe.prim_uppers.numpy().view(np.uint32), hi.numpy().view(np.uint32))
    # And NumPy's values where no vertex is NaN.
    tri = vertices[faces]
    finite = ~np.isnan(tri).any(axis=(1, 2))
    np.testing.assert_array_equal(pipe.prim_lowers.numpy()[finite], tri.min(axis=1)[finite])
    np.testing.assert_array_equal(pipe.prim_uppers.numpy()[finite], tri.max(axis=1)[finite])


def test_a_refit_on_several_cores_boxes_the_moved_triangles(device):
    """A `Builder`'s refit computes its triangle boxes on several cores: every node box is NumPy's
    float64 union of the moved triangles' boxes."""
    from hlbvh_warp.builder import Builder
    from oracles import numpy_node_boxes

    n = hlbvh.PARALLEL_BOUNDS_MIN_PRIMS + 500
    vertices, faces = _scene(n, seed=5)
    vertices = np.nan_to_num(vertices)
    builder = Builder(n, hw.BuildConfig(cpu_threads=2), device=device, policy="refit")
    builder.build(vertices, faces)
    moved = vertices + np.float32(0.003) * np.sin(np.arange(vertices.size, dtype=np.float32)).reshape(-1, 3)
    builder.update(moved)
    tree = builder.bvh.to_numpy()
    tri = moved[faces]
    node_lo, node_hi = numpy_node_boxes(tree, tri.min(axis=1), tri.max(axis=1))
    np.testing.assert_array_equal(tree["node_lowers"], node_lo.astype(np.float32))
    np.testing.assert_array_equal(tree["node_uppers"], node_hi.astype(np.float32))
