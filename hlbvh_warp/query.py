"""Ray, box and closest-point queries on a built BVH: host wrappers around
``kernels/traversal.py`` and ``kernels/proximity.py``.

Batched calls (`intersect`, `occluded`, `intersect_all`, `query_aabb`, `closest_point`) validate
their input, launch one thread per ray, box or point on the BVH's device and return NumPy arrays.
`view` hands the same data to user kernels, which call the ``@wp.func`` queries re-exported here
(`bvh_closest_hit`, `bvh_any_hit`, `bvh_occluded`, `bvh_aabb_count`, `bvh_aabb_pairs`,
`bvh_closest_point`).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import warp as wp

from . import inputs
from .host_morton import morton_order
from .bvh import Bvh, holding_tree, not_a_bvh
from .kernels import proximity, traversal
from .kernels.proximity import ClosestPoint, bvh_closest_point  # noqa: F401  (re-exported for user kernels)
from .kernels.traversal import (  # noqa: F401  (re-exported for user kernels)
    BvhView,
    RayHit,
    bvh_aabb_count,
    bvh_aabb_pairs,
    bvh_any_hit,
    bvh_closest_hit,
    bvh_occluded,
)


@dataclasses.dataclass
class TraversalStats:
    """Per-ray counts of one batched query (Wodniok & Goesele, GI 2016, Sec. 5).

    Attributes:
        nodes_visited: n_s, traversal steps (interior and leaf nodes popped) per ray.
        prims_tested: n_t, ray-triangle tests per ray.
    """

    nodes_visited: np.ndarray
    prims_tested: np.ndarray

    def measured_cost(self, c_t: float = 1.2, c_i: float = 1.0) -> float:
        """Average measured traversal cost m = n_s * c_t + n_t * c_i (the paper's eq. 10 and constants)."""
        if self.nodes_visited.size == 0:
            return 0.0
        return float(self.nodes_visited.mean() * c_t + self.prims_tested.mean() * c_i)

    def summary(self, c_t: float = 1.2, c_i: float = 1.0) -> dict:
        return {
            "mean_nodes_visited": float(self.nodes_visited.mean()) if self.nodes_visited.size else 0.0,
            "mean_prims_tested": float(self.prims_tested.mean()) if self.prims_tested.size else 0.0,
            "measured_cost": self.measured_cost(c_t, c_i),
        }


class TraversalLayout:
    """The packed ray traversal layout of one mesh BVH (see ``kernels/traversal.py``).

    Derived from the node boxes, the topology and the vertices, so it is refreshed, in place, by
    every `Bvh.invalidate` (which refits and rebuilds call): views handed out earlier keep working.
    Costs 64 bytes per interior node and 36 per triangle, plus 4 per node of scratch.
    """

    def __init__(self, bvh: Bvh):
        device = bvh.device
        # Positions of prim_order: more than the triangles where spatial splits duplicated some.
        num_prims = bvh.num_refs
        self.first_steps = wp.zeros(bvh.node_left.shape[0], dtype=wp.int32, device=device)
        # Positions of interior nodes lie below N - 1; keep one record for a single-leaf tree.
        self.nodes = wp.zeros(max(num_prims - 1, 1), dtype=traversal.PackedNode, device=device)
        self.triangles = wp.zeros(num_prims, dtype=traversal.PackedTriangle, device=device)
        self.refresh(bvh)

    def refresh(self, bvh: Bvh, per_node: bool | None = None):
        """Rewrite the layout from the BVH's current arrays: launches only, no host reads.
        ``per_node``: a thread per node (CUDA's way), or one sequential sweep (the CPU's);
        ``None`` picks by device. Both write the same layout (tested on the CPU)."""
        device = bvh.device
        nodes = [bvh.node_count, bvh.node_lowers, bvh.node_uppers, bvh.node_left, bvh.node_right, bvh.node_begin,
                 bvh.node_end, self.first_steps, self.nodes]
        if per_node is None:
            per_node = not device.is_cpu
        if not per_node:
            # One sequential pass: on the CPU a thread per node costs more than the work it does.
            wp.launch(traversal.pack_nodes_sweep_kernel, dim=1, inputs=nodes, device=device)
        else:
            capacity = bvh.node_left.shape[0]
            wp.launch(traversal.first_steps_climb_kernel, dim=capacity, device=device,
                      inputs=[bvh.node_count, bvh.node_parent, bvh.node_begin, self.first_steps])
            wp.launch(traversal.pack_nodes_kernel, dim=capacity, inputs=nodes, device=device)
        wp.launch(traversal.pack_triangles_kernel, dim=bvh.num_refs, device=device,
                  inputs=[bvh.prim_order, bvh.vertices, bvh.faces, self.triangles])


@holding_tree
def view(bvh: Bvh) -> BvhView:
    """The `BvhView` struct of ``bvh`` for user kernels (``wp.launch(k, inputs=[view(bvh), ...])``).

    The view refers to the BVH's arrays and to its `TraversalLayout` (made on the first call for a
    mesh BVH), which refits and rebuilds refresh in place: it stays valid after a refit of the
    same BVH.
    """
    if not isinstance(bvh, Bvh):
        raise ValueError(not_a_bvh("view", bvh))
    cached = bvh._cache.get("view")
    if cached is not None:
        return cached
    v = BvhView()
    v.node_lowers = bvh.node_lowers
    v.node_uppers = bvh.node_uppers
    v.node_left = bvh.node_left
    v.node_right = bvh.node_right
    v.node_begin = bvh.node_begin
    v.node_end = bvh.node_end
    v.prim_order = bvh.prim_order
    v.prim_lowers = bvh.prim_lowers
    v.prim_uppers = bvh.prim_uppers
    # A BVH over bare boxes has no triangles: empty arrays, which only box queries accept.
    device = bvh.device
    v.vertices = bvh.vertices if bvh.vertices is not None else wp.zeros(0, dtype=wp.vec3, device=device)
    v.faces = bvh.faces if bvh.faces is not None else wp.zeros((0, 3), dtype=wp.int32, device=device)
    if bvh.vertices is not None and bvh.faces is not None:
        layout = bvh._cache.get("traversal_layout")
        if layout is None:
            layout = bvh._cache["traversal_layout"] = TraversalLayout(bvh)
        v.packed_nodes = layout.nodes
        v.packed_triangles = layout.triangles
    else:
        v.packed_nodes = wp.zeros(0, dtype=traversal.PackedNode, device=device)
        v.packed_triangles = wp.zeros(0, dtype=traversal.PackedTriangle, device=device)
    bvh._cache["view"] = v
    return v


def _require_mesh(bvh: Bvh, name: str):
    if not isinstance(bvh, Bvh):
        raise ValueError(not_a_bvh(name, bvh))
    if bvh.vertices is None or bvh.faces is None:
        raise ValueError(f"{name}() needs a BVH built over a mesh (build()), not over bare boxes")


def _require_whole_boxes(bvh: Bvh, name: str):
    # Box queries test a primitive's whole box at a leaf; a spatial-split leaf's box bounds only its
    # part of a triangle, so the walk could miss a triangle whose box meets the query elsewhere.
    if bvh.has_duplicates:
        raise ValueError(f"{name}() needs a tree whose leaves bound whole primitives; this {bvh.method!r} tree "
                         "lists a primitive in more than one leaf (as spatial splits do): build one with an "
                         "object-split method")


def _per_query_values(value, count: int, name: str) -> np.ndarray:
    """A limit given as one number (or a one-element array) or one per query, checked: a float64
    array of shape ``(1,)`` or ``(count,)``. Shapes and dtypes are errors that name the shape,
    never the values."""
    # Any Warp array, a wp.indexedarray too (no wp.array subclass), as `inputs.query_array` reads
    # the rays: taken by np.asarray as one object, it was refused as "must be a number".
    values = np.asarray(value.numpy() if wp.types.is_array(value) else value)
    if values.ndim == 0 and values.dtype.kind == "b":
        # Booleans are no distances, one or one per query: True read as 1 silently dropped every
        # hit past it, where a flag was passed by position (``intersect(bvh, o, d, True)``).
        raise ValueError(f"{name} must be a number, got bool {value!r}")
    if values.ndim == 0 and values.dtype.kind not in "fiu":
        # What float() takes: a Python int past int64 (an object array), "inf", a Fraction.
        try:
            values = np.asarray(float(value))
        except OverflowError:
            # An integer or fraction past float64's range: as far as any float is, an infinity.
            values = np.asarray(np.inf if value > 0 else -np.inf)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{name} must be a number, got {type(value).__name__} {value!r}") from exc
    if values.dtype.kind not in "fiu":
        raise ValueError(f"{name} must hold real numbers, got dtype {values.dtype}")
    if values.size == 1 and values.ndim <= 1:
        values = values.reshape(1)
    elif values.shape != (count,):
        raise ValueError(f"{name} must be a number or have shape ({count},), got {values.shape}")
    return values.astype(np.float64)


def _refuse_first(values: np.ndarray, bad: np.ndarray, rule: str, query: str):
    """Raise a ValueError stating ``rule`` and the first value where ``bad`` holds, naming its
    query (``ray`` or ``point``) when there is one value per query."""
    first = np.flatnonzero(bad)
    if first.size:
        where = "" if values.shape[0] == 1 else f" ({query} {first[0]})"
        raise ValueError(f"{rule}, got {values[first[0]]}{where}")


def _t_max_values(t_max, num_rays: int) -> np.ndarray:
    """``t_max`` as float32: ``(1,)`` for one number (or a one-element array), ``(num_rays,)`` for
    one per ray. Each is rounded up: a float32 t is below t_max exactly when it is below the
    float32 at or above it, where rounding to nearest dropped a hit at t = 1 under t_max = 1 + 1e-12."""
    return _round_up_to_float32_array(_per_query_values(t_max, num_rays, "t_max"))


def _t_min_values(t_min, num_rays: int) -> np.ndarray:
    """``t_min`` as float32, ``(1,)`` or ``(num_rays,)``: each at least 0 (NaN is an error), and
    rounded down, as ``t_max`` is rounded up: a float32 t lies above t_min exactly when it lies
    above the float32 at or below it. An infinite ``t_min`` leaves its ray nothing to hit."""
    values = _per_query_values(t_min, num_rays, "t_min")
    _refuse_first(values, ~(values >= 0.0), "t_min must be >= 0", "ray")
    return _round_down_to_float32_array(values)


def _ignore_prim_values(ignore_prim, num_rays: int, num_prims: int) -> np.ndarray:
    """``ignore_prim`` as int32: empty for None (no ray ignores anything), else ``(1,)`` for one
    triangle every ray ignores or ``(num_rays,)``, each -1 (none) or a triangle index."""
    if ignore_prim is None:
        return np.zeros(0, np.int32)
    values = np.asarray(ignore_prim.numpy() if wp.types.is_array(ignore_prim) else ignore_prim)
    # An empty list is an empty batch's ignore_prim (NumPy reads it as float64), as it is its t_max.
    if values.dtype.kind not in "iu" and values.size > 0:
        raise ValueError(f"ignore_prim must hold integer triangle indices (-1 for none), got dtype {values.dtype}")
    if values.size == 1 and values.ndim <= 1:
        values = values.reshape(1)
    elif values.shape != (num_rays,):
        raise ValueError(f"ignore_prim must be one index or have shape ({num_rays},), got {values.shape}")
    _refuse_first(values, (values < -1) | (values >= num_prims),
                  f"ignore_prim must be -1 (none) or a triangle index in [0, {num_prims})", "ray")
    return values.astype(np.int32)


def _ray_range(t_min, t_max, ignore_prim, num_rays: int, num_prims: int):
    """The checked ``t_min``, ``t_max`` and ``ignore_prim`` of a ray call, and whether a ray has a
    near end or ignores a triangle (``ranged``): the calls keep their lean kernels when none does."""
    limits = _t_max_values(t_max, num_rays)
    lows = _t_min_values(t_min, num_rays)
    skips = _ignore_prim_values(ignore_prim, num_rays, num_prims)
    ranged = bool(lows.any()) or len(skips) > 0
    return lows, limits, skips, ranged


def _max_dist_values(max_dist, num_points: int):
    """``max_dist`` as float32 bounds: a float for one number (or a one-element array), a
    ``(num_points,)`` float32 array for one per point. The kernel takes float32: each bound is
    rounded up, never to nearest, so that a triangle at exactly the float64 bound still counts
    (inclusive); past float32's range a bound is unbounded."""
    if isinstance(max_dist, float):
        # The common call, in scalar arithmetic: a small query must not pay for array checks.
        if not max_dist >= 0.0:
            raise ValueError(f"max_dist must be >= 0, got {max_dist}")
        return _round_up_to_float32(max_dist)
    values = _per_query_values(max_dist, num_points, "max_dist")
    _refuse_first(values, ~(values >= 0.0), "max_dist must be >= 0", "point")
    if values.shape[0] == 1:
        return _round_up_to_float32(float(values[0]))
    return _round_up_to_float32_array(values)


def _round_up_to_float32_array(values: np.ndarray) -> np.ndarray:
    """Each float64 value as the float32 at or above it (inf past float32's range; NaN stays)."""
    with np.errstate(over="ignore"):
        bounds = values.astype(np.float32)
    low = bounds.astype(np.float64) < values
    bounds[low] = np.nextafter(bounds[low], np.float32(np.inf))
    return bounds


def _round_down_to_float32_array(values: np.ndarray) -> np.ndarray:
    """Each float64 value as the float32 at or below it (the largest finite float32 past its range;
    inf and NaN stay)."""
    with np.errstate(over="ignore"):
        bounds = values.astype(np.float32)
    high = bounds.astype(np.float64) > values
    bounds[high] = np.nextafter(bounds[high], np.float32(-np.inf))
    return bounds


def _round_up_to_float32(value: float) -> float:
    """The float32 at or above ``value`` (inf past float32's range), as a Python float."""
    with np.errstate(over="ignore"):
        bound = np.float32(value)
    if float(bound) < value:
        bound = np.nextafter(bound, np.float32(np.inf))
    return float(bound)


def _empty(dtype, device, shape=0):
    return wp.empty(shape, dtype=dtype, device=device)


def _optional_outputs(dtype, count: int, wanted: bool, device):
    """Two per-query output arrays the kernels fill only when asked (barycentrics, statistics);
    empty ones tell a kernel to skip them."""
    size = count if wanted else 0
    return _empty(dtype, device, size), _empty(dtype, device, size)


@holding_tree
def intersect(bvh: Bvh, origins, directions, t_max: float = float("inf"), return_barycentrics: bool = False,
              stats: bool = False, *, t_min: float = 0.0, ignore_prim=None):
    """Closest hit of every ray, watertight (Woop et al. 2013) over a padded traversal (Ize 2013).

    Args:
        bvh: a BVH built over a mesh with `hlbvh_warp.build`.
        origins, directions: ``(R, 3)`` rays (NumPy or Warp, any real dtype; a single ``(3,)`` ray
            is accepted, and one origin or one direction serves every ray). Directions need not be
            normalized: t is in units of the direction.
        t_max: only hits with t in (t_min, t_max) count: one number, or one per ray (``(R,)``).
        return_barycentrics: also return ``u, v``, the weights of each hit triangle's second and
            third vertex (0 on a miss).
        stats: also return a `TraversalStats` (nodes visited, triangles tested per ray).
        t_min: the near end of the range, at least 0: one number, or one per ray. A ray whose
            range is empty (``t_min >= t_max``) misses.
        ignore_prim: a triangle index each ray does not hit, -1 for none: one for every ray, or
            one per ray (``(R,)``). A secondary ray leaving a surface ignores the triangle it
            starts on, which rounding would otherwise let it hit at t near 0.

    Returns:
        ``(t, prim_id)`` NumPy arrays (float32, int32), a miss being ``(inf, -1)``; then ``u, v``
        when asked, then the stats when asked. Rays with NaN or Inf components, or a zero
        direction, miss.

    Raises:
        ValueError: a BVH over bare boxes, origins/directions of a wrong shape or dtype, a negative
            or NaN ``t_min``, a boolean ``t_min`` or ``t_max`` (a flag passed by position), or an
            ``ignore_prim`` that is no triangle of the mesh.
    """
    _require_mesh(bvh, "intersect")
    o, d = inputs.ray_arrays(origins, directions)
    num_rays = o.shape[0]
    lows, limits, skips, ranged = _ray_range(t_min, t_max, ignore_prim, num_rays, bvh.num_prims)
    device = bvh.device
    hit_t = wp.empty(num_rays, dtype=float, device=device)
    hit_prim = wp.empty(num_rays, dtype=wp.int32, device=device)
    hit_u, hit_v = _optional_outputs(float, num_rays, return_barycentrics, device)
    visits, tests = _optional_outputs(wp.int32, num_rays, stats, device)
    if num_rays:
        rays = [view(bvh), wp.array(o, dtype=wp.vec3, device=device), wp.array(d, dtype=wp.vec3, device=device)]
        if return_barycentrics or stats or ranged or len(limits) > 1:
            ranges = [wp.array(lows, dtype=float, device=device), wp.array(limits, dtype=float, device=device),
                      wp.array(skips, dtype=wp.int32, device=device)]
            wp.launch(traversal.closest_hit_details_kernel, dim=num_rays, device=device,
                      inputs=rays + ranges + [hit_t, hit_prim, hit_u, hit_v, visits, tests])
        else:
            # The lean kernel (one limit, no optional outputs): the common camera-ray call.
            wp.launch(traversal.closest_hit_kernel, dim=num_rays, inputs=rays + [float(limits[0]), hit_t, hit_prim],
                      device=device)
    out = (hit_t.numpy(), hit_prim.numpy())
    if return_barycentrics:
        out += (hit_u.numpy(), hit_v.numpy())
    if stats:
        out += (TraversalStats(visits.numpy(), tests.numpy()),)
    return out


@holding_tree
def occluded(bvh: Bvh, origins, directions, t_max=float("inf"), stats: bool = False, *, t_min=0.0,
             ignore_prim=None):
    """Whether each ray hits any triangle with t in (t_min, t_max) (shadow rays; stops at the
    first hit).

    Args:
        t_max: one number, or one per ray (``(R,)``), e.g. the distance to a light.
        t_min, ignore_prim: as for `intersect`: a shadow ray from a surface point ignores the
            triangle the point lies on.

    Returns:
        ``(R,)`` bool NumPy array, and a `TraversalStats` when ``stats``.
    """
    _require_mesh(bvh, "occluded")
    o, d = inputs.ray_arrays(origins, directions)
    num_rays = o.shape[0]
    # Each: one value, or one per ray (`traversal.query_limit`, `traversal.query_prim`).
    lows, limits, skips, ranged = _ray_range(t_min, t_max, ignore_prim, num_rays, bvh.num_prims)
    device = bvh.device
    result = wp.empty(num_rays, dtype=wp.int32, device=device)
    visits, tests = _optional_outputs(wp.int32, num_rays, stats, device)
    if num_rays:
        rays = [view(bvh), wp.array(o, dtype=wp.vec3, device=device), wp.array(d, dtype=wp.vec3, device=device)]
        outputs = [result, visits, tests]
        limit_array = wp.array(limits, dtype=float, device=device)
        if not ranged:
            wp.launch(traversal.occluded_kernel, dim=num_rays, inputs=rays + [limit_array] + outputs, device=device)
        else:
            ranges = [wp.array(lows, dtype=float, device=device), limit_array, wp.array(skips, dtype=wp.int32,
                                                                                          device=device)]
            wp.launch(traversal.occluded_range_kernel, dim=num_rays, inputs=rays + ranges + outputs, device=device)
    hit = result.numpy().astype(bool)
    if stats:
        return hit, TraversalStats(visits.numpy(), tests.numpy())
    return hit


#: The most results one query call returns: offsets into its output are int32.
MAX_RESULTS = 2**31 - 1


def _offsets(counts: wp.array, what: str) -> tuple[wp.array, int]:
    """Exclusive prefix sum of the per-query counts, and the total (read to the host).

    The total is summed on the host in int64 first: the device's int32 scan of counts past
    2^31 would wrap, and the write pass would then write outside the output it sized.
    """
    total = int(counts.numpy().sum(dtype=np.int64))
    if total > MAX_RESULTS:
        raise ValueError(f"{total} {what}: more than the {MAX_RESULTS} one query call can return")
    offsets = wp.empty_like(counts)
    if total:
        wp.utils.array_scan(counts, offsets, inclusive=False)
    return offsets, total


@holding_tree
def intersect_all(bvh: Bvh, origins, directions, t_max: float = float("inf"), *, t_min=0.0, ignore_prim=None):
    """Every triangle each ray hits with t in (t_min, t_max) (trimesh's ``multiple_hits``) but its
    ``ignore_prim``; ``t_min``, ``t_max`` and ``ignore_prim`` are one value or one per ray, as for
    `intersect`.

    Returns:
        ``(ray_id, prim_id, t)`` NumPy arrays, sorted by ray, then t, then primitive. A ray
        through a shared edge or vertex lists every triangle the watertight test accepts there.
    """
    _require_mesh(bvh, "intersect_all")
    o, d = inputs.ray_arrays(origins, directions)
    num_rays = o.shape[0]
    lows, limits, skips, _ = _ray_range(t_min, t_max, ignore_prim, num_rays, bvh.num_prims)
    if num_rays == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32)
    device = bvh.device
    ow = wp.array(o, dtype=wp.vec3, device=device)
    dw = wp.array(d, dtype=wp.vec3, device=device)
    ranges = [wp.array(lows, dtype=float, device=device), wp.array(limits, dtype=float, device=device),
              wp.array(skips, dtype=wp.int32, device=device)]
    counts = wp.zeros(num_rays, dtype=wp.int32, device=device)
    none_i, none_f = _empty(wp.int32, device), _empty(float, device)
    # Count pass, prefix sum, write pass: each ray owns a slice, no atomics, deterministic.
    wp.launch(traversal.all_hits_kernel, dim=num_rays,
              inputs=[view(bvh), ow, dw] + ranges + [counts, counts, none_i, none_f], device=device)
    offsets, total = _offsets(counts, "ray hits")
    if total == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32)
    out_prim = wp.empty(total, dtype=wp.int32, device=device)
    out_t = wp.empty(total, dtype=float, device=device)
    wp.launch(traversal.all_hits_kernel, dim=num_rays,
              inputs=[view(bvh), ow, dw] + ranges + [offsets, counts, out_prim, out_t], device=device)
    ray_id = np.repeat(np.arange(num_rays, dtype=np.int64), counts.numpy())
    prim = out_prim.numpy().astype(np.int64)
    t = out_t.numpy()
    order = np.lexsort((prim, t, ray_id))
    ray_id, prim, t = ray_id[order], prim[order], t[order]
    if bvh.has_duplicates:
        # A triangle split across leaves is met once per leaf the ray enters, with the same t
        # (the same test on the same triangle): equal neighbours after the sort.
        keep = np.ones(len(prim), bool)
        keep[1:] = (ray_id[1:] != ray_id[:-1]) | (prim[1:] != prim[:-1]) | (t[1:] != t[:-1])
        ray_id, prim, t = ray_id[keep], prim[keep], t[keep]
    return ray_id, prim, t


