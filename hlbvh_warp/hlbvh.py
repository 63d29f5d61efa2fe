"""Host side of the HLBVH build: buffers, stage wrappers and the orchestrator.

Pantaleoni & Luebke, "HLBVH: Hierarchical LBVH Construction for Real-Time Ray Tracing of
Dynamic Geometry", HPG 2010. `HlbvhPipeline.build` reads like the paper's Fig. 1 and Fig. 4:
one commented step per stage, named as the stage's timing label.
"""

from __future__ import annotations

import bisect
import time

import numpy as np
import warp as wp

from . import memory
from . import threads as threads_module
from .bvh import Bvh
from .config import BuildConfig
from .kernels import block_sort, bounds, compress, merge, morton, treelets

#: Below this many primitives the depth-first emission stays in one thread (see `emit_depth_first`).
PARALLEL_MIN_PRIMS = 8192

#: Primitives per thread of the centroid-bounds reduction on the CPU device.
CPU_REDUCTION_CHUNK = 4096

#: Primitives per thread of the Morton pass on the CPU device (`compute_morton_codes`).
CPU_MORTON_CHUNK = 4096

#: Below this many primitives the CPU's box and centroid-bounds pass stays in one thread (see
#: `_reduce_centroid_bounds`): the handoff between threads costs what the second core saves up
#: to about 120k triangles (one and two threads alternating in one process: 0.94x at 100k,
#: 1.14x at 150k, 1.29x at 200k, 1.37x at 260k, 1.53x on the 400k armadillo).
PARALLEL_BOUNDS_MIN_PRIMS = 1 << 17

#: Below this many primitives the CPU's global sort stays one radix sort in one thread (see
#: `HlbvhPipeline.global_sort`): the halves' handoffs between threads and the merge cost about
#: what the second core saves up to about 150k codes (the armadillo's, two cores, old and new
#: sorts alternating in one process: 0.83x at 100k, 1.08x at 200k, 1.14x at 260k, 1.48x at 400k).
PARALLEL_SORT_MIN_PRIMS = 1 << 18

#: Whether Warp's CPU radix sort may run in several threads at once: Warp 1.19 keeps its digit
#: histogram per thread (``thread_local`` in its sort.cpp); earlier releases kept static tables,
#: which two sorts at once would corrupt.
SORTS_SIDE_BY_SIDE = tuple(int(x) for x in wp.config.version.split(".")[:2]) >= (1, 19)

#: The CPU's own bounds and Morton kernels take a box's centre as 0.5 * (lower + upper), which
#: overflows past 1.7e38; where the centroid bounds (or the fixed grid) reach this far on an axis,
#: the host takes the kernels with `morton.box_centroid` instead (`HlbvhPipeline.compute_morton_codes`).
#: Below it no centre can overflow, and one that overflowed lies outside the grid on the side its
#: infinity does, which clamps it to the same border cell.
CENTROID_OVERFLOW_BOUND = 2.0**127

#: Adjacent pairs of the input codes a CPU build samples to estimate its run count before
#: encoding (`HlbvhPipeline.sampled_run_fraction`): a standard error of at most 0.016 in M / N.
RUN_SAMPLES = 1024


class StageTimer:
    """Milliseconds per stage label, only when asked: no host synchronization otherwise."""

    def __init__(self, device, enabled: bool):
        self.device = device
        self.enabled = enabled
        self.timings: dict[str, float] = {}
        self._label = None
        self._start = 0.0

    def stage(self, label: str):
        """Close the running stage and start timing `label` (the device synchronized at both ends)."""
        if not self.enabled:
            return
        self._close()
        wp.synchronize_device(self.device)
        self._label = label
        self._start = time.perf_counter()

    def skipped(self, label: str):
        """Record that a stage's work was found already done (reported as 'skipped')."""
        if self.enabled:
            self._close()
            self.timings.setdefault("skipped", []).append(label)

    def _close(self):
        if self._label is not None:
            wp.synchronize_device(self.device)
            elapsed = (time.perf_counter() - self._start) * 1e3
            self.timings[self._label] = self.timings.get(self._label, 0.0) + elapsed
            self._label = None

    def finish(self) -> dict:
        """Close the running stage and return the timings with their ``total`` and ``skipped``
        (empty when disabled)."""
        if self.enabled:
            self._close()
            # Always there, empty when nothing was skipped: where it came and went with the
            # schedule (the CPU's depth-first emission skips bbox, the treelet passes do not),
            # ``timings["skipped"]`` raised a KeyError on one device and not on the other.
            self.timings.setdefault("skipped", [])
            # A second call must not count the first one's total in.
            self.timings["total"] = sum(v for k, v in self.timings.items() if k not in ("skipped", "total"))
        return self.timings


