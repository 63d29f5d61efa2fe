"""Stages 1-2 of HLBVH: primitive bounds, scene centroid bounds, Morton codes.

Pantaleoni & Luebke, "HLBVH: Hierarchical LBVH Construction for Real-Time Ray Tracing of
Dynamic Geometry", HPG 2010, sections 2.1 and 3.1 (Morton codes as in LBVH, Lauterbach et al. 2009).
"""

import numpy as np
import warp as wp

# Forward-only kernels: no adjoints to compile.
wp.set_module_options({"enable_backward": False})

# The empty box's corners for the min / max reductions: float32's largest finite value. At 3.4e38
# the bounds of centroids past it (up to 3.4028e38, finite input the checks accept) kept the
# sentinel as a corner, a grid wider than the centroids.
FLOAT32_MAX = wp.constant(3.4028234663852886e38)


@wp.func
def box_centroid(lower: wp.vec3, upper: wp.vec3):
    """The centre of the box [lower, upper]: 0.5 * (lower + upper), without overflow."""
    c = 0.5 * (lower + upper)
    # The sum overflows to inf past 1.7e38 (finite input the checks accept), which put every
    # centroid in one Morton cell. There the halves are exact (at least 2^126: not subnormal)
    # and their sum is rounded once, the correctly rounded centre; an infinite or NaN input
    # gives what it always did. Axis by axis: the halves of a subnormal lose a bit, so the other
    # axes keep the plain expression's bits. (The CPU's own kernels keep the plain expression
    # and leave the rare overflow to the host: `HlbvhPipeline.compute_morton_codes`.)
    for k in range(3):
        if wp.abs(c[k]) > FLOAT32_MAX:
            c[k] = 0.5 * lower[k] + 0.5 * upper[k]
    return c


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
    big = FLOAT32_MAX
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
        centroid = box_centroid(box_lower, box_upper)
        lower = wp.min(lower, centroid)
        upper = wp.max(upper, centroid)
    wp.atomic_min(scene_bounds, 0, lower)
    wp.atomic_max(scene_bounds, 1, upper)


@wp.func
def min_of_ordered(m: wp.vec3, v: wp.vec3):
    """wp.min(m, v) on the CPU for an m with no NaN component, by one comparison per component."""
    # The CPU's wp.min(m, v) is (m <= v ? m : (v == v ? v : m)) per component: for m not NaN that
    # is (v < m ? v : m), signed zeros included (a tie keeps m), and a NaN v gives m. One
    # instruction where the NaN test takes three or four. CUDA's wp.min is fminf, whose choice
    # between +0 and -0 this need not match: CUDA kernels keep wp.min.
    return wp.vec3(wp.where(v[0] < m[0], v[0], m[0]), wp.where(v[1] < m[1], v[1], m[1]),
                   wp.where(v[2] < m[2], v[2], m[2]))


@wp.func
def max_of_ordered(m: wp.vec3, v: wp.vec3):
    """wp.max(m, v) on the CPU for an m with no NaN component (`min_of_ordered`)."""
    return wp.vec3(wp.where(v[0] > m[0], v[0], m[0]), wp.where(v[1] > m[1], v[1], m[1]),
                   wp.where(v[2] > m[2], v[2], m[2]))


