"""Top-down builders, one launch per tree level: full-sweep SAH, binned SAH, object median.

The greedy SAH sweep of MacDonald & Booth 1990 as organized by Wald, Boulos & Shirley 2007
("Ray tracing deformable scenes using dynamic bounding volume hierarchies", section 4.1): the
items are sorted once by centroid on each of the three axes, every node evaluates all N - 1
split positions of each axis (a right-to-left pass stores area(R) * W(R) of every suffix, a left-to-right pass
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

from typing import Any

import warp as wp

from .metrics import box_area64
from .treelets import link_children

# Forward-only kernels: no adjoints to compile.
wp.set_module_options({"enable_backward": False})

#: Split rules, the `mode` argument of `choose_splits_kernel`.
MODE_SWEEP = wp.constant(0)
MODE_BINNED = wp.constant(1)
MODE_MEDIAN = wp.constant(2)

# The price of "no split found yet": infinite, so that every finite price beats it. A finite mark
# (1e300, above any price of unit weights: areas reach ~1e78) can lie below every price of heavily
# weighted items (`TopDownBuilder.build_levels`); then no split was ever found, and every node
# fell back to the index median.
NO_COST = wp.constant(wp.float64(float("inf")))


@wp.func
def item_centroid(lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3), item: int, axis: int) -> float:
    """Centroid of item `item` along `axis`."""
    # As morton.box_centroid: in float32 lower + upper overflows past 1.7e38.
    return centroid_of(lowers[item][axis], uppers[item][axis])


@wp.func
def centroid_of(lower: float, upper: float) -> float:
    """0.5 * (lower + upper) without overflow, as `morton.box_centroid`."""
    c = 0.5 * (lower + upper)
    return wp.where(wp.abs(c) > BIG, 0.5 * lower + 0.5 * upper, c)


@wp.func
def ordered_bits(x: float) -> int:
    """The bits of a float32 as an int32 that sorts like the float."""
    # Non-negative floats already sort so; negative ones are flipped below them. Adding 0.0 turns
    # -0.0 into +0.0, equal to it.
    bits = wp.cast(x + 0.0, wp.int32)
    if bits < 0:
        bits = bits ^ 0x7FFFFFFF
    return bits


@wp.kernel
def centroid_keys_kernel(
    item_lowers: wp.array(dtype=wp.vec3),
    item_uppers: wp.array(dtype=wp.vec3),
    axis: int,
    keys: wp.array(dtype=wp.int32),
    ids: wp.array(dtype=wp.int32),
):
    """Sort keys of the items' centroids along `axis` (order-preserving int32 bits), with the item ids."""
    # Sorted with ids as values by a stable radix sort: equal centroids stay in index order. The
    # keys are the centroids' bits as order-preserving integers: the same order as sorting the
    # floats, and Warp's radix sort takes int32 keys in about 0.6x the time of float32 ones on
    # the CPU (0.26 against 0.40 ms for 11,771 keys).
    i = wp.tid()
    keys[i] = ordered_bits(item_centroid(item_lowers, item_uppers, i, axis))
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
    """Reset the arena (every node a parentless leaf) and make the root [0, num_items) the first level."""
    # Launched over the arena.
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
def bin_of(c: float, cmin: float, scale: wp.float64, num_bins: int) -> int:
    """Bin of centroid c: floor((c - cmin) * scale), clamped to [0, num_bins - 1]."""
    # In float64, with `scale` = num_bins / extent: over a centroid extent near float32's smallest
    # normal (about 1e-38) the float32 scale overflowed to infinity and every item fell in one
    # bin (a valid but poor tree). Clamped before the conversion, which is undefined past int32.
    x = (wp.float64(c) - wp.float64(cmin)) * scale
    if x >= wp.float64(num_bins - 1):
        return num_bins - 1
    if x > wp.float64(0.0):
        return int(x)
    return 0


