"""`auto`'s ``max_refits`` counts every refit since the last rebuild, forced ones too: a
simulation that refits each substep through `refit()`, or runs under the ``refit`` policy for a
while, must not leave `auto` refitting past its limit. SAH costs are checked against this file's
own float64 NumPy pricing of the tree."""

from __future__ import annotations

import numpy as np
import pytest

from hlbvh_warp.builder import Builder


def _sphere_soup(rng, count=400):
    """Small triangles scattered on a unit sphere: refits keep their SAH cost under small motion."""
    centres = rng.normal(size=(count, 1, 3))
    centres /= np.linalg.norm(centres, axis=2, keepdims=True)
    v = (centres + 0.03 * rng.normal(size=(count, 3, 3))).reshape(-1, 3)
    return v, np.arange(3 * count, dtype=np.int32).reshape(-1, 3)


def _numpy_sah(tree: dict, vertices, faces, t_traversal: float, t_intersect: float) -> float:
    """The SAH cost (paper eq. 1) of a tree's topology with every box recomputed in float64
    from the float32 triangles: only the topology comes from the library."""
    v = np.asarray(vertices, np.float32).astype(np.float64)
    tris = v[np.asarray(faces)]
    tri_lo, tri_hi = tris.min(1), tris.max(1)
    left, right = tree["node_left"], tree["node_right"]
    begin, end, order = tree["node_begin"], tree["node_end"], tree["prim_order"]
    visit, stack = [], [0]
    while stack:
        node = stack.pop()
        visit.append(node)
        if left[node] >= 0:
            stack += [left[node], right[node]]
    lo, hi = {}, {}
    for node in reversed(visit):  # children before parents
        if left[node] < 0:
            ids = order[begin[node]:end[node]]
            lo[node], hi[node] = tri_lo[ids].min(0), tri_hi[ids].max(0)
        else:
            lo[node] = np.minimum(lo[left[node]], lo[right[node]])
            hi[node] = np.maximum(hi[left[node]], hi[right[node]])
    total = 0.0
    for node in visit:
        d = hi[node] - lo[node]
        area = 2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0])
        total += area * (t_intersect * (end[node] - begin[node]) if left[node] < 0 else 2.0 * t_traversal)
    d = hi[0] - lo[0]
    return total / (2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0]))


def _calm(v, rng):
    return v + 2e-4 * rng.normal(size=v.shape)


def test_auto_counts_refits_forced_between_its_frames():
    """`max_refits` bounds the refits in a row since the last rebuild, and `refit()` "forces one
    whatever the policy": a forced refit is one of them. A simulation refitting at every substep
    (`refit()`) and updating once a frame (`update()`) kept refitting past the limit, and the
    report claimed fewer refits than the tree had been through."""
    rng = np.random.default_rng(11)
    v, f = _sphere_soup(rng)
    builder = Builder(len(f), device="cpu", policy="auto", max_refits=2)
    builder.build(v, f)
    refits = 0  # our own count of refits since the last rebuild
    for frame in range(6):
        v = _calm(v, rng)
        report = builder.update(v)
        if report["decision"] == "refit":
            refits += 1
            # A refit frame is only allowed below the limit.
            assert refits <= 2, (frame, refits, report["reason"])
        else:
            assert report["decision"] == "rebuild", report
            refits = 0
        for _ in range(2):  # substeps
            v = _calm(v, rng)
            builder.refit(v)
            refits += 1


def test_auto_after_refit_frames_under_another_policy():
    """A builder switched from `refit` to `auto` (a documented switch between frames) has refit
    for many frames since its last rebuild: its first `auto` frame must rebuild for the refits in a
    row, not refit once more and report "after 1 refits"."""
    rng = np.random.default_rng(12)
    v, f = _sphere_soup(rng)
    builder = Builder(len(f), device="cpu", policy="auto", max_refits=4)
    builder.build(v, f)
    builder.policy = "refit"
    for _ in range(10):
        v = _calm(v, rng)
        builder.update(v)
    builder.policy = "auto"
    report = builder.update(_calm(v, rng))
    assert report["decision"] == "rebuild" and "refits in a row" in report["reason"], report


def test_a_forced_rebuild_starts_the_refit_count_again():
    """After `rebuild()` the tree is fresh: the refits before it no longer count toward
    `max_refits`, and the SAH growth the next refits report is over the fresh tree's cost, checked
    against the SAH recomputed in NumPy from the topology."""
    rng = np.random.default_rng(13)
    v, f = _sphere_soup(rng)
    builder = Builder(len(f), device="cpu", policy="auto", max_refits=3)
    cfg = builder.config
    builder.build(v, f)
    for _ in range(3):
        v = _calm(v, rng)
        assert builder.update(v)["decision"] == "refit"
    v = _calm(v, rng)
    builder.rebuild(v)
    v = _calm(v, rng)
    first = builder.update(v)  # no priced tree after a rebuild on request: rebuilt and priced
    assert first["decision"] == "rebuild", first
    best = _numpy_sah(builder.bvh.to_numpy(), v, f, cfg.sah_traversal_cost, cfg.sah_intersection_cost)
    assert first["sah"] == pytest.approx(best, rel=1e-4)
    decisions = []
    for _ in range(3):
        v = _calm(v, rng)
        report = builder.update(v)
        decisions.append(report["decision"])
        if report["decision"] == "refit":
            mine = _numpy_sah(builder.bvh.to_numpy(), v, f, cfg.sah_traversal_cost, cfg.sah_intersection_cost)
            assert report["sah_growth"] == pytest.approx(mine / best - 1.0, abs=1e-4)
            best = min(best, mine)
    assert decisions == ["refit"] * 3, decisions
