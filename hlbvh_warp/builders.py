"""Reference builders beside HLBVH, registered into `api.BUILDERS` on import.

* ``"sweep_sah"``: greedy top-down full plane-sweep SAH (MacDonald & Booth 1990; Wald, Boulos &
  Shirley 2007), the quality reference of Pantaleoni & Luebke 2010, Table 3.
* ``"binned_sah"``: the same sweep priced only at ``config.sah_bins`` bin boundaries per axis
  (Wald 2007).
* ``"median"``: object median on the longest centroid axis.
* ``"hlbvh_sah"``: SAH-optimized HLBVH (Pantaleoni & Luebke 2010, section 3.3): HLBVH's sort and
  Morton treelets inside every coarse voxel, the top levels a SAH sweep over the voxel clusters
  weighted by their subtrees' SAH costs.

The top-down builders run one data-parallel step per tree level (kernels/sah.py); the host
reads one count per level to know when the tree is finished. By default they split down to
``config.max_leaf_size`` so that every builder is compared at the same leaf rule;
`build_top_down` takes ``terminate_leaf_size`` for the usual SAH leaf termination.
"""

from __future__ import annotations

import math

import warp as wp

from . import api, memory
from .memory import array_bytes
from . import threads as threads_module
from .bvh import Bvh
from .config import BuildConfig
from .hlbvh import HlbvhPipeline, StageTimer, compute_bounds
from .kernels import block_sort
from .kernels import metrics as metrics_kernels
from .kernels import sah, treelets, upper_sah

#: The SAH-optimized HLBVH's cluster tree prices nodes of more than TOP_TREE_BINNED_ABOVE
#: clusters at TOP_TREE_BINS bin boundaries (Wald 2007) and sweeps every position below that.
#: Measured on the armadillo's 11,771 clusters: the cluster tree took 10.6 ms instead of 12.1,
#: and the SAH cost moved from 1.0734 to 1.0743 of sweep_sah (bunny: 1.0489 to 1.0499).
TOP_TREE_BINNED_ABOVE = 256
TOP_TREE_BINS = 64

#: Below this many items a depth-first top-down build stays in one thread: handing subtrees to
#: other threads costs about as much as building them.
PARALLEL_MIN_ITEMS = 4096

#: Split rule of each top-down method (kernels/sah.py).
TOP_DOWN_MODES = {"sweep_sah": sah.MODE_SWEEP, "binned_sah": sah.MODE_BINNED, "median": sah.MODE_MEDIAN}


