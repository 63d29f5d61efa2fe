"""Spatial-split BVH (SBVH; Stich, Friedrich & Dietrich, "Spatial Splits in Bounding Volume
Hierarchies", HPG 2009): the split search of one node and the distribution of its references.

A reference is a triangle id with a box that bounds the part of the triangle it stands for: the
whole triangle's box at first, a clipped one after a spatial split cut the triangle in two. Every
node picks the cheaper by the SAH A(L) N(L) + A(R) N(R) of

- the best object split: centroids of its references' boxes in ``num_bins`` bins per axis
  (Wald 2007), the cheapest, of equals the most balanced, then the first in axis-then-boundary order;
- the best spatial split (only where the object split's two boxes overlap by more than alpha of
  the root's area, Stich et al.'s section 4.4): ``num_bins`` equal slabs of the node's box per
  axis; a reference enters the slab of its box's lower corner and exits at its upper corner's,
  and every slab it spans gets the box of the triangle clipped to that slab within the
  reference's box (their "chopped" binning). A reference straddling the chosen plane goes to
  both children, each with the box of its side's part.

One thread per node of a tree level (``split_search_kernel``, then ``distribute_kernel`` at the
offsets the host scans from the chosen splits). Clipping is the float64 Sutherland-Hodgman of
the EPO metric; a clipped box is rounded outward to float32 and kept inside the box it was cut
from, so a reference's box always contains its part of the triangle and its parent's box.
"""

import warp as wp

from .metrics import box_area64, clip_to_slab, mat93d, triangle_in_box
from .morton import box_centroid
from .recursive_sah import bin_of as centroid_bin
from .sah import BIG, MAX_SWEEP_BINS, best_bin_split

# Forward-only kernels: no adjoints to compile.
wp.set_module_options({"enable_backward": False})

MAX_BINS = MAX_SWEEP_BINS
bin_counts = wp.types.vector(length=3 * MAX_BINS, dtype=wp.int32)
bin_boxes = wp.types.matrix(shape=(3 * MAX_BINS, 3), dtype=wp.float32)

#: The kinds of node the host may choose; the distribution kernel takes the host's choice.
KIND_LEAF = wp.constant(0)
KIND_OBJECT = wp.constant(1)
KIND_SPATIAL = wp.constant(2)
KIND_HALVE = wp.constant(3)
# Float32 rounding outward by at least one unit in the last place (2^-23 relative), and a floor
# for values near zero.
OUTWARD = wp.constant(2.4e-7)
TINY = wp.constant(1.0e-30)
# The float64 clip's own error is relative to the triangle's coordinates, not to its clipped
# part's: a part near the origin cut from a triangle spanning +-1e6 is off by about 1e-11, far
# more than one float32 unit of the part's coordinates. Parts are widened by 2^-44 (about 256
# float64 units) of the triangle's largest coordinate.
CLIP_MARGIN = wp.constant(5.684342e-14)


# Out of line (``inline=False``): Warp passes vectors and matrices by value, and inlined into
# split_search_kernel each of the two sweeps copied its four bin arrays (2 x 192x3 float32 +
# 2 x 192 int32: 1,536 scalars) into every one of the three per-axis sweeps, and the reference's
# clip was inlined at each of the three unrolled axes (18 Sutherland-Hodgman passes). NVRTC took
# 40-55 s per architecture on that kernel; out of line, about 7 s. The CPU's time is unchanged.
try:
    out_of_line = wp.func(inline=False)
except TypeError:  # a Warp without the inlining hint: the same functions, inlined
    out_of_line = wp.func


@out_of_line
def best_split_of_bins(boxes_lo: bin_boxes, boxes_hi: bin_boxes, enter: bin_counts, leave: bin_counts,
                       extent: wp.vec3, num_bins: int, n: int):
    """`best_bin_split` over the kernel's bin arrays (of exact equals the most balanced), compiled once."""
    return best_bin_split(boxes_lo, boxes_hi, enter, leave, extent, num_bins, n)


@out_of_line
def reference_polygon(a: wp.vec3, b: wp.vec3, c: wp.vec3, lower: wp.vec3, upper: wp.vec3):
    """`triangle_in_box` (the part of the triangle a reference stands for), compiled once."""
    return triangle_in_box(a, b, c, lower, upper)


