"""Stages 3-4 of HLBVH: compress-sort-decompress of the coarse-voxel runs.

Pantaleoni & Luebke 2010, section 3.1 and Fig. 1, after the compress-sort-decompress scheme of
Garanzha & Loop 2010 (summarized in the paper's section 2.3): the codes are run-length encoded by
their high 3m bits, the M run codes are radix sorted with their run ids, and the runs are
expanded back in sorted order. Coherent input (e.g. the previous frame's order) has
M << N, so the global sort touches M keys instead of N.
"""

import warp as wp

# Forward-only kernels: no adjoints to compile.
wp.set_module_options({"enable_backward": False})


@wp.kernel
def iota_kernel(values: wp.array(dtype=wp.int32)):
    """values[i] = i: the run ids of the top-level sort, or the identity order."""
    tid = wp.tid()
    values[tid] = tid


@wp.func
def sift_down_ids(ids: wp.array(dtype=wp.int32), base: int, root: int, count: int):
    """Restore the max-heap of ids[base : base + count] below `root` (`order_tied_ids_kernel`)."""
    r = root
    while 2 * r + 1 < count:
        child = 2 * r + 1
        if child + 1 < count:
            if ids[base + child] < ids[base + child + 1]:
                child += 1
        if ids[base + r] >= ids[base + child]:
            break
        t = ids[base + r]
        ids[base + r] = ids[base + child]
        ids[base + child] = t
        r = child


@wp.func
def order_run_ids(ids: wp.array(dtype=wp.int32), begin: int, end: int):
    """ids[begin:end] (one run of equal codes) in ascending order: one scan where already so, a
    heapsort in place otherwise (O(k log k) for a run of k, whatever its order)."""
    k = begin + 1
    while k < end:
        if ids[k - 1] > ids[k]:
            break
        k += 1
    if k < end:
        count = end - begin
        root = count // 2 - 1
        while root >= 0:
            sift_down_ids(ids, begin, root, count)
            root -= 1
        last = count - 1
        while last > 0:
            t = ids[begin]
            ids[begin] = ids[begin + last]
            ids[begin + last] = t
            sift_down_ids(ids, begin, 0, last)
            last -= 1


@wp.func
def run_end(codes: wp.array(dtype=wp.int32), begin: int, n: int):
    """One past the last of the equal codes from ``begin`` on."""
    c = codes[begin]
    end = begin + 1
    # Warp evaluates both sides of an `and`: the bound is tested before the read, apart.
    while end < n:
        if codes[end] != c:
            break
        end += 1
    return end


@wp.kernel
def order_tied_ids_kernel(codes: wp.array(dtype=wp.int32), ids: wp.array(dtype=wp.int32), n: int):
    """Each run of equal sorted codes with its ids put in ascending order, by the thread at its
    head: the order a build from scratch gives them (Pantaleoni & Luebke 2010, section 2.2, ask a
    resorted build for the same tree).

    The sort is stable, so equal codes keep their input order: the faces' order from scratch, the
    previous tree's in a resorted frame, where a primitive whose code changed joins its new equals
    elsewhere; the index-median splits of a run then paired other primitives, and `hlbvh_sah`
    priced other clusters (0.1-6% of SAH apart at 2 bits per axis, where most codes tie). A
    resorted frame pays one read of the codes for it (0.14 ms of a 5.4 ms frame of the bending
    100k-triangle armadillo on the CPU); frames in face order skip it."""
    i = wp.tid()
    if i + 1 >= n:
        return
    if codes[i + 1] != codes[i]:
        return
    if i > 0:
        if codes[i - 1] == codes[i]:
            return
    order_run_ids(ids, i, run_end(codes, i, n))


@wp.kernel
def flag_descents_kernel(
    run_count: wp.array(dtype=wp.int32),
    run_codes: wp.array(dtype=wp.int32),
    descents: wp.array(dtype=wp.int32),
):
    """Set descents[0] to 1 if some code is smaller than its predecessor (the codes are not in order)."""
    # descents[0] (zeroed by the caller) becomes 1 if any code descends. Only "any descent?" is
    # asked, so every thread that finds one stores the same 1: no atomic, where counting with an
    # atomic add on one address would serialize the thousands of descents of a moving frame.
    r = wp.tid()
    if r == 0 or r >= run_count[0]:
        return
    if run_codes[r - 1] > run_codes[r]:
        descents[0] = 1


@wp.kernel
def find_descent_kernel(
    run_count: wp.array(dtype=wp.int32),
    run_codes: wp.array(dtype=wp.int32),
    descents: wp.array(dtype=wp.int32),
):
    """`flag_descents_kernel` in one thread, for the CPU device: descents[0] = 1 if some code
    descends, else 0."""
    # One thread scans the codes and stops at the first descent. Only "any descent?" is asked, and
    # a moving scene's runs are out of order within the first few (the check then costs nothing);
    # in-order runs cost one read each.
    m = run_count[0]
    for r in range(1, m):
        if run_codes[r - 1] > run_codes[r]:
            descents[0] = 1
            return
    descents[0] = 0


