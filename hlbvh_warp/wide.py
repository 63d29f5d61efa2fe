"""Wide BVHs (k = 2 .. 16 children per node) collapsed from any binary BVH of this library.

Garczorz (2026) builds BVHs of branching factor k in {2, 4, 8, 16} by direct k-way splitting or
by collapsing a binary BVH, and measures serial CPU closest-hit traversal against k = 2. This
module is the collapse (level by level on the device, ``kernels/wide.py``), a closest-hit ray
query through the result, and its SAH cost:

    wide = hlbvh_warp.wide.collapse(bvh, width=4)
    t, prim = hlbvh_warp.wide.intersect(wide, origins, directions)

and, in a user kernel, ``hlbvh_warp.wide.bvh_wide_closest_hit(view, origin, direction, t_max)``
(or ``(view, origin, direction, t_min, t_max, ignore_prim)`` for secondary rays) on the struct
``hlbvh_warp.wide.view(wide)``.

The wide tree shares the binary tree's ``prim_order``, vertices and faces; it owns only its
nodes. ``width=2`` gives the binary tree itself in the wide layout, the baseline of a k-ary
comparison that changes nothing but k.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import warp as wp

from . import inputs, metrics
from .bvh import Bvh, held, holding_tree, not_a_bvh
from .kernels import wide as kernels
from .kernels.traversal import PackedTriangle
from .kernels.wide import WideHit, WideView, bvh_wide_closest_hit  # noqa: F401  (re-exported for user kernels)

WIDTHS = tuple(range(2, kernels.MAX_WIDTH + 1))


@dataclass
class WideTraversalStats:
    """Per ray: wide nodes visited, child boxes tested, triangles tested."""

    nodes_visited: np.ndarray
    boxes_tested: np.ndarray
    prims_tested: np.ndarray

    def summary(self) -> dict:
        """The three counters' means over the rays (0 for no rays)."""
        def mean(a):
            return float(a.mean()) if a.size else 0.0

        return {"mean_nodes_visited": mean(self.nodes_visited), "mean_boxes_tested": mean(self.boxes_tested),
                "mean_prims_tested": mean(self.prims_tested)}


def _holding_binary_tree(fn):
    """`held` around a host call on a wide tree: it reads its binary tree's primitive order and
    triangles, which a `Builder` rewrites in place, so it waits for an update in progress as the
    binary queries do, and its generation check then sees that update (and refuses)."""

    @functools.wraps(fn)
    def wrapper(wide, *args, **kwargs):
        with held(getattr(wide, "bvh", None)):
            return fn(wide, *args, **kwargs)

    return wrapper


class WideBvh:
    """A BVH of up to ``width`` children per node (see ``kernels/wide.py`` for the slot layout).

    ``slot_*`` arrays have ``num_nodes * width`` entries; ``wide_begin`` / ``wide_end`` are each
    node's range of the binary tree's ``prim_order``. ``bvh`` is the binary tree it came from.
    ``slots`` (the same fields as one `WideSlot` record per slot) and ``triangles`` (the binary
    tree's packed triangles) are what the ray traversal reads. The wide tree's boxes are copied at
    the collapse, but it reads the binary tree's ``prim_order`` and triangles: after a refit or
    rebuild of that tree, collapse it again. Its host calls (`intersect`, `view`, `launch_args`,
    `sah_cost`, `to_numpy`) refuse it once the binary tree has changed (`Bvh.generation`); a view
    already handed to a kernel cannot tell.
    """

    def __init__(self, bvh: Bvh, width: int, num_nodes: int, arrays: dict, levels: int):
        self.bvh = bvh
        #: The binary tree's `Bvh.generation` at the collapse.
        self.generation = bvh.generation
        self.width = width
        self.num_nodes = num_nodes
        #: Levels of wide nodes (the root's is 1).
        self.depth = levels
        for name, array in arrays.items():
            setattr(self, name, array)
        self._view = None  # `collapse` makes it for a mesh tree, with the slots it snapshots

    def view(self):
        """A `WideView` struct of this tree for user kernels (``bvh_wide_closest_hit``)."""
        return view(self)

    def __ctype__(self):
        """Refuse to be a kernel argument, naming the view to pass instead (see `Bvh.__ctype__`)."""
        raise TypeError("a Warp kernel takes the wide tree's view, not the WideBvh: pass wide.view(w) "
                        "(w.view()) as the WideView argument")

    @property
    def device(self):
        """The device of the binary tree it was collapsed from."""
        return self.bvh.device

    @_holding_binary_tree
    def to_numpy(self) -> dict:
        """The slot and per-node range arrays, and the binary tree's ``prim_order``, as NumPy, keyed by
        attribute name."""
        _require_current(self, "to_numpy")
        names = ("slot_lowers", "slot_uppers", "slot_child", "slot_begin", "slot_end", "wide_begin", "wide_end")
        # Copies: on the CPU `numpy()` shares the device memory, and an edit would change the trees
        # (``prim_order`` is the binary tree's own).
        out = {name: getattr(self, name).numpy().copy() for name in names}
        out["prim_order"] = self.bvh.prim_order.numpy().copy()
        return out


