"""Stage 6 of HLBVH: hierarchy emission by treelets, p Morton bit planes per pass.

Pantaleoni & Luebke 2010, section 3.2, Figs. 3 and 4. Every current leaf segment of the sorted
primitive array owns a block descriptor of 2^p - 1 split slots laid out as a heap over the p
bit planes of the pass (MSB first, like an MSD radix sort):

    slot 0          first element whose p-bit digit is 1xx
    slots 1, 2      first of 01x (inside 0xx), first of 11x (inside 1xx)
    slots 3 .. 6    first of 001, 011, 101, 111

Bookkeeping, as in the paper: `head_to_node[N]` (the node of the segment a primitive heads),
`segment_heads`, `segment_id = scan(head_flags)`. A foreach over primitives writes the split
positions, an exclusive scan of the per-segment split counts gives every segment its output
offset, and a foreach over segments emits its treelet, 2 nodes per real split, so the node arena
has no holes and no singleton nodes.

Only segments that can still split (more than `max_leaf_size` primitives) are flagged as heads:
a finished leaf drops out of every later pass, so late passes, where most segments are single
primitives, touch only the few segments left. Each head also records where its segment ends
(`head_to_end`), because the next flagged head may lie past finished leaves.
"""

import warp as wp

from .bounds import leaf_box_in_order
from .metrics import interior_cost

# Forward-only kernels: no adjoints to compile.
wp.set_module_options({"enable_backward": False})

# Slot heaps hold at most 2^4 - 1 slots (planes_per_pass <= 4).
vec16i = wp.types.vector(length=16, dtype=wp.int32)


@wp.kernel
def init_nodes_kernel(
    num_prims: int,
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_parent: wp.array(dtype=wp.int32),
    node_visits: wp.array(dtype=wp.int32),
    max_leaf_size: int,
    head_to_node: wp.array(dtype=wp.int32),
    head_to_end: wp.array(dtype=wp.int32),
    head_flags: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    node_count: wp.array(dtype=wp.int32),
):
    """Reset the arena for the treelet passes: every node a leaf, and the root owning the one segment
    [0, N), as the hierarchy emission of Pantaleoni & Luebke 2010 (Fig. 4) starts."""
    # Launched over the node arena (2N - 1 entries): -1 children mark a leaf until a split.
    i = wp.tid()
    node_left[i] = -1
    node_right[i] = -1
    node_parent[i] = -1
    node_visits[i] = 0
    if i < num_prims:
        head_to_node[i] = -1
        head_flags[i] = 0
    if i == 0:
        # One segment, [0, N), owned by the root.
        head_to_node[0] = 0
        head_to_end[0] = num_prims
        if num_prims > max_leaf_size:
            head_flags[0] = 1
        node_begin[0] = 0
        node_end[0] = num_prims
        node_count[0] = 1


@wp.kernel
def compact_segments_kernel(
    num_prims: int,
    head_flags: wp.array(dtype=wp.int32),
    head_to_node: wp.array(dtype=wp.int32),
    head_to_end: wp.array(dtype=wp.int32),
    segment_id: wp.array(dtype=wp.int32),
    segment_heads: wp.array(dtype=wp.int32),
    segment_ends: wp.array(dtype=wp.int32),
    segment_nodes: wp.array(dtype=wp.int32),
    segment_count: wp.array(dtype=wp.int32),
):
    """Fig. 4's bookkeeping (Pantaleoni & Luebke 2010, section 3.2): the heads, ends and nodes of
    the open segments, compacted in segment order, and the segment count."""
    # segment_id is the inclusive scan of the head flags: segment of primitive i, plus one.
    # Split slots are not cleared: a stale slot fails `split_is_valid`, which saves N * (2^p - 1)
    # writes per pass.
    i = wp.tid()
    if head_flags[i] != 0:
        s = segment_id[i] - 1
        segment_heads[s] = i
        segment_ends[s] = head_to_end[i]
        segment_nodes[s] = head_to_node[i]
    if i == num_prims - 1:
        segment_count[0] = segment_id[i]


@wp.func
def highest_bit(x: int):
    """Index of the most significant set bit of x > 0."""
    b = int(0)
    while (x >> (b + 1)) != 0:
        b += 1
    return b