@wp.func
def triangle_box_cpu(a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """The box of triangle (a, b, c) on the CPU: the bits of wp.min(wp.min(a, b), c) and
    wp.max(wp.max(a, b), c)."""
    # When a has no NaN, neither has wp.min(a, b), so both steps of the chain may drop their NaN
    # test (min_of_ordered); a vertex with a NaN (a broken mesh) takes wp.min's chain. The NaN
    # tests were 0.2 of the 0.56 ms the boxes took on the 100k-triangle armadillo (one core).
    if a == a:
        return min_of_ordered(min_of_ordered(a, b), c), max_of_ordered(max_of_ordered(a, b), c)
    return wp.min(wp.min(a, b), c), wp.max(wp.max(a, b), c)


@wp.kernel
def triangle_bounds_cpu_kernel(
    num_prims: int,
    chunk: int,
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.int32, ndim=2),
    prim_lowers: wp.array(dtype=wp.vec3),
    prim_uppers: wp.array(dtype=wp.vec3),
):
    """`triangle_bounds_kernel` for the CPU device, `chunk` triangles per thread, with the same
    boxes to the bit (`triangle_box_cpu`): a refit's boxes, or a fixed grid's."""
    begin = wp.tid() * chunk
    end = wp.min(begin + chunk, num_prims)
    for i in range(begin, end):
        box_lower, box_upper = triangle_box_cpu(vertices[faces[i, 0]], vertices[faces[i, 1]], vertices[faces[i, 2]])
        prim_lowers[i] = box_lower
        prim_uppers[i] = box_upper


@wp.kernel
def triangle_bounds_centroids_cpu_kernel(
    num_prims: int,
    chunk: int,
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.int32, ndim=2),
    prim_lowers: wp.array(dtype=wp.vec3),
    prim_uppers: wp.array(dtype=wp.vec3),
    scene_bounds: wp.array(dtype=wp.vec3),
):
    """`triangle_bounds_centroids_kernel` for the CPU device, with the same results to the bit."""
    # 0.53 against 0.83 ms on the armadillo, the two kernels side by side in one process.
    begin = wp.tid() * chunk
    end = wp.min(begin + chunk, num_prims)
    if begin >= end:
        return
    big = FLOAT32_MAX
    lower = wp.vec3(big, big, big)
    upper = wp.vec3(-big, -big, -big)
    for i in range(begin, end):
        box_lower, box_upper = triangle_box_cpu(vertices[faces[i, 0]], vertices[faces[i, 1]], vertices[faces[i, 2]])
        prim_lowers[i] = box_lower
        prim_uppers[i] = box_upper
        # The plain centre: where it overflows (past 1.7e38) the bounds come out past 2^127 and
        # the host reduces them again with `box_centroid` (`HlbvhPipeline.compute_triangle_bounds`);
        # its test here cost 0.1 ms of 0.5 on 100k triangles.
        centroid = 0.5 * (box_lower + box_upper)
        # lower and upper start finite and only ever take a centroid that is not NaN.
        lower = min_of_ordered(lower, centroid)
        upper = max_of_ordered(upper, centroid)
    wp.atomic_min(scene_bounds, 0, lower)
    wp.atomic_max(scene_bounds, 1, upper)


@wp.kernel
def reset_bounds_kernel(scene_bounds: wp.array(dtype=wp.vec3)):
    """Empty the scene bounds (inverted at +-FLOAT32_MAX) before the atomic min/max reduction."""
    # scene_bounds[0] is the lower corner, scene_bounds[1] the upper corner.
    big = FLOAT32_MAX
    scene_bounds[0] = wp.vec3(big, big, big)
    scene_bounds[1] = wp.vec3(-big, -big, -big)


@wp.kernel
def set_bounds_kernel(scene_bounds: wp.array(dtype=wp.vec3), lower: wp.vec3, upper: wp.vec3):
    """A fixed Morton grid (``BuildConfig.morton_bounds``) in place of the centroid bounds."""
    scene_bounds[0] = lower
    scene_bounds[1] = upper


@wp.kernel
def reset_partial_bounds_kernel(partials: wp.array(dtype=wp.vec3)):
    """Empty bounds t (partials[2t] and [2t + 1]) as `reset_bounds_kernel` does, one per thread."""
    t = wp.tid()
    big = FLOAT32_MAX
    partials[2 * t] = wp.vec3(big, big, big)
    partials[2 * t + 1] = wp.vec3(-big, -big, -big)


