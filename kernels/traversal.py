"""Ray and box queries on a built BVH, callable from any user ``@wp.kernel``.

- Triangles: Woop, Benthin & Wald, "Watertight Ray/Triangle Intersection", JCGT 2013. Rays
  through shared edges and vertices of a closed mesh hit one of the triangles, never none.
- Boxes: Ize, "Robust BVH Ray Traversal", JCGT 2013: the far slab distance is padded by
  1 + 2 * gamma(3). A zero (or underflowing) direction component gives an inverse of +-inf; the
  slab distance of an origin lying on that slab face is then 0 * inf = NaN, which every
  comparison below ignores, so such an axis never constrains the interval. A ray whose box
  differences may pass float32's range (coordinates near 1.7e38 on both sides of it,
  `ray_may_overflow`) decides the boxes it would miss again in float64 (`ray_box_entry_wide`).
- Traversal is ordered front to back: the nearer child is visited next, the farther one deferred
  on a fixed stack of ``TRAVERSAL_STACK_SIZE`` entries. Only deferred siblings are stacked, so a
  tree of depth D needs at most D entries. The HLBVH builders keep D <= 3n + ceil(log2 N) <= 60
  (config.py). For any other tree a node met with a full stack is treated as one leaf over its
  whole primitive range (``node_begin``..``node_end``), so traversal is correct at any depth: it
  only gets slower below depth 64, and never writes past the stack.
- Statistics count traversal steps (nodes visited) and primitive tests per query: the n_s and
  n_t of the measured traversal cost m = n_s * c_t + n_t * c_i (Wodniok & Goesele, GI 2016, eq. 10).
- ``bvh_ray_all_hits``, and box queries on a BVH over bare boxes, walk the canonical arrays.
  Closest-hit and any-hit ray queries, and box queries on a mesh BVH, read a traversal layout
  derived from them (``pack_nodes_sweep_kernel`` on the CPU,
  ``pack_nodes_kernel`` elsewhere, ``pack_triangles_kernel``; made and kept current by
  ``hlbvh_warp.query.TraversalLayout``): every interior node
  is one 64-byte `PackedNode` holding both children's boxes and references, so the two box tests of
  a step read one cache line, and a leaf child costs no node read at all (the child boxes stored in
  the parent, as in the multi-BVH nodes of Ernst & Greiner, "Multi Bounding Volume Hierarchies",
  RT 2008, here with two children). Records sit in depth-first order, so a node's first child is
  the next record, and triangles are copied in tree order next to each other. Incoherent rays are
  bound by memory latency, not arithmetic: both children's records are prefetched before their
  boxes are tested.
"""

import functools
import inspect

import warp as wp

# Forward-only kernels: no adjoints to compile.
wp.set_module_options({"enable_backward": False})

#: ``@inline_func``: a `wp.func` always inlined where Warp can say so (1.18 and later). A function
#: taking the `BvhView` struct is passed it by value: called out of line, every query copied its
#: thirteen arrays (about 700 bytes) first, which cost camera rays 12% once the walk grew past the
#: C++ compiler's own inlining threshold.
_HINTS = "inline" in inspect.signature(wp.func).parameters
inline_func = functools.partial(wp.func, inline=True) if _HINTS else wp.func
#: ``@outline_func``: a `wp.func` kept out of line where Warp can say so: code only rare queries
#: run (a far origin's float64 start), which inlined would crowd the walk every query runs.
outline_func = functools.partial(wp.func, inline=False) if _HINTS else wp.func

#: Traversal stacks are this deep. HLBVH trees are at most 3n + ceil(log2 N) < 64 deep; the top-down
#: builders split exact SAH ties at the middle, so duplicates do not chain; a deeper tree (possible
#: for hand-made topologies) is still traversed exactly: a node met with a full stack is tested as
#: one leaf over its whole primitive range.
TRAVERSAL_STACK_SIZE = 64
vec64i = wp.types.vector(length=TRAVERSAL_STACK_SIZE, dtype=wp.int32)
vec64f = wp.types.vector(length=TRAVERSAL_STACK_SIZE, dtype=wp.float32)

# Ize 2013: 1 + 2 * gamma(3), gamma(n) = n * eps / (1 - n * eps), eps = 2^-24.
FAR_PAD = wp.constant(1.0 + 2.0 * (3.0 * 5.960464477539063e-08) / (1.0 - 3.0 * 5.960464477539063e-08))
INF = wp.constant(float("inf"))
# Below this the float32 determinant is near the subnormals (2^-126 = 1.2e-38): decided in float64.
DET_FLOOR = wp.constant(1.0e-35)
STACK_SIZE = wp.constant(TRAVERSAL_STACK_SIZE)
# A direction whose largest component is below 2^-64 is scaled by powers of 2^32 into range (at
# most 2^96: 2^128 is past float32): below about 3e-39, 1 / d overflows and every box test missed.
TINY_DIRECTION = wp.constant(5.421010862427522e-20)
DIRECTION_STEP = wp.constant(4294967296.0)
# One above 2^64 is scaled down by powers of 2^-32 (at most 2^-64): past 2^126 (8.5e37), 1 / d is
# subnormal, so are the slab distances of a hit at t below 2^-126, and the padding of Ize 2013,
# relative, no longer covers their rounding: rays from inside a unit sphere through its vertices
# with directions of 1.7e38 found no hit, 5 of 4000.
HUGE_DIRECTION = wp.constant(1.8446744073709552e19)
DIRECTION_STEP_DOWN = wp.constant(2.3283064365386963e-10)
# A nonzero component below 2^-126 beside one of at most 2^32 is scaled up by 2^24, into float32's
# normal range: below about 2^-128, 1 / d overflows and the slab test missed every box off the
# origin's slab on that axis, while the watertight test, which takes d / dz, still hit in it.
SMALL_COMPONENT_STEP = wp.constant(16777216.0)
SMALL_COMPONENT_LIMIT = wp.constant(4294967296.0)
FLOAT32_MAX = wp.constant(3.4028234663852886e38)
# The least normal float32 (2^-126) and the least subnormal (2^-149).
FLOAT32_TINY = wp.constant(1.1754943508222875e-38)
FLOAT32_SUBNORMAL = wp.constant(1.401298464324817e-45)
# 1 - 2^-24 and 2^-24: y * BELOW_ONE is the float32 below y, y + y * ULP_FRACTION the one above,
# for a normal y that is no power of two (both products exact or rounded once, never fused away).
BELOW_ONE = wp.constant(0.9999999403953552)
ULP_FRACTION = wp.constant(5.960464477539063e-08)
# An origin farther from the root box than this many times the box's extent is first moved along
# its ray to the box (`ray_far_shift`): float32 differences of triangle and origin coordinates
# (the shear of the watertight test) lose a triangle's size as the distance grows, about 2^-24 of
# the distance. Below the bound the caller's ray is walked exactly as given: the moved origin is
# rounded to float32, which decides a ray grazing a silhouette edge anew (a cube's edge from 100
# sizes away missed 12 of 30 times at a bound of 16). At 1024 (the first choice) rays from just
# inside it differed from a float64 brute force on about 2% of a scanned mesh's rays.
FAR_ORIGIN = wp.constant(256.0)
FAR_BOX_PAD = wp.constant(wp.float64(2.0**-30))
# A bound, with a margin of ten, on float64's rounding of a slab distance from a far origin, per
# unit of the origin's and the box's largest coordinates.
FAR_ORIGIN_PAD = wp.constant(wp.float64(2.0**-48))


@wp.struct
class PackedNode:
    """One interior node of the traversal layout: 64 bytes, one cache line.

    Child ``a`` is the one whose primitive range starts where the parent's does, ``b`` the other
    (the canonical left/right order does not matter to a ray). ``child_*`` is the position of the
    child's own record, or minus its primitive count for a leaf; ``count_*`` is the number of
    primitives under the child, so a traversal that knows where a node's range begins knows where
    each child's begins.
    """

    lower_a: wp.vec3
    upper_a: wp.vec3
    lower_b: wp.vec3
    upper_b: wp.vec3
    child_a: wp.int32
    child_b: wp.int32
    count_a: wp.int32
    count_b: wp.int32


@wp.struct
class PackedTriangle:
    """The vertices of the triangle at one position of ``prim_order``: one read instead of a face
    row and three scattered vertex rows."""

    a: wp.vec3
    b: wp.vec3
    c: wp.vec3


@wp.struct
class BvhView:
    """Everything a query reads, passed by value into user kernels (see ``hlbvh_warp.query.view``).

    Node fields follow ``hlbvh_warp.bvh.Bvh``; ``vertices`` and ``faces`` are empty arrays for a
    BVH built from bare boxes, which supports box queries only (ray and closest-point queries on
    its view find nothing). ``packed_nodes`` and
    ``packed_triangles`` are the ray traversal layout of the module docstring; ray queries on a view
    without them (empty arrays) walk the canonical arrays instead, with the same results.
    A spatial-split tree (Stich et al. 2009) lists some primitives more than once (``prim_order``
    longer than ``prim_lowers``, `splits_prims`) and its leaf boxes bound parts of triangles: its
    box queries test every primitive's box instead of walking the nodes.
    """

    node_lowers: wp.array(dtype=wp.vec3)
    node_uppers: wp.array(dtype=wp.vec3)
    node_left: wp.array(dtype=wp.int32)
    node_right: wp.array(dtype=wp.int32)
    node_begin: wp.array(dtype=wp.int32)
    node_end: wp.array(dtype=wp.int32)
    prim_order: wp.array(dtype=wp.int32)
    prim_lowers: wp.array(dtype=wp.vec3)
    prim_uppers: wp.array(dtype=wp.vec3)
    vertices: wp.array(dtype=wp.vec3)
    faces: wp.array(dtype=wp.int32, ndim=2)
    packed_nodes: wp.array(dtype=PackedNode)
    packed_triangles: wp.array(dtype=PackedTriangle)


@wp.struct
class TriangleHit:
    t: float
    u: float
    v: float
    hit: int


