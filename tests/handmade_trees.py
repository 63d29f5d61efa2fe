"""BVHs made by hand for the tests: valid trees no builder of the library would make."""

from __future__ import annotations

import numpy as np
import warp as wp

import hlbvh_warp as hw
from hlbvh_warp.bvh import Bvh


def left_caterpillar(vertices, faces, device):
    """A valid but maximally deep BVH: interior node k has interior node k + 1 as its left child
    and one triangle as its right, so a walk that goes left first stacks every right child."""
    tris = vertices[faces].astype(np.float64)
    n = len(faces)
    num_nodes = 2 * n - 1
    left = np.full(num_nodes, -1, np.int32)
    right = np.full(num_nodes, -1, np.int32)
    parent = np.full(num_nodes, -1, np.int32)
    begin = np.zeros(num_nodes, np.int32)
    end = np.zeros(num_nodes, np.int32)
    # Interior k is node 2k and covers [0, n - k); its right leaf (node 2k + 1) holds position
    # n - k - 1. The deepest interior's left child is the leaf at position 0 (the last node).
    for k in range(n - 1):
        node = 2 * k
        left[node] = 2 * k + 2 if k < n - 2 else num_nodes - 1
        right[node] = 2 * k + 1
        parent[left[node]] = parent[right[node]] = node
        begin[node], end[node] = 0, n - k
        begin[2 * k + 1], end[2 * k + 1] = n - k - 1, n - k
    begin[num_nodes - 1], end[num_nodes - 1] = 0, 1
    lo, hi = tris.min(axis=1), tris.max(axis=1)
    node_lo = np.array([lo[begin[i]:end[i]].min(0) for i in range(num_nodes)], np.float32)
    node_hi = np.array([hi[begin[i]:end[i]].max(0) for i in range(num_nodes)], np.float32)

    def arr(a, dtype=wp.int32):
        return wp.array(a, dtype=dtype, device=device)

    return Bvh(method="caterpillar", config=hw.BuildConfig(), device=device,
               prim_lowers=arr(lo.astype(np.float32), wp.vec3), prim_uppers=arr(hi.astype(np.float32), wp.vec3),
               prim_order=arr(np.arange(n, dtype=np.int32)), node_lowers=arr(node_lo, wp.vec3),
               node_uppers=arr(node_hi, wp.vec3), node_left=arr(left), node_right=arr(right),
               node_parent=arr(parent), node_begin=arr(begin), node_end=arr(end),
               node_count=arr(np.array([num_nodes], np.int32)), vertices=arr(vertices, wp.vec3),
               faces=arr(faces))
