"""Per-frame BVH builds for dynamic scenes: buffers allocated once, reused every frame.

Pantaleoni & Luebke 2010 rebuild a dynamic scene from scratch every frame, feeding the
primitives in the previous frame's BVH order so that the build's input is almost sorted
(resorting, section 2.2). `Builder` does that, and can also refit, or skip a frame, when a
per-frame policy finds the full rebuild unnecessary:

- ``policy="rebuild"``: a full (resorted) rebuild every frame, the paper's setup.
- ``policy="refit"``: recompute the boxes, keep the topology.
- ``policy="auto"``: nothing moved -> no work; small motion -> refit while the SAH cost has
  grown by at most ``sah_growth_limit`` over its lowest value since the last rebuild, for at
  most ``max_refits`` frames in a row; large motion, too much SAH growth (or growth on course
  past the limit by the next refit), or too many refits -> full (resorted) rebuild. A refit
  that fails on its first frame starts a chaotic wait (rebuilds, a refit retried after
  ``max_refits`` frames, twice as long after each retry that fails), whose frames only check
  whether anything moved. Each decision and its reason land in ``Builder.last_report``.

The primitives are a triangle mesh (`Builder.build(vertices, faces)`, then new vertices each
frame) or arbitrary primitives given by their boxes (`Builder.build_from_bounds(lowers, uppers)`,
then new ``bounds=(lowers, uppers)`` each frame: particles, spheres or capsules of a
simulation's broad phase).

``"auto"`` reads values back to the host every frame (the displacement, the SAH cost of the
trees a refit may compare with): it has to, to decide, so its `update` refuses a capture.
``refit`` given device arrays never synchronizes. An ``"hlbvh"`` or ``"lbvh"`` ``rebuild`` on
CUDA runs the pipeline's ``sync_free`` build: it never synchronizes either and can be captured
in a CUDA graph (``wp.ScopedCapture``). Other rebuilds read small counts on the host (the runs,
the resort sample, ``"hlbvh_sah"``'s cluster count) and refuse a capture. A replay runs no
Python: call ``builder.bvh.invalidate()`` after each ``wp.capture_launch``, before host reads of the tree
or ray queries (their host copies and, unless made before the capture, the traversal layout are
refreshed there, not by the graph).
"""

from __future__ import annotations

import collections
import functools
import math
import threading
import time

import numpy as np
import warp as wp

from . import inputs, metrics
from . import threads as threads_module
from .builders import HlbvhSahPipeline
from .bvh import Bvh
from .config import BuildConfig
from .hlbvh import PARALLEL_MIN_PRIMS, HlbvhPipeline, StageTimer, compute_bounds
from .launches import RecordedLaunches
from .kernels import compress, dynamic
from .kernels.bounds import bounds_sweep_kernel

POLICIES = ("rebuild", "refit", "auto")


def _check_policy(policy):
    if not isinstance(policy, str) or policy not in POLICIES:
        raise ValueError(f"policy must be one of {POLICIES}, got {policy!r}")


# After chaotic motion `auto` waits max_refits frames before trying a refit again, twice as long
# after each retry that fails on its first frame, up to this many times max_refits.
MAX_CHAOTIC_BACKOFF = 8
# Vertices per thread of the auto policy's motion measure on the CPU (one atomic per chunk).
MOTION_CHUNK_CPU = 4096
# Vertices (or boxes) a frame of the auto policy's chaotic wait samples before comparing them all.
CHANGE_SAMPLES = 1024
MAX_PRIMS = inputs.MAX_PRIMS
PIPELINE_METHODS = ("hlbvh", "lbvh", "hlbvh_sah")
# Adjacent pairs of the previous tree's order sampled to decide whether resorting pays (the
# estimate of M / N is within about 0.03 (one standard error) of the whole order's).
RESORT_SAMPLES = 256
# The report's reason for the frame after one that raised partway (`Builder._begin_frame`).
UNFINISHED_REASON = "the previous frame raised partway and left its tree unfinished: built from scratch"


def _finite_or_none(cost: float) -> float | None:
    """A tree's SAH cost as the auto policy's reference, or None for a tree boxed over a NaN or
    Inf frame, whose cost would make every later growth NaN and never exceed the limit."""
    return cost if math.isfinite(cost) else None


def _one_call_at_a_time(method):
    """Calls on one `Builder` from several Python threads take turns: a frame rewrites the
    builder's buffers and its tree in place, and two frames at once crashed the process."""

    @functools.wraps(method)
    def locked(self, *args, **kwargs):
        with self._lock:
            self._calls_in_progress += 1
            try:
                return method(self, *args, **kwargs)
            finally:
                self._calls_in_progress -= 1
                # A frame that raised partway leaves its tree half written: the queries refuse it
                # (`bvh.held`) until a frame starts over it (`_frame_writes`). Read, it gave wrong
                # hit ids and a fraction of the pairs. Set as the outermost call ends: a frame's
                # own `sah_cost()` ends while the frame is still writing.
                if self._calls_in_progress == 0 and self.bvh is not None:
                    self.bvh._unfinished = self.frame_unfinished

    return locked