@wp.struct
class RayHit:
    """Result of a ray query: ``prim`` is -1 and ``t`` inf on a miss.

    ``u``, ``v`` weigh the triangle's second and third vertex (the hit point is
    ``(1 - u - v) * a + u * b + v * c``); ``nodes_visited`` and ``prims_tested`` are the n_s and
    n_t of Wodniok & Goesele 2016.
    """

    t: float
    prim: int
    u: float
    v: float
    nodes_visited: int
    prims_tested: int


vec6d = wp.types.vector(length=6, dtype=wp.float64)
# Below this fraction of |ab|^2 |ac|^2, |ab x ac|^2 in float64 may be rounding alone (the edges'
# own rounding included, at most about 2^-48 |ab| |ac| on each component): the area is decided exactly.
AREA_RECHECK = wp.constant(wp.float64(1.0e-24))


@wp.func
def cross_component_is_zero(ay: float, az: float, by: float, bz: float, cy: float, cz: float):
    """1 when this component of (b - a) x (c - a) = a x b + b x c + c x a is exactly zero. The six
    products of float32 coordinates are exact in float64 (24 + 24 bits); they are summed into a
    nonoverlapping expansion by exact two-sums (Shewchuk, "Adaptive Precision Floating-Point
    Arithmetic and Fast Robust Geometric Predicates", 1997, Grow-Expansion), which is zero exactly
    when every one of its terms is. (`proximity.exact_cross_component` forms the same products
    and rounds their sum once, for a normal accurate to an ulp; a zero needs the whole expansion.)"""
    terms = vec6d(wp.float64(ay) * wp.float64(bz), -wp.float64(az) * wp.float64(by),
                  wp.float64(by) * wp.float64(cz), -wp.float64(bz) * wp.float64(cy),
                  wp.float64(cy) * wp.float64(az), -wp.float64(cz) * wp.float64(ay))
    expansion = vec6d()
    for m in range(6):
        q = terms[m]
        for i in range(m):
            # Knuth's TwoSum: s + err == q + expansion[i] exactly.
            s = q + expansion[i]
            z = s - q
            expansion[i] = (q - (s - z)) + (expansion[i] - z)
            q = s
        expansion[m] = q
    zero = int(1)
    for i in range(6):
        if expansion[i] != wp.float64(0.0):
            zero = 0
    return zero


