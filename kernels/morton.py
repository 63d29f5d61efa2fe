"""Stages 1-2 of HLBVH: primitive bounds, scene centroid bounds, Morton codes.

Pantaleoni & Luebke, "HLBVH: Hierarchical LBVH Construction for Real-Time Ray Tracing of
Dynamic Geometry", HPG 2010, sections 2.1 and 3.1 (Morton codes as in LBVH, Lauterbach et al. 2009).
"""

import warp as wp

# Forward-only kernels: no adjoints to compile.
wp.set_module_options({"enable_backward": False})


@wp.kernel
def triangle_bounds_kernel(
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.int32, ndim=2),
    prim_lowers: wp.array(dtype=wp.vec3),
    prim_uppers: wp.array(dtype=wp.vec3),
):
    """Box of triangle tid from its three vertices into prim_lowers/uppers[tid]."""
    tid = wp.tid()
    a = vertices[faces[tid, 0]]
    b = vertices[faces[tid, 1]]
    c = vertices[faces[tid, 2]]
    prim_lowers[tid] = wp.min(wp.min(a, b), c)
    prim_uppers[tid] = wp.max(wp.max(a, b), c)


@wp.kernel
def triangle_bounds_centroids_kernel(
    num_prims: int,
    chunk: int,
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.int32, ndim=2),
    prim_lowers: wp.array(dtype=wp.vec3),
    prim_uppers: wp.array(dtype=wp.vec3),
    scene_bounds: wp.array(dtype=wp.vec3),
):
    """Triangle boxes, and the scene's centroid bounds reduced from them in the same pass."""
    # triangle_bounds_kernel and centroid_bounds_kernel in one pass (chunked like the latter), for
    # per-frame builds from vertices: the reduction reads the boxes while they are in registers
    # instead of in a second pass over 24 bytes per triangle.
    begin = wp.tid() * chunk
    end = wp.min(begin + chunk, num_prims)
    if begin >= end:
        return
    big = 3.4e38
    lower = wp.vec3(big, big, big)
    upper = wp.vec3(-big, -big, -big)
    for i in range(begin, end):
        a = vertices[faces[i, 0]]
        b = vertices[faces[i, 1]]
        c = vertices[faces[i, 2]]
        box_lower = wp.min(wp.min(a, b), c)
        box_upper = wp.max(wp.max(a, b), c)
        prim_lowers[i] = box_lower
        prim_uppers[i] = box_upper
        centroid = 0.5 * (box_lower + box_upper)
        lower = wp.min(lower, centroid)
        upper = wp.max(upper, centroid)
    wp.atomic_min(scene_bounds, 0, lower)
    wp.atomic_max(scene_bounds, 1, upper)


@wp.kernel
def reset_bounds_kernel(scene_bounds: wp.array(dtype=wp.vec3)):
    """Empty the scene bounds (inverted at +-3.4e38) before the atomic min/max reduction."""
    # scene_bounds[0] is the lower corner, scene_bounds[1] the upper corner.
    big = 3.4e38
    scene_bounds[0] = wp.vec3(big, big, big)
    scene_bounds[1] = wp.vec3(-big, -big, -big)


@wp.kernel
def set_bounds_kernel(scene_bounds: wp.array(dtype=wp.vec3), lower: wp.vec3, upper: wp.vec3):
    """A fixed Morton grid (``BuildConfig.morton_bounds``) in place of the centroid bounds."""
    scene_bounds[0] = lower
    scene_bounds[1] = upper


@wp.kernel
def centroid_bounds_kernel(
    num_prims: int,
    chunk: int,
    prim_lowers: wp.array(dtype=wp.vec3),
    prim_uppers: wp.array(dtype=wp.vec3),
    scene_bounds: wp.array(dtype=wp.vec3),
):
    """The scene's centroid bounds, the box the Morton grid is laid over: the min and max of the
    primitive centroids into scene_bounds[0] and [1]."""
    # Thread t reduces primitives [t * chunk, (t + 1) * chunk) and publishes with one atomic per
    # corner: chunk 1 on CUDA (one thread per primitive); on the CPU, whose launches run threads
    # in sequence, long chunks save the per-primitive atomics.
    begin = wp.tid() * chunk
    end = wp.min(begin + chunk, num_prims)
    if begin >= end:
        return
    lower = 0.5 * (prim_lowers[begin] + prim_uppers[begin])
    upper = lower
    for i in range(begin + 1, end):
        c = 0.5 * (prim_lowers[i] + prim_uppers[i])
        lower = wp.min(lower, c)
        upper = wp.max(upper, c)
    wp.atomic_min(scene_bounds, 0, lower)
    wp.atomic_max(scene_bounds, 1, upper)


