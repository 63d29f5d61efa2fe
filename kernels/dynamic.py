"""Device code for dynamic scenes: per-frame deformations, resorting, motion and SAH measures.

Pantaleoni & Luebke 2010, section 2.2: a dynamic scene is rebuilt every frame, and feeding the
primitives in the previous frame's BVH order (resorting) makes the next build's input almost
sorted. The host side (``hlbvh_warp.builder``, ``hlbvh_warp.dynamic``) allocates and launches.
"""

import warp as wp

from .morton import morton_code

# Forward-only kernels: no adjoints to compile.
wp.set_module_options({"enable_backward": False})

# A NaN coordinate's move, squared: its square root is infinite as a float32, the largest move.
NAN_MOVE_SQ = wp.constant(1.0e300)
# The smallest float32 above zero: a move that rounds below it still counts as a move.
SMALLEST_MOVE = wp.constant(1.0e-45)


# ------------------------------------------------------------------ resorting
@wp.kernel
def resort_gather_kernel(
    prim_order: wp.array(dtype=wp.int32),
    user_codes: wp.array(dtype=wp.int32),
    input_order: wp.array(dtype=wp.int32),
    morton_codes: wp.array(dtype=wp.int32),
):
    """Resorting (Pantaleoni & Luebke 2010, section 2.2): the previous tree's order becomes the
    build's input order; input i is user face prim_order[i], and its Morton code is gathered."""
    # Only the 4-byte Morton code is gathered; the sort carries the face id along
    # (input_order, the pipeline's input ids), so the tree names user faces and reads the boxes
    # where they were computed, in the user's order. Gathering the 24-byte boxes as well, and
    # mapping the tree's ids back afterwards, cost two random reads per primitive instead of one
    # small one (about 2 ms more of a 19 ms frame for the exploding 100k-triangle armadillo on
    # the CPU).
    i = wp.tid()
    f = prim_order[i]
    input_order[i] = f
    morton_codes[i] = user_codes[f]


@wp.kernel
def resort_gather_compare_kernel(
    prim_order: wp.array(dtype=wp.int32),
    user_codes: wp.array(dtype=wp.int32),
    last_codes: wp.array(dtype=wp.int32),
    input_order: wp.array(dtype=wp.int32),
    morton_codes: wp.array(dtype=wp.int32),
    changed: wp.array(dtype=wp.int32),
):
    """`resort_gather_kernel`, and changed[0] = 1 where a gathered code differs from the last
    tree's sorted code at its position (`last_codes`, the previous build's sort output).

    No code differs: the input is the last tree's order with the last tree's codes, so it is
    sorted already, a stable sort leaves it as it is, and the emission (a function of the sorted
    codes alone, Pantaleoni & Luebke 2010, section 3.2) would make the last tree's topology again.
    The caller then keeps that topology and recomputes the boxes only. That happens when nothing
    moved across a Morton cell, such as a mesh at rest or a whole scene translated or scaled,
    since the grid spans each frame's centroid bounds."""
    # The compare reads last_codes in order, next to the gather's one random read; a moving
    # frame's differences only set the flag (one value, so concurrent writes agree).
    i = wp.tid()
    f = prim_order[i]
    code = user_codes[f]
    input_order[i] = f
    morton_codes[i] = code
    if code != last_codes[i]:
        changed[0] = 1


