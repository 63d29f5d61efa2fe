"""Recursive SAH (Wodniok & Goesele, GI 2016, Alg. 1): the SAH cost of a temporary, greedily
built binned-SAH BVH over one side of a split candidate.

One thread per side. The thread owns a range of a scratch array holding the side's primitive ids
and builds the temporary BVH in it depth first, partitioning the range in place; it never stores
the tree, only its cost. Eq. (1) of Pantaleoni & Luebke 2010 unrolled over the nodes,

    C(root) * area(root) = sum over nodes n of term(n) * area(n),

term(n) = 2 T1 for an interior node and T2 N for a leaf, so the cost accumulates top down with no
second pass; the thread returns the left side (unnormalized: the caller divides by the split
node's area, which is the recursive SAH split cost of Alg. 1's eq. 4).

The temporary builds split at ``num_bins`` bin boundaries per axis (Wald 2007) by the usual
binned SAH A(L) N(L) + A(R) N(R), first best in axis-then-boundary order, down to ``max_leaf``
primitives. A range whose centroids all coincide is halved. The smaller child is built first,
so the stack holds at most log2(N) deferred siblings.
"""

import warp as wp

from .metrics import box_area64
from .morton import box_centroid
from .sah import BIG, best_bin_split

# Forward-only kernels: no adjoints to compile.
wp.set_module_options({"enable_backward": False})

MAX_TEMP_BINS = 32
STACK_SIZE = 64
vec64i = wp.types.vector(length=STACK_SIZE, dtype=wp.int32)
binned_counts = wp.types.vector(length=3 * MAX_TEMP_BINS, dtype=wp.int32)
binned_boxes = wp.types.matrix(shape=(3 * MAX_TEMP_BINS, 3), dtype=wp.float32)


@wp.func
def bin_of(c: float, lower: float, upper: float, num_bins: int) -> int:
    """Bin of centroid c among `num_bins` equal bins over [lower, upper], clamped."""
    # The host's binning of the main splits uses the same expressions.
    extent = upper - lower
    offset = c - lower
    product = float(num_bins) * offset
    b = int(0)
    if wp.isinf(extent):
        # Centroids spanning more than float32's largest value (-3e38 to 3e38): the float32
        # extent is inf and every centroid fell in bin 0, so no candidate split the node. Such
        # extents are rare; they take float64, where nothing overflows.
        b = int(wp.float64(num_bins) * (wp.float64(c) - wp.float64(lower)) / (wp.float64(upper) - wp.float64(lower)))
    elif wp.isinf(product):
        # Overflowed (a scene past about 1e36): divide first, which cannot; int(inf) is undefined.
        b = int(offset / extent * float(num_bins))
    else:
        b = int(product / extent)
    return wp.clamp(b, 0, num_bins - 1)