class TopDownBuilder:
    """Scratch of the level-parallel top-down build over `num_items` items, allocated once.

    The greedy top-down builders of ``kernels/sah.py``: the full SAH sweep (MacDonald & Booth 1990,
    as organized by Wald, Boulos & Shirley 2007), binned SAH (Wald 2007) and the object median.

    ``capacity`` (default `num_items`) sizes the scratch; `resize` then sets the item count of
    the next builds anywhere up to it without allocating, as the cluster tree of a per-frame
    ``hlbvh_sah`` build needs (its cluster count changes every frame).
    """

    def __init__(self, num_items: int, device, capacity: int | None = None):
        if num_items < 1:
            raise ValueError("a top-down build needs at least one item")
        self.capacity = k = max(num_items, capacity or 0)
        self.num_items = num_items
        self.device = device = wp.get_device(device)

        def ints(count):
            return memory.empty(count, dtype=wp.int32, device=device)

        # The radix sort needs keys and values of twice the item count.
        self.sort_keys = ints(2 * k)
        self.sort_ids = ints(2 * k)
        # Per-axis orders, ping-ponged every level: order[axis * k + position].
        self.order = ints(3 * k)
        self.order_next = ints(3 * k)
        self.item_side = ints(k)
        self.suffix_cost = memory.empty(k, dtype=wp.float64, device=device)
        # Bins of the one-pass binned pricing, in the slots of each node's own range.
        self.bin_lowers = memory.empty(k, dtype=wp.vec3, device=device)
        self.bin_uppers = memory.empty(k, dtype=wp.vec3, device=device)
        self.bin_weight = memory.empty(k, dtype=wp.float64, device=device)
        self.bin_count = ints(k)
        # A level holds disjoint non-empty ranges, so at most k nodes.
        self.level_nodes = ints(k)
        self.next_level_nodes = ints(k)
        self.level_count = ints(1)
        self.next_level_count = ints(1)
        self.split_axis = ints(k)
        self.split_pos = ints(k)
        self.split_flag = ints(k)
        self.split_offset = ints(k)

    def resize(self, num_items: int):
        """Build over the first `num_items` items next (at most `capacity`); allocates nothing.
        The per-axis orders are laid out with the item count as their stride, so any count up to
        the capacity fits the same arrays."""
        if not 1 <= num_items <= self.capacity:
            raise ValueError(f"num_items must be in [1, {self.capacity}], got {num_items}")
        self.num_items = num_items

    def _launch(self, kernel, dim, inputs):
        wp.launch(kernel, dim=dim, inputs=inputs, device=self.device)

    @staticmethod
    def _split_frontier(subtree, threads: int, node_left, node_begin, node_end):
        """Split the largest open subtree, one node at a time, until `threads` of them are open
        (or none can split); returns ``[(root, items)]`` largest first and the next free node id."""
        frontier = [(0, int(node_end.numpy()[0]))]
        next_free = 1
        while len(frontier) < threads:
            frontier.sort(key=lambda item: -item[1])
            root, size = frontier[0]
            if size < 2:
                break
            subtree(root, next_free, split_root_only=1)
            frontier.pop(0)
            if int(node_left.numpy()[root]) >= 0:
                begin, end = node_begin.numpy(), node_end.numpy()
                for child in (next_free, next_free + 1):
                    frontier.append((child, int(end[child] - begin[child])))
                next_free += 2
        frontier.sort(key=lambda item: -item[1])
        return frontier, next_free

    def sort_axes(self, item_lowers: wp.array, item_uppers: wp.array):
        """Presort the items by centroid on each axis (stable: ties keep index order)."""
        k = self.num_items
        for axis in range(3):
            self._launch(sah.centroid_keys_kernel, k, [item_lowers, item_uppers, axis, self.sort_keys, self.sort_ids])
            wp.utils.radix_sort_pairs(self.sort_keys, self.sort_ids, k)
            wp.copy(self.order, self.sort_ids, dest_offset=axis * k, count=k)

    def build_levels(
        self,
        item_lowers: wp.array,
        item_uppers: wp.array,
        item_weights: wp.array,
        *,
        mode: int,
        num_bins: int,
        max_leaf_size: int,
        terminate_leaf_size: int,
        t_traversal: float,
        t_intersect: float,
        node_left: wp.array,
        node_right: wp.array,
        node_parent: wp.array,
        node_begin: wp.array,
        node_end: wp.array,
        node_count: wp.array,
        item_order: wp.array,
        emission: str = "treelets",
        binned_above: int = 0,
        threads: int = 1,
    ) -> int:
        """Split until every node is a leaf; returns the number of launches that split.

        ``emission`` is the resolved `BuildConfig.emission`: ``"treelets"`` splits level by level,
        every open node of a level at once (for CUDA); ``"depth_first"`` walks the whole tree in
        one thread (for the CPU device). Both make the same splits. With ``mode=sah.MODE_SWEEP``,
        nodes of more than ``binned_above`` items (0: none) are priced at ``num_bins`` bin
        boundaries instead of at every position. ``threads`` > 1 builds disjoint subtrees side
        by side on the CPU (depth first, one item per leaf; see `hlbvh_warp.threads`).
        """
        k = self.num_items
        inputs = sah.SplitInputs()
        inputs.order = self.order
        inputs.num_items = k
        inputs.item_lowers, inputs.item_uppers, inputs.item_weights = item_lowers, item_uppers, item_weights
        inputs.mode, inputs.num_bins, inputs.binned_above = mode, num_bins, binned_above
        inputs.max_leaf_size, inputs.terminate_leaf_size = max_leaf_size, terminate_leaf_size
        inputs.t_traversal, inputs.t_intersect = wp.float64(t_traversal), wp.float64(t_intersect)
        inputs.suffix_cost = self.suffix_cost
        inputs.bin_lowers, inputs.bin_uppers = self.bin_lowers, self.bin_uppers
        inputs.bin_weight, inputs.bin_count = self.bin_weight, self.bin_count
        if emission == "depth_first":
            self._launch(sah.init_root_kernel, 1, [k, node_left, node_right, node_parent, node_begin, node_end])
            shared = [inputs, self.order_next, self.item_side, self.level_nodes, node_left, node_right, node_parent,
                      node_begin, node_end, node_count, item_order]

            def subtree(root, first_free, split_root_only=0, write_count=0):
                self._launch(sah.build_depth_first_kernel, 1, shared + [root, first_free, split_root_only, write_count])

            # Subtrees run side by side only where their node ids are known in advance: with one
            # item per leaf, a subtree of s items has exactly 2s - 2 nodes below its root.
            exact = max_leaf_size == 1 and terminate_leaf_size <= 0
            if threads <= 1 or not exact or k < PARALLEL_MIN_ITEMS:
                subtree(0, 1, write_count=1)
                return 1
            frontier, next_free = self._split_frontier(subtree, threads, node_left, node_begin, node_end)
            jobs = []
            for root, size in frontier:
                jobs.append(lambda root=root, base=next_free: subtree(root, base))
                next_free += 2 * size - 2
            threads_module.run(jobs, threads)
            node_count.fill_(2 * k - 1)
            return 1
        self._launch(
            sah.init_top_down_kernel,
            node_left.shape[0],
            [k, node_left, node_right, node_parent, node_begin, node_end, node_count, self.level_nodes,
             self.level_count],
        )
        count = 1
        levels = 0
        while count > 0:
            levels += 1
            # Every open node of the level picks its split (or stays a leaf) on this level's orders.
            inputs.order = self.order
            self._launch(
                sah.choose_splits_kernel,
                count,
                [self.level_count, self.level_nodes, node_begin, node_end, inputs,
                 self.split_axis, self.split_pos, self.split_flag],
            )
            # Number the children of the splitting nodes without holes.
            wp.utils.array_scan(self.split_flag[:count], self.split_offset[:count], inclusive=False)
            # Emit the children, partition the three orders, place the finished leaves.
            self._launch(
                sah.emit_children_kernel,
                count,
                [self.level_count, self.level_nodes, self.split_axis, self.split_pos, self.split_flag,
                 self.split_offset, k, self.order, self.order_next, self.item_side, node_count, node_left,
                 node_right, node_parent, node_begin, node_end, self.next_level_nodes, item_order],
            )
            self._launch(
                sah.advance_level_kernel,
                1,
                [self.level_count, self.split_flag, self.split_offset, node_count, self.next_level_count],
            )
            self.order, self.order_next = self.order_next, self.order
            self.level_nodes, self.next_level_nodes = self.next_level_nodes, self.level_nodes
            self.level_count, self.next_level_count = self.next_level_count, self.level_count
            # The one host read per level: whether (and how wide) the next level is.
            count = int(self.level_count.numpy()[0])
        return levels