@wp.func
def boundary_slot(codes: wp.array(dtype=wp.int32), i: int, shift: int, planes: int):
    """The block-descriptor slot (Pantaleoni & Luebke 2010, section 3.2) whose split lies between
    elements i - 1 and i of one segment, or -1 when their p-bit digits agree."""
    # The level is the highest differing bit, the slot within the level the digit prefix above it.
    mask = (1 << planes) - 1
    prev = (codes[i - 1] >> shift) & mask
    cur = (codes[i] >> shift) & mask
    if prev == cur:
        return -1
    hb = highest_bit(prev ^ cur)
    level = planes - 1 - hb
    return (1 << level) - 1 + (cur >> (hb + 1))


@wp.func
def split_is_valid(
    codes: wp.array(dtype=wp.int32),
    sp: int,
    slot: int,
    begin: int,
    end: int,
    max_leaf_size: int,
    shift: int,
    planes: int,
    median: int,
):
    """Whether `sp`, read from split slot `slot` of segment [begin, end), is this pass's split of it."""
    # Slots are never cleared, so a value is trusted only if it is this pass's split of the slot.
    if sp <= begin or sp >= end or end - begin <= max_leaf_size:
        return False
    if median != 0:
        return slot == 0 and sp == (begin + end + 1) // 2
    return boundary_slot(codes, sp, shift, planes) == slot


@wp.kernel
def mark_splits_kernel(
    shift: int,
    planes: int,
    stride: int,
    codes: wp.array(dtype=wp.int32),
    segment_id: wp.array(dtype=wp.int32),
    segment_heads: wp.array(dtype=wp.int32),
    segment_ends: wp.array(dtype=wp.int32),
    split_pos: wp.array(dtype=wp.int32),
):
    """The foreach over primitives that fills the block descriptors (Pantaleoni & Luebke 2010,
    section 3.2, Fig. 4's emit_block_splits): primitive i writes its position into the slot of the split
    between it and its predecessor, if their p-bit digits differ."""
    # Each boundary between neighbours of one segment whose p-bit digits differ is the split of
    # exactly one slot. Digits are sorted inside a segment, so no slot is written twice.
    i = wp.tid()
    s = segment_id[i] - 1
    if s < 0:
        return
    # Primitives of finished leaves map to the last open segment before them: skip them here.
    if i <= segment_heads[s] or i >= segment_ends[s]:
        return
    slot = boundary_slot(codes, i, shift, planes)
    if slot >= 0:
        split_pos[s * stride + slot] = i


@wp.kernel
def mark_median_splits_kernel(
    max_leaf_size: int,
    stride: int,
    segment_heads: wp.array(dtype=wp.int32),
    segment_ends: wp.array(dtype=wp.int32),
    segment_count: wp.array(dtype=wp.int32),
    split_pos: wp.array(dtype=wp.int32),
):
    """Slot 0 of every open segment set to its index median (codes exhausted)."""
    # Segments whose codes are exhausted (duplicates, or all 3n bits used) are split at the index
    # median: ceil(log2(size / max_leaf_size)) such passes bring every segment down to a leaf.
    s = wp.tid()
    if s >= segment_count[0]:
        return
    begin = segment_heads[s]
    end = segment_ends[s]
    if end - begin > max_leaf_size:
        split_pos[s * stride] = (begin + end + 1) // 2


@wp.func
def open_segment(
    lo: int,
    hi: int,
    node: int,
    max_leaf_size: int,
    head_to_node: wp.array(dtype=wp.int32),
    head_to_end: wp.array(dtype=wp.int32),
    head_flags: wp.array(dtype=wp.int32),
):
    """Make [lo, hi) a segment owned by `node`: open while it can still split, else a finished leaf."""
    head_to_node[lo] = node
    head_to_end[lo] = hi
    if hi - lo > max_leaf_size:
        head_flags[lo] = 1
    else:
        head_flags[lo] = 0
    return 0


@wp.func
def link_children(
    node: int,
    left: int,
    right: int,
    begin: int,
    split: int,
    end: int,
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_parent: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
):
    """Make `left` and `right` the children of `node`, covering [begin, split) and [split, end)."""
    node_left[node] = left
    node_right[node] = right
    node_parent[left] = node
    node_parent[right] = node
    node_begin[left] = begin
    node_end[left] = split
    node_begin[right] = split
    node_end[right] = end
    return 0


