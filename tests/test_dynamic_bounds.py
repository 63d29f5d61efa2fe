"""Builder over arbitrary primitives given by their boxes (`Builder.build_from_bounds`): a
simulation's broad phase rebuilt every frame, with every policy, checked against NumPy."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import hlbvh_warp as hw
from hlbvh_warp import metrics, query
from hlbvh_warp.builder import Builder
from hlbvh_warp.scenes import default_scene

from oracles import brute_overlaps, check_tree_invariants, numpy_node_boxes

TOPOLOGY = ("node_left", "node_right", "node_begin", "node_end")


class Particles:
    """Spheres moving at constant velocities and bouncing off the walls of the unit cube, each
    growing or shrinking a little every step: boxes that drift, cross and pile up as a
    simulation's do, whose lower and upper corners move by different amounts."""

    def __init__(self, rng, count: int, speed: float = 0.02):
        self.rng = rng
        self.centers = rng.random((count, 3))
        self.velocities = speed * rng.standard_normal((count, 3))
        self.radii = 0.002 + 0.01 * rng.random((count, 1))

    def step(self):
        self.centers += self.velocities
        out = (self.centers < 0.0) | (self.centers > 1.0)
        self.velocities[out] *= -1.0
        self.centers = np.clip(self.centers, 0.0, 1.0)
        self.radii *= 1.0 + 0.2 * (self.rng.random(self.radii.shape) - 0.5)
        return self.bounds()

    def bounds(self):
        return ((self.centers - self.radii).astype(np.float32), (self.centers + self.radii).astype(np.float32))


def check_frame(builder: Builder, lowers: np.ndarray, uppers: np.ndarray, rng, exact_boxes: bool = True):
    """The tree holds exactly these boxes, every node box is the union of its primitives' (a
    refit tree's too), and box queries match a brute force over them."""
    tree = builder.bvh.to_numpy()
    np.testing.assert_array_equal(tree["prim_lowers"], lowers)
    np.testing.assert_array_equal(tree["prim_uppers"], uppers)
    check_tree_invariants(tree, len(lowers))
    if exact_boxes:
        lo, hi = numpy_node_boxes(tree, lowers, uppers)
        np.testing.assert_array_equal(tree["node_lowers"], lo)
        np.testing.assert_array_equal(tree["node_uppers"], hi)
    q_lo = rng.random((64, 3)).astype(np.float32) * 1.1 - 0.05
    q_hi = q_lo + np.float32(0.08)
    counts, pairs = query.query_aabb(builder.bvh, q_lo, q_hi, return_pairs=True)
    expected = brute_overlaps(lowers, uppers, q_lo, q_hi)
    np.testing.assert_array_equal(counts, expected.sum(1))
    np.testing.assert_array_equal(pairs, np.argwhere(expected))


@pytest.mark.parametrize("method", ["hlbvh", "lbvh", "hlbvh_sah"])
@pytest.mark.parametrize("resort", [False, True])
def test_box_rebuilds_match_one_shot_builds(device, rng, method, resort):
    # Every frame's tree is right for that frame's boxes and as good as a one-shot build of them:
    # the same SAH cost (resorted input may swap primitives with equal codes, nothing else).
    particles = Particles(rng, 3000)
    builder = Builder(3000, device=device, method=method, resort=resort)
    lowers, uppers = particles.bounds()
    builder.build_from_bounds(lowers, uppers)
    check_frame(builder, lowers, uppers, rng)
    for frame in range(4):
        lowers, uppers = particles.step()
        host = frame % 2 == 0
        given = (lowers, uppers) if host else (wp.array(lowers, dtype=wp.vec3, device=device),
                                               wp.array(uppers, dtype=wp.vec3, device=device))
        report = builder.update(bounds=given)
        assert report["decision"] == "rebuild"
        check_frame(builder, lowers, uppers, rng)
        one_shot = hw.build_from_bounds(lowers, uppers, method=method, device=device)
        assert metrics.sah_cost(builder.bvh) == pytest.approx(metrics.sah_cost(one_shot), rel=1e-5)
        if not resort:
            tree, ref = builder.bvh.to_numpy(), one_shot.to_numpy()
            for name in TOPOLOGY + ("prim_order",):
                np.testing.assert_array_equal(tree[name], ref[name], err_msg=name)