def build_top_down(
    prim_lowers: wp.array,
    prim_uppers: wp.array,
    config: BuildConfig,
    device,
    timer: StageTimer,
    *,
    method: str = "sweep_sah",
    terminate_leaf_size: int = 0,
) -> Bvh:
    """Top-down build over primitive boxes with the split rule of `method` (see `TOP_DOWN_MODES`):
    the greedy SAH sweep (MacDonald & Booth 1990; Wald, Boulos & Shirley 2007), binned SAH (Wald
    2007) or the object median.

    Args:
        terminate_leaf_size: nodes of up to this many primitives become leaves when splitting them
            costs more than a leaf under the SAH (T1 = ``config.sah_traversal_cost``, T2 =
            ``config.sah_intersection_cost``); 0 (the default) always splits down to
            ``config.max_leaf_size``. Only the SAH modes use it.
    """
    device = wp.get_device(device)
    n = prim_lowers.shape[0]
    arena = 2 * n - 1

    def ints(count):
        return memory.empty(count, dtype=wp.int32, device=device)

    out = _Arena(device, n, arena)
    weights = memory.empty(n, dtype=wp.float64, device=device)
    wp.launch(sah.fill_float64_kernel, dim=n, inputs=[weights, wp.float64(1.0)], device=device)
    builder = TopDownBuilder(n, device)

    # Sort the primitive centroids once per axis.
    timer.stage("sort_axes")
    builder.sort_axes(prim_lowers, prim_uppers)
    # Split top-down: sweep (or bin, or halve) every open node, partition the orders.
    timer.stage("top_down")
    builder.build_levels(
        prim_lowers,
        prim_uppers,
        weights,
        mode=TOP_DOWN_MODES[method],
        num_bins=config.sah_bins,
        max_leaf_size=config.max_leaf_size,
        terminate_leaf_size=max(terminate_leaf_size, 0),
        t_traversal=config.sah_traversal_cost,
        t_intersect=config.sah_intersection_cost,
        node_left=out.node_left,
        node_right=out.node_right,
        node_parent=out.node_parent,
        node_begin=out.node_begin,
        node_end=out.node_end,
        node_count=out.node_count,
        item_order=out.prim_order,
        emission=config.resolved_emission(device),
        threads=threads_module.resolved_threads(config, device),
    )
    # Bounding boxes of all nodes, bottom-up.
    timer.stage("bbox")
    node_visits = ints(arena)
    compute_bounds(device, out.node_count, out.node_left, out.node_right, out.node_parent, out.node_begin,
                   out.node_end, out.prim_order, prim_lowers, prim_uppers, node_visits, out.node_lowers,
                   out.node_uppers)
    bvh = out.to_bvh(method, config, prim_lowers, prim_uppers, timer.finish())
    bvh.buffer_bytes = array_bytes(out, builder) + weights.capacity + node_visits.capacity
    return bvh