@wp.func
def walk_treelet(
    emit: int,
    s: int,
    next_node: int,
    shift: int,
    planes: int,
    stride: int,
    median: int,
    max_leaf_size: int,
    codes: wp.array(dtype=wp.int32),
    segment_heads: wp.array(dtype=wp.int32),
    segment_ends: wp.array(dtype=wp.int32),
    segment_nodes: wp.array(dtype=wp.int32),
    split_pos: wp.array(dtype=wp.int32),
    head_to_node: wp.array(dtype=wp.int32),
    head_to_end: wp.array(dtype=wp.int32),
    head_flags: wp.array(dtype=wp.int32),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_parent: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
):
    """Walk segment s's slot heap top-down; count its real splits, and with `emit` write them.

    The block descriptor and treelet of Pantaleoni & Luebke 2010 (section 3.2, Fig. 3): slot j's
    split is the first element of its range whose bit of slot j's level is 1, and each real split
    emits two nodes.

    A slot splits only when its split is valid and its own range still exceeds the leaf size, so
    a range that is small enough stops splitting inside the treelet too, exactly as a top-down
    build would. Counting and emitting share this walk so their counts always agree.
    """
    slots = (1 << planes) - 1
    first_leaf_slot = (1 << (planes - 1)) - 1
    # Range [lo, hi) and owning node of every slot of the heap; empty where lo == hi.
    lo = vec16i()
    hi = vec16i()
    owner = vec16i()
    begin = segment_heads[s]
    end = segment_ends[s]
    lo[0] = begin
    hi[0] = end
    owner[0] = segment_nodes[s]
    count = int(0)

    for j in range(slots):
        a = lo[j]
        b = hi[j]
        node = owner[j]
        # Children of the slot: two heap slots, or (on the last level) two new segments.
        left_lo = a
        left_hi = a
        right_lo = b
        right_hi = b
        left_owner = node
        right_owner = node
        if b > a:
            sp = split_pos[s * stride + j]
            real = False
            if b - a > max_leaf_size:
                real = split_is_valid(codes, sp, j, begin, end, max_leaf_size, shift, planes, median)
            if real:
                count += 1
                left_owner = next_node
                right_owner = next_node + 1
                next_node += 2
                left_hi = sp
                right_lo = sp
                if emit != 0:
                    link_children(node, left_owner, right_owner, a, sp, b, node_left, node_right, node_parent,
                                  node_begin, node_end)
            else:
                # No split here: the whole range goes to the side its bit of this level says.
                level = highest_bit(j + 1)
                bit = (codes[a] >> (shift + planes - 1 - level)) & 1
                if bit == 0:
                    left_hi = b
                else:
                    right_lo = a
        if j < first_leaf_slot:
            lo[2 * j + 1] = left_lo
            hi[2 * j + 1] = left_hi
            owner[2 * j + 1] = left_owner
            lo[2 * j + 2] = right_lo
            hi[2 * j + 2] = right_hi
            owner[2 * j + 2] = right_owner
        elif emit != 0:
            if left_hi > left_lo:
                open_segment(left_lo, left_hi, left_owner, max_leaf_size, head_to_node, head_to_end, head_flags)
            if right_hi > right_lo:
                open_segment(right_lo, right_hi, right_owner, max_leaf_size, head_to_node, head_to_end, head_flags)
    return count


@wp.kernel
def count_splits_kernel(
    shift: int,
    planes: int,
    stride: int,
    median: int,
    max_leaf_size: int,
    codes: wp.array(dtype=wp.int32),
    segment_heads: wp.array(dtype=wp.int32),
    segment_ends: wp.array(dtype=wp.int32),
    segment_nodes: wp.array(dtype=wp.int32),
    segment_count: wp.array(dtype=wp.int32),
    split_pos: wp.array(dtype=wp.int32),
    split_count: wp.array(dtype=wp.int32),
    head_to_node: wp.array(dtype=wp.int32),
    head_to_end: wp.array(dtype=wp.int32),
    head_flags: wp.array(dtype=wp.int32),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_parent: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
):
    """Real splits of every segment's block descriptor (`walk_treelet` without writing), for the
    exclusive scan that gives each treelet its node offset (Pantaleoni & Luebke 2010, section 3.2,
    Fig. 4: ``block_offsets = ex_scan(count_splits(s))``)."""
    # Launched over at least the segment count; past it the counts are zero for the scan.
    s = wp.tid()
    c = int(0)
    if s < segment_count[0]:
        c = walk_treelet(0, s, 0, shift, planes, stride, median, max_leaf_size, codes, segment_heads, segment_ends,
                         segment_nodes, split_pos, head_to_node, head_to_end, head_flags, node_left, node_right,
                         node_parent, node_begin, node_end)
    split_count[s] = c