@wp.func
def spread_bits_10(x: wp.int32):
    """Spread the 10 low bits of x to every third bit: one axis of a 30-bit Morton code (Morton 1966)."""
    # Insert two zero bits between each of the 10 low bits of x:
    #   ---- ---- ---- ---- ---- --98 7654 3210
    # -> ---- 9--8 --7- -6-- 5--4 --3- -2-- 1--0
    v = x & 0x3FF
    v = (v | (v << 16)) & 0x030000FF
    v = (v | (v << 8)) & 0x0300F00F
    v = (v | (v << 4)) & 0x030C30C3
    v = (v | (v << 2)) & 0x09249249
    return v


@wp.func
def quantize(c: float, lo: float, hi: float, cells: int):
    """The cell of coordinate c among `cells` equal cells over [lo, hi], clamped to [0, cells - 1]."""
    # Quantize in float64: at 1e18 the float32 product (c - lo) * scale loses the cell index.
    extent = wp.float64(hi) - wp.float64(lo)
    q = int(0)
    if extent > wp.float64(0.0):
        x = (wp.float64(c) - wp.float64(lo)) / extent * wp.float64(cells)
        # Clamped before the conversion: a centroid millions of cells outside a fixed grid
        # (`BuildConfig.morton_bounds`) is past int32, where the conversion is undefined (INT_MIN
        # on x86, clamped to cell 0, not the border cell); a NaN takes cell 0.
        if x >= wp.float64(cells - 1):
            q = cells - 1
        elif x > wp.float64(0.0):
            q = int(x)
    return q


@wp.func
def morton_code(lower: wp.vec3, upper: wp.vec3, scene_lower: wp.vec3, scene_upper: wp.vec3, bits_per_axis: int):
    """The 3n-bit Morton code (Morton 1966) of a box's centroid on the grid of 2^n cells per axis over the
    scene box, n = `bits_per_axis`, as LBVH (Lauterbach et al. 2009) and HLBVH (Pantaleoni & Luebke 2010,
    sections 2.1 and 3.1) order primitives."""
    c = 0.5 * (lower + upper)
    cells = 1 << bits_per_axis
    x = quantize(c[0], scene_lower[0], scene_upper[0], cells)
    y = quantize(c[1], scene_lower[1], scene_upper[1], cells)
    z = quantize(c[2], scene_lower[2], scene_upper[2], cells)
    # x takes the most significant bit of each triple: code = ... x1 y1 z1 x0 y0 z0.
    return (spread_bits_10(x) << 2) | (spread_bits_10(y) << 1) | spread_bits_10(z)


@wp.kernel
def morton_codes_kernel(
    prim_lowers: wp.array(dtype=wp.vec3),
    prim_uppers: wp.array(dtype=wp.vec3),
    scene_bounds: wp.array(dtype=wp.vec3),
    bits_per_axis: int,
    morton_codes: wp.array(dtype=wp.int32),
):
    """Morton code (Morton 1966) of every primitive's centroid, as in LBVH (Lauterbach et al. 2009):
    the first foreach of Pantaleoni & Luebke 2010, Fig. 1 (``codes[i] = morton_code(prim[i], n)``)."""
    tid = wp.tid()
    morton_codes[tid] = morton_code(prim_lowers[tid], prim_uppers[tid], scene_bounds[0], scene_bounds[1], bits_per_axis)


@wp.kernel
def coarse_codes_kernel(morton_codes: wp.array(dtype=wp.int32), shift: int, coarse_codes: wp.array(dtype=wp.int32)):
    """The high 3m bits of every code (``shift`` = 3(n - m)), the keys of the run-length encoding
    (Pantaleoni & Luebke 2010, Fig. 1: ``codes[i] >> d``)."""
    tid = wp.tid()
    coarse_codes[tid] = morton_codes[tid] >> shift
