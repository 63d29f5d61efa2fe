"""Triangle-triangle intersection with exact predicates, for mesh-mesh and self-intersection queries.

The broad phase is the box query of ``traversal.py``: one thread per triangle of one mesh walks
the other mesh's BVH with the triangle's box, the approach of Karras ("Maximizing Parallelism in
the Construction of BVHs, Octrees, and k-d Trees", HPG 2012, Sec. 4), where a self query keeps
only partners later in the tree's order, so that each pair is found once. This module is the narrow phase.

**Exactness.** Every decision reduces to the sign of an orientation determinant of float32 points:
``orient3d`` (which side of a plane a point lies) and ``orient2d`` (the same in a coordinate
plane). Both are evaluated as Shewchuk does ("Adaptive Precision Floating-Point Arithmetic and
Fast Robust Geometric Predicates", DCG 1997): a float64 evaluation from coordinate differences,
trusted when it exceeds a bound on its rounding error, else the exact sign from an expansion (a
sum of float64 components that do not overlap). The exact path expands the determinant over the
raw coordinates, products of two or three float32 values: two are exact in float64 (48 bits);
for three, the 48-bit product is split in two halves of at most 27 bits by adding and removing a
scale (no exponent extraction, no Dekker split whose multiply a fused multiply-add could alter),
and each half times the third factor is exact again. Every product formed is exact, so contracting
a multiply and an add into an FMA cannot change a result. Touching, coplanar and collinear
configurations are therefore decided exactly for the coordinates as stored.

**Closed triangles.** Two triangles of nonzero area meet iff an edge of one meets the other (the
intersection, when not empty, is convex and each of its extreme points lies on an edge of one of
them). An edge meets a triangle when its end points are not strictly on one side of the
triangle's plane and the line through it passes the triangle: the signs of the three volumes it
spans with the triangle's edges are not mixed (Moeller & Trumbore's test in signed-volume form;
Segura & Feito, WSCG 2001). An edge lying in the plane is tested in 2D, in the coordinate plane
where the triangle's projection has the largest area. A zero-area triangle (valid input) is the
segment or point its vertices span and is tested as its edges; two of them as segment pairs.

**Neighbours.** In a self query, triangles sharing a vertex position always touch there. The
pair counts only when the triangles meet elsewhere (see `neighbours_meet`).
"""

import warp as wp

from .traversal import outline_func

wp.set_module_options({"enable_backward": False, "max_unroll": 0})

vec12d = wp.types.vector(length=12, dtype=wp.float64)
vec4i = wp.types.vector(length=4, dtype=wp.int32)
#: One component per exact product term: 24 triple products of orient3d, two halves each.
vec48d = wp.types.vector(length=48, dtype=wp.float64)

#: Rounding error bounds of the float64 filters, relative to the permanent (the determinant with
#: every term's absolute value). Shewchuk's (3 + 16e)e and (7 + 56e)e with e = 2^-53, rounded up.
ORIENT2D_ERROR = wp.constant(wp.float64(4.0e-16))
ORIENT3D_ERROR = wp.constant(wp.float64(1.0e-15))
#: 3 * 2^27: adding |p| * SPLIT_SCALE to a 48-bit product p and removing it again rounds p to its
#: top 27 bits or fewer, since the sum's unit in the last place is about 2^-(53 - 28.6) of p.
SPLIT_SCALE = wp.constant(wp.float64(402653184.0))


@wp.func
def grow_expansion(e: vec48d, n: int, t: wp.float64):
    """Add ``t`` to the expansion ``e[0:n]`` (components in increasing magnitude, not overlapping).

    Shewchuk's Grow-Expansion with zero elimination: each component is added to the running sum
    by Knuth's TwoSum, whose rounding error is exactly representable and kept as a component.
    """
    q = t
    m = int(0)
    for i in range(n):
        s = q + e[i]
        bv = s - q
        av = s - bv
        err = (q - av) + (e[i] - bv)
        q = s
        if err != wp.float64(0.0):
            e[m] = err
            m += 1
    if q != wp.float64(0.0):
        e[m] = q
        m += 1
    return e, m


