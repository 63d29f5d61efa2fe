"""Wide BVHs: a binary BVH collapsed to up to k children per node, and rays through one.

Collapse (the usual construction of k-ary BVHs from binary ones; Garczorz 2026 compares it with
direct k-way splitting): each wide node starts from its binary node's two children and, while it
has fewer than k, replaces the interior child of largest surface area by that child's two
children (a greedy rule of this library's, not the thesis's: see `expand_kernel`). The interior
children left at the end become the next level's wide nodes, so the collapse runs level by level,
one thread per wide node of a level, with a scan placing each level's new nodes.

Layout: wide node w owns slots ``w * k .. w * k + k - 1``. A slot holds a child's box, its range
of ``prim_order`` and ``slot_child``: the child's wide node index, ``LEAF`` for a leaf (its
triangles are the range), or ``EMPTY`` past the last child. The child boxes sit in the parent
(as in the multi-BVH nodes of Ernst & Greiner 2008), so a step tests all k boxes of one node.
"""

from typing import Any

import warp as wp

from .metrics import box_area64
from .traversal import (INF, PackedTriangle, far_hit_in_range, intersect_triangle_watertight, query_limit,
                        query_prim, ray_box_entry, ray_direction_scale, ray_inverse_direction, ray_is_valid,
                        ray_may_overflow, ray_scaled_t_max, ray_scaled_t_min, walk_start)

# Forward-only kernels: no adjoints to compile.
wp.set_module_options({"enable_backward": False})

MAX_WIDTH = 16
LEAF_SLOT = -1
EMPTY_SLOT = -2
LEAF = wp.constant(LEAF_SLOT)
EMPTY = wp.constant(EMPTY_SLOT)
vec16i = wp.types.vector(length=MAX_WIDTH, dtype=wp.int32)
vec16f = wp.types.vector(length=MAX_WIDTH, dtype=wp.float32)
#: Deferred entries of the wide traversal: up to k - 1 per level of the wide tree.
WIDE_STACK_SIZE = 256
vec256i = wp.types.vector(length=WIDE_STACK_SIZE, dtype=wp.int32)
vec256f = wp.types.vector(length=WIDE_STACK_SIZE, dtype=wp.float32)
WIDE_STACK = wp.constant(WIDE_STACK_SIZE)


@wp.kernel
def expand_kernel(
    width: int,
    frontier: wp.array(dtype=wp.int32),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
    chosen: wp.array(dtype=wp.int32),
    interior_count: wp.array(dtype=wp.int32),
):
    """The children of one wide node (the binary node ``frontier[w]``): binary node ids into
    ``chosen[w * width ...]`` (-1 past the last), and how many of them are interior.

    The greedy collapse: start from the binary node's two children and, while there are fewer than
    `width`, replace the interior child of largest surface area by its two children. This rule is
    not taken from a paper. Garczorz (2026, Bachelor thesis, HHU Duesseldorf), whose comparison of
    collapsed and directly k-way split wide BVHs the project follows, describes collapsing only as
    merging nodes with their children to double the branching factor (its section 1.4; its section
    3.2.3 on the collapse function is empty in the copy we have).
    """
    w = wp.tid()
    b = frontier[w]
    picked = vec16i()
    count = int(1)
    picked[0] = b
    if node_left[b] >= 0:
        picked[0] = node_left[b]
        picked[1] = node_right[b]
        count = 2
    while count < width:
        best = int(-1)
        best_area = wp.float64(-1.0)
        for j in range(count):
            c = picked[j]
            if node_left[c] >= 0:
                # In float64: float32 areas overflowed to inf past coordinates of about 1e19 and
                # underflowed to 0 below about 1e-20, so every child tied and the earliest won.
                a = box_area64(node_lowers[c], node_uppers[c])
                if a > best_area:
                    best_area = a
                    best = j
        if best < 0:
            break
        c = picked[best]
        picked[best] = node_left[c]
        picked[count] = node_right[c]
        count += 1
    interior = int(0)
    for j in range(width):
        if j < count:
            chosen[w * width + j] = picked[j]
            if node_left[picked[j]] >= 0:
                interior += 1
        else:
            chosen[w * width + j] = -1
    interior_count[w] = interior


