"""Fuzzed frame sequences for the per-frame `Builder`: every method, policy and resort setting,
through motions a simulation produces (rest, jitter, jumps, collapse to a point, huge and tiny
scales, vertices written in place), each frame checked against float64 NumPy.

Whatever the policy decides, the tree after `update` must describe the frame: a valid tree over
all faces whose every node box is exactly the union of its faces' boxes (min/max of the same
floats, so no tolerance), rays that hit what a brute force hits, and, for a from-scratch rebuild,
exactly the tree a one-shot `build` gives.
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, rule, run_state_machine_as_test

import hlbvh_warp as hw
from hlbvh_warp import stress_report
from hlbvh_warp.builder import PIPELINE_METHODS, POLICIES, Builder

from oracles import (assert_exact_node_boxes, brute_force_closest_hit, brute_overlaps, check_tree_invariants,
                     numpy_node_boxes, numpy_sah)

MOTIONS = ("rest", "jitter", "jump", "collapse", "huge", "tiny", "in_place")
TOPOLOGY = ("node_left", "node_right", "node_begin", "node_end", "prim_order")


def next_vertices(rng, motion: str, current: np.ndarray) -> np.ndarray:
    if motion == "rest":
        return current.copy()
    if motion == "jitter":
        scale = float(np.abs(current).max() or 1.0) * 1e-3
        return (current + rng.normal(scale=scale, size=current.shape)).astype(np.float32)
    if motion == "collapse":
        # Every triangle degenerate, at one point: a valid scene with a zero-extent Morton grid.
        return np.broadcast_to(current[:1], current.shape).astype(np.float32).copy()
    if motion == "huge":
        return (rng.random(current.shape) * 1e12).astype(np.float32)
    if motion == "tiny":
        return (1.0 + rng.random(current.shape) * 1e-6).astype(np.float32)
    # "jump" and "in_place": a fresh random placement.
    return (rng.random(current.shape) * 4.0 - 2.0).astype(np.float32)


def check_frame(builder: Builder, vertices: np.ndarray, faces: np.ndarray, rng):
    tree = builder.bvh.to_numpy()
    check_tree_invariants(tree, len(faces), builder.config.max_leaf_size)
    assert_exact_node_boxes(tree, vertices, faces)
    for origins, directions in stress_report.ray_families(rng, vertices, faces, num_rays=24).values():
        t, prim = hw.intersect(builder.bvh, origins, directions)
        t_ref, prim_ref = brute_force_closest_hit(vertices, faces, origins, directions)
        _, unexplained = stress_report.classify(vertices, faces, origins, directions, t, prim, t_ref, prim_ref)
        assert unexplained == 0
    return tree


def fuzz_settings(max_examples: int):
    # Derandomized: CI runs the same examples every time.
    return settings(max_examples=max_examples, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture])


#: What every fuzzed sequence draws: the builder's setup and the frames' motions.
SEQUENCES = dict(
    seed=st.integers(0, 2**32 - 1),
    method=st.sampled_from(PIPELINE_METHODS),
    policy=st.sampled_from(POLICIES),
    resort=st.booleans(),
    motions=st.lists(st.sampled_from(MOTIONS), min_size=1, max_size=6),
)


@fuzz_settings(60)
@given(
    num_tris=st.integers(1, 80),
    shared=st.booleans(),
    # The default, where a resorted frame takes the faces' order when its runs do not compress,
    # and 1.0, where it always takes the previous tree's order.
    global_sort_runs=st.sampled_from([hw.BuildConfig().global_sort_runs, 1.0]),
    **SEQUENCES,
)
def test_fuzzed_frame_sequences(device, seed, num_tris, method, policy, resort, shared, motions, global_sort_runs):
    rng = np.random.default_rng(seed)
    vertices, faces = stress_report._soup(rng, num_tris, scale=1.0, offset=0.0)
    vertices = vertices.astype(np.float32)
    if shared:
        # A mesh whose faces share vertices (and may repeat one within a face: degenerate).
        vertices = vertices[: num_tris // 2 + 3]
        faces = rng.integers(0, len(vertices), size=(num_tris, 3)).astype(np.int32)
    config = hw.BuildConfig(global_sort_runs=global_sort_runs)
    builder = Builder(num_tris, config, device=device, method=method, policy=policy, resort=resort, max_refits=2)
    builder.build(vertices, faces)
    check_frame(builder, vertices, faces, rng)
    for motion in motions:
        vertices = next_vertices(rng, motion, vertices)
        if motion == "in_place":
            builder.vertices.assign(vertices)
            report = builder.update()
        else:
            report = builder.update(vertices)
        assert report["decision"] in ("rebuild", "refit", "none")
        if policy == "auto" and motion == "rest" and report["decision"] == "none":
            assert report["max_displacement"] == 0.0
        tree = check_frame(builder, vertices, faces, rng)
        if report["decision"] == "rebuild" and not resort:
            one_shot = hw.build(vertices, faces, method=method, device=device, config=config).to_numpy()
            for name in TOPOLOGY:
                np.testing.assert_array_equal(tree[name], one_shot[name], err_msg=name)


@pytest.mark.parametrize("policy", POLICIES)
def test_auto_never_skips_a_frame_that_moved(device, policy, rng):
    # A frame that moved one vertex by the smallest float step is not "nothing moved".
    vertices, faces = stress_report._soup(rng, 40, scale=1.0, offset=0.0)
    vertices = vertices.astype(np.float32)
    builder = Builder(len(faces), device=device, policy=policy)
    builder.build(vertices, faces)
    moved = vertices.copy()
    moved[7, 1] = np.nextafter(moved[7, 1], np.float32(np.inf))
    report = builder.update(moved)
    assert report["decision"] != "none"
    check_frame(builder, moved, faces, rng)


def check_box_frame(builder: Builder, lowers: np.ndarray, uppers: np.ndarray, rng):
    tree = builder.bvh.to_numpy()
    check_tree_invariants(tree, len(lowers), builder.config.max_leaf_size)
    node_lo, node_hi = numpy_node_boxes(tree, lowers, uppers)
    np.testing.assert_array_equal(tree["node_lowers"], node_lo)
    np.testing.assert_array_equal(tree["node_uppers"], node_hi)
    # Query boxes around some of the boxes (touching counts) and random ones.
    picks = rng.integers(0, len(lowers), size=8)
    q_lo = np.concatenate([lowers[picks], rng.random((8, 3)).astype(np.float32) * 4.0 - 2.0])
    q_hi = np.concatenate([lowers[picks], q_lo[8:] + np.float32(0.5)])
    counts, pairs = hw.query_aabb(builder.bvh, q_lo, q_hi, return_pairs=True)
    expected = brute_overlaps(lowers, uppers, q_lo, q_hi)
    np.testing.assert_array_equal(counts, expected.sum(1))
    np.testing.assert_array_equal(pairs, np.argwhere(expected))
    return tree


@fuzz_settings(30)
@given(num_boxes=st.integers(1, 80), **SEQUENCES)
def test_fuzzed_box_frame_sequences(device, seed, num_boxes, method, policy, resort, motions):
    # The same motions for a builder over bare boxes (`build_from_bounds`): each box spans two
    # moving points, so boxes collapse, flatten to points and blow up with them.
    rng = np.random.default_rng(seed)
    points = (rng.random((2 * num_boxes, 3)) * 4.0 - 2.0).astype(np.float32)

    def boxes(p):
        return np.minimum(p[0::2], p[1::2]), np.maximum(p[0::2], p[1::2])

    builder = Builder(num_boxes, device=device, method=method, policy=policy, resort=resort, max_refits=2)
    lowers, uppers = boxes(points)
    builder.build_from_bounds(lowers, uppers)
    check_box_frame(builder, lowers, uppers, rng)
    for motion in motions:
        points = next_vertices(rng, motion, points)
        lowers, uppers = boxes(points)
        if motion == "in_place":
            builder.prim_lowers.assign(lowers)
            builder.prim_uppers.assign(uppers)
            report = builder.update()
        else:
            report = builder.update(bounds=(lowers, uppers))
        assert report["decision"] in ("rebuild", "refit", "none")
        if policy == "auto" and motion == "rest" and report["decision"] == "none":
            assert report["max_displacement"] == 0.0
        tree = check_box_frame(builder, lowers, uppers, rng)
        if report["decision"] == "rebuild" and not resort:
            one_shot = hw.build_from_bounds(lowers, uppers, method=method, device=device).to_numpy()
            for name in TOPOLOGY:
                np.testing.assert_array_equal(tree[name], one_shot[name], err_msg=name)


class BuilderCalls(RuleBasedStateMachine):
    """Random sequences of a `Builder`'s calls (`update`, `rebuild`, `refit` with every input form,
    policy switches, refused frames, set-ups again with triangles or boxes), each frame checked
    against float64 NumPy and every rebuild against a fresh one-shot build of the same frame: the
    same topology and SAH cost, resorted or not (primitives with equal codes may only trade
    places within a leaf pair). A refused frame must leave the last tree as it was."""

    device = "cpu"

    @initialize(method=st.sampled_from(PIPELINE_METHODS), resort=st.booleans(), policy=st.sampled_from(POLICIES),
                threads=st.sampled_from([1, 2, 3]), num_prims=st.integers(1, 60), boxes=st.booleans(),
                keep=st.integers(1, 3), timings=st.booleans(), seed=st.integers(0, 2**32 - 1),
                bits=st.sampled_from([2, 10]), leaf=st.sampled_from([1, 3]))
    def set_up(self, method, resort, policy, threads, num_prims, boxes, keep, timings, seed, bits, leaf):
        self.rng = np.random.default_rng(seed)
        self.config = hw.BuildConfig(cpu_threads=threads, bits_per_axis=bits, max_leaf_size=leaf)
        self.method, self.num_prims, self.keep = method, num_prims, keep
        self.builder = Builder(num_prims, self.config, device=self.device, method=method, resort=resort,
                               policy=policy, keep_reports=keep, timings=timings, max_refits=2)
        self.build(boxes, more_vertices=False)

    def build(self, boxes: bool, more_vertices: bool):
        n = self.num_prims
        self.boxes = boxes
        if boxes:
            points = self.rng.random((2 * n, 3)).astype(np.float32)
            self.lowers, self.uppers = np.minimum(points[0::2], points[1::2]), np.maximum(points[0::2], points[1::2])
            self.builder.build_from_bounds(self.lowers, self.uppers)
        else:
            count = 3 * n + (5 if more_vertices else 0)
            self.vertices = self.rng.random((count, 3)).astype(np.float32)
            self.faces = self.rng.integers(0, count, size=(n, 3)).astype(np.int32)
            self.builder.build(self.vertices, self.faces)

    def move(self, motion: str, scale: float):
        if motion == "rest":
            return
        if self.boxes:
            if motion == "jump":
                step = self.rng.random(self.lowers.shape).astype(np.float32) - self.lowers
            else:
                step = self.rng.normal(scale=scale, size=self.lowers.shape).astype(np.float32)
            self.lowers, self.uppers = self.lowers + step, self.uppers + step
        elif motion == "jump":
            self.vertices = self.rng.random(self.vertices.shape).astype(np.float32)
        else:
            self.vertices = (self.vertices + self.rng.normal(scale=scale, size=self.vertices.shape)).astype(np.float32)

    def frame_input(self, form: str) -> dict:
        """The frame as the call takes it; nothing for a frame written into the builder's buffers."""
        device = self.device
        if form == "in_place":
            if self.boxes:
                self.builder.prim_lowers.assign(self.lowers)
                self.builder.prim_uppers.assign(self.uppers)
            else:
                self.builder.vertices.assign(self.vertices)
            return {}
        if self.boxes:
            if form == "warp":
                return {"bounds": (wp.array(self.lowers, dtype=wp.vec3, device=device),
                                   wp.array(self.uppers, dtype=wp.vec3, device=device))}
            return {"bounds": (self.lowers.astype(np.float64) if form == "float64" else self.lowers, self.uppers)}
        if form == "warp":
            return {"vertices": wp.array(self.vertices, dtype=wp.vec3, device=device)}
        if form == "warp64":
            return {"vertices": wp.array(self.vertices.astype(np.float64), dtype=wp.vec3d, device=device)}
        return {"vertices": self.vertices.astype(np.float64) if form == "float64" else self.vertices}

    def call(self, op: str, given: dict):
        if op == "update":
            self.builder.update(given.get("vertices"), bounds=given.get("bounds"))
        else:
            getattr(self.builder, op)(given.get("vertices"), bounds=given.get("bounds"))

    @rule(op=st.sampled_from(["update", "update", "rebuild", "refit"]),
          motion=st.sampled_from(["rest", "move", "jump"]), scale=st.sampled_from([1e-4, 1e-2, 0.3]),
          form=st.sampled_from(["numpy", "float64", "warp", "warp64", "in_place"]))
    def frame(self, op, motion, scale, form):
        self.move(motion, scale)
        self.call(op, self.frame_input(form))

    @rule(policy=st.sampled_from(POLICIES))
    def switch_policy(self, policy):
        self.builder.policy = policy

    @rule(fault=st.sampled_from(["nan", "inf", "past_float32", "columns", "rows", "bool"]),
          op=st.sampled_from(["update", "rebuild", "refit"]))
    def refused_frame(self, fault, op):
        before = {name: a.copy() for name, a in self.builder.bvh.to_numpy().items()}
        frame = (self.lowers if self.boxes else self.vertices).copy()
        if fault == "nan":
            frame[0, 1] = np.nan
        elif fault == "inf":
            frame[-1, 2] = np.inf
        elif fault == "past_float32":
            frame = frame.astype(np.float64)
            frame[0, 0] = -1e39
        elif fault == "columns":
            frame = frame[:, :2]
        elif fault == "rows":
            frame = np.concatenate([frame, frame[:1]])
        else:
            frame = frame > 0.5
        with pytest.raises(ValueError):
            self.call(op, {"bounds": (frame, self.uppers)} if self.boxes else {"vertices": frame})
        after = self.builder.bvh.to_numpy()
        for name, array in before.items():
            np.testing.assert_array_equal(after[name], array, err_msg=name)

    @rule(boxes=st.booleans(), more_vertices=st.booleans())
    def set_up_again(self, boxes, more_vertices):
        self.build(boxes, more_vertices)

    @invariant()
    def tree_describes_the_frame(self):
        builder, rng = self.builder, self.rng
        if self.boxes:
            tree = check_box_frame(builder, self.lowers, self.uppers, rng)
        else:
            tree = check_frame(builder, self.vertices, self.faces, rng)
        assert len(builder.reports) <= self.keep
        if builder.last_report["decision"] != "rebuild":
            return
        if self.boxes:
            fresh = hw.build_from_bounds(self.lowers, self.uppers, method=self.method, config=self.config,
                                         device=self.device)
        else:
            fresh = hw.build(self.vertices, self.faces, method=self.method, config=self.config, device=self.device)
        fresh = fresh.to_numpy()
        for name in TOPOLOGY[:-1]:
            np.testing.assert_array_equal(tree[name], fresh[name], err_msg=name)
        with np.errstate(invalid="ignore"):  # a scene of zero area prices as NaN, both trees alike
            cost, fresh_cost = numpy_sah(tree), numpy_sah(fresh)
        assert cost == pytest.approx(fresh_cost, rel=1e-9, nan_ok=True)


def test_builder_call_sequences_match_fresh_builds(device):
    machine = type("BuilderCallsOn", (BuilderCalls,), {"device": device})
    run_state_machine_as_test(machine, settings=settings(max_examples=40, stateful_step_count=10, deadline=None,
                                                         derandomize=True,
                                                         suppress_health_check=[HealthCheck.too_slow]))
