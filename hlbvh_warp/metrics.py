"""Tree quality: the SAH cost of Pantaleoni & Luebke 2010 (eq. 1), the end-point overlap of
Aila, Karras & Laine 2013 (`end_point_overlap`) and shape statistics.

The cost is computed on the build device, bottom-up (kernels/metrics.py):

    C(leaf) = T2 * N_prims
    C(node) = T1 * N_children + sum_i C(child_i) * area(child_i) / area(node)

with T1 = T2 = 1 as in the paper. T1 is the cost of one child box, so an interior node costs 2 T1;
Wodniok & Goesele 2016 (their eq. 1, with c_t = 1.2, c_i = 1.0) and Aila et al. 2013 charge c_t
once per interior node, so their SAH at (c_t, c_i) is this one at T1 = c_t / 2, T2 = c_i. Areas
are float64. A node whose box has zero area (a point or a segment)
passes its children's costs through unscaled: P_hit = 1 when area(parent) = 0.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .bvh import Bvh, holding_tree, not_a_bvh
from .kernels import metrics as kernels


def check_costs(t_traversal, t_intersect) -> tuple[float, float]:
    """The SAH constants as floats: real and finite, T1 >= 0 and T2 > 0 (a NaN would make every
    cost NaN, not an error)."""
    values = []
    for name, value in (("t_traversal", t_traversal), ("t_intersect", t_intersect)):
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
            raise ValueError(f"{name} must be a number, got {value!r}")
        try:
            values.append(float(value))
        except OverflowError:
            # A Python int past float's range (10**400): not finite either.
            values.append(float("inf") if value > 0 else float("-inf"))
    t1, t2 = values
    if not (np.isfinite(t1) and np.isfinite(t2) and t1 >= 0 and t2 > 0):
        # The floats, not the values given: an integer of 5000 digits cannot even be printed.
        raise ValueError(f"need finite t_traversal >= 0 and t_intersect > 0, got {t1}, {t2}")
    return t1, t2


def require_bvh(bvh, name: str):
    """Raise a ValueError naming the function `name` unless `bvh` is a `Bvh`."""
    if not isinstance(bvh, Bvh):
        raise ValueError(not_a_bvh(name, bvh))


@holding_tree
def node_costs(bvh: Bvh, t_traversal: float = 1.0, t_intersect: float = 1.0, scratch=None) -> wp.array:
    """SAH cost of every node's subtree (float64, arena-sized; the used part is ``num_nodes``):
    eq. (1) of Pantaleoni & Luebke 2010, the SAH of Goldsmith & Salmon 1987 and MacDonald & Booth
    1990, bottom-up with the atomic visit counters of Karras 2012.

    ``scratch``: an optional ``(visits int32, costs float64)`` pair of arena-sized arrays, so that a
    caller pricing every frame allocates nothing; the returned array is then ``costs``.
    """
    require_bvh(bvh, "node_costs")
    t_traversal, t_intersect = check_costs(t_traversal, t_intersect)
    device = bvh.device
    capacity = bvh.node_left.shape[0]
    if scratch is None:
        visits = wp.empty(capacity, dtype=wp.int32, device=device)
        costs = wp.zeros(capacity, dtype=wp.float64, device=device)
    else:
        if not isinstance(scratch, (tuple, list)) or len(scratch) != 2:
            raise ValueError("node_costs scratch must be a (visits, costs) pair of arrays")
        visits, costs = scratch
        # The kernels write every node's entry: a shorter array is written past its end.
        _check_scratch("node_costs scratch visits", visits, wp.int32, capacity, device)
        _check_scratch("node_costs scratch costs", costs, wp.float64, capacity, device)
    wp.launch(kernels.reset_visits_kernel, dim=capacity, inputs=[visits], device=device)
    wp.launch(
        kernels.sah_cost_kernel,
        dim=capacity,
        inputs=[0, bvh.node_count, bvh.node_left, bvh.node_right, bvh.node_parent, bvh.node_begin, bvh.node_end,
                bvh.node_lowers, bvh.node_uppers, wp.float64(t_traversal), wp.float64(t_intersect), visits, costs],
        device=device,
    )
    return costs


#: Nodes summed by one thread of `sah_cost` on the CPU (launches run their threads in sequence).
CPU_SAH_CHUNK = 4096
#: Nodes summed by one thread of `sah_cost` on CUDA.
CUDA_SAH_CHUNK = 64


@holding_tree
def sah_cost(bvh: Bvh, t_traversal: float = 1.0, t_intersect: float = 1.0, scratch=None) -> float:
    """The tree's SAH cost: the root's C(node) (Pantaleoni & Luebke 2010, section 4.2).

    Eq. (1) unrolled: C(root) = sum over nodes of term(n) area(n) / area(root), with term = 2 T1 for
    an interior node and T2 N for a leaf, summed in one pass over the nodes instead of the
    bottom-up climb of `node_costs` (about 8x less time on the CPU: no atomic visit counters, no
    dependent reads up the tree), which matters to `Builder(policy="auto")`, which costs a tree
    every frame. A root of zero area (every primitive at one point or on one segment) passes every
    cost through unscaled, as `node_costs` does: the sum of the terms.

    ``scratch``: an optional float64 array of at least ``ceil(capacity / chunk)`` entries, so
    that a per-frame caller allocates nothing (`sah_scratch_size`).
    """
    require_bvh(bvh, "sah_cost")
    t_traversal, t_intersect = check_costs(t_traversal, t_intersect)
    device = bvh.device
    chunk = CPU_SAH_CHUNK if device.is_cpu else CUDA_SAH_CHUNK
    size = sah_scratch_size(bvh.node_left.shape[0], device)
    if scratch is None:
        partial = wp.empty(size, dtype=wp.float64, device=device)
    else:
        partial = _check_scratch("sah_cost scratch", scratch, wp.float64, size, device)
    count = bvh.num_nodes
    if count == 0:
        return 0.0
    threads = (count + chunk - 1) // chunk
    wp.launch(kernels.sah_terms_kernel, dim=threads,
              inputs=[bvh.node_count, bvh.node_left, bvh.node_begin, bvh.node_end, bvh.node_lowers, bvh.node_uppers,
                      wp.float64(t_traversal), wp.float64(t_intersect), chunk, partial], device=device)
    return cost_from_sum(bvh, float(partial[:threads].numpy().sum()), count, t_traversal, t_intersect)


def _check_scratch(name: str, array, dtype, size: int, device) -> wp.array:
    """``array`` when it is a one-dimensional Warp array of ``dtype`` on ``device`` with at least
    ``size`` entries, else a ValueError naming it."""
    if not (isinstance(array, wp.array) and array.dtype == dtype and array.ndim == 1 and array.device == device
            and array.shape[0] >= size):
        got = (f"{wp.types.type_repr(array.dtype)} of shape {array.shape} on {array.device}"
               if isinstance(array, wp.array) else type(array).__name__)
        raise ValueError(f"{name} must be a one-dimensional Warp array of {wp.types.type_repr(dtype)} on {device} "
                         f"with at least {size} entries, got {got}")
    return array


def cost_from_sum(bvh: Bvh, total: float, count: int, t_traversal: float, t_intersect: float) -> float:
    """C(root) from the sum over the nodes of term x area (`sah_cost`), for a tree of `count` nodes."""
    lower = bvh.node_lowers[0:1].numpy()[0].astype(np.float64)
    upper = bvh.node_uppers[0:1].numpy()[0].astype(np.float64)
    extent = upper - lower
    if not np.isfinite(extent).all():
        # A root reaching infinity (a frame that blew up) prices as NaN, quietly: the caller
        # decides. Its area is no guide: a flat one's, inf x 0, would read as zero below.
        return float("nan")
    root_area = 2.0 * (extent[0] * extent[1] + extent[1] * extent[2] + extent[2] * extent[0])
    if root_area > 0.0:
        return float(total / root_area)
    # Zero-area root: every ratio is taken as 1, so the cost is the sum of the terms of a binary
    # tree with N references in (count + 1) / 2 leaves.
    return float(2.0 * t_traversal * ((count + 1) // 2 - 1) + t_intersect * bvh.num_refs)


def sah_scratch_size(capacity: int, device) -> int:
    """Entries of the float64 scratch `sah_cost` needs for a node arena of `capacity` nodes."""
    chunk = CPU_SAH_CHUNK if wp.get_device(device).is_cpu else CUDA_SAH_CHUNK
    return max((capacity + chunk - 1) // chunk, 1)


@holding_tree
def tree_stats(bvh: Bvh, t_traversal: float = 1.0, t_intersect: float = 1.0) -> dict:
    """Node and leaf counts, depth, leaf-size histogram and SAH cost, computed on the device.

    ``leaf_size_histogram[k]`` is the number of leaves holding k primitives (references, in a
    spatial-split tree: ``num_refs`` counts them).
    """
    require_bvh(bvh, "tree_stats")
    t_traversal, t_intersect = check_costs(t_traversal, t_intersect)
    device = bvh.device
    num_nodes = bvh.num_nodes
    depths = wp.empty(num_nodes, dtype=wp.int32, device=device)
    max_depth = wp.zeros(1, dtype=wp.int32, device=device)
    wp.launch(kernels.node_depth_kernel, dim=num_nodes, inputs=[bvh.node_parent, depths, max_depth], device=device)
    counts = wp.zeros(2, dtype=wp.int32, device=device)
    wp.launch(kernels.leaf_sizes_kernel, dim=num_nodes, inputs=[bvh.node_left, bvh.node_begin, bvh.node_end, counts],
              device=device)
    num_leaves, largest = (int(x) for x in counts.numpy())
    histogram = wp.zeros(largest + 1, dtype=wp.int32, device=device)
    wp.launch(kernels.leaf_histogram_kernel, dim=num_nodes,
              inputs=[bvh.node_left, bvh.node_begin, bvh.node_end, histogram], device=device)
    hist = histogram.numpy().astype(np.int64)
    return {
        "num_prims": bvh.num_prims,
        "num_refs": bvh.num_refs,
        "num_nodes": num_nodes,
        "num_leaves": num_leaves,
        "num_interior": num_nodes - num_leaves,
        "depth": int(max_depth.numpy()[0]),
        "leaf_size_histogram": hist.tolist(),
        "mean_leaf_size": float(bvh.num_refs / max(num_leaves, 1)),
        "sah_cost": sah_cost(bvh, t_traversal, t_intersect),
    }


#: Nodes per launch of the end-point overlap on the CPU, where slices run side by side.
EPO_CPU_SLICES = 64


def _ref_index(bvh: Bvh):
    """The EPO kernel's `RefIndex`: empty for a permutation, else every triangle's positions."""
    device = bvh.device
    refs = kernels.RefIndex()
    refs.has_duplicates = int(bvh.has_duplicates)
    if not bvh.has_duplicates:
        refs.start = refs.positions = refs.leaf_of = wp.zeros(1, dtype=wp.int32, device=device)
        return refs
    tree = bvh.to_numpy()
    order = tree["prim_order"]
    leaves = np.nonzero(tree["node_left"] < 0)[0]
    # The leaves' ranges tile [0, num_refs): in order of their first positions, one run each.
    leaves = leaves[np.argsort(tree["node_begin"][leaves], kind="stable")]
    leaf_of = np.repeat(leaves, tree["node_end"][leaves] - tree["node_begin"][leaves]).astype(np.int32)
    positions = np.argsort(order, kind="stable").astype(np.int32)  # ascending within each triangle
    start = np.concatenate([[0], np.cumsum(np.bincount(order, minlength=bvh.num_prims))]).astype(np.int32)
    refs.start = wp.array(start, dtype=wp.int32, device=device)
    refs.positions = wp.array(positions, dtype=wp.int32, device=device)
    refs.leaf_of = wp.array(leaf_of, dtype=wp.int32, device=device)
    return refs


@holding_tree
def end_point_overlap(bvh: Bvh, t_traversal: float = 1.0, t_intersect: float = 1.0, per_node: bool = False):
    """End-point overlap, EPO (Aila, Karras & Laine, *On Quality Metrics of Bounding Volume
    Hierarchies*, HPG 2013), the metric Wodniok & Goesele 2016 report beside the SAH:

        EPO = sum over nodes n of term(n) * A((S minus Q(n)) inside box(n)) / A(S)

    S is the surface of all triangles, Q(n) the triangles under n, A an area; term(n) is the node's
    own term of the SAH as `sah_cost` counts it (2 T1 for an interior node, T2 N for a leaf of N
    triangles), so that EPO and SAH come in one unit. Aila et al. weight an interior node by c_t
    alone: their EPO at (c_t, c_i) is this one at ``t_traversal = c_t / 2``. The two weightings
    rank and compare trees differently, since trees split their overlap between interior nodes
    and leaves differently (on suzanne the median split's EPO is 1.71 of the sweep's here at
    T1 = 1.2, and 1.62 at T1 = 0.6).

    Where the SAH prices the rays that cross a node's box, the EPO prices the surface a ray can
    end on inside a box it did not need to enter: the overlap of boxes with triangles of other
    subtrees, which the SAH cannot see (Aila et al. find SAH and EPO together predict measured
    traversal cost far better than SAH alone).

    Every node walks the tree from the root to the foreign triangles whose boxes meet its own and
    clips each to its box in float64 (Sutherland-Hodgman): about O(N log N) clips on good trees, so
    it is a measurement, not a per-frame stage. Returns the EPO (a float), or with `per_node` the
    float64 array of each node's term(n) * A(...) (not yet divided by A(S)) as well.
    """
    require_bvh(bvh, "end_point_overlap")
    if bvh.vertices is None or bvh.faces is None:
        raise ValueError("end_point_overlap() needs a BVH built over a mesh (build()), not over bare boxes")
    t_traversal, t_intersect = check_costs(t_traversal, t_intersect)
    from . import threads as threads_module

    device = bvh.device
    num_nodes = bvh.num_nodes
    node_epo = wp.zeros(max(num_nodes, 1), dtype=wp.float64, device=device)
    areas = wp.zeros(bvh.num_prims, dtype=wp.float64, device=device)
    wp.launch(kernels.triangle_areas_kernel, dim=bvh.num_prims, inputs=[bvh.vertices, bvh.faces, areas],
              device=device)
    args = [bvh.node_count, bvh.node_lowers, bvh.node_uppers, bvh.node_left, bvh.node_right, bvh.node_begin,
            bvh.node_end, bvh.prim_order, bvh.prim_lowers, bvh.prim_uppers, bvh.vertices, bvh.faces,
            _ref_index(bvh), wp.float64(t_traversal), wp.float64(t_intersect), node_epo]
    threads = threads_module.resolved_threads(bvh.config, device)
    if threads > 1 and num_nodes > EPO_CPU_SLICES:
        # Nodes near the root meet far more foreign triangles than the rest: many small slices
        # keep both threads busy to the end.
        cuts = threads_module.split_bounds(num_nodes, EPO_CPU_SLICES)
        parts = [(hi - lo, [lo] + args) for lo, hi in zip(cuts, cuts[1:]) if hi > lo]
        threads_module.launch_parts(kernels.end_point_overlap_kernel, device, parts, threads)
    else:
        wp.launch(kernels.end_point_overlap_kernel, dim=num_nodes, inputs=[0] + args, device=device)
    total_area = float(areas.numpy().sum())
    values = node_epo.numpy()[:num_nodes]
    epo = float(values.sum() / total_area) if total_area > 0.0 else 0.0
    return (epo, values) if per_node else epo
