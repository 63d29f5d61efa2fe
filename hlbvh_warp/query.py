"""Ray queries on a built BVH (host wrappers around the traversal kernels)."""

from __future__ import annotations

import numpy as np
import warp as wp

from . import inputs
from .bvh import Bvh
from .kernels import traversal


def intersect(bvh: Bvh, origins, directions, t_max: float = float("inf")):
    """Closest hit of every ray: ``(t, prim_id)`` as NumPy arrays; a miss is ``(inf, -1)``.

    Rays with NaN or Inf components, or a zero direction, miss.
    """
    if bvh.vertices is None or bvh.faces is None:
        raise ValueError("intersect() needs a BVH built over a mesh (build()), not over bare boxes")
    o, d = inputs.ray_arrays(origins, directions)
    num_rays = o.shape[0]
    device = bvh.device
    hit_t = wp.empty(num_rays, dtype=float, device=device)
    hit_prim = wp.empty(num_rays, dtype=wp.int32, device=device)
    if num_rays:
        wp.launch(
            traversal.closest_hit_kernel,
            dim=num_rays,
            inputs=[
                bvh.node_lowers,
                bvh.node_uppers,
                bvh.node_left,
                bvh.node_right,
                bvh.node_begin,
                bvh.node_end,
                bvh.prim_order,
                bvh.vertices,
                bvh.faces,
                wp.array(o, dtype=wp.vec3, device=device),
                wp.array(d, dtype=wp.vec3, device=device),
                float(t_max),
                hit_t,
                hit_prim,
            ],
            device=device,
        )
    return hit_t.numpy(), hit_prim.numpy()
