"""Top-down builders, one launch per tree level: full-sweep SAH, binned SAH, object median.

The greedy SAH sweep of MacDonald & Booth 1990 as organized by Wald, Boulos & Shirley 2007
("Ray tracing deformable scenes using dynamic bounding volume hierarchies", section 4.1): the
items are sorted once by centroid on each of the three axes, every node evaluates all N - 1
split positions of each axis (a right-to-left pass stores the suffix areas, a left-to-right pass
grows the prefix box and prices each split as area(L) * W(L) + area(R) * W(R)), and the three
per-axis orders are stably partitioned at the chosen split so the children stay sorted without
sorting again. The quality reference of Pantaleoni & Luebke 2010, Table 3.

Every level is data-parallel: one thread per open node of the level sweeps and partitions its
own range [begin, end), which no other thread touches, and an exclusive scan of the split flags
numbers the children, so children always come after their parents and the arena has no holes.

The items are primitives (weight 1 each) or, for the SAH-optimized HLBVH (section 3.3), coarse
clusters weighted by the SAH cost of their subtrees. Split costs are evaluated in float64.

Orders are stored flat: ``order[axis * num_items + position]``.
"""

import warp as wp

from .metrics import box_area64

# Forward-only kernels: no adjoints to compile.
wp.set_module_options({"enable_backward": False})

#: Split rules, the `mode` argument of `choose_splits_kernel`.
MODE_SWEEP = wp.constant(0)
MODE_BINNED = wp.constant(1)
MODE_MEDIAN = wp.constant(2)

# Larger than any split cost (areas are at most ~1e78 in float64, weights ~1e9).
NO_COST = wp.constant(wp.float64(1.0e300))


@wp.func
def item_centroid(lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3), item: int, axis: int) -> float:
    return 0.5 * (lowers[item][axis] + uppers[item][axis])


@wp.kernel
def centroid_keys_kernel(
    item_lowers: wp.array(dtype=wp.vec3),
    item_uppers: wp.array(dtype=wp.vec3),
    axis: int,
    keys: wp.array(dtype=float),
    ids: wp.array(dtype=wp.int32),
):
    # Sorted with ids as values by a stable radix sort: equal centroids stay in index order.
    i = wp.tid()
    keys[i] = item_centroid(item_lowers, item_uppers, i, axis)
    ids[i] = i


@wp.kernel
def init_top_down_kernel(
    num_items: int,
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_parent: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    node_count: wp.array(dtype=wp.int32),
    level_nodes: wp.array(dtype=wp.int32),
    level_count: wp.array(dtype=wp.int32),
):
    # Launched over the arena: every node starts as a leaf; the first level is the root alone.
    i = wp.tid()
    node_left[i] = -1
    node_right[i] = -1
    node_parent[i] = -1
    if i == 0:
        node_begin[0] = 0
        node_end[0] = num_items
        node_count[0] = 1
        level_nodes[0] = 0
        level_count[0] = 1


@wp.func
def bin_of(c: float, cmin: float, scale: float, num_bins: int) -> int:
    return wp.clamp(int((c - cmin) * scale), 0, num_bins - 1)