class _Arena:
    """The output arrays of a build: prim_order and the node arena of 2N - 1 slots."""

    def __init__(self, device, num_prims: int, arena: int):
        self.prim_order = memory.empty(num_prims, dtype=wp.int32, device=device)
        self.node_lowers = memory.empty(arena, dtype=wp.vec3, device=device)
        self.node_uppers = memory.empty(arena, dtype=wp.vec3, device=device)
        for name in ("node_left", "node_right", "node_parent", "node_begin", "node_end"):
            setattr(self, name, memory.empty(arena, dtype=wp.int32, device=device))
        self.node_count = wp.zeros(1, dtype=wp.int32, device=device)

    def to_bvh(self, method, config, prim_lowers, prim_uppers, timings) -> Bvh:
        """A `Bvh` over these arrays (no copy) and the given primitive boxes."""
        return Bvh._trusted(
            method=method,
            config=config,
            device=self.prim_order.device,
            prim_lowers=prim_lowers,
            prim_uppers=prim_uppers,
            prim_order=self.prim_order,
            node_lowers=self.node_lowers,
            node_uppers=self.node_uppers,
            node_left=self.node_left,
            node_right=self.node_right,
            node_parent=self.node_parent,
            node_begin=self.node_begin,
            node_end=self.node_end,
            node_count=self.node_count,
            timings=timings,
        )