# Sweeps over per-bin boxes kept in a thread's local arrays (Wald 2007), shared by the recursive-SAH
# builder's temporary BVHs and the SBVH's object and spatial splits: at most this many bins.
MAX_SWEEP_BINS = 64
sweep_areas = wp.types.vector(length=MAX_SWEEP_BINS, dtype=wp.float64)
sweep_counts = wp.types.vector(length=MAX_SWEEP_BINS, dtype=wp.int32)
# The empty box's corners for min / max reductions: float32's largest finite value. At 3e38,
# boxes of finite input past it (up to 3.4e38, accepted) kept the sentinel as a corner.
BIG = wp.constant(3.4028234663852886e38)


@wp.func
def sweep_bin_boundaries(
    boxes_lo: Any,
    boxes_hi: Any,
    enter: Any,
    leave: Any,
    axis: int,
    num_bins: int,
    n: int,
    best_cost: wp.float64,
    best_axis: int,
    best_bin: int,
    best_left: int,
    best_right: int,
):
    """Price the boundaries j = 1 .. num_bins - 1 of one axis's bins (slots axis * num_bins + j)
    by A(L) N(L) + A(R) N(R): N(L) counts `enter` of the bins below j, N(R) counts `leave` of the
    bins from j on. An object split passes each bin's count as both; a spatial split's
    references enter at the bin of their lower corner and leave at their upper corner's. Both
    sides non-empty and smaller than n. Returns the best so far, updated: the cheapest, of exact
    equals the most balanced (least |N(L) - N(R)|), then the first in axis-then-boundary order.

    The binned SAH sweep of Wald ("On Fast Construction of SAH-based Bounding Volume Hierarchies",
    IEEE RT 2007): the greedy SAH split of MacDonald & Booth 1990 priced at bin boundaries only, one
    right-to-left pass for the suffix boxes and one left-to-right pass for the prefixes."""
    right_area = sweep_areas()
    right_count = sweep_counts()
    r_lo = wp.vec3(BIG)
    r_hi = wp.vec3(-BIG)
    r_n = int(0)
    for j in range(num_bins - 1, 0, -1):
        slot = axis * num_bins + j
        r_lo = wp.min(r_lo, wp.vec3(boxes_lo[slot]))
        r_hi = wp.max(r_hi, wp.vec3(boxes_hi[slot]))
        r_n += leave[slot]
        right_area[j] = box_area64(r_lo, r_hi)
        right_count[j] = r_n
    l_lo = wp.vec3(BIG)
    l_hi = wp.vec3(-BIG)
    l_n = int(0)
    for j in range(1, num_bins):
        slot = axis * num_bins + j - 1
        l_lo = wp.min(l_lo, wp.vec3(boxes_lo[slot]))
        l_hi = wp.max(l_hi, wp.vec3(boxes_hi[slot]))
        l_n += enter[slot]
        r_n = right_count[j]
        if l_n > 0 and r_n > 0 and l_n < n and r_n < n:
            cost = box_area64(l_lo, l_hi) * wp.float64(l_n) + right_area[j] * wp.float64(r_n)
            better = best_axis < 0 or cost < best_cost
            if best_axis >= 0 and cost == best_cost:
                # Zero-area boxes (degenerate triangles on one axis-parallel line) price every
                # boundary at 0: the first one peeled a bin off per level, a chain some 60 ln N
                # deep, where the sweep builders send exact ties to the middle.
                better = wp.abs(l_n - r_n) < wp.abs(best_left - best_right)
            if better:
                best_cost = cost
                best_axis = axis
                best_bin = j
                best_left = l_n
                best_right = r_n
    return best_cost, best_axis, best_bin, best_left, best_right


@wp.func
def best_bin_split(boxes_lo: Any, boxes_hi: Any, enter: Any, leave: Any, extent: wp.vec3, num_bins: int, n: int):
    """The cheapest bin boundary over the axes of nonzero `extent`, of exact equals the most
    balanced (`sweep_bin_boundaries` per axis, binned SAH after Wald 2007): ``(cost, axis,
    boundary, left count, right count)``, axis -1 where none splits."""
    best_cost = wp.float64(0.0)
    best_axis = int(-1)
    best_bin = int(0)
    best_left = int(0)
    best_right = int(0)
    for axis in range(3):
        if extent[axis] > 0.0:
            best_cost, best_axis, best_bin, best_left, best_right = sweep_bin_boundaries(
                boxes_lo, boxes_hi, enter, leave, axis, num_bins, n, best_cost, best_axis, best_bin, best_left,
                best_right)
    return best_cost, best_axis, best_bin, best_left, best_right


