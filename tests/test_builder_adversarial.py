"""Adversarial frame sequences for the per-frame `Builder`, and what its tree and reports say
about each frame, checked against float64 NumPy and one-shot builds."""

from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, rule, run_state_machine_as_test

import hlbvh_warp as hw
from hlbvh_warp import stress_report
from hlbvh_warp.builder import PIPELINE_METHODS, POLICIES, Builder

from oracles import (assert_exact_node_boxes, assert_hits_match, brute_force_closest_hit, brute_overlaps,
                     check_tree_invariants, numpy_node_boxes, numpy_sah, random_rays)


def _soup(rng, num_tris):
    return rng.random((3 * num_tris, 3)).astype(np.float32), np.arange(3 * num_tris, dtype=np.int32).reshape(-1, 3)


def _check_tree_timings(timings: dict, report: dict, enabled: bool):
    """A Builder's `bvh.timings` in the form of a one-shot tree's: empty when not timed, else ms per
    stage with the stages found already done under "skipped" and their sum under "total"."""
    if not enabled:
        assert timings == {}
        return
    assert isinstance(timings["skipped"], list) and timings["skipped"] == report["stages_skipped"]
    stages = {k: v for k, v in timings.items() if k not in ("skipped", "total")}
    assert stages == report["stages_ms"]
    assert timings["total"] == pytest.approx(math.fsum(stages.values()), rel=1e-12, abs=1e-12)
    # The tree's timings are its own dict: editing them leaves the frame's report as it was.
    assert timings is not report["stages_ms"]


@pytest.mark.parametrize("timings", [False, True])
def test_a_builders_tree_reports_its_timings_as_a_one_shot_tree_does(device, rng, timings):
    vertices, faces = _soup(rng, 40)
    one_shot = hw.build(vertices, faces, device=device, timings=timings).timings
    assert ("skipped" in one_shot and "total" in one_shot) == timings
    builder = Builder(len(faces), device=device, policy="auto", timings=timings)
    builder.build(vertices, faces)
    _check_tree_timings(builder.bvh.timings, builder.last_report, timings)
    moved = vertices + np.float32(1e-4)
    frames = [("update", vertices + np.float32(1e-4)), ("update", moved), ("update", rng.random(vertices.shape)),
              ("rebuild", moved), ("rebuild", moved), ("refit", moved)]
    decisions = []
    for call, frame in frames:
        getattr(builder, call)(frame.astype(np.float32))
        decisions.append(builder.last_report["decision"])
        _check_tree_timings(builder.bvh.timings, builder.last_report, timings)
    # Every kind of frame was seen: a refit, nothing moved, a rebuild, one that kept its topology.
    assert {"refit", "none", "rebuild"} <= set(decisions)


def _check_mesh_frame(builder: Builder, vertices: np.ndarray, faces: np.ndarray, rng):
    """The tree over this frame: valid, every node box the union of its triangles' boxes (min and
    max of the same floats, so exact), and the closest hits of a float64 brute force."""
    tree = builder.bvh.to_numpy()
    check_tree_invariants(tree, len(faces), builder.config.max_leaf_size)
    assert_exact_node_boxes(tree, vertices, faces)
    origins = rng.random((64, 3)).astype(np.float32) * 3.0 - 1.0
    directions = (rng.random((64, 3)).astype(np.float32) - origins).astype(np.float32)
    t, prim = hw.intersect(builder.bvh, origins, directions)
    t_ref, prim_ref = brute_force_closest_hit(vertices, faces, origins, directions)
    assert (prim >= 0).sum() > 10, "too few hits for the comparison to mean anything"
    assert_hits_match(t, prim, t_ref, prim_ref)


