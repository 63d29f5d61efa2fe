"""Stage 7 of HLBVH: node bounding boxes, bottom-up on the device.

Pantaleoni & Luebke 2010 ("bbox computation" in their Table 2). One thread per leaf computes
the leaf box and climbs; at each parent the first arriving child stops and the second, which
finds both children done (an atomic visit counter, as in Karras 2012), writes the union.
The same kernel refits a tree whose primitives moved (topology unchanged).
"""

import warp as wp

from .metrics import device_fence, weighted_term

# Forward-only kernels: no adjoints to compile.
wp.set_module_options({"enable_backward": False})


@wp.func
def leaf_box(
    node: int,
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    prim_order: wp.array(dtype=wp.int32),
    prim_lowers: wp.array(dtype=wp.vec3),
    prim_uppers: wp.array(dtype=wp.vec3),
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
):
    """Box of a leaf from its primitives' boxes, read through prim_order, into node_lowers/uppers."""
    p = prim_order[node_begin[node]]
    lower = prim_lowers[p]
    upper = prim_uppers[p]
    for k in range(node_begin[node] + 1, node_end[node]):
        p = prim_order[k]
        lower = wp.min(lower, prim_lowers[p])
        upper = wp.max(upper, prim_uppers[p])
    node_lowers[node] = lower
    node_uppers[node] = upper
    return 0


@wp.func
def leaf_box_in_order(
    node: int,
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    leaf_lowers: wp.array(dtype=wp.vec3),
    leaf_uppers: wp.array(dtype=wp.vec3),
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
):
    """`leaf_box` over primitive boxes already in tree order (`gather_boxes_kernel`); returns the box."""
    # Position k's box is leaf_lowers[k], read without going through prim_order.
    lower = leaf_lowers[node_begin[node]]
    upper = leaf_uppers[node_begin[node]]
    for k in range(node_begin[node] + 1, node_end[node]):
        lower = wp.min(lower, leaf_lowers[k])
        upper = wp.max(upper, leaf_uppers[k])
    node_lowers[node] = lower
    node_uppers[node] = upper
    return lower, upper


@wp.kernel
def gather_boxes_kernel(
    prim_order: wp.array(dtype=wp.int32),
    prim_lowers: wp.array(dtype=wp.vec3),
    prim_uppers: wp.array(dtype=wp.vec3),
    leaf_lowers: wp.array(dtype=wp.vec3),
    leaf_uppers: wp.array(dtype=wp.vec3),
):
    """leaf_lowers/uppers[k] = the box of primitive prim_order[k]: the primitive boxes in tree order."""
    # The primitive boxes in tree order, for the CPU's depth-first emission. Its walk reads each
    # box once, but behind a chain of dependent loads (node range, then prim_order, then the box)
    # that a serial loop cannot overlap: reading the boxes through prim_order made the walk take
    # 1.9x as long as reading them in order (11.1 against 5.9 ms on the 100k-triangle armadillo,
    # one core). This loop has no such chain, so the CPU overlaps its random reads (0.4 ms).
    k = wp.tid()
    p = prim_order[k]
    leaf_lowers[k] = prim_lowers[p]
    leaf_uppers[k] = prim_uppers[p]


@wp.kernel
def reset_visits_kernel(node_visits: wp.array(dtype=wp.int32)):
    """Zero the atomic visit counters of `node_bounds_kernel`."""
    node_visits[wp.tid()] = 0


@wp.kernel
def node_bounds_kernel(
    node_count: wp.array(dtype=wp.int32),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_parent: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    prim_order: wp.array(dtype=wp.int32),
    prim_lowers: wp.array(dtype=wp.vec3),
    prim_uppers: wp.array(dtype=wp.vec3),
    node_visits: wp.array(dtype=wp.int32),
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
):
    """Node boxes bottom-up, one thread per leaf, after Karras ("Maximizing Parallelism in the
    Construction of BVHs, Octrees, and k-d Trees", HPG 2012): the thread boxes its leaf and climbs; at
    each parent an atomic visit counter stops the first child to arrive, and the second writes the
    union. The "bbox computation" of Pantaleoni & Luebke 2010, Table 2; also a refit (topology kept)."""
    node = wp.tid()
    if node >= node_count[0] or node_left[node] >= 0:
        return
    leaf_box(node, node_begin, node_end, prim_order, prim_lowers, prim_uppers, node_lowers, node_uppers)

    parent = node_parent[node]
    while parent >= 0:
        # The first child to arrive leaves; the second sees its sibling's box written (the
        # fences order this thread's box before its visit and the visit before the reads).
        device_fence()
        if wp.atomic_add(node_visits, parent, 1) == 0:
            return
        device_fence()
        left = node_left[parent]
        right = node_right[parent]
        node_lowers[parent] = wp.min(node_lowers[left], node_lowers[right])
        node_uppers[parent] = wp.max(node_uppers[left], node_uppers[right])
        parent = node_parent[parent]


@wp.kernel
def bounds_sweep_kernel(
    first: int,
    stop: int,
    cost_slot: int,
    node_count: wp.array(dtype=wp.int32),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    prim_order: wp.array(dtype=wp.int32),
    prim_lowers: wp.array(dtype=wp.vec3),
    prim_uppers: wp.array(dtype=wp.vec3),
    price: int,
    t_traversal: wp.float64,
    t_intersect: wp.float64,
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
    cost_sum: wp.array(dtype=wp.float64),
):
    """Node boxes in one thread, one reverse sweep over the nodes [first, stop) (`stop` < 0: to
    node_count[0]); with `price`, also the sum of their SAH terms x area into cost_sum[cost_slot].

    A range whose nodes' children all lie in it can be swept beside another such range: the
    runs of seeds the depth-first emission made side by side (`HlbvhPipeline.sweep_parts`),
    with the nodes above them swept after."""
    # One thread: children are numbered after their parents, so a reverse sweep sees both
    # children finished, a leaf's box computed from its primitives as the sweep reaches it. Used
    # on the CPU device, which runs a launch's threads one after another anyway: the sweep does
    # the climb's work without its atomics and random parent hops, and in one pass over the nodes
    # where a leaf pass and an interior sweep took two (1.2 + 1.2 ms on the armadillo's 200k nodes).
    # With `price`, it also sums every node's SAH term as its box becomes final (the one-pass form
    # of Pantaleoni & Luebke 2010, eq. 1, that metrics.sah_cost divides by the root's area), so a
    # refit frame of the auto policy prices its tree without a second pass over the nodes.
    node = stop - 1
    if stop < 0:
        node = node_count[0] - 1
    total = wp.float64(0.0)
    while node >= first:
        left = node_left[node]
        if left >= 0:
            right = node_right[node]
            node_lowers[node] = wp.min(node_lowers[left], node_lowers[right])
            node_uppers[node] = wp.max(node_uppers[left], node_uppers[right])
        else:
            leaf_box(node, node_begin, node_end, prim_order, prim_lowers, prim_uppers, node_lowers, node_uppers)
        if price != 0:
            total += weighted_term(node, node_left, node_begin, node_end, node_lowers[node], node_uppers[node],
                                   t_traversal, t_intersect)
        node -= 1
    if price != 0:
        cost_sum[cost_slot] = total
