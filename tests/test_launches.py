"""Recorded launches (`hlbvh_warp.launches`): a replay does what `wp.launch` does."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from hlbvh_warp import launches
from hlbvh_warp.builder import Builder
from hlbvh_warp.config import BuildConfig
from hlbvh_warp.dynamic import ExplodingMesh
from hlbvh_warp.launches import RecordedLaunches
from hlbvh_warp.scenes import default_scene


@wp.kernel
def _axpy_kernel(a: float, x: wp.array(dtype=wp.vec3), shift: wp.vec3, scale: wp.float64, offset: int,
                 y: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    y[i] = a * x[i] + shift * float(scale) + wp.vec3(float(offset), 0.0, 0.0)


def test_replays_match_plain_launches(device, rng):
    # Same arguments: replayed, and the arrays' current contents are read; another launch size:
    # the replay covers it; other arrays or scalar values: recorded anew. Every result against NumPy.
    rec = RecordedLaunches(device)
    x = wp.array(rng.random((64, 3)), dtype=wp.vec3, device=device)
    y = wp.zeros(64, dtype=wp.vec3, device=device)
    other = wp.zeros(64, dtype=wp.vec3, device=device)

    def expected(a, xs, shift, scale, offset, count):
        out = a * xs[:count] + np.asarray(shift) * scale
        out[:, 0] += offset
        return out

    calls = [
        (2.0, x, wp.vec3(1.0, 2.0, 3.0), wp.float64(0.5), 0, y, 64),
        (2.0, x, wp.vec3(1.0, 2.0, 3.0), wp.float64(0.5), 0, y, 64),   # a replay
        (2.0, x, wp.vec3(1.0, 2.0, 3.0), wp.float64(0.5), 0, y, 10),   # a replay, smaller
        (3.0, x, wp.vec3(1.0, 2.0, 3.0), wp.float64(0.5), 0, y, 64),   # another scalar
        (3.0, x, wp.vec3(0.0, 2.0, 3.0), wp.float64(0.25), np.int32(7), y, 64),  # vector, float64, NumPy int
        (3.0, x, wp.vec3(0.0, 2.0, 3.0), wp.float64(0.25), np.int32(7), other, 64),  # another array
    ]
    for k, (a, xs, shift, scale, offset, out, count) in enumerate(calls):
        out.zero_()
        if k == 1:
            x.assign(rng.random((64, 3)))  # new contents, same array: the replay must read them
        rec.launch(_axpy_kernel, count, [a, xs, shift, scale, offset, out])
        got = out.numpy()
        want = expected(a, xs.numpy().astype(np.float64), tuple(shift), float(scale.value), int(offset), count)
        np.testing.assert_allclose(got[:count], want, rtol=1e-6, atol=1e-6)
        assert not got[count:].any()
    assert len(rec.records) == 4
    rec.launch(_axpy_kernel, 0, [1.0, x, wp.vec3(), wp.float64(1.0), 0, y])  # nothing to launch
    assert len(rec.records) == 4


def test_varying_argument_is_swapped_into_one_record(device, rng):
    # An argument named in `vary` may be another array every call: one record, its argument set
    # before each replay (and only the latest one kept alive), every result right.
    import gc
    import weakref

    rec = RecordedLaunches(device)
    y = wp.zeros(16, dtype=wp.vec3, device=device)
    refs = []
    for k in range(5):
        values = rng.random((16, 3))
        x = wp.array(values, dtype=wp.vec3, device=device)
        refs.append(weakref.ref(x))
        rec.launch(_axpy_kernel, 16, [2.0, x, wp.vec3(), wp.float64(0.0), 0, y], vary=(1,))
        np.testing.assert_allclose(y.numpy(), 2.0 * values, rtol=1e-6)
        del x
    gc.collect()
    assert len(rec.records) == 1
    assert sum(ref() is not None for ref in refs[:-1]) == 0


@pytest.mark.parametrize("limit", ["MAX_RECORDED", "MAX_RECORDS_PER_KERNEL"])
def test_records_stay_bounded(device, monkeypatch, limit):
    # A scalar that changes every call makes a new argument set every call. Past MAX_RECORDED the
    # record starts over; past MAX_RECORDS_PER_KERNEL a kernel's new sets launch plainly (a record
    # of them would never be replayed) and its records made before still replay. Either way
    # every result is right.
    monkeypatch.setattr(launches, limit, 3)
    rec = RecordedLaunches(device)
    x = wp.ones(4, dtype=wp.vec3, device=device)
    y = wp.zeros(4, dtype=wp.vec3, device=device)
    for a in range(10):
        rec.launch(_axpy_kernel, 4, [float(a), x, wp.vec3(), wp.float64(0.0), 0, y])
        np.testing.assert_allclose(y.numpy(), np.full((4, 3), float(a)))
        assert len(rec.records) <= 3
    if limit == "MAX_RECORDS_PER_KERNEL":
        assert len(rec.records) == 3
        rec.launch(_axpy_kernel, 4, [1.0, x, wp.vec3(), wp.float64(0.0), 0, y])
        np.testing.assert_allclose(y.numpy(), np.ones((4, 3)))


@pytest.mark.parametrize("method", ["hlbvh", "lbvh", "hlbvh_sah"])
def test_builder_frames_equal_plain_launches(device, method):
    # A Builder records its launches; one made to launch plainly must give the same trees,
    # frame after frame, under a policy that rebuilds, refits and measures.
    v, f = default_scene(3000)
    mesh = ExplodingMesh(v, f, device=device, seed=4)
    recorded = Builder(len(mesh.faces), device=device, method=method, policy="auto", max_refits=2)
    plain = Builder(len(mesh.faces), device=device, method=method, policy="auto", max_refits=2,
                    record_launches=False)
    assert plain.pipeline.launches is None
    for b in (recorded, plain):
        b.build(mesh.vertices, mesh.faces)
    assert recorded.pipeline.launches is not None
    decisions = set()
    for frame in range(1, 7):
        vertices = mesh.update(frame / 240.0 if frame < 4 else frame / 12.0)
        reports = [b.update(vertices) for b in (recorded, plain)]
        assert reports[0]["decision"] == reports[1]["decision"]
        decisions.add(reports[0]["decision"])
        a, b = recorded.bvh.to_numpy(), plain.bvh.to_numpy()
        for name in ("node_left", "node_right", "node_begin", "node_end", "prim_order", "node_lowers",
                     "node_uppers"):
            np.testing.assert_array_equal(a[name], b[name], err_msg=f"frame {frame}: {name}")
    assert {"refit", "rebuild"} <= decisions, decisions
    assert len(recorded.pipeline.launches.records) > 0


def _count_plain_launches(monkeypatch) -> list:
    """From now on, the kernels launched through plain `wp.launch` (not made into a record)."""
    plain = []
    real_launch = wp.launch

    def counting_launch(kernel, *args, **kwargs):
        if not kwargs.get("record_cmd", False):
            plain.append(getattr(kernel, "key", kernel))
        return real_launch(kernel, *args, **kwargs)

    monkeypatch.setattr(wp, "launch", counting_launch)
    return plain


@pytest.mark.parametrize("policy, emission", [("refit", "auto"), ("rebuild", "auto"), ("rebuild", "treelets")])
def test_a_recording_builders_frames_launch_nothing_plainly(device, monkeypatch, policy, emission):
    # Packing a launch's arguments costs more than a small mesh's whole refit: the node-box
    # sweep of a refit frame went through plain `wp.launch` (0.11 ms a frame at 80 triangles on
    # the CPU, 0.08 recorded). Once warm, every frame's launches must be replays.
    # The treelet emission (CUDA's default) launches its kernels once per pass of bit planes:
    # eleven argument sets a frame, past the eight a kernel could record.
    v, f = default_scene(2000)
    builder = Builder(len(f), BuildConfig(emission=emission), device=device, policy=policy)
    builder.build(v, f)
    frames = [v * np.float32(1.0 + 0.001 * k) for k in range(1, 6)]
    for frame in frames[:2]:
        builder.update(frame)
    plain = _count_plain_launches(monkeypatch)
    for frame in frames[2:]:
        assert builder.update(frame)["decision"] == policy
    assert plain == []


def test_a_builder_set_up_anew_over_new_buffers_records_afresh(device, monkeypatch):
    # A second build() with another vertex count allocates new vertex buffers; the records over
    # the old ones stayed, holding them, and after eight such set-ups each kernel's quota was
    # full: the new buffers' launches went unrecorded for the builder's life.
    v, f = default_scene(1000)
    builder = Builder(len(f), device=device, policy="refit")
    counts = []
    for extra in range(10):
        grown = np.concatenate([v, np.zeros((extra + 1, 3), np.float32)])
        builder.build(grown, f)
        builder.update(grown * np.float32(1.001))
        counts.append(len(builder.pipeline.launches.records))
    assert counts == counts[:1] * len(counts)  # one set-up's records, not all of them
    plain = _count_plain_launches(monkeypatch)
    for k in range(2, 5):
        assert builder.update(grown * np.float32(1.0 + 0.001 * k))["decision"] == "refit"
    assert plain == []


def test_recording_builders_survive_side_by_side_launches(tmp_path):
    # On a multi-core CPU parts of a build run as launches side by side (`hlbvh_warp.threads`);
    # recorded launches made or replayed there crashed the process with a segmentation fault
    # (hlbvh_sah, two threads). Run in a child process, so that a crash fails this test alone.
    import subprocess
    import sys

    script = tmp_path / "frames.py"
    script.write_text(
        "import warp as wp\n"
        "wp.config.quiet = True\n"
        "from hlbvh_warp.builder import Builder\n"
        "from hlbvh_warp.config import BuildConfig\n"
        "from hlbvh_warp.dynamic import ExplodingMesh\n"
        "from hlbvh_warp.scenes import default_scene\n"
        "v, f = default_scene(60000)\n"
        "with wp.ScopedDevice('cpu'):\n"
        "    mesh = ExplodingMesh(v, f, seed=0)\n"
        "    for method in ('hlbvh_sah', 'hlbvh'):\n"
        "        for rep in range(3):\n"
        "            b = Builder(len(mesh.faces), BuildConfig(cpu_threads=2), method=method)\n"
        "            b.build(mesh.update(0.0), mesh.faces)\n"
        "            for k in range(1, 8):\n"
        "                b.rebuild(mesh.update(k / 24.0))\n"
        "print('done')\n"
    )
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0 and "done" in result.stdout, (result.returncode, result.stderr[-2000:])


def test_a_record_keeping_another_load_than_its_entry_points_is_dropped(device, monkeypatch):
    # `wp.launch(..., record_cmd=True)` takes the kernel's entry points from the module it
    # loaded, then the Launch keeps what a second load returns. Another thread loading the module
    # in between (Warp's Module.load is not thread-safe) left a record holding one load and
    # calling into the other, which Warp unloaded: its replay crashed the process. Here that
    # second load is made to load anew: such a record must be refused and the launch made
    # plainly, and the next call, with no load in between, records as usual.
    from hlbvh_warp.launches import holds_its_code

    x = wp.array(np.ones((8, 3)), dtype=wp.vec3, device=device)
    y = wp.zeros(8, dtype=wp.vec3, device=device)
    args = [2.0, x, wp.vec3(), wp.float64(0.0), 0, y]
    wp.launch(_axpy_kernel, dim=8, inputs=args, device=device)  # loaded before
    module = _axpy_kernel.module
    replaced = []
    real_init = wp.Launch.__init__

    def reloading_init(self, kernel, *rest, **kwargs):
        # As another thread's load replacing this one's. The replaced load is kept alive here:
        # freed, its code's place could go to the next load's (Warp places a CPU module's code on
        # its first lookup), and the entry points would then be the same, the replay safe.
        replaced.extend(module.execs.values())
        module.execs = {}
        real_init(self, kernel, *rest, **kwargs)

    monkeypatch.setattr(wp.Launch, "__init__", reloading_init)
    torn = wp.launch(_axpy_kernel, dim=8, inputs=args, device=device, record_cmd=True)
    assert not holds_its_code(torn)
    del torn  # never replayed: its entry points may be unloaded code
    rec = RecordedLaunches(device)
    y.zero_()
    rec.launch(_axpy_kernel, 8, args)
    np.testing.assert_allclose(y.numpy(), np.full((8, 3), 2.0))
    assert len(rec.records) == 0 and not rec.made
    monkeypatch.setattr(wp.Launch, "__init__", real_init)
    y.zero_()
    rec.launch(_axpy_kernel, 8, args)
    np.testing.assert_allclose(y.numpy(), np.full((8, 3), 2.0))
    (cmd, _), = rec.records.values()
    assert holds_its_code(cmd)


BUILDERS_LOADING_MODULES_SCRIPT = """
import sys, threading
import numpy as np, warp as wp
wp.config.quiet = True
import warp._src.context as warp_context
import hlbvh_warp as hb
from hlbvh_warp.launches import holds_its_code
from hlbvh_warp.scenes import default_scene