@wp.func
def clip_margin(a: wp.vec3, b: wp.vec3, c: wp.vec3) -> float:
    """The widening of a clipped part of triangle abc: CLIP_MARGIN times its largest coordinate magnitude."""
    m = wp.max(wp.max(wp.abs(a), wp.abs(b)), wp.abs(c))
    return wp.max(wp.max(m[0], m[1]), m[2]) * CLIP_MARGIN


@wp.func
def slab_plane(lower: float, upper: float, j: int, num_bins: int) -> float:
    """Boundary j (1 .. num_bins - 1) of the equal slabs of [lower, upper] along one axis; monotone in j."""
    extent = upper - lower
    if wp.isinf(extent):
        # A box wider than float32's largest value (-3e38 to 3e38): every float32 plane was inf,
        # every reference fell in slab 0 and no spatial split was found. Such boxes are rare;
        # their planes come from float64, rounded once (still monotone in j, and within the box).
        wide = wp.float64(upper) - wp.float64(lower)
        return float(wp.float64(lower) + wide * (wp.float64(j) / wp.float64(num_bins)))
    return lower + extent * (float(j) / float(num_bins))


@wp.func
def planes_at_or_below(x: float, lower: float, upper: float, num_bins: int, strict: int) -> int:
    """How many of the planes 1 .. num_bins - 1 lie at or below x (strictly below if `strict`):
    the slab of x, found from the planes' own float32 values so that the reference's side of a
    plane never disagrees with the plane the distribution cuts at."""
    extent = upper - lower
    j = int(0)
    if wp.isinf(extent):
        # The guess in float64, as the planes are (`slab_plane`); in float32 it is inf / inf.
        j = int(wp.float64(num_bins) * (wp.float64(x) - wp.float64(lower)) / (wp.float64(upper) - wp.float64(lower)))
        j = wp.clamp(j, 0, num_bins - 1)
    else:
        j = wp.clamp(int(float(num_bins) * (x - lower) / extent), 0, num_bins - 1)
    # The guess is off by at most a step or two of rounding: walk it to the exact count.
    while j > 0:
        p = slab_plane(lower, upper, j, num_bins)
        if p > x or (strict == 1 and p == x):
            j -= 1
        else:
            break
    while j < num_bins - 1:
        p = slab_plane(lower, upper, j + 1, num_bins)
        if p < x or (strict == 0 and p == x):
            j += 1
        else:
            break
    return j


@wp.func
def slab_box(lower: wp.vec3, upper: wp.vec3, axis: int, lo: float, hi: float):
    """[lower, upper] with its extent along `axis` narrowed to [lo, hi] (clamped to it)."""
    out_lower = lower
    out_upper = upper
    out_lower[axis] = wp.max(lower[axis], lo)
    out_upper[axis] = wp.min(upper[axis], hi)
    return out_lower, out_upper


@wp.func
def round_down(x: wp.float64, margin: float) -> float:
    """x rounded down to float32 by at least one ulp, `margin` and a floor near zero: a lower bound."""
    f = float(x)
    return f - (wp.abs(f) * OUTWARD + margin + TINY)


@wp.func
def round_up(x: wp.float64, margin: float) -> float:
    """x rounded up to float32 by at least one ulp, `margin` and a floor near zero: an upper bound."""
    f = float(x)
    return f + (wp.abs(f) * OUTWARD + margin + TINY)


@wp.func
def slab_part_box(polygon: mat93d, count: int, axis: int, ref_lo: wp.vec3, ref_hi: wp.vec3, slab_lo: float,
                  slab_hi: float, margin: float):
    """The box of a reference's part in one slab, as the spatial-split binning of the SBVH (Stich,
    Friedrich & Dietrich, HPG 2009) gives each slab a reference spans the box of the triangle's part
    in it.

    The box of the polygon's part with slab_lo <= x[axis] <= slab_hi, widened by the clip's
    `margin` (`clip_margin`), rounded outward to float32 and clamped to the reference's box
    [ref_lo, ref_hi], along `axis` to the slab widened by the margin. A point of the triangle
    that the clip's rounding put just across the plane lies in one side's part or the other's
    (both sides cut at the same crossings), so the margin must reach across the plane too.
    Where the cut leaves nothing (the part touches the slab only by rounding) the reference's
    box narrowed to the slab is returned: conservative, never inverted."""
    part, n = clip_to_slab(polygon, count, axis, wp.float64(slab_lo), wp.float64(slab_hi))
    if n == 0:
        return slab_box(ref_lo, ref_hi, axis, slab_lo, slab_hi)
    lo = part[0]
    hi = part[0]
    for i in range(1, n):
        lo = wp.min(lo, part[i])
        hi = wp.max(hi, part[i])
    out_lo = wp.vec3(round_down(lo[0], margin), round_down(lo[1], margin), round_down(lo[2], margin))
    out_hi = wp.vec3(round_up(hi[0], margin), round_up(hi[1], margin), round_up(hi[2], margin))
    clamp_lo, clamp_hi = slab_box(ref_lo, ref_hi, axis, slab_lo - margin, slab_hi + margin)
    return wp.max(out_lo, clamp_lo), wp.min(out_hi, clamp_hi)