def _require_current(wide: WideBvh, name: str):
    """Raise unless the binary tree is the one `wide` was collapsed from (no refit or rebuild since)."""
    if wide.generation != wide.bvh.generation:
        raise ValueError(f"{name}(): the binary tree was refit or rebuilt since this wide tree was collapsed from "
                         "it, and the wide tree reads its primitive order and triangles: collapse it again")


@holding_tree
def collapse(bvh: Bvh, width: int = 4) -> WideBvh:
    """Collapse a binary BVH to one of up to `width` children per node (greedy: a wide node's
    interior child of largest surface area is replaced by its two children while there is room).

    Garczorz (2026), whose comparison this module follows, collapses a binary BVH by merging nodes
    with their children to double the branching factor (k = 2, 4, 8, 16); the largest-area rule
    here, which allows any k from 2 to 16, is this library's own (`kernels.wide.expand_kernel`).

    One expand launch, one scan and one emit launch per level of the wide tree, and one count
    read on the host per level: a conversion after the build, not a per-frame stage.
    """
    if not isinstance(bvh, Bvh):
        raise ValueError(not_a_bvh("collapse", bvh))
    if isinstance(width, bool) or not isinstance(width, (int, np.integer)) or not 2 <= width <= kernels.MAX_WIDTH:
        raise ValueError(f"width must be an integer in [2, {kernels.MAX_WIDTH}], got {width!r}")
    width = int(width)
    device = bvh.device
    level_arrays = []
    frontier = wp.array(np.zeros(1, dtype=np.int32), dtype=wp.int32, device=device)
    num_level, first = 1, 0
    while num_level > 0:
        chosen = wp.empty(num_level * width, dtype=wp.int32, device=device)
        interior = wp.empty(num_level, dtype=wp.int32, device=device)
        wp.launch(kernels.expand_kernel, dim=num_level, device=device,
                  inputs=[width, frontier, bvh.node_left, bvh.node_right, bvh.node_lowers, bvh.node_uppers,
                          chosen, interior])
        offsets = wp.empty(num_level, dtype=wp.int32, device=device)
        wp.utils.array_scan(interior, offsets, inclusive=False)
        # The one host read of a level: how many wide nodes the next one has.
        last = np.concatenate([offsets[num_level - 1:].numpy(), interior[num_level - 1:].numpy()])
        num_next = int(last.sum())
        slots = {name: wp.empty(num_level * width, dtype=dtype, device=device)
                 for name, dtype in (("slot_lowers", wp.vec3), ("slot_uppers", wp.vec3), ("slot_child", wp.int32),
                                     ("slot_begin", wp.int32), ("slot_end", wp.int32))}
        ranges = {name: wp.empty(num_level, dtype=wp.int32, device=device) for name in ("wide_begin", "wide_end")}
        next_frontier = wp.empty(max(num_next, 1), dtype=wp.int32, device=device)
        wp.launch(kernels.emit_kernel, dim=num_level, device=device,
                  inputs=[width, 0, first + num_level, frontier, chosen, offsets, bvh.node_left, bvh.node_lowers,
                          bvh.node_uppers, bvh.node_begin, bvh.node_end, slots["slot_lowers"], slots["slot_uppers"],
                          slots["slot_child"], slots["slot_begin"], slots["slot_end"], ranges["wide_begin"],
                          ranges["wide_end"], next_frontier])
        level_arrays.append((num_level, {**slots, **ranges}))
        first += num_level
        frontier, num_level = next_frontier, num_next
    # The levels side by side in one array each: node numbers are already global.
    total = first
    arrays = {}
    for name in ("slot_lowers", "slot_uppers", "slot_child", "slot_begin", "slot_end"):
        arrays[name] = wp.empty(total * width, dtype=level_arrays[0][1][name].dtype, device=device)
    for name in ("wide_begin", "wide_end"):
        arrays[name] = wp.empty(total, dtype=wp.int32, device=device)
    offset = 0
    for count, level in level_arrays:
        for name, array in level.items():
            per_node = width if name.startswith("slot_") else 1
            wp.copy(arrays[name], array, dest_offset=offset * per_node, count=count * per_node)
        offset += count
    # The traversal layout: each slot's fields in one record, and the binary tree's packed
    # triangles (in prim_order order, shared with its own ray queries).
    arrays["slots"] = wp.empty(total * width, dtype=kernels.WideSlot, device=device)
    wp.launch(kernels.pack_slots_kernel, dim=total * width, device=device,
              inputs=[arrays["slot_lowers"], arrays["slot_uppers"], arrays["slot_child"], arrays["slot_begin"],
                      arrays["slot_end"], arrays["slots"]])
    if bvh.vertices is not None and bvh.faces is not None:
        from .query import view as binary_view

        arrays["triangles"] = binary_view(bvh).packed_triangles
    else:
        arrays["triangles"] = wp.empty(0, dtype=PackedTriangle, device=device)
    wide = WideBvh(bvh, width, total, arrays, len(level_arrays))
    if bvh.vertices is not None and bvh.faces is not None:
        view(wide)  # the root box read now, with the slots it was cut from
    return wide


