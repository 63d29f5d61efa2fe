"""Recorded kernel launches for per-frame builds: arguments packed once, replayed every frame.

`wp.launch` packs every argument into its C form on each call, about 20 us on the CPU for a
kernel of eight arguments, where replaying a recorded `wp.Launch` takes about 4. A `Builder`
launches the same kernels on the same buffers every frame, so it records each launch the first
time and replays it after, changing only the launch size when a count changed. Below a few
thousand primitives those launches are most of a frame.

One-shot builds do not record: their pipelines read the caller's boxes, and a recorded launch
keeps its arguments alive. Launches made while the CPU runs kernels side by side
(`hlbvh_warp.threads.side_by_side`) go through `wp.launch`: recorded launches made or replayed
there crashed the process (a segmentation fault in Warp 1.19's CPU `invoke`, with `hlbvh_sah`
on two cores). Those are the launches whose arguments change every frame anyway (each run's
first seed), so nothing is lost.

A record is kept only if it holds the loaded module its entry points are in (`holds_its_code`):
made while another thread was loading the same module, one could hold one load and call into
the other, which Warp then unloaded, and its replay crashed the process.
"""

from __future__ import annotations

import ctypes

import numpy as np
import warp as wp

from . import threads

#: Recorded launches kept per builder; past this the record starts over (a frame launches about
#: twenty distinct ones, so only changing arguments, e.g. new arrays every frame, reach it).
MAX_RECORDED = 256
#: Distinct argument sets recorded per kernel. Some launches change an argument every frame (the
#: SAH-optimized build's cluster counts, the seeds of the CPU emission's parallel runs): a
#: record of those is never replayed, so past this many a kernel's new ones launch plainly.
#: Others take one fixed set per pass of a frame: the treelet emission (CUDA's schedule) launches
#: its three kernels once per p bit planes, ceil(30 / 3) passes and the median pass, 11 sets each
#: frame, so at 8 it launched 28 kernels plainly every frame.
MAX_RECORDS_PER_KERNEL = 24


def _entry_address(entry) -> int | None:
    """The address of a kernel entry point as `KernelHooks` holds it: a ctypes function on the
    CPU, a CUDA function handle on a GPU."""
    if entry is None or isinstance(entry, int):
        return entry
    return ctypes.cast(entry, ctypes.c_void_p).value


def holds_its_code(cmd) -> bool:
    """Whether the recorded launch `cmd` keeps alive the loaded module its kernel's entry points
    are in, so that replaying it can never call unloaded code.

    `wp.launch(..., record_cmd=True)` takes the entry points (``cmd.hooks``) from the module it
    loaded, then keeps whatever a second ``kernel.module.load`` returns (``cmd.module_exec``).
    Warp 1.19's `Module.load` is not thread-safe: two threads launching a kernel of a module not
    yet loaded both load it, and the later one replaces the earlier in the module's table. When
    that replacement lands between the two calls, the record keeps the newer module and the entry
    points of the older, which Warp unloads once nothing else holds it; a replay then jumped into
    freed code (a segmentation fault in its CPU `invoke`). Compared by address, not by the hooks
    objects: two threads asking one module for a kernel's hooks at once may get two objects,
    and an address that equals the kept module's entry point is that module's code whichever
    load handed it out. Once per record, never per replay."""
    try:
        own = cmd.module_exec.get_kernel_hooks(cmd.kernel)
        return (_entry_address(own.forward) == _entry_address(cmd.hooks.forward)
                and _entry_address(own.backward) == _entry_address(cmd.hooks.backward))
    except AttributeError:  # a Warp whose Launch keeps these otherwise: trust it
        return True


def _arg_key(value):
    """What identifies an argument's packed form: an array by its memory, shape, strides and
    type (the packed struct holds nothing else), a scalar or vector by its value."""
    if isinstance(value, wp.array):
        return (value.ptr, value.shape, value.strides, value.dtype)
    if isinstance(value, (bool, int, float)):
        return (type(value), value)
    if isinstance(value, np.generic):
        return (type(value), value.item())
    scalar = getattr(value, "value", None)
    if isinstance(scalar, (bool, int, float)):
        return (type(value), scalar)
    try:
        return (type(value), tuple(value))
    except TypeError:
        # Anything else (a struct) by identity: the recorded launch keeps it alive, so the
        # identity cannot be reused while the record stands.
        return (type(value), id(value))


class RecordedLaunches:
    """``launch(kernel, dim, inputs)`` with the effect of `wp.launch`, replaying a recorded
    launch when the kernel and every argument are the same as before."""

    def __init__(self, device):
        self.device = wp.get_device(device)
        self.records: dict = {}
        # Records made per kernel since the record last started over.
        self.made: dict = {}

    def clear(self):
        """Start over: drop every record and the arrays it keeps alive (a `Builder` set up anew
        over other buffers; the old records would hold those buffers and fill the per-kernel
        quota, after which the new ones' launches went unrecorded)."""
        self.records.clear()
        self.made.clear()

    def launch(self, kernel, dim, inputs: list, vary: tuple = ()):
        """`vary`: positions of arguments that may be another array every call (a caller's input):
        left out of the key and set on the record before each replay. A record keeps its
        arguments alive, so one record per such array held every new one it was given."""
        if dim == 0:
            return
        if threads.side_by_side():
            wp.launch(kernel, dim=dim, inputs=inputs, device=self.device)
            return
        key = (kernel, *(None if i in vary else _arg_key(a) for i, a in enumerate(inputs)))
        entry = self.records.get(key)
        if entry is None:
            if self.made.get(kernel, 0) >= MAX_RECORDS_PER_KERNEL:
                wp.launch(kernel, dim=dim, inputs=inputs, device=self.device)
                return
            if len(self.records) >= MAX_RECORDED:
                self.clear()
            cmd = wp.launch(kernel, dim=dim, inputs=inputs, device=self.device, record_cmd=True)
            if not holds_its_code(cmd):
                # Recorded while another thread loaded the kernel's module: this time plainly,
                # the next call records anew.
                wp.launch(kernel, dim=dim, inputs=inputs, device=self.device)
                return
            self.made[kernel] = self.made.get(kernel, 0) + 1
            entry = self.records[key] = [cmd, dim]
        else:
            if entry[1] != dim:
                entry[0].set_dim(dim)
                entry[1] = dim
            for i in vary:
                entry[0].set_param_at_index(i, inputs[i])
        entry[0].launch()