def _box_arrays(lowers, uppers):
    """Query boxes: shapes and dtypes are errors; NaN bounds overlap nothing, infinite ones are fine."""
    lo, hi = inputs.query_array(lowers, "lowers"), inputs.query_array(uppers, "uppers")
    if lo.shape != hi.shape:
        raise ValueError(f"lowers and uppers differ in shape: {lo.shape} vs {hi.shape}")
    return lo, hi


@holding_tree
def query_aabb(bvh: Bvh, lowers, uppers, return_pairs: bool = False):
    """How many primitives' boxes overlap each query box (closed boxes: touching counts), and
    with ``return_pairs`` which ones.

    Works on every object-split BVH, built from a mesh (triangle boxes) or from bare boxes; a
    spatial-split (``sbvh``) tree is refused with a ``ValueError``, since its leaves bound parts
    of triangles, not whole boxes.

    Args:
        lowers, uppers: ``(Q, 3)`` query boxes. A box with lowers > uppers on an axis is empty
            and overlaps nothing, as does one with a NaN bound; infinite bounds are fine.
        return_pairs: also return the ``(P, 2)`` int64 ``(query, prim)`` pairs, sorted.

    Returns:
        ``(Q,)`` int32 counts, then the pairs when asked.
    """
    if not isinstance(bvh, Bvh):
        raise ValueError(not_a_bvh("query_aabb", bvh))
    _require_whole_boxes(bvh, "query_aabb")
    lo, hi = _box_arrays(lowers, uppers)
    num_queries = lo.shape[0]
    if num_queries == 0:
        counts = np.zeros(0, np.int32)
        return (counts, np.zeros((0, 2), np.int64)) if return_pairs else counts
    device = bvh.device
    lw = wp.array(lo, dtype=wp.vec3, device=device)
    hw = wp.array(hi, dtype=wp.vec3, device=device)
    counts = wp.zeros(num_queries, dtype=wp.int32, device=device)
    none, no_order = _empty(wp.vec2i, device), _empty(wp.int32, device)
    wp.launch(traversal.aabb_query_kernel, dim=num_queries, device=device,
              inputs=[view(bvh), lw, hw, no_order, 0, counts, counts, none])
    if not return_pairs:
        return counts.numpy()
    offsets, total = _offsets(counts, "overlapping pairs")
    pairs = np.zeros((0, 2), np.int64)
    if total:
        out = wp.empty(total, dtype=wp.vec2i, device=device)
        wp.launch(traversal.aabb_query_kernel, dim=num_queries, device=device,
                  inputs=[view(bvh), lw, hw, no_order, 0, offsets, counts, out])
        pairs = out.numpy().astype(np.int64).reshape(-1, 2)
        pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
    return counts.numpy(), pairs