def test_box_refit_and_in_place_frames(device, rng):
    # Refit keeps the topology and recomputes every node box; a frame written into the builder's
    # own boxes (prim_lowers / prim_uppers) and passed as nothing is read from there.
    particles = Particles(rng, 2000, speed=0.002)
    builder = Builder(2000, device=device, policy="refit")
    builder.build_from_bounds(*particles.bounds())
    topology = {name: builder.bvh.to_numpy()[name] for name in TOPOLOGY}
    for frame in range(3):
        lowers, uppers = particles.step()
        if frame == 1:
            builder.prim_lowers.assign(lowers)
            builder.prim_uppers.assign(uppers)
            report = builder.update()
        else:
            report = builder.update(bounds=(lowers, uppers))
        assert report["decision"] == "refit"
        check_frame(builder, lowers, uppers, rng)
        tree = builder.bvh.to_numpy()
        for name in TOPOLOGY:
            np.testing.assert_array_equal(tree[name], topology[name], err_msg=name)
    # In place again, rebuilt this time.
    lowers, uppers = particles.step()
    builder.prim_lowers.assign(lowers)
    builder.prim_uppers.assign(uppers)
    builder.rebuild()
    check_frame(builder, lowers, uppers, rng)


def slow_particles_under_auto(rng, device, max_refits: int):
    """2,000 slowly moving particles and an `auto` builder set up on their first frame."""
    particles = Particles(rng, 2000, speed=0.0005)
    builder = Builder(2000, device=device, policy="auto", max_refits=max_refits)
    lowers, uppers = particles.bounds()
    builder.build_from_bounds(lowers, uppers)
    return particles, builder, lowers, uppers


def test_auto_policy_on_boxes(device, rng):
    # `auto` measures how far a box corner moved (checked against NumPy), does nothing when no
    # box moved, refits slow motion and rebuilds fast motion; every tree stays right.
    particles, builder, lowers, uppers = slow_particles_under_auto(rng, device, max_refits=3)
    decisions, reasons = [], []
    for frame in range(8):
        if frame == 5:
            particles.velocities *= 200.0  # a burst
        new_lowers, new_uppers = particles.step()
        report = builder.update(bounds=(new_lowers, new_uppers))
        expected = max(np.linalg.norm(new_lowers.astype(np.float64) - lowers, axis=1).max(),
                       np.linalg.norm(new_uppers.astype(np.float64) - uppers, axis=1).max())
        assert expected > 0.0
        assert report["max_displacement"] == pytest.approx(expected, rel=1e-5)
        decisions.append(report["decision"])
        reasons.append(report["reason"])
        lowers, uppers = new_lowers, new_uppers
        check_frame(builder, lowers, uppers, rng)
    assert "refit" in decisions[:5] and decisions[5] == "rebuild", decisions
    # The burst's reason names what was measured: boxes, which have corners, not vertices.
    assert "large motion: a box corner moved" in reasons[5], reasons[5]
    report = builder.update(bounds=(lowers.copy(), uppers.copy()))
    assert report["decision"] == "none" and "no box moved" in report["reason"], report
    # Written in place: the first such frame has no snapshot to compare with, the next does.
    builder.prim_lowers.assign(lowers + np.float32(0.25))
    builder.prim_uppers.assign(uppers + np.float32(0.25))
    assert "in place" in builder.update()["reason"]
    lowers, uppers = lowers + np.float32(0.25), uppers + np.float32(0.25)
    check_frame(builder, lowers, uppers, rng)
    assert builder.update()["decision"] == "none"
    # Half in place: only the lowers moved, written into the builder's own array, and the uppers
    # passed as they were. The motion is still seen, against the snapshot of the previous frame.
    lowers = lowers - np.float32(0.125)
    builder.prim_lowers.assign(lowers)
    report = builder.update(bounds=(builder.prim_lowers, uppers.copy()))
    assert report["decision"] != "none", report
    assert report["max_displacement"] == pytest.approx(0.125 * np.sqrt(3.0), rel=1e-4)
    check_frame(builder, lowers, uppers, rng)


