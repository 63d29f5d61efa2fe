"""Tree-quality metrics on the device: the SAH cost of every node, depths, leaf sizes, and the
end-point overlap (Aila, Karras & Laine 2013; at the end of this file).

The SAH cost is the recursive formula of Pantaleoni & Luebke 2010, section 4.2 (eq. 1, after
Goldsmith & Salmon 1987):

    C(leaf) = T2 * N_prims
    C(node) = T1 * N_children + sum_i C(child_i) * area(child_i) / area(node)

evaluated bottom-up with the atomic visit counter of kernels/bounds.py: the second child to
reach a parent finds both child costs written and computes the parent's.

Areas are taken in float64 from the float32 corners: extents of up to 2 * 3.4e38 squared would
overflow float32, and at 1e18 coordinates float32 products already lose the ratio.
"""

import warp as wp

from .traversal import box_overlap

# Forward-only kernels: no adjoints to compile.
wp.set_module_options({"enable_backward": False})


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    __threadfence();
#endif
"""
)
def device_fence():
    """``__threadfence()`` on CUDA (nothing on the CPU, whose launches run their threads in
    sequence). The climbs below publish a box through an atomic visit counter, Karras 2012: the
    first child to arrive writes its box and leaves, the second reads it. Without a fence between
    the first one's stores and its atomic, and between the second one's atomic and its loads, the
    second may read the box from before the store (stores and relaxed atomics to other addresses
    are not ordered across SMs, and the reader's L1 may hold the line); Warp's own BVH refit
    (native/bvh.cu) fences the same way."""
    ...


@wp.func
def box_area64(lower: wp.vec3, upper: wp.vec3) -> wp.float64:
    """Surface area 2 (dx dy + dy dz + dz dx) of the box, in float64."""
    # Differences taken in float64 so they cannot overflow.
    dx = wp.float64(upper[0]) - wp.float64(lower[0])
    dy = wp.float64(upper[1]) - wp.float64(lower[1])
    dz = wp.float64(upper[2]) - wp.float64(lower[2])
    return wp.float64(2.0) * (dx * dy + dy * dz + dz * dx)


@wp.func
def child_term(cost: wp.float64, child_area: wp.float64, parent_area: wp.float64) -> wp.float64:
    """C(child) * P_hit(child), P_hit = area(child) / area(parent): one summand of eq. (1)."""
    # A parent of zero area (a point or a segment: its children are then degenerate too) is hit
    # by a ray exactly when its children are, so the ratio 0 / 0 is taken as 1 rather than
    # dropping the subtree's cost.
    if parent_area > wp.float64(0.0):
        return cost * (child_area / parent_area)
    return cost


@wp.func
def interior_cost(
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
    node_cost: wp.array(dtype=wp.float64),
    left: int,
    right: int,
    lower: wp.vec3,
    upper: wp.vec3,
    t_traversal: wp.float64,
) -> wp.float64:
    """C(node) of eq. (1) (Pantaleoni & Luebke 2010) for an interior node of box [lower, upper] over
    its two finished children: 2 T1 plus each child's cost weighted by its area ratio."""
    parent_area = box_area64(lower, upper)
    c = wp.float64(2.0) * t_traversal
    c += child_term(node_cost[left], box_area64(node_lowers[left], node_uppers[left]), parent_area)
    c += child_term(node_cost[right], box_area64(node_lowers[right], node_uppers[right]), parent_area)
    return c


@wp.func
def weighted_term(
    node: int,
    node_left: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    lower: wp.vec3,
    upper: wp.vec3,
    t_traversal: wp.float64,
    t_intersect: wp.float64,
) -> wp.float64:
    """term(node) x area(node), the node's share of C(root) x area(root) (`sah_terms_kernel`):
    2 T1 for an interior node, T2 N for a leaf of N primitives."""
    term = wp.float64(2.0) * t_traversal
    if node_left[node] < 0:
        term = t_intersect * wp.float64(node_end[node] - node_begin[node])
    return term * box_area64(lower, upper)


@wp.kernel
def sah_terms_kernel(
    node_count: wp.array(dtype=wp.int32),
    node_left: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
    t_traversal: wp.float64,
    t_intersect: wp.float64,
    chunk: int,
    partial: wp.array(dtype=wp.float64),
):
    """The tree's SAH cost (Pantaleoni & Luebke 2010, section 4.2, eq. 1; the SAH of Goldsmith &
    Salmon 1987 and MacDonald & Booth 1990) in one pass: thread c sums term(n) x area(n) over its chunk
    of nodes into partial[c]."""
    # The root's cost without the climb: multiplying eq. (1) by area(node) gives
    # S(node) = term(node) area(node) + sum_i S(child_i), with term = 2 T1 for an interior node and
    # T2 N for a leaf, so C(root) = sum over all nodes of term(n) area(n) / area(root). A zero-area
    # subtree adds nothing either way (the ratio into it is 0 / area(parent)); the caller handles a
    # root of zero area. One thread sums a chunk of nodes, in index order, so the sum is the same
    # on every run; the host adds the chunks' sums.
    c = wp.tid()
    count = node_count[0]
    begin = c * chunk
    end = wp.min(begin + chunk, count)
    total = wp.float64(0.0)
    for node in range(begin, end):
        total += weighted_term(node, node_left, node_begin, node_end, node_lowers[node], node_uppers[node],
                               t_traversal, t_intersect)
    partial[c] = total


@wp.kernel
def reset_visits_kernel(node_visits: wp.array(dtype=wp.int32)):
    """Zero the atomic visit counters of the bottom-up climbs."""
    node_visits[wp.tid()] = 0


@wp.kernel
def sah_cost_kernel(
    first_node: int,
    node_count: wp.array(dtype=wp.int32),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_parent: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
    t_traversal: wp.float64,
    t_intersect: wp.float64,
    node_visits: wp.array(dtype=wp.int32),
    node_cost: wp.array(dtype=wp.float64),
):
    """SAH cost of every node's subtree (Pantaleoni & Luebke 2010, eq. 1; the SAH of Goldsmith & Salmon
    1987 and MacDonald & Booth 1990), bottom-up: one thread per leaf climbs, and at each parent the
    atomic visit counter of Karras 2012 lets the second child to arrive write the parent's cost."""
    # Launched over the arena; nodes below `first_node` are skipped so a caller can cost a forest
    # of subtrees (roots with parent -1) before the nodes above them exist.
    node = wp.tid()
    if node < first_node or node >= node_count[0] or node_left[node] >= 0:
        return
    node_cost[node] = t_intersect * wp.float64(node_end[node] - node_begin[node])
    parent = node_parent[node]
    while parent >= 0:
        # The first child to arrive leaves; the second sees its sibling's cost written (fenced
        # as in bounds.node_bounds_kernel).
        device_fence()
        if wp.atomic_add(node_visits, parent, 1) == 0:
            return
        device_fence()
        left = node_left[parent]
        right = node_right[parent]
        node_cost[parent] = interior_cost(node_lowers, node_uppers, node_cost, left, right, node_lowers[parent],
                                          node_uppers[parent], t_traversal)
        parent = node_parent[parent]


@wp.kernel
def bounds_and_cost_kernel(
    first_node: int,
    node_count: wp.array(dtype=wp.int32),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_parent: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    prim_order: wp.array(dtype=wp.int32),
    prim_lowers: wp.array(dtype=wp.vec3),
    prim_uppers: wp.array(dtype=wp.vec3),
    t_traversal: wp.float64,
    t_intersect: wp.float64,
    node_visits: wp.array(dtype=wp.int32),
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
    node_cost: wp.array(dtype=wp.float64),
):
    """Boxes and SAH costs (eq. 1) in one climb, for subtrees whose boxes are not known yet: the
    cluster subtrees of the SAH-optimized HLBVH (Pantaleoni & Luebke 2010, section 3.3), costed before
    the top levels are built."""
    node = wp.tid()
    if node < first_node or node >= node_count[0] or node_left[node] >= 0:
        return
    b = node_begin[node]
    p = prim_order[b]
    lower = prim_lowers[p]
    upper = prim_uppers[p]
    for k in range(b + 1, node_end[node]):
        p = prim_order[k]
        lower = wp.min(lower, prim_lowers[p])
        upper = wp.max(upper, prim_uppers[p])
    node_lowers[node] = lower
    node_uppers[node] = upper
    node_cost[node] = t_intersect * wp.float64(node_end[node] - b)
    parent = node_parent[node]
    while parent >= 0:
        device_fence()
        if wp.atomic_add(node_visits, parent, 1) == 0:
            return
        device_fence()
        left = node_left[parent]
        right = node_right[parent]
        lower = wp.min(node_lowers[left], node_lowers[right])
        upper = wp.max(node_uppers[left], node_uppers[right])
        node_lowers[parent] = lower
        node_uppers[parent] = upper
        node_cost[parent] = interior_cost(node_lowers, node_uppers, node_cost, left, right, lower, upper, t_traversal)
        parent = node_parent[parent]


@wp.kernel
def node_depth_kernel(
    node_parent: wp.array(dtype=wp.int32),
    node_depth: wp.array(dtype=wp.int32),
    max_depth: wp.array(dtype=wp.int32),
):
    """Depth of every node (edges to the root), and the largest into max_depth[0]."""
    # By climbing: O(depth) per node, no ordering between threads needed.
    node = wp.tid()
    d = int(0)
    parent = node_parent[node]
    while parent >= 0:
        d += 1
        parent = node_parent[parent]
    node_depth[node] = d
    wp.atomic_max(max_depth, 0, d)


@wp.kernel
def leaf_sizes_kernel(
    node_left: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
):
    """counts[0]: the number of leaves, counts[1]: the largest leaf's primitive count."""
    node = wp.tid()
    if node_left[node] >= 0:
        return
    wp.atomic_add(counts, 0, 1)
    wp.atomic_max(counts, 1, node_end[node] - node_begin[node])


@wp.kernel
def leaf_histogram_kernel(
    node_left: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    histogram: wp.array(dtype=wp.int32),
):
    """histogram[k] counts the leaves of k primitives."""
    node = wp.tid()
    if node_left[node] >= 0:
        return
    wp.atomic_add(histogram, node_end[node] - node_begin[node], 1)


# End-point overlap (Aila, Karras & Laine 2013): the area of every triangle lying inside the box of
# a node whose subtree does not hold it. A clipped triangle gains at most one vertex per plane.
CLIP_CAPACITY = 9
mat93d = wp.types.matrix(shape=(CLIP_CAPACITY, 3), dtype=wp.float64)
EPO_STACK_SIZE = 64
vec64i = wp.types.vector(length=EPO_STACK_SIZE, dtype=wp.int32)
EPO_STACK = wp.constant(EPO_STACK_SIZE)


@wp.func
def clip_polygon(polygon: mat93d, count: int, axis: int, bound: wp.float64, sign: wp.float64):
    """Sutherland-Hodgman ("Reentrant Polygon Clipping", CACM 1974): the part of the polygon where
    sign * (p[axis] - bound) >= 0."""
    out = mat93d()
    kept = int(0)
    for i in range(count):
        p = polygon[i]
        q = polygon[(i + 1) % count]
        dp = sign * (p[axis] - bound)
        dq = sign * (q[axis] - bound)
        if dp >= wp.float64(0.0):
            out[kept] = p
            kept += 1
        if (dp >= wp.float64(0.0)) != (dq >= wp.float64(0.0)):
            # The edge crosses the plane: dp and dq have opposite signs, so dp - dq is not zero.
            t = dp / (dp - dq)
            crossing = p + t * (q - p)
            # Land exactly on the plane: the next plane's test must not see rounding past it.
            crossing[axis] = bound
            out[kept] = crossing
            kept += 1
    return out, kept


@wp.func
def clip_to_slab(polygon: mat93d, count: int, axis: int, lower: wp.float64, upper: wp.float64):
    """The part of the polygon with lower <= p[axis] <= upper."""
    if count > 0:
        polygon, count = clip_polygon(polygon, count, axis, lower, wp.float64(1.0))
    if count > 0:
        polygon, count = clip_polygon(polygon, count, axis, upper, wp.float64(-1.0))
    return polygon, count


@wp.func
def triangle_in_box(a: wp.vec3, b: wp.vec3, c: wp.vec3, lower: wp.vec3, upper: wp.vec3):
    """The polygon of triangle abc inside the closed box [lower, upper], in float64 (the EPO's
    overlap; the part of a triangle a spatial-split reference stands for)."""
    polygon = mat93d()
    polygon[0] = wp.vec3d(a)
    polygon[1] = wp.vec3d(b)
    polygon[2] = wp.vec3d(c)
    count = int(3)
    for axis in range(3):
        polygon, count = clip_to_slab(polygon, count, axis, wp.float64(lower[axis]), wp.float64(upper[axis]))
    return polygon, count


@wp.func
def clipped_triangle_area(a: wp.vec3, b: wp.vec3, c: wp.vec3, lower: wp.vec3, upper: wp.vec3) -> wp.float64:
    """Area of triangle abc inside the closed box [lower, upper], in float64."""
    polygon, count = triangle_in_box(a, b, c, lower, upper)
    # A fan from the first vertex: half the length of the summed cross products (planar polygon).
    twice = wp.vec3d()
    for i in range(1, count - 1):
        twice += wp.cross(polygon[i] - polygon[0], polygon[i + 1] - polygon[0])
    return wp.float64(0.5) * wp.length(twice)


@wp.struct
class RefIndex:
    """Where each triangle sits in prim_order, for trees that list a triangle more than once
    (spatial splits): positions ``positions[start[p]:start[p + 1]]`` of triangle p, ascending, and
    the leaf holding each position. Unused (empty) when ``has_duplicates`` is 0."""

    has_duplicates: int
    start: wp.array(dtype=wp.int32)
    positions: wp.array(dtype=wp.int32)
    leaf_of: wp.array(dtype=wp.int32)


@wp.func
def counted_here(refs: RefIndex, node_lowers: wp.array(dtype=wp.vec3), node_uppers: wp.array(dtype=wp.vec3),
                 begin: int, end: int, lower: wp.vec3, upper: wp.vec3, p: int, k: int) -> int:
    """1 if foreign triangle p, met at position k, counts for the node (range [begin, end), box
    [lower, upper]) in the EPO, else 0."""
    # A triangle with a reference under the node is not foreign to it; a foreign triangle met
    # through several references counts once: at the first of them whose leaf meets the box
    # (the walk reaches every such leaf, or a whole range holding it).
    first_met = int(-1)
    for i in range(refs.start[p], refs.start[p + 1]):
        q = refs.positions[i]
        if q >= begin and q < end:
            return 0
        leaf = refs.leaf_of[q]
        if first_met < 0 and box_overlap(lower, upper, node_lowers[leaf], node_uppers[leaf]) == 1:
            first_met = q
    if first_met == k:
        return 1
    return 0


@wp.func
def foreign_area(
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    prim_order: wp.array(dtype=wp.int32),
    prim_lowers: wp.array(dtype=wp.vec3),
    prim_uppers: wp.array(dtype=wp.vec3),
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.int32, ndim=2),
    refs: RefIndex,
    node: int,
    first: int,
    last: int,
) -> wp.float64:
    """Area inside the node's box of the triangles at positions [first, last) of prim_order that lie
    outside the node's own range: the node's share of A((S minus Q(n)) inside box(n)) in the end-point
    overlap of Aila, Karras & Laine 2013."""
    area = wp.float64(0.0)
    lower = node_lowers[node]
    upper = node_uppers[node]
    for k in range(first, last):
        if k < node_begin[node] or k >= node_end[node]:
            p = prim_order[k]
            if box_overlap(lower, upper, prim_lowers[p], prim_uppers[p]) == 1:
                if refs.has_duplicates == 0 or counted_here(refs, node_lowers, node_uppers, node_begin[node],
                                                            node_end[node], lower, upper, p, k) == 1:
                    area += clipped_triangle_area(vertices[faces[p, 0]], vertices[faces[p, 1]],
                                                  vertices[faces[p, 2]], lower, upper)
    return area