@wp.func
def triangle_has_no_area(a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """1 when the float32 vertices are exactly collinear (or coincide): the float64 cross product
    decides every triangle but those within its rounding of zero, which are decided exactly."""
    ab = wp.vec3d(b) - wp.vec3d(a)
    ac = wp.vec3d(c) - wp.vec3d(a)
    n = wp.cross(ab, ac)
    if wp.dot(n, n) > AREA_RECHECK * wp.dot(ab, ab) * wp.dot(ac, ac):
        return 0
    return (cross_component_is_zero(a[1], a[2], b[1], b[2], c[1], c[2])
            * cross_component_is_zero(a[2], a[0], b[2], b[0], c[2], c[0])
            * cross_component_is_zero(a[0], a[1], b[0], b[1], c[0], c[1]))


# x * y - z * w with both products rounded, never fused into a multiply-add. Watertightness
# (Woop et al. 2013) rests on two triangles sharing an edge computing that edge's function as
# exact negatives of each other: fused, one product stays exact and the other rounds, so both
# can come out negative and a ray through the edge misses both triangles. CUDA fuses by default
# (NVRTC's --fmad=true), and so does the CPU with -ffp-contract=fast, in the library's kernels
# and in users' kernels that call the queries alike: 538 of 200k rays from inside a closed
# sphere through its edges escaped. The products are rounded explicitly on CUDA and kept apart
# on the CPU: the same three operations as written, none extra.
_DIFFERENCE_OF_PRODUCTS = """
#if defined(__CUDA_ARCH__)
    return __fsub_rn(__fmul_rn(x, y), __fmul_rn(z, w));
#else
    {
#pragma clang fp contract(off)
    return x * y - z * w;
    }
#endif
"""


@wp.func_native(_DIFFERENCE_OF_PRODUCTS)
def difference_of_products(x: float, y: float, z: float, w: float) -> float: ...


# x - y * z with the product rounded, never fused into a multiply-add: the shear of Woop et al.
# 2013, p[kx] - sx * p[kz]. For a point the ray passes through exactly (p - origin = k * direction),
# rounding the product gives p[kx] back whenever rn(rn(dx / dz) * dz) does, which is the common
# case, so the point's edge functions read zero and the hit is decided exactly; fused, the
# difference keeps the whole rounding error of sx, and rays aimed at a cube's silhouette edge
# missed it (21 of 30). Rounded explicitly on CUDA, kept apart on the CPU (as
# `difference_of_products`): the same two operations as written.
_DIFFERENCE_OF_PRODUCT = """
#if defined(__CUDA_ARCH__)
    return __fsub_rn(x, __fmul_rn(y, z));
#else
    {
#pragma clang fp contract(off)
    return x - y * z;
    }
#endif
"""


@wp.func_native(_DIFFERENCE_OF_PRODUCT)
def difference_of_product(x: float, y: float, z: float) -> float: ...


@wp.func
def intersect_triangle_watertight(
    origin: wp.vec3, direction: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3, t_min: float, t_max: float
):
    """Woop et al. 2013: shear/scale into ray space, edge functions with a float64 fallback.

    Returns t in (t_min, t_max) and the barycentrics (u, v) of b and c, hit = 1; else hit = 0.
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
    # Swapping kx and ky keeps the winding, so the sign of the edge functions means the same side.
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
    ax = difference_of_product(pa[kx], sx, pa[kz])
    ay = difference_of_product(pa[ky], sy, pa[kz])
    bx = difference_of_product(pb[kx], sx, pb[kz])
    by = difference_of_product(pb[ky], sy, pb[kz])
    cx = difference_of_product(pc[kx], sx, pc[kz])
    cy = difference_of_product(pc[ky], sy, pc[kz])

    u = difference_of_products(cx, by, cy, bx)
    v = difference_of_products(ax, cy, ay, cx)
    w = difference_of_products(bx, ay, by, ax)
    det = u + v + w
    az = sz * pa[kz]
    bz = sz * pb[kz]
    cz = sz * pc[kz]
    t = float(0.0)
    bary_b = float(0.0)
    bary_c = float(0.0)
    if u == 0.0 or v == 0.0 or w == 0.0 or not wp.isfinite(det) or wp.abs(det) < DET_FLOOR:
        # An edge function of exactly zero is decided in float64 so that neighbours agree; the
        # same path keeps coordinates near 1e19 (products overflow float32) finite, and those
        # near 1e-19 exact: their products fall among float32's subnormals, where 1 / det
        # overflows and the edge functions lose their digits.
        ax64 = wp.float64(ax)
        ay64 = wp.float64(ay)
        bx64 = wp.float64(bx)
        by64 = wp.float64(by)
        cx64 = wp.float64(cx)
        cy64 = wp.float64(cy)
        az64 = wp.float64(az)
        bz64 = wp.float64(bz)
        cz64 = wp.float64(cz)
        if not (wp.isfinite(ax) and wp.isfinite(ay) and wp.isfinite(bx) and wp.isfinite(by) and wp.isfinite(cx)
                and wp.isfinite(cy) and wp.isfinite(az) and wp.isfinite(bz) and wp.isfinite(cz)):
            # Coordinates beyond about 1e38 overflow float32 in the shear itself (a difference
            # of two such values, or one scaled by 1 / dz): shear them in float64 instead. Only
            # then, so that finite sheared values, which neighbours sharing an edge compute
            # alike, still decide that edge. (The same shear as above, in the wider type.)
            dz64 = wp.float64(dz)
            sx64 = wp.float64(direction[kx]) / dz64
            sy64 = wp.float64(direction[ky]) / dz64
            o64 = wp.vec3d(origin)
            pa64 = wp.vec3d(a) - o64
            pb64 = wp.vec3d(b) - o64
            pc64 = wp.vec3d(c) - o64
            ax64 = pa64[kx] - sx64 * pa64[kz]
            ay64 = pa64[ky] - sy64 * pa64[kz]
            bx64 = pb64[kx] - sx64 * pb64[kz]
            by64 = pb64[ky] - sy64 * pb64[kz]
            cx64 = pc64[kx] - sx64 * pc64[kz]
            cy64 = pc64[ky] - sy64 * pc64[kz]
            az64 = pa64[kz] / dz64
            bz64 = pb64[kz] / dz64
            cz64 = pc64[kz] / dz64
        u64 = cx64 * by64 - cy64 * bx64
        v64 = ax64 * cy64 - ay64 * cx64
        w64 = bx64 * ay64 - by64 * ax64
        zero = wp.float64(0.0)
        if (u64 < zero or v64 < zero or w64 < zero) and (u64 > zero or v64 > zero or w64 > zero):
            return result
        det64 = u64 + v64 + w64
        # det == 0: the ray lies in the triangle's plane, or the triangle has no area (a point or
        # a segment); both count as a miss, as in the paper.
        if det64 == zero:
            return result
        t = float((u64 * az64 + v64 * bz64 + w64 * cz64) / det64)
        bary_b = float(v64 / det64)
        bary_c = float(w64 / det64)
    else:
        if (u < 0.0 or v < 0.0 or w < 0.0) and (u > 0.0 or v > 0.0 or w > 0.0):
            return result
        # Normalize before weighting the depths: u * az would overflow float32 (or underflow)
        # for coordinates near 1e18 (or 1e-18), the barycentrics never do.
        inv_det = 1.0 / det
        bary_a = u * inv_det
        bary_b = v * inv_det
        bary_c = w * inv_det
        t = bary_a * az + bary_b * bz + bary_c * cz
    if not (t > t_min and t < t_max):
        return result
    # A triangle of three distinct collinear vertices sheared in float32 can keep three tiny edge
    # functions of one sign, which read as a hit with meaningless weights: a zero-area triangle has
    # no surface to hit. Checked only for hits, which are few.
    if triangle_has_no_area(a, b, c) == 1:
        return result
    result.t = t
    # u weighs a, v weighs b, w weighs c: report (beta, gamma) of b and c.
    result.u = bary_b
    result.v = bary_c
    result.hit = 1
    return result


@wp.func
def intersect_triangle_watertight(  # noqa: F811  (a Warp overload, chosen by argument count)
    origin: wp.vec3, direction: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3, t_max: float
):
    """The hit with t in (0, t_max)."""
    return intersect_triangle_watertight(origin, direction, a, b, c, 0.0, t_max)


@wp.func
def ray_direction_scale(direction: wp.vec3):
    """A power of two s that brings a tiny direction's largest component to at least 2^-64, a huge
    one's to at most 2^64, and a component below 2^-126 beside ones of at most 2^32 into float32's
    normal range; 1.0 for every other direction (NaN, Inf and zero included), whose rays are left
    bit for bit alone.

    The query runs with ``direction * s`` and the range moved into its units
    (`ray_scaled_t_min`, `ray_scaled_t_max`), and multiplies the t it finds by s. Scaling up is
    exact, and so is the hit distance. Scaling down rounds only a component below 2^-158 of the
    largest one, whose d / dz the watertight test rounds to zero either way; the t found, times s,
    is rounded once, where unscaled a hit's subnormal t was rounded at every step of the test.
    """
    m = wp.max(wp.abs(direction[0]), wp.max(wp.abs(direction[1]), wp.abs(direction[2])))
    s = float(1.0)
    if m > 0.0 and m <= FLOAT32_MAX:
        while m * s < TINY_DIRECTION:
            s = s * DIRECTION_STEP
        while m * s > HUGE_DIRECTION:
            s = s * DIRECTION_STEP_DOWN
        n = m
        for k in range(3):
            a = wp.abs(direction[k])
            if a > 0.0 and a < n:
                n = a
        # d / dz rounds to zero for a component below 2^-150 dz: only beside dz up to 2^22 does
        # an overflowing 1 / d make the box test miss what the triangle test hits.
        if n * s < FLOAT32_TINY and m * s <= SMALL_COMPONENT_LIMIT:
            s = s * SMALL_COMPONENT_STEP
    return s


@wp.func
def ray_scaled_t_min(t_min: float, scale: float):
    """`t_min` in units of the direction scaled by ``scale`` (see `ray_direction_scale`): the
    largest float32 L such that a hit t > L is exactly one whose reported ``t * scale`` lies above
    ``t_min``. Rounded among the subnormals, ``t_min / scale`` alone would refuse a hit on L
    itself (scaled up), or count hits whose product rounds down onto ``t_min`` (scaled down)."""
    # NaN (or a negative t_min) passes through unchanged, for `ray_is_valid` to refuse.
    if scale == 1.0 or not (t_min >= 0.0):
        return t_min
    # Scaled up, t * scale is exact: L is t_min / scale rounded down. Scaled down, exact (or past
    # every hit: inf).
    low = t_min / scale
    if scale > 1.0:
        if low * scale > t_min:
            low = low - FLOAT32_SUBNORMAL
    elif t_min < FLOAT32_TINY:
        # t * scale rounds among the subnormals: products up to half a step above t_min round
        # onto it. The half-way point, (2 j + 1) 2^-150 / scale, is a float32; it rounds to even.
        low = low + 0.5 * (FLOAT32_SUBNORMAL / scale)
        if low * scale > t_min:
            low = low * BELOW_ONE
    return low


@wp.func
def ray_scaled_t_max(t_max: float, scale: float):
    """`t_max` in units of the scaled direction, as `ray_scaled_t_min`: the least float32 H such
    that a hit t < H is exactly one whose reported ``t * scale`` lies below ``t_max``. Clamped to
    float32's range first: a true distance past it is a miss, scaled or not."""
    # NaN (or no positive range) passes through unchanged, for `ray_is_valid` to refuse.
    if scale == 1.0 or not (t_max > 0.0):
        return t_max
    limit = wp.min(t_max, FLOAT32_MAX)
    high = limit / scale
    if scale > 1.0:
        if high * scale < limit:
            high = high + FLOAT32_SUBNORMAL
    elif t_max <= FLOAT32_TINY:
        # The half-way point below t_max, as in `ray_scaled_t_min`. (For t_max = 2^-149 it is a
        # power of two and stays: every t below it reports 0, which no range holds.)
        high = high - 0.5 * (FLOAT32_SUBNORMAL / scale)
        if high * scale < t_max:
            high = high + high * ULP_FRACTION
    return high


@wp.func
def origin_is_far(origin: wp.vec3, lower: wp.vec3, upper: wp.vec3):
    """1 when ``origin`` lies farther outside the box than `FAR_ORIGIN` times its extent: the test
    every ray pays, kept apart from the float64 work only far rays do (`ray_start`)."""
    extent = wp.max(upper[0] - lower[0], wp.max(upper[1] - lower[1], upper[2] - lower[2]))
    gap = wp.max(wp.max(lower[0] - origin[0], origin[0] - upper[0]),
                 wp.max(wp.max(lower[1] - origin[1], origin[1] - upper[1]),
                        wp.max(lower[2] - origin[2], origin[2] - upper[2])))
    # NaN anywhere fails this test: such a ray is refused later, unmoved.
    return wp.where(gap > FAR_ORIGIN * extent and wp.isfinite(gap), 1, 0)


@wp.func
def ray_far_shift(origin: wp.vec3, direction: wp.vec3, lower: wp.vec3, upper: wp.vec3):
    """How far along the ray (in units of ``direction``) to move an origin that lies far outside
    the root box ``[lower, upper]`` before the traversal: 0 for every other origin.

    Seen from an origin 1e6 box sizes away, float32 coordinates relative to the origin keep
    nothing of a triangle's size: the watertight test's edge functions are rounding noise (hits
    lost or invented) and the padded box test (Ize 2013), whose slack grows with the distance,
    opens every node. Moved in float64 to a box size before the root box, the origin keeps the
    triangles' float32 resolution and the ray its direction: the walk is then as for a near
    origin, and the t found there is added to the shift. No hit is lost: every hit lies at or
    beyond the box's entry distance, and the new origin stops short of it.

    Returns -1 for a far origin whose ray misses the root box in float64 (the box slightly
    widened): a float32 walk would open every node the padded test cannot rule out and could
    only find rounding artifacts there.

    The box is widened by more than float64's rounding of the slab distances (a few units in the
    last place of the origin's coordinates): no ray that meets the box is refused, and the shift
    never passes its entry. From about 1e15 box extents on that rounding exceeds the box itself,
    and the walk starts that much before it, where float32 resolves less of each triangle.
    """
    shift = wp.float64(0.0)
    extent = wp.max(upper[0] - lower[0], wp.max(upper[1] - lower[1], upper[2] - lower[2]))
    # Called for origins `origin_is_far` calls far (`walk_start`); the test again, for any other caller.
    if origin_is_far(origin, lower, upper) == 1:
        t0 = wp.float64(0.0)
        t1 = wp.float64(INF)
        reach = float(0.0)
        box_size = wp.float64(wp.max(wp.max(wp.abs(lower[0]), wp.abs(upper[0])), wp.max(
            wp.max(wp.abs(lower[1]), wp.abs(upper[1])), wp.max(wp.abs(lower[2]), wp.abs(upper[2])))))
        origin_size = wp.float64(wp.max(wp.abs(origin[0]), wp.max(wp.abs(origin[1]), wp.abs(origin[2]))))
        pad = (wp.float64(FAR_BOX_PAD) * (wp.float64(extent) + box_size)
               + wp.float64(FAR_ORIGIN_PAD) * (origin_size + box_size))
        for k in range(3):
            dk = wp.float64(direction[k])
            reach = wp.max(reach, wp.abs(direction[k]))
            lo = wp.float64(lower[k]) - pad - wp.float64(origin[k])
            hi = wp.float64(upper[k]) + pad - wp.float64(origin[k])
            if dk != wp.float64(0.0):
                near = lo / dk
                far = hi / dk
                if dk < wp.float64(0.0):
                    near = hi / dk
                    far = lo / dk
                t0 = wp.max(t0, near)
                t1 = wp.min(t1, far)
            elif lo > wp.float64(0.0) or hi < wp.float64(0.0):
                t1 = wp.float64(-1.0)
        # Stop one box extent short of the box, so the rounded origin still lies outside it.
        if t0 <= t1 and reach > 0.0:
            shift = wp.max(t0 - wp.float64(extent) / wp.float64(reach), wp.float64(0.0))
        else:
            shift = wp.float64(-1.0)
    return shift


@wp.func
def two_sum_error(a: wp.float64, b: wp.float64, s: wp.float64):
    """The rounding error of ``s = a + b`` (Knuth's TwoSum): ``a + b == s + error`` exactly."""
    z = s - a
    return (a - (s - z)) + (b - z)


# x * y rounded on its own, never fused into a multiply-add with what uses it: Veltkamp's split
# below takes c = 134217729 s rounded, then c - (c - s). Fused into c - (c - s) (CUDA's default,
# NVRTC's --fmad=true; the CPU with -ffp-contract=fast), the head keeps all of s's bits, its
# products with the direction are no longer exact, and a far origin's start point leaves the ray
# by 2^-53 of the origin's coordinates: a whole box at 1e16 box sizes. Products of the split's
# halves with float32 values are exact and need no such care.
_ROUNDED_PRODUCT64 = """
#if defined(__CUDA_ARCH__)
    return __dmul_rn(x, y);
#else
    {
#pragma clang fp contract(off)
    return x * y;
    }
#endif
"""


@wp.func_native(_ROUNDED_PRODUCT64)
def rounded_product64(x: wp.float64, y: wp.float64) -> wp.float64: ...


@wp.func
def point_on_ray(origin: wp.vec3, direction: wp.vec3, s: wp.float64):
    """``origin + s * direction`` with each coordinate rounded once, to float32, from a sum whose
    own error is about 2^-106 of the origin's coordinates.

    From a far origin a plain float64 ``o + s * d`` is off the ray by float64's rounding of ``o``
    (2^-53 of it, a whole box at 1e16 box sizes), which moves the ray sideways. Here ``s`` is cut
    into two halves, whose products with a float32 direction are both exact, and the three terms
    are summed with their rounding errors kept (TwoSum): the point lies on the ray wherever ``s``
    puts it along.
    """
    # Veltkamp's split: a head of 26 bits and a tail of 27, each exact times a 24-bit float32.
    c = rounded_product64(wp.float64(134217729.0), s)
    s_head = c - (c - s)
    s_tail = s - s_head
    out = wp.vec3()
    for k in range(3):
        dk = wp.float64(direction[k])
        o = wp.float64(origin[k])
        p_head = s_head * dk
        p_tail = s_tail * dk
        a = o + p_head
        ea = two_sum_error(o, p_head, a)
        b = a + p_tail
        eb = two_sum_error(a, p_tail, b)
        out[k] = wp.float32(b + (ea + eb))
    return out


@wp.func
def far_hit_in_range(t: float, shift: wp.float64, t_min: float, t_max: float):
    """1 when a hit found at ``t`` from a moved origin lies, as the float32 distance from the
    caller's origin it is reported as, strictly inside the caller's (t_min, t_max): rounded onto an
    end, or past float32's range, it does not count. Always 1 for an origin that was not moved."""
    ok = int(1)
    if shift > wp.float64(0.0):
        reported = wp.float32(wp.float64(t) + shift)
        if not (reported > t_min and reported < t_max):
            ok = 0
    return ok


@wp.struct
class RayStart:
    """Where a walk starts (`ray_start`): the origin, the range in units of the direction from that
    origin, and ``shift``, the distance from the caller's origin to add to a hit's t."""

    origin: wp.vec3
    t_min: float
    t_max: float
    shift: wp.float64


@outline_func
def ray_start(origin: wp.vec3, direction: wp.vec3, t_min: float, t_max: float, lower: wp.vec3, upper: wp.vec3):
    """The walk's start for a ray and its range (t_min, t_max) against the root box
    ``[lower, upper]``: the ray itself, or for a far origin the origin moved by `ray_far_shift`
    and the range moved with it; a far ray that misses the box gets an empty range."""
    result = RayStart()
    result.origin = origin
    result.t_min = t_min
    result.t_max = t_max
    result.shift = wp.float64(0.0)
    # An empty range (t_min < 0 or NaN included) stays as it is, for `ray_is_valid` to refuse:
    # moved, it could become a valid one.
    if not (t_min >= 0.0 and t_max > t_min):
        return result
    result.shift = ray_far_shift(origin, direction, lower, upper)
    if result.shift > wp.float64(0.0):
        result.origin = point_on_ray(origin, direction, result.shift)
        result.t_min = float(wp.max(wp.float64(t_min) - result.shift, wp.float64(0.0)))
        result.t_max = float(wp.float64(t_max) - result.shift)
    elif result.shift < wp.float64(0.0):
        result.t_max = float(0.0)
        result.shift = wp.float64(0.0)
    return result


@inline_func
def walk_start(origin: wp.vec3, direction: wp.vec3, t_min: float, t_max: float, lower: wp.vec3, upper: wp.vec3):
    """Where every ray walk starts: the ray as given (shift 0), or for an origin `origin_is_far`
    calls far the out-of-line `ray_start`. Inlined: the cheap test every ray pays stays in the
    caller, the float64 move only far rays run stays out of its loop."""
    start = RayStart()
    start.origin = origin
    start.t_min = t_min
    start.t_max = t_max
    if origin_is_far(origin, lower, upper) == 1:
        start = ray_start(origin, direction, t_min, t_max, lower, upper)
    return start


@wp.func
def ray_inverse_direction(direction: wp.vec3):
    """1 / d per axis; a zero component gives +-inf, which `ray_box_entry` is written to accept."""
    return wp.vec3(1.0 / direction[0], 1.0 / direction[1], 1.0 / direction[2])


@wp.func
def ray_box_entry(origin: wp.vec3, inv_dir: wp.vec3, lower: wp.vec3, upper: wp.vec3, t_min: float, t_max: float):
    """Entry distance of the ray into the box, or INF when it misses within [t_min, t_max].

    Slab distances that are NaN (origin on a slab face, direction parallel to it) fail every
    comparison and so leave [t0, t1] unchanged: the ray stays on that face, inside the slab. The
    padded far distance is what a box behind ``t_min`` is dropped on, so a triangle whose own t
    lies just past ``t_min`` is not lost to the box test's rounding.
    """
    t0 = t_min
    t1 = t_max
    for k in range(3):
        near = (lower[k] - origin[k]) * inv_dir[k]
        far = (upper[k] - origin[k]) * inv_dir[k]
        if inv_dir[k] < 0.0:
            tmp = near
            near = far
            far = tmp
        if near > t0:
            t0 = near
        far = far * FAR_PAD
        if far < t1:
            t1 = far
    if t0 <= t1:
        return t0
    return INF


@wp.func
def ray_box_entry(  # noqa: F811  (a Warp overload, chosen by argument count)
    origin: wp.vec3, inv_dir: wp.vec3, lower: wp.vec3, upper: wp.vec3, t_max: float
):
    """Entry distance into the box, or INF when the ray misses it within [0, t_max]."""
    return ray_box_entry(origin, inv_dir, lower, upper, 0.0, t_max)


@wp.func
def ray_may_overflow(origin: wp.vec3, lower: wp.vec3, upper: wp.vec3):
    """1 when a coordinate of a box inside ``[lower, upper]`` (the root's) minus the origin may
    be past float32's range, as it is from one side of a mesh whose coordinates reach 1.7e38 to
    the other: |b - o| <= |b| + |o|, and rounding keeps the order, so where each axis's sum is
    finite no difference overflows. A NaN origin answers 1 too; such a ray misses anyway."""
    wide = int(0)
    for k in range(3):
        if not wp.isfinite(wp.abs(origin[k]) + wp.max(wp.abs(lower[k]), wp.abs(upper[k]))):
            wide = 1
    return wide


@outline_func
def ray_box_entry_wide(origin: wp.vec3, inv_dir: wp.vec3, lower: wp.vec3, upper: wp.vec3, t_min: float,
                       t_max: float):
    """`ray_box_entry` with the slab distances in float64, for a ray `ray_may_overflow` flags. In
    float32 a difference past float32's range is infinite: a near slab distance then reads
    infinite and the box was missed, though its triangles, whose test shears in float64 there,
    are hit. The float64 differences and products round less than the float32 ones, which the
    far distance's padding (Ize 2013) covers; the entry is rounded to float32 as it is returned
    (past float32's range, to INF: no hit there has a float32 t)."""
    t0 = wp.float64(t_min)
    t1 = wp.float64(t_max)
    for k in range(3):
        inv = wp.float64(inv_dir[k])
        near = (wp.float64(lower[k]) - wp.float64(origin[k])) * inv
        far = (wp.float64(upper[k]) - wp.float64(origin[k])) * inv
        if inv < wp.float64(0.0):
            tmp = near
            near = far
            far = tmp
        if near > t0:
            t0 = near
        far = far * wp.float64(FAR_PAD)
        if far < t1:
            t1 = far
    if t0 <= t1:
        return float(t0)
    return INF


@wp.func
def ray_box_entry(  # noqa: F811  (a Warp overload, chosen by argument count)
    origin: wp.vec3, inv_dir: wp.vec3, lower: wp.vec3, upper: wp.vec3, t_min: float, t_max: float, wide: int
):
    """`ray_box_entry`, and for a ray that `ray_may_overflow` flags (``wide`` 1) a miss decided
    again in float64 (`ray_box_entry_wide`). An overflowed difference only ever turns a hit into a
    miss: a near distance of +inf empties the interval, one of -inf lies behind t_min anyway, and
    an infinite far distance only widens it, leaving the entry (the largest near one) as it is."""
    t = ray_box_entry(origin, inv_dir, lower, upper, t_min, t_max)
    if wide == 1 and t == INF:
        t = ray_box_entry_wide(origin, inv_dir, lower, upper, t_min, t_max)
    return t


@wp.func
def box_overlap(lower_a: wp.vec3, upper_a: wp.vec3, lower_b: wp.vec3, upper_b: wp.vec3):
    """Closed boxes overlap (touching counts); a NaN bound overlaps nothing, and neither does an
    empty box a (lower > upper on an axis: a query box; the tree's own boxes are never empty)."""
    ok = int(1)
    for k in range(3):
        # Each bound of a against the opposite bound of b alone lets an inverted a whose bounds
        # both lie inside b's range on that axis (x in [0.5, 0.4] against [0, 1]) meet b.
        if not (lower_a[k] <= upper_b[k] and lower_b[k] <= upper_a[k] and lower_a[k] <= upper_a[k]):
            ok = 0
    return ok


@wp.func
def ray_is_valid(origin: wp.vec3, direction: wp.vec3, t_min: float, t_max: float):
    """NaN or Inf anywhere, a zero direction, or an empty range (t_min < 0 or NaN included): the
    ray misses."""
    ok = int(1)
    for k in range(3):
        if not wp.isfinite(origin[k]) or not wp.isfinite(direction[k]):
            ok = 0
    if direction[0] == 0.0 and direction[1] == 0.0 and direction[2] == 0.0:
        ok = 0
    if not (t_min >= 0.0 and t_max > t_min):
        ok = 0
    return ok


@wp.func
def ray_is_valid(origin: wp.vec3, direction: wp.vec3, t_max: float):  # noqa: F811  (a Warp overload)
    """`ray_is_valid` over (0, t_max)."""
    return ray_is_valid(origin, direction, 0.0, t_max)


@wp.func
def bvh_triangle(bvh: BvhView, prim: int, origin: wp.vec3, direction: wp.vec3, t_min: float, t_max: float):
    return intersect_triangle_watertight(
        origin,
        direction,
        bvh.vertices[bvh.faces[prim, 0]],
        bvh.vertices[bvh.faces[prim, 1]],
        bvh.vertices[bvh.faces[prim, 2]],
        t_min,
        t_max,
    )


@wp.func
def canonical_ray_query(
    bvh: BvhView, origin: wp.vec3, direction: wp.vec3, t_min: float, t_max: float, ignore_prim: int, any_hit: int
):
    """`packed_ray_query` on the canonical arrays, for a view that carries no traversal layout."""
    shift = wp.float64(0.0)
    range_min = t_min
    range_max = t_max
    if bvh.faces.shape[0] > 0:
        start = walk_start(origin, direction, t_min, t_max, bvh.node_lowers[0], bvh.node_uppers[0])
        origin = start.origin
        t_min = start.t_min
        t_max = start.t_max
        shift = start.shift
    best_t = t_max
    best_prim = int(-1)
    best_u = float(0.0)
    best_v = float(0.0)
    visited = int(0)
    tested = int(0)
    node = int(-1)
    # Deferred nodes and their entry distances: one popped behind the closest hit is skipped.
    stack = vec64i()
    stack_t = vec64f()
    top = int(0)
    inv = wp.vec3(0.0)
    wide = int(0)
    # A view of a box BVH has no triangles to test (its faces are empty): nothing to find.
    if bvh.faces.shape[0] > 0 and ray_is_valid(origin, direction, t_min, t_max) == 1:
        inv = ray_inverse_direction(direction)
        wide = ray_may_overflow(origin, bvh.node_lowers[0], bvh.node_uppers[0])
        if ray_box_entry(origin, inv, bvh.node_lowers[0], bvh.node_uppers[0], t_min, best_t, wide) < INF:
            node = 0
    while node >= 0:
        visited += 1
        left = bvh.node_left[node]
        # A leaf, or an interior node whose far child could not be deferred: test its whole range.
        if left < 0 or top >= STACK_SIZE:
            for k in range(bvh.node_begin[node], bvh.node_end[node]):
                p = bvh.prim_order[k]
                tested += 1
                h = bvh_triangle(bvh, p, origin, direction, t_min, best_t)
                if h.hit == 1 and p != ignore_prim and far_hit_in_range(h.t, shift, range_min, range_max) == 1:
                    best_t = h.t
                    best_prim = p
                    best_u = h.u
                    best_v = h.v
                    if any_hit == 1:
                        break
            node = int(-1)
            if not (any_hit == 1 and best_prim >= 0):
                # Pop the nearest deferred node still in front of the closest hit so far.
                while top > 0 and node < 0:
                    top -= 1
                    if stack_t[top] <= best_t:
                        node = stack[top]
        else:
            right = bvh.node_right[node]
            tl = ray_box_entry(origin, inv, bvh.node_lowers[left], bvh.node_uppers[left], t_min, best_t, wide)
            tr = ray_box_entry(origin, inv, bvh.node_lowers[right], bvh.node_uppers[right], t_min, best_t, wide)
            if tl < INF and tr < INF:
                # Visit the nearer child next, defer the farther one.
                if tl <= tr:
                    node = left
                    stack[top] = right
                    stack_t[top] = tr
                else:
                    node = right
                    stack[top] = left
                    stack_t[top] = tl
                top += 1
            elif tl < INF:
                node = left
            elif tr < INF:
                node = right
            else:
                node = int(-1)
                while top > 0 and node < 0:
                    top -= 1
                    if stack_t[top] <= best_t:
                        node = stack[top]
    result = RayHit()
    result.t = INF
    result.prim = best_prim
    result.u = best_u
    result.v = best_v
    if best_prim >= 0:
        result.t = float(wp.float64(best_t) + shift)
    result.nodes_visited = visited
    result.prims_tested = tested
    return result


# Software prefetch of one record. A traversal step depends on the record the previous step chose,
# so an incoherent ray waits for memory at every step; asking for both children's records before
# their boxes are tested overlaps that wait with the tests. A hint only: no effect on results, and
# nothing on CUDA, where other warps hide the latency.
_PREFETCH_NODE = """
#if !defined(__CUDA_ARCH__)
    __builtin_prefetch((const char*)nodes.data + (size_t)index * (size_t)nodes.strides[0]);
#endif
"""
_PREFETCH_TRIANGLE = """
#if !defined(__CUDA_ARCH__)
    __builtin_prefetch((const char*)triangles.data + (size_t)index * (size_t)triangles.strides[0]);
#endif
"""


@wp.func_native(_PREFETCH_NODE)
def prefetch_node(nodes: wp.array(dtype=PackedNode), index: int): ...


@wp.func_native(_PREFETCH_TRIANGLE)
def prefetch_triangle(triangles: wp.array(dtype=PackedTriangle), index: int): ...


@wp.func
def prefetch_child(
    nodes: wp.array(dtype=PackedNode), triangles: wp.array(dtype=PackedTriangle), child: int, begin: int
):
    # The arrays, not the view: a struct argument is passed by value.
    if child >= 0:
        prefetch_node(nodes, child)
    else:
        prefetch_triangle(triangles, begin)


@wp.func
def packed_ray_query(
    nodes: wp.array(dtype=PackedNode),
    triangles: wp.array(dtype=PackedTriangle),
    prim_order: wp.array(dtype=wp.int32),
    root_lower: wp.vec3,
    root_upper: wp.vec3,
    root_begin: int,
    root: int,
    origin: wp.vec3,
    direction: wp.vec3,
    t_min: float,
    t_max: float,
    ignore_prim: int,
    any_hit: int,
    shift: wp.float64,
    range_min: float,
    range_max: float,
):
    """Front-to-back traversal of the packed layout, shared by the closest-hit and any-hit queries.

    Takes the arrays it reads rather than the `BvhView`, which is passed by value: a copy of the
    whole struct per call costs incoherent rays several percent.

    A node reference is a `PackedNode` position, or minus the primitive count for a leaf; the
    traversal carries where the current node's primitive range begins, so a leaf needs no read
    besides its triangles, and the stack-overflow fallback knows the range of any node. Each step
    tests both children's boxes from the parent's record, continues with the nearer child and
    defers the farther one with its entry distance (the padded test of Ize 2013 orders the
    children); a deferred node entered behind the closest hit found since is dropped when popped.

    Hits count with t in (t_min, t_max), and never on ``ignore_prim`` (-1: none), the triangle a
    secondary ray leaves from. Which triangle a position holds is read only for a hit. For a far
    origin the caller passes the start `ray_start` moved it to, the ``shift`` to add back and the
    caller's own range, which the reported t must lie in (`far_hit_in_range`); the t returned is
    from the caller's origin.
    """
    best_t = t_max
    best_k = int(-1)
    best_u = float(0.0)
    best_v = float(0.0)
    visited = int(0)
    tested = int(0)
    stack = vec64i()
    stack_begin = vec64i()
    stack_t = vec64f()
    top = int(0)
    inv = wp.vec3(0.0)
    node = int(0)
    begin = int(0)
    active = int(0)
    if ray_is_valid(origin, direction, t_min, t_max) == 1:
        inv = ray_inverse_direction(direction)
        if ray_box_entry(origin, inv, root_lower, root_upper, t_min, best_t) < INF:
            active = 1
            node = root
            begin = root_begin
    while active == 1:
        visited += 1
        if node >= 0 and top >= STACK_SIZE:
            # No room to defer a child: test the node's whole range as one leaf.
            full = nodes[node]
            node = -(full.count_a + full.count_b)
        if node < 0:
            for k in range(begin, begin - node):
                tested += 1
                tri = triangles[k]
                h = intersect_triangle_watertight(origin, direction, tri.a, tri.b, tri.c, t_min, best_t)
                if (h.hit == 1 and (ignore_prim < 0 or prim_order[k] != ignore_prim)
                        and far_hit_in_range(h.t, shift, range_min, range_max) == 1):
                    best_t = h.t
                    best_k = k
                    best_u = h.u
                    best_v = h.v
                    if any_hit == 1:
                        break
            active = int(0)
            if not (any_hit == 1 and best_k >= 0):
                # Pop the nearest deferred node still in front of the closest hit so far.
                while top > 0 and active == 0:
                    top -= 1
                    if stack_t[top] <= best_t:
                        node = stack[top]
                        begin = stack_begin[top]
                        active = 1
        else:
            n = nodes[node]
            begin_b = begin + n.count_a
            prefetch_child(nodes, triangles, n.child_a, begin)
            prefetch_child(nodes, triangles, n.child_b, begin_b)
            ta = ray_box_entry(origin, inv, n.lower_a, n.upper_a, t_min, best_t)
            tb = ray_box_entry(origin, inv, n.lower_b, n.upper_b, t_min, best_t)
            if ta < INF and tb < INF:
                # Visit the nearer child next, defer the farther one.
                if ta <= tb:
                    stack[top] = n.child_b
                    stack_begin[top] = begin_b
                    stack_t[top] = tb
                    node = n.child_a
                else:
                    stack[top] = n.child_a
                    stack_begin[top] = begin
                    stack_t[top] = ta
                    node = n.child_b
                    begin = begin_b
                top += 1
            elif ta < INF:
                node = n.child_a
            elif tb < INF:
                node = n.child_b
                begin = begin_b
            else:
                active = int(0)
                while top > 0 and active == 0:
                    top -= 1
                    if stack_t[top] <= best_t:
                        node = stack[top]
                        begin = stack_begin[top]
                        active = 1
    result = RayHit()
    result.t = INF
    result.prim = int(-1)
    result.u = best_u
    result.v = best_v
    if best_k >= 0:
        result.t = float(wp.float64(best_t) + shift)
        result.prim = prim_order[best_k]
    result.nodes_visited = visited
    result.prims_tested = tested
    return result


@inline_func
def bvh_ray_query(
    bvh: BvhView, origin: wp.vec3, direction: wp.vec3, t_min: float, t_max: float, ignore_prim: int, any_hit: int
):
    """Front-to-back traversal shared by the closest-hit and the any-hit query."""
    # A miss's t is inf, and inf times the scale is inf: no test needed before scaling back.
    scale = ray_direction_scale(direction)
    d = direction * scale
    low = ray_scaled_t_min(t_min, scale)
    limit = ray_scaled_t_max(t_max, scale)
    h = RayHit()
    packed = bvh.packed_nodes.shape[0] > 0
    if packed:
        root_begin = bvh.node_begin[0]
        # The root's record is at position 0; a root that is a leaf has none.
        root = wp.where(bvh.node_left[0] < 0, root_begin - bvh.node_end[0], 0)
        root_lower = bvh.node_lowers[0]
        root_upper = bvh.node_uppers[0]
        # A far origin is moved here, out of the walk: its float64 code, out of line, stays out of
        # the loop every ray runs (inside the walk it cost near rays 5-7%).
        start = walk_start(origin, d, low, limit, root_lower, root_upper)
        # A ray whose box differences may leave float32's range (coordinates near 1.7e38 on both
        # sides) takes the canonical walk, which decides its misses again in float64: the packed
        # walk, which every other ray runs, keeps its box test as it is. One call of the canonical
        # walk serves both cases, not a copy in each branch.
        packed = ray_may_overflow(start.origin, root_lower, root_upper) == 0
        if packed:
            h = packed_ray_query(
                bvh.packed_nodes,
                bvh.packed_triangles,
                bvh.prim_order,
                root_lower,
                root_upper,
                root_begin,
                root,
                start.origin,
                d,
                start.t_min,
                start.t_max,
                ignore_prim,
                any_hit,
                start.shift,
                low,
                limit,
            )
    if not packed:
        h = canonical_ray_query(bvh, origin, d, low, limit, ignore_prim, any_hit)
    h.t = h.t * scale
    return h


@inline_func
def bvh_closest_hit(bvh: BvhView, origin: wp.vec3, direction: wp.vec3, t_max: float):
    """Closest triangle hit with t in (0, t_max), as a `RayHit` (prim -1 and t inf on a miss).

    t is in units of ``direction`` (which need not be normalized). Rays with NaN or Inf, or a
    zero direction, miss.
    """
    return bvh_ray_query(bvh, origin, direction, 0.0, t_max, -1, 0)


@inline_func
def bvh_closest_hit(  # noqa: F811  (a Warp overload, chosen by argument count)
    bvh: BvhView, origin: wp.vec3, direction: wp.vec3, t_min: float, t_max: float, ignore_prim: int
):
    """Closest hit with t in (t_min, t_max) on any triangle but ``ignore_prim`` (-1: none).

    For secondary rays (shadows, ambient occlusion, reflections) leaving a surface: ``ignore_prim``
    is the triangle the ray starts on, so it cannot hit itself at t near 0 through rounding;
    ``t_min`` skips whatever lies closer than that (a neighbour across a crease). A range
    with ``t_min < 0``, NaN, or ``t_max <= t_min`` finds nothing.
    """
    return bvh_ray_query(bvh, origin, direction, t_min, t_max, ignore_prim, 0)


@inline_func
def bvh_any_hit(bvh: BvhView, origin: wp.vec3, direction: wp.vec3, t_max: float):
    """The first triangle found with t in (0, t_max), not necessarily the closest (occlusion)."""
    return bvh_ray_query(bvh, origin, direction, 0.0, t_max, -1, 1)


@inline_func
def bvh_any_hit(  # noqa: F811  (a Warp overload, chosen by argument count)
    bvh: BvhView, origin: wp.vec3, direction: wp.vec3, t_min: float, t_max: float, ignore_prim: int
):
    """The first triangle found with t in (t_min, t_max) other than ``ignore_prim`` (-1: none)."""
    return bvh_ray_query(bvh, origin, direction, t_min, t_max, ignore_prim, 1)


@inline_func
def bvh_occluded(bvh: BvhView, origin: wp.vec3, direction: wp.vec3, t_max: float):
    """1 when some triangle lies on the ray with t in (0, t_max), else 0 (shadow rays)."""
    return wp.where(bvh_ray_query(bvh, origin, direction, 0.0, t_max, -1, 1).prim >= 0, 1, 0)


@inline_func
def bvh_occluded(  # noqa: F811  (a Warp overload, chosen by argument count)
    bvh: BvhView, origin: wp.vec3, direction: wp.vec3, t_min: float, t_max: float, ignore_prim: int
):
    """1 when a triangle other than ``ignore_prim`` (-1: none) lies on the ray with t in (t_min,
    t_max), else 0: a shadow ray from a surface point to a light, ``ignore_prim`` its triangle."""
    return wp.where(bvh_ray_query(bvh, origin, direction, t_min, t_max, ignore_prim, 1).prim >= 0, 1, 0)


@wp.func
def bvh_ray_all_hits(
    bvh: BvhView,
    origin: wp.vec3,
    direction: wp.vec3,
    t_min: float,
    t_max: float,
    ignore_prim: int,
    out_prim: wp.array(dtype=wp.int32),
    out_t: wp.array(dtype=float),
    offset: int,
    capacity: int,
):
    """Every triangle but ``ignore_prim`` (-1: none) hit with t in (t_min, t_max), in traversal
    order; returns how many.

    The first ``capacity`` hits go to ``out_prim`` / ``out_t`` from ``offset`` on: a count pass
    (capacity 0), a prefix sum, then a write pass gives each ray its own slice without atomics.
    """
    count = int(0)
    stack = vec64i()
    top = int(0)
    node = int(-1)
    inv = wp.vec3(0.0)
    scale = ray_direction_scale(direction)
    d = direction * scale
    low = ray_scaled_t_min(t_min, scale)
    limit = ray_scaled_t_max(t_max, scale)
    start = origin
    shift = wp.float64(0.0)
    range_min = low
    range_max = limit
    if bvh.faces.shape[0] > 0:
        ray = walk_start(origin, d, low, limit, bvh.node_lowers[0], bvh.node_uppers[0])
        start = ray.origin
        low = ray.t_min
        limit = ray.t_max
        shift = ray.shift
    wide = int(0)
    if bvh.faces.shape[0] > 0 and ray_is_valid(start, d, low, limit) == 1:
        inv = ray_inverse_direction(d)
        wide = ray_may_overflow(start, bvh.node_lowers[0], bvh.node_uppers[0])
        if ray_box_entry(start, inv, bvh.node_lowers[0], bvh.node_uppers[0], low, limit, wide) < INF:
            node = 0
    while node >= 0:
        left = bvh.node_left[node]
        if left < 0 or top >= STACK_SIZE - 1:
            for k in range(bvh.node_begin[node], bvh.node_end[node]):
                p = bvh.prim_order[k]
                h = bvh_triangle(bvh, p, start, d, low, limit)
                if h.hit == 1 and p != ignore_prim and far_hit_in_range(h.t, shift, range_min, range_max) == 1:
                    if count < capacity:
                        out_prim[offset + count] = p
                        out_t[offset + count] = float(wp.float64(h.t) + shift) * scale
                    count += 1
            node = -1
        else:
            right = bvh.node_right[node]
            node = -1
            if ray_box_entry(start, inv, bvh.node_lowers[left], bvh.node_uppers[left], low, limit, wide) < INF:
                stack[top] = left
                top += 1
            if ray_box_entry(start, inv, bvh.node_lowers[right], bvh.node_uppers[right], low, limit, wide) < INF:
                stack[top] = right
                top += 1
        if top > 0:
            top -= 1
            node = stack[top]
    return count


@wp.func
def bvh_ray_all_hits(  # noqa: F811  (a Warp overload, chosen by argument count)
    bvh: BvhView,
    origin: wp.vec3,
    direction: wp.vec3,
    t_max: float,
    out_prim: wp.array(dtype=wp.int32),
    out_t: wp.array(dtype=float),
    offset: int,
    capacity: int,
):
    """`bvh_ray_all_hits` over (0, t_max), every triangle counted."""
    return bvh_ray_all_hits(bvh, origin, direction, 0.0, t_max, -1, out_prim, out_t, offset, capacity)


@wp.func
def canonical_aabb_query(
    bvh: BvhView,
    lower: wp.vec3,
    upper: wp.vec3,
    query: int,
    after: int,
    out_pairs: wp.array(dtype=wp.vec2i),
    offset: int,
    capacity: int,
):
    """`bvh_aabb_query` over the canonical arrays (the BVHs over bare boxes have no packed layout)."""
    count = int(0)
    stack = vec64i()
    top = int(0)
    node = int(-1)
    if box_overlap(lower, upper, bvh.node_lowers[0], bvh.node_uppers[0]) == 1 and bvh.node_end[0] > after + 1:
        node = 0
    while node >= 0:
        left = bvh.node_left[node]
        # Both children may be pushed: keep two free slots, else test the node's whole range.
        if left < 0 or top >= STACK_SIZE - 1:
            for k in range(wp.max(bvh.node_begin[node], after + 1), bvh.node_end[node]):
                p = bvh.prim_order[k]
                if box_overlap(lower, upper, bvh.prim_lowers[p], bvh.prim_uppers[p]) == 1:
                    if count < capacity:
                        out_pairs[offset + count] = wp.vec2i(query, p)
                    count += 1
            node = -1
        else:
            right = bvh.node_right[node]
            node = -1
            if bvh.node_end[left] > after + 1:
                if box_overlap(lower, upper, bvh.node_lowers[left], bvh.node_uppers[left]) == 1:
                    stack[top] = left
                    top += 1
            if bvh.node_end[right] > after + 1:
                if box_overlap(lower, upper, bvh.node_lowers[right], bvh.node_uppers[right]) == 1:
                    stack[top] = right
                    top += 1
        if top > 0:
            top -= 1
            node = stack[top]
    return count


@wp.func
def packed_aabb_query(
    nodes: wp.array(dtype=PackedNode),
    triangles: wp.array(dtype=PackedTriangle),
    prim_order: wp.array(dtype=wp.int32),
    root_begin: int,
    root: int,
    lower: wp.vec3,
    upper: wp.vec3,
    query: int,
    after: int,
    out_pairs: wp.array(dtype=wp.vec2i),
    offset: int,
    capacity: int,
):
    """`bvh_aabb_query` over the packed layout of a mesh BVH: both children's boxes in one record,
    a leaf's triangles next to each other in tree order (their boxes taken from the vertices, as
    the build takes them). The caller has tested the root's box."""
    count = int(0)
    stack = vec64i()
    stack_begin = vec64i()
    top = int(0)
    node = root
    begin = root_begin
    active = int(1)
    while active == 1:
        if node >= 0 and top >= STACK_SIZE:
            # No room to defer a child: test the node's whole range as one leaf.
            full = nodes[node]
            node = -(full.count_a + full.count_b)
        if node < 0:
            for k in range(wp.max(begin, after + 1), begin - node):
                tri = triangles[k]
                tri_lower = wp.min(wp.min(tri.a, tri.b), tri.c)
                if box_overlap(lower, upper, tri_lower, wp.max(wp.max(tri.a, tri.b), tri.c)) == 1:
                    if count < capacity:
                        out_pairs[offset + count] = wp.vec2i(query, prim_order[k])
                    count += 1
            active = int(0)
        else:
            n = nodes[node]
            begin_b = begin + n.count_a
            # A child whose range ends at or before position `after` holds no partner.
            hit_a = begin_b > after + 1 and box_overlap(lower, upper, n.lower_a, n.upper_a) == 1
            hit_b = begin_b + n.count_b > after + 1 and box_overlap(lower, upper, n.lower_b, n.upper_b) == 1
            if hit_a and hit_b:
                stack[top] = n.child_b
                stack_begin[top] = begin_b
                top += 1
                node = n.child_a
            elif hit_a:
                node = n.child_a
            elif hit_b:
                node = n.child_b
                begin = begin_b
            else:
                active = int(0)
        if active == 0 and top > 0:
            top -= 1
            node = stack[top]
            begin = stack_begin[top]
            active = int(1)
    return count


@wp.func
def splits_prims(bvh: BvhView):
    """A spatial-split tree: more entries in ``prim_order`` than primitives (read from the arrays,
    so no flag of the view can disagree with the tree it describes)."""
    return bvh.prim_order.shape[0] != bvh.prim_lowers.shape[0]


@wp.func
def scan_aabb_query(
    bvh: BvhView,
    lower: wp.vec3,
    upper: wp.vec3,
    query: int,
    after: int,
    out_pairs: wp.array(dtype=wp.vec2i),
    offset: int,
    capacity: int,
):
    """`bvh_aabb_query` on a spatial-split tree: every primitive with an id above ``after``, each once.
    ``after`` is a primitive id here, not a position: such a tree lists a primitive at several
    positions, so the self-pair recipe of `bvh_aabb_query` (a thread per position) does not
    apply; a self query passes its primitive's id instead (the host's pair queries refuse
    these trees).

    Its node boxes bound the parts of triangles in their leaves (Stich et al. 2009), so a walk
    that prunes by them misses a triangle whose box meets the query outside those parts, and
    meets a split triangle once per part; no pruning is right here.
    """
    count = int(0)
    for p in range(wp.max(after + 1, 0), bvh.prim_lowers.shape[0]):
        if box_overlap(lower, upper, bvh.prim_lowers[p], bvh.prim_uppers[p]) == 1:
            if count < capacity:
                out_pairs[offset + count] = wp.vec2i(query, p)
            count += 1
    return count


@wp.func
def bvh_aabb_query(
    bvh: BvhView,
    lower: wp.vec3,
    upper: wp.vec3,
    query: int,
    after: int,
    out_pairs: wp.array(dtype=wp.vec2i),
    offset: int,
    capacity: int,
):
    """Every primitive at a position of ``prim_order`` above ``after`` whose box overlaps
    [lower, upper] (closed); returns how many.

    The first ``capacity`` of them are written as ``(query, prim)`` to ``out_pairs`` from
    ``offset`` on (pass capacity 0 to count only). Works for BVHs built from bare boxes too.
    ``after`` -1 keeps every primitive. A self query from the primitive at position k passes k:
    each pair of the tree's primitives is then found once, and a subtree whose range ends at or
    before k is skipped whole, about half the tree's nodes (Karras, HPG 2012, Sec. 4). On a
    spatial-split tree (`splits_prims`) ``after`` is a primitive id: see `scan_aabb_query`.
    """
    count = int(0)
    if splits_prims(bvh):
        count = scan_aabb_query(bvh, lower, upper, query, after, out_pairs, offset, capacity)
    elif bvh.packed_nodes.shape[0] > 0:
        root_begin = bvh.node_begin[0]
        if bvh.node_end[0] > after + 1 and box_overlap(lower, upper, bvh.node_lowers[0], bvh.node_uppers[0]) == 1:
            # The root's record is at position 0; a root that is a leaf has none.
            root = wp.where(bvh.node_left[0] < 0, root_begin - bvh.node_end[0], 0)
            count = packed_aabb_query(bvh.packed_nodes, bvh.packed_triangles, bvh.prim_order, root_begin, root,
                                      lower, upper, query, after, out_pairs, offset, capacity)
    else:
        count = canonical_aabb_query(bvh, lower, upper, query, after, out_pairs, offset, capacity)
    return count


@wp.func
def bvh_aabb_count(bvh: BvhView, lower: wp.vec3, upper: wp.vec3):
    """How many primitives have a box overlapping [lower, upper] (closed).

    On a spatial-split tree (`splits_prims`) every primitive is tested: see `scan_aabb_query`.
    """
    count = int(0)
    stack = vec64i()
    top = int(0)
    node = int(-1)
    if splits_prims(bvh):
        for p in range(bvh.prim_lowers.shape[0]):
            count += box_overlap(lower, upper, bvh.prim_lowers[p], bvh.prim_uppers[p])
    elif box_overlap(lower, upper, bvh.node_lowers[0], bvh.node_uppers[0]) == 1:
        node = 0
    while node >= 0:
        left = bvh.node_left[node]
        if left < 0 or top >= STACK_SIZE - 1:
            for k in range(bvh.node_begin[node], bvh.node_end[node]):
                p = bvh.prim_order[k]
                count += box_overlap(lower, upper, bvh.prim_lowers[p], bvh.prim_uppers[p])
            node = -1
        else:
            right = bvh.node_right[node]
            node = -1
            if box_overlap(lower, upper, bvh.node_lowers[left], bvh.node_uppers[left]) == 1:
                stack[top] = left
                top += 1
            if box_overlap(lower, upper, bvh.node_lowers[right], bvh.node_uppers[right]) == 1:
                stack[top] = right
                top += 1
        if top > 0:
            top -= 1
            node = stack[top]
    return count


@wp.func
def bvh_aabb_pairs(
    bvh: BvhView,
    lower: wp.vec3,
    upper: wp.vec3,
    query: int,
    pairs: wp.array(dtype=wp.vec2i),
    pair_count: wp.array(dtype=wp.int32),
):
    """Append ``(query, prim)`` for every overlapping primitive through an atomic counter.

    ``pair_count[0]`` ends as the number of pairs found by all threads; pairs beyond
    ``pairs.shape[0]`` are counted but not written, so a caller can detect overflow and rerun
    with a larger array. Returns this query's count. Pair order depends on thread scheduling.
    On a spatial-split tree (`splits_prims`) every primitive is tested: see `scan_aabb_query`.
    """
    count = int(0)
    stack = vec64i()
    top = int(0)
    node = int(-1)
    capacity = pairs.shape[0]
    if splits_prims(bvh):
        for p in range(bvh.prim_lowers.shape[0]):
            if box_overlap(lower, upper, bvh.prim_lowers[p], bvh.prim_uppers[p]) == 1:
                slot = wp.atomic_add(pair_count, 0, 1)
                if slot < capacity:
                    pairs[slot] = wp.vec2i(query, p)
                count += 1
    elif box_overlap(lower, upper, bvh.node_lowers[0], bvh.node_uppers[0]) == 1:
        node = 0
    while node >= 0:
        left = bvh.node_left[node]
        if left < 0 or top >= STACK_SIZE - 1:
            for k in range(bvh.node_begin[node], bvh.node_end[node]):
                p = bvh.prim_order[k]
                if box_overlap(lower, upper, bvh.prim_lowers[p], bvh.prim_uppers[p]) == 1:
                    slot = wp.atomic_add(pair_count, 0, 1)
                    if slot < capacity:
                        pairs[slot] = wp.vec2i(query, p)
                    count += 1
            node = -1
        else:
            right = bvh.node_right[node]
            node = -1
            if box_overlap(lower, upper, bvh.node_lowers[left], bvh.node_uppers[left]) == 1:
                stack[top] = left
                top += 1
            if box_overlap(lower, upper, bvh.node_lowers[right], bvh.node_uppers[right]) == 1:
                stack[top] = right
                top += 1
        if top > 0:
            top -= 1
            node = stack[top]
    return count


# ------------------------------------------------------------------ traversal layout
# Depth-first positions without a traversal. Call a node's child "first" when its range starts
# where the node's does, and let L(i) count the first-child steps on the path from the root to i.
# Then begin(i) + L(i) is the depth-first (pre-order) position of interior node i among interior
# nodes when leaves hold one primitive, and for any leaf sizes still distinct and below N - 1 (a
# subtree of k primitives holds at most k - 1 interior nodes): an N - 1 record array holds every
# tree over N primitives, and a node's first child is the very next record.


@wp.func
def packed_child_reference(node_left: wp.array(dtype=wp.int32), node_begin: wp.array(dtype=wp.int32),
                           node_end: wp.array(dtype=wp.int32), first_steps: wp.array(dtype=wp.int32), child: int):
    if node_left[child] < 0:
        return node_begin[child] - node_end[child]
    return node_begin[child] + first_steps[child]


@wp.func
def pack_node(
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    first_steps: wp.array(dtype=wp.int32),
    packed: wp.array(dtype=PackedNode),
    i: int,
):
    """Write interior node i's record at begin + L; L of its children must be known."""
    a = node_left[i]
    b = node_right[i]
    if node_begin[a] != node_begin[i]:
        tmp = a
        a = b
        b = tmp
    n = PackedNode()
    n.lower_a = node_lowers[a]
    n.upper_a = node_uppers[a]
    n.lower_b = node_lowers[b]
    n.upper_b = node_uppers[b]
    n.child_a = packed_child_reference(node_left, node_begin, node_end, first_steps, a)
    n.child_b = packed_child_reference(node_left, node_begin, node_end, first_steps, b)
    n.count_a = node_end[a] - node_begin[a]
    n.count_b = node_end[b] - node_begin[b]
    packed[node_begin[i] + first_steps[i]] = n


@wp.kernel
def pack_nodes_sweep_kernel(
    node_count: wp.array(dtype=wp.int32),
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    first_steps: wp.array(dtype=wp.int32),
    packed: wp.array(dtype=PackedNode),
):
    """All records in one thread, parents first (children are numbered after parents): L flows
    down in the same pass. For the CPU, where a thread per node costs more than the work."""
    first_steps[0] = 0
    for i in range(node_count[0]):
        left = node_left[i]
        if left >= 0:
            right = node_right[i]
            steps = first_steps[i]
            first_steps[left] = steps + wp.where(node_begin[left] == node_begin[i], 1, 0)
            first_steps[right] = steps + wp.where(node_begin[right] == node_begin[i], 1, 0)
            pack_node(node_lowers, node_uppers, node_left, node_right, node_begin, node_end, first_steps, packed, i)


@wp.kernel
def first_steps_climb_kernel(
    node_count: wp.array(dtype=wp.int32),
    node_parent: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    first_steps: wp.array(dtype=wp.int32),
):
    """L(i) with one thread per node climbing to the root: for devices with many threads."""
    i = wp.tid()
    if i >= node_count[0]:
        return
    steps = int(0)
    child = i
    parent = node_parent[i]
    while parent >= 0:
        if node_begin[child] == node_begin[parent]:
            steps += 1
        child = parent
        parent = node_parent[parent]
    first_steps[i] = steps


@wp.kernel
def pack_nodes_kernel(
    node_count: wp.array(dtype=wp.int32),
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    first_steps: wp.array(dtype=wp.int32),
    packed: wp.array(dtype=PackedNode),
):
    """One record per interior node, one thread each, after `first_steps_climb_kernel`."""
    i = wp.tid()
    if i < node_count[0] and node_left[i] >= 0:
        pack_node(node_lowers, node_uppers, node_left, node_right, node_begin, node_end, first_steps, packed, i)


@wp.kernel
def pack_triangles_kernel(
    prim_order: wp.array(dtype=wp.int32),
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.int32, ndim=2),
    packed: wp.array(dtype=PackedTriangle),
):
    k = wp.tid()
    p = prim_order[k]
    tri = PackedTriangle()
    tri.a = vertices[faces[p, 0]]
    tri.b = vertices[faces[p, 1]]
    tri.c = vertices[faces[p, 2]]
    packed[k] = tri