@pytest.mark.parametrize("given", ["numpy", "warp"])
def test_auto_keeps_no_reference_to_a_callers_frame(device, rng, given):
    # `auto` measures the motion straight from the caller's arrays; a new record of that measure
    # for every new array kept the first four frames' boxes alive for as long as the builder lived.
    # At most the latest frame's arrays may stay referenced (set on the one record).
    import gc
    import weakref

    particles = Particles(rng, 500, speed=0.0005)
    builder = Builder(500, device=device, policy="auto")
    builder.build_from_bounds(*particles.bounds())
    refs = []
    for _ in range(6):
        lowers, uppers = particles.step()
        given_bounds = (lowers, uppers) if given == "numpy" else (
            wp.array(lowers, dtype=wp.vec3, device=device), wp.array(uppers, dtype=wp.vec3, device=device))
        refs += [weakref.ref(array) for array in given_bounds]
        builder.update(bounds=given_bounds)
        check_frame(builder, lowers, uppers, rng, exact_boxes=True)
        del given_bounds
    del lowers, uppers
    gc.collect()
    assert sum(ref() is not None for ref in refs[:-2]) == 0


def test_box_builder_rejects_bad_frames_and_keeps_its_tree(device, rng):
    # Bad input raises a ValueError naming the problem before anything is loaded: the tree and
    # the next good frame are unaffected.
    particles = Particles(rng, 500)
    builder = Builder(500, device=device, policy="auto")
    lowers, uppers = particles.bounds()
    builder.build_from_bounds(lowers, uppers)
    nan = lowers.copy()
    nan[7, 1] = np.nan
    inverted = uppers.copy()
    inverted[3] = lowers[3] - 1.0
    huge = uppers.astype(np.float64)
    huge[9, 0] = 1e39
    bad = [
        (dict(bounds=(nan, uppers)), "NaN or Inf"),
        (dict(bounds=(lowers, inverted)), "box 3 has lowers > uppers"),
        (dict(bounds=(lowers[:-1], uppers[:-1])), "499 rows"),
        (dict(bounds=(lowers,)), "pair"),
        (dict(bounds=(lowers[:, :2], uppers)), "shape"),
        (dict(vertices=lowers), "set up with boxes"),
        # float64 that float32 cannot hold would become Inf when narrowed for the build.
        (dict(bounds=(lowers, huge)), "float32 range"),
        (dict(bounds=(wp.array(lowers, dtype=wp.vec3, device=device), huge)), "float32 range"),
        # The builder's own buffers swapped (each side would be read after the other's load).
        (dict(bounds=(builder.prim_uppers, builder.prim_lowers)), "own prim_uppers"),
        (dict(bounds=(lowers, builder.prim_lowers)), "own prim_lowers"),
    ]
    for kwargs, message in bad:
        for call in (builder.update, builder.rebuild, builder.refit):
            with pytest.raises(ValueError, match=message):
                call(**kwargs)
    check_frame(builder, lowers, uppers, rng)
    lowers, uppers = particles.step()
    builder.update(bounds=(lowers, uppers))
    check_frame(builder, lowers, uppers, rng)
    with pytest.raises(ValueError, match="lowers > uppers"):
        Builder(500, device=device).build_from_bounds(lowers, lowers - 1.0)
    with pytest.raises(ValueError, match="rows"):
        Builder(400, device=device).build_from_bounds(lowers, uppers)


def test_a_builder_switches_between_triangles_and_boxes(device, rng):
    # The same builder set up with a mesh, then with boxes, then with the mesh again: each
    # setup's frames take their own kind of input and name the other kind's as the error.
    v, f = default_scene(2000)
    builder = Builder(len(f), device=device)
    builder.build(v, f)
    with pytest.raises(ValueError, match="set up with triangles"):
        builder.rebuild(bounds=(v[:len(f)], v[:len(f)]))
    particles = Particles(rng, len(f))
    builder.build_from_bounds(*particles.bounds())
    lowers, uppers = particles.step()
    builder.rebuild(bounds=(lowers, uppers))
    check_frame(builder, lowers, uppers, rng)
    with pytest.raises(ValueError):
        hw.intersect(builder.bvh, np.zeros((1, 3)), np.ones((1, 3)))  # boxes have no triangles
    builder.build(v, f)
    builder.rebuild(v * np.float32(1.5))
    tree = builder.bvh.to_numpy()
    corners = (v * np.float32(1.5)).astype(np.float64)[f]
    check_frame(builder, corners.min(axis=1).astype(np.float32), corners.max(axis=1).astype(np.float32), rng)
    check_tree_invariants(tree, len(f))