@wp.kernel
def sample_run_breaks_kernel(
    prim_order: wp.array(dtype=wp.int32),
    prim_lowers: wp.array(dtype=wp.vec3),
    prim_uppers: wp.array(dtype=wp.vec3),
    scene_bounds: wp.array(dtype=wp.vec3),
    bits_per_axis: int,
    num_prims: int,
    num_samples: int,
    shift: int,
    breaks: wp.array(dtype=wp.int32),
):
    """How well resorting (Pantaleoni & Luebke 2010, section 2.2) would compress, sampled: over
    `num_samples` evenly spaced adjacent pairs of the previous tree's order, breaks[0] counts the pairs in
    two coarse voxels (an estimate of the run-length encoding's M / N) and breaks[1] the pairs whose
    codes descend."""
    # A pair in two coarse voxels starts a run. No descending pair: the order may be sorted
    # already, which the build then skips. The two codes are computed from the boxes here, so the
    # decision comes before any pass over all the codes.
    t = wp.tid()
    i = wp.int32(wp.int64(1) + wp.int64(t) * wp.int64(num_prims - 1) // wp.int64(num_samples))
    f = prim_order[i - 1]
    g = prim_order[i]
    lo = scene_bounds[0]
    hi = scene_bounds[1]
    a = morton_code(prim_lowers[f], prim_uppers[f], lo, hi, bits_per_axis)
    b = morton_code(prim_lowers[g], prim_uppers[g], lo, hi, bits_per_axis)
    if (a >> shift) != (b >> shift):
        wp.atomic_add(breaks, 0, 1)
    if b < a:
        wp.atomic_add(breaks, 1, 1)


# --------------------------------------------------------- motion and quality
@wp.kernel
def round_to_float32_kernel(source: wp.array(dtype=wp.vec3d), dest: wp.array(dtype=wp.vec3)):
    """A float64 frame given on the builder's device, rounded into its float32 buffer."""
    i = wp.tid()
    dest[i] = wp.vec3(source[i])


@wp.kernel
def reset_stats_kernel(stats: wp.array(dtype=wp.float64)):
    """Zero stats[0] (the largest move) and stats[1] (the root's diagonal)."""
    stats[0] = wp.float64(0.0)
    stats[1] = wp.float64(0.0)


@wp.kernel
def load_and_measure_kernel(
    num_vertices: int,
    chunk: int,
    first_chunk: int,
    source: wp.array(dtype=wp.vec3),
    dest: wp.array(dtype=wp.vec3),
    largest_move: wp.array(dtype=wp.float32),
):
    """Load a frame's vertices and measure how far they moved: largest_move[0] = max |source - dest|
    (a NaN coordinate counts as an infinite move), then dest = source."""
    # One pass: copying the last frame aside and comparing afterwards took three passes over the
    # vertices (about 2.6 ms a frame for the 300k vertices of the exploding armadillo on the CPU).
    # A thread takes a chunk and does one square root and one atomic, not one per vertex. Launches from
    # different `first_chunk`s, each with its own `largest_move`, run side by side on a
    # multi-core CPU.
    c = wp.tid() + first_chunk
    begin = c * chunk
    end = wp.min(begin + chunk, num_vertices)
    largest = wp.float64(0.0)
    for i in range(begin, end):
        p = source[i]
        # In float64, where a difference of float32 values is exact and its square neither
        # overflows (coordinates near 1e20 square past float32's range) nor underflows (a move of
        # 1e-23 squares to zero in float32): the measure holds at every scene scale.
        d = wp.vec3d(p) - wp.vec3d(dest[i])
        d2 = wp.dot(d, d)
        # A comparison, not wp.max, whose NaN handling doubled the kernel's time on the CPU (2.1
        # against 1.3 ms for the 300k vertices of the exploding armadillo, one core): a NaN d2
        # fails it too and is then replaced, so the result is the same maximum.
        if not (d2 <= largest):
            largest = d2
            if d2 != d2:
                largest = wp.float64(NAN_MOVE_SQ)
        dest[i] = p
    if largest > wp.float64(0.0):
        # Rounded up to float32 as a length: a move is never reported as none.
        wp.atomic_max(largest_move, 0, wp.max(float(wp.sqrt(largest)), SMALLEST_MOVE))


@wp.kernel
def sample_changes_kernel(
    num_vertices: int,
    num_samples: int,
    source: wp.array(dtype=wp.vec3),
    dest: wp.array(dtype=wp.vec3),
    changed: wp.array(dtype=wp.int32),
):
    """changed[0] = 1 if one of `num_samples` evenly spaced vertices of source differs from dest
    (as `load_and_compare_kernel` tells it); nothing is loaded."""
    t = wp.tid()
    i = wp.int32(wp.int64(t) * wp.int64(num_vertices) // wp.int64(num_samples))
    d = source[i] - dest[i]
    if wp.abs(d[0]) + wp.abs(d[1]) + wp.abs(d[2]) != 0.0:
        changed[0] = 1


@wp.kernel
def load_and_compare_kernel(
    num_vertices: int,
    chunk: int,
    first_chunk: int,
    source: wp.array(dtype=wp.vec3),
    dest: wp.array(dtype=wp.vec3),
    changed: wp.array(dtype=wp.int32),
):
    """Load a frame's vertices and tell whether any moved: changed[0] = 1 if some vertex of source
    differs from dest (a NaN or infinite coordinate counts as a change), then dest = source."""
    # For the auto policy's chaotic wait, which rebuilds any frame that moved however far: whether,
    # not how far. The sum of |source - dest| in float32 is zero exactly when every coordinate
    # is equal (the difference of two different float32 values is never zero, gradual underflow
    # keeping the tiny ones), and it takes about 0.8 of the float64 measure's time on the CPU.
    c = wp.tid() + first_chunk
    begin = c * chunk
    end = wp.min(begin + chunk, num_vertices)
    total = float(0.0)
    for i in range(begin, end):
        p = source[i]
        d = p - dest[i]
        total = total + wp.abs(d[0]) + wp.abs(d[1]) + wp.abs(d[2])
        dest[i] = p
    if total != 0.0:
        changed[0] = 1


@wp.kernel
def finish_motion_kernel(largest_move: wp.array(dtype=wp.float32), count: int, stats: wp.array(dtype=wp.float64)):
    """stats[0]: the largest displacement over the `count` partial maxima of the measure."""
    largest = float(0.0)
    for j in range(count):
        largest = wp.max(largest, largest_move[j])
    stats[0] = wp.float64(largest)


@wp.kernel
def root_diagonal_kernel(
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
    stats: wp.array(dtype=wp.float64),
):
    """stats[1]: the length of the root box's diagonal, the scale a frame's motion is measured against."""
    stats[1] = wp.length(wp.vec3d(node_uppers[0]) - wp.vec3d(node_lowers[0]))


# --------------------------------------------------------------- deformations
@wp.kernel
def explode_kernel(
    centroids: wp.array(dtype=wp.vec3),
    offsets: wp.array(dtype=wp.vec3),
    velocities: wp.array(dtype=wp.vec3),
    axes: wp.array(dtype=wp.vec3),
    spins: wp.array(dtype=float),
    time: float,
    vertices: wp.array(dtype=wp.vec3),
):
    """One frame of an exploding mesh (after the Exploding Turbine Blade of Pantaleoni & Luebke 2010,
    section 4, Fig. 7): every triangle's centroid flies with its velocity and its corners spin."""
    # Triangle tid owns vertices 3 tid .. 3 tid + 2: its centroid flies, its corners spin.
    tid = wp.tid()
    q = wp.quat_from_axis_angle(axes[tid], spins[tid] * time)
    c = centroids[tid] + velocities[tid] * time
    for k in range(3):
        vertices[3 * tid + k] = c + wp.quat_rotate(q, offsets[3 * tid + k])


@wp.kernel
def bend_kernel(
    rest: wp.array(dtype=wp.vec3),
    origin: wp.vec3,
    length_axis: wp.vec3,
    bend_axis: wp.vec3,
    curvature: wp.float64,
    vertices: wp.array(dtype=wp.vec3),
):
    """One frame of a bending mesh (after the Bending Armadillo of Pantaleoni & Luebke 2010, section 4,
    Fig. 7): the straight length axis bent into an arc of the given curvature (1 / radius) towards
    bend_axis; the third axis is unchanged and zero curvature is the identity."""
    tid = wp.tid()
    p = rest[tid] - origin
    along = wp.dot(p, length_axis)
    across = wp.dot(p, bend_axis)
    other = p - along * length_axis - across * bend_axis
    # Only an exact zero is the identity, and the arc is computed in float64: the curvature is
    # 1 / radius in the mesh's own units, so any fixed floor (it was 1e-12, in float32) left a
    # mesh longer than about 1e12 unbent at every amount, and float32 holds the curvature of a
    # mesh near 1e38 long only as a subnormal, with a few bits.
    if curvature == wp.float64(0.0):
        vertices[tid] = rest[tid]
        return
    # radius - (radius - across) cos(theta), written as radius (1 - cos(theta)) + across cos(theta)
    # with 1 - cos(theta) = 2 sin^2(theta / 2): the plain difference of two values near the radius
    # lost `across` to float32 rounding as the radius grew (a unit mesh bent by 1e-8 of pi has a
    # radius of about 3e7, where float32 steps by 4: its vertices moved by the mesh's whole size).
    along64 = wp.float64(along)
    across64 = wp.float64(across)
    theta = along64 * curvature
    s = wp.sin(theta)
    h = wp.sin(wp.float64(0.5) * theta)
    new_along = float(s / curvature - across64 * s)
    new_across = float(wp.float64(2.0) * h * h / curvature + across64 * wp.cos(theta))
    vertices[tid] = origin + new_along * length_axis + new_across * bend_axis + other