# ------------------------------------------------------------------ kernels of the host calls
@wp.kernel
def closest_hit_kernel(
    bvh: BvhView,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    t_max: float,
    hit_t: wp.array(dtype=float),
    hit_prim: wp.array(dtype=wp.int32),
):
    """One ray per thread, distance and triangle only.

    Kept apart from `closest_hit_details_kernel`: on the CPU every thread copies the kernel's
    arguments, and four unused output arrays cost coherent rays about a tenth of their time.
    """
    tid = wp.tid()
    h = bvh_closest_hit(bvh, origins[tid], directions[tid], t_max)
    hit_t[tid] = h.t
    hit_prim[tid] = h.prim


@wp.func
def query_limit(limits: wp.array(dtype=float), query: int):
    """``limits`` holds one limit for every query (shape 1) or one per query: a ray's ``t_max``,
    a point's ``max_dist``."""
    return limits[wp.where(limits.shape[0] == 1, 0, query)]


@wp.func
def query_limit(limits: float, query: int):  # noqa: F811  (a Warp overload, chosen by type)
    """One limit for every query, passed by value: the launch packs no array for it."""
    return limits


@wp.func
def query_limit(limits: int, query: int):  # noqa: F811  (a Warp overload, chosen by type)
    """An integer limit (a generic kernel launched with an int): the same limit as a float. Without
    it such a launch would fail to compile, and Warp would keep the failure for the whole module."""
    return float(limits)


