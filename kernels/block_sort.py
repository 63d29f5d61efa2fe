"""Stage 5 of HLBVH: the voxel sort.

Pantaleoni & Luebke 2010, section 3.1: after compress-sort-decompress the primitives are
ordered by coarse voxel; consecutive voxel segments are grouped into blocks of roughly
`block_capacity` primitives and every block is sorted by its full codes (within a block the
voxels are already in order, so this sorts each voxel by its low 3(n - m) bits) in one launch.

The paper sorts a block with an odd-even sort in shared memory, one thread per element. Here a
block is sorted by one thread: on Warp's CPU device a launch runs its threads one after another,
where odd-even transposition would cost O(k^2) per block. The thread insertion-sorts the block,
O(k + inversions), which is all a block of small voxels (a surface mesh) or of the previous
frame's order (resorting) needs; past a budget of moves it finishes with a stable merge sort per
voxel that streams through a global scratch buffer, which also lifts the paper's assumption that
a voxel fits in a block, so an oversized voxel needs no separate path.
"""

import warp as wp

# Forward-only kernels: no adjoints to compile.
wp.set_module_options({"enable_backward": False})

# Runs of this many elements are insertion-sorted before merging starts.
INSERTION_RUN = 16
# A block is first insertion-sorted whole, O(k + inversions), until it has moved this many
# elements per element of the block; past that (a large voxel in random order) the rest is merge
# sorted voxel by voxel. On the scanned meshes' blocks of 2000 (voxels of a few primitives each,
# from scratch or resorted) 4 halved the voxel sort against merge-sorting every voxel from the
# start; 1 falls back too often, 64 risks O(k^2) on a random voxel.
INSERTION_MOVES_PER_ELEMENT = 4


@wp.kernel
def compact_voxel_starts_kernel(
    run_count: wp.array(dtype=wp.int32),
    voxel_flags: wp.array(dtype=wp.int32),
    voxel_index: wp.array(dtype=wp.int32),
    sorted_run_offsets: wp.array(dtype=wp.int32),
    voxel_starts: wp.array(dtype=wp.int32),
    voxel_count: wp.array(dtype=wp.int32),
):
    """Compact the voxel heads: voxel_starts[v] = sorted position of voxel v's first primitive,
    and voxel_count[0] = the number of voxels."""
    # voxel_index is the inclusive scan of voxel_flags.
    r = wp.tid()
    m = run_count[0]
    if r >= m:
        return
    if voxel_flags[r] != 0:
        voxel_starts[voxel_index[r] - 1] = sorted_run_offsets[r]
    if r == m - 1:
        voxel_count[0] = voxel_index[r]


@wp.kernel
def block_head_flags_kernel(
    voxel_count: wp.array(dtype=wp.int32),
    voxel_starts: wp.array(dtype=wp.int32),
    block_capacity: int,
    block_flags: wp.array(dtype=wp.int32),
):
    """1 where a voxel starts a new block of about `block_capacity` sorted positions, else 0."""
    # A block is the voxels whose first primitive lies in the same window of `block_capacity`
    # sorted positions: decided locally, so grouping needs no serial pass.
    v = wp.tid()
    if v >= voxel_count[0]:
        block_flags[v] = 0
        return
    flag = int(1)
    if v > 0:
        if voxel_starts[v] // block_capacity == voxel_starts[v - 1] // block_capacity:
            flag = 0
    block_flags[v] = flag


@wp.kernel
def compact_block_starts_kernel(
    voxel_count: wp.array(dtype=wp.int32),
    block_flags: wp.array(dtype=wp.int32),
    block_index: wp.array(dtype=wp.int32),
    voxel_starts: wp.array(dtype=wp.int32),
    block_starts: wp.array(dtype=wp.int32),
    block_count: wp.array(dtype=wp.int32),
):
    """Compact the block heads: block_starts[b] = first sorted position of block b, and
    block_count[0] = the number of blocks."""
    v = wp.tid()
    nv = voxel_count[0]
    if v >= nv:
        return
    if block_flags[v] != 0:
        block_starts[block_index[v] - 1] = voxel_starts[v]
    if v == nv - 1:
        block_count[0] = block_index[v]


@wp.func
def merge_pass(
    src_keys: wp.array(dtype=wp.int32),
    src_vals: wp.array(dtype=wp.int32),
    dst_keys: wp.array(dtype=wp.int32),
    dst_vals: wp.array(dtype=wp.int32),
    begin: int,
    end: int,
    width: int,
):
    """One bottom-up merge pass: adjacent runs of `width` in src[begin, end) merged stably into dst."""
    lo = begin
    while lo < end:
        mid = wp.min(lo + width, end)
        hi = wp.min(lo + 2 * width, end)
        i = lo
        j = mid
        k = lo
        while k < hi:
            # `<=` takes from the left run on ties: the merge is stable.
            if i < mid and (j >= hi or src_keys[i] <= src_keys[j]):
                dst_keys[k] = src_keys[i]
                dst_vals[k] = src_vals[i]
                i += 1
            else:
                dst_keys[k] = src_keys[j]
                dst_vals[k] = src_vals[j]
                j += 1
            k += 1
        lo = hi
    return 0