@holding_tree
def closest_point(bvh: Bvh, points, max_dist: float = float("inf"), return_barycentrics: bool = False,
                  stats: bool = False):
    """The closest point on the mesh to every query point (``kernels/proximity.py``).

    Args:
        bvh: a BVH built over a mesh with `hlbvh_warp.build`; any builder, spatial splits included.
        points: ``(P, 3)`` query points (NumPy or Warp, any real dtype; a single ``(3,)`` point is
            accepted). A point with a NaN or Inf coordinate finds nothing.
        max_dist: only triangles within this distance (inclusive) count; a point with none finds
            nothing. One number, or one per point (``(P,)``, NumPy or Warp). A smaller bound is
            faster: boxes beyond it are never opened. Taken as the float32 at or above it.
        return_barycentrics: also return ``u, v``, the weights of the triangle's second and third
            vertex at the closest point (0 where nothing was found).
        stats: also return a `TraversalStats` (nodes visited, triangles tested per point).

    Returns:
        ``(closest, distance, prim_id)`` NumPy arrays: ``(P, 3)`` float32 points on the surface,
        ``(P,)`` float32 distances and ``(P,)`` int32 triangles (trimesh's ``closest_point``
        order); where nothing is found, NaN, inf and -1. Then ``u, v`` when asked, then the
        stats. Equal distances go to the lowest triangle id. ``prim_id >= 0`` is the test for
        found: a distance past float32's range (two points near +-3e38) reads inf as well.

    Raises:
        ValueError: a BVH over bare boxes, points of a wrong shape or dtype, or a ``max_dist`` of
            a wrong shape, negative, NaN (the first such point named) or boolean.
    """
    _require_mesh(bvh, "closest_point")
    p = inputs.query_array(points, "points")
    num_points = p.shape[0]
    bounds = _max_dist_values(max_dist, num_points)
    device = bvh.device
    order = _point_order(p, device)
    if order is not None:
        p = p[order]
        if isinstance(bounds, np.ndarray):
            bounds = bounds[order]
    out_point = wp.empty(num_points, dtype=wp.vec3, device=device)
    out_distance = wp.empty(num_points, dtype=float, device=device)
    out_prim = wp.empty(num_points, dtype=wp.int32, device=device)
    out_u, out_v = _optional_outputs(float, num_points, return_barycentrics, device)
    visits, tests = _optional_outputs(wp.int32, num_points, stats, device)
    if num_points:
        # One bound goes by value (see `traversal.query_limit`): no array to make or pack.
        if isinstance(bounds, float):
            kernel, limit = proximity.closest_point_kernel, bounds
        else:
            kernel, limit = proximity.closest_point_bounds_kernel, wp.array(bounds, dtype=float, device=device)
        wp.launch(kernel, dim=num_points, device=device,
                  inputs=[view(bvh), wp.array(p, dtype=wp.vec3, device=device), limit, out_point, out_distance,
                          out_prim, out_u, out_v, visits, tests])
    out = [out_point.numpy().reshape(num_points, 3), out_distance.numpy(), out_prim.numpy()]
    if return_barycentrics:
        out += [out_u.numpy(), out_v.numpy()]
    if stats:
        out += [visits.numpy(), tests.numpy()]
    out = _in_caller_order(order, out)
    if stats:
        out = out[:-2] + [TraversalStats(out[-2], out[-1])]
    return tuple(out)