@wp.kernel
def split_search_kernel(
    first_seg: int,
    seg_begin: wp.array(dtype=wp.int32),
    seg_end: wp.array(dtype=wp.int32),
    seg_open: wp.array(dtype=wp.int32),
    ref_tri: wp.array(dtype=wp.int32),
    ref_lo: wp.array(dtype=wp.vec3),
    ref_hi: wp.array(dtype=wp.vec3),
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.int32, ndim=2),
    num_bins: int,
    max_leaf: int,
    root_area: wp.float64,
    alpha: wp.float64,
    seg_lo: wp.array(dtype=wp.vec3),
    seg_hi: wp.array(dtype=wp.vec3),
    seg_cen_lo: wp.array(dtype=wp.vec3),
    seg_cen_hi: wp.array(dtype=wp.vec3),
    obj_axis: wp.array(dtype=wp.int32),
    obj_bin: wp.array(dtype=wp.int32),
    obj_left: wp.array(dtype=wp.int32),
    obj_cost: wp.array(dtype=wp.float64),
    sp_axis: wp.array(dtype=wp.int32),
    sp_bin: wp.array(dtype=wp.int32),
    sp_left: wp.array(dtype=wp.int32),
    sp_right: wp.array(dtype=wp.int32),
    sp_cost: wp.array(dtype=wp.float64),
):
    """The split search of one node (segment s) of the SBVH (Stich, Friedrich & Dietrich, "Spatial
    Splits in Bounding Volume Hierarchies", HPG 2009): the best object split over binned centroids
    (Wald 2007) and, only where that split's two boxes overlap by more than alpha x area(root), their
    restriction of spatial split attempts, the best spatial split over equal slabs of the node's box.
    Writes the node's box and centroid bounds and each split's axis, boundary, side counts and SAH
    A(L) N(L) + A(R) N(R); the host chooses between them."""
    s = first_seg + wp.tid()
    obj_axis[s] = -1
    sp_axis[s] = -1
    if seg_open[s] == 0:
        return
    b = seg_begin[s]
    e = seg_end[s]
    n = e - b
    box_lo = wp.vec3(BIG)
    box_hi = wp.vec3(-BIG)
    cen_lo = wp.vec3(BIG)
    cen_hi = wp.vec3(-BIG)
    for k in range(b, e):
        lo = ref_lo[k]
        hi = ref_hi[k]
        c = box_centroid(lo, hi)
        box_lo = wp.min(box_lo, lo)
        box_hi = wp.max(box_hi, hi)
        cen_lo = wp.min(cen_lo, c)
        cen_hi = wp.max(cen_hi, c)
    seg_lo[s] = box_lo
    seg_hi[s] = box_hi
    seg_cen_lo[s] = cen_lo
    seg_cen_hi[s] = cen_hi
    if n <= max_leaf:
        return

    # Object split: centroid bins, the sweep of every bin boundary.
    counts = bin_counts()
    boxes_lo = bin_boxes()
    boxes_hi = bin_boxes()
    for i in range(3 * num_bins):
        boxes_lo[i] = wp.vec3(BIG)
        boxes_hi[i] = wp.vec3(-BIG)
    extent = cen_hi - cen_lo
    for k in range(b, e):
        lo = ref_lo[k]
        hi = ref_hi[k]
        c = box_centroid(lo, hi)
        for axis in range(3):
            if extent[axis] > 0.0:
                slot = axis * num_bins + centroid_bin(c[axis], cen_lo[axis], cen_hi[axis], num_bins)
                counts[slot] = counts[slot] + 1
                boxes_lo[slot] = wp.min(wp.vec3(boxes_lo[slot]), lo)
                boxes_hi[slot] = wp.max(wp.vec3(boxes_hi[slot]), hi)
    best_cost, best_axis, best_bin, best_left, best_right = best_split_of_bins(
        boxes_lo, boxes_hi, counts, counts, extent, num_bins, n)
    obj_axis[s] = best_axis
    obj_bin[s] = best_bin
    obj_left[s] = best_left
    obj_cost[s] = best_cost

    # Stich et al.'s test: try spatial splits where the object split's children overlap.
    try_spatial = int(1)
    if best_axis >= 0:
        l_lo = wp.vec3(BIG)
        l_hi = wp.vec3(-BIG)
        r_lo = wp.vec3(BIG)
        r_hi = wp.vec3(-BIG)
        for j in range(num_bins):
            slot = best_axis * num_bins + j
            if j < best_bin:
                l_lo = wp.min(l_lo, wp.vec3(boxes_lo[slot]))
                l_hi = wp.max(l_hi, wp.vec3(boxes_hi[slot]))
            else:
                r_lo = wp.min(r_lo, wp.vec3(boxes_lo[slot]))
                r_hi = wp.max(r_hi, wp.vec3(boxes_hi[slot]))
        o_lo = wp.max(l_lo, r_lo)
        o_hi = wp.min(l_hi, r_hi)
        overlap = wp.float64(0.0)
        if o_lo[0] <= o_hi[0] and o_lo[1] <= o_hi[1] and o_lo[2] <= o_hi[2]:
            overlap = box_area64(o_lo, o_hi)
        if not (overlap > alpha * root_area):
            try_spatial = 0
    if try_spatial == 0:
        return

    # Spatial split: chopped binning into equal slabs of the node's box.
    entries = bin_counts()
    exits = bin_counts()
    for i in range(3 * num_bins):
        boxes_lo[i] = wp.vec3(BIG)
        boxes_hi[i] = wp.vec3(-BIG)
    size = box_hi - box_lo
    for k in range(b, e):
        lo = ref_lo[k]
        hi = ref_hi[k]
        tri = ref_tri[k]
        polygon = mat93d()
        count = int(-1)  # the reference's polygon, clipped on first need
        margin = float(0.0)
        for axis in range(3):
            if size[axis] > 0.0:
                b0 = planes_at_or_below(lo[axis], box_lo[axis], box_hi[axis], num_bins, 0)
                b1 = wp.max(b0, planes_at_or_below(hi[axis], box_lo[axis], box_hi[axis], num_bins, 1))
                entries[axis * num_bins + b0] = entries[axis * num_bins + b0] + 1
                exits[axis * num_bins + b1] = exits[axis * num_bins + b1] + 1
                if b0 == b1:
                    slot = axis * num_bins + b0
                    boxes_lo[slot] = wp.min(wp.vec3(boxes_lo[slot]), lo)
                    boxes_hi[slot] = wp.max(wp.vec3(boxes_hi[slot]), hi)
                else:
                    if count < 0:
                        a = vertices[faces[tri, 0]]
                        bv = vertices[faces[tri, 1]]
                        cv = vertices[faces[tri, 2]]
                        polygon, count = reference_polygon(a, bv, cv, lo, hi)
                        margin = clip_margin(a, bv, cv)
                    for bb in range(b0, b1 + 1):
                        slab_lo = lo[axis]
                        slab_hi = hi[axis]
                        if bb > b0:
                            slab_lo = slab_plane(box_lo[axis], box_hi[axis], bb, num_bins)
                        if bb < b1:
                            slab_hi = slab_plane(box_lo[axis], box_hi[axis], bb + 1, num_bins)
                        part_lo, part_hi = slab_part_box(polygon, count, axis, lo, hi, slab_lo, slab_hi, margin)
                        slot = axis * num_bins + bb
                        boxes_lo[slot] = wp.min(wp.vec3(boxes_lo[slot]), part_lo)
                        boxes_hi[slot] = wp.max(wp.vec3(boxes_hi[slot]), part_hi)
    # Both sides strictly smaller than the node (the sweep's rule): the recursion ends.
    sp_best, sp_best_axis, sp_best_bin, sp_best_left, sp_best_right = best_split_of_bins(
        boxes_lo, boxes_hi, entries, exits, size, num_bins, n)
    sp_axis[s] = sp_best_axis
    sp_bin[s] = sp_best_bin
    sp_left[s] = sp_best_left
    sp_right[s] = sp_best_right
    sp_cost[s] = sp_best


