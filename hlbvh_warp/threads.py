"""Independent CPU launches on several cores.

Warp's CPU device runs the threads of one launch one after another. The serial stages of a build
(a depth-first walk per subtree) are independent once their subtrees are known, so on a
multi-core CPU their launches can run side by side: a Warp CPU launch releases the GIL while the
kernel runs, and each launch carries its own argument block. Work given to `run` must write
disjoint memory and must not rely on ``wp.atomic_*`` between launches (on the CPU device those
are plain read-modify-writes, atomic only within one serial launch).

Library calls stay in the calling thread, but for the radix sorts of the global sort's two halves
(`HlbvhPipeline.global_sort`): Warp 1.19's CPU radix sort keeps its digit histogram per thread,
where earlier releases kept static tables that two sorts at once would corrupt
(`hlbvh.SORTS_SIDE_BY_SIDE`). Its scans and run-length encoding are not made for that.

The thread count comes from ``BuildConfig.cpu_threads``: 0 (the default) uses the cores this
process may run on; 1 keeps everything in the calling thread.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor, wait

import warp as wp

_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()
# How many `run` calls have jobs on several threads right now (see `side_by_side`).
_SIDE_BY_SIDE = 0


def usable_cores() -> int:
    """Cores this process may run on: its CPU affinity (``os.sched_getaffinity``, Linux), else
    ``os.cpu_count()``; at least 1."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


#: Work parts per usable core at the most: parts beyond the pool's workers only queue, and each
#: costs a launch and a share of the scratch (2^31 asked for had a Builder allocate 8.6 GB).
MAX_THREADS_PER_CORE = 4


def resolved_threads(config, device) -> int:
    """Threads for the serial stages of a build on `device` (always 1 off the CPU): the config's
    count, or every usable core for 0, at most `MAX_THREADS_PER_CORE` per core."""
    if not device.is_cpu:
        return 1
    cores = usable_cores()
    requested = config.cpu_threads
    return max(1, min(requested, MAX_THREADS_PER_CORE * cores) if requested > 0 else cores)


def _pool() -> ThreadPoolExecutor:
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(max_workers=max(usable_cores() - 1, 1), thread_name_prefix="hlbvh_warp")
        return _POOL


def side_by_side() -> bool:
    """Whether launches are running side by side on several threads now. Recorded launches
    (`hlbvh_warp.launches`) stay out of such stretches: made or replayed while another thread
    ran a kernel, they crashed the process in Warp 1.19 (a segmentation fault in its CPU
    `invoke`), where plain `wp.launch` calls side by side are safe."""
    return _SIDE_BY_SIDE > 0


def run(jobs, threads: int):
    """Run the callables `jobs` on up to `threads` threads (the caller's included); re-raises."""
    global _SIDE_BY_SIDE
    jobs = list(jobs)
    # Warp 1.19's CPU kernels compiled in its debug mode (a user debugging kernels of their own)
    # crash the process when two run at once: each launch points one static variable at tile
    # storage on its own stack (`wp.config.enable_tiles_in_stack_memory`, x86-64), and unoptimized
    # code reads it back after the other launch has reset it. There the jobs run one after
    # another, the same work.
    if threads <= 1 or len(jobs) <= 1 or wp.config.mode == "debug":
        for job in jobs:
            job()
        return
    # Greedy: the caller takes every `threads`-th job, the pool the rest in order.
    mine = jobs[::threads]
    others = [job for i, job in enumerate(jobs) if i % threads != 0]
    with _POOL_LOCK:
        _SIDE_BY_SIDE += 1
    try:
        futures = []
        for index, job in enumerate(others):
            try:
                futures.append(_pool().submit(job))
            except RuntimeError:
                # The pool is shut down: `concurrent.futures` does so when the main thread ends,
                # before the threads still running are joined, and a build in such a thread (a
                # worker started by a script that then returned) failed with "cannot schedule
                # new futures after shutdown". The rest run in this thread, the same work.
                mine = mine + others[index:]
                break
        try:
            for job in mine:
                job()
        finally:
            # Every job has finished before run returns or raises: re-raising the first failed
            # job's error at once left the pool's other jobs running after the caller went on
            # (writing its buffers, outside the side-by-side stretch that `side_by_side` reports).
            wait(futures)
            for future in futures:
                future.result()
    finally:
        with _POOL_LOCK:
            _SIDE_BY_SIDE -= 1


def split_bounds(num: int, parts: int) -> list:
    """`parts` + 1 boundaries cutting [0, num) into contiguous slices of near-equal size."""
    parts = max(1, min(parts, num))
    return [num * j // parts for j in range(parts + 1)]


def launch_parts(kernel, device, parts: list, threads: int):
    """Launch `kernel` once per ``(dim, inputs)`` of `parts` on up to `threads` threads: one
    elementwise launch cut into slices whose inputs are views of the whole arrays. The views are
    made once by the caller, so a per-frame launch creates no arrays."""
    # Load (on a fresh cache: compile) the kernel's module here, once: launched first from
    # several threads at once, each compiled the same module into the same cache files. CPU
    # launches load it for a block size of 1 (Warp's default there), so that is the one loaded.
    device = wp.get_device(device)
    kernel.module.load(device, 1 if device.is_cpu else None)
    run([lambda dim=dim, inputs=inputs: wp.launch(kernel, dim=dim, inputs=inputs, device=device)
         for dim, inputs in parts], threads)