class HlbvhSahPipeline(HlbvhPipeline):
    """SAH-optimized HLBVH (Pantaleoni & Luebke 2010, section 3.3) on the HLBVH buffers.

    The primitive sort and the treelet emission are HLBVH's own stages; what differs is the
    top of the tree, built by a SAH sweep over the coarse voxels (clusters) with each cluster
    priced by its subtree's SAH cost instead of a unit primitive cost. See kernels/upper_sah.py
    for how the two halves share one arena.
    """

    def __init__(self, num_prims: int, config: BuildConfig, device, prim_lowers: wp.array | None = None,
                 prim_uppers: wp.array | None = None):
        super().__init__(num_prims, config, device, prim_lowers, prim_uppers)
        # The SAH cost of every node below the cluster roots times 2^cost_exponent (`build_sah`).
        self.node_cost = memory.empty(2 * num_prims - 1, dtype=wp.float64, device=self.device)
        self.cost_exponent = 0
        self.prim_order = memory.empty(num_prims, dtype=wp.int32, device=self.device)
        self.top = None

    #: sorted_prim_ids stays scratch here: the tree's order is `prim_order`, written by the join.
    OUTPUTS = HlbvhPipeline.OUTPUTS[:-1] + ("prim_order",)

    def held_bytes(self) -> int:
        """Bytes of the arrays this pipeline holds, the cluster tree's scratch included."""
        return super().held_bytes() + (self.top.nbytes() if self.top is not None else 0)

    def max_clusters(self) -> int:
        """The most clusters a build of this pipeline can have: no more than the primitives or the
        voxels of the 3m-bit grid, and, where m is automatic, no more than one per
        ``cluster_min_prims`` primitives (the coarsening stops there) or the 8 voxels of m = 1."""
        n, cfg = self.num_prims, self.config
        bound = min(n, 1 << (3 * self.coarse_bits))
        if cfg.coarse_bits is None and cfg.cluster_min_prims > 0.0:
            most = int(n / cfg.cluster_min_prims)
            # The coarsening stops once n >= cluster_min_prims x C in float64, which can hold at
            # one count past the rounded quotient (17 / 1.7000000000000002 = 9.999..., while
            # 1.7000000000000002 x 10 = 17.0): the reserve was one cluster short. One step is
            # enough where the quotient is below n (counts above n are capped anyway): there the
            # products of adjacent counts differ by more than 1.
            if (most + 1) * cfg.cluster_min_prims <= n:
                most += 1
            bound = min(bound, max(8, most))
        return max(bound, 1)

    def reserve_top_tree(self):
        """Allocate the cluster tree's scratch for `max_clusters`, so that no later build allocates."""
        capacity = self.max_clusters()
        if self.top is None or self.top.capacity < capacity:
            self.top = _TopTree(capacity, self.device)

    def build_sah(self, timer: StageTimer, inputs_ready: str = "boxes") -> dict:
        """Run the SAH-optimized build on `prim_lowers` / `prim_uppers`; ``inputs_ready`` as in
        `HlbvhPipeline.build` (what the caller has already computed: ``"boxes"``, ``"bounds"``
        or ``"codes"``). Returns the timings.

        Reads the cluster count on the host (it sizes the cluster tree), so unlike the plain
        pipeline this build cannot be captured in a CUDA graph.
        """
        n = self.num_prims
        cfg = self.config

        # Morton codes, run-length encoding by coarse voxel, compress-sort-decompress, voxel sort:
        # the primitive order of HLBVH, unchanged.
        self.compute_codes(timer, inputs_ready)
        self.sort_codes(timer, need_voxels=True)
        self.order_tied_ids(timer)

        # Clusters: the non-empty voxels, merged into coarser voxels while they are too small
        # on average (BuildConfig.cluster_min_prims).
        num_clusters = int(self.voxel_count.numpy()[0])
        self.cluster_bits = self.coarse_bits
        if cfg.coarse_bits is None:
            while self.cluster_bits > 1 and n < cfg.cluster_min_prims * num_clusters:
                self.cluster_bits -= 1
                num_clusters = self.merge_clusters(num_clusters)
        voxel_bits = 3 * (cfg.bits_per_axis - self.cluster_bits)

        # The cluster costs are priced with T1 and T2 scaled by one power of two that brings the
        # larger into [1, 2). Eq. (1) is linear in (T1, T2), so the scale multiplies every cost and
        # every price of the cluster tree's sweep exactly (short of a ratio T1 / T2 so extreme that
        # the smaller becomes subnormal) and changes no split; unscaled, finite constants the
        # config accepts (T1 = T2 = 2^1020) priced the clusters past float64's range, inf, and every
        # cluster split fell back to the index median.
        # The exponent by ldexp: 2^k itself is past float64 for the smallest T2 (5e-324, k = 1074).
        self.cost_exponent = k = 1 - math.frexp(max(cfg.sah_traversal_cost, cfg.sah_intersection_cost))[1]
        costs = (math.ldexp(cfg.sah_traversal_cost, k), math.ldexp(cfg.sah_intersection_cost, k))

        # Voxel hierarchy: one treelet segment per cluster, emitted over the low 3(n - m) bits.
        timer.stage("voxel_hierarchy")
        if self.emission == "depth_first":
            # The top tree's 2C - 1 slots are taken; treelet nodes are numbered after them.
            self.node_count.fill_(2 * num_clusters - 1)
            # Boxes and SAH costs of the cluster subtrees come out of the same walk.
            self.emit_depth_first(self.voxel_starts, self.voxel_count, num_clusters - 1, num_clusters,
                                  node_cost=self.node_cost, costs=costs)
        else:
            self._launch(
                treelets.init_nodes_kernel,
                2 * n - 1,
                [n, self.node_left, self.node_right, self.node_parent, self.node_visits, cfg.max_leaf_size,
                 self.head_to_node, self.head_to_end, self.head_flags, self.node_begin, self.node_end,
                 self.node_count],
            )
            self._launch(
                upper_sah.seed_clusters_kernel,
                num_clusters,
                [n, num_clusters, cfg.max_leaf_size, self.voxel_starts, self.head_to_node, self.head_to_end,
                 self.head_flags, self.node_begin, self.node_end, self.node_count],
            )
            self.emit_hierarchy(voxel_bits)
            self.split_exhausted_segments()

        # Cluster costs: boxes and SAH costs of every cluster subtree, bottom-up (the depth-first
        # emission wrote them as it went).
        first_cluster_root = num_clusters - 1
        t_traversal, t_intersect = wp.float64(costs[0]), wp.float64(costs[1])
        if self.emission == "depth_first":
            timer.skipped("cluster_costs")
            timer.stage("cluster_items")
        else:
            timer.stage("cluster_costs")
            self._launch(metrics_kernels.reset_visits_kernel, 2 * n - 1, [self.node_visits])
            self._launch(
                metrics_kernels.bounds_and_cost_kernel,
                2 * n - 1,
                [first_cluster_root, self.node_count, self.node_left, self.node_right, self.node_parent,
                 self.node_begin, self.node_end, self.sorted_prim_ids, self.prim_lowers, self.prim_uppers,
                 t_traversal, t_intersect, self.node_visits, self.node_lowers, self.node_uppers, self.node_cost],
            )
        # The top tree's scratch is kept while the clusters fit it: a per-frame `Builder` reserves
        # it for the most clusters a build can have (`reserve_top_tree`).
        if self.top is None or self.top.capacity < num_clusters:
            self.top = _TopTree(num_clusters, self.device)
        top = self.top
        top.resize(num_clusters)
        self._launch(
            upper_sah.cluster_items_kernel,
            num_clusters,
            [n, num_clusters, self.voxel_starts, self.node_lowers, self.node_uppers, self.node_cost, self.node_left,
             self.node_right, top.cluster_lowers, top.cluster_uppers, top.cluster_cost, top.cluster_left,
             top.cluster_right, top.cluster_size],
        )

        # Top-level hierarchy: greedy SAH sweep over the clusters, weighted by their costs.
        timer.stage("top_level_sah")
        top.builder.sort_axes(top.cluster_lowers, top.cluster_uppers)
        top.builder.build_levels(
            top.cluster_lowers,
            top.cluster_uppers,
            top.cluster_cost,
            mode=sah.MODE_SWEEP,
            num_bins=TOP_TREE_BINS,
            max_leaf_size=1,
            terminate_leaf_size=0,
            t_traversal=costs[0],
            t_intersect=costs[1],
            node_left=top.arena.node_left,
            node_right=top.arena.node_right,
            node_parent=top.arena.node_parent,
            node_begin=top.arena.node_begin,
            node_end=top.arena.node_end,
            node_count=top.arena.node_count,
            item_order=top.arena.prim_order,
            emission=self.emission,
            binned_above=TOP_TREE_BINNED_ABOVE,
            threads=threads_module.resolved_threads(cfg, self.device),
        )

        # Join: top nodes take slots [0, 2C - 1), clusters move to where the top tree put them.
        timer.stage("join")
        cluster_order = top.arena.prim_order
        self._launch(upper_sah.gather_cluster_sizes_kernel, num_clusters,
                     [cluster_order, top.cluster_size, top.ordered_sizes])
        wp.utils.array_scan(top.ordered_sizes[:num_clusters], top.ordered_starts[:num_clusters], inclusive=False)
        self._launch(upper_sah.cluster_shift_kernel, num_clusters,
                     [cluster_order, top.ordered_starts, self.voxel_starts, top.cluster_shift])
        self._launch(
            upper_sah.join_top_kernel,
            2 * num_clusters - 1,
            [n, num_clusters, top.arena.node_left, top.arena.node_right, top.arena.node_parent,
             top.arena.node_begin, top.arena.node_end, cluster_order, top.ordered_starts, top.cluster_left,
             top.cluster_right, self.node_left, self.node_right, self.node_parent, self.node_begin, self.node_end],
        )
        # Free since the voxel sort: which cluster each sorted position belongs to.
        position_cluster = self.scratch_ids
        self._launch(upper_sah.scatter_clusters_kernel, num_clusters,
                     [n, num_clusters, self.voxel_starts, top.cluster_shift, self.sorted_prim_ids, self.prim_order,
                      position_cluster])
        self._launch(
            upper_sah.shift_treelets_kernel,
            2 * n - 1,
            [2 * num_clusters - 1, self.node_count, position_cluster, top.cluster_shift, self.node_begin,
             self.node_end],
        )

        # Bounding boxes of all nodes, bottom-up.
        timer.stage("bbox")
        if self.emission == "depth_first":
            # Cluster subtrees were boxed while costing them; only the top tree's 2C - 1 are new,
            # swept over the top tree's own arena from the cluster boxes.
            self._launch(upper_sah.top_bounds_sweep_kernel, 1,
                         [2 * num_clusters - 1, top.arena.node_left, top.arena.node_right, top.arena.node_begin,
                          cluster_order, top.cluster_lowers, top.cluster_uppers, top.arena.node_lowers,
                          top.arena.node_uppers, self.node_lowers, self.node_uppers])
        else:
            compute_bounds(self.device, self.node_count, self.node_left, self.node_right, self.node_parent,
                           self.node_begin, self.node_end, self.prim_order, self.prim_lowers, self.prim_uppers,
                           self.node_visits, self.node_lowers, self.node_uppers)
        return timer.finish()


    def merge_clusters(self, num_voxels: int) -> int:
        """Merge the clusters into the voxels of `cluster_bits` bits per axis; returns their
        count. The primitive order is unchanged: sorted by the full codes, it is sorted by any
        prefix of them."""
        shift = 3 * (self.config.bits_per_axis - self.cluster_bits)
        self._launch(upper_sah.coarser_cluster_flags_kernel, num_voxels,
                     [self.voxel_starts, self.sorted_codes, shift, self.voxel_flags])
        wp.utils.array_scan(self.voxel_flags[:num_voxels], self.voxel_index[:num_voxels], inclusive=True)
        # The voxel-start compaction of the voxel sort, over voxels instead of runs; block_starts
        # and block_count are free once that sort is done (the count goes to its own array, as
        # every thread reads the input count).
        self._launch(block_sort.compact_voxel_starts_kernel, num_voxels,
                     [self.voxel_count, self.voxel_flags, self.voxel_index, self.voxel_starts, self.block_starts,
                      self.block_count])
        num_clusters = int(self.block_count.numpy()[0])
        self.voxel_count.fill_(num_clusters)
        wp.copy(self.voxel_starts, self.block_starts, count=num_clusters)
        return num_clusters