@wp.kernel
def emit_treelets_kernel(
    shift: int,
    planes: int,
    stride: int,
    median: int,
    max_leaf_size: int,
    codes: wp.array(dtype=wp.int32),
    segment_heads: wp.array(dtype=wp.int32),
    segment_ends: wp.array(dtype=wp.int32),
    segment_nodes: wp.array(dtype=wp.int32),
    segment_count: wp.array(dtype=wp.int32),
    split_pos: wp.array(dtype=wp.int32),
    split_count: wp.array(dtype=wp.int32),
    split_offset: wp.array(dtype=wp.int32),
    node_count: wp.array(dtype=wp.int32),
    head_to_node: wp.array(dtype=wp.int32),
    head_to_end: wp.array(dtype=wp.int32),
    head_flags: wp.array(dtype=wp.int32),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_parent: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
):
    """The foreach over segments of Pantaleoni & Luebke 2010 (section 3.2, Fig. 4's emit_treelets):
    segment s emits its treelet, 2 nodes per real split, from its scanned offset, and updates
    head_to_node and the segment heads for the next pass."""
    s = wp.tid()
    if s >= segment_count[0]:
        return
    if split_count[s] == 0:
        return
    # The s-th segment's 2 * split_count[s] new nodes start here: no holes in the arena.
    next_node = node_count[0] + 2 * split_offset[s]
    walk_treelet(1, s, next_node, shift, planes, stride, median, max_leaf_size, codes, segment_heads, segment_ends,
                 segment_nodes, split_pos, head_to_node, head_to_end, head_flags, node_left, node_right, node_parent,
                 node_begin, node_end)


@wp.kernel
def advance_node_count_kernel(
    segment_count: wp.array(dtype=wp.int32),
    split_count: wp.array(dtype=wp.int32),
    split_offset: wp.array(dtype=wp.int32),
    node_count: wp.array(dtype=wp.int32),
):
    """node_count += 2 x the pass's real splits (Fig. 4: ``node_count += N_splits * 2``)."""
    last = segment_count[0] - 1
    if last < 0:
        return
    node_count[0] = node_count[0] + 2 * (split_offset[last] + split_count[last])


@wp.kernel
def max_segment_size_kernel(
    segment_heads: wp.array(dtype=wp.int32),
    segment_ends: wp.array(dtype=wp.int32),
    segment_count: wp.array(dtype=wp.int32),
    max_size: wp.array(dtype=wp.int32),
):
    """The largest open segment's size into max_size[0] (how many index-median passes remain)."""
    s = wp.tid()
    if s >= segment_count[0]:
        return
    size = segment_ends[s] - segment_heads[s]
    wp.atomic_max(max_size, 0, size)


# --------------------------------------------------------------------------- depth-first schedule
# The same splits, scheduled for a device that runs a launch's threads one after another (Warp's
# CPU device): one thread per seed segment walks its subtree depth first, so no pass rescans all
# N primitives, and each node's children are written next to it while its range is in cache.

#: Depth of the explicit stack: radix levels (3n <= 30) plus index-median levels (<= 31).
DEPTH_FIRST_STACK = 64

vec64i = wp.types.vector(length=DEPTH_FIRST_STACK, dtype=wp.int32)


@wp.func
def highest_bit_mask(x: int):
    """x with only its most significant set bit kept (x > 0)."""
    # Smear the top set bit of x > 0 downwards, then keep only it:
    #   x = 0b0010_1100  ->  0b0011_1111  ->  0b0010_0000
    s = x | (x >> 1)
    s = s | (s >> 2)
    s = s | (s >> 4)
    s = s | (s >> 8)
    s = s | (s >> 16)
    return s ^ (s >> 1)


@wp.func
def radix_split(codes: wp.array(dtype=wp.int32), begin: int, end: int):
    """Split position of the sorted range [begin, end): the first code with the highest differing bit
    set, the split the treelet passes make (Pantaleoni & Luebke 2010, section 3.2, the LBVH topology of
    Lauterbach et al. 2009), found by binary search as in Karras 2012."""
    # Split of the sorted range [begin, end) at the highest bit where its codes differ: its codes
    # share every bit above it, so the first code with the bit set is found by binary search.
    # Equal codes (duplicates, or bits exhausted) split at the index median, as the passes do.
    x = codes[begin] ^ codes[end - 1]
    if x == 0:
        return (begin + end + 1) // 2
    bit = highest_bit_mask(x)
    lo = begin + 1
    hi = end - 1
    while lo < hi:
        mid = (lo + hi) >> 1
        if (codes[mid] & bit) != 0:
            hi = mid
        else:
            lo = mid + 1
    return lo


#: Largest subtree the CPU's depth-first walk emits in straight-line code (one primitive per
#: leaf): a node of 2 to 4 primitives, 64% of the interior nodes of a mesh's tree.
SMALL_SUBTREE = 4