@wp.func
def query_prim(prims: wp.array(dtype=wp.int32), query: int):
    """A query's primitive to ignore: none (-1) when ``prims`` is empty, else one for every query
    (shape 1) or one per query."""
    prim = int(-1)
    if prims.shape[0] > 0:
        prim = prims[wp.where(prims.shape[0] == 1, 0, query)]
    return prim


@wp.kernel
def closest_hit_details_kernel(
    bvh: BvhView,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    t_min: wp.array(dtype=float),
    t_max: wp.array(dtype=float),
    ignore_prim: wp.array(dtype=wp.int32),
    hit_t: wp.array(dtype=float),
    hit_prim: wp.array(dtype=wp.int32),
    hit_u: wp.array(dtype=float),
    hit_v: wp.array(dtype=float),
    nodes_visited: wp.array(dtype=wp.int32),
    prims_tested: wp.array(dtype=wp.int32),
):
    """One ray per thread, its range from `query_limit` and its ignored triangle from `query_prim`;
    ``hit_u``/``hit_v`` and the statistics are written when non-empty."""
    tid = wp.tid()
    h = bvh_closest_hit(bvh, origins[tid], directions[tid], query_limit(t_min, tid), query_limit(t_max, tid),
                        query_prim(ignore_prim, tid))
    hit_t[tid] = h.t
    hit_prim[tid] = h.prim
    if hit_u.shape[0] > 0:
        hit_u[tid] = h.u
        hit_v[tid] = h.v
    if nodes_visited.shape[0] > 0:
        nodes_visited[tid] = h.nodes_visited
        prims_tested[tid] = h.prims_tested


