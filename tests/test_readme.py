"""The README's usage example runs as written, and what it prints is what the library computes."""

from __future__ import annotations

import contextlib
import io
import re

import numpy as np
import pytest

from conftest import REPO_ROOT


def readme_usage_block() -> str:
    text = (REPO_ROOT / "README.md").read_text()
    section = text.split("## Using it", 1)[1]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_readme_usage_example_runs():
    namespace: dict = {}
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(readme_usage_block(), "README.md", "exec"), namespace)
    mesh, bvh = namespace["mesh"], namespace["bvh"]
    assert bvh.num_nodes == 2 * len(mesh.faces) - 1
    # The ray from z = -5 towards +z hits the unit sphere's mesh near z = -1.
    t, prim = namespace["t"], namespace["prim"]
    assert prim[0] >= 0 and abs(t[0] - 4.0) < 0.01
    assert namespace["builder"].last_report["decision"] in ("refit", "rebuild", "none")
    # The broad phase: each query box overlaps at least its own particle's box.
    centers = namespace["centers"]
    # In float32, as the builder and the query store them.
    lo, hi = (centers - 0.01).astype(np.float32), (centers + 0.01).astype(np.float32)
    expected = ((lo[None] <= hi[:4, None]) & (hi[None] >= lo[:4, None])).all(-1).sum(1)
    printed = out.getvalue().strip().splitlines()[-1]
    np.testing.assert_array_equal(np.array(printed.strip("[]").split(), dtype=int), expected)
    assert (expected >= 1).all()


def test_every_public_name_is_in_the_readme():
    # Each name the package exports is documented in the README's "Using it" section, quoted as
    # code (`name`, a call `name(...`, or imported in the usage example), so that no part of the
    # API is only in a docstring.
    import hlbvh_warp

    section = (REPO_ROOT / "README.md").read_text().split("## Using it", 1)[1].split("## The pipeline", 1)[0]
    missing = [name for name in hlbvh_warp.__all__
               if not re.search(rf"`(hb\.|hlbvh_warp\.)?{re.escape(name)}[`(.]|import {re.escape(name)}\b", section)]
    assert not missing, f"public names the README does not document: {missing}"


@pytest.mark.parametrize("method", ["hlbvh", "lbvh", "hlbvh_sah", "sweep_sah", "binned_sah", "median"])
@pytest.mark.parametrize("emission", ["depth_first", "treelets"])
def test_timings_hold_total_and_skipped(method, emission):
    # The README's usage example: timings hold ms per stage, "total" and "skipped". "skipped"
    # (the stages found already done) was there only when some stage was skipped: not for the
    # treelet schedule with the paper's sort, nor for the top-down builders.
    import trimesh

    import hlbvh_warp as hb

    mesh = trimesh.creation.icosphere(subdivisions=2)
    config = hb.BuildConfig(emission=emission, global_sort_runs=1.0)
    timings = hb.build(mesh, method=method, device="cpu", config=config, timings=True).timings
    assert isinstance(timings["skipped"], list), timings
    stages = {k: v for k, v in timings.items() if k not in ("total", "skipped")}
    assert stages and all(isinstance(v, float) and v >= 0.0 for v in stages.values()), timings
    assert timings["total"] == pytest.approx(sum(stages.values()))