@wp.kernel
def sample_code_breaks_kernel(
    codes: wp.array(dtype=wp.int32),
    num_codes: int,
    num_samples: int,
    shift: int,
    breaks: wp.array(dtype=wp.int32),
):
    """Over `num_samples` evenly spaced adjacent pairs of the input codes, count in breaks[0] the
    pairs in two coarse voxels (codes >> shift differ): an estimate of the M / N the run-length
    encoding (Pantaleoni & Luebke 2010, section 3.1) would give, without the pass over all N."""
    # Pair t is (i - 1, i) with i = 1 + t (N - 1) / S: the same positions as the NumPy oracle's.
    t = wp.tid()
    i = wp.int32(wp.int64(1) + wp.int64(t) * wp.int64(num_codes - 1) // wp.int64(num_samples))
    if (codes[i - 1] >> shift) != (codes[i] >> shift):
        wp.atomic_add(breaks, 0, 1)


@wp.kernel
def pad_run_codes_kernel(run_count: wp.array(dtype=wp.int32), pad_code: int, run_codes: wp.array(dtype=wp.int32)):
    """Give the slots past the device-side run count `pad_code`, the largest key, so that a stable
    sort over all N slots leaves them after every real run."""
    r = wp.tid()
    if r >= run_count[0]:
        run_codes[r] = pad_code


@wp.kernel
def gather_run_lengths_kernel(
    run_count: wp.array(dtype=wp.int32),
    sorted_run_ids: wp.array(dtype=wp.int32),
    run_lengths: wp.array(dtype=wp.int32),
    sorted_run_lengths: wp.array(dtype=wp.int32),
):
    """The run lengths in sorted run order, to be scanned for the runs' new offsets (Pantaleoni &
    Luebke 2010, section 3.1, Fig. 1: "compute offsets for the sorted run-lengths")."""
    r = wp.tid()
    if r >= run_count[0]:
        # Zero past the count, so a scan over the launch bound leaves the real offsets intact.
        sorted_run_lengths[r] = 0
        return
    sorted_run_lengths[r] = run_lengths[sorted_run_ids[r]]


@wp.kernel
def decompress_runs_kernel(
    run_count: wp.array(dtype=wp.int32),
    sorted_run_ids: wp.array(dtype=wp.int32),
    run_starts: wp.array(dtype=wp.int32),
    run_lengths: wp.array(dtype=wp.int32),
    sorted_run_offsets: wp.array(dtype=wp.int32),
    morton_codes: wp.array(dtype=wp.int32),
    input_ids: wp.array(dtype=wp.int32),
    sorted_prim_ids: wp.array(dtype=wp.int32),
    sorted_codes: wp.array(dtype=wp.int32),
    first_run: int,
):
    """Run-length decoding (Pantaleoni & Luebke 2010, section 3.1, Fig. 1; the decompress step of
    Garanzha & Loop's compress-sort-decompress): sorted run r expands into its primitive ids and codes at
    its scanned offset, leaving the codes sorted by coarse voxel. The paper's two foreach loops (indices,
    then codes) are one here."""
    # One thread per run: runs are contiguous in the input and are copied whole. On a multi-core
    # CPU, slices of the runs run as launches side by side, each from its `first_run`. The ids
    # written are the input positions, or with `input_ids` (not empty) the ids they stand for:
    # a resorted frame's input is the previous tree order, and its tree then names user faces
    # directly, with no pass to map the ids back.
    r = wp.tid() + first_run
    if r >= run_count[0]:
        return
    run = sorted_run_ids[r]
    src = run_starts[run]
    dst = sorted_run_offsets[r]
    if input_ids.shape[0] > 0:
        for j in range(run_lengths[run]):
            sorted_prim_ids[dst + j] = input_ids[src + j]
            sorted_codes[dst + j] = morton_codes[src + j]
    else:
        for j in range(run_lengths[run]):
            sorted_prim_ids[dst + j] = src + j
            sorted_codes[dst + j] = morton_codes[src + j]


@wp.kernel
def voxel_head_flags_kernel(
    run_count: wp.array(dtype=wp.int32),
    sorted_run_codes: wp.array(dtype=wp.int32),
    voxel_flags: wp.array(dtype=wp.int32),
):
    """1 where a sorted run starts a new coarse voxel, else 0 (0 past the run count)."""
    # A voxel is a maximal stretch of sorted runs with the same coarse code.
    r = wp.tid()
    if r >= run_count[0]:
        voxel_flags[r] = 0
        return
    flag = int(1)
    if r > 0:
        if sorted_run_codes[r] == sorted_run_codes[r - 1]:
            flag = 0
    voxel_flags[r] = flag
