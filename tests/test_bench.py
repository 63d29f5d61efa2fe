"""The benchmark command end to end on a small generated scene (no timing is asserted)."""

from __future__ import annotations

import json

import pytest

from hlbvh_warp import bench


def test_bench_rows_are_checked_and_priced(tmp_path, capsys):
    out = tmp_path / "bench.json"
    code = bench.main(["--scene-tris", "3000", "--builders", "hlbvh,hlbvh_sah,sweep_sah,wp.Bvh:sah", "--repeats", "1",
                       "--warmup", "0", "--device", "cpu", "--cpu-threads", "1", "--json", str(out)])
    assert code in (0, None)
    data = json.loads(out.read_text())
    assert data["cpu_threads"] == 1
    rows = {r["builder"]: r for r in data["rows"]}
    # Every tree of ours passed the brute-force ray check and is priced against sweep_sah.
    assert rows["sweep_sah"]["sah_ratio"] == pytest.approx(1.0)
    for name in ("hlbvh", "hlbvh_sah"):
        assert "error" not in rows[name]
        assert rows[name]["rays_checked"] > 0
        assert rows[name]["num_nodes"] == 2 * rows[name]["num_tris"] - 1
        # A greedy sweep is not optimal, so a ratio may fall a little below 1 on a given scene.
        assert 0.8 < rows[name]["sah_ratio"] < 2.0
        assert rows[name]["sah_ratio"] == pytest.approx(rows[name]["sah"] / rows["sweep_sah"]["sah"])
    assert "wp.Bvh:sah" in rows and rows["wp.Bvh:sah"]["time_ms"]["median"] > 0


def test_bench_rejects_bad_arguments():
    with pytest.raises(SystemExit):
        bench.parse_args(["--cpu-threads", "-1"])
    with pytest.raises(SystemExit):
        bench.parse_args(["--builders", "nope"])