@wp.kernel
def distribute_kernel(
    first_seg: int,
    seg_begin: wp.array(dtype=wp.int32),
    seg_end: wp.array(dtype=wp.int32),
    seg_kind: wp.array(dtype=wp.int32),
    seg_axis: wp.array(dtype=wp.int32),
    seg_bin: wp.array(dtype=wp.int32),
    seg_left: wp.array(dtype=wp.int32),
    seg_out: wp.array(dtype=wp.int32),
    seg_lo: wp.array(dtype=wp.vec3),
    seg_hi: wp.array(dtype=wp.vec3),
    seg_cen_lo: wp.array(dtype=wp.vec3),
    seg_cen_hi: wp.array(dtype=wp.vec3),
    num_bins: int,
    ref_tri: wp.array(dtype=wp.int32),
    ref_lo: wp.array(dtype=wp.vec3),
    ref_hi: wp.array(dtype=wp.vec3),
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.int32, ndim=2),
    out_tri: wp.array(dtype=wp.int32),
    out_lo: wp.array(dtype=wp.vec3),
    out_hi: wp.array(dtype=wp.vec3),
):
    """Write segment s's references at seg_out[s]: a leaf's as they are, a split node's left side
    (seg_left[s] references) and then its right side, in their current order.

    The SBVH's reference distribution (Stich, Friedrich & Dietrich, HPG 2009): under a spatial split a
    reference straddling the plane goes to both children, each with the box of its side's part. Their
    reference unsplitting (keeping such a reference whole on one side when that is cheaper) is not
    done here: a straddling reference is always split.
    """
    s = first_seg + wp.tid()
    b = seg_begin[s]
    e = seg_end[s]
    kind = seg_kind[s]
    axis = seg_axis[s]
    j = seg_bin[s]
    left = seg_out[s]
    right = left + seg_left[s]
    if kind == KIND_HALVE:
        right = left + (e - b) // 2
    box_lo = seg_lo[s]
    box_hi = seg_hi[s]
    cen_lo = seg_cen_lo[s]
    cen_hi = seg_cen_hi[s]
    plane = float(0.0)
    if kind == KIND_SPATIAL:
        plane = slab_plane(box_lo[axis], box_hi[axis], j, num_bins)
    for k in range(b, e):
        tri = ref_tri[k]
        lo = ref_lo[k]
        hi = ref_hi[k]
        to_left = int(0)
        to_right = int(0)
        if kind == KIND_LEAF:
            to_left = 1
        elif kind == KIND_HALVE:
            if k - b < (e - b) // 2:
                to_left = 1
            else:
                to_right = 1
        elif kind == KIND_OBJECT:
            # The search kernel's expression, so both count the same side.
            c = box_centroid(lo, hi)
            if centroid_bin(c[axis], cen_lo[axis], cen_hi[axis], num_bins) < j:
                to_left = 1
            else:
                to_right = 1
        else:
            b0 = planes_at_or_below(lo[axis], box_lo[axis], box_hi[axis], num_bins, 0)
            b1 = wp.max(b0, planes_at_or_below(hi[axis], box_lo[axis], box_hi[axis], num_bins, 1))
            if b0 < j:
                to_left = 1
            if b1 >= j:
                to_right = 1
        if to_left == 1 and to_right == 1:
            # Straddles the plane: each side gets the box of its part of the triangle.
            a = vertices[faces[tri, 0]]
            bv = vertices[faces[tri, 1]]
            cv = vertices[faces[tri, 2]]
            polygon, count = reference_polygon(a, bv, cv, lo, hi)
            margin = clip_margin(a, bv, cv)
            part_lo, part_hi = slab_part_box(polygon, count, axis, lo, hi, lo[axis], plane, margin)
            out_tri[left] = tri
            out_lo[left] = part_lo
            out_hi[left] = part_hi
            left += 1
            part_lo, part_hi = slab_part_box(polygon, count, axis, lo, hi, plane, hi[axis], margin)
            out_tri[right] = tri
            out_lo[right] = part_lo
            out_hi[right] = part_hi
            right += 1
        elif to_left == 1:
            out_tri[left] = tri
            out_lo[left] = lo
            out_hi[left] = hi
            left += 1
        else:
            out_tri[right] = tri
            out_lo[right] = lo
            out_hi[right] = hi
            right += 1