@_holding_binary_tree
def sah_cost(wide: WideBvh, t_traversal: float = 1.0, t_intersect: float = 1.0) -> float:
    """Pantaleoni & Luebke's eq. (1) on the wide tree: C(node) = T1 * N_children + sum of
    C(child) * area(child) / area(node), C(leaf) = T2 * N_prims. At width 2 it is
    `metrics.sah_cost` of the binary tree."""
    if not isinstance(wide, WideBvh):
        raise ValueError(f"sah_cost() takes a WideBvh (wide.collapse), got {type(wide).__name__}")
    _require_current(wide, "sah_cost")
    t_traversal, t_intersect = metrics.check_costs(t_traversal, t_intersect)
    bvh = wide.bvh
    if int(bvh.node_left[0:1].numpy()[0]) < 0:
        # A single leaf: no traversal step at all.
        return float(t_intersect * bvh.num_refs)
    root_lo, root_hi = (a[0:1].numpy()[0].astype(np.float64) for a in (bvh.node_lowers, bvh.node_uppers))
    d = root_hi - root_lo
    root_area = 2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0])
    terms = wp.empty(wide.num_nodes, dtype=wp.float64, device=wide.device)
    wp.launch(kernels.wide_sah_terms_kernel, dim=wide.num_nodes, device=wide.device,
              inputs=[wide.width, wp.float64(root_area), wide.slot_lowers, wide.slot_uppers, wide.slot_child,
                      wide.slot_begin, wide.slot_end, wp.float64(t_traversal), wp.float64(t_intersect), terms])
    root_children = int((wide.slot_child[: wide.width].numpy() != kernels.EMPTY_SLOT).sum())
    return float(t_traversal * root_children + terms.numpy().sum())


def view(wide: WideBvh) -> kernels.WideView:
    """The `WideView` struct of ``wide`` for user kernels, which call
    ``hlbvh_warp.wide.bvh_wide_closest_hit(view, origin, direction, t_max)`` or, for a range and
    an ignored triangle, ``bvh_wide_closest_hit(view, origin, direction, t_min, t_max, ignore_prim)``.

    It reads the wide tree's slots and the binary tree's primitive order and triangles: after a
    refit or rebuild of the binary tree, collapse it again and take a new view (this call refuses
    a wide tree whose binary tree has changed; a view already in a kernel cannot tell).

    Raises:
        ValueError: not a `WideBvh`, or one collapsed from a BVH over bare boxes (no triangles to hit).
    """
    if not isinstance(wide, WideBvh):
        raise ValueError(f"view() takes a WideBvh (wide.collapse), got {type(wide).__name__}")
    bvh = wide.bvh
    if bvh.vertices is None or bvh.faces is None:
        raise ValueError("view() needs a wide BVH collapsed from a mesh BVH, not from bare boxes")
    _require_current(wide, "view")
    if wide._view is not None:
        return wide._view
    v = kernels.WideView()
    v.width = wide.width
    # The root's box: one element read back, not the node arrays (a copy of each on CUDA).
    v.root_lower = wp.vec3(*bvh.node_lowers[0:1].numpy()[0])
    v.root_upper = wp.vec3(*bvh.node_uppers[0:1].numpy()[0])
    v.slots = wide.slots
    v.wide_begin = wide.wide_begin
    v.wide_end = wide.wide_end
    v.prim_order = bvh.prim_order
    v.triangles = wide.triangles
    wide._view = v
    return v