@pytest.mark.parametrize("policy", ["rebuild", "refit", "auto"])
def test_frames_take_flat_float_warp_arrays_as_build_does(device, rng, policy):
    # `build` takes a flat float32 Warp array (x y z after x y z); the frames after it refused the
    # same form ("must be a wp.array of vec3 / vec3d or float32 / float64 (N, 3)").
    vertices, faces = _soup(rng, 30)
    builder = Builder(len(faces), device=device, policy=policy)
    builder.build(wp.array(vertices.reshape(-1), dtype=wp.float32, device=device), faces)
    _check_mesh_frame(builder, vertices, faces, rng)
    for step, dtype in enumerate([wp.float32, wp.float64, wp.float32]):
        moved = vertices.astype(np.float64) * (1.0 + 0.01 * (step + 1)) + 1e-9
        expected = moved.astype(np.float32)  # a float64 frame is rounded to float32 as it is loaded
        flat = wp.array(moved.reshape(-1), dtype=dtype, device=device)
        if step == 2:
            builder.refit(flat)
        else:
            builder.update(flat)
        _check_mesh_frame(builder, expected, faces, rng)
    # The boxes of a box builder, flat too, as `build_from_bounds` takes them.
    lowers, uppers = vertices[faces].min(axis=1), vertices[faces].max(axis=1)
    boxes = Builder(len(faces), device=device, policy=policy)
    boxes.build_from_bounds(*(wp.array(x.reshape(-1), dtype=wp.float32, device=device) for x in (lowers, uppers)))
    lowers, uppers = lowers + np.float32(0.5), uppers + np.float32(0.625)
    boxes.update(bounds=tuple(wp.array(x.reshape(-1), dtype=wp.float64, device=device) for x in (lowers, uppers)))
    tree = boxes.bvh.to_numpy()
    check_tree_invariants(tree, len(faces))
    node_lo, node_hi = numpy_node_boxes(tree, lowers, uppers)
    np.testing.assert_array_equal(tree["node_lowers"], node_lo)
    np.testing.assert_array_equal(tree["node_uppers"], node_hi)
    q_lo, q_hi = lowers[:10], uppers[:10] + np.float32(0.1)
    expected = brute_overlaps(lowers, uppers, q_lo, q_hi).sum(1)
    np.testing.assert_array_equal(hw.query_aabb(boxes.bvh, q_lo, q_hi), expected)
    # Refused, before any state changes, with the dtype named as Warp names it: a length that is
    # not whole points, and a strided view (one point in two, read in place it would be garbage).
    before = builder.bvh.to_numpy()
    with pytest.raises(ValueError, match=r"float32 / float64 shaped \(N, 3\) or flat \(3N,\), got float32 with shape"):
        builder.update(wp.array(np.zeros(3 * len(vertices) + 1, np.float32), device=device))
    with pytest.raises(ValueError, match="float32 flat vertices must be contiguous"):
        builder.update(wp.array(np.zeros(6 * len(vertices), np.float32), device=device)[::2])
    for name, array in builder.bvh.to_numpy().items():
        np.testing.assert_array_equal(array, before[name], err_msg=name)


TOPOLOGY = ("node_left", "node_right", "node_begin", "node_end", "prim_order")
MOTIONS = ("rest", "jitter", "one_ulp", "fly", "collapse", "degenerate", "two_ago", "translate", "jump", "nan")