meshes = [default_scene(n) for n in (400, 1500)]
rng = np.random.default_rng(0)
origins = rng.normal(size=(64, 3)).astype(np.float32) * 3
other = hb.build(*meshes[1], device="cpu")
for round in range(60):
    # Each round's first launches load the library's modules afresh, as a process's first
    # frames do: Warp forgets the loaded ones (records made before keep theirs alive).
    for module in list(warp_context.user_modules.values()):
        if module.name.startswith("hlbvh_warp."):
            module.execs = {}
    start = threading.Barrier(3)
    builders = [None, None]

    def drive(i):
        v, f = meshes[i]
        start.wait()
        b = hb.Builder(len(f), device="cpu", policy="auto")
        b.build(v, f)
        for k in range(1, 7):
            b.update(v * np.float32(1.0 + 0.01 * k))
        builders[i] = b

    def query():
        start.wait()
        hb.intersect(other, origins, -origins)
        hb.closest_point(other, origins)
        hb.overlapping_pairs(other)

    threads = [threading.Thread(target=drive, args=(0,)), threading.Thread(target=drive, args=(1,)),
               threading.Thread(target=query)]
    [t.start() for t in threads]
    [t.join() for t in threads]
    torn = [cmd.kernel.key for b in builders for cmd, _ in b.pipeline.launches.records.values()
            if not holds_its_code(cmd)]
    assert not torn, (round, torn)