@wp.func
def temp_bvh_cost(
    items: wp.array(dtype=wp.int32),
    first: int,
    last: int,
    prim_lowers: wp.array(dtype=wp.vec3),
    prim_uppers: wp.array(dtype=wp.vec3),
    num_bins: int,
    max_leaf: int,
    t_traversal: wp.float64,
    t_intersect: wp.float64,
) -> wp.float64:
    """Sum of term(n) * area(n) over a greedy binned-SAH BVH of items[first:last] (permuted).

    The temporary BVH of Wodniok & Goesele's recursive SAH (GI 2016, Alg. 1: build_temporary_bvh,
    then compute_sah), split at binned-SAH boundaries (Wald 2007) and never stored. Divided by the
    split node's area, the sum is p c(t) of their eq. 4: the side's area ratio times its SAH cost
    (Pantaleoni & Luebke 2010, eq. 1).
    """
    total = wp.float64(0.0)
    stack_first = vec64i()
    stack_last = vec64i()
    top = int(0)
    if last > first:
        stack_first[0] = first
        stack_last[0] = last
        top = 1
    while top > 0:
        top -= 1
        b = stack_first[top]
        e = stack_last[top]
        n = e - b
        box_lo = wp.vec3(BIG)
        box_hi = wp.vec3(-BIG)
        cen_lo = wp.vec3(BIG)
        cen_hi = wp.vec3(-BIG)
        for k in range(b, e):
            p = items[k]
            lo = prim_lowers[p]
            hi = prim_uppers[p]
            c = box_centroid(lo, hi)
            box_lo = wp.min(box_lo, lo)
            box_hi = wp.max(box_hi, hi)
            cen_lo = wp.min(cen_lo, c)
            cen_hi = wp.max(cen_hi, c)
        area = box_area64(box_lo, box_hi)
        if n <= max_leaf:
            total += t_intersect * wp.float64(n) * area
            continue
        total += wp.float64(2.0) * t_traversal * area
        # Bin the centroids on every axis: counts and boxes per bin.
        counts = binned_counts()
        boxes_lo = binned_boxes()
        boxes_hi = binned_boxes()
        for i in range(3 * num_bins):
            boxes_lo[i] = wp.vec3(BIG)
            boxes_hi[i] = wp.vec3(-BIG)
        extent = cen_hi - cen_lo
        for k in range(b, e):
            p = items[k]
            lo = prim_lowers[p]
            hi = prim_uppers[p]
            c = box_centroid(lo, hi)
            for axis in range(3):
                if extent[axis] > 0.0:
                    slot = axis * num_bins + bin_of(c[axis], cen_lo[axis], cen_hi[axis], num_bins)
                    counts[slot] = counts[slot] + 1
                    boxes_lo[slot] = wp.min(wp.vec3(boxes_lo[slot]), lo)
                    boxes_hi[slot] = wp.max(wp.vec3(boxes_hi[slot]), hi)
        # Sweep the bin boundaries of every axis (an object split: a bin's count on both sides).
        best_cost, best_axis, best_bin, best_left, best_right = best_bin_split(
            boxes_lo, boxes_hi, counts, counts, extent, num_bins, n)
        mid = b + n // 2
        if best_axis >= 0:
            # Partition in place: the items of bins below best_bin first.
            i = b
            j = e - 1
            while i <= j:
                p = items[i]
                c = box_centroid(prim_lowers[p], prim_uppers[p])
                if bin_of(c[best_axis], cen_lo[best_axis], cen_hi[best_axis], num_bins) < best_bin:
                    i += 1
                else:
                    items[i] = items[j]
                    items[j] = p
                    j -= 1
            mid = i
        # The larger side waits on the stack; the smaller is built next.
        if mid - b >= e - mid:
            stack_first[top] = b
            stack_last[top] = mid
            stack_first[top + 1] = mid
            stack_last[top + 1] = e
        else:
            stack_first[top] = mid
            stack_last[top] = e
            stack_first[top + 1] = b
            stack_last[top + 1] = mid
        top += 2
    return total


@wp.kernel
def side_costs_kernel(
    first_side: int,
    side_first: wp.array(dtype=wp.int32),
    side_last: wp.array(dtype=wp.int32),
    items: wp.array(dtype=wp.int32),
    prim_lowers: wp.array(dtype=wp.vec3),
    prim_uppers: wp.array(dtype=wp.vec3),
    num_bins: int,
    max_leaf: int,
    t_traversal: wp.float64,
    t_intersect: wp.float64,
    costs: wp.array(dtype=wp.float64),
):
    """`temp_bvh_cost` of side s = first_side + tid into costs[s]: the temporary BVHs of a level's
    split candidates, one thread each (Wodniok & Goesele, GI 2016, Alg. 1, lines 4-7)."""
    s = first_side + wp.tid()
    costs[s] = temp_bvh_cost(items, side_first[s], side_last[s], prim_lowers, prim_uppers, num_bins, max_leaf,
                             t_traversal, t_intersect)