@pytest.mark.skipif(not wp.get_cuda_devices(), reason="CUDA graph capture needs a CUDA device")
def test_box_rebuild_is_graph_capturable_on_cuda(rng):
    # A simulation writes its boxes into the same device arrays every step: the rebuild over
    # them is captured once and replayed.
    device = wp.get_cuda_devices()[0]
    particles = Particles(rng, 3000)
    lowers, uppers = particles.bounds()
    lo = wp.array(lowers, dtype=wp.vec3, device=device)
    hi = wp.array(uppers, dtype=wp.vec3, device=device)
    builder = Builder(3000, device=device, resort=True)
    builder.build_from_bounds(lowers, uppers)
    builder.rebuild(bounds=(lo, hi))  # warm-up: module loads happen outside the capture
    with wp.ScopedCapture(device) as capture:
        builder.rebuild(bounds=(lo, hi))
    for _ in range(3):
        lowers, uppers = particles.step()
        lo.assign(lowers)
        hi.assign(uppers)
        wp.capture_launch(capture.graph)
        check_frame(builder, lowers, uppers, rng)
        one_shot = hw.build_from_bounds(lowers, uppers, device=device)
        assert metrics.sah_cost(builder.bvh) == pytest.approx(metrics.sah_cost(one_shot), rel=1e-5)


@pytest.mark.parametrize("policy", ["rebuild", "auto", "refit"])
def test_non_finite_device_boxes_neither_crash_nor_stick(device, rng, policy):
    # Device arrays are not read back to be checked (that would cost a synchronization every
    # frame), so a simulation that blows up hands the builder NaN and Inf boxes. The frame must
    # still complete, and the next finite frame must give a right tree again.
    particles = Particles(rng, 3000)
    builder = Builder(3000, device=device, policy=policy)
    lowers, uppers = particles.bounds()
    builder.build_from_bounds(lowers, uppers)
    bad_lowers, bad_uppers = lowers.copy(), uppers.copy()
    bad_lowers[::7] = np.nan
    bad_uppers[3] = np.inf
    report = builder.update(bounds=(wp.array(bad_lowers, dtype=wp.vec3, device=device),
                                    wp.array(bad_uppers, dtype=wp.vec3, device=device)))
    assert report["decision"] in ("rebuild", "refit")
    lowers, uppers = particles.step()
    builder.update(bounds=(wp.array(lowers, dtype=wp.vec3, device=device),
                           wp.array(uppers, dtype=wp.vec3, device=device)))
    # Under `refit` the topology is still the first frame's; every box is recomputed exactly.
    check_frame(builder, lowers, uppers, rng)


def test_auto_counts_a_move_too_small_to_square_in_float32(device, rng):
    # A point box at the origin moving by 1e-24 (or the smallest subnormal) squares to zero in
    # float32; the frame moved all the same, and "nothing moved" would keep a stale tree.
    lowers = rng.random((300, 3)).astype(np.float32) * 2.0 - 1.0
    lowers[7] = 0.0
    uppers = lowers + np.float32(0.01)
    uppers[7] = 0.0
    for step in (np.float32(1e-24), np.nextafter(np.float32(0.0), np.float32(1.0))):
        builder = Builder(300, device=device, policy="auto")
        builder.build_from_bounds(lowers, uppers)
        moved_lo, moved_hi = lowers.copy(), uppers.copy()
        moved_lo[7] = moved_hi[7] = step
        report = builder.update(bounds=(moved_lo, moved_hi))
        assert report["decision"] != "none", report
        assert report["max_displacement"] > 0.0
        check_frame(builder, moved_lo, moved_hi, rng)


def test_auto_sets_no_sah_reference_from_a_non_finite_frame(device, rng):
    # Two frames with the same infinite corners: the second moved by Inf - Inf = NaN over a root
    # diagonal of Inf, which read as no motion relative to the scene, so it rebuilt and priced its
    # tree at Inf / Inf = NaN. Taken as the reference, that made every later growth NaN, which
    # never exceeds the limit, so `auto` kept refitting that tree's topology until `max_refits`
    # ran out. A refit must only ever be judged against a finite reference.
    particles, builder, lowers, uppers = slow_particles_under_auto(rng, device, max_refits=50)
    bad_lowers = lowers.copy()
    bad_lowers[::5] = -np.inf
    for _ in range(2):
        builder.update(bounds=(wp.array(bad_lowers, dtype=wp.vec3, device=device),
                               wp.array(uppers, dtype=wp.vec3, device=device)))
    assert builder.sah_reference is None
    for _ in range(6):
        lowers, uppers = particles.step()
        report = builder.update(bounds=(lowers, uppers))
        assert builder.sah_reference is None or np.isfinite(builder.sah_reference)
        if report["decision"] == "refit":
            assert np.isfinite(report["sah_growth"]), report
        fresh = metrics.sah_cost(hw.build_from_bounds(lowers, uppers, device=device))
        assert metrics.sah_cost(builder.bvh) <= fresh * (1.0 + builder.sah_growth_limit) * 1.01
        check_frame(builder, lowers, uppers, rng)