#: Batches of points at least this large are queried in Morton order on the CPU: sorting costs
#: about 0.2 us a point, a query one to several us. (Rays were tried and left in the caller's
#: order: a camera ray costs less than its share of the sort.)
SORT_QUERIES_FROM = 4096


def _point_order(points: np.ndarray, device):
    """The order to query points in (None: as given). Nearby points walk the same nodes: in
    Morton order each query finds most of its nodes and triangles in the cache the previous one
    warmed. A CPU launch runs its threads in order, so the order is the whole effect there; on
    CUDA this host-side sort would cost more than the queries. Points already coherent (a mesh's
    vertices in file order, a simulation's particles kept sorted) are left as they are: there the
    sort only costs. A sample of consecutive steps decides: a median step above 5% of the points'
    extent is an order worth sorting."""
    n = points.shape[0]
    if not device.is_cpu or n < SORT_QUERIES_FROM:
        return None
    finite = points[np.isfinite(points).all(axis=1)]
    if finite.shape[0] < 2:
        return None
    extent = float(np.linalg.norm(finite.max(axis=0).astype(np.float64) - finite.min(axis=0)))
    starts = np.linspace(0, n - 2, num=min(n - 1, 1024)).astype(np.int64)
    with np.errstate(invalid="ignore", over="ignore"):
        steps = np.linalg.norm(points[starts + 1].astype(np.float64) - points[starts], axis=1)
    # Every sampled step may meet a NaN point (every other point NaN): no step to judge by, and
    # np.nanmedian of them all would warn of an all-NaN slice.
    if np.isnan(steps).all() or not np.nanmedian(steps) > 0.05 * extent:
        return None
    return morton_order(points)


def _in_caller_order(order, arrays):
    """Results computed in ``order`` back in the caller's order."""
    if order is None:
        return arrays
    out = []
    for values in arrays:
        back = np.empty_like(values)
        back[order] = values
        out.append(back)
    return out
