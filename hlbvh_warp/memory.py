"""Recycled host buffers for builds on Warp's CPU device.

Why this exists: a build touches about 200 bytes per triangle of fresh buffers (codes, orders,
the node arena). On the CPU device those come from the C allocator, which hands large blocks
back to the operating system when they are freed; the next build's buffers then page-fault on
first touch. On the machines we measure on that costs about 0.7 ms per MB, which made a
one-shot build of the 100k-triangle armadillo take 1.5-2x as long as the same build on reused
buffers (see the README). Rebuilding every frame with `Builder` never pays it; a program that
calls `build` in a loop did, every time.

`empty` therefore serves large CPU arrays from blocks that earlier arrays gave back: each array
is a view of a pool-owned block, and when the last reference to the view goes (the `Bvh` that
held it, or a pipeline's scratch), the block returns to the pool instead of to the system. The
same idea as the caching allocators of CUDA stream-ordered memory pools and PyTorch's host
allocator. CUDA arrays never come here: Warp allocates them from the device's memory pool,
which already recycles.

The pool's idle blocks and the scratch sets below share one cap of `limit` bytes
(`set_host_cache_limit`; 0 turns both off); `clear_host_cache` drops them. Contents of a
recycled block are whatever was there: `empty` is for buffers the build writes before it
reads, like `wp.empty`.
"""

from __future__ import annotations

import ctypes
import sys
import threading
import weakref
from collections import OrderedDict

import warp as wp

from . import inputs

#: Arrays smaller than this come from `wp.empty` directly: the C allocator keeps small blocks.
MIN_POOLED_BYTES = 1 << 16
#: Default cap on the idle bytes the pool keeps.
DEFAULT_LIMIT_BYTES = 1 << 30


