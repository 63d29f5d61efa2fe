"""Adversarial frame sequences for the per-frame `Builder`, and what its tree and reports say
about each frame, checked against float64 NumPy and one-shot builds."""

from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp

import hlbvh_warp as hw
from hlbvh_warp.builder import Builder

from oracles import assert_hits_match, brute_force_closest_hit, brute_overlaps, check_tree_invariants, numpy_node_boxes


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
    corners = vertices.astype(np.float64)[faces]
    node_lo, node_hi = numpy_node_boxes(tree, corners.min(axis=1), corners.max(axis=1))
    np.testing.assert_array_equal(tree["node_lowers"], node_lo.astype(np.float32))
    np.testing.assert_array_equal(tree["node_uppers"], node_hi.astype(np.float32))
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