@wp.func
def emit_leaf_of_one(
    node: int,
    k: int,
    leaf_lowers: wp.array(dtype=wp.vec3),
    leaf_uppers: wp.array(dtype=wp.vec3),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
    with_cost: int,
    t_intersect: wp.float64,
    node_cost: wp.array(dtype=wp.float64),
):
    """Leaf `node` over position k alone (its range was written by its parent); returns its box."""
    node_left[node] = -1
    node_right[node] = -1
    lower = leaf_lowers[k]
    upper = leaf_uppers[k]
    node_lowers[node] = lower
    node_uppers[node] = upper
    if with_cost != 0:
        node_cost[node] = t_intersect * wp.float64(1)
    return lower, upper


@wp.func
def finish_interior(
    node: int,
    left: int,
    right: int,
    lower_a: wp.vec3,
    upper_a: wp.vec3,
    lower_b: wp.vec3,
    upper_b: wp.vec3,
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
    with_cost: int,
    t_traversal: wp.float64,
    node_cost: wp.array(dtype=wp.float64),
):
    """Box (and with `with_cost` the SAH cost) of `node` from its finished children; returns the box."""
    lower = wp.min(lower_a, lower_b)
    upper = wp.max(upper_a, upper_b)
    node_lowers[node] = lower
    node_uppers[node] = upper
    if with_cost != 0:
        node_cost[node] = interior_cost(node_lowers, node_uppers, node_cost, left, right, lower, upper, t_traversal)
    return lower, upper


@wp.func
def emit_small_subtree(
    node: int,
    first_free: int,
    k: int,
    size: int,
    codes: wp.array(dtype=wp.int32),
    leaf_lowers: wp.array(dtype=wp.vec3),
    leaf_uppers: wp.array(dtype=wp.vec3),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_parent: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
    with_cost: int,
    t_traversal: wp.float64,
    t_intersect: wp.float64,
    node_cost: wp.array(dtype=wp.float64),
):
    """The subtree of `node` over [k, k + size), size 1 to 3, one primitive per leaf, its node pairs
    taken from `first_free` on as the walk would take them (the splits of Pantaleoni & Luebke 2010,
    section 3.2); returns the node's box.

    The split of three primitives is `radix_split`'s, found without a search: the neighbours that
    differ at the range's highest differing bit have the larger XOR (as in Karras 2012's delta), and
    with all three codes equal both XORs are 0, giving the index median k + 2."""
    if size == 1:
        return emit_leaf_of_one(node, k, leaf_lowers, leaf_uppers, node_left, node_right, node_lowers, node_uppers,
                                with_cost, t_intersect, node_cost)
    left = first_free
    right = left + 1
    split = k + 1
    if size == 3:
        middle = codes[k + 1]
        if (codes[k] ^ middle) <= (middle ^ codes[k + 2]):
            split = k + 2
    link_children(node, left, right, k, split, k + size, node_left, node_right, node_parent, node_begin, node_end)
    # The pair below a node of three takes the next two ids, on whichever side it is.
    pair = left
    pair_k = k
    if split == k + 1:
        pair = right
        pair_k = k + 1
    lower_a = wp.vec3()
    upper_a = wp.vec3()
    lower_b = wp.vec3()
    upper_b = wp.vec3()
    if size == 3:
        link_children(pair, left + 2, left + 3, pair_k, pair_k + 1, pair_k + 2, node_left, node_right, node_parent,
                      node_begin, node_end)
        lower_p, upper_p = emit_leaf_of_one(left + 2, pair_k, leaf_lowers, leaf_uppers, node_left, node_right,
                                            node_lowers, node_uppers, with_cost, t_intersect, node_cost)
        lower_q, upper_q = emit_leaf_of_one(left + 3, pair_k + 1, leaf_lowers, leaf_uppers, node_left, node_right,
                                            node_lowers, node_uppers, with_cost, t_intersect, node_cost)
        lower_pair, upper_pair = finish_interior(pair, left + 2, left + 3, lower_p, upper_p, lower_q, upper_q,
                                                 node_lowers, node_uppers, with_cost, t_traversal, node_cost)
        if pair == left:
            lower_a = lower_pair
            upper_a = upper_pair
            lower_b, upper_b = emit_leaf_of_one(right, k + 2, leaf_lowers, leaf_uppers, node_left, node_right,
                                                node_lowers, node_uppers, with_cost, t_intersect, node_cost)
        else:
            lower_a, upper_a = emit_leaf_of_one(left, k, leaf_lowers, leaf_uppers, node_left, node_right,
                                                node_lowers, node_uppers, with_cost, t_intersect, node_cost)
            lower_b = lower_pair
            upper_b = upper_pair
    else:
        lower_a, upper_a = emit_leaf_of_one(left, k, leaf_lowers, leaf_uppers, node_left, node_right, node_lowers,
                                            node_uppers, with_cost, t_intersect, node_cost)
        lower_b, upper_b = emit_leaf_of_one(right, k + 1, leaf_lowers, leaf_uppers, node_left, node_right,
                                            node_lowers, node_uppers, with_cost, t_intersect, node_cost)
    return finish_interior(node, left, right, lower_a, upper_a, lower_b, upper_b, node_lowers, node_uppers,
                           with_cost, t_traversal, node_cost)