def _size_class(nbytes: int) -> int:
    """Round up to one of 8 steps per power of two, so similar sizes share blocks: at most 12.5%
    waste from 512 KiB up; below that, to a multiple of the MIN_POOLED_BYTES step (64 KiB)."""
    step = max(1 << max(nbytes.bit_length() - 4, 0), MIN_POOLED_BYTES)
    return -(-nbytes // step) * step


class HostBufferPool:
    """Blocks of CPU memory recycled between arrays; thread-safe."""

    def __init__(self, limit: int = DEFAULT_LIMIT_BYTES):
        self.limit = int(limit)
        self.idle_bytes = 0
        self._idle: dict[int, list] = {}
        #: Bytes kept elsewhere under the same cap (the scratch sets): each counted against the
        #: other, the two together held up to twice the limit.
        self.held_elsewhere = lambda: 0
        # Re-entrant: `_give_back` runs as a finalizer, and the garbage collector may run one on
        # this thread while it holds the lock (an allocation under it collecting a dropped cycle
        # that held a pooled array); a plain lock waited on itself there, and the process hung.
        self._lock = threading.RLock()

    def empty(self, shape, dtype, device) -> wp.array:
        """An uninitialized array like ``wp.empty``; a large CPU array is a view of a recycled block."""
        device = wp.get_device(device)
        dtype = {float: wp.float32, int: wp.int32}.get(dtype, dtype)
        shape = (shape,) if isinstance(shape, int) else tuple(shape)
        count = 1
        for s in shape:
            count *= int(s)
        nbytes = count * wp.types.type_size_in_bytes(dtype)
        if not device.is_cpu or self.limit <= 0 or nbytes < MIN_POOLED_BYTES:
            return wp.empty(shape, dtype=dtype, device=device)
        size = _size_class(nbytes)
        with self._lock:
            blocks = self._idle.get(size)
            block = blocks.pop() if blocks else None
            if block is not None:
                self.idle_bytes -= size
        if block is None:
            block = wp.empty(size, dtype=wp.uint8, device=device)
        view = wp.array(ptr=block.ptr, dtype=dtype, shape=shape, capacity=nbytes, device=device)
        # The finalizer holds the block: it outlives the view and every slice or NumPy view of it
        # (those keep the view alive), then goes back to the pool.
        weakref.finalize(view, self._give_back, size, block)
        return view

    def _give_back(self, size: int, block: wp.array):
        fresh = []  # allocated before the lock, so that the usual case allocates nothing under it
        with self._lock:
            if self.idle_bytes + self.held_elsewhere() + size <= self.limit:
                self._idle.setdefault(size, fresh).append(block)
                self.idle_bytes += size

    def trim(self, max_idle_bytes: int):
        """Drop idle blocks, the largest first, until at most `max_idle_bytes` are left."""
        with self._lock:
            for size in sorted(self._idle, reverse=True):
                blocks = self._idle[size]
                while blocks and self.idle_bytes > max_idle_bytes:
                    blocks.pop()
                    self.idle_bytes -= size
                if not blocks:
                    del self._idle[size]

    def clear(self):
        """Drop every idle block."""
        with self._lock:
            self._idle.clear()
            self.idle_bytes = 0


_POOL = HostBufferPool()


class ScratchCache:
    """Whole scratch sets (a pipeline's buffers) kept between one-shot builds of the same shape.

    The pool above saves the page faults of fresh memory, but a pipeline still wraps about sixty
    buffers in Warp arrays, about 1.5 ms of Python per build of the 100k-triangle armadillo
    (7% of an ``hlbvh_sah`` build). A program that calls `build` in a loop gets the previous
    build's pipeline of the same size, config and device back instead, its outputs renewed (the
    last `Bvh` keeps the old ones).

    Sets are kept while their bytes (`array_bytes`, the outputs they still point at included)
    fit the pool's limit, and at most `max_entries` of them, the least recently used dropped
    first. A scene of several meshes, each built one-shot every frame, needs one set per mesh:
    with room for only two, four meshes built in turn each paid for a new pipeline and took
    1.3-1.7x as long (see the README). The pool's limit of 0 turns this off too, and
    `clear_host_cache` empties it.
    """

    def __init__(self, max_entries: int = 16):
        self.max_entries = max_entries
        self.held_bytes = 0
        self._entries: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    def take(self, key):
        """The kept set for `key` (now owned by the caller), or None."""
        with self._lock:
            entry = self._entries.pop(key, None)
            if entry is None:
                return None
            self.held_bytes -= entry[1]
            return entry[0]

    def give_back(self, key, scratch, nbytes: int = 0):
        """Keep `scratch` (holding `nbytes`) under `key`, dropping the oldest sets past the limits."""
        nbytes = int(nbytes)
        if _POOL.limit <= 0 or nbytes > _POOL.limit:
            return
        with self._lock:
            old = self._entries.pop(key, None)
            if old is not None:
                self.held_bytes -= old[1]
            self._entries[key] = (scratch, nbytes)
            self.held_bytes += nbytes
            self._trim(_POOL.limit)
        # One cap for both: a kept set is worth more than idle blocks (it saves the wrapping too).
        _POOL.trim(_POOL.limit - self.held_bytes)

    def _trim(self, limit_bytes: int):
        while self._entries and (len(self._entries) > self.max_entries or self.held_bytes > limit_bytes):
            _, (_, dropped) = self._entries.popitem(last=False)
            self.held_bytes -= dropped

    def trim(self, limit_bytes: int):
        """Drop the oldest sets until the rest hold at most `limit_bytes`."""
        with self._lock:
            self._trim(limit_bytes)

    def clear(self):
        """Drop every kept scratch set."""
        with self._lock:
            self._entries.clear()
            self.held_bytes = 0


_SCRATCH = ScratchCache()
_POOL.held_elsewhere = lambda: _SCRATCH.held_bytes


def _return_freed_memory():
    """Ask glibc to hand its freed heap memory back to the system. Freed large blocks raise its
    threshold for mapping blocks of their own, so later ones stay in its heap after `free`:
    without this, `clear_host_cache` left the process's memory about where it was (350 MB
    after 600 builds of varying sizes; 258 MB with it)."""
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL("libc.so.6").malloc_trim(0)
        except (OSError, AttributeError):
            pass  # another C library (musl): nothing to ask


def take_scratch(key):
    """A scratch set kept by `give_back_scratch` under `key`, or None."""
    return _SCRATCH.take(key)


def give_back_scratch(key, scratch, nbytes: int = 0):
    """Keep `scratch`, which holds `nbytes` of arrays, for the next one-shot build under `key`
    (see `ScratchCache`)."""
    _SCRATCH.give_back(key, scratch, nbytes)


def array_bytes(*holders) -> int:
    """Bytes of every Warp array held as an attribute of `holders` (what a build allocates)."""
    seen = set()
    total = 0
    for holder in holders:
        for value in vars(holder).values():
            if isinstance(value, wp.array) and id(value) not in seen:
                seen.add(id(value))
                total += value.capacity
    return total


def empty(shape, dtype, device) -> wp.array:
    """An uninitialized array like ``wp.empty``; large CPU arrays reuse recycled blocks."""
    return _POOL.empty(shape, dtype, device)


def set_host_cache_limit(limit_bytes: int):
    """Cap the host memory kept for later builds: the pool's idle blocks and the kept scratch sets
    together (0 disables both)."""
    _POOL.limit = inputs.count_arg(limit_bytes, "limit_bytes", 0)
    if _POOL.limit <= 0:
        _SCRATCH.clear()
    else:
        _SCRATCH.trim(_POOL.limit)
    _POOL.trim(_POOL.limit - _SCRATCH.held_bytes)


def set_scratch_cache_sets(count: int):
    """Keep at most `count` one-shot pipeline scratch sets (default 16; 0 keeps none, while the
    pool still recycles blocks). One per mesh a program builds one-shot in turn is enough."""
    _SCRATCH.max_entries = inputs.count_arg(count, "count", 0)
    _SCRATCH.trim(_POOL.limit)


def clear_host_cache():
    """Release every idle block, and every kept scratch set, to the system."""
    _SCRATCH.clear()
    _POOL.clear()
    _return_freed_memory()


def host_cache_bytes() -> int:
    """Bytes the cache holds now: idle blocks and kept scratch sets, together at most the limit."""
    return _POOL.idle_bytes + _SCRATCH.held_bytes