class _TopTree:
    """Scratch of the top-level SAH build over up to `capacity` clusters; `resize` sets the
    cluster count of the next build without allocating."""

    def __init__(self, capacity: int, device):
        self.capacity = self.num_clusters = c = capacity

        def ints(count):
            return memory.empty(count, dtype=wp.int32, device=device)

        self.cluster_lowers = memory.empty(c, dtype=wp.vec3, device=device)
        self.cluster_uppers = memory.empty(c, dtype=wp.vec3, device=device)
        self.cluster_cost = memory.empty(c, dtype=wp.float64, device=device)
        self.cluster_left = ints(c)
        self.cluster_right = ints(c)
        self.cluster_size = ints(c)
        self.ordered_sizes = ints(c)
        self.ordered_starts = ints(c)
        self.cluster_shift = ints(c)
        self.arena = _Arena(device, c, 2 * c - 1)
        self.builder = TopDownBuilder(c, device)

    def resize(self, num_clusters: int):
        """Build over the first `num_clusters` clusters next (at most `capacity`); allocates nothing."""
        self.num_clusters = num_clusters
        self.builder.resize(num_clusters)

    def nbytes(self) -> int:
        """Bytes of the arrays this scratch holds."""
        return array_bytes(self, self.arena, self.builder)


def _top_down(method: str):
    def run(prim_lowers: wp.array, prim_uppers: wp.array, config: BuildConfig, device, timer: StageTimer) -> Bvh:
        return build_top_down(prim_lowers, prim_uppers, config, device, timer, method=method)

    return run