@wp.kernel
def choose_splits_kernel(
    level_count: wp.array(dtype=wp.int32),
    level_nodes: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    order: wp.array(dtype=wp.int32),
    num_items: int,
    item_lowers: wp.array(dtype=wp.vec3),
    item_uppers: wp.array(dtype=wp.vec3),
    item_weights: wp.array(dtype=wp.float64),
    mode: int,
    num_bins: int,
    max_leaf_size: int,
    terminate_leaf_size: int,
    t_traversal: wp.float64,
    t_intersect: wp.float64,
    suffix_area: wp.array(dtype=wp.float64),
    suffix_weight: wp.array(dtype=wp.float64),
    split_axis: wp.array(dtype=wp.int32),
    split_pos: wp.array(dtype=wp.int32),
    split_flag: wp.array(dtype=wp.int32),
):
    s = wp.tid()
    split_flag[s] = 0
    if s >= level_count[0]:
        return
    node = level_nodes[s]
    b = node_begin[node]
    e = node_end[node]
    size = e - b
    if size <= max_leaf_size:
        return

    if mode == MODE_MEDIAN:
        # Object median on the axis of largest centroid extent: the extent is read off the ends
        # of the presorted order, no pass over the range needed.
        best_axis = int(0)
        best_extent = float(-1.0)
        for a in range(3):
            lo_c = item_centroid(item_lowers, item_uppers, order[a * num_items + b], a)
            hi_c = item_centroid(item_lowers, item_uppers, order[a * num_items + e - 1], a)
            if hi_c - lo_c > best_extent:
                best_extent = hi_c - lo_c
                best_axis = a
        split_axis[s] = best_axis
        split_pos[s] = b + size // 2
        split_flag[s] = 1
        return

    best_cost = NO_COST
    best_axis = int(-1)
    best_pos = int(-1)
    node_area = wp.float64(0.0)
    total_weight = wp.float64(0.0)
    for a in range(3):
        base = a * num_items
        cmin = item_centroid(item_lowers, item_uppers, order[base + b], a)
        cmax = item_centroid(item_lowers, item_uppers, order[base + e - 1], a)
        scale = float(0.0)
        if mode == MODE_BINNED:
            # Binned SAH (Wald 2007) prices only the bin boundaries; with the items presorted a
            # boundary is where two neighbours fall into different bins.
            if not (cmax > cmin):
                continue
            scale = float(num_bins) / (cmax - cmin)

        # Right to left: area and weight of every suffix [i, e).
        item = order[base + e - 1]
        lower = item_lowers[item]
        upper = item_uppers[item]
        w = item_weights[item]
        suffix_area[e - 1] = box_area64(lower, upper)
        suffix_weight[e - 1] = w
        for k in range(size - 2):
            i = e - 2 - k
            item = order[base + i]
            lower = wp.min(lower, item_lowers[item])
            upper = wp.max(upper, item_uppers[item])
            w += item_weights[item]
            suffix_area[i] = box_area64(lower, upper)
            suffix_weight[i] = w

        # Left to right: the prefix [b, i) against the stored suffix [i, e).
        item = order[base + b]
        lower = item_lowers[item]
        upper = item_uppers[item]
        w = item_weights[item]
        prev_bin = int(0)
        for i in range(b + 1, e):
            candidate = True
            if mode == MODE_BINNED:
                next_bin = bin_of(item_centroid(item_lowers, item_uppers, order[base + i], a), cmin, scale, num_bins)
                candidate = prev_bin != next_bin
                prev_bin = next_bin
            if candidate:
                cost = box_area64(lower, upper) * w + suffix_area[i] * suffix_weight[i]
                # Exact ties go to the position nearest the middle (then the lower axis): equal or
                # zero-area boxes tie everywhere, and leftmost ties would chain them N deep.
                better = cost < best_cost
                if cost == best_cost and best_pos >= 0:
                    better = wp.abs(2 * i - b - e) < wp.abs(2 * best_pos - b - e)
                if better:
                    best_cost = cost
                    best_axis = a
                    best_pos = i
            item = order[base + i]
            lower = wp.min(lower, item_lowers[item])
            upper = wp.max(upper, item_uppers[item])
            w += item_weights[item]
        node_area = box_area64(lower, upper)
        total_weight = w

    if best_axis < 0:
        # Binned: every centroid coincides on every axis, no plane separates them; halve by index.
        split_axis[s] = 0
        split_pos[s] = b + size // 2
        split_flag[s] = 1
        return

    if size <= terminate_leaf_size:
        # Optional SAH termination: keep the node a leaf when splitting costs more than
        # intersecting all its items, C = T1 * 2 + T2 * best / area(node) against T2 * W.
        split_cost = wp.float64(2.0) * t_traversal + t_intersect * total_weight
        if node_area > wp.float64(0.0):
            split_cost = wp.float64(2.0) * t_traversal + t_intersect * best_cost / node_area
        if split_cost >= t_intersect * total_weight:
            return

    split_axis[s] = best_axis
    split_pos[s] = best_pos
    split_flag[s] = 1


@wp.kernel
def emit_children_kernel(
    level_count: wp.array(dtype=wp.int32),
    level_nodes: wp.array(dtype=wp.int32),
    split_axis: wp.array(dtype=wp.int32),
    split_pos: wp.array(dtype=wp.int32),
    split_flag: wp.array(dtype=wp.int32),
    split_offset: wp.array(dtype=wp.int32),
    num_items: int,
    order_in: wp.array(dtype=wp.int32),
    order_out: wp.array(dtype=wp.int32),
    item_side: wp.array(dtype=wp.int32),
    node_count: wp.array(dtype=wp.int32),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_parent: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    next_level_nodes: wp.array(dtype=wp.int32),
    item_order: wp.array(dtype=wp.int32),
):
    s = wp.tid()
    if s >= level_count[0]:
        return
    node = level_nodes[s]
    b = node_begin[node]
    e = node_end[node]
    if split_flag[s] == 0:
        # A finished leaf: its items take their final place in tree order (any axis will do,
        # all three orders hold the same set on [b, e)).
        for i in range(b, e):
            item_order[i] = order_in[i]
        return

    # The s-th split's two children: numbered by the scan, after every node of earlier levels.
    left = node_count[0] + 2 * split_offset[s]
    right = left + 1
    pos = split_pos[s]
    node_left[node] = left
    node_right[node] = right
    node_parent[left] = node
    node_parent[right] = node
    node_begin[left] = b
    node_end[left] = pos
    node_begin[right] = pos
    node_end[right] = e
    next_level_nodes[2 * split_offset[s]] = left
    next_level_nodes[2 * split_offset[s] + 1] = right

    # Stable partition of all three orders by the side each item took on the split axis.
    base = split_axis[s] * num_items
    for i in range(b, e):
        if i < pos:
            item_side[order_in[base + i]] = 1
        else:
            item_side[order_in[base + i]] = 0
    for a in range(3):
        base = a * num_items
        lo = b
        hi = pos
        for i in range(b, e):
            item = order_in[base + i]
            if item_side[item] != 0:
                order_out[base + lo] = item
                lo += 1
            else:
                order_out[base + hi] = item
                hi += 1


@wp.kernel
def advance_level_kernel(
    level_count: wp.array(dtype=wp.int32),
    split_flag: wp.array(dtype=wp.int32),
    split_offset: wp.array(dtype=wp.int32),
    node_count: wp.array(dtype=wp.int32),
    next_level_count: wp.array(dtype=wp.int32),
):
    last = level_count[0] - 1
    splits = split_offset[last] + split_flag[last]
    node_count[0] = node_count[0] + 2 * splits
    next_level_count[0] = 2 * splits


@wp.kernel
def fill_float64_kernel(values: wp.array(dtype=wp.float64), value: wp.float64):
    values[wp.tid()] = value
