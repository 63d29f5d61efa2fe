"""Closest-point queries on a built BVH, callable from any user ``@wp.kernel``.

- Point to triangle (`closest_point_on_triangle`): the closest point lies in the point's Voronoi
  region of the triangle, a vertex, an edge or the face (Ericson, "Real-Time Collision Detection",
  2005, Sec. 5.1.5). Here the face region is decided by the signs of three edge functions and the
  rest by the nearest of the three edges, in float64, for accuracy on slivers and range at 1e18 or
  1e-18 (the function's docstring says why). A degenerate triangle (a segment or a point, valid
  input) has no face and is measured as its edges; a point on a vertex is at distance 0 exactly.
- Traversal: nearest child first, the farther one deferred on the stack with its box distance
  (the squared distance from the point to the box); a deferred node is dropped when popped if its
  box lies farther than the closest triangle found since, and a box is entered only when it is
  not farther than that. Box distances are float32, measured again in float64 where float32
  cannot tell a box from the best triangle (a point far from the mesh, a mesh beyond 1e19). A
  spatial-split leaf bounds part of a triangle, and the part holding the closest point lies in
  some leaf whose box is no farther: so spatial-split trees answer correctly as well, testing the
  whole triangle at each of its leaves.
- Equal distances go to the lowest primitive id, whatever the tree, so every builder gives the same
  answer where the float64 distances are equal. An edge is measured from the same end in every
  triangle holding it (`edge_closest`), so a point nearest an edge shared by two triangles is at
  bitwise equal distances from both.
- Stack overflow is handled as in ``traversal.py``: a node met with a full stack is tested as one
  leaf over its whole primitive range.
"""

from typing import Any

import warp as wp

from . import collide
from .traversal import (
    INF,
    STACK_SIZE,
    TRAVERSAL_STACK_SIZE,
    BvhView,
    PackedNode,
    PackedTriangle,
    inline_func,
    outline_func,
    prefetch_child,
    query_limit,
    vec64f,
    vec64i,
)

wp.set_module_options({"enable_backward": False})

NAN = wp.constant(float("nan"))



@wp.struct
class ClosestPoint:
    """Result of a closest-point query: ``prim`` is -1 and ``distance`` inf when no triangle lies
    within the query's ``max_dist`` (or the point has a NaN or Inf coordinate). Test ``prim``: a
    distance beyond float32's range (points near +-3e38) reads inf too.

    ``point`` is the closest point on triangle ``prim``, ``(1 - u - v) * a + u * b + v * c`` for its
    vertices a, b, c (the same weights as a `RayHit`); ``nodes_visited`` and ``prims_tested`` count
    the traversal's steps and point-triangle tests.
    """

    point: wp.vec3
    distance: float
    prim: int
    u: float
    v: float
    nodes_visited: int
    prims_tested: int


@wp.struct
class TrianglePoint:
    """The closest point of one triangle to a query point, its weights of ``b`` and ``c``, and
    its squared distance in float64."""

    point: wp.vec3
    u: float
    v: float
    d2: wp.float64


@wp.func
def segment_parameter(ap: wp.vec3d, ab: wp.vec3d):
    """Where the closest point of segment a + t * ab to a + ap lies, t in [0, 1] (0 for a point):
    the projection parameter clamped to the segment (Ericson, "Real-Time Collision Detection", 2005,
    Sec. 5.1.2)."""
    den = wp.dot(ab, ab)
    t = wp.float64(0.0)
    if den > wp.float64(0.0):
        t = wp.clamp(wp.dot(ap, ab) / den, wp.float64(0.0), wp.float64(1.0))
    return t


@wp.func
def edge_closest(p: wp.vec3d, x: wp.vec3, y: wp.vec3):
    """``(t, d2)``: the closest point x + t (y - x) of segment xy to p (`segment_parameter`) and its
    squared distance, in float64. Measured from the end that comes first in lexicographic order,
    whichever order the edge is given in: an edge shared by two triangles (as ab of one and bc
    of the other, say) then gives both the same bits, so that a point nearest that edge is at
    equal distances from both and goes to the lower id, as an exact tie should."""
    flip = y[0] < x[0] or (y[0] == x[0] and (y[1] < x[1] or (y[1] == x[1] and y[2] < x[2])))
    o = x
    e = y
    if flip:
        o = y
        e = x
    o64 = wp.vec3d(o)
    oe = wp.vec3d(e) - o64
    op = p - o64
    t = segment_parameter(op, oe)
    d2 = wp.length_sq(op - oe * t)
    if flip:
        t = wp.float64(1.0) - t
    return wp.vec2d(t, d2)


@wp.func
def sum_compensated(s: wp.float64, c: wp.float64, x: wp.float64):
    """One step of a compensated sum (Ogita, Rump & Oishi, "Accurate Sum and Dot Product", SIAM
    J. Sci. Comput. 2005, Sum2): adds x to the sum s and its rounding error to c (Knuth's
    TwoSum: exact, with no multiplication for an FMA contraction to change)."""
    t = s + x
    z = t - s
    c = c + ((s - (t - z)) + (x - z))
    return wp.vec2d(t, c)