class HlbvhPipeline:
    """The HLBVH build of Pantaleoni & Luebke (HPG 2010): the primitive sort of their section 3.1
    (Fig. 1) and the hierarchy emission of section 3.2 (Fig. 4), one method per stage, and the
    scratch buffers for one primitive count, allocated once and reused by every build."""

    #: The arrays a `Bvh` takes over from a build (`api.bvh_from_pipeline`).
    OUTPUTS = ("node_lowers", "node_uppers", "node_left", "node_right", "node_parent", "node_begin", "node_end",
               "node_count", "sorted_prim_ids")

    @classmethod
    def one_shot(cls, num_prims: int, config: BuildConfig, device, prim_lowers: wp.array, prim_uppers: wp.array):
        """A pipeline for one build over the caller's boxes: the one the previous one-shot build
        of this class, size, config and device gave back (`memory.ScratchCache`), with fresh
        outputs, else a new one. Hand it back with `give_back` once its outputs are in a `Bvh`."""
        device = wp.get_device(device)
        pipe = memory.take_scratch((cls, num_prims, config, device.alias))
        if pipe is None:
            return cls(num_prims, config, device, prim_lowers, prim_uppers)
        pipe.renew_outputs()
        pipe.prim_lowers, pipe.prim_uppers = prim_lowers, prim_uppers
        return pipe

    def give_back(self):
        """Keep this pipeline's scratch for the next `one_shot` build; its outputs now belong to a
        `Bvh` and are replaced before the pipeline builds again."""
        self.prim_lowers = self.prim_uppers = None
        # Views over the boxes and over the tree's ids, which now belong to the caller.
        self._slices = {}
        self.sweep_parts = None
        memory.give_back_scratch((type(self), self.num_prims, self.config, self.device.alias), self,
                                 self.held_bytes())

    def held_bytes(self) -> int:
        """Bytes of the arrays this pipeline holds (its outputs included)."""
        return memory.array_bytes(self)

    def renew_outputs(self):
        """Replace the output arrays (`OUTPUTS`) with fresh ones; the old ones stay with the `Bvh`
        that holds them."""
        for name in self.OUTPUTS:
            old = getattr(self, name)
            setattr(self, name, memory.empty(old.shape, dtype=old.dtype, device=self.device))

    def __init__(self, num_prims: int, config: BuildConfig, device, prim_lowers: wp.array | None = None,
                 prim_uppers: wp.array | None = None):
        if num_prims < 1:
            raise ValueError("HLBVH needs at least one primitive")
        self.num_prims = n = num_prims
        self.config = config
        self.device = device = wp.get_device(device)
        self.coarse_bits = config.resolved_coarse_bits(n)
        self.emission = config.resolved_emission(device)
        # Recorded launches (`hlbvh_warp.launches`), set by a per-frame `Builder`; None: plain ones.
        self.launches = None
        num_node_slots = 2 * n - 1
        stride = (1 << config.planes_per_pass) - 1

        def ints(count):
            return memory.empty(count, dtype=wp.int32, device=device)

        self.scene_bounds = wp.empty(2, dtype=wp.vec3, device=device)
        # A NumPy view of the CPU's bounds, made once: the frame's overflow check reads six floats.
        self.scene_bounds_host = self.scene_bounds.numpy() if self.device.is_cpu else None
        # The CPU's bounds pass on several cores: each slice reduces into its own pair (atomics on
        # the CPU device are not atomic across threads), combined in order after.
        self.partial_bounds = wp.empty(2 * 64, dtype=wp.vec3, device=device)
        self.partial_bounds_views = [self.partial_bounds[2 * j : 2 * j + 2] for j in range(64)]
        self.morton_codes = ints(n)
        self.coarse_codes = ints(n)
        # Run-length encoding and the radix sort, whose buffers need 2x the key count.
        self.run_codes = ints(2 * n)
        self.run_ids = ints(2 * n)
        self.run_lengths = ints(n)
        self.run_starts = ints(n)
        self.run_count = ints(1)
        self.out_of_order = ints(1)
        self.sampled_breaks = ints(1)
        self.prim_count = wp.full(1, n, dtype=wp.int32, device=device)
        self.sorted_run_lengths = ints(n)
        self.sorted_run_offsets = ints(n)
        self.sorted_codes = ints(2 * n)
        self.sorted_prim_ids = ints(2 * n)
        # What each input position stands for, carried into the sorted ids (`set_input_ids`);
        # empty: the position itself.
        self.no_input_ids = wp.empty(0, dtype=wp.int32, device=device)
        self.input_ids = self.no_input_ids
        # Voxel sort.
        self.voxel_flags = ints(n)
        self.voxel_index = ints(n)
        self.voxel_starts = ints(n)
        self.voxel_count = ints(1)
        self.block_flags = ints(n)
        self.block_index = ints(n)
        self.block_starts = ints(n)
        self.block_count = ints(1)
        # Blocks the voxel sort had to sort: one counter per slice of blocks run side by side.
        self.blocks_sorted = ints(64)
        self.blocks_sorted_views = [self.blocks_sorted[j : j + 1] for j in range(self.blocks_sorted.shape[0])]
        self.scratch_codes = ints(n)
        self.scratch_ids = ints(n)
        # Treelet emission (Fig. 4): 8 + 2^p ints per primitive (64 bytes at p = 3) that only the
        # treelet passes read. The depth-first schedule, the CPU's default, emits the same splits
        # from the sorted codes alone, so there the passes' scratch is not allocated.
        treelet = self.emission == "treelets"
        for name, count in (("head_to_node", n), ("head_to_end", n), ("head_flags", n), ("segment_id", n),
                            ("segment_heads", n), ("segment_ends", n), ("segment_nodes", n), ("segment_count", 1),
                            ("split_pos", n * stride), ("split_count", n), ("split_offset", n), ("max_segment", 1)):
            setattr(self, name, ints(count) if treelet else None)
        # The tree itself.
        # A one-shot build reads the caller's boxes in place (the pipeline never writes them
        # unless asked to compute triangle bounds); a `Builder` owns its own.
        if prim_lowers is not None:
            self.prim_lowers, self.prim_uppers = prim_lowers, prim_uppers
        else:
            self.prim_lowers = memory.empty(n, dtype=wp.vec3, device=device)
            self.prim_uppers = memory.empty(n, dtype=wp.vec3, device=device)
        # The depth-first emission reads the primitive boxes in tree order (`emit_depth_first`).
        if self.emission == "depth_first":
            self.leaf_lowers = memory.empty(n, dtype=wp.vec3, device=device)
            self.leaf_uppers = memory.empty(n, dtype=wp.vec3, device=device)
        # Node ranges a refit may sweep side by side, from the last depth-first emission that ran
        # its seeds side by side: (first node below the top, [(first, stop) per run]); else None.
        self.sweep_parts = None
        self.node_lowers = memory.empty(num_node_slots, dtype=wp.vec3, device=device)
        self.node_uppers = memory.empty(num_node_slots, dtype=wp.vec3, device=device)
        self.node_left = ints(num_node_slots)
        self.node_right = ints(num_node_slots)
        self.node_parent = ints(num_node_slots)
        self.node_begin = ints(num_node_slots)
        self.node_end = ints(num_node_slots)
        self.node_visits = ints(num_node_slots)
        self.node_count = ints(1)
        # The depth-first emission's one seed: the root segment [0, N).
        self.root_seed_start = wp.zeros(1, dtype=wp.int32, device=device)
        self.root_seed_count = wp.full(1, 1, dtype=wp.int32, device=device)
        # Stands in for the node costs of an emission that does not compute them.
        self.empty_cost = wp.empty(1, dtype=wp.float64, device=device)
        # The parallel depth-first emission: the top of the tree cut into seeds, a counter per run.
        self.top_seed_starts = wp.zeros(treelets.MAX_TOP_SEEDS, dtype=wp.int32, device=device)
        self.top_seed_ends = wp.zeros(treelets.MAX_TOP_SEEDS, dtype=wp.int32, device=device)
        self.top_seed_count = wp.zeros(1, dtype=wp.int32, device=device)
        self.emit_counters = wp.zeros(64, dtype=wp.int32, device=device)
        self.emit_counter_views = [self.emit_counters[j : j + 1] for j in range(self.emit_counters.shape[0])]
        self.sync_free = False
        # The CPU's chunked passes cut into slices for its cores (`_cpu_slices`), made on first use.
        self._slices = {}
        # The global sort's two halves on the CPU's cores (`global_sort`), made on first use.
        self._sort_halves = None

    # ------------------------------------------------------------------ stages
    def _launch(self, kernel, dim, inputs):
        if self.launches is not None:
            self.launches.launch(kernel, dim, inputs)
        else:
            wp.launch(kernel, dim=dim, inputs=inputs, device=self.device)

    def compute_triangle_bounds(self, vertices: wp.array, faces: wp.array, lowers: wp.array | None = None,
                                uppers: wp.array | None = None):
        """Triangle boxes (into `prim_lowers`/`prim_uppers` unless given), and in the same pass the
        scene's centroid bounds that `compute_morton_codes(bounds_ready=True)` then uses."""
        lowers = self.prim_lowers if lowers is None else lowers
        uppers = self.prim_uppers if uppers is None else uppers
        if self.config.morton_bounds is not None:
            self.compute_triangle_boxes(vertices, faces, lowers, uppers)
            self._set_fixed_bounds()
            return
        kernel = morton.triangle_bounds_centroids_cpu_kernel if self.device.is_cpu \
            else morton.triangle_bounds_centroids_kernel
        self._reduce_centroid_bounds(kernel, [vertices, faces, lowers, uppers], per_prim=(1, 2, 3))
        if self.device.is_cpu and not self.grid_within_overflow_bound():
            # A centre may have overflowed in the CPU kernel's plain expression: the bounds
            # again, from the boxes, with `box_centroid` (coordinates past 1.7e38 only).
            self._reduce_centroid_bounds(morton.centroid_bounds_kernel, [lowers, uppers], per_prim=(0, 1))

    def grid_within_overflow_bound(self) -> bool:
        """Whether the CPU's `scene_bounds` lie within +-`CENTROID_OVERFLOW_BOUND` on every axis
        (NaN bounds do not), where the plain centres of its own kernels cannot overflow."""
        # Six Python floats: NumPy's ufuncs on this view cost 20 us a frame, the list 2.
        bound = CENTROID_OVERFLOW_BOUND
        return all(-bound < x < bound for x in self.scene_bounds_host.ravel().tolist())

    def compute_triangle_boxes(self, vertices: wp.array, faces: wp.array, lowers: wp.array | None = None,
                               uppers: wp.array | None = None):
        """Triangle boxes alone (into `prim_lowers`/`prim_uppers` unless given): a refit, or a build
        over a fixed Morton grid, needs no centroid bounds. On the CPU, chunks of triangles per
        thread (`morton.triangle_bounds_cpu_kernel`), in slices side by side on several cores
        from `PARALLEL_BOUNDS_MIN_PRIMS` triangles; the same boxes to the bit either way."""
        n = self.num_prims
        lowers = self.prim_lowers if lowers is None else lowers
        uppers = self.prim_uppers if uppers is None else uppers
        if not self.device.is_cpu:
            self._launch(morton.triangle_bounds_kernel, n, [vertices, faces, lowers, uppers])
            return
        chunk = CPU_REDUCTION_CHUNK
        num_chunks = (n + chunk - 1) // chunk
        threads = min(threads_module.resolved_threads(self.config, self.device), num_chunks)
        if threads > 1 and n >= PARALLEL_BOUNDS_MIN_PRIMS:
            parts = self._cpu_slices("boxes", threads, chunk, [vertices, faces, lowers, uppers], per_prim=(1, 2, 3))
            threads_module.launch_parts(morton.triangle_bounds_cpu_kernel, self.device, parts, threads)
            return
        self._launch(morton.triangle_bounds_cpu_kernel, num_chunks, [n, chunk, vertices, faces, lowers, uppers])

    def compute_centroid_bounds(self):
        """The scene's centroid bounds from `prim_lowers` / `prim_uppers` (or the fixed grid of
        ``BuildConfig.morton_bounds``), which `compute_morton_codes(bounds_ready=True)` then uses:
        boxes given as such, where `compute_triangle_bounds` reduces them while computing the boxes."""
        if self.config.morton_bounds is not None:
            self._set_fixed_bounds()
        else:
            self._reduce_centroid_bounds(morton.centroid_bounds_kernel, [self.prim_lowers, self.prim_uppers],
                                         per_prim=(0, 1))

    def _reduce_centroid_bounds(self, kernel, inputs: list, per_prim: tuple):
        """Reset `scene_bounds`, then launch a chunked centroid reduction `kernel(n, chunk, *inputs,
        scene_bounds)`: chunks of CPU_REDUCTION_CHUNK primitives on the CPU, one per thread on CUDA.
        `per_prim`: the positions in `inputs` of the arrays with one row per primitive.

        On a multi-core CPU, slices of whole chunks side by side, each over views of those arrays
        and into its own pair of `partial_bounds`, combined in order after
        (`morton.combine_bounds_kernel`): the same boxes and the same bounds to the bit."""
        n = self.num_prims
        chunk = CPU_REDUCTION_CHUNK if self.device.is_cpu else 1
        num_chunks = (n + chunk - 1) // chunk
        threads = min(threads_module.resolved_threads(self.config, self.device), num_chunks,
                      len(self.partial_bounds_views))
        if self.device.is_cpu and threads > 1 and n >= PARALLEL_BOUNDS_MIN_PRIMS:
            parts = self._cpu_slices(kernel.key, threads, chunk, inputs, per_prim, self.partial_bounds_views)
            self._launch(morton.reset_partial_bounds_kernel, len(parts), [self.partial_bounds])
            threads_module.launch_parts(kernel, self.device, parts, threads)
            self._launch(morton.combine_bounds_kernel, 1, [self.partial_bounds, len(parts), self.scene_bounds])
            return
        self._launch(morton.reset_bounds_kernel, 1, [self.scene_bounds])
        self._launch(kernel, num_chunks, [n, chunk, *inputs, self.scene_bounds])

    def _cpu_slices(self, name: str, threads: int, chunk: int, inputs: list, per_prim: tuple,
                    per_slice: list | None = None) -> list:
        """The ``(dim, inputs)`` parts of a chunked CPU pass ``kernel(count, chunk, *inputs[, out])``
        over the N primitives cut into up to `threads` slices of whole chunks, for
        `threads_module.launch_parts`: the arrays at the positions `per_prim` (one row per
        primitive) cut to each slice, and slice j given ``per_slice[j]`` last where there is one
        (its own output: atomics on the CPU device are not atomic across threads). Made once per
        set of arrays and kept under `name` (a Builder's arrays stay the same every frame)."""
        key = (tuple(x.ptr if isinstance(x, wp.array) else x for x in inputs), threads, chunk)
        cached = self._slices.get(name)
        if cached is None or cached[0] != key:
            n = self.num_prims
            cuts = [min(chunk * c, n) for c in threads_module.split_bounds((n + chunk - 1) // chunk, threads)]
            parts = []
            for j, (lo, hi) in enumerate(zip(cuts, cuts[1:])):
                args = [x[lo:hi] if i in per_prim else x for i, x in enumerate(inputs)]
                tail = [per_slice[j]] if per_slice is not None else []
                parts.append(((hi - lo + chunk - 1) // chunk, [hi - lo, chunk, *args, *tail]))
            cached = self._slices[name] = (key, parts)
        return cached[1]

    def _set_fixed_bounds(self):
        lower, upper = self.config.morton_bounds
        self._launch(morton.set_bounds_kernel, 1, [self.scene_bounds, wp.vec3(*lower), wp.vec3(*upper)])

    def set_input_ids(self, input_ids: wp.array | None):
        """Have the sort carry ``input_ids[i]`` for input position i (a resorted `Builder` frame:
        the user face each position holds), so that the tree's order names those ids; None: the
        positions themselves."""
        if input_ids is None:
            self.input_ids = self.no_input_ids
            return
        if input_ids.dtype != wp.int32 or input_ids.shape != (self.num_prims,) or input_ids.device != self.device:
            raise ValueError(f"input_ids must be {self.num_prims} int32 on {self.device}")
        self.input_ids = input_ids

    def compute_morton_codes(self, bounds_ready: bool = False, codes: wp.array | None = None):
        """Morton codes of the primitive centroids over the centroid bounds (or the fixed grid)
        into `morton_codes` (or `codes`); `bounds_ready`: `compute_triangle_bounds` has already
        reduced the bounds."""
        n = self.num_prims
        codes = self.morton_codes if codes is None else codes
        if not bounds_ready:
            self.compute_centroid_bounds()
        if not self.device.is_cpu or not self.grid_within_overflow_bound():
            # CUDA, or a CPU grid so wide that a centre may overflow in the CPU kernel's plain
            # expression: the kernel with `box_centroid`.
            self._launch(
                morton.morton_codes_kernel,
                n,
                [self.prim_lowers, self.prim_uppers, self.scene_bounds, self.config.bits_per_axis, codes],
            )
            return
        threads = threads_module.resolved_threads(self.config, self.device)
        chunk = CPU_MORTON_CHUNK
        # Shared by every pipeline on the device, so not among the arrays this one holds.
        spread = morton.spread_table(self.device)
        if threads > 1 and n >= PARALLEL_MIN_PRIMS:
            # Slices side by side on a multi-core CPU.
            inputs = [self.prim_lowers, self.prim_uppers, self.scene_bounds, self.config.bits_per_axis, spread, codes]
            parts = self._cpu_slices("morton", threads, chunk, inputs, per_prim=(0, 1, 5))
            threads_module.launch_parts(morton.morton_codes_cpu_kernel, self.device, parts, threads)
            return
        self._launch(
            morton.morton_codes_cpu_kernel,
            (n + chunk - 1) // chunk,
            [n, chunk, self.prim_lowers, self.prim_uppers, self.scene_bounds, self.config.bits_per_axis,
             spread, codes],
        )

    def run_length_encode(self, sync_free: bool = False) -> int:
        """Run-length encode the codes by their high 3m bits (Pantaleoni & Luebke 2010, section 3.1,
        Fig. 1: the run_heads compaction), with wp.utils.runlength_encode.

        Returns M, the run count, read on the host (it sizes the top-level sort); with
        `sync_free` the count stays on the device and N, its bound, is returned instead.
        """
        n = self.num_prims
        shift = 3 * (self.config.bits_per_axis - self.coarse_bits)
        self._launch(morton.coarse_codes_kernel, n, [self.morton_codes, shift, self.coarse_codes])
        if sync_free:
            wp.utils.runlength_encode(self.coarse_codes, self.run_codes, self.run_lengths, run_count=self.run_count,
                                      value_count=n)
            num_runs = n
        else:
            num_runs = wp.utils.runlength_encode(self.coarse_codes, self.run_codes, self.run_lengths, value_count=n)
            self.run_count.fill_(num_runs)
        # Runs past the count hold stale lengths; an exclusive scan's first M entries ignore them.
        wp.utils.array_scan(self.run_lengths[:num_runs], self.run_starts[:num_runs], inclusive=False)
        return num_runs

    def runs_in_order(self, num_runs: int) -> bool:
        """True when the run codes already ascend (resorted input): the top-level sort has no work."""
        return self._ascending(self.run_count, self.run_codes, num_runs)

    def codes_in_order(self) -> bool:
        """True when the Morton codes already ascend in input order: a resorted frame whose
        primitives kept their order (nothing moved, or a translation, which moves the centroid
        grid with the scene), the paper's "resorting" row of its Table 1. Then the sort has no
        work at all. A moving scene's codes descend within the first few (the CPU's check stops
        there, so it costs nothing)."""
        return self._ascending(self.prim_count, self.morton_codes, self.num_prims)

    def sampled_run_fraction(self) -> float:
        """An estimate of M / N, the runs per primitive the run-length encoding of the input codes
        by their high 3m bits would give (Pantaleoni & Luebke 2010, section 3.1), from
        `RUN_SAMPLES` evenly spaced adjacent pairs (`compress.sample_code_breaks_kernel`), read on
        the host."""
        n = self.num_prims
        samples = min(n - 1, RUN_SAMPLES)
        if samples < 1:
            return 0.0
        self.sampled_breaks.zero_()
        shift = 3 * (self.config.bits_per_axis - self.coarse_bits)
        self._launch(compress.sample_code_breaks_kernel, samples,
                     [self.morton_codes, n, samples, shift, self.sampled_breaks])
        return int(self.sampled_breaks.numpy()[0]) / samples

    def _ascending(self, count: wp.array, codes: wp.array, bound: int) -> bool:
        if self.device.is_cpu:
            # Threads run in sequence there: one scan that stops at the first descent.
            self._launch(compress.find_descent_kernel, 1, [count, codes, self.out_of_order])
        else:
            self.out_of_order.zero_()
            self._launch(compress.flag_descents_kernel, bound, [count, codes, self.out_of_order])
        return int(self.out_of_order.numpy()[0]) == 0

    def top_level_sort(self, num_runs: int, sort: bool = True):
        """The top-level sort of Pantaleoni & Luebke 2010 (section 3.1, Fig. 1): a radix sort of the
        M run codes (3m bits) with their run ids as values; without `sort`, the ids alone (runs
        already in order)."""
        self._launch(compress.iota_kernel, num_runs, [self.run_ids])
        if not sort:
            return
        end_bit = max(3 * self.coarse_bits, 1)
        if num_runs == self.num_prims:
            # Sync-free: sort all N slots; the ones past the device-side run count get the largest
            # key and, the sort being stable, land after every real run.
            self._launch(compress.pad_run_codes_kernel, num_runs, [self.run_count, (1 << end_bit) - 1, self.run_codes])
        wp.utils.radix_sort_pairs(self.run_codes, self.run_ids, num_runs, end_bit=end_bit)

    def run_length_decode(self, num_runs: int):
        """Run-length decoding (Pantaleoni & Luebke 2010, section 3.1, Fig. 1): an exclusive scan of
        the sorted run lengths, then every run expanded in sorted order, codes and ids."""
        self._launch(
            compress.gather_run_lengths_kernel,
            num_runs,
            [self.run_count, self.run_ids, self.run_lengths, self.sorted_run_lengths],
        )
        wp.utils.array_scan(self.sorted_run_lengths[:num_runs], self.sorted_run_offsets[:num_runs], inclusive=False)
        args = [self.run_count, self.run_ids, self.run_starts, self.run_lengths, self.sorted_run_offsets,
                self.morton_codes, self.input_ids, self.sorted_prim_ids, self.sorted_codes]
        threads = threads_module.resolved_threads(self.config, self.device)
        if threads > 1 and self.num_prims >= PARALLEL_MIN_PRIMS and not self.sync_free:
            # On a multi-core CPU: slices of the runs side by side (they write disjoint ranges).
            cuts = threads_module.split_bounds(num_runs, threads)
            parts = [(hi - lo, args + [lo]) for lo, hi in zip(cuts, cuts[1:])]
            threads_module.launch_parts(compress.decompress_runs_kernel, self.device, parts, threads)
            return
        self._launch(compress.decompress_runs_kernel, num_runs, args + [0])

    def voxel_sort(self, num_runs: int):
        """The voxel sort (Pantaleoni & Luebke 2010, section 3.1): group voxel segments into blocks
        of about ``block_capacity`` primitives and sort every block by its codes in one launch."""
        n = self.num_prims
        self._launch(compress.voxel_head_flags_kernel, num_runs, [self.run_count, self.run_codes, self.voxel_flags])
        wp.utils.array_scan(self.voxel_flags[:num_runs], self.voxel_index[:num_runs], inclusive=True)
        self._launch(
            block_sort.compact_voxel_starts_kernel,
            num_runs,
            [self.run_count, self.voxel_flags, self.voxel_index, self.sorted_run_offsets, self.voxel_starts,
             self.voxel_count],
        )
        self._launch(
            block_sort.block_head_flags_kernel,
            num_runs,
            [self.voxel_count, self.voxel_starts, self.config.block_capacity, self.block_flags],
        )
        wp.utils.array_scan(self.block_flags[:num_runs], self.block_index[:num_runs], inclusive=True)
        self._launch(
            block_sort.compact_block_starts_kernel,
            num_runs,
            [self.voxel_count, self.block_flags, self.block_index, self.voxel_starts, self.block_starts,
             self.block_count],
        )
        self.blocks_sorted.zero_()
        args = [n, 3 * (self.config.bits_per_axis - self.coarse_bits), self.block_count, self.block_starts,
                self.sorted_codes, self.sorted_prim_ids, self.scratch_codes, self.scratch_ids]
        threads = min(threads_module.resolved_threads(self.config, self.device), self.blocks_sorted.shape[0])
        if threads > 1 and n >= PARALLEL_MIN_PRIMS and not self.sync_free:
            # On a multi-core CPU: slices of blocks cut at about equal primitive counts (the block
            # starts are read on the host, free there), side by side, each with its own counter.
            num_blocks = int(self.block_count.numpy()[0])
            starts = self.block_starts.numpy()[:num_blocks]
            cuts = [0] + [int(np.searchsorted(starts, n * j // threads)) for j in range(1, threads)] + [num_blocks]
            parts = [(hi - lo, args + [self.blocks_sorted_views[j], lo])
                     for j, (lo, hi) in enumerate(zip(cuts, cuts[1:])) if hi > lo]
            threads_module.launch_parts(block_sort.block_sort_kernel, self.device, parts, threads)
            return
        self._launch(block_sort.block_sort_kernel, num_runs, args + [self.blocks_sorted, 0])

    def blocks_were_sorted(self) -> bool:
        """Whether the last voxel sort had any block to sort (read on the host)."""
        return int(self.blocks_sorted.numpy().sum()) > 0

    def global_sort(self, sort: bool = True):
        """The LBVH baseline (Lauterbach et al. 2009; the LBVH column of Pantaleoni & Luebke 2010,
        Table 1): one radix sort over all 3n bits; without `sort`, the codes and ids copied as they
        are (input already in order). On a multi-core CPU the two halves of the codes are sorted
        side by side and merged (`_global_sort_halves`), with the same result."""
        n = self.num_prims
        threads = threads_module.resolved_threads(self.config, self.device)
        if sort and threads > 1 and n >= PARALLEL_SORT_MIN_PRIMS and SORTS_SIDE_BY_SIDE and not self.sync_free:
            self._global_sort_halves(threads)
            return
        wp.copy(self.sorted_codes, self.morton_codes, count=n)
        if self.input_ids.shape[0] > 0:
            wp.copy(self.sorted_prim_ids, self.input_ids, count=n)
        else:
            self._launch(compress.iota_kernel, n, [self.sorted_prim_ids])
        if sort:
            wp.utils.radix_sort_pairs(self.sorted_codes, self.sorted_prim_ids, n,
                                      end_bit=3 * self.config.bits_per_axis)

    def order_tied_ids(self, timer: StageTimer):
        """After the sort of a build fed in another order than the faces' (`set_input_ids`: a
        resorted `Builder` frame), put the ids of equal codes in face order, as a build from
        scratch has them, so that the tree is that build's (`compress.order_tied_ids_kernel`).
        Builds in face order have them so already and skip it."""
        if self.input_ids.shape[0] == 0:
            return
        timer.stage("tie_order")
        self._launch(compress.order_tied_ids_kernel, self.num_prims,
                     [self.sorted_codes, self.sorted_prim_ids, self.num_prims])

    def _global_sort_halves(self, threads: int):
        """The global sort on two cores: each half of the codes (with its ids) gathered and radix
        sorted in its own thread, then the sorted halves merged into `sorted_codes` /
        `sorted_prim_ids` by Merge Path (Green, McColgan & Yalamanchili 2012; Odeh et al. 2012),
        cut into `threads` parts side by side. The merge takes ties from the first half, so
        codes and ids come out exactly as the stable sort of all N gives them, which the tree
        depends on. Two halves, whatever the thread count: more would need a k-way merge, and
        below `PARALLEL_SORT_MIN_PRIMS` even two do not pay."""
        n = self.num_prims
        bits = 3 * self.config.bits_per_axis
        first_count = n // 2
        second_count = n - first_count
        if self._sort_halves is None:
            # The radix sort needs twice its count of room, the second half its scratch: the
            # halves take run_codes / run_ids whole, which the global sort leaves unused.
            self._sort_halves = [
                (0, first_count, self.run_codes[: 2 * first_count], self.run_ids[: 2 * first_count]),
                (first_count, second_count, self.run_codes[2 * first_count :], self.run_ids[2 * first_count :]),
            ]
            # Loaded here, before the threads: compiled from two threads at once, both wrote the
            # same cache files.
            merge.gather_half_kernel.module.load(self.device, 1)
        codes, input_ids, device = self.morton_codes, self.input_ids, self.device

        # Plain launches in every job: recorded ones made or replayed on worker threads crashed
        # the process (`hlbvh_warp.launches`).
        def sort_half(first, count, half_codes, half_ids):
            wp.launch(merge.gather_half_kernel, count, [codes, input_ids, first, half_codes, half_ids], device=device)
            wp.utils.radix_sort_pairs(half_codes, half_ids, count, end_bit=bits)

        threads_module.run([lambda half=half: sort_half(*half) for half in self._sort_halves], threads)
        parts = [(1, [self.run_codes, self.run_ids, first_count, 2 * first_count, second_count, threads, part,
                      self.sorted_codes, self.sorted_prim_ids]) for part in range(threads)]
        threads_module.launch_parts(merge.merge_halves_kernel, device, parts, threads)

    def _host_count(self, count: wp.array, bound: int) -> int:
        """Launch size for a per-segment stage: the exact count where reading it is free (the CPU
        device shares host memory and has already finished), else the bound, with threads past the
        device-side count returning at once, so CUDA never waits for the host."""
        if self.device.is_cpu and not self.sync_free:
            return int(count.numpy()[0])
        return bound

    def _segment_pass(self) -> int:
        """Fig. 4 bookkeeping: segment_id = scan(head_to_node != -1) and the segment_heads list."""
        n = self.num_prims
        wp.utils.array_scan(self.head_flags, self.segment_id, inclusive=True)
        self._launch(
            treelets.compact_segments_kernel,
            n,
            [n, self.head_flags, self.head_to_node, self.head_to_end, self.segment_id, self.segment_heads,
             self.segment_ends, self.segment_nodes, self.segment_count],
        )
        return self._host_count(self.segment_count, n)

    def _emit(self, num_segments: int, shift: int, planes: int, stride: int, median: int):
        """Count each segment's valid splits, scan them for offsets, emit the treelets."""
        leaf = self.config.max_leaf_size
        walk = [
            self.sorted_codes,
            self.segment_heads,
            self.segment_ends,
            self.segment_nodes,
            self.segment_count,
            self.split_pos,
        ]
        heads_and_nodes = [
            self.head_to_node,
            self.head_to_end,
            self.head_flags,
            self.node_left,
            self.node_right,
            self.node_parent,
            self.node_begin,
            self.node_end,
        ]
        self._launch(
            treelets.count_splits_kernel,
            num_segments,
            [shift, planes, stride, median, leaf, *walk, self.split_count, *heads_and_nodes],
        )
        wp.utils.array_scan(self.split_count[:num_segments], self.split_offset[:num_segments], inclusive=False)
        self._launch(
            treelets.emit_treelets_kernel,
            num_segments,
            [shift, planes, stride, median, leaf, *walk, self.split_count, self.split_offset, self.node_count,
             *heads_and_nodes],
        )
        self._launch(
            treelets.advance_node_count_kernel,
            1,
            [self.segment_count, self.split_count, self.split_offset, self.node_count],
        )

    def emit_hierarchy(self, top_bit: int):
        """Treelet passes over the bit planes [0, top_bit), p planes at a time, MSB first:
        the hierarchy emission of Pantaleoni & Luebke 2010 (section 3.2, Fig. 4)."""
        n = self.num_prims
        p = self.config.planes_per_pass
        stride = (1 << p) - 1
        hi = top_bit
        while hi > 0:
            planes = min(p, hi)
            shift = hi - planes
            num_segments = self._segment_pass()
            self._launch(
                treelets.mark_splits_kernel,
                n,
                [
                    shift,
                    planes,
                    stride,
                    self.sorted_codes,
                    self.segment_id,
                    self.segment_heads,
                    self.segment_ends,
                    self.split_pos,
                ],
            )
            self._emit(num_segments, shift, planes, stride, 0)
            hi = shift

    def split_exhausted_segments(self):
        """Segments whose codes are all equal (duplicates, bits exhausted): index-median passes."""
        n = self.num_prims
        leaf = self.config.max_leaf_size
        stride = (1 << self.config.planes_per_pass) - 1
        num_segments = self._segment_pass()
        self.max_segment.zero_()
        self._launch(
            treelets.max_segment_size_kernel,
            num_segments,
            [self.segment_heads, self.segment_ends, self.segment_count, self.max_segment],
        )
        # The one host read of the hierarchy stage: how many halvings the largest segment needs.
        # Sync-free builds assume the worst, a segment of all N primitives; passes with nothing
        # left to split cost a launch each and change nothing.
        size = n if self.sync_free else int(self.max_segment.numpy()[0])
        passes = 0
        while size > leaf:
            size = (size + 1) // 2
            passes += 1
        for k in range(passes):
            if k > 0:
                num_segments = self._segment_pass()
            self._launch(
                treelets.mark_median_splits_kernel,
                num_segments,
                [leaf, stride, self.segment_heads, self.segment_ends, self.segment_count, self.split_pos],
            )
            self._emit(num_segments, 0, 1, stride, 1)

    def emit_depth_first(self, seed_starts: wp.array | None = None, seed_count: wp.array | None = None,
                         first_seed_node: int = 0, num_seeds: int = 1, node_cost: wp.array | None = None,
                         costs: tuple | None = None):
        """The depth-first schedule of the emission (``BuildConfig.emission``): one thread per
        seed segment (default: the root, [0, N)) emits its whole subtree with every box, and with
        `node_cost` given, every node's SAH cost, priced with ``costs = (T1, T2)`` (default the
        config's). The splits, and so the tree, are those of the
        treelet passes of Pantaleoni & Luebke 2010 (section 3.2); the schedule is this library's,
        for Warp's CPU device. With seeds given, the caller has set `node_count` past the seeds'
        nodes and links their parents afterwards.

        On a multi-core CPU (``BuildConfig.cpu_threads``) with one primitive per leaf, the seeds
        are cut into runs of about equal primitive counts emitted side by side: a seed of k
        primitives has exactly 2k - 2 nodes below its root, so every run's node ids are known
        before it starts and no counter is shared. The top of the tree is split first into seeds of
        at most N / (4 threads) primitives (`treelets.split_top_kernel`): the root's two halves
        alone can be far from equal (65% / 35% on the bunny)."""
        n = self.num_prims
        cfg = self.config
        threads = min(threads_module.resolved_threads(cfg, self.device), self.emit_counters.shape[0])
        parallel = threads > 1 and cfg.max_leaf_size == 1 and n >= PARALLEL_MIN_PRIMS
        top_split = False
        self.sweep_parts = None
        if seed_starts is None:
            seed_starts, seed_count, first_seed_node, num_seeds = self.root_seed_start, self.root_seed_count, 0, 1
            if parallel:
                # Seeds of at most an eighth of the primitives per two threads: runs of whole seeds
                # then come within about that of an equal share.
                self._launch(treelets.split_top_kernel, 1,
                             [n, max(n // (4 * threads), 1), self.sorted_codes, self.node_left, self.node_right,
                              self.node_parent, self.node_begin, self.node_end, self.top_seed_starts,
                              self.top_seed_ends, self.top_seed_count])
                top_seeds = int(self.top_seed_count.numpy()[0])
                if top_seeds > 1:
                    seed_starts, seed_count, num_seeds = self.top_seed_starts, self.top_seed_count, top_seeds
                    first_seed_node = top_seeds - 1
                    top_split = True
            self.node_count.fill_(first_seed_node + num_seeds)
        serial = int(self.device.is_cpu)
        # On the CPU each seed gathers its own boxes as it starts (the kernel's `gather_boxes`):
        # a separate gather was one more launch, and on several cores one more handoff
        # between threads for 0.3 ms of work.
        if not serial:
            self.gather_leaf_boxes()
        shared = [n, seed_starts, seed_count, first_seed_node, cfg.max_leaf_size, self.sorted_codes,
                  self.leaf_lowers, self.leaf_uppers, serial, self.sorted_prim_ids, self.prim_lowers,
                  self.prim_uppers]
        t_traversal, t_intersect = costs if costs is not None else (cfg.sah_traversal_cost, cfg.sah_intersection_cost)
        tail = [self.node_left, self.node_right, self.node_parent, self.node_begin, self.node_end, self.node_lowers,
                self.node_uppers, int(node_cost is not None), wp.float64(t_traversal), wp.float64(t_intersect),
                node_cost if node_cost is not None else self.empty_cost]
        if not parallel or num_seeds < 2:
            self._launch(treelets.emit_depth_first_kernel, num_seeds, shared + [self.node_count] + tail + [0, serial])
            return
        # Runs of seeds with about n / threads primitives each; run j allocates from its own counter.
        first_free = int(self.node_count.numpy()[0])
        # Python lists and `bisect`: NumPy's calls on a handful of seeds cost more than the search.
        starts = seed_starts.numpy()[:num_seeds].tolist()
        cuts = [bisect.bisect_left(starts, j * (n / threads)) for j in range(1, threads)]
        bounds = sorted({0, *cuts, num_seeds})
        counters = self.emit_counters.numpy()
        jobs, lows = [], []
        for j, (s0, s1) in enumerate(zip(bounds[:-1], bounds[1:])):
            # Seeds before s0 hold starts[s0] primitives and own 2 * starts[s0] - 2 * s0 nodes.
            low = first_free + 2 * starts[s0] - 2 * s0
            counters[j] = low
            lows.append(low)
            counter = self.emit_counter_views[j]
            jobs.append(lambda s0=s0, s1=s1, counter=counter: self._launch(
                treelets.emit_depth_first_kernel, s1 - s0, shared + [counter] + tail + [s0, serial]))
        threads_module.run(jobs, threads)
        end = first_free + 2 * (n - starts[0]) - 2 * num_seeds
        self.node_count.fill_(end)
        # Each run's nodes (its seeds' descendants, allocated from its own counter) have their
        # children in that run: a refit can sweep the runs side by side, then the nodes above
        # (the top of the tree, or hlbvh_sah's cluster tree, and the seeds' roots).
        self.sweep_parts = (first_free, list(zip(lows, lows[1:] + [end])))
        if top_split:
            self._launch(treelets.finish_top_kernel, 1,
                         [self.top_seed_count, self.node_left, self.node_right, self.node_parent, self.node_lowers,
                          self.node_uppers])

    def gather_leaf_boxes(self):
        """The primitive boxes in tree order (`leaf_lowers`/`leaf_uppers`) for CUDA's depth-first
        walk, which then reads them in order (see `bounds.gather_boxes_kernel` for the measure);
        the CPU's walk gathers each seed's boxes itself."""
        self._launch(bounds.gather_boxes_kernel, self.num_prims,
                     [self.sorted_prim_ids, self.prim_lowers, self.prim_uppers, self.leaf_lowers, self.leaf_uppers])

    def compute_node_bounds(self):
        """Boxes of all nodes bottom-up (`compute_bounds`): the "bbox computation" of Pantaleoni &
        Luebke 2010, Table 2."""
        compute_bounds(
            self.device,
            self.node_count,
            self.node_left,
            self.node_right,
            self.node_parent,
            self.node_begin,
            self.node_end,
            self.sorted_prim_ids,
            self.prim_lowers,
            self.prim_uppers,
            self.node_visits,
            self.node_lowers,
            self.node_uppers,
            launch=self._launch,
        )

    # ------------------------------------------------------------ orchestrator
    def compute_codes(self, timer: StageTimer, inputs_ready: str = "boxes"):
        """The Morton codes, unless the caller has them: ``inputs_ready`` is what it has already
        computed: ``"boxes"``; ``"bounds"`` (and the centroid bounds, `compute_triangle_bounds`);
        ``"codes"`` (and the Morton codes, as a resorted `Builder` frame does while gathering)."""
        if inputs_ready not in ("boxes", "bounds", "codes"):
            raise ValueError(f"inputs_ready must be 'boxes', 'bounds' or 'codes', got {inputs_ready!r}")
        # Morton codes of the primitive centroids over the centroid bounds (n bits per axis).
        if inputs_ready != "codes":
            timer.stage("morton")
            self.compute_morton_codes(bounds_ready=inputs_ready == "bounds")

    def sort_codes(self, timer: StageTimer, sync_free: bool = False, need_voxels: bool = False) -> int:
        """HLBVH's primitive sort (Pantaleoni & Luebke 2010, section 3.1, Fig. 1): run-length
        encoding by the high 3m bits, compress-sort-decompress, the voxel sort; skips the sorts
        whose work is already done, and on the CPU the encoding too where a sample of the codes says
        the runs will not compress (`sampled_run_fraction`). Returns M, the run count (its bound N
        with `sync_free`, or when nothing was encoded). `need_voxels`: the caller reads
        the voxel segments (`voxel_starts`, the SAH-optimized build's clusters)."""
        sort_stages = ("run_length_encode", "top_level_sort", "run_length_decode", "voxel_sort")
        if self.device.is_cpu and not sync_free and not need_voxels:
            # Codes already in order (a resorted frame in which nothing changed order): no sort,
            # the input is the sorted order. On the CPU the check reads the codes up to their
            # first descent. On CUDA it would be a pass over N and a wait for the host in every
            # one-shot build (a CUDA Builder's rebuilds keep their counts on the device anyway).
            timer.stage("order_check")
            if self.codes_in_order():
                self.global_sort(sort=False)
                for stage in sort_stages:
                    timer.skipped(stage)
                return self.num_prims
            # Runs that a sample says will not compress: the encoding would only confirm it (a
            # pass over N: 0.56 ms of a 7.3 ms frame of the exploding armadillo here), so the
            # global sort runs at once. Near the limit the two sorts cost about the same, which
            # is where the sample's error can pick the other one; the order is the same.
            limit = self.config.global_sort_runs
            if limit < 1.0 and self.sampled_run_fraction() > limit:
                timer.stage("global_sort")
                self.global_sort()
                for stage in sort_stages:
                    timer.skipped(stage)
                return self.num_prims
        # Run-length encode the codes by their high 3m bits: M runs of one coarse voxel each.
        timer.stage("run_length_encode")
        num_runs = self.run_length_encode(sync_free)
        if not sync_free and not need_voxels and num_runs > self.config.global_sort_runs * self.num_prims:
            # About one run per primitive (fragments scattered at random): compress-sort-decompress
            # has nothing to compress, and sorting the runs, expanding them and sorting the blocks
            # cost more than the one radix sort they stand in for. That sort gives the same
            # order: both are stable sorts of the full codes.
            timer.stage("global_sort")
            self.global_sort()
            for stage in sort_stages[1:]:
                timer.skipped(stage)
            return num_runs
        # Compress-sort-decompress: sort the M run codes, then expand the runs in order.
        # Runs already in order (resorted input) need no sort.
        sort = sync_free or not self.runs_in_order(num_runs)
        timer.stage("top_level_sort")
        self.top_level_sort(num_runs, sort)
        if not sort:
            timer.skipped("top_level_sort")
        timer.stage("run_length_decode")
        self.run_length_decode(num_runs)
        # Sort each block of voxels by the low 3(n - m) bits; blocks in order are left alone.
        timer.stage("voxel_sort")
        self.voxel_sort(num_runs)
        if timer.enabled and not self.blocks_were_sorted():
            timer.skipped("voxel_sort")
        return num_runs

    def build(self, method: str = "hlbvh", timer: StageTimer | None = None, sync_free: bool = False,
              inputs_ready: str = "boxes"):
        """Run the pipeline on `prim_lowers` / `prim_uppers` (already filled); returns the timings.

        The stages of Pantaleoni & Luebke 2010: Morton codes, the primitive sort (section 3.1), the
        hierarchy emission (section 3.2) and the node boxes.

        Args:
            method: ``"hlbvh"`` or ``"lbvh"`` (one global radix sort, the paper's Table 1 baseline,
                after Lauterbach et al. 2009).
            timer: a `StageTimer`; stages are timed only when it is enabled.
            sync_free: keep every count on the device (launches sized by their bounds) so that the
                build never waits for the device and can be captured in a CUDA graph.
            inputs_ready: what the caller has already computed: ``"boxes"``; ``"bounds"`` (and
                the centroid bounds, `compute_triangle_bounds`); ``"codes"`` (and the Morton
                codes, as a resorted `Builder` frame does while gathering).
        """
        n = self.num_prims
        timer = timer or StageTimer(self.device, False)
        bits = 3 * self.config.bits_per_axis
        self.sync_free = sync_free
        self.compute_codes(timer, inputs_ready)
        if method == "hlbvh":
            self.sort_codes(timer, sync_free)
        elif method == "lbvh":
            timer.stage("global_sort")
            self.global_sort()
        else:
            raise ValueError(f"unknown pipeline method {method!r}")
        self.order_tied_ids(timer)

        # Emit the hierarchy by treelets, p bit planes per pass, then split what the bits cannot.
        timer.stage("hierarchy")
        if self.emission == "depth_first":
            self.emit_depth_first()
        else:
            self._launch(
                treelets.init_nodes_kernel,
                2 * n - 1,
                [
                    n,
                    self.node_left,
                    self.node_right,
                    self.node_parent,
                    self.node_visits,
                    self.config.max_leaf_size,
                    self.head_to_node,
                    self.head_to_end,
                    self.head_flags,
                    self.node_begin,
                    self.node_end,
                    self.node_count,
                ],
            )
            self.emit_hierarchy(bits)
            self.split_exhausted_segments()

        # Bounding boxes of all nodes, bottom-up (the depth-first emission wrote them as it went).
        if self.emission == "depth_first":
            timer.skipped("bbox")
        else:
            timer.stage("bbox")
            self.compute_node_bounds()
        return timer.finish()


def compute_bounds(device, node_count, node_left, node_right, node_parent, node_begin, node_end, prim_order,
                   prim_lowers, prim_uppers, node_visits, node_lowers, node_uppers, strategy: str | None = None,
                   priced: tuple | None = None, launch=None):
    """Node boxes bottom-up. `strategy`: ``"climb"`` (one thread per leaf climbing with atomic visit
    counters, Karras 2012: parallel, for CUDA) or ``"sweep"`` (one reverse sweep over the nodes, leaves
    boxed as it reaches them: the CPU device runs threads in sequence, and there the sweep does
    the same work without atomics or random parent hops, about 2x faster on a 100k-triangle
    mesh). ``None`` picks by device. ``priced=(t_traversal, t_intersect, cost_sum)``
    (the sweep only) also writes to ``cost_sum[0]`` the sum of every node's SAH term x area, which
    `metrics.cost_from_sum` turns into the tree's SAH cost. ``launch(kernel, dim, inputs)``: how
    to launch (a per-frame caller's recorded launches: packing the fourteen arguments anew was
    most of a small mesh's refit); `wp.launch` on ``device`` by default."""
    device = wp.get_device(device)
    if launch is None:
        def launch(kernel, dim, inputs):
            wp.launch(kernel, dim=dim, inputs=inputs, device=device)
    if strategy is None:
        strategy = "sweep" if device.is_cpu else "climb"
    dim = node_left.shape[0]
    if strategy == "sweep":
        t_traversal, t_intersect, cost_sum = priced if priced is not None else (0.0, 0.0, None)
        launch(bounds.bounds_sweep_kernel, 1,
               [0, -1, 0, node_count, node_left, node_right, node_begin, node_end, prim_order, prim_lowers, prim_uppers,
                int(priced is not None), wp.float64(t_traversal), wp.float64(t_intersect), node_lowers, node_uppers,
                cost_sum])
        return
    if strategy != "climb":
        raise ValueError(f"unknown bounds strategy {strategy!r}")
    if priced is not None:
        raise ValueError("priced bounds need the sweep strategy")
    launch(bounds.reset_visits_kernel, node_visits.shape[0], [node_visits])
    launch(bounds.node_bounds_kernel, dim,
           [node_count, node_left, node_right, node_parent, node_begin, node_end, prim_order, prim_lowers,
            prim_uppers, node_visits, node_lowers, node_uppers])


def refit_bounds(bvh: Bvh, node_visits: wp.array | None = None, strategy: str | None = None):
    """Recompute every node box from the primitive boxes, keeping the topology: a refit, as
    Pantaleoni & Luebke 2010 (section 2.2) describe it. The paper itself always rebuilds, since a
    refit tree degrades as primitives move; this is for callers who choose to refit."""
    if node_visits is None:
        node_visits = wp.empty(bvh.node_left.shape[0], dtype=wp.int32, device=bvh.device)
    compute_bounds(bvh.device, bvh.node_count, bvh.node_left, bvh.node_right, bvh.node_parent, bvh.node_begin,
                   bvh.node_end, bvh.prim_order, bvh.prim_lowers, bvh.prim_uppers, node_visits, bvh.node_lowers,
                   bvh.node_uppers, strategy)
    bvh.invalidate()
