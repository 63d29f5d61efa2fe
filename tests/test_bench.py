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
    with pytest.raises(SystemExit):
        bench.parse_args(["--subdivide", "-1"])


def test_bench_table_keeps_long_mesh_names(tmp_path, capsys):
    # Names past the old 12-character column were cut ("armadillo_x16" printed as "armadillo_x1").
    import trimesh

    path = tmp_path / "a_mesh_with_a_long_name.ply"
    trimesh.creation.icosphere(subdivisions=2).export(path)
    # --subdivide 1: every triangle split into four, and the name says so.
    code = bench.main(["--mesh", str(path), "--subdivide", "1", "--builders", "hlbvh", "--repeats", "1", "--warmup",
                       "0", "--device", "cpu", "--rays", "8", "--json", str(tmp_path / "b.json")])
    assert code in (0, None)
    lines = capsys.readouterr().out.splitlines()
    header = next(line for line in lines if "builder" in line and "tris" in line)
    name = path.stem + "_sub1"
    row = next(line for line in lines if line.strip().startswith(name))
    # The full name, and the columns still line up under the header (right-aligned: same ends).
    num_tris = 4 * len(trimesh.creation.icosphere(subdivisions=2).faces)
    assert row.split()[:3] == [name, str(num_tris), "hlbvh"]
    assert header.index("mesh") + len("mesh") == len(name)
    assert header.index("tris") + len("tris") == row.index(f" {num_tris} ") + 1 + len(str(num_tris))