@wp.func
def grow_triple_product(e: vec48d, n: int, x: wp.float64, y: wp.float64, z: wp.float64, sign: wp.float64):
    """Add ``sign * x * y * z`` exactly, for float32 values x, y, z held in float64."""
    p = x * y  # 48 bits at most: exact
    scale = wp.abs(p) * SPLIT_SCALE  # 50 bits at most: exact
    hi = (p + scale) - scale
    lo = p - hi
    e, n = grow_expansion(e, n, sign * hi * z)
    e, n = grow_expansion(e, n, sign * lo * z)
    return e, n


@wp.func
def expansion_sign(e: vec48d, n: int):
    """Sign of a nonoverlapping expansion (Shewchuk 1997): -1, 0 or +1."""
    # The largest component decides: the others sum to less than its last bit.
    s = int(0)
    if n > 0:
        if e[n - 1] > wp.float64(0.0):
            s = int(1)
        else:
            s = int(-1)
    return s


@wp.func
def to_d(p: wp.vec3):
    """The point in float64."""
    return wp.vec3d(p)


@wp.func
def orient3d_exact(a: wp.vec3, b: wp.vec3, c: wp.vec3, d: wp.vec3):
    """Sign of det[b - a, c - a, d - a] from the 4x4 determinant over the raw coordinates.

    orient3d = det3(b, c, d) - det3(a, c, d) + det3(a, b, d) - det3(a, b, c) (expansion along the
    column of ones), each 3x3 determinant six signed triple products. Every product is exact
    (`grow_triple_product`) and they are summed without error into a nonoverlapping expansion by
    Shewchuk's Grow-Expansion ("Adaptive Precision Floating-Point Arithmetic and Fast Robust
    Geometric Predicates", DCG 1997), whose largest component gives the sign.
    """
    pts = vec12d(
        wp.float64(a[0]), wp.float64(a[1]), wp.float64(a[2]),
        wp.float64(b[0]), wp.float64(b[1]), wp.float64(b[2]),
        wp.float64(c[0]), wp.float64(c[1]), wp.float64(c[2]),
        wp.float64(d[0]), wp.float64(d[1]), wp.float64(d[2]),
    )
    e = vec48d()
    n = int(0)
    # A while loop, which no module's max_unroll unrolls: other modules' kernels call this too
    # (`point_on_triangle`), and 4 unrolled copies of 24 inlined products slowed their CUDA builds.
    m = int(0)
    while m < 4:
        # Rows of the minor: the three points other than point m, in order (offsets into pts).
        r0 = 0
        if m == 0:
            r0 = 3
        r1 = 3
        if m <= 1:
            r1 = 6
        r2 = 6
        if m <= 2:
            r2 = 9
        sign = wp.float64(1.0)
        if m % 2 == 1:
            sign = wp.float64(-1.0)
        # The six permutations (c0, c1, c2) of the columns with their signs.
        e, n = grow_triple_product(e, n, pts[r0 + 0], pts[r1 + 1], pts[r2 + 2], sign)
        e, n = grow_triple_product(e, n, pts[r0 + 0], pts[r1 + 2], pts[r2 + 1], -sign)
        e, n = grow_triple_product(e, n, pts[r0 + 1], pts[r1 + 0], pts[r2 + 2], -sign)
        e, n = grow_triple_product(e, n, pts[r0 + 1], pts[r1 + 2], pts[r2 + 0], sign)
        e, n = grow_triple_product(e, n, pts[r0 + 2], pts[r1 + 0], pts[r2 + 1], sign)
        e, n = grow_triple_product(e, n, pts[r0 + 2], pts[r1 + 1], pts[r2 + 0], -sign)
        m += 1
    return expansion_sign(e, n)


