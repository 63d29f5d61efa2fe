"""Tree-quality metrics on the device: the SAH cost of every node, depths, leaf sizes.

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

# Forward-only kernels: no adjoints to compile.
wp.set_module_options({"enable_backward": False})


@wp.func
def box_area64(lower: wp.vec3, upper: wp.vec3) -> wp.float64:
    # Surface area 2 (dx dy + dy dz + dz dx); differences taken in float64 so they cannot overflow.
    dx = wp.float64(upper[0]) - wp.float64(lower[0])
    dy = wp.float64(upper[1]) - wp.float64(lower[1])
    dz = wp.float64(upper[2]) - wp.float64(lower[2])
    return wp.float64(2.0) * (dx * dy + dy * dz + dz * dx)


@wp.func
def child_term(cost: wp.float64, child_area: wp.float64, parent_area: wp.float64) -> wp.float64:
    # P_hit = area(child) / area(parent). A parent of zero area (a point or a segment: its
    # children are then degenerate too) is hit by a ray exactly when its children are, so the
    # ratio 0 / 0 is taken as 1 rather than dropping the subtree's cost.
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
    # Eq. (1) for an interior node of box [lower, upper] over its two finished children.
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
    # term(node) x area(node), the node's share of C(root) x area(root) (sah_terms_kernel):
    # 2 T1 for an interior node, T2 N for a leaf of N primitives.
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
    # Launched over the arena; nodes below `first_node` are skipped so a caller can cost a forest
    # of subtrees (roots with parent -1) before the nodes above them exist.
    node = wp.tid()
    if node < first_node or node >= node_count[0] or node_left[node] >= 0:
        return
    node_cost[node] = t_intersect * wp.float64(node_end[node] - node_begin[node])
    parent = node_parent[node]
    while parent >= 0:
        # The first child to arrive leaves; the second sees its sibling's cost written.
        if wp.atomic_add(node_visits, parent, 1) == 0:
            return
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
    # Boxes and SAH costs in one climb, for subtrees whose boxes are not known yet (the cluster
    # subtrees of the SAH-optimized HLBVH, costed before the top levels are built).
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
        if wp.atomic_add(node_visits, parent, 1) == 0:
            return
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
    # Edges to the root, by climbing: O(depth) per node, no ordering between threads needed.
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
    # counts[0]: leaves, counts[1]: largest leaf.
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
    node = wp.tid()
    if node_left[node] >= 0:
        return
    wp.atomic_add(histogram, node_end[node] - node_begin[node], 1)
