"""``"recursive_sah"``: the recursive-SAH BVH (RBVH) of Wodniok & Goesele, GI 2016.

A greedy top-down builder whose split candidates are rated not by the linear SAH estimate
c_t + p_l |L| c_i + p_r |R| c_i but by the SAH cost of temporary BVHs actually built, greedily
with binned SAH, over each side (their Alg. 1 and eq. 4):

    c_split = term + area(L) C(T_L) / area(node) + area(R) C(T_R) / area(node)

with term = 2 T1 (this library's eq. (1) convention). This is their binning-binning variant:
``config.recursive_sah_bins`` bin boundaries per axis for the BVH itself (RBVH*: 64, RBVH: 256)
and ``config.recursive_sah_temp_bins`` (32) for the temporary BVHs, O(B N log^2 N) in all. It
splits down to ``config.max_leaf_size`` like every other builder here, so trees compare at the
same leaf rule. The paper measured its SAH 12.7% and its EPO 23.2% below a plane-sweep BVH on
average over ten scenes, at one to two orders of magnitude more build time: an offline builder.

The tree is built one level at a time. The host bins the open nodes' centroids (NumPy, one pass
per level over the primitives); every candidate with two non-empty sides becomes two ranges of a
scratch array holding that side's primitive ids, and one Warp launch builds every side's
temporary BVH, one thread each (``kernels/recursive_sah.py``). The host then keeps each node's
cheapest candidate and partitions its primitives. Scratch is bounded by ``SCRATCH_ITEMS`` per
launch; a level with more candidates runs in several.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from . import threads as threads_module
from .bvh import Bvh, bvh_from_numpy
from .config import BuildConfig
from .hlbvh import StageTimer
from .kernels import recursive_sah as kernels

#: Primitive ids one launch of temporary builds may hold (side ranges of the scratch array).
SCRATCH_ITEMS = 1 << 23


def _bins(centroids: np.ndarray, lower: np.ndarray, upper: np.ndarray, num_bins: int) -> np.ndarray:
    """Bin of every centroid per axis among bins over [lower, upper], the expressions of the
    kernel's `bin_of`; an axis of zero extent puts everything in bin 0."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        extent = upper - lower
        offset = centroids - lower
        product = np.float32(num_bins) * offset
        scaled = product / extent
        # Past about 1e36 the product overflows to inf, whose cast to an integer is undefined
        # (bin 0 on x86: every centroid in one bin). Dividing first cannot overflow; the float32
        # expression is kept elsewhere so that the kernel and this host binning agree.
        scaled = np.where(np.isinf(product), (offset / extent) * np.float32(num_bins), scaled)
        # An extent past float32's range (centroids from -3e38 to 3e38) is inf: there the kernel
        # bins in float64, and so does this.
        wide = np.float64(num_bins) * (centroids.astype(np.float64) - lower) / (upper.astype(np.float64) - lower)
        scaled = np.where(np.isinf(extent), wide, scaled)
    bins = np.where(extent > 0, scaled, 0).astype(np.int64)
    return np.clip(bins, 0, num_bins - 1)


