"""Subtrees built side by side on CPU cores give the same tree as one thread."""

from __future__ import annotations

import io
import sys

import numpy as np
import pytest

import hlbvh_warp as hw
from hlbvh_warp import threads
from oracles import check_tree_invariants, random_soup

METHODS = ["hlbvh", "lbvh", "hlbvh_sah", "sweep_sah", "binned_sah", "median"]


def canonical(tree):
    """Nodes as (begin, end, box) rows in a fixed order: the tree up to node numbering."""
    rows = np.column_stack([tree["node_begin"], tree["node_end"], tree["node_lowers"], tree["node_uppers"]])
    return rows[np.lexsort(rows.T[::-1])]


@pytest.mark.parametrize("method", METHODS)
def test_threaded_builds_equal_one_thread(device, rng, method):
    # Large enough for every parallel path (top-down: 4096 items; emission: 8192 primitives).
    n = 12_000
    v, f = random_soup(rng, n)
    trees = []
    for count in (1, 2, 3):
        bvh = hw.build(v, f, method=method, device=device, config=hw.BuildConfig(cpu_threads=count))
        tree = bvh.to_numpy()
        check_tree_invariants(tree, n, 1, exact_node_count=2 * n - 1)
        trees.append(tree)
    for tree in trees[1:]:
        assert np.array_equal(tree["prim_order"], trees[0]["prim_order"])
        assert np.array_equal(canonical(tree), canonical(trees[0]))