@wp.kernel
def emit_kernel(
    width: int,
    first_wide: int,
    next_first: int,
    frontier: wp.array(dtype=wp.int32),
    chosen: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),
    node_left: wp.array(dtype=wp.int32),
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    slot_lowers: wp.array(dtype=wp.vec3),
    slot_uppers: wp.array(dtype=wp.vec3),
    slot_child: wp.array(dtype=wp.int32),
    slot_begin: wp.array(dtype=wp.int32),
    slot_end: wp.array(dtype=wp.int32),
    wide_begin: wp.array(dtype=wp.int32),
    wide_end: wp.array(dtype=wp.int32),
    next_frontier: wp.array(dtype=wp.int32),
):
    """Write wide node ``first_wide + w``: its slots, its own range, and its interior children
    as the next level's wide nodes, numbered from ``next_first + offsets[w]``: the second half of
    the greedy collapse of `expand_kernel` (see there for where the rule comes from)."""
    w = wp.tid()
    node = first_wide + w
    b = frontier[w]
    wide_begin[node] = node_begin[b]
    wide_end[node] = node_end[b]
    o = offsets[w]
    for j in range(width):
        s = node * width + j
        c = chosen[w * width + j]
        if c < 0:
            # An empty slot: an inverted box no ray enters.
            slot_lowers[s] = wp.vec3(INF)
            slot_uppers[s] = wp.vec3(-INF)
            slot_child[s] = EMPTY
            slot_begin[s] = 0
            slot_end[s] = 0
        else:
            slot_lowers[s] = node_lowers[c]
            slot_uppers[s] = node_uppers[c]
            slot_begin[s] = node_begin[c]
            slot_end[s] = node_end[c]
            if node_left[c] >= 0:
                slot_child[s] = next_first + o
                next_frontier[o] = c
                o += 1
            else:
                slot_child[s] = LEAF


@wp.kernel
def wide_sah_terms_kernel(
    width: int,
    root_area: wp.float64,
    slot_lowers: wp.array(dtype=wp.vec3),
    slot_uppers: wp.array(dtype=wp.vec3),
    slot_child: wp.array(dtype=wp.int32),
    slot_begin: wp.array(dtype=wp.int32),
    slot_end: wp.array(dtype=wp.int32),
    t_traversal: wp.float64,
    t_intersect: wp.float64,
    terms: wp.array(dtype=wp.float64),
):
    """Pantaleoni & Luebke's (HPG 2010) eq. (1) unrolled over a wide node's slots: every child costs
    T1 at its parent, and each child's own term (T1 times its children, or T2 times its
    triangles) weighs by area(child) / area(root)."""
    w = wp.tid()
    total = wp.float64(0.0)
    for j in range(width):
        s = w * width + j
        kind = slot_child[s]
        if kind != EMPTY:
            ratio = wp.float64(1.0)
            if root_area > wp.float64(0.0):
                ratio = box_area64(slot_lowers[s], slot_uppers[s]) / root_area
            own = t_intersect * wp.float64(slot_end[s] - slot_begin[s])
            if kind >= 0:
                grandchildren = int(0)
                for i in range(width):
                    if slot_child[kind * width + i] != EMPTY:
                        grandchildren += 1
                own = t_traversal * wp.float64(grandchildren)
            total += own * ratio
    terms[w] = total


@wp.struct
class WideSlot:
    """One child of a wide node in the traversal layout: the slot arrays' five fields in one
    36-byte record, so a node's k children are k records side by side (one or two cache lines at
    k = 2, four at k = 4) instead of five arrays' worth of lines."""

    lower: wp.vec3
    upper: wp.vec3
    child: wp.int32
    begin: wp.int32
    end: wp.int32


@wp.kernel
def pack_slots_kernel(
    slot_lowers: wp.array(dtype=wp.vec3),
    slot_uppers: wp.array(dtype=wp.vec3),
    slot_child: wp.array(dtype=wp.int32),
    slot_begin: wp.array(dtype=wp.int32),
    slot_end: wp.array(dtype=wp.int32),
    slots: wp.array(dtype=WideSlot),
):
    """Pack the five slot arrays into one `WideSlot` record per slot (the traversal layout)."""
    s = wp.tid()
    record = WideSlot()
    record.lower = slot_lowers[s]
    record.upper = slot_uppers[s]
    record.child = slot_child[s]
    record.begin = slot_begin[s]
    record.end = slot_end[s]
    slots[s] = record


# Software prefetch of a wide node's first slot records (as the binary traversal's, a hint only).
_PREFETCH_SLOTS = """
#if !defined(__CUDA_ARCH__)
    const char* first = (const char*)slots.data + (size_t)index * (size_t)slots.strides[0];
    __builtin_prefetch(first);
    __builtin_prefetch(first + 64);
#endif
"""


@wp.func_native(_PREFETCH_SLOTS)
def prefetch_slots(slots: wp.array(dtype=WideSlot), index: int):
    """Prefetch the first two cache lines of slot records from `index` on the CPU (nothing on CUDA)."""
    ...