print("done")
"""


def test_builders_first_launching_in_several_threads_record_safely():
    # Two recording Builders, each built and updated in its own thread, and a third thread
    # querying: their first launches load Warp modules in several threads at once, and a record
    # made meanwhile could keep one load of a module while calling into another, unloaded one.
    # Its replay crashed the process (a segmentation fault in Warp's CPU `invoke`) within a few
    # rounds in every run. In a child process, so that a crash fails this test alone.
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-c", BUILDERS_LOADING_MODULES_SCRIPT], capture_output=True,
                            text=True, timeout=300)
    assert result.returncode == 0 and "done" in result.stdout, (result.returncode, result.stderr[-2000:])


@wp.kernel
def _shape_kernel(x: wp.array(dtype=float), out: wp.array(dtype=float)):
    i = wp.tid()
    out[i] = float(x.shape[0]) * 1000.0 + x[i % x.shape[0]]


def test_views_of_one_address_are_recorded_apart(device):
    # Views that start at the same address but differ in shape or in strides pack differently:
    # a replay of another view's record read the wrong elements or the wrong length.
    rec = RecordedLaunches(device)
    base = wp.array(np.arange(16, dtype=np.float32), dtype=float, device=device)
    out = wp.zeros(4, dtype=float, device=device)
    whole = np.arange(16, dtype=np.float64)
    for view, values in ((base, whole), (base[:4], whole[:4]), (base[::4], whole[::4]), (base[:8], whole[:8])):
        assert view.ptr == base.ptr
        rec.launch(_shape_kernel, 4, [view, out])
        expected = len(values) * 1000.0 + values[np.arange(4) % len(values)]
        np.testing.assert_array_equal(out.numpy(), expected)
    assert len(rec.records) == 4


def test_replayed_launch_sizes_follow_every_change(device):
    # One record replayed at 64, 10 and 64 again: each replay covers exactly its own size.
    rec = RecordedLaunches(device)
    x = wp.array(np.ones((64, 3)), dtype=wp.vec3, device=device)
    y = wp.zeros(64, dtype=wp.vec3, device=device)
    for count in (64, 10, 64, 64, 3, 10):
        y.zero_()
        rec.launch(_axpy_kernel, count, [1.0, x, wp.vec3(), wp.float64(0.0), 0, y])
        got = y.numpy()
        assert (got[:count] == 1.0).all() and not got[count:].any(), count
    assert len(rec.records) == 1


def test_starting_over_resets_the_per_kernel_counts(device, monkeypatch):
    # Past MAX_RECORDED the record starts over, per-kernel counts included: the kernel's next
    # argument sets are recorded again rather than launched plainly for good.
    monkeypatch.setattr(launches, "MAX_RECORDED", 3)
    monkeypatch.setattr(launches, "MAX_RECORDS_PER_KERNEL", 4)
    rec = RecordedLaunches(device)
    x = wp.ones(4, dtype=wp.vec3, device=device)
    y = wp.zeros(4, dtype=wp.vec3, device=device)
    for a in range(12):
        rec.launch(_axpy_kernel, 4, [float(a), x, wp.vec3(), wp.float64(0.0), 0, y])
        np.testing.assert_allclose(y.numpy(), np.full((4, 3), float(a)))
        assert rec.made[_axpy_kernel] == len(rec.records) == a % 3 + 1