@wp.kernel
def emit_depth_first_kernel(
    num_prims: int,
    seed_starts: wp.array(dtype=wp.int32),
    seed_count: wp.array(dtype=wp.int32),
    first_seed_node: int,
    max_leaf_size: int,
    codes: wp.array(dtype=wp.int32),
    leaf_lowers: wp.array(dtype=wp.vec3),
    leaf_uppers: wp.array(dtype=wp.vec3),
    gather_boxes: int,
    prim_order: wp.array(dtype=wp.int32),
    prim_lowers: wp.array(dtype=wp.vec3),
    prim_uppers: wp.array(dtype=wp.vec3),
    node_count: wp.array(dtype=wp.int32),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_parent: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
    with_cost: int,
    t_traversal: wp.float64,
    t_intersect: wp.float64,
    node_cost: wp.array(dtype=wp.float64),
    seed_offset: int,
    serial: int,
):
    """Emit the subtree of seed segment s: [seed_starts[s], seed_starts[s + 1] or N), rooted at
    node first_seed_node + s, parentless until the caller links it.

    Topology equals the treelet passes' (a top-down radix split at the highest differing bit,
    index medians for equal codes, leaves at `max_leaf_size`), only the node numbering differs:
    children are allocated in pairs when their parent is popped, so they follow it.

    The primitive boxes come in tree order: position k's box is ``leaf_lowers[k]``, gathered
    through `prim_order` beforehand (`bounds.gather_boxes_kernel`, on CUDA) or, with
    `gather_boxes` (the CPU), by each seed over its own range as it starts. The separate gather
    was one more launch and, with seeds run side by side, one more handoff between threads for
    0.3 ms of work at 100k primitives; gathered per seed, it is shared out with the seeds. The
    hierarchy stage on two cores went from 2.16 to 1.86 ms on the 100k-triangle armadillo and
    from 7.26 to 7.07 ms at 400k; on one core it costs the same (old and new alternating in one
    process, the same tree bit for bit).

    Boxes are written in the same walk, bottom-up: the left subtree is finished before the right
    one starts, so when a leaf that is a right child is done, its parent's two children are
    finished, and so on up while the finished node is a right child. That replaces a separate
    bottom-up pass over the 2N - 1 nodes. With `with_cost`, the SAH cost of every node (eq. 1
    of Pantaleoni & Luebke 2010, the cluster weights of section 3.3) is accumulated the same way.

    Thread t emits seed `seed_offset` + t, allocating node pairs from `node_count`; launches over
    disjoint seed ranges with counters of their own can run side by side (`hlbvh_warp.threads`).
    With `serial` (the CPU device, whose threads of one launch run one after another) a seed
    takes the counter into a local at its start and writes it back at its end, not one atomic
    per node pair: the counter is then touched twice per seed, where otherwise it is written
    once per node pair. The two cores' runs kept their counters in one cache line, so each such
    write took the line from the other core: the hierarchy stage of the bending armadillo went
    from 3.5 to 2.7 ms at 100k triangles and from 13.3 to 10.7 ms at 400k (A/B in one process,
    medians of 48 and 24 frames).

    With `serial` and one primitive per leaf, a node of at most `SMALL_SUBTREE` primitives is
    emitted whole in straight-line code (`emit_small_subtree`), its ids taken in the walk's order,
    instead of pushed, popped and climbed node by node; and since a seed's pairs then come from
    one counter, a left child has the parity of the seed's first id and its sibling follows it, so
    the climb tests the parity instead of loading the parent's children. The walk went from 3.3
    to 2.6 ms on the 100k-triangle armadillo and from 13.9 to 11.4 ms at 400k (one core, old and
    new kernels alternating in one process). The NaN-free comparison form of `morton.min_of_ordered`
    bought nothing here (2.47 against 2.49 ms): the walk waits on branches and loads, not on the
    unions.
    """
    s = seed_offset + wp.tid()
    num_seeds = seed_count[0]
    if s >= num_seeds:
        return
    begin = seed_starts[s]
    end = num_prims
    if s + 1 < num_seeds:
        end = seed_starts[s + 1]
    root = first_seed_node + s
    next_node = int(0)
    if serial != 0:
        next_node = node_count[0]
    first_pair = next_node
    # Ranges this small are emitted whole: leaves, or with one primitive per leaf on the CPU,
    # subtrees of up to SMALL_SUBTREE primitives.
    small = max_leaf_size
    if serial != 0 and max_leaf_size == 1:
        small = SMALL_SUBTREE
    if gather_boxes != 0:
        for k in range(begin, end):
            p = prim_order[k]
            leaf_lowers[k] = prim_lowers[p]
            leaf_uppers[k] = prim_uppers[p]
    node_begin[root] = begin
    node_end[root] = end
    node_parent[root] = -1

    stack_begin = vec64i()
    stack_end = vec64i()
    stack_node = vec64i()
    # The current range: a left child goes on at once, its right sibling waits on the stack.
    top = int(0)
    a = begin
    b = end
    node = root
    while node >= 0:
        size = b - a
        if size > small:
            split = radix_split(codes, a, b)
            left = int(0)
            if serial != 0:
                left = next_node
                next_node += 2
            else:
                left = wp.atomic_add(node_count, 0, 2)
            right = left + 1
            link_children(node, left, right, a, split, b, node_left, node_right, node_parent, node_begin, node_end)
            stack_begin[top] = split
            stack_end[top] = b
            stack_node[top] = right
            top += 1
            b = split
            node = left
            continue
        lower = wp.vec3()
        upper = wp.vec3()
        if size <= max_leaf_size:
            node_left[node] = -1
            node_right[node] = -1
            lower, upper = leaf_box_in_order(node, node_begin, node_end, leaf_lowers, leaf_uppers, node_lowers,
                                             node_uppers)
            if with_cost != 0:
                node_cost[node] = t_intersect * wp.float64(size)
        elif size < 4:
            lower, upper = emit_small_subtree(node, next_node, a, size, codes, leaf_lowers, leaf_uppers, node_left,
                                              node_right, node_parent, node_begin, node_end, node_lowers,
                                              node_uppers, with_cost, t_traversal, t_intersect, node_cost)
            next_node += 2 * (size - 1)
        else:
            # Four primitives: split as the walk would, then each side (1 to 3) whole, the left
            # side's node pairs first.
            split = radix_split(codes, a, b)
            left = next_node
            right = left + 1
            link_children(node, left, right, a, split, b, node_left, node_right, node_parent, node_begin, node_end)
            left_size = split - a
            lower_a, upper_a = emit_small_subtree(left, left + 2, a, left_size, codes, leaf_lowers, leaf_uppers,
                                                  node_left, node_right, node_parent, node_begin, node_end,
                                                  node_lowers, node_uppers, with_cost, t_traversal, t_intersect,
                                                  node_cost)
            lower_b, upper_b = emit_small_subtree(right, left + 2 * left_size, split, size - left_size, codes,
                                                  leaf_lowers, leaf_uppers, node_left, node_right, node_parent,
                                                  node_begin, node_end, node_lowers, node_uppers, with_cost,
                                                  t_traversal, t_intersect, node_cost)
            lower, upper = finish_interior(node, left, right, lower_a, upper_a, lower_b, upper_b, node_lowers,
                                           node_uppers, with_cost, t_traversal, node_cost)
            next_node += 6
        # Climb while the finished node is a right child: its parent's children are both done.
        child = node
        while child != root:
            left_child = child - 1
            if serial != 0:
                # Pairs come from one counter: left children share the parity of the first one.
                if ((child - first_pair) & 1) == 0:
                    break
            parent = node_parent[child]
            if serial == 0:
                if node_right[parent] != child:
                    break
                left_child = node_left[parent]
            lower, upper = finish_interior(parent, left_child, child, node_lowers[left_child],
                                           node_uppers[left_child], lower, upper, node_lowers, node_uppers,
                                           with_cost, t_traversal, node_cost)
            child = parent
        if top == 0:
            node = -1
        else:
            top -= 1
            a = stack_begin[top]
            b = stack_end[top]
            node = stack_node[top]
    if serial != 0:
        node_count[0] = next_node