@wp.struct
class SplitInputs:
    """What a split decision reads: the presorted orders, the items, the rule and its scratch.

    Scratch arrays are indexed by position, so a node touches only the slots of its own range.
    """

    order: wp.array(dtype=wp.int32)
    num_items: int
    item_lowers: wp.array(dtype=wp.vec3)
    item_uppers: wp.array(dtype=wp.vec3)
    item_weights: wp.array(dtype=wp.float64)
    mode: int
    num_bins: int
    max_leaf_size: int
    terminate_leaf_size: int
    t_traversal: wp.float64
    t_intersect: wp.float64
    binned_above: int
    suffix_cost: wp.array(dtype=wp.float64)
    bin_lowers: wp.array(dtype=wp.vec3)
    bin_uppers: wp.array(dtype=wp.vec3)
    bin_weight: wp.array(dtype=wp.float64)
    bin_count: wp.array(dtype=wp.int32)


@wp.func
def binned_split_presorted(b: int, e: int, inputs: SplitInputs):
    """Binned SAH (Wald 2007) on presorted items in one light pass per axis: ``(axis, pos, found)``.

    The same candidates and costs as pricing every bin boundary of the full sweep (MODE_BINNED
    in `choose_split`), without its per-item area and stores: items sorted by centroid fall into
    non-decreasing bins, so each bin is one run of the order, boxed as the pass goes; the sweep
    then runs over the bins. Bins live in scratch slots [b, b + num_bins) of this node's own
    range, so the range needs at least `num_bins` items.
    """
    order = inputs.order
    num_items = inputs.num_items
    item_lowers = inputs.item_lowers
    item_uppers = inputs.item_uppers
    item_weights = inputs.item_weights
    num_bins = inputs.num_bins
    bin_lowers = inputs.bin_lowers
    bin_uppers = inputs.bin_uppers
    bin_weight = inputs.bin_weight
    bin_count = inputs.bin_count
    suffix_cost = inputs.suffix_cost
    best_cost = NO_COST
    best_axis = int(-1)
    best_pos = int(-1)
    for a in range(3):
        base = a * num_items
        cmin = item_centroid(item_lowers, item_uppers, order[base + b], a)
        cmax = item_centroid(item_lowers, item_uppers, order[base + e - 1], a)
        if not (cmax > cmin):
            continue
        scale = wp.float64(num_bins) / (wp.float64(cmax) - wp.float64(cmin))
        for j in range(num_bins):
            bin_count[b + j] = 0
        item = order[base + b]
        lower = item_lowers[item]
        upper = item_uppers[item]
        w = item_weights[item]
        count = int(1)
        current = bin_of(centroid_of(lower[a], upper[a]), cmin, scale, num_bins)
        for i in range(b + 1, e):
            item = order[base + i]
            item_lower = item_lowers[item]
            item_upper = item_uppers[item]
            j = bin_of(centroid_of(item_lower[a], item_upper[a]), cmin, scale, num_bins)
            if j != current:
                bin_lowers[b + current] = lower
                bin_uppers[b + current] = upper
                bin_weight[b + current] = w
                bin_count[b + current] = count
                current = j
                lower = item_lower
                upper = item_upper
                w = item_weights[item]
                count = 1
            else:
                lower = wp.min(lower, item_lower)
                upper = wp.max(upper, item_upper)
                w += item_weights[item]
                count += 1
        bin_lowers[b + current] = lower
        bin_uppers[b + current] = upper
        bin_weight[b + current] = w
        bin_count[b + current] = count

        # Right to left over the bins: area * weight of everything from bin j on.
        started = int(0)
        for k in range(num_bins):
            j = num_bins - 1 - k
            if bin_count[b + j] > 0:
                if started == 0:
                    lower = bin_lowers[b + j]
                    upper = bin_uppers[b + j]
                    w = bin_weight[b + j]
                    started = 1
                else:
                    lower = wp.min(lower, bin_lowers[b + j])
                    upper = wp.max(upper, bin_uppers[b + j])
                    w += bin_weight[b + j]
                suffix_cost[b + j] = box_area64(lower, upper) * w
        # Left to right: a candidate before every non-empty bin that has items to its left.
        started = int(0)
        count = int(0)
        for j in range(num_bins):
            n_j = bin_count[b + j]
            if n_j > 0:
                if started == 1:
                    pos = b + count
                    cost = box_area64(lower, upper) * w + suffix_cost[b + j]
                    better = cost < best_cost
                    if cost == best_cost and best_pos >= 0:
                        better = wp.abs(2 * pos - b - e) < wp.abs(2 * best_pos - b - e)
                    if better:
                        best_cost = cost
                        best_axis = a
                        best_pos = pos
                    lower = wp.min(lower, bin_lowers[b + j])
                    upper = wp.max(upper, bin_uppers[b + j])
                    w += bin_weight[b + j]
                else:
                    lower = bin_lowers[b + j]
                    upper = bin_uppers[b + j]
                    w = bin_weight[b + j]
                    started = 1
                count += n_j
    if best_axis < 0:
        return wp.vec3i(0, 0, 0)
    return wp.vec3i(best_axis, best_pos, 1)