@wp.struct
class WideHit:
    """What `wide_closest_hit` returns: hit distance, primitive (-1 on a miss) and traversal counters."""

    t: float
    prim: int
    nodes_visited: int
    boxes_tested: int
    prims_tested: int


@wp.func
def wide_closest_hit(
    width: int,
    root_lower: wp.vec3,
    root_upper: wp.vec3,
    slots: wp.array(dtype=WideSlot),
    wide_begin: wp.array(dtype=wp.int32),
    wide_end: wp.array(dtype=wp.int32),
    prim_order: wp.array(dtype=wp.int32),
    triangles: wp.array(dtype=PackedTriangle),
    origin: wp.vec3,
    direction: wp.vec3,
    t_min: float,
    t_max: float,
    ignore_prim: int,
):
    """Closest hit through a wide BVH: at each node all k child boxes are tested and the hit ones
    stacked farthest first, so the nearest is taken next; an entry popped behind the closest hit
    so far is dropped. Stack entries are wide nodes (>= 0) or leaf slots (-(slot + 1)). The same
    watertight triangle test and padded box test as the binary traversal (kernels/traversal.py),
    so both find the same hits. ``triangles`` are the binary tree's, in ``prim_order`` order.

    Hits count with t in (t_min, t_max), and never on ``ignore_prim`` (-1: none), the triangle a
    secondary ray leaves from, as in the binary `traversal.packed_ray_query`: boxes are entered
    from t_min on, and a hit on the ignored triangle is refused after the triangle test, where
    ``prim_order`` is read for every hit anyway."""
    best_t = t_max
    best_prim = int(-1)
    visited = int(0)
    boxes = int(0)
    tested = int(0)
    stack = vec256i()
    stack_t = vec256f()
    top = int(0)
    inv = wp.vec3(0.0)
    # A tiny or huge direction is scaled into range (see `ray_direction_scale`).
    scale = ray_direction_scale(direction)
    d = direction * scale
    low = ray_scaled_t_min(t_min, scale)
    best_t = ray_scaled_t_max(t_max, scale)
    range_min = low
    range_max = best_t
    # A far origin starts nearer, in float64, as in the binary walk.
    ray = walk_start(origin, d, low, best_t, root_lower, root_upper)
    start = ray.origin
    low = ray.t_min
    best_t = ray.t_max
    shift = ray.shift
    # Box differences that may pass float32's range (coordinates near 1.7e38 on both sides of the
    # origin) have the boxes they would miss decided again in float64, as in the binary walk.
    wide = int(0)
    if ray_is_valid(start, d, low, best_t) == 1:
        inv = ray_inverse_direction(d)
        wide = ray_may_overflow(start, root_lower, root_upper)
        t_root = ray_box_entry(start, inv, root_lower, root_upper, low, best_t, wide)
        if t_root < INF:
            stack[0] = 0
            stack_t[0] = t_root
            top = 1
    while top > 0:
        top -= 1
        entry = stack[top]
        if stack_t[top] <= best_t:
            first = int(0)
            last = int(0)
            if entry < 0:
                record = slots[-entry - 1]
                first = record.begin
                last = record.end
            elif top + width > WIDE_STACK:
                # No room to stack the children: test the node's whole range instead.
                visited += 1
                first = wide_begin[entry]
                last = wide_end[entry]
            else:
                visited += 1
                hit_t = vec16f()
                hit_e = vec16i()
                hits = int(0)
                for j in range(width):
                    s = entry * width + j
                    record = slots[s]
                    if record.child != EMPTY:
                        boxes += 1
                        t = ray_box_entry(start, inv, record.lower, record.upper, low, best_t, wide)
                        if t < INF:
                            e = record.child
                            if e == LEAF:
                                e = -(s + 1)
                            # Insertion by descending entry distance.
                            i = hits
                            while i > 0 and hit_t[i - 1] < t:
                                hit_t[i] = hit_t[i - 1]
                                hit_e[i] = hit_e[i - 1]
                                i -= 1
                            hit_t[i] = t
                            hit_e[i] = e
                            hits += 1
                for i in range(hits):
                    stack[top] = hit_e[i]
                    stack_t[top] = hit_t[i]
                    top += 1
                # The nearest child is taken next: ask for its records now.
                if hits > 0 and hit_e[hits - 1] >= 0:
                    prefetch_slots(slots, hit_e[hits - 1] * width)
            for k in range(first, last):
                tested += 1
                tri = triangles[k]
                h = intersect_triangle_watertight(start, d, tri.a, tri.b, tri.c, low, best_t)
                if h.hit == 1:
                    p = prim_order[k]
                    if p != ignore_prim and far_hit_in_range(h.t, shift, range_min, range_max) == 1:
                        best_t = h.t
                        best_prim = p
    result = WideHit()
    result.t = INF
    result.prim = best_prim
    if best_prim >= 0:
        result.t = float(wp.float64(best_t) + shift) * scale
    result.nodes_visited = visited
    result.boxes_tested = boxes
    result.prims_tested = tested
    return result