@wp.func
def find_seed(seed_starts: wp.array(dtype=wp.int32), seed_ends: wp.array(dtype=wp.int32), count: int, begin: int,
              end: int):
    """The seed whose range is exactly [begin, end), or -1."""
    # At most MAX_TOP_SEEDS to look at.
    for s in range(count):
        if seed_starts[s] == begin and seed_ends[s] == end:
            return s
    return -1


#: Most seeds `split_top_kernel` cuts the top of the tree into.
MAX_TOP_SEEDS = 64


@wp.kernel
def split_top_kernel(
    num_prims: int,
    max_seed_size: int,
    codes: wp.array(dtype=wp.int32),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_parent: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    seed_starts: wp.array(dtype=wp.int32),
    seed_ends: wp.array(dtype=wp.int32),
    seed_count: wp.array(dtype=wp.int32),
):
    """The top of the tree, split until no seed holds more than `max_seed_size` primitives (or
    there are MAX_TOP_SEEDS), so that the depth-first walks of the seeds can be dealt out to
    threads in runs of about equal size. Splitting the root alone left the bunny's halves at
    65% / 35% of its primitives, so two threads waited on the larger.

    The splits are `radix_split`'s, as the walk's, so the tree is the one a single walk emits;
    only the numbering differs. With S seeds (one thread, dim 1):
      1. split the largest seed until done, keeping the seeds in order of their starts;
      2. walk the splits again from the root: the S - 1 interior nodes above the seeds get ids
         0 .. S - 2 in the order they are reached (a child after its parent), seed s gets
         S - 1 + s, the walk's ``first_seed_node``. `finish_top_kernel` boxes them afterwards.
    """
    seed_starts[0] = 0
    seed_ends[0] = num_prims
    count = int(1)
    while count < MAX_TOP_SEEDS:
        largest = int(0)
        for t in range(1, count):
            if seed_ends[t] - seed_starts[t] > seed_ends[largest] - seed_starts[largest]:
                largest = t
        a = seed_starts[largest]
        b = seed_ends[largest]
        if b - a <= max_seed_size or b - a < 2:
            break
        split = radix_split(codes, a, b)
        # The right half goes right after the left one; later seeds shift up by one.
        t = count
        while t > largest + 1:
            seed_starts[t] = seed_starts[t - 1]
            seed_ends[t] = seed_ends[t - 1]
            t -= 1
        seed_ends[largest] = split
        seed_starts[largest + 1] = split
        seed_ends[largest + 1] = b
        count += 1
    seed_count[0] = count
    if count == 1:
        # Nothing to split: the walk emits the root as the only seed.
        return

    stack_begin = vec64i()
    stack_end = vec64i()
    stack_node = vec64i()
    stack_begin[0] = 0
    stack_end[0] = num_prims
    stack_node[0] = 0
    node_parent[0] = -1
    node_begin[0] = 0
    node_end[0] = num_prims
    next_interior = int(1)
    first_seed = count - 1
    top = int(1)
    while top > 0:
        top -= 1
        a = stack_begin[top]
        b = stack_end[top]
        node = stack_node[top]
        split = radix_split(codes, a, b)
        # Each child is seed s when its range is exactly that seed's, else a new interior node.
        left = find_seed(seed_starts, seed_ends, count, a, split)
        if left < 0:
            left = next_interior
            next_interior += 1
        else:
            left += first_seed
        right = find_seed(seed_starts, seed_ends, count, split, b)
        if right < 0:
            right = next_interior
            next_interior += 1
        else:
            right += first_seed
        link_children(node, left, right, a, split, b, node_left, node_right, node_parent, node_begin, node_end)
        if right < first_seed:
            stack_begin[top] = split
            stack_end[top] = b
            stack_node[top] = right
            top += 1
        if left < first_seed:
            stack_begin[top] = a
            stack_end[top] = split
            stack_node[top] = left
            top += 1


@wp.kernel
def finish_top_kernel(
    seed_count: wp.array(dtype=wp.int32),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_parent: wp.array(dtype=wp.int32),
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
):
    """Link and box the interior nodes above the seeds of `split_top_kernel`, children first."""
    # The walk left every seed root parentless. A child's id is always above its parent's, so
    # counting down from S - 2 finishes both children first.
    node = seed_count[0] - 2
    while node >= 0:
        left = node_left[node]
        right = node_right[node]
        node_parent[left] = node
        node_parent[right] = node
        node_lowers[node] = wp.min(node_lowers[left], node_lowers[right])
        node_uppers[node] = wp.max(node_uppers[left], node_uppers[right])
        node -= 1