def launch_args(wide: WideBvh, origins: wp.array, directions: wp.array, t_max, hit_t: wp.array,
                hit_prim: wp.array, counts: wp.array) -> tuple:
    """``(kernel, inputs)`` to launch the closest hits of these rays through `wide` into these
    outputs (``wp.launch(kernel, dim=len(origins), inputs=inputs)``): ``kernels.wide``'s
    ``wide_closest_hit_kernel`` for one limit, ``wide_closest_hit_limits_kernel`` for one per
    ray. ``t_max``: one number, or one per ray as `intersect` takes it (a float32 Warp array on
    the tree's device of 1 or ``len(origins)`` entries is used as it is). It takes no ``t_min``
    or ``ignore_prim``: these lean kernels are the timed path of plain rays (the bench, the camera
    example); secondary rays go through `intersect` or a user kernel's six-argument
    ``bvh_wide_closest_hit``.

    Every array is checked against what the kernel reads (type, length, device), since a launch
    past an array's end reads or writes memory it does not own."""
    n = _check_launch_arrays(wide, origins, directions, hit_t, hit_prim, counts)
    if isinstance(t_max, wp.array):
        if t_max.dtype != wp.float32 or t_max.ndim != 1 or t_max.shape[0] not in (1, n) or \
                t_max.device != wide.device:
            raise ValueError(f"t_max as a Warp array must be float32 of shape (1,) or ({n},) on {wide.device}, "
                             f"got {wp.types.type_repr(t_max.dtype)} of shape {t_max.shape} on {t_max.device}")
        return kernels.wide_closest_hit_limits_kernel, [view(wide), origins, directions, t_max, hit_t, hit_prim,
                                                        counts]
    from .query import _t_max_values

    return _launch_for(wide, origins, directions, _t_max_values(t_max, n), hit_t, hit_prim, counts)


def _check_launch_arrays(wide, origins, directions, hit_t, hit_prim, counts) -> int:
    """The ray count, once the arrays `launch_args` hands to a user's launch fit it: ``origins`` and
    ``directions`` ``vec3`` of one length N, ``hit_t`` float32 and ``hit_prim`` int32 of N entries,
    ``counts`` ``vec3i`` of 0 or N, all one-dimensional on the tree's device."""
    if not isinstance(wide, WideBvh):
        raise ValueError(f"launch_args() takes a WideBvh, got {type(wide).__name__}")
    if wide.bvh.vertices is None or wide.bvh.faces is None:
        raise ValueError("launch_args() needs a wide BVH collapsed from a mesh BVH, not from bare boxes")
    _require_current(wide, "launch_args")
    wanted = (("origins", origins, wp.vec3, None), ("directions", directions, wp.vec3, None),
              ("hit_t", hit_t, wp.float32, None), ("hit_prim", hit_prim, wp.int32, None),
              ("counts", counts, wp.vec3i, 0))
    n = None
    for name, array, dtype, or_length in wanted:
        if not isinstance(array, wp.array):
            raise ValueError(f"launch_args(): {name} must be a Warp array, got {type(array).__name__}")
        if array.dtype != dtype or array.ndim != 1 or array.device != wide.device:
            raise ValueError(f"launch_args(): {name} must be a one-dimensional {wp.types.type_repr(dtype)} array "
                             f"on {wide.device}, got {wp.types.type_repr(array.dtype)} of shape {array.shape} "
                             f"on {array.device}")
        if n is None:
            n = array.shape[0]
        elif array.shape[0] != n and array.shape[0] != or_length:
            lengths = f"{n}" if or_length is None else f"{or_length} or {n}"
            raise ValueError(f"launch_args(): {name} has {array.shape[0]} entries where the {n} rays need {lengths}")
    return n


