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
