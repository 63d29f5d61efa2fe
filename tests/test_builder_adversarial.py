"""Adversarial frame sequences for the per-frame `Builder`, and what its tree and reports say
about each frame, checked against float64 NumPy and one-shot builds."""

from __future__ import annotations

import math

import numpy as np
import pytest

import hlbvh_warp as hw
from hlbvh_warp.builder import Builder


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