class ReportedFrames(RuleBasedStateMachine):
    """Random frames through every call and policy, each report checked against what the frame was:
    "none" only when no vertex changed, a refit (or a kept topology) with the last tree's topology,
    the measured displacement and the reported SAH cost those of float64 NumPy, and a rebuild the
    tree a one-shot build of the frame gives. Motions include a vertex flung to 1e30, the mesh
    collapsed to a point, every triangle degenerate, the frame of two frames ago, and a device frame
    with a NaN (taken unchecked: the next finite frame must be right again)."""

    device = "cpu"

    @initialize(method=st.sampled_from(PIPELINE_METHODS), resort=st.booleans(), policy=st.sampled_from(POLICIES),
                threads=st.sampled_from([1, 2]), num_tris=st.sampled_from([1, 3, 24]), leaf=st.sampled_from([1, 3]),
                seed=st.integers(0, 2**32 - 1))
    def set_up(self, method, resort, policy, threads, num_tris, leaf, seed):
        self.rng = np.random.default_rng(seed)
        self.config = hw.BuildConfig(cpu_threads=threads, max_leaf_size=leaf)
        self.method = method
        self.builder = Builder(num_tris, self.config, device=self.device, method=method, resort=resort, policy=policy,
                               max_refits=2)
        self.vertices, self.faces = _soup(self.rng, num_tris)
        self.history = [self.vertices]
        self.builder.build(self.vertices, self.faces)
        self.tree = self.check(None)

    def finite_frame(self) -> np.ndarray:
        return next(v for v in reversed(self.history) if np.isfinite(v).all())

    def check(self, previous: np.ndarray | None) -> dict:
        builder, report, v = self.builder, self.builder.last_report, self.vertices
        tree = {name: array.copy() for name, array in builder.bvh.to_numpy().items()}
        assert np.array_equal(np.sort(tree["prim_order"]), np.arange(len(self.faces)))
        finite = bool(np.isfinite(v).all())
        if finite:
            check_tree_invariants(tree, len(self.faces), self.config.max_leaf_size)
            corners = v.astype(np.float64)[self.faces]
            node_lo, node_hi = numpy_node_boxes(tree, corners.min(axis=1), corners.max(axis=1))
            np.testing.assert_array_equal(tree["node_lowers"], node_lo.astype(np.float32))
            np.testing.assert_array_equal(tree["node_uppers"], node_hi.astype(np.float32))
            if np.abs(v).max() < 1e6:
                # Slivers and degenerate triangles: answers may differ only where rounding decides.
                origins, directions = random_rays(self.rng, v, 16)
                t, prim = hw.intersect(builder.bvh, origins, directions)
                t_ref, prim_ref = brute_force_closest_hit(v, self.faces, origins, directions)
                _, unexplained = stress_report.classify(v, self.faces, origins, directions, t, prim, t_ref, prim_ref)
                assert unexplained == 0
        decision = report["decision"]
        if previous is not None:
            if decision == "none":
                assert np.array_equal(v, previous), "'none' for a frame that moved"
            if decision in ("none", "refit") or report.get("kept_topology"):
                for name in TOPOLOGY:
                    np.testing.assert_array_equal(tree[name], self.tree[name], err_msg=name)
            if "max_displacement" in report:
                with np.errstate(invalid="ignore"):
                    moves = np.sqrt(((v.astype(np.float64) - previous) ** 2).sum(axis=1))
                expected = np.inf if np.isnan(moves).any() else moves.max()
                assert report["max_displacement"] == pytest.approx(expected, rel=1e-6)
        if decision == "rebuild" and finite:
            fresh = hw.build(v, self.faces, method=self.method, config=self.config, device=self.device).to_numpy()
            for name in TOPOLOGY[:-1]:
                np.testing.assert_array_equal(tree[name], fresh[name], err_msg=name)
        if report.get("sah") is not None and finite:
            with np.errstate(invalid="ignore"):
                cost = numpy_sah(tree)
            if not np.isfinite(cost):
                # A root of zero area (the mesh at one point, or on a line) takes every node's area
                # ratio as 1 (`metrics.sah_cost`): the sum of the terms alone.
                leaf = tree["node_left"] < 0
                cost = float(np.where(leaf, tree["node_end"] - tree["node_begin"], 2.0).sum())
            assert report["sah"] == pytest.approx(cost, rel=1e-6)
        return tree

    @rule(op=st.sampled_from(["update", "update", "rebuild", "refit"]), motion=st.sampled_from(MOTIONS),
          form=st.sampled_from(["numpy", "warp", "in_place"]))
    def frame(self, op, motion, form):
        v, rng = self.finite_frame(), self.rng
        new = v.copy()
        if motion == "jitter":
            new = (v + rng.normal(scale=1e-3, size=v.shape)).astype(np.float32)
        elif motion == "one_ulp":
            new[-1, 1] = np.nextafter(new[-1, 1], np.float32(np.inf))
        elif motion == "fly":
            new[rng.integers(len(v))] = np.float32(1e30)
        elif motion == "collapse":
            new[:] = v[0]
        elif motion == "degenerate":
            new[:, 1:] = np.float32(0.5)
        elif motion == "two_ago" and len(self.history) > 1 and np.isfinite(self.history[-2]).all():
            new = self.history[-2].copy()
        elif motion == "translate":
            new += np.float32(0.375)
        elif motion == "jump":
            new = rng.random(v.shape).astype(np.float32)
        elif motion == "nan":
            # Only a device frame gets through unchecked; NumPy input raises (see `refused_frame`).
            new[0, 0] = np.nan
            form = "warp" if form == "numpy" else form
        if form == "in_place":
            self.builder.vertices.assign(new)
            given = None
        else:
            given = new if form == "numpy" else wp.array(new, dtype=wp.vec3, device=self.device)
        getattr(self.builder, op)(given)
        previous, self.vertices = self.vertices, new
        self.history.append(new)
        self.tree = self.check(previous)

    @rule(op=st.sampled_from(["update", "rebuild", "refit"]), fault=st.sampled_from(["nan", "float64_columns", "rows"]))
    def refused_frame(self, op, fault):
        frame = self.finite_frame().astype(np.float64)
        if fault == "nan":
            frame[-1, 2] = np.nan
        elif fault == "float64_columns":
            frame = frame[:, :2]
        else:
            frame = frame[:-1]
        report = self.builder.last_report
        with pytest.raises(ValueError):
            getattr(self.builder, op)(frame)
        assert self.builder.last_report is report
        for name, array in self.builder.bvh.to_numpy().items():
            np.testing.assert_array_equal(array, self.tree[name], err_msg=name)

    @rule(policy=st.sampled_from(POLICIES))
    def switch_policy(self, policy):
        self.builder.policy = policy


def test_reports_tell_what_each_frame_was(device):
    machine = type("ReportedFramesOn", (ReportedFrames,), {"device": device})
    run_state_machine_as_test(machine, settings=settings(max_examples=40, stateful_step_count=12, deadline=None,
                                                         derandomize=True,
                                                         suppress_health_check=[HealthCheck.too_slow]))


def test_a_blown_up_device_frame_is_named_in_the_reason(device, rng):
    """A device frame with a NaN coordinate is measured as an infinite move and rebuilt (frames
    given as Warp arrays are not checked); the reason said "moved inf% of the scene diagonal". It
    names the NaN or Inf instead, and a finite large move keeps its percentage."""
    vertices, faces = _soup(rng, 8)
    builder = Builder(len(faces), device=device, policy="auto")
    builder.build(vertices, faces)
    blown = vertices.copy()
    blown[5, 1] = np.nan
    builder.update(wp.array(blown, dtype=wp.vec3, device=device))
    report = builder.last_report
    assert report["decision"] == "rebuild"
    assert "inf%" not in report["reason"] and "NaN" in report["reason"], report["reason"]
    builder.update(vertices)  # the tree boxed over the NaN: any motion counts as large again
    builder.update(vertices * np.float32(3.0))
    report = builder.last_report
    assert report["decision"] == "rebuild" and "%" in report["reason"], report["reason"]
    assert f"{report['relative_motion']:.1%}" in report["reason"]