@wp.kernel
def occluded_kernel(
    bvh: BvhView,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    t_max: wp.array(dtype=float),
    occluded: wp.array(dtype=wp.int32),
    nodes_visited: wp.array(dtype=wp.int32),
    prims_tested: wp.array(dtype=wp.int32),
):
    """Shadow rays over (0, t_max), one limit or one per ray. Kept apart from
    `occluded_range_kernel` for the reason `closest_hit_kernel` is: short shadow rays cost a few
    nanoseconds each, and two more arrays copied per thread made them 30% slower."""
    tid = wp.tid()
    h = bvh_any_hit(bvh, origins[tid], directions[tid], query_limit(t_max, tid))
    occluded[tid] = wp.where(h.prim >= 0, 1, 0)
    if nodes_visited.shape[0] > 0:
        nodes_visited[tid] = h.nodes_visited
        prims_tested[tid] = h.prims_tested


@wp.kernel
def occluded_range_kernel(
    bvh: BvhView,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    t_min: wp.array(dtype=float),
    t_max: wp.array(dtype=float),
    ignore_prim: wp.array(dtype=wp.int32),
    occluded: wp.array(dtype=wp.int32),
    nodes_visited: wp.array(dtype=wp.int32),
    prims_tested: wp.array(dtype=wp.int32),
):
    """`occluded_kernel` with each ray's near end and ignored triangle (`query_limit`, `query_prim`)."""
    tid = wp.tid()
    h = bvh_any_hit(bvh, origins[tid], directions[tid], query_limit(t_min, tid), query_limit(t_max, tid),
                    query_prim(ignore_prim, tid))
    occluded[tid] = wp.where(h.prim >= 0, 1, 0)
    if nodes_visited.shape[0] > 0:
        nodes_visited[tid] = h.nodes_visited
        prims_tested[tid] = h.prims_tested


