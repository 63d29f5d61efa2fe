"""BVHs made by hand for the tests: valid trees no builder of the library would make."""

from __future__ import annotations

import numpy as np
import warp as wp

import hlbvh_warp as hw
from hlbvh_warp import query
from hlbvh_warp.bvh import bvh_from_numpy
from hlbvh_warp.kernels import traversal


def caterpillar(vertices, faces, device, deep: str = "left", boxes_only: bool = False):
    """A valid but maximally deep BVH of depth N - 1: interior node 2k has one triangle as a leaf
    child (node 2k + 1) and the rest of the chain (node 2k + 2) as its other child, on the
    `deep` side. With the chain on the left, a walk that goes left first stacks every leaf.
    ``boxes_only``: a tree over the triangles' boxes alone, as `build_from_bounds` makes (walked
    over the canonical arrays, with no packed layout)."""
    tris = vertices[faces].astype(np.float64)
    n = len(faces)
    num_nodes = 2 * n - 1
    left = np.full(num_nodes, -1, np.int32)
    right = np.full(num_nodes, -1, np.int32)
    begin = np.zeros(num_nodes, np.int32)
    end = np.zeros(num_nodes, np.int32)
    k = np.arange(n - 1)
    chain, leaf = 2 * k + 2, 2 * k + 1
    if deep == "left":
        # Interior 2k covers [0, n - k); its leaf holds position n - k - 1.
        left[2 * k], right[2 * k] = chain, leaf
        begin[2 * k], end[2 * k] = 0, n - k
        begin[leaf], end[leaf] = n - k - 1, n - k
        begin[num_nodes - 1], end[num_nodes - 1] = 0, 1
    else:
        # Interior 2k covers [k, n); its leaf holds position k.
        left[2 * k], right[2 * k] = leaf, chain
        begin[2 * k], end[2 * k] = k, n
        begin[leaf], end[leaf] = k, k + 1
        begin[num_nodes - 1], end[num_nodes - 1] = n - 1, n
    return bvh_from_numpy(method="caterpillar", config=hw.BuildConfig(), device=device,
                          prim_lowers=tris.min(axis=1).astype(np.float32),
                          prim_uppers=tris.max(axis=1).astype(np.float32),
                          prim_order=np.arange(n), node_left=left, node_right=right, node_begin=begin, node_end=end,
                          vertices=None if boxes_only else wp.array(vertices, dtype=wp.vec3, device=device),
                          faces=None if boxes_only else wp.array(faces, dtype=wp.int32, device=device))


def canonical_view(bvh):
    """A view without the packed layout: ray and closest-point queries then walk the canonical arrays."""
    packed = query.view(bvh)
    canonical = query.BvhView()
    for name in ("node_lowers", "node_uppers", "node_left", "node_right", "node_begin", "node_end", "prim_order",
                 "prim_lowers", "prim_uppers", "vertices", "faces"):
        setattr(canonical, name, getattr(packed, name))
    canonical.packed_nodes = wp.zeros(0, dtype=traversal.PackedNode, device=bvh.device)
    canonical.packed_triangles = wp.zeros(0, dtype=traversal.PackedTriangle, device=bvh.device)
    return canonical
