"""BVHs made by hand for the tests: valid trees no builder of the library would make."""

from __future__ import annotations

import numpy as np
import warp as wp

import hlbvh_warp as hw
from hlbvh_warp.bvh import bvh_from_numpy


def left_caterpillar(vertices, faces, device):
    """A valid but maximally deep BVH: interior node k has interior node k + 1 as its left child
    and one triangle as its right, so a walk that goes left first stacks every right child."""
    tris = vertices[faces].astype(np.float64)
    n = len(faces)
    num_nodes = 2 * n - 1
    left = np.full(num_nodes, -1, np.int32)
    right = np.full(num_nodes, -1, np.int32)
    begin = np.zeros(num_nodes, np.int32)
    end = np.zeros(num_nodes, np.int32)
    # Interior k is node 2k and covers [0, n - k); its right leaf (node 2k + 1) holds position
    # n - k - 1. The deepest interior's left child is the leaf at position 0 (the last node).
    for k in range(n - 1):
        left[2 * k] = 2 * k + 2 if k < n - 2 else num_nodes - 1
        right[2 * k] = 2 * k + 1
        begin[2 * k], end[2 * k] = 0, n - k
        begin[2 * k + 1], end[2 * k + 1] = n - k - 1, n - k
    begin[num_nodes - 1], end[num_nodes - 1] = 0, 1
    return bvh_from_numpy(method="caterpillar", config=hw.BuildConfig(), device=device,
                          prim_lowers=tris.min(axis=1).astype(np.float32),
                          prim_uppers=tris.max(axis=1).astype(np.float32),
                          prim_order=np.arange(n), node_left=left, node_right=right, node_begin=begin, node_end=end,
                          vertices=wp.array(vertices, dtype=wp.vec3, device=device),
                          faces=wp.array(faces, dtype=wp.int32, device=device))