class Builder:
    """BVH builds over a fixed number of primitives (a mesh's triangles, or boxes), reusing every buffer.

    Args:
        num_prims: the number of primitives of every frame: triangles (faces) for `build`, boxes
            for `build_from_bounds`.
        config: `BuildConfig`; defaults when ``None``.
        device: Warp device; the current default device when ``None``.
        method: ``"hlbvh"``, ``"lbvh"`` or ``"hlbvh_sah"`` (SAH-optimized HLBVH, paper 3.3: the
            same sort, the top levels a SAH sweep over the coarse clusters; its rebuilds read
            the cluster count on the host, so only ``"hlbvh"`` and ``"lbvh"`` rebuilds can be
            captured in a CUDA graph).
        resort: feed each rebuild the primitives in the previous tree's order (paper 2.2).
        policy: ``"rebuild"``, ``"refit"`` or ``"auto"`` for `update`.
        sah_growth_limit: ``auto`` rebuilds once a refit tree's SAH cost exceeds the lowest cost
            since the last rebuild by more than this fraction (default 10%), or is on course to
            exceed it by the next refit.
        large_motion: ``auto`` rebuilds without trying a refit when some vertex moved farther
            than this fraction of the scene's diagonal since the previous frame.
        max_refits: ``auto`` rebuilds after this many refit frames in a row even when the refit
            tree's SAH cost holds: a deformation can make a fresh build better while the refit
            tree's cost stays flat, which no measure of the refit tree alone can see.
            Refits forced by `refit` (or made under the ``refit`` policy) count toward it;
            `rebuild` starts the count again.
            Also the number of frames ``auto`` rebuilds without trying a refit after a refit
            failed on its first frame (chaotic motion), doubled after each retry that fails again,
            up to ``MAX_CHAOTIC_BACKOFF`` times.
        timings: synchronize around every stage and record ms per stage in the reports.
        keep_reports: how many of the latest frame reports `reports` keeps (a long animation
            would otherwise grow the list by one dict per frame for as long as it runs).
        record_launches: pack each kernel launch's arguments once and replay the launch every
            frame (`hlbvh_warp.launches`). Safe with builders driven from several Python threads
            at once: a record that could call into a module Warp unloaded (made while another
            thread loaded the same module) is refused, that launch made plainly. Off: every
            launch through `wp.launch`, the same trees at more time per frame. (Calls on one
            builder from several threads take turns either way.)

    Example::

        builder = Builder(len(faces), device="cuda:0")
        bvh = builder.build(vertices, faces)
        for frame in frames:
            report = builder.update(frame_vertices)   # bvh now describes this frame
    """

    def __init__(self, num_prims: int, config: BuildConfig | None = None, device=None, method: str = "hlbvh", *,
                 resort: bool = True, policy: str = "rebuild", sah_growth_limit: float = 0.10,
                 large_motion: float = 0.05, max_refits: int = 8, timings: bool = False, keep_reports: int = 1024,
                 record_launches: bool = True):
        if config is None:
            config = BuildConfig()
        if not isinstance(config, BuildConfig):
            raise ValueError(f"config must be a BuildConfig, got {type(config).__name__}")
        if method not in PIPELINE_METHODS:
            raise ValueError(f"Builder method must be one of {PIPELINE_METHODS}, got {method!r}")
        _check_policy(policy)
        if not sah_growth_limit >= 0.0:
            raise ValueError(f"sah_growth_limit must be >= 0, got {sah_growth_limit}")
        if not large_motion > 0.0:
            raise ValueError(f"large_motion must be > 0, got {large_motion}")
        self.num_prims = n = inputs.count_arg(num_prims, "num_prims", 1)
        if n >= MAX_PRIMS:
            raise ValueError(f"num_prims must be below {MAX_PRIMS} (int32 node ids, 2N - 1 nodes), got {n}")
        # Reentrant: `update` runs `rebuild` or `refit` under the same lock.
        self._lock = threading.RLock()
        self._calls_in_progress = 0
        self.config = config
        self.device = device = wp.get_device(device)
        self.method = method
        self.resort = bool(resort)
        self.policy = policy
        self.sah_growth_limit = float(sah_growth_limit)
        self.large_motion = float(large_motion)
        self.max_refits = inputs.count_arg(max_refits, "max_refits", 0)
        self.refits_since_rebuild = 0
        # SAH growth of the latest refit frame (over the best cost since the last rebuild).
        self.last_growth = 0.0
        self.previous_growth = 0.0
        # Frames left during which `auto` rebuilds without trying a refit (chaotic motion), and
        # how long the next such wait lasts.
        self.chaotic_frames = 0
        self.first_chaotic_wait = max(self.max_refits, 1)
        self.chaotic_wait = self.first_chaotic_wait
        self.timings = bool(timings)
        if method == "hlbvh_sah":
            self.pipeline = pipe = HlbvhSahPipeline(n, config, device)
            # The cluster tree's scratch, for as many clusters as any frame can have.
            pipe.reserve_top_tree()
            # The tree's order (user face ids) is written by the SAH build's join.
            self.prim_order = pipe.prim_order
        else:
            self.pipeline = pipe = HlbvhPipeline(n, config, device)
            self.prim_order = pipe.sorted_prim_ids[:n]
        # Every frame launches the same kernels on the same buffers: record them once.
        pipe.launches = RecordedLaunches(device) if record_launches else None
        # A CUDA rebuild keeps every count on the device, so it never waits and can be captured
        # (not hlbvh_sah's, which reads its cluster count).
        self.sync_free = device.is_cuda and method != "hlbvh_sah"

        self.faces = wp.empty((n, 3), dtype=wp.int32, device=device)
        # The BVH's per-face boxes are the pipeline's input boxes, in the user's face order.
        self.prim_lowers = pipe.prim_lowers
        self.prim_uppers = pipe.prim_uppers
        self.input_order = self.user_codes = None
        self.gather_parts = self.compare_parts = None
        self.keeps_topology = False
        self.may_be_sorted = True
        # Whether `pipe.sorted_codes` holds the sorted codes of the tree now in the node arrays:
        # not before a mesh's first build (they are uninitialized memory then, maybe a recycled
        # block, maybe zeros, which equal the codes of a mesh collapsed to a point).
        self.has_last_codes = False
        # How the latest build was fed: "previous tree" or "faces", and the sampled M / N.
        self.last_input: dict = {}
        if self.resort:
            # The build's input is the previous tree's order: input i is user face input_order[i].
            # The sort carries those face ids, so the tree names user faces with no pass to map
            # them back, and reads the boxes where they were computed.
            self.input_order = wp.empty(n, dtype=wp.int32, device=device)
            self.user_codes = wp.empty(n, dtype=wp.int32, device=device)
            pipe.set_input_ids(self.input_order)
            self.run_breaks = wp.zeros(2, dtype=wp.int32, device=device)
            self.resort_samples = min(n - 1, RESORT_SAMPLES)
            # An hlbvh tree is a function of its sorted codes alone: a frame whose gathered codes
            # all equal the last tree's keeps its topology (`resort_gather_compare_kernel`). Not
            # hlbvh_sah's (its cluster tree prices the boxes), and not on the sync-free path,
            # which reads nothing on the host to choose by.
            self.keeps_topology = method == "hlbvh" and not self.sync_free
            self.codes_changed = wp.zeros(1, dtype=wp.int32, device=device)
            # The gather reads one code at random per primitive: on a multi-core CPU its slices run
            # side by side, each a launch over views made once here.
            threads = threads_module.resolved_threads(config, device)
            if threads > 1 and n >= PARALLEL_MIN_PRIMS:
                cuts = threads_module.split_bounds(n, threads)
                self.gather_parts = [
                    (hi - lo, [self.prim_order[lo:hi], self.user_codes, self.input_order[lo:hi],
                               pipe.morton_codes[lo:hi]])
                    for lo, hi in zip(cuts, cuts[1:])]
                if self.keeps_topology:
                    self.compare_parts = [
                        (hi - lo, [self.prim_order[lo:hi], self.user_codes, pipe.sorted_codes[lo:hi],
                                   self.input_order[lo:hi], pipe.morton_codes[lo:hi], self.codes_changed])
                        for lo, hi in zip(cuts, cuts[1:])]
        self.stats = wp.zeros(2, dtype=wp.float64, device=device)  # max displacement, root diagonal
        # The motion measure's maxima, one per slice of vertices run side by side.
        self.motion_threads = threads_module.resolved_threads(config, device) if device.is_cpu else 1
        self.largest_move = wp.zeros(max(self.motion_threads, 1), dtype=wp.float32, device=device)
        self.largest_move_views = [self.largest_move[j : j + 1] for j in range(self.largest_move.shape[0])]
        # Whether a frame of the auto policy's chaotic wait moved at all (`_load_and_compare`).
        self.frame_changed = wp.zeros(1, dtype=wp.int32, device=device)
        # The sums of a refit's sweeps side by side, one per run and one for the nodes above.
        self.sweep_costs = wp.zeros(pipe.emit_counters.shape[0] + 1, dtype=wp.float64, device=device)
        self._sweep_args = None
        # Scratch of metrics.sah_cost, so the per-frame SAH check allocates nothing.
        self.sah_scratch = wp.empty(metrics.sah_scratch_size(pipe.node_left.shape[0], device), dtype=wp.float64,
                                    device=device)
        # Vertex buffers: allocated by the first `build`, when the vertex count is known.
        self.vertices = None
        # What the builder was set up with: "triangles" (`build`) or "boxes" (`build_from_bounds`).
        self.kind: str | None = None
        # The auto policy's copy of the previous frame, kept only for callers who write a new
        # frame into the builder's buffers in place (`update()` with no argument); also where
        # host input is staged. One per buffer (`_buffers`): allocated by the first build of each kind.
        self.previous_vertices = None
        self.previous_bounds = None
        self.snapshots: list = []
        self.snapshot_valid = False
        # Whether a frame has begun changing the buffers and not finished: one that raised partway
        # (an error in a worker thread, an interrupt) left a half-written tree, and maybe a
        # half-written order (`_begin_frame`).
        self.frame_unfinished = False
        self.bvh: Bvh | None = None
        self.frame = 0
        self.sah_reference = None
        self.last_report: dict = {}
        self.reports: collections.deque = collections.deque(maxlen=inputs.count_arg(keep_reports, "keep_reports", 1))

    # --------------------------------------------------------------- inputs
    @staticmethod
    def _check_points(values, name: str) -> int:
        """Shape and dtype checks only; NaN/Inf and float32-range checks for NumPy input (already on
        the host; device arrays are not read back, see `build_from_bounds`)."""
        if isinstance(values, wp.array):
            if values.dtype in (wp.vec3, wp.vec3d) and values.ndim == 1:
                return values.shape[0]
            if values.dtype in (wp.float32, wp.float64) and values.ndim == 2 and values.shape[1] == 3:
                return values.shape[0]
            # Flat floats, x y z after x y z, as `build` takes them (`inputs.mesh_arrays`).
            if values.dtype in (wp.float32, wp.float64) and values.ndim == 1 and values.shape[0] % 3 == 0:
                return values.shape[0] // 3
            raise ValueError(f"{name} must be a wp.array of vec3 / vec3d, or of float32 / float64 shaped (N, 3) or "
                             f"flat (3N,), got {wp.types.type_repr(values.dtype)} with shape {values.shape}")
        arr = np.asarray(values)
        # Integers as `build` takes them (a voxel grid's corners); booleans and objects are not points.
        if arr.dtype.kind not in "fiu" or arr.ndim != 2 or arr.shape[1] != 3:
            raise ValueError(f"{name} must be numbers of shape (N, 3), got {arr.dtype} {arr.shape}")
        inputs.check_float32_range(arr, name)
        return arr.shape[0]

    def _source(self, values, name: str, rows: int) -> wp.array:
        """A vec3 view of checked `values`: on their own device, or on the host for NumPy input."""
        count = self._check_points(values, name)
        if count != rows:
            raise ValueError(f"{name} has {count} rows, the builder was set up with {rows}")
        if isinstance(values, wp.array):
            double = values.dtype in (wp.vec3d, wp.float64)
            if values.dtype in (wp.float32, wp.float64):
                if not values.is_contiguous:
                    shape = "(N, 3)" if values.ndim == 2 else "flat"
                    raise ValueError(f"{'float64' if double else 'float32'} {shape} {name} must be contiguous")
                values = wp.array(ptr=values.ptr, dtype=wp.vec3d if double else wp.vec3, shape=count,
                                  device=values.device)
            if not double or values.device == self.device:
                # A float64 frame on this device is rounded to float32 as it is loaded (`_copy_frame`).
                return values
            # Float64 on another device: rounded on the host, and checked there like NumPy input.
            values = values.numpy()
            inputs.check_float32_range(values, name)
        host = np.ascontiguousarray(values, dtype=np.float32)
        return wp.array(host, dtype=wp.vec3, device="cpu", copy=False)

    def _buffers(self) -> list:
        """The builder's own copies of a frame's input: the vertices, or the boxes (which are the
        pipeline's input boxes and the BVH's `prim_lowers`/`prim_uppers`)."""
        return [self.vertices] if self.kind == "triangles" else [self.prim_lowers, self.prim_uppers]

    def _frame_sources(self, vertices, bounds) -> list | None:
        """Check one frame's input against what `build` / `build_from_bounds` set up, before any
        state changes. Returns the arrays to load, one per buffer, or None when the frame was
        written into the builder's own buffers in place (nothing given, or those buffers)."""
        if self.kind == "triangles":
            if bounds is not None:
                raise ValueError("this Builder was set up with triangles (build): pass the frame's vertices, "
                                 "not bounds")
            if vertices is None:
                return None
            sources = [self._source(vertices, "vertices", self.vertices.shape[0])]
        else:
            if vertices is not None:
                raise ValueError("this Builder was set up with boxes (build_from_bounds): pass the frame's "
                                 "bounds=(lowers, uppers), not vertices")
            if bounds is None:
                return None
            if not isinstance(bounds, (tuple, list)) or len(bounds) != 2:
                raise ValueError("bounds must be a pair (lowers, uppers)")
            lowers, uppers = bounds
            if not isinstance(lowers, wp.array) and not isinstance(uppers, wp.array):
                # On the host the boxes are checked whole, as `build_from_bounds` does, and come
                # back as contiguous float32: loaded from there with no second pass.
                lo, hi = inputs.bounds_arrays(lowers, uppers)
                if lo.shape[0] != self.num_prims:
                    raise ValueError(f"lowers has {lo.shape[0]} rows, the builder was set up with {self.num_prims}")
                sources = [wp.array(x, dtype=wp.vec3, device="cpu", copy=False) for x in (lo, hi)]
            else:
                sources = [self._source(lowers, "lowers", self.num_prims),
                           self._source(uppers, "uppers", self.num_prims)]
            for name, src, other in (("lowers", sources[0], "prim_uppers"), ("uppers", sources[1], "prim_lowers")):
                # The builder's own buffers swapped: loading the lowers would overwrite the
                # uppers before they were read, and both sides came out as the old uppers.
                if src.ptr == getattr(self, other).ptr:
                    raise ValueError(f"{name} is this Builder's own {other} buffer: pass its buffers in their "
                                     "own places (written in place), or copies")
        if all(src.ptr == buf.ptr for src, buf in zip(sources, self._buffers())):
            return None
        return sources

    def _refuse_host_frame_in_capture(self, sources: list | None):
        """A frame given on the host (NumPy, or a CPU array) while a graph is captured on this
        Builder's device: the graph would hold a copy from memory the caller frees or rewrites
        (a NumPy frame is staged in a temporary array), so every replay would read stale or freed
        memory. Refused before any launch; a device array, or the builder's own buffers written
        in place, can be captured."""
        if sources is None or not self.device.is_capturing:
            return
        for src in sources:
            if src.device != self.device:
                raise RuntimeError(f"a frame on {src.device} cannot be captured in a graph on {self.device}: a replay "
                                   "would copy from memory the capture does not own; pass the frame as an array "
                                   f"on {self.device}, or write it into the builder's buffers")

    def _copy_frame(self, dest: wp.array, source: wp.array):
        """``dest = source``; a float64 source (on this device, see `_source`) is rounded to float32."""
        if source.dtype == wp.vec3:
            wp.copy(dest, source)
        elif self.pipeline.launches is not None:
            # The caller's array, often a new one every frame: swapped into one record.
            self.pipeline.launches.launch(dynamic.round_to_float32_kernel, dest.shape[0], [source, dest], vary=(0,))
        else:
            wp.launch(dynamic.round_to_float32_kernel, dim=dest.shape[0], inputs=[source, dest], device=self.device)

    def _load(self, sources: list | None):
        """Copy into the preallocated buffers: no device allocation on the per-frame path."""
        # Whatever the call, the buffers no longer hold the auto policy's snapshot.
        self.snapshot_valid = False
        if sources is None:
            return
        for src, buf in zip(sources, self._buffers()):
            if src.ptr != buf.ptr:
                self._copy_frame(buf, src)

    def _load_and_measure(self, sources: list | None) -> bool:
        """Load the frame and put the largest displacement since the previous frame (of a vertex,
        or of a box corner) in ``stats[0]``, in one pass (`dynamic.load_and_measure_kernel`).
        Returns False when there is nothing to measure against: the frame was written in place
        and the previous frame left no snapshot."""
        self.pipeline._launch(dynamic.reset_stats_kernel, 1, [self.stats])
        buffers, snapshots = self._buffers(), self.snapshots
        if sources is not None and any(src.ptr == buf.ptr for src, buf in zip(sources, buffers)):
            # Part of the frame (the lowers, say) was written in place: a buffer compared with
            # itself would hide its motion. Load the rest, then measure the frame as written in place.
            for src, buf in zip(sources, buffers):
                if src.ptr != buf.ptr:
                    self._copy_frame(buf, src)
            sources = None
        if sources is None:
            # Written into the builder's buffers by the caller: compare with the snapshot of the
            # previous frame, refreshing it in the same pass. Only callers who write in place pay for one.
            measured = self.snapshot_valid
            if measured:
                self._measure(list(zip(buffers, snapshots)))
            else:
                for buf, snap in zip(buffers, snapshots):
                    wp.copy(snap, buf)
            self.snapshot_valid = True
            return measured
        pairs = []
        for src, buf, snap in zip(sources, buffers, snapshots):
            if src.device != self.device or src.dtype != wp.vec3:
                # NumPy input, another device or float64: staged on this device, as float32, first.
                self._copy_frame(snap, src)
                src = snap
            pairs.append((src, buf))
        self._measure(pairs)
        self.snapshot_valid = False
        return True

    def _measure(self, pairs: list):
        """stats[0] = the largest |source - dest| over every pair of arrays, then dest = source."""
        self.largest_move.zero_()
        used = 1
        for source, dest in pairs:
            slices = self._launch_chunks(dynamic.load_and_measure_kernel, source, dest, self.largest_move_views)
            used = max(used, slices)
        self.pipeline._launch(dynamic.finish_motion_kernel, 1, [self.largest_move, used, self.stats])

    def _launch_chunks(self, kernel, source: wp.array, dest: wp.array, outputs: list) -> int:
        """Launch a load kernel of `dynamic` (``count, chunk, first_chunk, source, dest, out``) over
        chunks of the vertices: on a multi-core CPU slices of chunks side by side, slice j writing
        ``outputs[j]``. Returns the number of slices."""
        count = dest.shape[0]
        chunk = MOTION_CHUNK_CPU if self.device.is_cpu else 1
        num_chunks = (count + chunk - 1) // chunk
        threads = min(self.motion_threads, num_chunks, len(outputs))
        if threads > 1 and count >= PARALLEL_MIN_PRIMS:
            # Slices of chunks side by side on a multi-core CPU, each with its own output (atomics
            # on the CPU device are not atomic across threads): 1.7 ms on two cores for 1.2M
            # vertices against 3.2 ms on one (the plain copy every policy makes: 0.8 ms).
            cuts = threads_module.split_bounds(num_chunks, threads)
            parts = [(hi - lo, [count, chunk, lo, source, dest, outputs[j]])
                     for j, (lo, hi) in enumerate(zip(cuts, cuts[1:]))]
            threads_module.launch_parts(kernel, self.device, parts, threads)
            return threads
        args = [count, chunk, 0, source, dest, outputs[0]]
        if self.pipeline.launches is None:
            wp.launch(kernel, dim=num_chunks, inputs=args, device=self.device)
        else:
            # The source is often the caller's array, a new one every frame: swapped into one
            # record, not recorded anew (each record kept its array alive with the builder).
            self.pipeline.launches.launch(kernel, num_chunks, args, vary=(3,))
        return 1

    def _comparable(self, sources: list | None) -> bool:
        """Whether `_load_and_compare` can take this frame: arrays of this device, float32, none of
        them one of the builder's buffers (those frames are measured against a snapshot)."""
        return sources is not None and all(
            src.device == self.device and src.dtype == wp.vec3 and src.ptr != buf.ptr
            for src, buf in zip(sources, self._buffers()))

    def _load_and_compare(self, sources: list) -> bool:
        """Load the frame and tell whether anything moved since the previous one, without measuring
        how far (`dynamic.load_and_compare_kernel`): for the frames of the auto policy's chaotic
        wait, which rebuild whatever moved. `sources` pass `_comparable`."""
        self.snapshot_valid = False
        self.frame_changed.zero_()
        # A sample first: in a chaotic wait nearly every vertex moves, so a few evenly spaced ones
        # settle it, and the frame is then only copied (0.3 ms for the exploding armadillo's 300k
        # vertices, against 1.05 for the full comparison on two cores). A frame whose sample did
        # not move is compared whole: "nothing moved" is never a guess.
        for src, buf in zip(sources, self._buffers()):
            samples = min(CHANGE_SAMPLES, buf.shape[0])
            args = [buf.shape[0], samples, src, buf, self.frame_changed]
            if self.pipeline.launches is None:
                wp.launch(dynamic.sample_changes_kernel, dim=samples, inputs=args, device=self.device)
            else:
                # The caller's array, often a new one every frame: swapped into one record.
                self.pipeline.launches.launch(dynamic.sample_changes_kernel, samples, args, vary=(2,))
        if int(self.frame_changed.numpy()[0]) != 0:
            self._load(sources)
            return True
        for src, buf in zip(sources, self._buffers()):
            # One flag for every slice: they only ever set it, all to 1.
            self._launch_chunks(dynamic.load_and_compare_kernel, src, buf, [self.frame_changed] * self.motion_threads)
        return int(self.frame_changed.numpy()[0]) != 0

    # ---------------------------------------------------------------- build
    @_one_call_at_a_time
    def build(self, vertices, faces=None) -> Bvh:
        """Set the mesh (faces are fixed from now on) and build its BVH from scratch: a
        `trimesh.Trimesh`, or vertices and faces, as `hlbvh_warp.build` takes them.

        This is the setup call: it validates everything on the host and allocates the vertex
        buffers. Later frames call `update`, `rebuild` or `refit` with new vertices.
        """
        verts_np, faces_np = inputs.mesh_arrays(vertices, faces)
        if faces_np.shape[0] != self.num_prims:
            raise ValueError(f"faces has {faces_np.shape[0]} rows, the builder was set up for {self.num_prims}")
        self._frame_writes()
        vertices, faces, previous = self.vertices, self.faces, self.previous_vertices
        if vertices is None or vertices.shape[0] != verts_np.shape[0]:
            if vertices is not None:
                # New faces too: a view taken earlier keeps the old vertex array, and the new
                # faces' indices would read past its end; with the old faces it stays in bounds.
                faces = wp.empty((self.num_prims, 3), dtype=wp.int32, device=self.device)
            vertices = wp.empty(verts_np.shape[0], dtype=wp.vec3, device=self.device)
            previous = wp.empty(verts_np.shape[0], dtype=wp.vec3, device=self.device)
        vertices.assign(verts_np)
        faces.assign(faces_np)
        # New buffers become the builder's only now, filled, and in one statement with the
        # snapshots that go with them (no interrupt lands inside it): taken before the copies, a
        # set-up interrupted between them (Ctrl-C, a failed allocation) left the new vertex count
        # with faces never written, and the next frame built over garbage indices and crashed.
        renewed = vertices is not self.vertices
        self.vertices, self.faces, self.previous_vertices, self.kind, self.snapshots = (
            vertices, faces, previous, "triangles", [previous])
        if renewed and self.pipeline.launches is not None:
            self.pipeline.launches.clear()
        return self._first_build(vertices=self.vertices, faces=self.faces)

    @_one_call_at_a_time
    def build_from_bounds(self, lowers, uppers) -> Bvh:
        """Set up the builder for arbitrary primitives given by their boxes, ``(N, 3)`` lowers and
        uppers (particles, spheres, capsules: a simulation's broad phase), and build their BVH.

        Later frames pass ``bounds=(lowers, uppers)`` to `update`, `rebuild` or `refit`, or
        write the boxes into ``prim_lowers`` / ``prim_uppers`` in place and pass nothing. Every
        policy works as for triangles; `auto` measures how far a box corner moved.
        """
        lo, hi = inputs.bounds_arrays(lowers, uppers)
        if lo.shape[0] != self.num_prims:
            raise ValueError(f"lowers has {lo.shape[0]} rows, the builder was set up for {self.num_prims}")
        self._frame_writes()
        if self.previous_bounds is None:
            self.previous_bounds = [wp.empty(self.num_prims, dtype=wp.vec3, device=self.device) for _ in range(2)]
        self.prim_lowers.assign(lo)
        self.prim_uppers.assign(hi)
        self.kind, self.snapshots = "boxes", list(self.previous_bounds)
        return self._first_build(vertices=None, faces=None)

    def _first_build(self, vertices, faces) -> Bvh:
        self.snapshot_valid = False
        # A mesh's first build is one from scratch: there is no last tree to keep.
        self.has_last_codes = False
        if self.resort:
            wp.launch(compress.iota_kernel, dim=self.num_prims, inputs=[self.prim_order], device=self.device)
        pipe = self.pipeline
        if self.bvh is None:
            # Unchecked: made before the first build fills its arrays.
            self.bvh = Bvh._trusted(
                method=self.method, config=self.config, device=self.device, prim_lowers=self.prim_lowers,
                prim_uppers=self.prim_uppers, prim_order=self.prim_order, node_lowers=pipe.node_lowers,
                node_uppers=pipe.node_uppers, node_left=pipe.node_left, node_right=pipe.node_right,
                node_parent=pipe.node_parent, node_begin=pipe.node_begin, node_end=pipe.node_end,
                node_count=pipe.node_count, vertices=vertices, faces=faces)
            self.bvh._lock = self._lock
        else:
            self._point_tree_at_buffers()
        if self._policy != "rebuild":
            # The refit's kernels compiled with the setup, untimed, as the build's are: a first run
            # compiled them inside the first refit frame (0.2-1.6 s on the CPU, against 2 ms frames),
            # which then led every frame-time table and plot.
            wp.load_module(bounds_sweep_kernel.module, device=self.device)
        self.frame = 0
        self.reports.clear()
        self.chaotic_frames, self.chaotic_wait = 0, self.first_chaotic_wait
        # The auto policy's refit history belongs to the previous mesh, not this one.
        self.refits_since_rebuild = 0
        self.previous_growth = self.last_growth = 0.0
        start = time.perf_counter()
        timer = StageTimer(self.device, self.timings)
        self._rebuild(timer)
        stages = self._finish(timer)
        # Priced only for `auto`; under another policy the reference is cleared, not left at the
        # previous mesh's cost, so a later switch to `auto` rebuilds first.
        self.sah_reference = _finite_or_none(self.sah_cost()) if self.policy == "auto" else None
        self._report("rebuild", "first build", start, stages)
        self.frame_unfinished = False
        return self.bvh

    @property
    def policy(self) -> str:
        """``"rebuild"``, ``"refit"`` or ``"auto"``: what `update` does; may be switched between
        frames (a switch to ``"auto"`` rebuilds first when no tree has been priced)."""
        return self._policy

    @policy.setter
    def policy(self, policy: str):
        # Checked here too: `update` reads any other value as "auto".
        _check_policy(policy)
        self._policy = policy

    def _require_built(self):
        if self.bvh is None:
            raise RuntimeError("call build(vertices, faces) or build_from_bounds(lowers, uppers) once before "
                               "rebuild/refit/update/sah_cost")

    def _point_tree_at_buffers(self):
        """Point the tree at the vertex and face buffers the builder is set up with (none for
        boxes). One Bvh for the builder's life: its node arrays are the pipeline's, overwritten by
        each build, so a second object would leave the first one's traversal layout stale (rays
        through it reported the old mesh's distances with the new tree's face ids). Over the same
        vertex and face arrays the layout is kept and refreshed by the build, so earlier views see
        this mesh; over new ones (another vertex count, or boxes) the views must be taken again:
        an old one keeps the old vertex and face arrays (its reads stay in bounds) beside the node
        arrays this build overwrites, a mix of the two meshes."""
        vertices, faces = (self.vertices, self.faces) if self.kind == "triangles" else (None, None)
        bvh = self.bvh
        layout = bvh._cache.get("traversal_layout")
        same_arrays = vertices is not None and bvh.vertices is vertices and bvh.faces is faces
        bvh._cache = {"traversal_layout": layout} if layout is not None and same_arrays else {}
        bvh.vertices, bvh.faces = vertices, faces

    def _frame_writes(self):
        """Mark the buffers as being rewritten, until the frame's report clears the mark; the
        tree is the frame's own again, so its queries inside the frame (the SAH reference, the
        views) read it."""
        self.frame_unfinished = True
        if self.bvh is not None:
            self.bvh._unfinished = False

    def _begin_frame(self) -> bool:
        """Mark a frame as changing the buffers (until its report) and return whether the previous
        one raised partway. Such a frame may have stopped inside its sort or emission: its tree is
        half written, and its order (the next resorted frame's input) may not be a permutation,
        nor its sorted codes those of any tree. The next frame then builds from scratch, as the
        first build does, whatever the policy or call: kept, refit or resorted, the half tree
        lived on (under `auto` the same vertices again were "no vertex moved")."""
        unfinished = self.frame_unfinished
        if unfinished:
            # A set-up interrupted before its first build pointed the tree at the new mesh's
            # buffers: the frames after it rebuilt over the new mesh while the tree read the old
            # one's triangles (or, after boxes, none).
            self._point_tree_at_buffers()
            if self.resort:
                wp.launch(compress.iota_kernel, dim=self.num_prims, inputs=[self.prim_order], device=self.device)
            self.has_last_codes = False
        self._frame_writes()
        return unfinished

    def _rebuild(self, timer: StageTimer):
        """The launches of one full build from `self.vertices` (or the boxes in `prim_lowers` /
        `prim_uppers`, for a builder set up with `build_from_bounds`). A sync-free (CUDA) build reads
        nothing on the host unless timed; the others read their run counts, and a resorted one
        its sample of the previous order (`_resorting_pays`).

        Resorted (Pantaleoni & Luebke 2010, 2.2), where that pays: the boxes and their Morton
        codes are computed in the user's face order (sequential passes, as from scratch), then
        only the codes are gathered in the previous tree's order, the build's input. The sort carries each input's
        face id, so the tree comes out naming user faces. Gathering the boxes too (for in-order
        reads in the emission) and mapping the ids back afterwards cost about 2 ms more of a
        19 ms frame on the exploding 100k-triangle armadillo on the CPU; gathering the triangles
        themselves, more again. Both kinds of frame reduce the centroid bounds in the pass that
        computes the triangle boxes. A resorted ``hlbvh`` frame whose codes all equal the last
        tree's keeps its topology and recomputes only the boxes (`_keep_topology`).
        """
        n, device, pipe = self.num_prims, self.device, self.pipeline
        # Triangle boxes in the user's face order, and the centroid bounds in the same pass (for
        # boxes given as such, the centroid bounds only).
        timer.stage("prim_bounds")
        if self.kind == "triangles":
            pipe.compute_triangle_bounds(self.vertices, self.faces)
        else:
            pipe.compute_centroid_bounds()
        resorted = self.resort and self._resorting_pays(timer)
        if resorted:
            timer.stage("morton")
            pipe.compute_morton_codes(bounds_ready=True, codes=self.user_codes)
            pipe.set_input_ids(self.input_order)
            # Resorting: the previous tree's order becomes this build's input order.
            timer.stage("resort_gather")
            if self.keeps_topology and self.may_be_sorted and self.has_last_codes:
                self.codes_changed.zero_()
                if self.compare_parts is not None:
                    threads_module.launch_parts(dynamic.resort_gather_compare_kernel, device, self.compare_parts,
                                                len(self.compare_parts))
                else:
                    pipe._launch(dynamic.resort_gather_compare_kernel, n,
                                 [self.prim_order, self.user_codes, pipe.sorted_codes, self.input_order,
                                  pipe.morton_codes, self.codes_changed])
                self.last_input["kept_topology"] = int(self.codes_changed.numpy()[0]) == 0
                if self.last_input["kept_topology"]:
                    self._keep_topology(timer)
                    return
            elif self.gather_parts is not None:
                threads_module.launch_parts(dynamic.resort_gather_kernel, device, self.gather_parts,
                                            len(self.gather_parts))
            else:
                pipe._launch(dynamic.resort_gather_kernel, n,
                             [self.prim_order, self.user_codes, self.input_order, pipe.morton_codes])
        elif self.resort:
            # The faces' own order, as from scratch: the pipeline computes the codes in place.
            timer.skipped("resort_gather")
            pipe.set_input_ids(None)
        pipeline_timings = timer.timings
        ready = "codes" if resorted else "bounds"
        # The sort overwrites the codes before the emission rewrites the tree: until it returns,
        # the two may disagree.
        self.has_last_codes = False
        if self.method == "hlbvh_sah":
            pipe.build_sah(timer, inputs_ready=ready)
        else:
            pipe.build(self.method, timer, sync_free=self.sync_free, inputs_ready=ready)
        self.has_last_codes = True
        pipeline_timings.pop("total", None)

    def _keep_topology(self, timer: StageTimer):
        """The rest of a resorted frame whose codes all equal the last tree's, at the same
        positions (`dynamic.resort_gather_compare_kernel`): the sort and the emission would make
        the last tree again (its order is this input's, and its nodes are a function of the sorted
        codes), so only the boxes are recomputed, bottom-up over the new triangle boxes. The tree
        is the one a build from scratch makes; the report says ``kept_topology``."""
        for stage in ("order_check", "run_length_encode", "top_level_sort", "run_length_decode", "voxel_sort",
                      "hierarchy"):
            timer.skipped(stage)
        timer.stage("bbox")
        self._sweep_boxes(False)

    def _sweep_boxes(self, price: bool) -> float | None:
        """Every node box over the current primitive boxes, bottom-up, the topology kept; with
        `price` (the CPU's sweep), also the sum of the nodes' SAH terms x area, returned.

        On a multi-core CPU, a tree whose emission ran its seeds side by side is swept the same
        way (`HlbvhPipeline.sweep_parts`): each run's nodes have their children in that run, so
        the runs' sweeps run side by side and the few nodes above them are swept after. Other
        trees take one sweep (the CPU) or the climb (CUDA)."""
        bvh, pipe, cfg = self.bvh, self.pipeline, self.config
        costs = (cfg.sah_traversal_cost, cfg.sah_intersection_cost)
        parts = pipe.sweep_parts if self.device.is_cpu else None
        if parts is None:
            priced = (*costs, self.sah_scratch) if price else None
            compute_bounds(self.device, bvh.node_count, bvh.node_left, bvh.node_right, bvh.node_parent,
                           bvh.node_begin, bvh.node_end, bvh.prim_order, bvh.prim_lowers, bvh.prim_uppers,
                           pipe.node_visits, bvh.node_lowers, bvh.node_uppers, "sweep" if priced else None, priced,
                           launch=pipe._launch)
            return float(self.sah_scratch[0:1].numpy()[0]) if price else None
        top, runs = parts
        key = (parts, bool(price), bvh.node_lowers.ptr)
        if self._sweep_args is None or self._sweep_args[0] != key:
            # The arguments of each run's launch, made once per emission layout (as the gather's
            # views are), not every frame.
            arrays = [bvh.node_count, bvh.node_left, bvh.node_right, bvh.node_begin, bvh.node_end, bvh.prim_order,
                      bvh.prim_lowers, bvh.prim_uppers, int(price), wp.float64(costs[0]), wp.float64(costs[1]),
                      bvh.node_lowers, bvh.node_uppers, self.sweep_costs]
            self._sweep_args = (key, [(1, [lo, stop, j + 1] + arrays) for j, (lo, stop) in enumerate(runs)],
                                [0, top, 0] + arrays)
        _, run_args, top_args = self._sweep_args
        # Plain launches side by side (recorded ones made or replayed on the worker threads
        # crashed the process; see `hlbvh_warp.launches`), then the top in the recorded one.
        threads_module.launch_parts(bounds_sweep_kernel, self.device, run_args, len(runs))
        pipe._launch(bounds_sweep_kernel, 1, top_args)
        return float(self.sweep_costs.numpy()[:len(runs) + 1].sum()) if price else None

    def _resorting_pays(self, timer: StageTimer) -> bool:
        """Whether to feed this frame in the previous tree's order (Pantaleoni & Luebke 2010, 2.2).

        Resorting buys a compress-sort-decompress with less to do, for the price of gathering the
        codes into that order (one random read per primitive: 15.6 ms of a 200 ms frame of the
        exploding 1.6M-triangle armadillo on the CPU). A build whose runs do not compress takes
        one radix sort of the full codes instead (`BuildConfig.global_sort_runs`), and a radix
        sort costs the same in any input order, so there the gather buys nothing. Where the build
        reads its run count on the host, a sample of adjacent pairs of the previous order
        (`dynamic.sample_run_breaks_kernel`) estimates the M / N that order would give; past the
        limit, unless no sampled pair descends (a sorted order skips every sort), the frame is
        fed in the faces' own order, exactly as from scratch. The sample computes its codes from
        the boxes, so the choice costs one launch of `RESORT_SAMPLES` threads and no pass over
        all the codes. ``lbvh`` always takes the radix sort. A sync-free (CUDA) build and
        ``hlbvh_sah`` (which needs the voxels) always compress, so they always resort.
        """
        self.last_input = {"input_order": "previous tree", "sampled_run_fraction": None}
        # Whether the codes may still be the last tree's, in its order: not once a sampled pair
        # descends (the last tree's codes ascend), and then the gather compares nothing.
        self.may_be_sorted = True
        if self.sync_free or self.method == "hlbvh_sah" or self.resort_samples < 1:
            return True
        if self.method == "hlbvh" and self.config.global_sort_runs >= 1.0:
            return True  # the paper's sort for every build: no M / N is past the limit
        if self.method == "lbvh":
            self.last_input["input_order"] = "faces"
            return False
        timer.stage("resort_check")
        pipe = self.pipeline
        self.run_breaks.zero_()
        bits = self.config.bits_per_axis
        pipe._launch(dynamic.sample_run_breaks_kernel, self.resort_samples,
                     [self.prim_order, pipe.prim_lowers, pipe.prim_uppers, pipe.scene_bounds, bits,
                      self.num_prims, self.resort_samples, 3 * (bits - pipe.coarse_bits), self.run_breaks])
        breaks, descents = (int(x) for x in self.run_breaks.numpy())
        self.may_be_sorted = descents == 0
        fraction = breaks / self.resort_samples
        self.last_input["sampled_run_fraction"] = fraction
        # No sampled pair descends: the order may be sorted already, and the build's order check
        # then skips every sort, whatever the runs (the paper's resorting of a static model).
        if fraction > self.config.global_sort_runs and descents > 0:
            self.last_input["input_order"] = "faces"
            return False
        return True

    def _refit(self, timer: StageTimer, price: bool = False) -> float | None:
        """Refit every box; with `price`, also return the refit tree's SAH cost (`sah_cost`)."""
        if self.kind == "triangles":
            timer.stage("prim_bounds")
            self.pipeline.compute_triangle_boxes(self.vertices, self.faces, self.prim_lowers, self.prim_uppers)
        timer.stage("refit")
        # The CPU refit sweeps the nodes; it sums the SAH terms as it goes, where pricing
        # afterwards took a second pass (about 1.5 ms on 100k triangles).
        total = self._sweep_boxes(price and self.device.is_cpu)
        if total is not None:
            cfg = self.config
            return metrics.cost_from_sum(self.bvh, total, self.bvh.num_nodes, cfg.sah_traversal_cost,
                                         cfg.sah_intersection_cost)
        if not price:
            return None
        timer.stage("sah")
        return self.sah_cost()

    def _finish(self, timer: StageTimer, changed: bool = True) -> dict:
        if changed:  # a frame in which nothing moved leaves the tree, and trees made from it, as they are
            self.bvh.invalidate()
        timings = timer.finish()
        return dict(timings)

    @_one_call_at_a_time
    def rebuild(self, vertices=None, *, bounds=None) -> Bvh:
        """Full build over new vertices (or the current contents of ``self.vertices``); for a
        builder set up with `build_from_bounds`, over new ``bounds=(lowers, uppers)`` (or the
        current contents of ``prim_lowers`` / ``prim_uppers``).

        Resorted when the builder was made with ``resort=True``. Given device arrays (or None)
        it allocates nothing; an ``"hlbvh"`` or ``"lbvh"`` rebuild on CUDA (the sync-free build)
        also launches work only, with no host synchronization, while the others read their run
        counts, the resort sample and, for ``"hlbvh_sah"``, the cluster count on the host.
        """
        self._require_built()
        sources = self._frame_sources(vertices, bounds)
        # Also a CPU graph capture (Warp 1.19 records those): the CPU rebuild reads counts on the
        # host, which a recording (kernels not run) would bake in; Warp itself refuses its run-length
        # encoding there, and launches from the CPU's worker threads crashed the process.
        if not self.sync_free and self.device.is_capturing:
            raise RuntimeError(f"a {self.method!r} rebuild on {self.device} reads counts on the host and cannot be "
                               "captured in a graph; capture a CUDA Builder with method='hlbvh' or 'lbvh'")
        self._refuse_host_frame_in_capture(sources)
        start = time.perf_counter()
        unfinished = self._begin_frame()
        return self._full_rebuild(sources, start, UNFINISHED_REASON if unfinished else "rebuild requested")

    def _full_rebuild(self, sources: list | None, start: float, reason: str) -> Bvh:
        self._load(sources)
        timer = StageTimer(self.device, self.timings)
        self._rebuild(timer)
        stages = self._finish(timer)
        self.sah_reference = None
        # A fresh tree: `auto`'s refits in a row and their growth start again from it.
        self.refits_since_rebuild = 0
        self.previous_growth = self.last_growth = 0.0
        self._report("rebuild", reason, start, stages)
        self.frame_unfinished = False
        return self.bvh

    @_one_call_at_a_time
    def refit(self, vertices=None, *, bounds=None) -> Bvh:
        """Recompute every box for new vertices (or boxes, ``bounds=(lowers, uppers)``), keeping
        the topology."""
        self._require_built()
        sources = self._frame_sources(vertices, bounds)
        # On the CPU the sweep of a tree emitted side by side runs its parts on worker threads,
        # which a capture on the calling thread does not record: the replayed graph reloaded the
        # boxes and left every node box at the captured frame's.
        if self.device.is_cpu and self.device.is_capturing:
            raise RuntimeError(f"a refit on {self.device} runs launches on worker threads and cannot be captured in "
                               "a graph; capture a CUDA Builder instead")
        self._refuse_host_frame_in_capture(sources)
        start = time.perf_counter()
        if self._begin_frame():
            # No whole topology to refit: the last frame stopped partway through writing it.
            return self._full_rebuild(sources, start, UNFINISHED_REASON)
        self._load(sources)
        timer = StageTimer(self.device, self.timings)
        self._refit(timer)
        stages = self._finish(timer)
        # One more refit of the same topology, forced or under the `refit` policy: `auto`'s
        # `max_refits` bounds them all, or substeps refit through `refit()` past the limit and
        # a switch back to `auto` priced a tree refit 40 times as "after 1 refits".
        self.refits_since_rebuild += 1
        self._report("refit", "refit requested", start, stages)
        self.frame_unfinished = False
        return self.bvh

    @_one_call_at_a_time
    def update(self, vertices=None, *, bounds=None) -> dict:
        """One frame under the builder's policy, over new vertices (or boxes, ``bounds=(lowers,
        uppers)``); returns the frame report (also `last_report`)."""
        self._require_built()
        if self.policy == "rebuild":
            self.rebuild(vertices, bounds=bounds)
        elif self.policy == "refit":
            self.refit(vertices, bounds=bounds)
        else:
            sources = self._frame_sources(vertices, bounds)
            # `auto` chooses each frame on the host from its motion measure (or its chaotic wait's
            # comparison), on every device: a capture runs nothing while it records, so the choice
            # would read stale numbers and bake them into the graph.
            if self.device.is_capturing:
                raise RuntimeError(f"the 'auto' policy reads its motion measure on the host and cannot be captured "
                                   f"in a graph on {self.device}; capture rebuild() or refit() instead")
            self._auto(sources)
        return self.last_report

    # ----------------------------------------------------------------- auto
    @_one_call_at_a_time
    def sah_cost(self) -> float:
        """SAH cost of the current tree (paper eq. 1, costs from the config), read to the host."""
        self._require_built()
        return metrics.sah_cost(self.bvh, self.config.sah_traversal_cost, self.config.sah_intersection_cost,
                                self.sah_scratch)

    def _projected_growth(self) -> float:
        """The refit SAH growth the next refit frame is on course for: the last refit's growth (over
        the best cost since the last rebuild) plus one more frame at the larger of its last step
        and its average step; a refit tree's cost tends to grow faster as the motion piles up."""
        k = self.refits_since_rebuild
        if k == 0:
            return 0.0
        return self.last_growth + max(self.last_growth - self.previous_growth, self.last_growth / k)

    def _auto(self, sources: list | None):
        start = time.perf_counter()
        unfinished = self._begin_frame()
        timer = StageTimer(self.device, self.timings)
        timer.stage("motion")
        compare_only = self.chaotic_frames > 0 and self._comparable(sources)
        if compare_only:
            # A frame of the chaotic wait is rebuilt if anything moved, however far: only whether
            # it did is needed, which a sample usually settles (the 300k vertices of the
            # exploding armadillo, alternating in one process on two cores: 0.34 ms against 1.08
            # for the measure; the plain copy of a rebuild 0.24).
            measured, extra = True, {"motion": "compared, not measured (chaotic wait)"}
            moved, relative = (None if self._load_and_compare(sources) else 0.0), None
        else:
            # Load the vertices and measure the largest displacement on the device, in one pass.
            measured = self._load_and_measure(sources)
            self.pipeline._launch(dynamic.root_diagonal_kernel, 1,
                                  [self.bvh.node_lowers, self.bvh.node_uppers, self.stats])
            moved, diagonal = (float(x) for x in self.stats.numpy())
            if 0.0 < diagonal < math.inf:
                relative = moved / diagonal
            else:
                # A zero-size scene, or a last tree boxed over NaN or Inf (a device frame that blew
                # up): any motion counts as large, and the tree is rebuilt.
                relative = 0.0 if moved == 0.0 else math.inf
            extra = {"max_displacement": moved, "relative_motion": relative} if measured else {}
        skipped = []
        large = False
        if unfinished:
            # Motion is measured against the buffers, not against what the half tree bounds.
            decision, reason = "rebuild", UNFINISHED_REASON
            self._rebuild(timer)
        elif not measured:
            decision = "rebuild"
            reason = "frame written in place, with no snapshot of the previous frame to measure against"
            self._rebuild(timer)
        elif moved == 0.0:
            what = "vertex" if self.kind == "triangles" else "box"
            decision, reason = "none", f"no {what} moved since the previous frame"
            skipped = ["prim_bounds", "refit", "rebuild"]
        elif relative is not None and relative > self.large_motion:
            decision = "rebuild"
            # A box builder measures its boxes' corners: "a vertex" would send a simulation's
            # author looking for vertices it never gave.
            what = "a vertex" if self.kind == "triangles" else "a box corner"
            if math.isinf(relative):
                # The measure counts a NaN or Inf coordinate (a device frame that blew up), or any
                # motion of a zero-size scene, as infinite: "moved inf%" would only puzzle.
                reason = (f"large motion: {what} moved past any share of the scene diagonal (a NaN or "
                          f"Inf coordinate, in this frame or the last tree, or a zero-size scene)")
            else:
                reason = (f"large motion: {what} moved {relative:.1%} of the scene diagonal "
                          f"(limit {self.large_motion:.1%})")
            large = True
            self._rebuild(timer)
        elif self.chaotic_frames > 0:
            self.chaotic_frames -= 1
            decision = "rebuild"
            reason = ("chaotic motion: a refit tree recently exceeded the SAH limit on its first frame "
                      f"(refit retried in {self.chaotic_frames + 1} frames)")
            self._rebuild(timer)
        elif self.sah_reference is None:
            decision = "rebuild"
            reason = "no SAH reference: the last tree was not priced (a rebuild on request or for large motion)"
            self._rebuild(timer)
        elif self.refits_since_rebuild >= self.max_refits:
            decision = "rebuild"
            reason = (f"small motion ({relative:.2%} of the diagonal), but {self.refits_since_rebuild} refits in a row "
                      f"(limit {self.max_refits})")
            self._rebuild(timer)
        elif self._projected_growth() > self.sah_growth_limit:
            # A refit that would exceed the limit costs a refit, its pricing and the rebuild after.
            decision = "rebuild"
            reason = (f"small motion ({relative:.2%} of the diagonal), but the refit SAH cost, "
                      f"{self.last_growth:+.1%} after {self.refits_since_rebuild} refits, is on course for about "
                      f"{self._projected_growth():+.1%} (limit {self.sah_growth_limit:.0%})")
            self._rebuild(timer)
        else:
            sah = self._refit(timer, price=True)
            # Growth over the best cost seen since the last rebuild: a deformation that lowers the
            # cost of the refit tree lowers that of a fresh build too, so the rebuild's own cost
            # would understate how far the refit tree has fallen behind.
            growth = sah / self.sah_reference - 1.0
            extra.update(sah_refit=sah, sah_growth=growth)
            if not growth <= self.sah_growth_limit:  # NaN too: a refit over a non-finite frame
                decision = "rebuild"
                reason = (f"small motion ({relative:.2%} of the diagonal) but the refit SAH cost grew "
                          f"{growth:+.1%} over its best since the last rebuild (limit {self.sah_growth_limit:.0%})")
                if self.refits_since_rebuild == 0:
                    # One frame of motion already ruins a fresh tree: stop trying refits for a
                    # while, twice as long after every retry that fails (an explosion stays
                    # chaotic, and each failed retry costs a refit and its pricing on top of the
                    # rebuild: 3 of 24 frames of the exploding 400k-triangle armadillo at a
                    # fixed wait of 8).
                    self.chaotic_frames = self.chaotic_wait
                    self.chaotic_wait = min(2 * self.chaotic_wait, MAX_CHAOTIC_BACKOFF * self.first_chaotic_wait)
                self._rebuild(timer)
            else:
                decision = "refit"
                reason = (f"small motion ({relative:.2%} of the diagonal); SAH cost {growth:+.1%} over its best "
                          f"since the last rebuild (limit {self.sah_growth_limit:.0%})")
                skipped = ["rebuild"]
                self.chaotic_wait = self.first_chaotic_wait
                self.sah_reference = min(self.sah_reference, sah)
                self.previous_growth, self.last_growth = self.last_growth, growth
        if decision == "refit":
            self.refits_since_rebuild += 1
        elif decision == "rebuild":
            self.refits_since_rebuild = 0
            self.previous_growth = self.last_growth = 0.0
        if decision == "rebuild":
            if large or self.chaotic_frames > 0:
                # Pricing a tree costs a pass over its nodes and a read; only a refit ever compares
                # with the price. After chaotic motion the next frame rebuilds anyway. After large
                # motion it likely does too; when it does not, it rebuilds once more for want of a
                # reference, which costs less than pricing every frame of a fast sequence.
                skipped.append("sah")
                if large:
                    self.sah_reference = None
            else:
                timer.stage("sah")
                # A tree over a non-finite frame has a NaN cost: no refit may be judged by it.
                self.sah_reference = _finite_or_none(self.sah_cost())
                extra["sah"] = self.sah_reference
        elif decision == "refit":
            extra["sah"] = extra["sah_refit"]
        stages = self._finish(timer, changed=decision != "none")
        stages["skipped"] = list(stages.get("skipped", [])) + skipped
        self._report(decision, reason, start, stages, **extra)
        self.frame_unfinished = False

    # --------------------------------------------------------------- report
    def _report(self, decision: str, reason: str, start: float, stages: dict, **extra):
        if self.timings:
            wp.synchronize_device(self.device)
        skipped = stages.pop("skipped", [])
        stages.pop("total", None)
        report = {
            "frame": self.frame,
            "decision": decision,
            "reason": reason,
            "policy": self.policy,
            "resort": self.resort,
            # Host time of the call; with timings=False on CUDA it excludes the queued device work.
            "ms": (time.perf_counter() - start) * 1e3,
            "stages_ms": stages,
            "stages_skipped": list(skipped),
        }
        if decision == "rebuild" and self.resort:
            report.update(self.last_input)
        report.update(extra)
        # The tree's timings in a one-shot tree's form (`StageTimer.finish`), in a dict of their
        # own: handed the report's stages, a Builder's tree had no "skipped" or "total" (a
        # KeyError where a one-shot tree's had them), and an edit to them rewrote the report.
        self.bvh.timings = dict(stages, skipped=list(skipped), total=sum(stages.values())) if self.timings else {}
        self.last_report = report
        self.reports.append(report)
        self.frame += 1
