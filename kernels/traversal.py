"""Ray traversal: watertight ray-triangle test and a conservative ray-box test.

- Triangles: Woop, Benthin & Wald, "Watertight Ray/Triangle Intersection", JCGT 2013. Rays
  through shared edges and vertices of a closed mesh hit one of the triangles, never none.
- Boxes: Ize, "Robust BVH Ray Traversal", JCGT 2013: the far slab distance is padded by
  1 + 2 * gamma(3), and axes with a zero direction component are tested as a containment of the
  origin instead of computing 0 * inf = NaN.
"""

import warp as wp

# Forward-only kernels: no adjoints to compile.
wp.set_module_options({"enable_backward": False})

TRAVERSAL_STACK_SIZE = 64
vec64i = wp.types.vector(length=TRAVERSAL_STACK_SIZE, dtype=wp.int32)

# Ize 2013: 1 + 2 * gamma(3), gamma(n) = n * eps / (1 - n * eps), eps = 2^-24.
FAR_PAD = wp.constant(1.0 + 2.0 * (3.0 * 5.960464477539063e-08) / (1.0 - 3.0 * 5.960464477539063e-08))
INF = wp.constant(float("inf"))


@wp.struct
class TriangleHit:
    t: float
    u: float
    v: float
    hit: int


@wp.func
def intersect_triangle_watertight(
    origin: wp.vec3, direction: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3, t_max: float
):
    """Woop et al. 2013: shear/scale into ray space, edge functions with a float64 fallback.

    Returns t in (0, t_max) and the barycentrics (u, v) of b and c, hit = 1; else hit = 0.
    """
    result = TriangleHit()
    result.hit = 0
    ad = wp.vec3(wp.abs(direction[0]), wp.abs(direction[1]), wp.abs(direction[2]))
    kz = int(0)
    if ad[1] > ad[kz]:
        kz = 1
    if ad[2] > ad[kz]:
        kz = 2
    kx = (kz + 1) % 3
    ky = (kx + 1) % 3
    if direction[kz] < 0.0:
        tmp = kx
        kx = ky
        ky = tmp
    dz = direction[kz]
    if dz == 0.0:
        return result
    sx = direction[kx] / dz
    sy = direction[ky] / dz
    sz = 1.0 / dz

    pa = a - origin
    pb = b - origin
    pc = c - origin
    ax = pa[kx] - sx * pa[kz]
    ay = pa[ky] - sy * pa[kz]
    bx = pb[kx] - sx * pb[kz]
    by = pb[ky] - sy * pb[kz]
    cx = pc[kx] - sx * pc[kz]
    cy = pc[ky] - sy * pc[kz]

    u = cx * by - cy * bx
    v = ax * cy - ay * cx
    w = bx * ay - by * ax
    # An edge function of exactly zero is decided in float64 so that neighbours agree.
    if u == 0.0 or v == 0.0 or w == 0.0:
        u = float(wp.float64(cx) * wp.float64(by) - wp.float64(cy) * wp.float64(bx))
        v = float(wp.float64(ax) * wp.float64(cy) - wp.float64(ay) * wp.float64(cx))
        w = float(wp.float64(bx) * wp.float64(ay) - wp.float64(by) * wp.float64(ax))
    if (u < 0.0 or v < 0.0 or w < 0.0) and (u > 0.0 or v > 0.0 or w > 0.0):
        return result
    det = u + v + w
    if det == 0.0:
        return result
    az = sz * pa[kz]
    bz = sz * pb[kz]
    cz = sz * pc[kz]
    t_scaled = u * az + v * bz + w * cz
    t = t_scaled / det
    if not (t > 0.0 and t < t_max):
        return result
    result.t = t
    # u weighs a, v weighs b, w weighs c: report (beta, gamma) of b and c.
    result.u = v / det
    result.v = w / det
    result.hit = 1
    return result


@wp.func
def ray_box_entry(origin: wp.vec3, inv_dir: wp.vec3, direction: wp.vec3, lower: wp.vec3, upper: wp.vec3, t_max: float):
    """Entry distance of the ray into the box, or INF when it misses within [0, t_max]."""
    t0 = float(0.0)
    t1 = t_max
    for k in range(3):
        if direction[k] == 0.0:
            if origin[k] < lower[k] or origin[k] > upper[k]:
                return INF
        else:
            near = (lower[k] - origin[k]) * inv_dir[k]
            far = (upper[k] - origin[k]) * inv_dir[k]
            if near > far:
                tmp = near
                near = far
                far = tmp
            t0 = wp.max(t0, near)
            t1 = wp.min(t1, far * FAR_PAD)
    if t0 <= t1:
        return t0
    return INF


@wp.func
def ray_is_valid(origin: wp.vec3, direction: wp.vec3):
    ok = int(1)
    for k in range(3):
        if not wp.isfinite(origin[k]) or not wp.isfinite(direction[k]):
            ok = 0
    if direction[0] == 0.0 and direction[1] == 0.0 and direction[2] == 0.0:
        ok = 0
    return ok


@wp.kernel
def closest_hit_kernel(
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    prim_order: wp.array(dtype=wp.int32),
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.int32, ndim=2),
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    t_max: float,
    hit_t: wp.array(dtype=float),
    hit_prim: wp.array(dtype=wp.int32),
):
    tid = wp.tid()
    o = origins[tid]
    d = directions[tid]
    best_t = t_max
    best_prim = int(-1)
    if ray_is_valid(o, d) == 1:
        inv = wp.vec3(1.0, 1.0, 1.0)
        for k in range(3):
            if d[k] != 0.0:
                inv[k] = 1.0 / d[k]
        stack = vec64i()
        top = int(0)
        if ray_box_entry(o, inv, d, node_lowers[0], node_uppers[0], best_t) < INF:
            stack[0] = 0
            top = 1
        while top > 0:
            top -= 1
            node = stack[top]
            left = node_left[node]
            if left < 0:
                for k in range(node_begin[node], node_end[node]):
                    p = prim_order[k]
                    h = intersect_triangle_watertight(
                        o, d, vertices[faces[p, 0]], vertices[faces[p, 1]], vertices[faces[p, 2]], best_t
                    )
                    if h.hit == 1:
                        best_t = h.t
                        best_prim = p
            else:
                right = node_right[node]
                tl = ray_box_entry(o, inv, d, node_lowers[left], node_uppers[left], best_t)
                tr = ray_box_entry(o, inv, d, node_lowers[right], node_uppers[right], best_t)
                # Push the far child first so the near one is visited next.
                if tl <= tr:
                    if tr < INF:
                        stack[top] = right
                        top += 1
                    if tl < INF:
                        stack[top] = left
                        top += 1
                else:
                    if tl < INF:
                        stack[top] = left
                        top += 1
                    if tr < INF:
                        stack[top] = right
                        top += 1
    if best_prim < 0:
        best_t = INF
    hit_t[tid] = best_t
    hit_prim[tid] = best_prim
