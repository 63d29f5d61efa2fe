"""The CPU's global sort on two cores: two halves radix sorted side by side, then merged.

Warp's CPU radix sort runs on one core. The LBVH baseline's global sort (and HLBVH's, where the
runs do not compress) sorts each half of the codes in its own thread and merges the two sorted
halves with Merge Path (Green, McColgan & Yalamanchili, "GPU Merge Path", ICS 2012; Odeh et
al., "Merge Path - Parallel Merging Made Simple", IPDPSW 2012): every part of the merge finds
where its slice of the output starts in each half by a binary search along its cross diagonal
(the co-rank), then merges sequentially, so the parts run side by side with no shared state.
Ties go to the first half, which keeps the result exactly the stable sort's order.
"""

import warp as wp

# Forward-only kernels: no adjoints to compile.
wp.set_module_options({"enable_backward": False})


@wp.kernel
def gather_half_kernel(
    codes: wp.array(dtype=wp.int32),
    input_ids: wp.array(dtype=wp.int32),
    first: int,
    half_codes: wp.array(dtype=wp.int32),
    half_ids: wp.array(dtype=wp.int32),
):
    """half[i] = (codes[first + i], its id): the id input_ids carries for it (a resorted frame),
    or the position itself where input_ids is empty."""
    i = wp.tid()
    half_codes[i] = codes[first + i]
    if input_ids.shape[0] > 0:
        half_ids[i] = input_ids[first + i]
    else:
        half_ids[i] = first + i


@wp.func
def co_rank(keys: wp.array(dtype=wp.int32), a_count: int, b_first: int, b_count: int, diagonal: int):
    """How many of the first `diagonal` merged elements come from the first half: the Merge Path
    crossing of that diagonal, with an element of the first half placed before an equal one of
    the second."""
    lo = wp.max(0, diagonal - b_count)
    hi = wp.min(diagonal, a_count)
    while lo < hi:
        mid = (lo + hi) // 2
        # The first half's element mid precedes the second half's element diagonal - mid - 1
        # (ties included): it lies before the crossing.
        if keys[mid] <= keys[b_first + diagonal - mid - 1]:
            lo = mid + 1
        else:
            hi = mid
    return lo


@wp.kernel
def merge_halves_kernel(
    keys: wp.array(dtype=wp.int32),
    ids: wp.array(dtype=wp.int32),
    a_count: int,
    b_first: int,
    b_count: int,
    parts: int,
    part: int,
    out_keys: wp.array(dtype=wp.int32),
    out_ids: wp.array(dtype=wp.int32),
):
    """Part `part` of `parts` of the stable merge of keys[0, a_count) with keys[b_first, b_first +
    b_count) (ids alongside) into out_keys / out_ids: one thread, output slice found by `co_rank`.
    Launched once per part, so that each part can run on its own core."""
    total = a_count + b_count
    # In int64: total * parts passes int32 from 2^31 (34M codes in 64 parts), where the bounds
    # wrapped negative and parts of the output were never written.
    begin = int(wp.int64(total) * wp.int64(part) // wp.int64(parts))
    end = int(wp.int64(total) * wp.int64(part + 1) // wp.int64(parts))
    i = co_rank(keys, a_count, b_first, b_count, begin)
    j = begin - i
    # A branch, not a select: the halves of a mesh's codes interleave in long stretches, where
    # the branch is predicted (a select of both halves' ids took 0.50 ms against 0.29 for the
    # armadillo's 100k codes, one thread; on random codes the select won).
    for k in range(begin, end):
        take_a = j >= b_count
        if i < a_count and j < b_count:
            take_a = keys[i] <= keys[b_first + j]
        if take_a:
            out_keys[k] = keys[i]
            out_ids[k] = ids[i]
            i += 1
        else:
            out_keys[k] = keys[b_first + j]
            out_ids[k] = ids[b_first + j]
            j += 1