@wp.struct
class WideView:
    """Everything `bvh_wide_closest_hit` reads, passed by value into user kernels (see
    ``hlbvh_warp.wide.view``). ``width`` is k; ``slots`` holds k records per wide node (the layout
    of the module docstring); ``wide_begin`` / ``wide_end`` are each wide node's range of
    ``prim_order``; ``triangles`` are the binary tree's packed triangles in ``prim_order`` order;
    ``root_lower`` / ``root_upper`` are the root's box."""

    width: int
    root_lower: wp.vec3
    root_upper: wp.vec3
    slots: wp.array(dtype=WideSlot)
    wide_begin: wp.array(dtype=wp.int32)
    wide_end: wp.array(dtype=wp.int32)
    prim_order: wp.array(dtype=wp.int32)
    triangles: wp.array(dtype=PackedTriangle)


@wp.func
def bvh_wide_closest_hit(view: WideView, origin: wp.vec3, direction: wp.vec3, t_max: float):
    """Closest hit of one ray through a wide BVH, for user kernels: a `WideHit` (``prim`` -1 and
    ``t`` inf on a miss; hits count for t in (0, t_max)). The same hits as
    ``hlbvh_warp.wide.intersect`` (see `wide_closest_hit`)."""
    return wide_closest_hit(view.width, view.root_lower, view.root_upper, view.slots, view.wide_begin, view.wide_end,
                            view.prim_order, view.triangles, origin, direction, 0.0, t_max, -1)


@wp.func
def bvh_wide_closest_hit(  # noqa: F811  (a Warp overload, chosen by argument count)
    view: WideView, origin: wp.vec3, direction: wp.vec3, t_min: float, t_max: float, ignore_prim: int
):
    """Closest hit with t in (t_min, t_max) on any triangle but ``ignore_prim`` (-1: none), as the
    binary tree's ``bvh_closest_hit`` of the same arguments: a secondary ray ignores the triangle
    it leaves from. A range with ``t_min < 0``, NaN, or ``t_max <= t_min`` finds nothing."""
    return wide_closest_hit(view.width, view.root_lower, view.root_upper, view.slots, view.wide_begin, view.wide_end,
                            view.prim_order, view.triangles, origin, direction, t_min, t_max, ignore_prim)


@wp.kernel
def wide_closest_hit_any_limit_kernel(
    view: WideView,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    t_max: Any,
    hit_t: wp.array(dtype=float),
    hit_prim: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.vec3i),
):
    """One ray per thread; ``t_max`` is one limit (a float) or one per ray (an array, see
    `query_limit`); ``counts`` (nodes visited, boxes tested, triangles tested) is written when it
    has an entry per ray."""
    i = wp.tid()
    h = bvh_wide_closest_hit(view, origins[i], directions[i], query_limit(t_max, i))
    hit_t[i] = h.t
    hit_prim[i] = h.prim
    if counts.shape[0] > 0:
        counts[i] = wp.vec3i(h.nodes_visited, h.boxes_tested, h.prims_tested)


# One limit for every ray, or one per ray; launched as these concrete overloads (see
# `proximity.closest_point_kernel`), the one-limit one under the kernel's old name.
wide_closest_hit_kernel = wp.overload(wide_closest_hit_any_limit_kernel, {"t_max": float})
wide_closest_hit_limits_kernel = wp.overload(wide_closest_hit_any_limit_kernel, {"t_max": wp.array(dtype=float)})


@wp.kernel
def wide_closest_hit_range_kernel(
    view: WideView,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    t_min: wp.array(dtype=float),
    t_max: wp.array(dtype=float),
    ignore_prim: wp.array(dtype=wp.int32),
    hit_t: wp.array(dtype=float),
    hit_prim: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.vec3i),
):
    """One ray per thread over its range (`query_limit` for each end) and its ignored triangle
    (`query_prim`); ``counts`` as in `wide_closest_hit_any_limit_kernel`. Kept apart from the
    lean kernels above: on the CPU every thread copies the kernel's arguments, which plain rays
    should not pay for."""
    i = wp.tid()
    h = bvh_wide_closest_hit(view, origins[i], directions[i], query_limit(t_min, i), query_limit(t_max, i),
                             query_prim(ignore_prim, i))
    hit_t[i] = h.t
    hit_prim[i] = h.prim
    if counts.shape[0] > 0:
        counts[i] = wp.vec3i(h.nodes_visited, h.boxes_tested, h.prims_tested)