@wp.func
def orient3d(a: wp.vec3, b: wp.vec3, c: wp.vec3, d: wp.vec3):
    """Exact sign of det[b - a, c - a, d - a]: +1 when d lies on the side of plane abc that
    (b - a) x (c - a) points to, -1 on the other, 0 on the plane.

    Shewchuk's filtered predicate (DCG 1997): the float64 determinant of the coordinate differences
    is trusted when it exceeds his error bound ``ORIENT3D_ERROR`` times the permanent; otherwise
    `orient3d_exact` decides. Unlike his orient3d there are no intermediate adaptive stages: the
    fallback goes straight to the exact expansion.
    """
    u = to_d(b) - to_d(a)
    v = to_d(c) - to_d(a)
    w = to_d(d) - to_d(a)
    vw0 = v[1] * w[2]
    vw1 = v[2] * w[1]
    vw2 = v[2] * w[0]
    vw3 = v[0] * w[2]
    vw4 = v[0] * w[1]
    vw5 = v[1] * w[0]
    det = u[0] * (vw0 - vw1) + u[1] * (vw2 - vw3) + u[2] * (vw4 - vw5)
    permanent = (wp.abs(u[0]) * (wp.abs(vw0) + wp.abs(vw1)) + wp.abs(u[1]) * (wp.abs(vw2) + wp.abs(vw3))
                 + wp.abs(u[2]) * (wp.abs(vw4) + wp.abs(vw5)))
    bound = ORIENT3D_ERROR * permanent
    s = int(0)
    if det > bound:
        s = int(1)
    elif det < -bound:
        s = int(-1)
    elif permanent != wp.float64(0.0) and not (d == a or d == b or d == c or c == a or c == b or b == a):
        # Two equal points zero the determinant: the usual case between neighbouring triangles of
        # a mesh, answered without the expansion. Permanent 0: every product vanished, and so did
        # the exact determinant.
        s = orient3d_exact(a, b, c, d)
    return s


@wp.func
def orient2d(a: wp.vec3, b: wp.vec3, c: wp.vec3, axis: int):
    """Exact sign of the component ``axis`` of (b - a) x (c - a): orientation of a, b, c in the
    coordinate plane that drops ``axis`` (axes axis + 1 and axis + 2, cyclically).

    Filtered as `orient3d` (Shewchuk, DCG 1997, with his bound ``ORIENT2D_ERROR``); the fallback is
    the exact expansion of the six products of the raw coordinates.
    """
    i = (axis + 1) % 3
    j = (axis + 2) % 3
    ux = wp.float64(b[i]) - wp.float64(a[i])
    uy = wp.float64(b[j]) - wp.float64(a[j])
    vx = wp.float64(c[i]) - wp.float64(a[i])
    vy = wp.float64(c[j]) - wp.float64(a[j])
    left = ux * vy
    right = uy * vx
    det = left - right
    bound = ORIENT2D_ERROR * (wp.abs(left) + wp.abs(right))
    s = int(0)
    if det > bound:
        s = int(1)
    elif det < -bound:
        s = int(-1)
    elif left != wp.float64(0.0) or right != wp.float64(0.0):
        # a_i b_j - a_j b_i + b_i c_j - b_j c_i + c_i a_j - c_j a_i: six exact float32 products.
        e = vec48d()
        n = int(0)
        e, n = grow_expansion(e, n, wp.float64(a[i]) * wp.float64(b[j]))
        e, n = grow_expansion(e, n, -wp.float64(a[j]) * wp.float64(b[i]))
        e, n = grow_expansion(e, n, wp.float64(b[i]) * wp.float64(c[j]))
        e, n = grow_expansion(e, n, -wp.float64(b[j]) * wp.float64(c[i]))
        e, n = grow_expansion(e, n, wp.float64(c[i]) * wp.float64(a[j]))
        e, n = grow_expansion(e, n, -wp.float64(c[j]) * wp.float64(a[i]))
        s = expansion_sign(e, n)
    return s