@wp.kernel
def end_point_overlap_kernel(
    first_node: int,
    node_count: wp.array(dtype=wp.int32),
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    prim_order: wp.array(dtype=wp.int32),
    prim_lowers: wp.array(dtype=wp.vec3),
    prim_uppers: wp.array(dtype=wp.vec3),
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.int32, ndim=2),
    refs: RefIndex,
    t_traversal: wp.float64,
    t_intersect: wp.float64,
    node_epo: wp.array(dtype=wp.float64),
):
    """Per node n: term(n) * area((S minus Q(n)) inside box(n)), S all triangles, Q(n) those
    under n, term(n) the node's own term of the SAH (2 T1 for an interior node, T2 N for a leaf):
    node n's summand of the end-point overlap (Aila, Karras & Laine, "On Quality Metrics of
    Bounding Volume Hierarchies", HPG 2013), before the division by A(S).

    A walk from the root visits the nodes whose boxes meet n's, skipping n's own subtree (its range
    of prim_order lies inside n's), and clips each foreign triangle to n's box.
    """
    n = first_node + wp.tid()
    if n >= node_count[0]:
        return
    lower = node_lowers[n]
    upper = node_uppers[n]
    begin = node_begin[n]
    end = node_end[n]
    area = wp.float64(0.0)
    stack = vec64i()
    top = int(0)
    node = int(0)
    while node >= 0:
        inside = node_begin[node] >= begin and node_end[node] <= end
        if inside or box_overlap(lower, upper, node_lowers[node], node_uppers[node]) == 0:
            node = -1
        else:
            left = node_left[node]
            # A full stack (a tree deeper than it) tests the node's whole range instead.
            if left < 0 or top >= EPO_STACK - 1:
                area += foreign_area(node_lowers, node_uppers, node_begin, node_end, prim_order, prim_lowers,
                                     prim_uppers, vertices, faces, refs, n, node_begin[node], node_end[node])
                node = -1
            else:
                stack[top] = node_right[node]
                top += 1
                node = left
        if node < 0 and top > 0:
            top -= 1
            node = stack[top]
    term = wp.float64(2.0) * t_traversal
    if node_left[n] < 0:
        term = t_intersect * wp.float64(end - begin)
    node_epo[n] = term * area


@wp.kernel
def triangle_areas_kernel(vertices: wp.array(dtype=wp.vec3), faces: wp.array(dtype=wp.int32, ndim=2),
                          areas: wp.array(dtype=wp.float64)):
    """Area of every triangle in float64; their sum is the EPO's A(S)."""
    i = wp.tid()
    a = wp.vec3d(vertices[faces[i, 0]])
    areas[i] = wp.float64(0.5) * wp.length(wp.cross(wp.vec3d(vertices[faces[i, 1]]) - a,
                                                    wp.vec3d(vertices[faces[i, 2]]) - a))