@wp.func
def insertion_sort_bounded(
    codes: wp.array(dtype=wp.int32),
    prim_ids: wp.array(dtype=wp.int32),
    begin: int,
    start: int,
    end: int,
    max_moves: int,
):
    """Stable insertion sort of codes (with prim_ids) on [begin, end), within a budget of moves."""
    # Stable insertion sort of [begin, end), whose prefix [begin, start) is already in order.
    # Returns `end` when done, or, when it stopped after `max_moves` moves, the end of the
    # prefix it left in order: the range is then a permutation in which equal codes keep their
    # order, so a stable sort can take over from there.
    moves = int(0)
    i = start
    while i < end:
        key = codes[i]
        if codes[i - 1] > key:
            val = prim_ids[i]
            j = i - 1
            while j >= begin and codes[j] > key:
                codes[j + 1] = codes[j]
                prim_ids[j + 1] = prim_ids[j]
                j -= 1
            codes[j + 1] = key
            prim_ids[j + 1] = val
            moves += i - 1 - j
            if moves > max_moves:
                return i + 1
        i += 1
    return end


@wp.func
def sort_range(
    codes: wp.array(dtype=wp.int32),
    prim_ids: wp.array(dtype=wp.int32),
    scratch_codes: wp.array(dtype=wp.int32),
    scratch_ids: wp.array(dtype=wp.int32),
    begin: int,
    end: int,
    run_length: int,
):
    """Stable sort of codes (with prim_ids) on [begin, end): insertion-sorted runs, then bottom-up merges."""
    # Stable insertion sort of runs of `run_length`, then bottom-up merges ping-ponging with
    # scratch (a range no longer than one run is just insertion-sorted).
    run_begin = begin
    while run_begin < end:
        run_end = wp.min(run_begin + run_length, end)
        # No budget: a run of k moves at most k(k - 1) / 2 elements.
        k = run_end - run_begin
        insertion_sort_bounded(codes, prim_ids, run_begin, run_begin + 1, run_end, k * k)
        run_begin = run_end

    width = run_length
    in_scratch = int(0)
    while width < end - begin:
        if in_scratch == 0:
            merge_pass(codes, prim_ids, scratch_codes, scratch_ids, begin, end, width)
        else:
            merge_pass(scratch_codes, scratch_ids, codes, prim_ids, begin, end, width)
        in_scratch = 1 - in_scratch
        width *= 2
    if in_scratch == 1:
        for i in range(begin, end):
            codes[i] = scratch_codes[i]
            prim_ids[i] = scratch_ids[i]
    return 0


@wp.kernel
def block_sort_kernel(
    num_prims: int,
    voxel_shift: int,
    block_count: wp.array(dtype=wp.int32),
    block_starts: wp.array(dtype=wp.int32),
    codes: wp.array(dtype=wp.int32),
    prim_ids: wp.array(dtype=wp.int32),
    scratch_codes: wp.array(dtype=wp.int32),
    scratch_ids: wp.array(dtype=wp.int32),
    blocks_sorted: wp.array(dtype=wp.int32),
    first_block: int,
):
    """The voxel sort of Pantaleoni & Luebke 2010 (section 3.1) for block b: its codes sorted, and with
    them its primitive ids. The paper sorts a block with an odd-even sort in shared memory, one CTA per
    block; here one thread sorts it (see the module docstring for why and how)."""
    # Blocks are independent: on a multi-core CPU, slices of them run as launches side by side,
    # each from its `first_block` (0 for one launch over all of them).
    b = wp.tid() + first_block
    nb = block_count[0]
    if b >= nb:
        return
    begin = block_starts[b]
    end = num_prims
    if b + 1 < nb:
        end = block_starts[b + 1]

    # A block that is already in order (resorted input) costs one read and no writes.
    first_descent = int(end)
    for i in range(begin + 1, end):
        if codes[i - 1] > codes[i]:
            first_descent = i
            break
    if first_descent == end:
        return
    wp.atomic_add(blocks_sorted, 0, 1)

    # Nearly sorted (voxels of a few primitives, or the previous frame's order): one insertion
    # sort from the first descent, O(k + inversions), until it exceeds its budget of moves.
    done = insertion_sort_bounded(codes, prim_ids, begin, first_descent, end,
                                  INSERTION_MOVES_PER_ELEMENT * (end - begin))
    if done == end:
        return
    # The block's voxels are already in order among themselves (the codes' high 3m bits), so
    # sorting the block is sorting each voxel: small voxels (a few primitives on a surface
    # mesh) are insertion-sorted in place and only a large voxel pays for merging. The voxels
    # wholly inside the prefix the insertion sort finished are left alone: the sort starts
    # from the voxel holding the first element it did not reach. On the armadillo subdivided
    # to 400k triangles most blocks run out of budget; there this took the voxel sort from 7.3
    # to 6.5 ms from scratch and from 5.4 to 4.5 ms resorted (A/B in one process, medians of
    # 21), where re-sorting the finished prefix cost up to what the insertion sort had done.
    voxel = codes[done] >> voxel_shift
    segment = done
    while segment > begin and (codes[segment - 1] >> voxel_shift) == voxel:
        segment -= 1
    for i in range(done + 1, end + 1):
        boundary = i == end
        if not boundary:
            boundary = (codes[i] >> voxel_shift) != voxel
        if boundary:
            if i - segment > 1:
                sort_range(codes, prim_ids, scratch_codes, scratch_ids, segment, i, INSERTION_RUN)
            if i < end:
                segment = i
                voxel = codes[i] >> voxel_shift