@wp.func
def exact_cross_component(ay: float, az: float, by: float, bz: float, cy: float, cz: float):
    """One component of (b - a) x (c - a) = a x b + b x c + c x a, accurate to an ulp of itself: each of
    the six products of float32 coordinates is exact in float64 (24 + 24 bits), and only their sum
    rounds, compensated."""
    acc = wp.vec2d(wp.float64(ay) * wp.float64(bz), wp.float64(0.0))
    acc = sum_compensated(acc[0], acc[1], -wp.float64(az) * wp.float64(by))
    acc = sum_compensated(acc[0], acc[1], wp.float64(by) * wp.float64(cz))
    acc = sum_compensated(acc[0], acc[1], -wp.float64(bz) * wp.float64(cy))
    acc = sum_compensated(acc[0], acc[1], wp.float64(cy) * wp.float64(az))
    acc = sum_compensated(acc[0], acc[1], -wp.float64(cz) * wp.float64(ay))
    return acc[0] + acc[1]


@wp.func
def exact_normal(a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """(b - a) x (c - a) with every component accurate to an ulp (`exact_cross_component`)."""
    return wp.vec3d(exact_cross_component(a[1], a[2], b[1], b[2], c[1], c[2]),
                    exact_cross_component(a[2], a[0], b[2], b[0], c[2], c[0]),
                    exact_cross_component(a[0], a[1], b[0], b[1], c[0], c[1]))


# Where |ab x ac| falls below this fraction of |ab| |ac| (sin(angle) < 3.6e-6), the rounding of the
# float64 cross product (at most about 2^-48 |ab| |ac|, the edges' own rounding included when their
# vertices differ by more than 2^29 in magnitude) could tilt the normal by more than 1e-9: the
# normal is then computed exactly instead.
NORMAL_RECHECK = wp.constant(1.3e-11)
# (height above the plane / longest edge)^2 past which the face's closest point is taken from its
# weights rather than the projection (see `closest_point_on_triangle`).
FAR_FROM_PLANE = wp.constant(wp.float64(1.0e12))
# Where the computed squared distance is at most this times |p|^2 + |a|^2 + |ab|^2 + |ac|^2, the
# point may lie exactly on the triangle and is tested exactly (`closest_point_on_triangle`). For a
# point on it, the face's residue is at most (TILT / 2 + a few u) |ap| plus u |p|, and the edges'
# a few u of their coordinates, below 4e-9 (|p| + |a| + the longest edge): squared and summed,
# well under 1e-15 of that sum.
ON_SURFACE = wp.constant(wp.float64(1.0e-15))


@wp.func
def closest_point_on_triangle(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """The point of triangle abc closest to p, as a `TrianglePoint`.

    The projection onto the plane when it falls inside the triangle, else the closest point of the
    three edges (Ericson, "Real-Time Collision Detection", 2005, Sec. 5.1.5: the closest point lies
    in the point's Voronoi region of the triangle). Inside or outside is decided by the signs of the
    three edge functions n . ((v_j - v_i) x (p - v_i)); near an edge, where their rounding could
    decide wrongly, the face and the edge are equally near. Computed in float64: a normal computed
    in float32 tilts by about 2^-24 / sin(angle), which moves the projection of a point by as much
    times its distance in the plane, and the squares of coordinates near 1e20 or 1e-20 leave the
    float32 range. On a needle (sin(angle) < 3.6e-6) even the float64 cross product tilts by more
    than 1e-9, and the normal is computed exactly (`exact_normal`).
    A degenerate triangle (a segment or a point, valid input) has no face and is its edges.
    Vertices come back exactly where the closest point is one.
    """
    result = TrianglePoint()
    # A point on a vertex is at distance 0: the plane projection below would leave a rounding
    # residue (about 1e-17 of the scale), so max_dist = 0 would miss it and a vertex shared by
    # several triangles would not go to the lowest id.
    if p == a or p == b or p == c:
        result.point = p
        if not (p == a):
            if p == b:
                result.u = 1.0
            else:
                result.v = 1.0
        result.d2 = wp.float64(0.0)
        return result
    p64 = wp.vec3d(p)
    a64 = wp.vec3d(a)
    ab = wp.vec3d(b) - a64
    ac = wp.vec3d(c) - a64
    ap = p64 - a64
    n = wp.cross(ab, ac)
    nn = wp.dot(n, n)
    ll = wp.dot(ab, ab) * wp.dot(ac, ac)
    if nn < wp.float64(NORMAL_RECHECK) * ll:
        n = exact_normal(a, b, c)
        nn = wp.dot(n, n)
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    u = zero
    v = zero
    face = int(0)
    # Below sin(angle) = 1e-15 the normal is float64 noise: the triangle is its edges.
    if nn > wp.float64(1.0e-30) * ll:
        s_b = wp.dot(n, wp.cross(ap, ac))
        s_c = wp.dot(n, wp.cross(ab, ap))
        s_a = wp.dot(n, wp.cross(ac - ab, ap - ab))
        if s_a >= zero and s_b >= zero and s_c >= zero:
            face = 1
            u = s_b / nn
            v = s_c / nn
    if face == 1:
        # The projection itself, not a + u ab + v ac: exact up to rounding however thin the triangle.
        height = wp.dot(n, ap)
        q = p64 - n * (height / nn)
        if height * height > FAR_FROM_PLANE * nn * wp.max(wp.dot(ab, ab), wp.dot(ac, ac)):
            # p is a million triangle sizes off the plane: the projection subtracts two nearly equal
            # large vectors, and its rounding (2^-53 |p|) had put the point of a mesh's triangle
            # 6.5e22 off it for p near 3e38. The weights, clamped, keep the point on the triangle.
            u = wp.clamp(u, zero, one)
            v = wp.clamp(v, zero, one - u)
            q = a64 + ab * u + ac * v
        result.point = wp.vec3(q)
        result.d2 = wp.length_sq(p64 - q)
    else:
        e_ab = edge_closest(p64, a, b)
        e_ac = edge_closest(p64, a, c)
        e_bc = edge_closest(p64, b, c)
        t_ab = e_ab[0]
        t_ac = e_ac[0]
        t_bc = e_bc[0]
        d_ab = e_ab[1]
        d_ac = e_ac[1]
        d_bc = e_bc[1]
        u = t_ab
        best = d_ab
        if d_ac < best:
            best = d_ac
            u = zero
            v = t_ac
        if d_bc < best:
            best = d_bc
            u = one - t_bc
            v = t_bc
        if u == zero and v == zero:
            result.point = a
        elif u == one and v == zero:
            result.point = b
        elif u == zero and v == one:
            result.point = c
        else:
            result.point = wp.vec3(a64 + ab * u + ac * v)
        result.d2 = best
    # A point exactly on the triangle (an edge or the face, not only a vertex) is at distance 0
    # too, but the projection leaves a residue: the same point on an edge shared by two
    # triangles got two different residues, and max_dist = 0 missed some. Where the computed
    # distance is within that residue (at most TILT and a few u of the coordinates, under
    # ON_SURFACE), the exact predicates of the collision tests decide; rarely run: only on
    # points within 1e-8 of the scale of the triangle.
    if result.d2 > zero:
        scale = wp.dot(p64, p64) + wp.dot(a64, a64) + wp.dot(ab, ab) + wp.dot(ac, ac)
        if result.d2 <= ON_SURFACE * scale:
            if collide.point_on_triangle(p, a, b, c) == 1:
                result.point = p
                result.d2 = zero
    result.u = float(u)
    result.v = float(v)
    return result


@wp.func
def box_distance_sq(p: wp.vec3, lower: wp.vec3, upper: wp.vec3):
    """Squared distance from p to the box (0 inside), float32: the gap to p clamped to the box
    (Ericson 2005, Sec. 5.1.3). Overflow to inf only prunes boxes farther than 1.8e19 when a nearer
    triangle is known, and underflow only keeps boxes that could have been pruned: both safe."""
    gap = wp.max(wp.max(lower - p, p - upper), wp.vec3(0.0))
    return wp.dot(gap, gap)


@wp.func
def point_is_valid(p: wp.vec3, max_dist: float):
    """1 when p is finite and max_dist >= 0 (not NaN), else 0: an invalid query finds nothing."""
    valid = int(1)
    for i in range(3):
        if not wp.isfinite(p[i]):
            valid = 0
    if not (max_dist >= 0.0):
        valid = 0
    return valid


@wp.func
def box_distance_sq64(p: wp.vec3, lower: wp.vec3, upper: wp.vec3):
    """`box_distance_sq` in float64: within (1 + 2^-53)^5 of the true squared distance at any scale
    (float32 inputs are exact in float64; each gap, square and sum rounds once, see FAR_LOW: a
    gap is exact only where the two coordinates lie within 2^28 of each other's magnitude)."""
    total = wp.float64(0.0)
    for i in range(3):
        x = wp.float64(p[i])
        gap = wp.max(wp.max(wp.float64(lower[i]) - x, x - wp.float64(upper[i])), wp.float64(0.0))
        total += gap * gap
    return total


# A box is entered unless it is certainly farther than the best triangle plus `near_bound`'s
# absolute slack. Its float32 squared distance d is within a few ulps of the true one, so d (1 - 1e-6)
# is a lower bound; below 1.2e-38 the squares are subnormal and their ulp is absolute (2^-149 =
# 1.4e-45), which PRUNE_SLACK, seven of those, covers. Where that bound and d (1 + 1e-6) straddle the
# best distance, float32 cannot decide and the box distance is computed again in float64. A point
# far from the mesh needs that: at 1e6 mesh sizes every box lies within float32's margin of the
# best triangle, and a search that entered them all tested every triangle (3000x wp.Mesh's time at
# 1e9). A deferred node is popped by its float32 distance alone (the stack keeps no box): such a
# node is entered, and its children are measured again. Kept off the common path: a float64 stack
# and bound for every child cost 5-15% of a near query. EXACT_LOW is that float64 test's relative
# margin on the near walk only; the far walk (`packed_far_point_query`) has its own, FAR_LOW and
# `far_slack`, derived below.
# Why the near walk never skips the answer: the best triangle's float64 distance s.d2 is compared
# with box distances through `near_bound`, s.d2 + 2 tau (tau + sqrt(s.d2)) (tau as in FAR_LOW's
# step 2), in float64 (s.bound) and rounded to float32 (s.box_d2). A relative margin alone is not
# enough: the computed d2c of a triangle T lies below its exact d^2 by up to about d tau, which is
# most of d^2 for a point within a few tau of T. Seen on a triangle of size 1 whose top edge lies
# near the origin (its far vertex makes p - a and the normal's terms round by 1e-16 of 1): a point
# 1e-16 above the face, just inside that edge, got d2c = 8.2e-33 for an exact 2.5e-32 and a box
# distance of 1.0e-32, and the walk, having found a triangle at 9.1e-33, pruned the box, while a leaf
# holding both returned T (`test_near_walk_keeps_boxes_beyond_a_triangle_measured_short`). With
# the slack: let T lie in a box B (as in FAR_LOW, some leaf's box holds T's point x at d, and so do
# its ancestors'), with d2c(T) <= s.d2 =: b, the case that matters (a triangle nearer, or as near,
# in float64 than the best so far). Step 2 gives (1 - 29u) d^2 - d tau <= b, so d <= (tau +
# sqrt(b)) / (1 - 29u), and (1 - 29u) d^2 <= b + (1 + 30u) Y with Y = tau (tau + sqrt(b)). The
# bound rounds down by at most 4 roundings, and tau by a few u: s.bound >= (1 - u) b + 1.9 Y. Then
# - float64: box_distance_sq64 * EXACT_LOW, rounded, is at most (1 + u)^6 (1 - 1e-12) d^2, which is
#   at most (1 - 0.99e-12) b + (1 + 31u) Y < s.bound: B is entered (<= keeps ties);
# - float32: box_d2 = float32(s.bound) >= s.bound (1 - 2^-24) (or inf), and B's float32 distance
#   exceeds its exact one, at most d^2 <= s.bound (1 + 62u), by at most a factor 1 + 3e-7 (five
#   roundings; PRUNE_SLACK where subnormal): times PRUNE_MARGIN it is at most s.bound (1 - 6e-7) <
#   box_d2, and B is not pruned (nor skipped when popped, by the same test).
# So every box holding a triangle whose d2c is at most the best one's is entered, and the answer is
# the float64 brute force's: the minimum d2c, the lowest id among equal ones (`offer`), whatever
# the tree. The slack is 2 tau^2 at b = 0 (a point on the surface) and about 2 tau / sqrt(b) of b
# beyond, tau about 2e-9 L where M is of the order of L: it exceeds the float32 test's 1e-6 only
# within 0.4% of L from the surface (measured on the bunny, 1e5 points: the same answers, and
# 1e-4 more nodes per point at 1e-7 to 1e-5 of L off the surface; on it and at 1e-3, none).
PRUNE_MARGIN = wp.constant(1.0 - 1.0e-6)
PRUNE_HIGH = wp.constant(1.0 + 1.0e-6)
PRUNE_SLACK = wp.constant(1.0e-44)
EXACT_LOW = wp.constant(wp.float64(1.0 - 1.0e-12))

# The far walk enters a box when box_distance_sq64(p, box) * FAR_LOW <= s.d2 + far_slack. Why that
# never skips the answer (u = 2^-53, float64's unit roundoff). Let T be any triangle, d its exact
# distance from p, x its point at d, and d2c the float64 squared distance `closest_point_on_triangle`
# computes for it. Some leaf holding T has x in its box (its whole box, or on a spatial-split tree
# the box of the part of T holding x), and so do all its ancestors: each box's exact squared
# distance is at most d^2. Then, on every box of that path:
# 1. box_distance_sq64 exceeds it by at most a factor (1 + u)^5: the float32 inputs are exact in
#    float64, then one rounding per gap (a difference of float32 values is exact only within 2^28
#    of each other's magnitude: not for a point 1e13 sizes off a mesh at the origin), per square
#    and per addition, all of non-negative terms; nothing under- or overflows (gaps of float32
#    values lie between 1.4e-45 and 6.8e38).
# 2. d2c >= (1 - 29u) d^2 - d tau, tau = TILT L + ROUND_ABS (sqrt(3) M + L), with L the root box's
#    diagonal (no triangle is longer) and M its largest coordinate magnitude (|point| <= sqrt(3) M):
#    - a vertex equal to p: d2c = 0 exactly, and so is p's box distance (its gaps round to <= 0);
#    - an edge xy, from its first end in lexicographic order (`edge_closest`): x + t xy (t clamped
#      to [0, 1]) is on the segment up to u |xy| (the product) and u of each coordinate of
#      xy = y - x (rounded); xp and the difference round by u of themselves: 3u d relative, 3u L
#      absolute;
#    - the face's projection: n . ap / |n| comes out within 9u of itself (ap: u, the dot: 3u, n.n:
#      3u, the division and the product n * h: u each) plus 4u L; the plane of the computed n,
#      tilted by at most TILT / 2 from the exact normal, lies within TILT L / 2 of the triangle
#      at p's foot (|foot - a| <= L); the rounded edge functions can misplace the foot across an
#      edge only by a small multiple of (u + TILT) d, where the plane's and the triangle's
#      distances differ by a factor 1 - O((u + TILT)^2), far below u; q = p - w rounds by u |q|
#      and p - q by u of itself;
#    - the face far off its plane (FAR_FROM_PLANE): a + u ab + v ac with clamped weights is on the
#      triangle up to u (2 |q| + 2L);
#    and the final sum of squares rounds down by at most 3u. So |p - q| >= (1 - 13u) d - tau / 2,
#    and d2c >= (1 - 3u) |p - q|^2 gives the bound.
# 3. d <= R = sqrt(root box distance) + L (every triangle lies in the root box): `far_slack`,
#    4 R tau, is at least 3 R tau >= 3 d tau after its own rounding.
# Hence box_distance_sq64 * FAR_LOW, rounded, is at most (1 + u)^6 (1 - 64u) d^2 <= (1 - 57u) d^2,
# and s.d2 + far_slack, rounded, at least (d2c - d tau + 3 d tau)(1 - u) >= (1 - 30u) d^2 while
# s.d2 >= d2c, i.e. until a triangle nearer than T in float64 is found: the boxes of the answer,
# and those of every triangle tied with it in float64, are all entered (<= keeps ties), so the
# lowest id among equal d2c wins (`offer`). The relative part, 64u = 7.1e-15, is nearly twice the
# 36u needed (measured: d2c within 8u of the exact d^2 wherever M < d, over random, needle and
# offset triangles from 256 to 1e14 sizes; up to 350u where M is 300 d, the absolute term's
# part); far_slack is about 4 (TILT L + 14u M) / d of d^2: below 1e-11 from 256 sizes on, where
# boxes differ by about their own size / d, orders of magnitude more.
# This replaced a relative margin of 1e-12 (9,000u), which also entered every box within 1e-12
# of the best one's distance: at d from a mesh of size S the boxes differ by about 2 S / d
# relative, so past 1e11 sizes the walk opened a growing share of the tree (3x the nodes of 1e3
# sizes at 1e11, 20x at 1e12, all of it from 1e13 on the bunny). Float64 rounding itself, a few
# u, ties the boxes only from about 1e15 sizes. (The relative 1e-12 alone was not a proof either:
# the tilt and coordinate terms reach 1e-11 of d^2 at 256 sizes, needing the absolute part.)
FAR_LOW = wp.constant(wp.float64(1.0 - 64.0 * 2.0**-53))
# The largest tilt of a face normal: where the float64 cross product is kept (NORMAL_RECHECK), its
# rounding tilts it by at most 2^-48 / 3.6e-6 = 1e-9 (see NORMAL_RECHECK); twice that.
TILT = wp.constant(wp.float64(2.0e-9))
ROUND_ABS = wp.constant(wp.float64(8.0 * 2.0**-53))


@wp.func
def distance_tau(lower: wp.vec3, upper: wp.vec3):
    """tau = TILT L + ROUND_ABS (sqrt(3) M + L) for the root box ``lower``, ``upper`` (diagonal L,
    largest coordinate magnitude M): the absolute error, per unit of distance, of the triangle
    distances computed under it (FAR_LOW's step 2)."""
    lo = wp.vec3d(lower)
    hi = wp.vec3d(upper)
    diagonal = wp.length(hi - lo)
    magnitude = wp.float64(0.0)
    for i in range(3):
        magnitude = wp.max(magnitude, wp.max(wp.abs(lo[i]), wp.abs(hi[i])))
    return TILT * diagonal + ROUND_ABS * (wp.float64(1.7320508075688772) * magnitude + diagonal)


@wp.func
def far_slack(lower: wp.vec3, upper: wp.vec3, root_d2: wp.float64):
    """The far walk's absolute margin, 4 R tau (see FAR_LOW): covers the errors of the triangle
    distance that scale with the triangle's size and its coordinates rather than its distance,
    for the root box ``lower``, ``upper`` at squared distance ``root_d2`` from the point."""
    diagonal = wp.length(wp.vec3d(upper) - wp.vec3d(lower))
    reach = wp.sqrt(root_d2) + diagonal
    return wp.float64(4.0) * reach * distance_tau(lower, upper)


@wp.struct
class PointSearch:
    """The best triangle so far: its squared distance in float64 (the triangle comparisons), the
    near walk's box bound (`near_bound`) in float64 and in float32 (the box tests float32 can
    decide), the ``tau`` it is made with (0 on the far walk, which has its own) and the primitive
    id."""

    best: TrianglePoint
    d2: wp.float64
    bound: wp.float64
    box_d2: float
    tau: wp.float64
    prim: int


@wp.func
def near_bound(d2: wp.float64, tau: wp.float64):
    """d2 + 2 tau (tau + sqrt(d2)): the squared box distance up to which a box may hold a
    triangle whose computed distance is at most d2 (see EXACT_LOW); d2 itself where tau is 0 or d2
    infinite (no NaN from 0 * inf)."""
    bound = d2
    if tau > wp.float64(0.0) and d2 < wp.float64(INF):
        bound = d2 + wp.float64(2.0) * tau * (tau + wp.sqrt(d2))
    return bound


# max_dist is inclusive, but the float64 squared distance of a triangle lying at exactly max_dist
# can round above max_dist^2 (57600 + 7e-12 for an exact 240^2 on a tilted triangle with integer
# vertices), which dropped the triangle. So a triangle counts when its computed squared distance is
# at most max_dist^2 (1 + 2^-26): the computed distance is within tens of u (2^-53) of the exact one,
# plus terms of u times the coordinates' magnitude and of TILT times the triangle's size (FAR_LOW's
# step 2), below 2^-26 of d^2 unless the point lies 1e7 times nearer the triangle than its
# coordinates' magnitude or a needle's size. The widening stays below float32's resolution: the
# distance reported, rounded to float32, is still at most max_dist, and a triangle one float32 step
# beyond max_dist (at least 2^-23 of d^2) still does not count. The walks' box bounds start from
# the widened bound, so the boxes of such a triangle are entered as their proofs say.
MAX_DIST_ROOM = wp.constant(wp.float64(1.0 + 2.0**-26))


@wp.func
def start_search(max_dist: float):
    """An empty `PointSearch` bounded by max_dist (squared and widened by `MAX_DIST_ROOM`, in
    float64 and in float32), with no slack (tau 0): the far walk's."""
    s = PointSearch()
    s.d2 = wp.float64(max_dist) * wp.float64(max_dist) * MAX_DIST_ROOM
    s.bound = s.d2
    s.box_d2 = max_dist * max_dist
    s.prim = -1
    return s


@wp.func
def start_near_search(max_dist: float, root_lower: wp.vec3, root_upper: wp.vec3):
    """`start_search` for the near walk: its box bounds carry `near_bound`'s slack, with tau from
    the root box."""
    s = start_search(max_dist)
    s.tau = distance_tau(root_lower, root_upper)
    s.bound = near_bound(s.d2, s.tau)
    s.box_d2 = float(s.bound)
    return s


@wp.func
def box_may_hold(p: wp.vec3, lower: wp.vec3, upper: wp.vec3, d: float, best32: float, best: wp.float64):
    """1 unless the box, whose float32 squared distance from p is d, is certainly farther than
    ``best`` (``best32`` in float32: a `PointSearch`'s ``bound`` and ``box_d2``, the best triangle's
    squared distance and `near_bound`'s slack): d decides where it can (the common case), else
    `box_distance_sq64`."""
    if d * PRUNE_MARGIN > best32 + PRUNE_SLACK:
        return 0
    if d * PRUNE_HIGH + PRUNE_SLACK < best32:
        return 1
    return int(box_distance_sq64(p, lower, upper) * EXACT_LOW <= best)


@wp.func
def offer(s: PointSearch, tp: TrianglePoint, prim: int):
    """`s` with the triangle taken if it is nearer, or as near with a lower id (or the first
    within max_dist)."""
    if tp.d2 < s.d2 or (tp.d2 == s.d2 and (s.prim < 0 or prim < s.prim)):
        s.best = tp
        s.d2 = tp.d2
        s.bound = near_bound(tp.d2, s.tau)
        s.box_d2 = float(s.bound)
        s.prim = prim
    return s


@wp.func
def finish(p: wp.vec3, s: PointSearch, visited: int, tested: int):
    """The `ClosestPoint` of a finished search: prim -1, distance inf and point NaN when nothing was found
    within max_dist."""
    result = ClosestPoint()
    result.prim = s.prim
    result.distance = INF
    result.point = wp.vec3(NAN)
    result.nodes_visited = visited
    result.prims_tested = tested
    if s.prim >= 0:
        result.point = s.best.point
        result.distance = float(wp.sqrt(s.d2))
        result.u = s.best.u
        result.v = s.best.v
    return result


@wp.func
def packed_point_query(
    nodes: wp.array(dtype=PackedNode),
    triangles: wp.array(dtype=PackedTriangle),
    prim_order: wp.array(dtype=wp.int32),
    root_lower: wp.vec3,
    root_upper: wp.vec3,
    root_begin: int,
    root: int,
    p: wp.vec3,
    max_dist: float,
):
    """Nearest-first traversal of the packed layout (``traversal.py``): a node reference is a
    `PackedNode` position, or minus the primitive count for a leaf, and the traversal carries where
    the current node's primitive range begins. Each triangle reached is measured by
    `closest_point_on_triangle` (Ericson 2005, Sec. 5.1.5)."""
    s = start_near_search(max_dist, root_lower, root_upper)
    visited = int(0)
    tested = int(0)
    stack = vec64i()
    stack_begin = vec64i()
    stack_d = vec64f()
    top = int(0)
    node = int(0)
    begin = int(0)
    active = int(0)
    if point_is_valid(p, max_dist) == 1:
        if box_may_hold(p, root_lower, root_upper, box_distance_sq(p, root_lower, root_upper), s.box_d2, s.bound) == 1:
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
                tp = closest_point_on_triangle(p, tri.a, tri.b, tri.c)
                if tp.d2 <= s.d2:
                    s = offer(s, tp, prim_order[k])
            active = int(0)
            # Pop the nearest deferred node not farther than the best triangle so far.
            while top > 0 and active == 0:
                top -= 1
                if stack_d[top] * PRUNE_MARGIN <= s.box_d2 + PRUNE_SLACK:
                    node = stack[top]
                    begin = stack_begin[top]
                    active = 1
        else:
            n = nodes[node]
            begin_b = begin + n.count_a
            prefetch_child(nodes, triangles, n.child_a, begin)
            prefetch_child(nodes, triangles, n.child_b, begin_b)
            da = box_distance_sq(p, n.lower_a, n.upper_a)
            db = box_distance_sq(p, n.lower_b, n.upper_b)
            open_a = box_may_hold(p, n.lower_a, n.upper_a, da, s.box_d2, s.bound) == 1
            open_b = box_may_hold(p, n.lower_b, n.upper_b, db, s.box_d2, s.bound) == 1
            if open_a and open_b:
                # Visit the nearer child next, defer the farther one.
                if da <= db:
                    stack[top] = n.child_b
                    stack_begin[top] = begin_b
                    stack_d[top] = db
                    node = n.child_a
                else:
                    stack[top] = n.child_a
                    stack_begin[top] = begin
                    stack_d[top] = da
                    node = n.child_b
                    begin = begin_b
                top += 1
            elif open_a:
                node = n.child_a
            elif open_b:
                node = n.child_b
                begin = begin_b
            else:
                active = int(0)
                while top > 0 and active == 0:
                    top -= 1
                    if stack_d[top] * PRUNE_MARGIN <= s.box_d2 + PRUNE_SLACK:
                        node = stack[top]
                        begin = stack_begin[top]
                        active = 1
    return finish(p, s, visited, tested)


# A point farther outside the root box than this many times the box's extent takes the float64
# walk (`packed_far_point_query`). See `point_is_far` for the choice.
FAR_POINT = wp.constant(256.0)
vec64d = wp.types.vector(length=TRAVERSAL_STACK_SIZE, dtype=wp.float64)


@wp.func
def point_is_far(p: wp.vec3, lower: wp.vec3, upper: wp.vec3):
    """1 when p lies farther outside the box than `FAR_POINT` times its extent (the test of
    ``traversal.origin_is_far``, which far rays take); 0 for a NaN or Inf point, which the float32
    walk refuses."""
    extent = wp.max(upper[0] - lower[0], wp.max(upper[1] - lower[1], upper[2] - lower[2]))
    gap = wp.max(wp.max(lower[0] - p[0], p[0] - upper[0]),
                 wp.max(wp.max(lower[1] - p[1], p[1] - upper[1]), wp.max(lower[2] - p[2], p[2] - upper[2])))
    return wp.where(gap > FAR_POINT * extent and wp.isfinite(gap), 1, 0)


@outline_func
def packed_far_point_query(
    nodes: wp.array(dtype=PackedNode),
    triangles: wp.array(dtype=PackedTriangle),
    prim_order: wp.array(dtype=wp.int32),
    root_lower: wp.vec3,
    root_upper: wp.vec3,
    root_begin: int,
    root: int,
    p: wp.vec3,
    max_dist: float,
):
    """`packed_point_query` for a point far from the mesh: every box distance in float64
    (`box_distance_sq64`), the deferred ones kept in float64 on the stack.

    Seen from afar, the squared distances of all boxes agree to float32's resolution: the float32
    walk then orders children by rounding noise and enters every deferred node it pops (its
    float32 distance cannot be told from the best triangle's), 3-4 times the nodes a point at 1e3
    mesh sizes visits. In float64 they differ by far more than their rounding (a few 1e-16) up to
    about 1e15 sizes, and the order and the pruning are those of a near point (the same
    branch-and-bound, Ericson 2005, Sec. 5.1.5 for the triangles). Out of line: the float32 walk
    every near point runs stays as it was; a far query visits hundreds of nodes, next to which a
    call costs nothing. A box is entered when its float64 distance, less FAR_LOW's relative
    margin, is within `far_slack` of the best triangle's: the bound derived above FAR_LOW, which
    never skips the answer."""
    s = start_search(max_dist)
    visited = int(0)
    tested = int(0)
    stack = vec64i()
    stack_begin = vec64i()
    stack_d = vec64d()
    top = int(0)
    node = int(0)
    begin = int(0)
    active = int(0)
    slack = wp.float64(0.0)
    if point_is_valid(p, max_dist) == 1:
        root_d2 = box_distance_sq64(p, root_lower, root_upper)
        slack = far_slack(root_lower, root_upper, root_d2)
        if root_d2 * FAR_LOW <= s.d2 + slack:
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
                tp = closest_point_on_triangle(p, tri.a, tri.b, tri.c)
                if tp.d2 <= s.d2:
                    s = offer(s, tp, prim_order[k])
            active = int(0)
        else:
            n = nodes[node]
            begin_b = begin + n.count_a
            da = box_distance_sq64(p, n.lower_a, n.upper_a)
            db = box_distance_sq64(p, n.lower_b, n.upper_b)
            open_a = da * FAR_LOW <= s.d2 + slack
            open_b = db * FAR_LOW <= s.d2 + slack
            if open_a and open_b:
                # Visit the nearer child next, defer the farther one.
                if da <= db:
                    stack[top] = n.child_b
                    stack_begin[top] = begin_b
                    stack_d[top] = db
                    node = n.child_a
                else:
                    stack[top] = n.child_a
                    stack_begin[top] = begin
                    stack_d[top] = da
                    node = n.child_b
                    begin = begin_b
                top += 1
            elif open_a:
                node = n.child_a
            elif open_b:
                node = n.child_b
                begin = begin_b
            else:
                active = int(0)
        # Pop the nearest deferred node not farther than the best triangle so far.
        while top > 0 and active == 0:
            top -= 1
            if stack_d[top] * FAR_LOW <= s.d2 + slack:
                node = stack[top]
                begin = stack_begin[top]
                active = 1
    return finish(p, s, visited, tested)


@wp.func
def canonical_point_query(bvh: BvhView, p: wp.vec3, max_dist: float):
    """`packed_point_query` on the canonical arrays, for a view that carries no traversal layout
    (triangles measured the same way: Ericson 2005, Sec. 5.1.5)."""
    s = start_search(max_dist)
    visited = int(0)
    tested = int(0)
    stack = vec64i()
    stack_d = vec64f()
    top = int(0)
    node = int(-1)
    # A view of a box BVH has no triangles (its faces are empty): nothing to find.
    if bvh.faces.shape[0] > 0 and point_is_valid(p, max_dist) == 1:
        root_lower = bvh.node_lowers[0]
        root_upper = bvh.node_uppers[0]
        s = start_near_search(max_dist, root_lower, root_upper)
        if box_may_hold(p, root_lower, root_upper, box_distance_sq(p, root_lower, root_upper), s.box_d2, s.bound) == 1:
            node = 0
    while node >= 0:
        visited += 1
        left = bvh.node_left[node]
        if left < 0 or top >= STACK_SIZE:
            for k in range(bvh.node_begin[node], bvh.node_end[node]):
                prim = bvh.prim_order[k]
                tested += 1
                tp = closest_point_on_triangle(p, bvh.vertices[bvh.faces[prim, 0]], bvh.vertices[bvh.faces[prim, 1]],
                                               bvh.vertices[bvh.faces[prim, 2]])
                if tp.d2 <= s.d2:
                    s = offer(s, tp, prim)
            node = int(-1)
        else:
            right = bvh.node_right[node]
            left_lower = bvh.node_lowers[left]
            left_upper = bvh.node_uppers[left]
            right_lower = bvh.node_lowers[right]
            right_upper = bvh.node_uppers[right]
            dl = box_distance_sq(p, left_lower, left_upper)
            dr = box_distance_sq(p, right_lower, right_upper)
            open_l = box_may_hold(p, left_lower, left_upper, dl, s.box_d2, s.bound) == 1
            open_r = box_may_hold(p, right_lower, right_upper, dr, s.box_d2, s.bound) == 1
            node = int(-1)
            if open_l and open_r:
                if dl <= dr:
                    node = left
                    stack[top] = right
                    stack_d[top] = dr
                else:
                    node = right
                    stack[top] = left
                    stack_d[top] = dl
                top += 1
            elif open_l:
                node = left
            elif open_r:
                node = right
        while node < 0 and top > 0:
            top -= 1
            if stack_d[top] * PRUNE_MARGIN <= s.box_d2 + PRUNE_SLACK:
                node = stack[top]
    return finish(p, s, visited, tested)


# Inlined: it takes the view, which a call out of line would copy per query (`traversal.inline_func`);
# the far walk it may call stays out of line.
@inline_func
def bvh_closest_point(bvh: BvhView, point: wp.vec3, max_dist: float):
    """The closest point on the mesh to ``point`` among triangles within ``max_dist`` (inclusive),
    as a `ClosestPoint` (prim -1 and distance inf when there is none).

    Pass ``wp.inf`` (or a large number) for an unbounded query; a small ``max_dist`` is faster,
    since every box farther than it is skipped. Points with NaN or Inf coordinates find nothing.

    A branch-and-bound search, nearest child first, pruning boxes by `box_distance_sq`; each
    triangle reached is measured by `closest_point_on_triangle` (Ericson, "Real-Time Collision
    Detection", 2005, Sec. 5.1.5).
    """
    if bvh.packed_nodes.shape[0] > 0:
        root_begin = bvh.node_begin[0]
        root = wp.where(bvh.node_left[0] < 0, root_begin - bvh.node_end[0], 0)
        root_lower = bvh.node_lowers[0]
        root_upper = bvh.node_uppers[0]
        if point_is_far(point, root_lower, root_upper) == 1:
            return packed_far_point_query(bvh.packed_nodes, bvh.packed_triangles, bvh.prim_order, root_lower,
                                          root_upper, root_begin, root, point, max_dist)
        return packed_point_query(bvh.packed_nodes, bvh.packed_triangles, bvh.prim_order, root_lower, root_upper,
                                  root_begin, root, point, max_dist)
    return canonical_point_query(bvh, point, max_dist)


@wp.kernel
def closest_point_any_bound_kernel(
    bvh: BvhView,
    points: wp.array(dtype=wp.vec3),
    max_dist: Any,
    out_point: wp.array(dtype=wp.vec3),
    out_distance: wp.array(dtype=float),
    out_prim: wp.array(dtype=wp.int32),
    out_u: wp.array(dtype=float),
    out_v: wp.array(dtype=float),
    nodes_visited: wp.array(dtype=wp.int32),
    prims_tested: wp.array(dtype=wp.int32),
):
    """One point per thread; ``max_dist`` is one bound (a float) or one per point (an array, see
    `query_limit`); the weights and the statistics are written when their arrays are not empty."""
    tid = wp.tid()
    r = bvh_closest_point(bvh, points[tid], query_limit(max_dist, tid))
    out_point[tid] = r.point
    out_distance[tid] = r.distance
    out_prim[tid] = r.prim
    if out_u.shape[0] > 0:
        out_u[tid] = r.u
        out_v[tid] = r.v
    if nodes_visited.shape[0] > 0:
        nodes_visited[tid] = r.nodes_visited
        prims_tested[tid] = r.prims_tested


# One bound for every point (the common call: nothing to pack but a float), or one per point.
# Launched as these concrete overloads: launching the generic kernel would infer its argument
# types on every call (about 50 us, a quarter of a small query on the CPU), and could not take
# the int or np.float32 bound a float parameter takes. `closest_point_kernel` keeps the name and
# signature the one-bound kernel always had.
closest_point_kernel = wp.overload(closest_point_any_bound_kernel, {"max_dist": float})
closest_point_bounds_kernel = wp.overload(closest_point_any_bound_kernel, {"max_dist": wp.array(dtype=float)})


@wp.kernel
def warp_mesh_closest_point_kernel(
    mesh: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    max_dist: float,
    out_point: wp.array(dtype=wp.vec3),
    out_distance: wp.array(dtype=float),
    out_prim: wp.array(dtype=wp.int32),
):
    """The benchmark's reference: Warp's own mesh BVH and ``wp.mesh_query_point_no_sign``."""
    tid = wp.tid()
    p = points[tid]
    q = wp.mesh_query_point_no_sign(mesh, p, max_dist)
    if q.result:
        x = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
        out_point[tid] = x
        out_distance[tid] = wp.length(p - x)
        out_prim[tid] = q.face
    else:
        out_point[tid] = wp.vec3(NAN)
        out_distance[tid] = INF
        out_prim[tid] = -1