@wp.func
def order_range_box(begin: int, end: int, inputs: SplitInputs):
    """``(lower, upper, weight)`` of the items at positions [begin, end) of axis 0's order
    (begin < end)."""
    order = inputs.order
    item = order[begin]
    lower = inputs.item_lowers[item]
    upper = inputs.item_uppers[item]
    weight = inputs.item_weights[item]
    for i in range(begin + 1, end):
        item = order[i]
        lower = wp.min(lower, inputs.item_lowers[item])
        upper = wp.max(upper, inputs.item_uppers[item])
        weight += inputs.item_weights[item]
    return lower, upper, weight


@wp.func
def index_split_price(b: int, pos: int, e: int, inputs: SplitInputs):
    """``(A(L) W(L) + A(R) W(R), A(node), W(node))`` of the split of axis 0's order on [b, e) at
    `pos`: the SAH price (MacDonald & Booth 1990) of a split chosen without one."""
    left_lower, left_upper, left_weight = order_range_box(b, pos, inputs)
    right_lower, right_upper, right_weight = order_range_box(pos, e, inputs)
    price = box_area64(left_lower, left_upper) * left_weight + box_area64(right_lower, right_upper) * right_weight
    node_area = box_area64(wp.min(left_lower, right_lower), wp.max(left_upper, right_upper))
    return price, node_area, left_weight + right_weight