@wp.kernel
def all_hits_kernel(
    bvh: BvhView,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    t_min: wp.array(dtype=float),
    t_max: wp.array(dtype=float),
    ignore_prim: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
    out_prim: wp.array(dtype=wp.int32),
    out_t: wp.array(dtype=float),
):
    """Count pass when ``out_prim`` is empty (writes ``counts``), else write pass at ``offsets``;
    the ray's range from `query_limit`, its ignored triangle from `query_prim`."""
    tid = wp.tid()
    low = query_limit(t_min, tid)
    limit = query_limit(t_max, tid)
    skip = query_prim(ignore_prim, tid)
    if out_prim.shape[0] == 0:
        counts[tid] = bvh_ray_all_hits(bvh, origins[tid], directions[tid], low, limit, skip, out_prim, out_t, 0, 0)
    else:
        bvh_ray_all_hits(bvh, origins[tid], directions[tid], low, limit, skip, out_prim, out_t, offsets[tid],
                         counts[tid])


@wp.kernel
def aabb_query_kernel(
    bvh: BvhView,
    lowers: wp.array(dtype=wp.vec3),
    uppers: wp.array(dtype=wp.vec3),
    order: wp.array(dtype=wp.int32),
    self_pairs: int,
    offsets: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
    out_pairs: wp.array(dtype=wp.vec2i),
):
    """Count pass when ``out_pairs`` is empty (writes ``counts``), else write pass at ``offsets``.

    Thread k queries box ``order[k]`` (box k when ``order`` is empty): a BVH's ``prim_order`` walks
    its primitives in tree order, where consecutive queries visit nearly the same nodes. With
    ``self_pairs`` 1 the queries are the tree's own primitives in its order: thread k keeps
    partners at later positions only, so each pair comes once, in either order.
    """
    tid = wp.tid()
    query = tid
    if order.shape[0] > 0:
        query = order[tid]
    after = int(-1)
    if self_pairs == 1:
        after = tid
    if out_pairs.shape[0] == 0:
        counts[tid] = bvh_aabb_query(bvh, lowers[query], uppers[query], query, after, out_pairs, 0, 0)
    else:
        bvh_aabb_query(bvh, lowers[query], uppers[query], query, after, out_pairs, offsets[tid], counts[tid])


@wp.kernel
def warp_mesh_closest_hit_kernel(
    mesh: wp.uint64,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    hit_t: wp.array(dtype=float),
    hit_prim: wp.array(dtype=wp.int32),
):
    """The benchmark's reference: Warp's own mesh BVH and ``wp.mesh_query_ray``, one ray per thread."""
    tid = wp.tid()
    q = wp.mesh_query_ray(mesh, origins[tid], directions[tid], 1.0e30)
    if q.result:
        hit_t[tid] = q.t
        hit_prim[tid] = q.face
    else:
        hit_t[tid] = INF
        hit_prim[tid] = -1