def _area(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    d = upper.astype(np.float64) - lower.astype(np.float64)
    return 2.0 * (d[..., 0] * d[..., 1] + d[..., 1] * d[..., 2] + d[..., 2] * d[..., 0])


def _side_costs(scratch: np.ndarray, firsts: np.ndarray, lasts: np.ndarray, prim_lowers, prim_uppers,
                config: BuildConfig, device) -> np.ndarray:
    """term(n) * area(n) summed over the temporary BVH of each scratch range (one thread each)."""
    count = len(firsts)
    device = wp.get_device(device)
    items = wp.array(scratch, dtype=wp.int32, device=device)
    first = wp.array(firsts.astype(np.int32), dtype=wp.int32, device=device)
    last = wp.array(lasts.astype(np.int32), dtype=wp.int32, device=device)
    costs = wp.zeros(count, dtype=wp.float64, device=device)
    args = [first, last, items, prim_lowers, prim_uppers, config.recursive_sah_temp_bins, config.max_leaf_size,
            wp.float64(config.sah_traversal_cost), wp.float64(config.sah_intersection_cost), costs]
    threads = threads_module.resolved_threads(config, device)
    if threads > 1 and count > 1:
        # Sides vary in size by orders of magnitude: many small slices keep both threads busy.
        cuts = threads_module.split_bounds(count, min(count, 16 * threads))
        parts = [(hi - lo, [lo] + args) for lo, hi in zip(cuts, cuts[1:]) if hi > lo]
        threads_module.launch_parts(kernels.side_costs_kernel, device, parts, threads)
    else:
        wp.launch(kernels.side_costs_kernel, dim=count, inputs=[0] + args, device=device)
    return costs.numpy()


def host_centroids(lowers: np.ndarray, uppers: np.ndarray) -> np.ndarray:
    """The kernels' `morton.box_centroid` on the host, to the bit: 0.5 * (lower + upper) in
    float32, and where that sum overflows (past 1.7e38), the sum of the exact halves."""
    half = np.float32(0.5)
    with np.errstate(over="ignore", invalid="ignore"):
        centroids = half * (lowers + uppers)
        over = np.isinf(centroids)
        if over.any():
            centroids[over] = (half * lowers + half * uppers)[over]
    return centroids


def build_recursive_sah(prim_lowers: wp.array, prim_uppers: wp.array, config: BuildConfig, device,
                        timer: StageTimer) -> Bvh:
    """The RBVH of Wodniok & Goesele (GI 2016, Alg. 1) over the primitive boxes: level by level on
    the host, every split candidate rated by the SAH cost of the temporary BVHs of its two sides, built
    on the device (see the module docstring). Returns a `Bvh` boxed on the device."""
    device = wp.get_device(device)
    lowers = prim_lowers.numpy()
    uppers = prim_uppers.numpy()
    centroids = host_centroids(lowers, uppers)
    n = len(lowers)
    num_bins = config.recursive_sah_bins
    t1 = config.sah_traversal_cost
    arena = 2 * n - 1
    left = np.full(arena, -1, np.int32)
    right = np.full(arena, -1, np.int32)
    node_begin = np.zeros(arena, np.int32)
    node_end = np.zeros(arena, np.int32)
    node_end[0] = n
    order = np.arange(n, dtype=np.int32)
    open_nodes = np.array([0], dtype=np.int64)
    next_node = 1
    timer.stage("top_down")
    while len(open_nodes):
        sizes = (node_end[open_nodes] - node_begin[open_nodes]).astype(np.int64)
        nodes = open_nodes[sizes > config.max_leaf_size]
        if not len(nodes):
            break
        begins = node_begin[nodes].astype(np.int64)
        counts = (node_end[nodes] - node_begin[nodes]).astype(np.int64)
        # The level's primitives, node by node, and each one's node (0 .. len(nodes) - 1).
        member = np.repeat(np.arange(len(nodes)), counts)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        positions = np.repeat(begins - starts, counts) + np.arange(counts.sum())
        items = order[positions]
        c = centroids[items]
        c_lo = np.minimum.reduceat(c, starts)
        c_hi = np.maximum.reduceat(c, starts)
        box_area = _area(np.minimum.reduceat(lowers[items], starts),
                         np.maximum.reduceat(uppers[items], starts))
        bins = _bins(c, c_lo[member], c_hi[member], num_bins)
        # Per axis, the level's primitives in (node, bin) order, stable: each node's segment holds
        # the candidates' left sides as prefixes.
        by_axis = [np.lexsort((bins[:, a], member)) for a in range(3)]
        sorted_items = np.concatenate([items[o] for o in by_axis]).astype(np.int32)
        histogram = np.zeros((len(nodes), 3, num_bins), np.int64)
        for a in range(3):
            np.add.at(histogram[:, a], (member, bins[:, a]), 1)
        left_counts = np.cumsum(histogram, axis=2)[:, :, :-1]  # boundary j = 1 .. B-1
        valid = (left_counts > 0) & (left_counts < counts[:, None, None])
        cand_node, cand_axis, cand_bound = np.nonzero(valid)
        cand_left = left_counts[cand_node, cand_axis, cand_bound]
        cand_size = counts[cand_node]
        cost = np.full(len(cand_node), np.inf)
        # Temporary builds, as many candidates per launch as the scratch holds.
        done = 0
        while done < len(cand_node):
            sizes_cum = np.cumsum(cand_size[done:])
            stop = done + max(1, int(np.searchsorted(sizes_cum, SCRATCH_ITEMS, side="right")))
            sel = slice(done, stop)
            size = cand_size[sel]
            offsets = np.concatenate([[0], np.cumsum(size)[:-1]])
            src = cand_axis[sel] * len(items) + starts[cand_node[sel]]
            gather = np.repeat(src - offsets, size) + np.arange(size.sum())
            scratch = sorted_items[gather]
            firsts = np.stack([offsets, offsets + cand_left[sel]], axis=1).ravel()
            lasts = np.stack([offsets + cand_left[sel], offsets + size], axis=1).ravel()
            sides = _side_costs(scratch, firsts, lasts, prim_lowers, prim_uppers, config, device).reshape(-1, 2)
            cost[sel] = 2.0 * t1 + (sides[:, 0] + sides[:, 1]) / np.maximum(box_area[cand_node[sel]], 1e-300)
            done = stop
        # Each node's cheapest candidate; among exact equals the one nearest the middle, then the
        # first in (axis, boundary) order. Zero-area boxes price every candidate alike (P_hit is
        # 0 / 0): the first would peel one bin off at a time, a chain about 60 ln N deep, where the
        # sweep builders send such ties to the middle.
        best = np.full(len(nodes), -1, np.int64)
        if len(cand_node):
            imbalance = np.abs(2 * cand_left - cand_size)
            pick = np.lexsort((np.arange(len(cost)), imbalance, cost, cand_node))
            first_of_node = np.concatenate([[True], cand_node[pick][1:] != cand_node[pick][:-1]])
            best[cand_node[pick][first_of_node]] = pick[first_of_node]
        # Partition: the chosen axis's (bin) order, cut after the left side's count. A node with
        # no candidate (every centroid equal) is halved in its current order.
        has = best >= 0
        pick = np.maximum(best, 0)
        axis = cand_axis[pick] if len(cand_node) else np.zeros(len(nodes), np.int64)
        left_count = cand_left[pick] if len(cand_node) else np.zeros(len(nodes), np.int64)
        level_index = np.arange(len(items))
        chosen = sorted_items[axis[member] * len(items) + level_index]
        order[positions] = np.where(has[member], chosen, items)
        cut = begins + np.where(has, left_count, counts // 2)
        children = next_node + 2 * np.arange(len(nodes))
        left[nodes], right[nodes] = children, children + 1
        node_begin[children], node_end[children] = begins, cut
        node_begin[children + 1], node_end[children + 1] = cut, begins + counts
        next_node += 2 * len(nodes)
        open_nodes = np.stack([children, children + 1], axis=1).ravel()

    timer.stage("bbox")
    used = slice(0, next_node)
    return bvh_from_numpy(method="recursive_sah", config=config, device=device, prim_lowers=prim_lowers,
                          prim_uppers=prim_uppers, prim_order=order, node_left=left[used], node_right=right[used],
                          node_begin=node_begin[used], node_end=node_end[used], timings=timer.finish())