def _launch_for(wide: WideBvh, origins, directions, limits: np.ndarray, hit_t, hit_prim, counts) -> tuple:
    """`launch_args` for limits already checked (`query._t_max_values`)."""
    if limits.shape[0] == 1:
        # One limit goes by value (`kernels.traversal.query_limit`): no array to make or pack.
        return kernels.wide_closest_hit_kernel, [view(wide), origins, directions, float(limits[0]), hit_t, hit_prim,
                                                 counts]
    limits = wp.array(limits, dtype=float, device=wide.device)
    return kernels.wide_closest_hit_limits_kernel, [view(wide), origins, directions, limits, hit_t, hit_prim, counts]


def launch_inputs(wide: WideBvh, origins: wp.array, directions: wp.array, t_max, hit_t: wp.array,
                  hit_prim: wp.array, counts: wp.array) -> list:
    """Inputs of ``kernels.wide.wide_closest_hit_kernel`` for one ``t_max`` for every ray (the
    call before `launch_args`, which also takes one per ray and names the kernel to launch)."""
    kernel, args = launch_args(wide, origins, directions, t_max, hit_t, hit_prim, counts)
    if kernel is not kernels.wide_closest_hit_kernel:
        raise ValueError("launch_inputs() takes one t_max for every ray; launch_args() takes one per ray")
    return args


@_holding_binary_tree
def intersect(wide: WideBvh, origins, directions, t_max=float("inf"), stats: bool = False, *, t_min=0.0,
              ignore_prim=None):
    """Closest hit of every ray through the wide tree: ``(t, prim)`` as `hlbvh_warp.intersect`
    returns them (a miss is ``(inf, -1)``), and a `WideTraversalStats` with `stats`. ``t_max``,
    ``t_min`` and ``ignore_prim``: one value, or one per ray, as `hlbvh_warp.intersect` takes
    them (hits count for t in (t_min, t_max), never on a ray's ``ignore_prim``), checked alike.

    Raises:
        ValueError: not a `WideBvh`, one collapsed from bare boxes or from a binary tree changed
            since, rays of a wrong shape, or a bad ``t_min`` / ``t_max`` / ``ignore_prim``.
    """
    from .query import _ray_range

    if not isinstance(wide, WideBvh):
        raise ValueError(f"intersect() takes a WideBvh, got {type(wide).__name__}")
    bvh = wide.bvh
    if bvh.vertices is None or bvh.faces is None:
        raise ValueError("intersect() needs a wide BVH collapsed from a mesh BVH, not from bare boxes")
    _require_current(wide, "intersect")
    o, d = inputs.ray_arrays(origins, directions)
    device = wide.device
    n = o.shape[0]
    lows, limits, skips, ranged = _ray_range(t_min, t_max, ignore_prim, n, bvh.num_prims)
    hit_t = wp.empty(n, dtype=float, device=device)
    hit_prim = wp.empty(n, dtype=wp.int32, device=device)
    counts = wp.empty(n if stats else 0, dtype=wp.vec3i, device=device)
    if n:
        rays = [wp.array(o, dtype=wp.vec3, device=device), wp.array(d, dtype=wp.vec3, device=device)]
        if not ranged:
            # No near end and nothing ignored: the lean kernels `launch_args` hands out, whose
            # per-thread copy of the arguments holds no range arrays.
            kernel, args = _launch_for(wide, *rays, limits, hit_t, hit_prim, counts)
        else:
            ranges = [wp.array(lows, dtype=float, device=device), wp.array(limits, dtype=float, device=device),
                      wp.array(skips, dtype=wp.int32, device=device)]
            kernel, args = kernels.wide_closest_hit_range_kernel, [view(wide), *rays, *ranges, hit_t, hit_prim, counts]
        wp.launch(kernel, dim=n, device=device, inputs=args)
    out = (hit_t.numpy(), hit_prim.numpy())
    if stats:
        c = counts.numpy().reshape(-1, 3)
        out += (WideTraversalStats(c[:, 0].copy(), c[:, 1].copy(), c[:, 2].copy()),)
    return out