@wp.func
def projection_axis(a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """The axis whose coordinate plane shows triangle abc with the largest area, or -1 when the
    triangle has zero area (its three vertices are collinear, exactly)."""
    n = wp.cross(to_d(b) - to_d(a), to_d(c) - to_d(a))
    # Try the axes from the largest float64 component down; the exact sign has the last word.
    k0 = int(0)
    if wp.abs(n[1]) > wp.abs(n[k0]):
        k0 = 1
    if wp.abs(n[2]) > wp.abs(n[k0]):
        k0 = 2
    axis = int(-1)
    for step in range(3):
        k = (k0 + step) % 3
        if axis < 0 and orient2d(a, b, c, k) != 0:
            axis = k
    return axis


@wp.func
def on_segment_2d(a: wp.vec3, b: wp.vec3, p: wp.vec3, axis: int):
    """Whether p, known collinear with a and b in the plane dropping ``axis``, lies in the box of
    the segment ab there (closed)."""
    i = (axis + 1) % 3
    j = (axis + 2) % 3
    inside = int(0)
    if wp.min(a[i], b[i]) <= p[i] and p[i] <= wp.max(a[i], b[i]):
        if wp.min(a[j], b[j]) <= p[j] and p[j] <= wp.max(a[j], b[j]):
            inside = int(1)
    return inside


@wp.func
def segments_meet_2d(a: wp.vec3, b: wp.vec3, c: wp.vec3, d: wp.vec3, axis: int):
    """Whether closed segments ab and cd meet in the plane dropping ``axis`` (points allowed)."""
    # The orientation of each end of one segment against the other: k = 0, 1 for c and d against
    # ab, k = 2, 3 for a and b against cd. Both pairs of signs opposite: a proper crossing; an
    # end on the other's line and within its box: a touch.
    signs = vec4i()
    touch = int(0)
    for k in range(4):
        p = pick(k, c, d, a)
        if k == 3:
            p = b
        u = a
        v = b
        if k >= 2:
            u = c
            v = d
        o = orient2d(u, v, p, axis)
        signs[k] = o
        if o == 0 and on_segment_2d(u, v, p, axis) == 1:
            touch = int(1)
    meet = touch
    if signs[0] * signs[1] < 0 and signs[2] * signs[3] < 0:
        meet = int(1)
    return meet


@wp.func
def pick(k: int, p0: wp.vec3, p1: wp.vec3, p2: wp.vec3):
    """Vertex k mod 3 of a triangle: lets one call site in a loop serve every edge. The loops of
    this module stay rolled (``max_unroll`` 0): inlined copies of the exact predicates at every
    call site made it slow to compile for CUDA."""
    j = k % 3
    p = p0
    if j == 1:
        p = p1
    elif j == 2:
        p = p2
    return p


@wp.func
def point_in_triangle_2d(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3, axis: int):
    """Whether p lies in the closed triangle abc, both in the plane dropping ``axis``, where abc
    has nonzero area: the signs of its three edge orientations are not mixed."""
    positive = int(0)
    negative = int(0)
    for k in range(3):
        o = orient2d(pick(k, a, b, c), pick(k + 1, a, b, c), p, axis)
        if o > 0:
            positive = int(1)
        elif o < 0:
            negative = int(1)
    return 1 - positive * negative


@wp.func
def segment_meets_triangle(x: wp.vec3, y: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3, axis: int):
    """Whether closed segment xy (a point when x = y) meets closed triangle abc of nonzero area,
    whose `projection_axis` is ``axis``."""
    # Which side of the plane each end lies on (k = 0: x, k = 1: y).
    sx = int(0)
    sy = int(0)
    for k in range(2):
        side = orient3d(a, b, c, pick(k, x, y, y))
        if k == 0:
            sx = side
        else:
            sy = side
    meet = int(0)
    if sx * sy > 0:
        meet = int(0)
    elif sx == 0 and sy == 0:
        # In the triangle's plane: 2D, where the projection keeps the triangle's area. An end
        # inside (k = 0, 1), or the segment crossing an edge (k = 2, 3, 4).
        for k in range(5):
            if meet == 0:
                if k < 2:
                    meet = point_in_triangle_2d(pick(k, x, y, y), a, b, c, axis)
                else:
                    meet = segments_meet_2d(x, y, pick(k, a, b, c), pick(k + 1, a, b, c), axis)
    else:
        # The segment reaches the plane at one point; the line through it passes the closed
        # triangle iff the volumes it spans with the three edges do not take both signs.
        positive = int(0)
        negative = int(0)
        for k in range(3):
            o = orient3d(x, y, pick(k, a, b, c), pick(k + 1, a, b, c))
            if o > 0:
                positive = int(1)
            elif o < 0:
                negative = int(1)
        meet = 1 - positive * negative
    return meet


@wp.func
def segments_meet(a: wp.vec3, b: wp.vec3, c: wp.vec3, d: wp.vec3):
    """Whether closed segments ab and cd (points allowed) meet in 3D.

    They must be coplanar; then they meet iff they meet in all three coordinate planes: a common
    point projects to one in each, and some coordinate plane keeps their common plane (or line)
    one to one, where disjoint segments stay disjoint.
    """
    meet = int(0)
    if orient3d(a, b, c, d) == 0:
        meet = int(1)
        for axis in range(3):
            if meet == 1:
                meet = segments_meet_2d(a, b, c, d, axis)
    return meet


@wp.func
def strictly_one_side(a: wp.vec3, b: wp.vec3, c: wp.vec3, p: wp.vec3, q: wp.vec3, r: wp.vec3):
    """Whether p, q and r lie strictly on one side of the plane of abc (nonzero area)."""
    positive = int(0)
    negative = int(0)
    for k in range(3):
        o = orient3d(a, b, c, pick(k, p, q, r))
        if o > 0:
            positive += 1
        elif o < 0:
            negative += 1
    return positive == 3 or negative == 3


@wp.func
def triangles_meet(a0: wp.vec3, a1: wp.vec3, a2: wp.vec3, b0: wp.vec3, b1: wp.vec3, b2: wp.vec3):
    """Whether closed triangles a and b share a point, exactly for their float32 coordinates.

    Zero-area triangles count as the segment or point they span. Neither Moeller's interval test
    ("A Fast Triangle-Triangle Intersection Test", JGT 1997) nor Guigue & Devillers' orientation
    cascade (JGT 2003): after the usual early exit (either triangle strictly on one side of the
    other's plane), every edge of each triangle is tested against the other (`segment_meets_triangle`,
    signed volumes, see the module docstring). Every decision is a sign of `orient3d` or `orient2d`,
    Shewchuk's exact predicates (DCG 1997), so the answer holds for touching and coplanar pairs too.
    """
    axis_a = projection_axis(a0, a1, a2)
    axis_b = projection_axis(b0, b1, b2)
    meet = int(0)
    if axis_a >= 0 or axis_b >= 0:
        # Each triangle strictly on one side of the other's plane: the usual early exit.
        apart = int(0)
        if axis_a >= 0 and axis_b >= 0:
            for k in range(2):
                if apart == 0:
                    # k = 0: a against the plane of b; k = 1: b against the plane of a.
                    p0 = pick(k, b0, a0, a0)
                    p1 = pick(k, b1, a1, a1)
                    p2 = pick(k, b2, a2, a2)
                    q0 = pick(k, a0, b0, b0)
                    q1 = pick(k, a1, b1, b1)
                    q2 = pick(k, a2, b2, b2)
                    if strictly_one_side(p0, p1, p2, q0, q1, q2):
                        apart = int(1)
        if apart == 0:
            # The edges of a against b (k = 0, 1, 2), then those of b against a (k = 3, 4, 5),
            # where the triangle tested against has nonzero area; a zero-area triangle is the
            # union of its edges.
            for k in range(6):
                if meet == 0:
                    x = pick(k, a0, a1, a2)
                    y = pick(k + 1, a0, a1, a2)
                    p = b0
                    q = b1
                    r = b2
                    axis = axis_b
                    if k >= 3:
                        x = pick(k, b0, b1, b2)
                        y = pick(k + 1, b0, b1, b2)
                        p = a0
                        q = a1
                        r = a2
                        axis = axis_a
                    if axis >= 0:
                        meet = segment_meets_triangle(x, y, p, q, r, axis)
    else:
        # Both are segments or points: edge against edge.
        for k in range(9):
            if meet == 0:
                i = k // 3
                j = k % 3
                meet = segments_meet(pick(i, a0, a1, a2), pick(i + 1, a0, a1, a2), pick(j, b0, b1, b2),
                                     pick(j + 1, b0, b1, b2))
    return meet


@outline_func
def point_on_triangle(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """1 if p lies on the closed triangle abc, exactly for the float32 coordinates, else 0. A
    zero-area abc is the segment or point it spans.

    In the triangle's plane (`orient3d` 0) and inside it in a coordinate plane that keeps its
    area (the signs of the three edge orientations not mixed); for a zero-area abc, collinear
    with one of its edges in all three coordinate planes and within the edge's box (see
    `segments_meet`). Written for other modules' kernels (the closest-point walks, for points
    within rounding of a triangle): out of line, and with while loops, which no module's
    ``max_unroll`` unrolls; inlined and unrolled at every call site, the exact predicates took
    CUDA minutes to compile.
    """
    # A coordinate plane where abc has nonzero area (exactly), or -1.
    axis = int(-1)
    k = int(0)
    while k < 3 and axis < 0:
        if orient2d(a, b, c, k) != 0:
            axis = k
        k += 1
    on = int(0)
    if axis >= 0:
        if orient3d(a, b, c, p) == 0:
            positive = int(0)
            negative = int(0)
            k = int(0)
            while k < 3:
                o = orient2d(pick(k, a, b, c), pick(k + 1, a, b, c), p, axis)
                if o > 0:
                    positive = int(1)
                elif o < 0:
                    negative = int(1)
                k += 1
            on = 1 - positive * negative
    else:
        # Edge k // 3 in the coordinate plane dropping axis k % 3.
        k = int(0)
        collinear = int(1)
        while k < 9 and on == 0:
            x = pick(k // 3, a, b, c)
            y = pick(k // 3 + 1, a, b, c)
            if k % 3 == 0:
                collinear = int(1)
            if orient2d(x, y, p, k % 3) != 0:
                collinear = int(0)
            if k % 3 == 2 and collinear == 1:
                inside = int(1)
                for i in range(3):
                    if p[i] < wp.min(x[i], y[i]) or p[i] > wp.max(x[i], y[i]):
                        inside = int(0)
                on = inside
            k += 1
    return on


@wp.func
def shared_with(p: wp.vec3, b0: wp.vec3, b1: wp.vec3, b2: wp.vec3):
    """1 if p equals one of b0, b1, b2 exactly (a vertex position the triangles share), else 0."""
    shared = int(0)
    if p == b0 or p == b1 or p == b2:
        shared = int(1)
    return shared


@wp.func
def neighbours_meet(a0: wp.vec3, a1: wp.vec3, a2: wp.vec3, b0: wp.vec3, b1: wp.vec3, b2: wp.vec3):
    """`triangles_meet` for two triangles of one mesh, where touching at shared vertices is expected.

    Vertices are shared when their coordinates are equal (welded or not). For a pair sharing some:
    - a zero-area triangle is not reported (it lies along its neighbours by construction);
    - the same three positions (a duplicated face) is reported;
    - one shared vertex v: reported iff the edge opposite v in either triangle meets the other,
      which for triangles of nonzero area is exactly "they meet somewhere other than v" (a corner
      of their intersection other than v is a vertex of one lying in the other or lies on the
      opposite edge of one of them);
    - a shared edge uv: reported iff the triangles are coplanar and fold over, their third
      vertices strictly on one side of uv; otherwise they meet exactly along uv.
    """
    s0 = shared_with(a0, b0, b1, b2)
    s1 = shared_with(a1, b0, b1, b2)
    s2 = shared_with(a2, b0, b1, b2)
    num_shared = s0 + s1 + s2
    meet = int(0)
    if num_shared == 0:
        meet = triangles_meet(a0, a1, a2, b0, b1, b2)
    else:
        axis_a = projection_axis(a0, a1, a2)
        axis_b = projection_axis(b0, b1, b2)
        if axis_a >= 0 and axis_b >= 0:
            # Nonzero area: three distinct vertices each, so the count is the same from b's side.
            if num_shared == 3:
                meet = int(1)
            elif num_shared == 1:
                # Rotate a so that a0 is the shared vertex, and find b's.
                v = a0
                x = a1
                y = a2
                if s1 == 1:
                    v = a1
                    x = a2
                    y = a0
                elif s2 == 1:
                    v = a2
                    x = a0
                    y = a1
                p = b1
                q = b2
                if v == b1:
                    p = b2
                    q = b0
                elif v == b2:
                    p = b0
                    q = b1
                # The edge opposite v in a against b (k = 0), then the one in b against a (k = 1).
                for k in range(2):
                    if meet == 0:
                        meet = segment_meets_triangle(pick(k, x, p, p), pick(k, y, q, q), pick(k, b0, a0, a0),
                                                      pick(k, b1, a1, a1), pick(k, b2, a2, a2),
                                                      wp.where(k == 0, axis_b, axis_a))
            else:
                # The unshared vertex of each, and the shared edge uv.
                x = a0
                u = a1
                v = a2
                if s1 == 0:
                    x = a1
                    u = a2
                    v = a0
                elif s2 == 0:
                    x = a2
                    u = a0
                    v = a1
                y = b0
                if shared_with(b1, a0, a1, a2) == 0:
                    y = b1
                elif shared_with(b2, a0, a1, a2) == 0:
                    y = b2
                if orient3d(u, v, x, y) == 0:
                    # Coplanar: same side of uv in a plane that keeps a's area (and so the plane's).
                    if orient2d(u, v, x, axis_a) == orient2d(u, v, y, axis_a):
                        meet = int(1)
    return meet


@wp.kernel
def triangle_pairs_kernel(
    vertices_a: wp.array(dtype=wp.vec3),
    faces_a: wp.array2d(dtype=wp.int32),
    vertices_b: wp.array(dtype=wp.vec3),
    faces_b: wp.array2d(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec2i),
    neighbours: int,
    meets: wp.array(dtype=wp.int32),
):
    """For each candidate ``(face of a, face of b)``, whether the two triangles meet (1) or not."""
    tid = wp.tid()
    fa = pairs[tid][0]
    fb = pairs[tid][1]
    a0 = vertices_a[faces_a[fa, 0]]
    a1 = vertices_a[faces_a[fa, 1]]
    a2 = vertices_a[faces_a[fa, 2]]
    b0 = vertices_b[faces_b[fb, 0]]
    b1 = vertices_b[faces_b[fb, 1]]
    b2 = vertices_b[faces_b[fb, 2]]
    if neighbours == 1:
        meets[tid] = neighbours_meet(a0, a1, a2, b0, b1, b2)
    else:
        meets[tid] = triangles_meet(a0, a1, a2, b0, b1, b2)


@wp.kernel
def warp_mesh_box_pairs_kernel(
    mesh: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    indices: wp.array(dtype=wp.int32),
    lowers: wp.array(dtype=wp.vec3),
    uppers: wp.array(dtype=wp.vec3),
    self_pairs: int,
    counts: wp.array(dtype=wp.int32),
):
    """The benchmark's reference: Warp's own mesh BVH and ``wp.mesh_query_aabb``, one box per thread,
    counting the faces whose box overlaps (tested here, as leaves may hold several faces)."""
    tid = wp.tid()
    lower = lowers[tid]
    upper = uppers[tid]
    query = wp.mesh_query_aabb(mesh, lower, upper)
    face = int(0)
    count = int(0)
    while wp.mesh_query_aabb_next(query, face):
        if self_pairs == 0 or face > tid:
            a = points[indices[3 * face]]
            b = points[indices[3 * face + 1]]
            c = points[indices[3 * face + 2]]
            lo = wp.min(wp.min(a, b), c)
            hi = wp.max(wp.max(a, b), c)
            if lo[0] <= upper[0] and lower[0] <= hi[0] and lo[1] <= upper[1] and lower[1] <= hi[1]:
                if lo[2] <= upper[2] and lower[2] <= hi[2]:
                    count += 1
    counts[tid] = count