@wp.kernel
def combine_bounds_kernel(partials: wp.array(dtype=wp.vec3), count: int, scene_bounds: wp.array(dtype=wp.vec3)):
    """scene_bounds = the union of the first `count` partial bounds, in their order."""
    # In order, each a wp.min / wp.max that keeps the value it has on a tie, as the serial
    # reduction's atomics do over the chunks: the same bits, the sign of a zero included.
    lower = partials[0]
    upper = partials[1]
    for j in range(1, count):
        lower = wp.min(lower, partials[2 * j])
        upper = wp.max(upper, partials[2 * j + 1])
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
    lower = box_centroid(prim_lowers[begin], prim_uppers[begin])
    upper = lower
    for i in range(begin + 1, end):
        c = box_centroid(prim_lowers[i], prim_uppers[i])
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
    c = box_centroid(lower, upper)
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


def spread_table_values() -> np.ndarray:
    """`spread_bits_10` of every 10-bit value, computed on the host: the table of
    `morton_codes_cpu_kernel` (Morton 1966)."""
    values = np.arange(1024, dtype=np.int64)
    table = np.zeros(1024, dtype=np.int64)
    for bit in range(10):
        table |= ((values >> bit) & 1) << (3 * bit)
    return table.astype(np.int32)


_SPREAD_TABLES: dict = {}


def spread_table(device) -> wp.array:
    """`spread_table_values` on `device`, made once per device (4 KB)."""
    device = wp.get_device(device)
    table = _SPREAD_TABLES.get(device.alias)
    if table is None:
        table = _SPREAD_TABLES[device.alias] = wp.array(spread_table_values(), dtype=wp.int32, device=device)
    return table


@wp.kernel
def morton_codes_cpu_kernel(
    num_prims: int,
    chunk: int,
    prim_lowers: wp.array(dtype=wp.vec3),
    prim_uppers: wp.array(dtype=wp.vec3),
    scene_bounds: wp.array(dtype=wp.vec3),
    bits_per_axis: int,
    spread: wp.array(dtype=wp.int32),
    morton_codes: wp.array(dtype=wp.int32),
):
    """`morton_codes_kernel` (Morton 1966; Pantaleoni & Luebke 2010, Fig. 1) for the CPU device,
    `chunk` primitives per thread, with the same codes to the bit; `spread` is `spread_table`."""
    # On the CPU spread_bits_10's shifts and masks were half the kernel's time (0.45 of 1.2 ms
    # on 100k boxes): its table, read from the L1 cache, takes three loads. A thread per chunk
    # lets the compiler keep the grid's extents and `cells` out of the loop. Together 1.6x as
    # fast; the three float64 divisions, which bound what is left, stay as `quantize` does them.
    begin = wp.tid() * chunk
    end = wp.min(begin + chunk, num_prims)
    cells = 1 << bits_per_axis
    scene_lower = scene_bounds[0]
    scene_upper = scene_bounds[1]
    for i in range(begin, end):
        # The plain centre: the host takes `morton_codes_kernel` (with `box_centroid`) instead
        # wherever a centre could overflow (`HlbvhPipeline.compute_morton_codes`).
        c = 0.5 * (prim_lowers[i] + prim_uppers[i])
        x = quantize(c[0], scene_lower[0], scene_upper[0], cells)
        y = quantize(c[1], scene_lower[1], scene_upper[1], cells)
        z = quantize(c[2], scene_lower[2], scene_upper[2], cells)
        morton_codes[i] = (spread[x & 0x3FF] << 2) | (spread[y & 0x3FF] << 1) | spread[z & 0x3FF]


@wp.kernel
def coarse_codes_kernel(morton_codes: wp.array(dtype=wp.int32), shift: int, coarse_codes: wp.array(dtype=wp.int32)):
    """The high 3m bits of every code (``shift`` = 3(n - m)), the keys of the run-length encoding
    (Pantaleoni & Luebke 2010, Fig. 1: ``codes[i] >> d``)."""
    tid = wp.tid()
    coarse_codes[tid] = morton_codes[tid] >> shift