@pytest.mark.parametrize("threads_count", [2, 3])
def test_top_split_balances_a_lopsided_tree(device, rng, threads_count):
    # 90% of the triangles in one corner: the root's radix split leaves one half with about 90%
    # of them, so splitting the root alone would hand one thread nine tenths of the walk. The
    # top split must cut seeds of at most N / (4 threads), and the tree must be one thread's.
    if device != "cpu":
        pytest.skip("threads split only the CPU device's serial walks")
    from hlbvh_warp.builder import Builder

    n = 16_000
    v, f = random_soup(rng, n)
    v[: 3 * (9 * n // 10)] *= 0.05
    trees = []
    for count in (1, threads_count):
        builder = Builder(n, hw.BuildConfig(cpu_threads=count), device=device, resort=False)
        tree = builder.build(v, f).to_numpy()
        check_tree_invariants(tree, n, 1, exact_node_count=2 * n - 1)
        trees.append(tree)
    pipe = builder.pipeline
    seeds = int(pipe.top_seed_count.numpy()[0])
    starts = pipe.top_seed_starts.numpy()[:seeds]
    sizes = np.diff(np.append(starts, n))
    assert seeds > 2 and starts[0] == 0 and (sizes >= 1).all()
    assert sizes.max() <= n // (4 * threads_count), sizes
    # The seeds are the subtrees of nodes seeds - 1 .. 2 seeds - 2, each under the top nodes.
    tree = trees[1]
    roots = np.arange(seeds - 1, 2 * seeds - 1)
    np.testing.assert_array_equal(tree["node_begin"][roots], starts)
    assert ((tree["node_parent"][roots] >= 0) & (tree["node_parent"][roots] < seeds - 1)).all()
    np.testing.assert_array_equal(trees[1]["prim_order"], trees[0]["prim_order"])
    np.testing.assert_array_equal(canonical(trees[1]), canonical(trees[0]))


def test_threaded_leaf_size_falls_back(device, rng):
    # With several primitives per leaf node counts are not known in advance: one thread, same tree.
    v, f = random_soup(rng, 10_000)
    a = hw.build(v, f, method="sweep_sah", device=device, config=hw.BuildConfig(cpu_threads=1, max_leaf_size=4))
    b = hw.build(v, f, method="sweep_sah", device=device, config=hw.BuildConfig(cpu_threads=2, max_leaf_size=4))
    assert np.array_equal(canonical(a.to_numpy()), canonical(b.to_numpy()))


def test_run_reraises_and_runs_every_job():
    done = []

    def ok(i):
        return lambda: done.append(i)

    def bad():
        raise RuntimeError("job failed")

    with pytest.raises(RuntimeError, match="job failed"):
        threads.run([ok(0), bad, ok(2), ok(3)], 2)
    threads.run([ok(4), ok(5), ok(6)], 3)
    assert sorted(done)[-3:] == [4, 5, 6] and {0, 2, 3} <= set(done)


def test_run_returns_only_after_every_job_finished():
    # A failed job's error is re-raised only once the other jobs have finished: raised at once,
    # run() returned while a pool job still ran, outside the side-by-side stretch.
    import time

    events = []

    def bad():
        raise RuntimeError("job failed")

    def slow():
        time.sleep(0.3)
        events.append(("slow", threads.side_by_side()))

    # The caller takes the first job, the pool the failing one and the slow one.
    with pytest.raises(RuntimeError, match="job failed"):
        threads.run([lambda: None, bad, slow], 3)
    assert events == [("slow", True)]


def test_bad_thread_count():
    with pytest.raises(ValueError, match="cpu_threads"):
        hw.BuildConfig(cpu_threads=-1)


def test_split_bounds_cover_every_index_once():
    for num, parts in ((1, 4), (7, 3), (12_000, 2), (12_001, 16)):
        cuts = threads.split_bounds(num, parts)
        assert cuts[0] == 0 and cuts[-1] == num and len(cuts) == min(parts, num) + 1
        sizes = np.diff(cuts)
        assert sizes.min() >= 1 and sizes.max() - sizes.min() <= 1


def test_resorted_frames_equal_with_split_gathers(device):
    # The resort gather and the Morton pass run in slices side by side on a multi-core CPU: the
    # frames' codes and trees must be those of one thread, bit for bit.
    from hlbvh_warp.builder import Builder
    from hlbvh_warp.dynamic import ExplodingMesh
    from hlbvh_warp.scenes import default_scene

    v, f = default_scene(12_000)
    mesh = ExplodingMesh(v, f, device=device, seed=4)
    builders = [Builder(len(f), hw.BuildConfig(cpu_threads=count), device=device, resort=resort)
                for count in (1, 3) for resort in (True, False)]
    for builder in builders:
        builder.build(mesh.vertices, mesh.faces)
    if device == "cpu":
        assert builders[0].gather_parts is None and len(builders[2].gather_parts) == 3
    for frame in range(1, 4):
        vertices = mesh.update(frame / 24.0)
        trees, codes = [], []
        for builder in builders:
            trees.append(builder.rebuild(vertices).to_numpy())
            codes.append(builder.pipeline.morton_codes.numpy().copy())
        for i in (2, 3):
            np.testing.assert_array_equal(codes[i], codes[i - 2])
            np.testing.assert_array_equal(trees[i]["prim_order"], trees[i - 2]["prim_order"])
            np.testing.assert_array_equal(canonical(trees[i]), canonical(trees[i - 2]))


def test_launch_parts_compiles_a_module_once(tmp_path, monkeypatch):
    """A kernel whose module is not loaded yet, launched first in parts on two threads, is
    compiled once (launched first from both threads, each compiled it)."""
    import importlib.util
    import uuid

    import numpy as np
    import warp as wp

    from hlbvh_warp import threads as threads_module

    name = f"fresh_{uuid.uuid4().hex[:8]}"
    path = tmp_path / f"{name}.py"
    path.write_text(
        "import warp as wp\n\n\n"
        "@wp.kernel\n"
        "def double(first: int, a: wp.array(dtype=float)):\n"
        "    i = first + wp.tid()\n"
        "    a[i] = 2.0 * float(i)\n"
    )
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    loads = []
    original = type(module.double.module).load

    def counting_load(self, device, block_dim=None, *args, **kwargs):
        # A load that finds no executable for its block size compiles (or reads the cache).
        key = (device.context, block_dim if block_dim is not None else self.options["block_dim"])
        missing = key not in self.execs
        result = original(self, device, block_dim, *args, **kwargs)
        if missing:
            loads.append((threading.current_thread().name, key[1]))
        return result

    import threading

    monkeypatch.setattr(type(module.double.module), "load", counting_load)
    a = wp.zeros(2000, dtype=float, device="cpu")
    parts = [(1000, [0, a]), (1000, [1000, a])]
    threads_module.launch_parts(module.double, "cpu", parts, 2)
    np.testing.assert_array_equal(a.numpy(), 2.0 * np.arange(2000))
    assert len(loads) == 1, loads


def test_default_thread_count_uses_every_usable_core():
    import warp as wp

    cpu = wp.get_device("cpu")
    assert threads.resolved_threads(hw.BuildConfig(), cpu) == threads.usable_cores()
    assert threads.resolved_threads(hw.BuildConfig(cpu_threads=3), cpu) == 3
    assert threads.resolved_threads(hw.BuildConfig(cpu_threads=1), cpu) == 1


def test_two_jobs_on_two_threads_run_side_by_side():
    # Two jobs and two threads: the pool takes the second while the caller runs the first.
    import threading

    seen = []

    def job():
        seen.append((threading.current_thread().name, threads.side_by_side()))

    threads.run([job, job], 2)
    assert len({name for name, _ in seen}) == 2 and all(flag for _, flag in seen), seen
    assert not threads.side_by_side()


ONE_BUILDER_TWO_THREADS_SCRIPT = """
import sys, threading
import numpy as np, trimesh, warp as wp
wp.config.quiet = True
import hlbvh_warp as hb
mesh = trimesh.creation.icosphere(subdivisions=3)
v, f = np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)
for record in (True, False):
    b = hb.Builder(len(f), device="cpu", record_launches=record)
    b.build(v, f)
    frames = [v * (1.0 + 0.01 * k) for k in range(30)]
    errors = []
    def drive(order):
        try:
            for k in order:
                b.rebuild(frames[k])
        except Exception as exc:
            errors.append(exc)
    threads = [threading.Thread(target=drive, args=(order,)) for order in (range(30), range(29, -1, -1))]
    [t.start() for t in threads]
    [t.join() for t in threads]
    assert not errors, errors
    # The calls took turns, so the tree is one frame's whole: its root box is that frame's
    # (min and max are exact), and its SAH cost a fresh build's of that frame.
    root = b.bvh.to_numpy()["node_uppers"][0]
    last = [k for k in range(30) if np.array_equal(root, frames[k].max(axis=0))]
    assert len(last) == 1, last
    ref = hb.build(frames[last[0]], f, device="cpu")
    assert abs(hb.metrics.sah_cost(b.bvh) / hb.metrics.sah_cost(ref) - 1.0) < 1e-6
    assert len(b.reports) == 61, len(b.reports)
print("done")
"""


def test_one_builder_from_two_threads_takes_turns():
    """Two threads rebuilding one Builder at once crashed the process (with launches recorded or
    not): its calls now take turns. In a child process, so a crash fails this test alone."""
    import subprocess

    result = subprocess.run([sys.executable, "-c", ONE_BUILDER_TWO_THREADS_SCRIPT], capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0 and "done" in result.stdout, (result.returncode, result.stderr[-2000:])


QUERIES_DURING_UPDATES_SCRIPT = """
import threading
import numpy as np, trimesh, warp as wp
import hlbvh_warp as hb
mesh = trimesh.creation.icosphere(subdivisions=3)
v, f = np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)
other = hb.build(v * np.float32(0.9) + np.float32(0.5), f, device="cpu")
frames = [v, (v * np.float32(1.1) + np.float32(0.2)).astype(np.float32)]
rng = np.random.default_rng(0)
o = rng.normal(size=(300, 3)).astype(np.float32) * 3
d = (-o + rng.normal(size=(300, 3)).astype(np.float32) * 0.3).astype(np.float32)
boxes = v[:64] - np.float32(0.1), v[:64] + np.float32(0.1)

def answers(bvh):
    return (tuple(map(tuple, hb.intersecting_pairs(bvh, other).tolist())),
            tuple(map(tuple, hb.overlapping_pairs(bvh, other).tolist())),
            tuple(map(tuple, hb.query_aabb(bvh, *boxes, return_pairs=True)[1].tolist())),
            tuple(np.concatenate(hb.intersect_all(bvh, o, d)[:2]).tolist()),
            tuple(hb.intersect(bvh, o, d)[1].tolist()))

expected = [answers(hb.build(frame, f, device="cpu")) for frame in frames]
assert expected[0] != expected[1]
for policy in ("rebuild", "refit"):
    b = hb.Builder(len(f), device="cpu", policy=policy)
    b.build(frames[0], f)
    stop = threading.Event()
    errors = []
    def update():
        k = 0
        while not stop.is_set():
            k += 1
            b.update(frames[k % 2])
    t = threading.Thread(target=update)
    t.start()
    try:
        for _ in range(15):
            got = answers(b.bvh)
            # Each query holds the builder's lock: it sees one frame's whole tree (the five may
            # see different frames). A refit tree answers as the fresh build of its frame does.
            wrong = [i for i, g in enumerate(got) if g not in (expected[0][i], expected[1][i])]
            if wrong:
                errors.append(wrong)
    finally:
        stop.set()
        t.join()
    assert not errors, (policy, len(errors), errors[:3])
    # The five together inside hold(): all of one frame.
    stop.clear()
    t = threading.Thread(target=update)
    t.start()
    try:
        for _ in range(5):
            with b.bvh.hold():
                assert answers(b.bvh) in expected
    finally:
        stop.set()
        t.join()
print("done")
"""


def test_queries_while_another_thread_updates_see_whole_frames():
    """Pair queries count, then write: a tree rebuilt between the passes got fewer pairs written
    than counted, and the unwritten rest (garbage ids) crashed `intersecting_pairs` in every run.
    Host queries now hold the builder's lock. In a child process, so a crash fails this alone."""
    import subprocess

    result = subprocess.run([sys.executable, "-c", QUERIES_DURING_UPDATES_SCRIPT], capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0 and "done" in result.stdout, (result.returncode, result.stderr[-2000:])


def test_a_pair_query_inside_another_trees_hold_does_not_deadlock(device):
    # Locks taken in one fixed order deadlocked here: the first thread holds the second lock
    # (its own kernel under `hold()`) and then asks for both, the second thread holds the first
    # and waits for the second. Both are taken together or not at all now.
    import threading
    import time

    rng = np.random.default_rng(0)

    def soup(n):
        v = (rng.uniform(-1, 1, (n, 1, 3)) + rng.normal(0, 0.05, (n, 3, 3))).astype(np.float32).reshape(-1, 3)
        return v, np.arange(3 * n, dtype=np.int32).reshape(-1, 3)

    builders = [hw.Builder(100, device=device), hw.Builder(120, device=device)]
    a, b = (builder.build(*soup(n)) for builder, n in zip(builders, (100, 120)))
    expected = hw.overlapping_pairs(a, b)
    later = a if id(a._lock) > id(b._lock) else b
    ready, results = threading.Event(), []

    def inside_hold():
        with later.hold():
            ready.set()
            time.sleep(0.3)
            results.append(hw.overlapping_pairs(a, b))

    def plain():
        ready.wait()
        results.append(hw.overlapping_pairs(a, b))

    workers = [threading.Thread(target=inside_hold, daemon=True), threading.Thread(target=plain, daemon=True)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join(30)
    assert len(results) == 2, "deadlocked"
    for pairs in results:
        np.testing.assert_array_equal(pairs, expected)


def test_a_huge_thread_count_is_capped_per_core(device):
    """Each thread of a build gets its work part and a share of the scratch: 2^31 - 1 threads
    asked for had a `Builder` allocate 8.6 GB and fail inside Warp, and 100,000 slowed a small
    one-shot build from under a second to 20 s. Past four per usable core the count is capped;
    off the CPU it is always one, and 0 still means every core."""
    import warp as wp

    from hlbvh_warp.builder import Builder
    from hlbvh_warp.threads import MAX_THREADS_PER_CORE, resolved_threads, usable_cores

    dev = wp.get_device(device)
    cap = MAX_THREADS_PER_CORE * usable_cores()
    for asked, cpu_threads in ((2**31 - 1, cap), (cap + 1, cap), (2, min(2, cap)), (0, usable_cores())):
        got = resolved_threads(hw.BuildConfig(cpu_threads=asked), dev)
        assert got == (cpu_threads if dev.is_cpu else 1), (asked, got)
    v, f = random_soup(np.random.default_rng(3), 300)
    builder = Builder(300, hw.BuildConfig(cpu_threads=2**31 - 1), device=device)
    tree = builder.build(v, f).to_numpy()
    check_tree_invariants(tree, 300, 1, exact_node_count=599)


def test_depth_read_while_another_thread_updates_is_not_kept_past_the_update(device, monkeypatch):
    """`Bvh.depth` computed the depth from a host copy taken under the builder's lock but stored it
    after letting go: an update in between (another thread) emptied the cache, and the old frame's
    depth went into the new frame's, where every later read found it. The update is made to land
    in that gap (or, once depth holds the lock throughout, to wait for it): the lock is wrapped so
    that the second thread says whether it got the lock or had to wait."""
    import threading

    from hlbvh_warp import bvh as bvh_module

    def oracle_depth(parent):
        # Edges from each node up to the root, walked in Python.
        depths = []
        for node in range(parent.shape[0]):
            steps = 0
            while parent[node] >= 0:
                node, steps = parent[node], steps + 1
            depths.append(steps)
        return max(depths)

    n = 64
    v, f = random_soup(np.random.default_rng(5), n)
    deep = v.copy()
    # Centroids spaced ever wider along x: each split cuts one triangle off, a deeper tree.
    deep[:, 0] = np.repeat(np.arange(n, dtype=np.float32) ** 8, 3)
    expected = [oracle_depth(hw.build(frame, f, device=device).to_numpy()["node_parent"]) for frame in (v, deep)]
    assert expected[0] != expected[1], expected
    builder = hw.Builder(n, device=device)
    tree = builder.build(v, f)
    updater = None
    decided = threading.Event()  # the second thread has updated, or waits for the lock

    class Watched:
        def __init__(self, lock):
            self.lock = lock

        def acquire(self, blocking=True, timeout=-1):
            if self.lock.acquire(blocking=False):
                return True
            if not blocking:
                return False
            if threading.current_thread() is updater:
                decided.set()
            return self.lock.acquire(True, timeout)

        def release(self):
            self.lock.release()

        __enter__ = acquire

        def __exit__(self, *exc):
            self.release()

    watched = Watched(builder._lock)
    builder._lock = tree._lock = watched
    real_depths = bvh_module.node_depths
    reached = threading.Event()

    def depths_after_an_update(arrays):
        reached.set()
        assert decided.wait(30), "the second thread neither updated nor waited"
        return real_depths(arrays)

    monkeypatch.setattr(bvh_module, "node_depths", depths_after_an_update)

    def update():
        assert reached.wait(30)
        builder.update(deep)
        decided.set()

    updater = threading.Thread(target=update, daemon=True)
    updater.start()
    during = tree.depth
    updater.join(30)
    assert not updater.is_alive()
    monkeypatch.setattr(bvh_module, "node_depths", real_depths)
    assert during in expected
    assert tree.depth == expected[1], (tree.depth, expected)


def _fail_a_frame_in_its_emission(builder, vertices, monkeypatch):
    """One frame of ``builder`` (a rebuild under every policy: large motion) over ``vertices``
    whose emission raises in a worker thread, leaving half a tree."""
    import sys as _sys

    real_run = threads.run

    def emission_fails_in_a_worker(jobs, count):
        jobs = list(jobs)
        if _sys._getframe(1).f_code.co_name == "emit_depth_first":
            def fail():
                raise RuntimeError("injected worker failure")

            # Job 1 goes to the pool (the caller takes every `count`-th job from job 0).
            jobs[1] = fail
        return real_run(jobs, count)

    monkeypatch.setattr(threads, "run", emission_fails_in_a_worker)
    with pytest.raises(RuntimeError, match="injected worker failure"):
        if builder.policy == "auto":
            builder.update(vertices)
        else:
            builder.rebuild(vertices)
    monkeypatch.setattr(threads, "run", real_run)


def test_queries_refuse_the_half_tree_of_a_frame_that_raised(device, monkeypatch):
    """After a frame that raised partway, and until the next frame, the tree mixes two frames:
    queries on it gave wrong hit ids (4% right) and a fraction of the pairs, as if it were whole.
    Every query, the views for user kernels and `hold()` now refuse it, naming why; a refused
    input in between leaves it refused; the next frame answers for its own vertices again."""
    from hlbvh_warp import metrics
    from hlbvh_warp.bvh import UNFINISHED_TREE
    from hlbvh_warp.reference import brute_force_closest_hit

    if device != "cpu":
        pytest.skip("worker threads run only the CPU device's launches")
    n = 10_000
    rng = np.random.default_rng(3)
    v0, f = random_soup(rng, n)
    v1 = (v0 * np.float32(1.5) + rng.random(v0.shape).astype(np.float32)).astype(np.float32)
    builder = hw.Builder(n, hw.BuildConfig(cpu_threads=2), device=device, policy="auto")
    builder.build(v0, f)
    tree = builder.bvh
    _fail_a_frame_in_its_emission(builder, v1, monkeypatch)
    o = np.zeros((4, 3), np.float32)
    d = np.tile(np.float32([0.3, 0.5, 1.0]), (4, 1))
    queries = {
        "intersect": lambda: hw.intersect(tree, o, d),
        "closest_point": lambda: hw.closest_point(tree, o),
        "query_aabb": lambda: hw.query_aabb(tree, o - 1, o + 1),
        "intersecting_pairs": lambda: hw.intersecting_pairs(tree),
        "sah_cost": lambda: metrics.sah_cost(tree),
        "builder.sah_cost": builder.sah_cost,
        "to_numpy": tree.to_numpy,
        "depth": lambda: tree.depth,
        "view": tree.view,
        "save_bvh": lambda: hw.save_bvh(tree, io.BytesIO()),
    }
    for name, query in queries.items():
        with pytest.raises(RuntimeError, match="unfinished"):
            query()
    with pytest.raises(RuntimeError, match="unfinished"):
        with tree.hold():
            pass
    with pytest.raises(ValueError):
        builder.update(v1[:-1])  # refused before it writes: the tree stays half written
    with pytest.raises(RuntimeError, match="unfinished"):
        hw.intersect(tree, o, d)
    assert "Builder" in UNFINISHED_TREE
    builder.update(v1)
    assert builder.bvh is tree
    t, prim = hw.intersect(tree, o, d)
    t_ref, prim_ref = brute_force_closest_hit(v1, f, o, d)
    np.testing.assert_array_equal(prim, prim_ref)
    np.testing.assert_allclose(t, t_ref, rtol=1e-5)


@pytest.mark.parametrize("policy", ["auto", "refit", "rebuild"])
def test_a_frame_that_raised_in_a_worker_is_not_kept_by_the_next(device, monkeypatch, policy):
    """A rebuild whose emission raised in a worker thread (one run of seeds never written) left
    half a tree behind, and the next frame kept it: under `auto` the same vertices again were "no
    vertex moved", under `refit` the half tree was refit. The next frame now builds from scratch,
    whatever the policy, and gives the tree a one-shot build of that frame gives."""
    if device != "cpu":
        pytest.skip("worker threads run only the CPU device's launches")
    n = 10_000  # past PARALLEL_MIN_PRIMS: the emission runs its seeds on two threads
    rng = np.random.default_rng(7)
    v0, f = random_soup(rng, n)
    v1 = (v0 * np.float32(1.5) + rng.random(v0.shape).astype(np.float32)).astype(np.float32)
    builder = hw.Builder(n, hw.BuildConfig(cpu_threads=2), device=device, policy=policy)
    builder.build(v0, f)
    _fail_a_frame_in_its_emission(builder, v1, monkeypatch)
    report = builder.update(v1)
    assert report["decision"] == "rebuild", report
    tree = builder.bvh.to_numpy()
    check_tree_invariants(tree, n, 1, exact_node_count=2 * n - 1)
    fresh = hw.build(v1, f, device=device).to_numpy()
    assert np.array_equal(tree["prim_order"], fresh["prim_order"])
    assert np.array_equal(canonical(tree), canonical(fresh))


def test_a_pair_query_on_a_tree_its_builder_keeps_updating_finishes(device):
    """Two trees' locks were taken by trying both without waiting and, while one was busy,
    sleeping a moment and trying again. A builder updating frame after frame in another thread
    holds its lock but between two frames, and the query, which ran only when the updating
    thread let go of the interpreter (in its kernel launches, lock held), never found it free:
    it hung. It now waits for the busy lock as a one-tree query does."""
    import threading

    n = 400
    rng = np.random.default_rng(11)
    v, f = random_soup(rng, n)
    other_v, other_f = random_soup(rng, n)
    frames = [v, (v + np.float32(0.05)).astype(np.float32)]
    # Launches not recorded: the builders run in two threads (see `Builder`'s record_launches).
    moving = hw.Builder(n, device=device, record_launches=False)
    still = hw.Builder(n, device=device, record_launches=False)
    moving.build(v, f)
    still.build(other_v, other_f)
    other = hw.build(other_v, other_f, device=device)
    expected = [hw.overlapping_pairs(hw.build(frame, f, device=device), other) for frame in frames]
    stop = threading.Event()

    def update():
        k = 0
        while not stop.is_set():
            k += 1
            moving.update(frames[k % 2])

    results = []
    updater = threading.Thread(target=update, daemon=True)
    query = threading.Thread(target=lambda: results.append(hw.overlapping_pairs(moving.bvh, still.bvh)), daemon=True)
    updater.start()
    try:
        query.start()
        query.join(20)
    finally:
        stop.set()
        updater.join(30)
    assert results, "the pair query did not finish while the other thread kept updating"
    assert any(np.array_equal(results[0], pairs) for pairs in expected)


class _InterruptedWait:
    """A lock whose timed wait is interrupted (Ctrl-C), as a pair query's wait for a second tree
    busy with its builder's frame is, while the first tree's lock is held."""

    def acquire(self, blocking=True, timeout=-1):
        if timeout >= 0:
            raise KeyboardInterrupt
        return True

    def release(self):
        pass


def test_an_interrupt_while_a_pair_query_waits_lets_go_of_the_lock_it_held(device):
    """`held` takes two trees' locks by holding one and waiting a while for the other. An
    interrupt in that wait (Ctrl-C while both builders updated in other threads) left the held
    one taken for good: its builder's next frame, on another thread, hung forever."""
    import threading

    from hlbvh_warp.bvh import held

    rng = np.random.default_rng(5)
    v, f = random_soup(rng, 60)
    builder = hw.Builder(60, device=device)
    tree = builder.build(v, f)
    other = hw.build(v, f, device=device)
    other._lock = _InterruptedWait()
    with pytest.raises(KeyboardInterrupt):
        with held(tree, other):
            pass
    finished = []
    frame = threading.Thread(target=lambda: finished.append(builder.update(v)), daemon=True)
    frame.start()
    frame.join(10)
    assert finished, "the builder's lock was left taken: its next frame on another thread hung"


AFTER_MAIN_RETURNED_SCRIPT = r"""
import threading
import time

import numpy as np
import warp as wp

wp.config.quiet = True
import hlbvh_warp as hw

rng = np.random.default_rng(2)
n = 9000  # past the size from which a build's stages run side by side
v = (rng.uniform(-1, 1, (n, 1, 3)) + rng.normal(0, 0.05, (n, 3, 3))).astype(np.float32).reshape(-1, 3)
f = np.arange(3 * n, dtype=np.int32).reshape(-1, 3)
config = hw.BuildConfig(cpu_threads=2)
builder, twin = hw.Builder(n, config, device="cpu"), hw.Builder(n, config, device="cpu")
builder.build(v, f)
twin.build(v, f)
# The same calls while the main thread runs, its parts on the pool's threads.
expected = [twin.rebuild(v * np.float32(1.5)).to_numpy(), hw.build(v * np.float32(1.5), f, device="cpu",
                                                                   config=config).to_numpy()]
main = threading.main_thread()


def frames_after_main_returned():
    while main.is_alive():
        time.sleep(0.01)
    time.sleep(0.2)
    got = [builder.rebuild(v * np.float32(1.5)).to_numpy(), hw.build(v * np.float32(1.5), f, device="cpu",
                                                                     config=config).to_numpy()]
    for tree, want in zip(got, expected):
        for name in ("prim_order", "node_left", "node_right", "node_begin", "node_end", "node_lowers",
                     "node_uppers"):
            assert np.array_equal(tree[name], want[name]), name
    print("done", flush=True)


threading.Thread(target=frames_after_main_returned).start()
"""


def test_builds_in_a_thread_still_running_after_the_main_thread_returned():
    """`concurrent.futures` shuts its pools down when the main thread ends, before the threads
    still running are joined: a build on several cores in such a thread (a script that starts a
    worker and returns) raised "cannot schedule new futures after shutdown", leaving the
    `Builder`'s frame unfinished. The parts then run in the calling thread. In a child process,
    whose main thread can end."""
    import subprocess

    result = subprocess.run([sys.executable, "-c", AFTER_MAIN_RETURNED_SCRIPT], capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0 and "done" in result.stdout, (result.returncode, result.stderr[-2000:])


DEBUG_MODE_BUILD_SCRIPT = r"""
import sys

import numpy as np
import trimesh
import warp as wp

wp.config.mode = "debug"
wp.config.quiet = True
import hlbvh_warp as hw

mesh = trimesh.creation.icosphere(subdivisions=5)  # 20,480 triangles: emitted in runs side by side
v, f = np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)
for _ in range(10):
    tree = hw.build(v, f, device="cpu", config=hw.BuildConfig(cpu_threads=2)).to_numpy()
np.savez(sys.argv[1], **tree)
print("done", flush=True)
"""


def test_a_build_with_warps_debug_mode_on_gives_the_release_tree(tmp_path):
    """Warp 1.19's CPU kernels compiled in its debug mode (``wp.config.mode = "debug"``, which a
    user sets to debug kernels of their own) crash the process when two launches run at once
    (their tile storage is found through one static pointer that each launch sets and resets):
    a build on several cores segfaulted in its side-by-side emission. In that mode the parts
    now run one after another. In a child process, so a crash fails this test alone."""
    import subprocess

    import trimesh

    path = tmp_path / "tree.npz"
    result = subprocess.run([sys.executable, "-c", DEBUG_MODE_BUILD_SCRIPT, str(path)], capture_output=True,
                            text=True, timeout=600)
    assert result.returncode == 0 and "done" in result.stdout, (result.returncode, result.stderr[-2000:])
    mesh = trimesh.creation.icosphere(subdivisions=5)
    v, f = np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)
    expected = hw.build(v, f, device="cpu", config=hw.BuildConfig(cpu_threads=2)).to_numpy()
    with np.load(path) as got:
        for name, array in expected.items():
            np.testing.assert_array_equal(got[name], array, err_msg=name)