@wp.func
def choose_split(b: int, e: int, inputs: SplitInputs):
    """The split of the range [b, e) under `mode`: ``(axis, position, 1)``, or ``(0, 0, 0)`` for a leaf.

    Uses the scratch arrays on [b, e) only, so disjoint ranges can be split at once. Ranges of
    more than `binned_above` items (0: never) are priced at `num_bins` bin boundaries instead of
    swept in full, as binned SAH always is; the SAH-optimized HLBVH uses that for the few large
    nodes at the top of its cluster tree.
    """
    order = inputs.order
    num_items = inputs.num_items
    item_lowers = inputs.item_lowers
    item_uppers = inputs.item_uppers
    item_weights = inputs.item_weights
    mode = inputs.mode
    num_bins = inputs.num_bins
    terminate_leaf_size = inputs.terminate_leaf_size
    t_traversal = inputs.t_traversal
    t_intersect = inputs.t_intersect
    suffix_cost = inputs.suffix_cost
    size = e - b
    if size <= inputs.max_leaf_size:
        return wp.vec3i(0, 0, 0)
    binned_above = inputs.binned_above
    fast_binned = mode == MODE_BINNED or (mode == MODE_SWEEP and binned_above > 0 and size > binned_above)
    if fast_binned and size >= num_bins and size > terminate_leaf_size:
        split = binned_split_presorted(b, e, inputs)
        if split[2] == 1:
            return split
        # No plane separates the centroids on any axis: halve by index, as below.
        return wp.vec3i(0, b + size // 2, 1)

    if mode == MODE_MEDIAN:
        # Object median on the axis of largest centroid extent: the extent is read off the ends
        # of the presorted order, no pass over the range needed.
        # Extents in float64: in float32 a scene spanning -3e38 to 3e38 has an infinite extent
        # on every axis, and the first axis won whatever its extent.
        best_axis = int(0)
        best_extent = wp.float64(-1.0)
        for a in range(3):
            lo_c = wp.float64(item_centroid(item_lowers, item_uppers, order[a * num_items + b], a))
            hi_c = wp.float64(item_centroid(item_lowers, item_uppers, order[a * num_items + e - 1], a))
            if hi_c - lo_c > best_extent:
                best_extent = hi_c - lo_c
                best_axis = a
        return wp.vec3i(best_axis, b + size // 2, 1)

    best_cost = NO_COST
    best_axis = int(-1)
    best_pos = int(-1)
    node_area = wp.float64(0.0)
    total_weight = wp.float64(0.0)
    for a in range(3):
        base = a * num_items
        cmin = item_centroid(item_lowers, item_uppers, order[base + b], a)
        cmax = item_centroid(item_lowers, item_uppers, order[base + e - 1], a)
        scale = wp.float64(0.0)
        if mode == MODE_BINNED:
            # Binned SAH (Wald 2007) prices only the bin boundaries; with the items presorted a
            # boundary is where two neighbours fall into different bins.
            if not (cmax > cmin):
                continue
            scale = wp.float64(num_bins) / (wp.float64(cmax) - wp.float64(cmin))

        # Right to left: area * weight of every suffix [i, e), one stored product per position.
        item = order[base + e - 1]
        lower = item_lowers[item]
        upper = item_uppers[item]
        w = item_weights[item]
        suffix_cost[e - 1] = box_area64(lower, upper) * w
        for k in range(size - 2):
            i = e - 2 - k
            item = order[base + i]
            lower = wp.min(lower, item_lowers[item])
            upper = wp.max(upper, item_uppers[item])
            w += item_weights[item]
            suffix_cost[i] = box_area64(lower, upper) * w

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
                cost = box_area64(lower, upper) * w + suffix_cost[i]
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
        best_axis = 0
        best_pos = b + size // 2
        if size > terminate_leaf_size:
            return wp.vec3i(best_axis, best_pos, 1)
        # Priced like a found split for the termination test below: made without it, a node
        # that a leaf serves better was halved down to single items.
        best_cost, node_area, total_weight = index_split_price(b, best_pos, e, inputs)

    if size <= terminate_leaf_size:
        # Optional SAH termination: keep the node a leaf when splitting costs more than
        # intersecting all its items, C = T1 * 2 + T2 * best / area(node) against T2 * W.
        split_cost = wp.float64(2.0) * t_traversal + t_intersect * total_weight
        if node_area > wp.float64(0.0):
            split_cost = wp.float64(2.0) * t_traversal + t_intersect * best_cost / node_area
        if split_cost >= t_intersect * total_weight:
            return wp.vec3i(0, 0, 0)

    return wp.vec3i(best_axis, best_pos, 1)


@wp.kernel
def choose_splits_kernel(
    level_count: wp.array(dtype=wp.int32),
    level_nodes: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    inputs: SplitInputs,
    split_axis: wp.array(dtype=wp.int32),
    split_pos: wp.array(dtype=wp.int32),
    split_flag: wp.array(dtype=wp.int32),
):
    """One level of the greedy top-down SAH build (MacDonald & Booth 1990; the sweep as organized by
    Wald, Boulos & Shirley 2007, binned as Wald 2007): every open node of the level picks its split with
    `choose_split` or stays a leaf."""
    s = wp.tid()
    split_flag[s] = 0
    if s >= level_count[0]:
        return
    node = level_nodes[s]
    split = choose_split(node_begin[node], node_end[node], inputs)
    split_axis[s] = split[0]
    split_pos[s] = split[1]
    split_flag[s] = split[2]


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
    """The level's splits carried out: every splitting node's two children, numbered after all earlier
    nodes by the scan of split flags, linked to it, and the three presorted orders stably partitioned at
    the split; a finished leaf writes its items to item_order."""
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
    link_children(node, left, right, b, pos, e, node_left, node_right, node_parent, node_begin, node_end)
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
    """Advance node_count past the level's new children and set the next level's node count."""
    last = level_count[0] - 1
    splits = split_offset[last] + split_flag[last]
    node_count[0] = node_count[0] + 2 * splits
    next_level_count[0] = 2 * splits


@wp.kernel
def fill_float64_kernel(values: wp.array(dtype=wp.float64), value: wp.float64):
    """Fill an array with one float64 value (unit item weights)."""
    values[wp.tid()] = value


@wp.kernel
def build_depth_first_kernel(
    inputs: SplitInputs,
    spill: wp.array(dtype=wp.int32),
    item_side: wp.array(dtype=wp.int32),
    stack: wp.array(dtype=wp.int32),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_parent: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    node_count: wp.array(dtype=wp.int32),
    item_order: wp.array(dtype=wp.int32),
    root: int,
    first_free: int,
    split_root_only: int,
    write_count: int,
):
    """The subtree of `root` in one thread, depth first (``BuildConfig.emission = "depth_first"``).

    The greedy top-down SAH build (MacDonald & Booth 1990; the full sweep as organized by Wald,
    Boulos & Shirley 2007, binned as Wald 2007; or object median) of `choose_splits_kernel`,
    scheduled depth first.
    The same splits as the level schedule (`choose_split` on the same sorted orders), so the same
    tree up to node numbering; for Warp's CPU device, where a level's threads run one after
    another anyway and the per-level launches, scans and count reads are pure overhead. Children
    are allocated in pairs after their parent, from `first_free` on; the stack (one slot per
    pending right child, at most the subtree's depth + 1 <= its item count) lives in the scratch
    slots of the root's own range, so no tree can overflow it and disjoint subtrees can be built
    at once (by separate launches: the node ids of each come from its own range). The orders are
    partitioned in place: left items are compacted forwards, right items spill to `spill` on
    [b, e) and are copied back, which keeps both sides stable. With `split_root_only` the root
    is split (or made a leaf) and nothing more; with `write_count`, node_count gets the next free
    id at the end.
    """
    order = inputs.order
    num_items = inputs.num_items
    base_slot = node_begin[root]
    count = first_free
    stack[base_slot] = root
    top = int(1)
    while top > 0:
        top -= 1
        node = stack[base_slot + top]
        b = node_begin[node]
        e = node_end[node]
        split = choose_split(b, e, inputs)
        if split[2] == 0:
            # A finished leaf: its items take their final place (all three orders agree on the set).
            for i in range(b, e):
                item_order[i] = order[i]
            continue
        axis = split[0]
        pos = split[1]
        left = count
        right = count + 1
        count += 2
        node_left[node] = left
        node_right[node] = right
        for child in range(left, right + 1):
            node_left[child] = -1
            node_right[child] = -1
            node_parent[child] = node
        node_begin[left] = b
        node_end[left] = pos
        node_begin[right] = pos
        node_end[right] = e

        # The split axis is already partitioned; the other two follow the side of every item.
        base = axis * num_items
        for i in range(b, e):
            if i < pos:
                item_side[order[base + i]] = 1
            else:
                item_side[order[base + i]] = 0
        for a in range(3):
            if a != axis:
                base = a * num_items
                # Branch-free: every item is written to both places and only the cursor of its
                # side advances (lo <= i, so nothing unread is overwritten). The side of an item
                # is a coin flip to the branch predictor; this loop ran about twice as long
                # with a branch.
                lo = b
                for i in range(b, e):
                    item = order[base + i]
                    order[base + lo] = item
                    spill[b + i - lo] = item
                    lo += item_side[item]
                for j in range(e - pos):
                    order[base + pos + j] = spill[b + j]

        if split_root_only != 0:
            break
        # Left on top: the left subtree is finished before the right one starts.
        stack[base_slot + top] = right
        stack[base_slot + top + 1] = left
        top += 2
    if write_count != 0:
        node_count[0] = count


@wp.kernel
def init_root_kernel(
    num_items: int,
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_parent: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
):
    """Make node 0 a root leaf over [0, num_items) for `build_depth_first_kernel`."""
    node_begin[0] = 0
    node_end[0] = num_items
    node_left[0] = -1
    node_right[0] = -1
    node_parent[0] = -1