def test_auto_counts_a_nan_corner_as_motion(device, rng):
    """A device frame in which nothing moved but one corner turned NaN: the motion measure
    must count it as the largest move (not as none), so `auto` does not keep the old tree."""
    lowers = rng.random((400, 3)).astype(np.float32)
    uppers = lowers + np.float32(0.01)
    builder = Builder(400, device=device, policy="auto")
    builder.build_from_bounds(lowers, uppers)
    bad = lowers.copy()
    bad[17, 1] = np.nan
    report = builder.update(bounds=(wp.array(bad, dtype=wp.vec3, device=device),
                                    wp.array(uppers, dtype=wp.vec3, device=device)))
    assert report["decision"] == "rebuild", report
    assert report["max_displacement"] > 1e18


def test_auto_reports_motion_relative_to_the_root_diagonal(device, rng):
    """`relative_motion` is the largest corner move over the previous tree's root diagonal,
    both from NumPy, in a scene far from the unit size."""
    lowers = (rng.random((500, 3)) * [40.0, 10.0, 5.0]).astype(np.float32)
    uppers = lowers + np.float32(0.1)
    builder = Builder(500, device=device, policy="auto", large_motion=0.5)
    builder.build_from_bounds(lowers, uppers)
    moved_lo, moved_hi = lowers.copy(), uppers.copy()
    moved_lo[42] += np.float32([0.3, -0.4, 0.0])
    moved_hi[42] += np.float32([0.3, -0.4, 0.0])
    report = builder.update(bounds=(moved_lo, moved_hi))
    diagonal = np.linalg.norm(uppers.astype(np.float64).max(0) - lowers.astype(np.float64).min(0))
    assert report["max_displacement"] == pytest.approx(0.5, rel=1e-5)
    assert report["relative_motion"] == pytest.approx(0.5 / diagonal, rel=1e-5)
    # A scene of zero size: any motion is large, whatever the distance.
    points = np.full((500, 3), 3.0, np.float32)
    builder.build_from_bounds(points, points)
    nudged = points.copy()
    nudged[7] += np.float32(1e-3)
    report = builder.update(bounds=(nudged, nudged))
    assert report["relative_motion"] == np.inf and report["decision"] == "rebuild", report


@pytest.mark.parametrize("moved", ["lower", "upper"])
def test_chaotic_wait_compares_both_box_arrays(device, moved):
    """A boxes `Builder` in `auto`'s chaotic wait compares the lowers and the uppers: equal boxes
    in new arrays are no work, and one corner moved by float32's smallest step in a box no sample
    reads (of either array) is rebuilt, its tree boxing the new corner (NumPy's float64 unions)."""
    rng = np.random.default_rng(11)
    n = 20000
    lowers = rng.random((n, 3)).astype(np.float32)
    uppers = lowers + np.float32(0.01)
    builder = Builder(n, device=device, policy="auto")
    builder.build_from_bounds(lowers, uppers)
    builder.chaotic_frames = 6
    report = builder.update(bounds=(lowers.copy(), uppers.copy()))
    assert report["decision"] == "none" and builder.chaotic_frames == 6, report
    where = n // 2 + 1  # the samples are i * n // 1024: not this one
    assert where not in set((np.arange(1024) * n // 1024).tolist())
    lo, hi = lowers.copy(), uppers.copy()
    if moved == "lower":
        lo[where, 0] = np.nextafter(lo[where, 0], np.float32(-np.inf))
    else:
        hi[where, 2] = np.nextafter(hi[where, 2], np.float32(np.inf))
    report = builder.update(bounds=(lo, hi))
    assert report["decision"] == "rebuild" and report["motion"].startswith("compared"), report
    tree = builder.bvh.to_numpy()
    check_tree_invariants(tree, n)
    node_lo, node_hi = numpy_node_boxes(tree, lo, hi)
    np.testing.assert_array_equal(tree["node_lowers"], node_lo.astype(np.float32))
    np.testing.assert_array_equal(tree["node_uppers"], node_hi.astype(np.float32))