def _hlbvh_sah(prim_lowers: wp.array, prim_uppers: wp.array, config: BuildConfig, device, timer: StageTimer) -> Bvh:
    n = prim_lowers.shape[0]
    pipe = HlbvhSahPipeline.one_shot(n, config, device, prim_lowers, prim_uppers)
    timings = pipe.build_sah(timer)
    bvh = api.bvh_from_pipeline(pipe, "hlbvh_sah", timings, prim_order=pipe.prim_order)
    # The caller's boxes, which the pipeline only reads, are not the build's: left out, as
    # build_top_down leaves them out.
    bvh.buffer_bytes = pipe.held_bytes() - pipe.prim_lowers.capacity - pipe.prim_uppers.capacity
    pipe.give_back()
    return bvh


def pipeline_buffer_bytes(num_prims: int, config: BuildConfig, device) -> int:
    """Bytes the plain HLBVH / LBVH pipeline allocates for `num_prims` primitives, besides the
    primitive boxes it reads (the caller's in a one-shot build)."""
    pipe = HlbvhPipeline(num_prims, config, device)
    return array_bytes(pipe) - pipe.prim_lowers.capacity - pipe.prim_uppers.capacity


for _name in TOP_DOWN_MODES:
    api.BUILDERS[_name] = _top_down(_name)
api.BUILDERS["hlbvh_sah"] = _hlbvh_sah

__all__ = ["TopDownBuilder", "HlbvhSahPipeline", "build_top_down", "array_bytes", "pipeline_buffer_bytes"]


def _recursive_sah(prim_lowers: wp.array, prim_uppers: wp.array, config: BuildConfig, device,
                   timer: StageTimer) -> Bvh:
    from .recursive_sah import build_recursive_sah

    return build_recursive_sah(prim_lowers, prim_uppers, config, device, timer)


api.BUILDERS["recursive_sah"] = _recursive_sah


def _sbvh(prim_lowers: wp.array, prim_uppers: wp.array, config: BuildConfig, device, timer: StageTimer,
          triangles: tuple | None = None) -> Bvh:
    from .spatial_split import build_sbvh

    return build_sbvh(prim_lowers, prim_uppers, config, device, timer, triangles)


# Spatial splits clip triangles: this builder needs the mesh, not only the boxes.
_sbvh.needs_triangles = True
api.BUILDERS["sbvh"] = _sbvh
