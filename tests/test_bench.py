"""The benchmark command end to end on a small generated scene (no timing is asserted)."""

from __future__ import annotations

import json

import numpy as np

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


def test_bench_notes_say_when_a_peer_falls_back(tmp_path):
    """wp.Bvh's "lbvh" constructor runs "sah" on the CPU: its row must say so (Warp reports it
    through its logger, which warnings.catch_warnings does not record)."""
    import warp as wp

    out = tmp_path / "b.json"
    code = bench.main(["--scene-tris", "500", "--builders", "hlbvh,wp.Bvh:lbvh,wp.Bvh:sah", "--repeats", "1",
                       "--warmup", "0", "--device", "cpu", "--rays", "8", "--json", str(out)])
    assert code in (0, None)
    rows = {r["builder"]: r for r in json.loads(out.read_text())["rows"]}
    assert any("Falling back to SAH" in note for note in rows["wp.Bvh:lbvh"]["notes"])
    assert rows["wp.Bvh:sah"]["notes"] == []
    assert type(wp.get_logger()).__name__ != "_RecordingLogger"


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


def test_bench_bytes_count_the_boxes_once_and_time_every_builder(tmp_path):
    """B/tri counts each device array once (the HLBVH pipelines read the caller's primitive boxes;
    those used to be added a second time), builders without a count of their own get none (not the
    HLBVH pipeline's), and the triangle-cutting sbvh is timed on the mesh it needs."""
    import trimesh
    import warp as wp

    from hlbvh_warp import memory
    from hlbvh_warp.builders import HlbvhSahPipeline
    from hlbvh_warp.config import BuildConfig
    from hlbvh_warp.hlbvh import HlbvhPipeline, StageTimer

    mesh = trimesh.creation.icosphere(subdivisions=2)
    path = tmp_path / "sphere.ply"
    mesh.export(path)
    out = tmp_path / "b.json"
    code = bench.main(["--mesh", str(path), "--builders", "hlbvh,hlbvh_sah,sweep_sah,sbvh,recursive_sah",
                       "--repeats", "1", "--warmup", "1", "--device", "cpu", "--rays", "8", "--json", str(out)])
    assert code in (0, None)
    rows = {r["builder"]: r for r in json.loads(out.read_text())["rows"]}
    assert all("error" not in r and r["time_ms"]["median"] > 0 for r in rows.values())
    n = len(mesh.faces)
    tri = np.asarray(mesh.vertices, np.float32)[np.asarray(mesh.faces)]
    lowers = wp.array(tri.min(axis=1), dtype=wp.vec3, device="cpu")
    uppers = wp.array(tri.max(axis=1), dtype=wp.vec3, device="cpu")
    config = BuildConfig()
    # A one-shot pipeline over the caller's boxes: every array it holds, the boxes among them, once.
    plain = HlbvhPipeline(n, config, "cpu", lowers, uppers)
    assert rows["hlbvh"]["bytes_per_tri"] == pytest.approx(memory.array_bytes(plain) / n)
    sah = HlbvhSahPipeline(n, config, "cpu", lowers, uppers)
    sah.build_sah(StageTimer("cpu", False))
    assert rows["hlbvh_sah"]["bytes_per_tri"] == pytest.approx(sah.held_bytes() / n)
    # The top-down arena does not hold the boxes: they are added once.
    swept = bench.api.build_from_bounds(tri.min(axis=1), tri.max(axis=1), method="sweep_sah", device="cpu")
    assert rows["sweep_sah"]["bytes_per_tri"] == pytest.approx((swept.buffer_bytes + 24 * n) / n)
    assert rows["sbvh"]["bytes_per_tri"] is None and rows["recursive_sah"]["bytes_per_tri"] is None


def test_bench_rays_fails_on_a_disagreement(tmp_path, monkeypatch, capsys):
    # bench-rays exits 1 when its hits disagree with wp.Mesh's, as bench-wide and quality do; it
    # used to print the count and exit 0 whatever it was.
    import trimesh

    from hlbvh_warp import cli, ray_bench

    path = tmp_path / "ball.ply"
    trimesh.creation.icosphere(2).export(path)
    argv = ["bench-rays", "--mesh", str(path), "--rays", "64", "--repeats", "1"]
    assert cli.main(argv) == 0
    assert "disagreements in total: 0" in capsys.readouterr().out
    monkeypatch.setattr(ray_bench, "count_disagreements", lambda *args, **kwargs: 3)
    assert cli.main(argv) == 1
    assert "disagreements in total: 0" not in capsys.readouterr().out


def test_bench_points_checks_distances_and_fails_on_a_disagreement(tmp_path, monkeypatch, capsys):
    """bench-points compares every distance with wp.Mesh's before timing, and exits 1 on a
    disagreement, as bench-rays does."""
    import trimesh

    from hlbvh_warp import cli, point_bench

    path = tmp_path / "ball.ply"
    trimesh.creation.icosphere(2).export(path)
    argv = ["bench-points", "--mesh", str(path), "--points", "64", "--repeats", "1"]
    assert cli.main(argv) == 0
    out = capsys.readouterr().out
    # One row per point set, every point found (no bound, or 5% of the diagonal around vertices
    # moved by about 1%: a miss there would be a 5-sigma offset, seed fixed).
    rows = [line.split() for line in out.splitlines() if line.startswith("ball ")]
    assert [r[3] for r in rows] == ["box", "near", "near-bounded"]
    assert all(r[5] == "64" and r[6] == "0" for r in rows), out
    monkeypatch.setattr(point_bench, "count_disagreements", lambda *args, **kwargs: 2)
    assert cli.main(argv) == 1
    # Two per point set, three sets.
    assert "disagreements in total: 6" in capsys.readouterr().out


def test_bench_pairs_checks_counts_and_fails_on_a_disagreement(tmp_path, monkeypatch, capsys):
    """bench-pairs compares every query's pair count with wp.mesh_query_aabb's before timing, and
    exits 1 on a disagreement, as bench-rays does."""
    import trimesh

    from hlbvh_warp import cli, pair_bench

    path = tmp_path / "ball.ply"
    trimesh.creation.icosphere(2).export(path)
    argv = ["bench-pairs", "--mesh", str(path), "--repeats", "1"]
    assert cli.main(argv) == 0
    out = capsys.readouterr().out
    rows = [line.split() for line in out.splitlines() if line.startswith("ball ")]
    assert [r[3] for r in rows] == ["self", "moved"]
    # An icosphere has no self-intersections; the moved copy passes through it.
    assert all(r[6] == "0" for r in rows) and rows[0][-1] == "0" and int(rows[1][-1]) > 0, out
    monkeypatch.setattr(pair_bench, "count_disagreements", lambda *args, **kwargs: 4)
    assert cli.main(argv) == 1
    assert "disagreements in total: 8" in capsys.readouterr().out


def test_pair_bench_disagreement_rule():
    """Counts are matched by face through the query order; self pairs by their totals."""
    from hlbvh_warp.pair_bench import count_disagreements

    order = np.array([2, 0, 1])
    assert count_disagreements(np.array([5, 1, 3]), np.array([1, 3, 5]), order, False) == 0
    assert count_disagreements(np.array([5, 1, 3]), np.array([5, 1, 3]), order, False) == 3
    assert count_disagreements(np.array([5, 1, 3]), np.array([4, 4, 1]), order, True) == 0
    assert count_disagreements(np.array([5, 1, 3]), np.array([4, 4, 2]), order, True) == 1


def test_point_bench_disagreement_rule():
    """Distances within 1e-5 of the scale agree, further ones and found-against-none do not."""
    from hlbvh_warp.point_bench import count_disagreements

    d_a = np.array([1.0, 1.0, 2.0, np.inf, 0.5], np.float32)
    d_b = np.array([1.0 + 0.9e-5, 1.0 + 1.1e-5, 2.0, np.inf, np.inf], np.float32)
    p_a = np.array([0, 1, 2, -1, 3], np.int32)
    p_b = np.array([5, 1, 2, -1, -1], np.int32)
    # Row 0 agrees (another triangle at the same distance), row 1 is past the tolerance, row 2
    # agrees, row 3 both found nothing, row 4 one found nothing.
    assert count_disagreements(d_a, p_a, d_b, p_b, scale=1.0) == 2
    assert count_disagreements(d_a, p_a, d_b, p_b, scale=10.0) == 1


def test_bench_rejects_an_empty_builder_list(capsys):
    # An empty list reached the plot and ended in matplotlib's "Number of columns must be a
    # positive integer, not 0": an argument error naming --builders now.
    for builders in ("", " , "):
        with pytest.raises(SystemExit) as exit_:
            bench.parse_args(["--builders", builders])
        err = capsys.readouterr().err
        assert exit_.value.code == 2 and "--builders names no builder" in err, (builders, err)


def test_bench_points_runs_on_a_mesh_whose_vertices_coincide(device, tmp_path, capsys):
    # Every vertex at one point (two zero-area triangles: valid input) gave a box diagonal of 0,
    # a ZeroDivisionError in the distance check. A cube around the point stands in for the box:
    # the sets spread around it, and every distance agrees with wp.Mesh's.
    from hlbvh_warp import cli, point_bench

    for corner in ((0.0, 0.0, 0.0), (1e3, -2e3, 5e2)):
        path = tmp_path / "degenerate.obj"
        path.write_text("".join(f"v {corner[0]} {corner[1]} {corner[2]}\n" for _ in range(3)) + "f 1 2 3\nf 1 2 3\n")
        rc = cli.main(["bench-points", "--mesh", str(path), "--points", "64", "--repeats", "1", "--device", device])
        out = capsys.readouterr().out
        rows = [line.split() for line in out.splitlines() if line.startswith("degenerate ")]
        assert rc == 0 and "disagreements in total: 0" in out, out
        assert [r[3] for r in rows] == ["box", "near", "near-bounded"]
        assert all(r[5] == "64" and r[6] == "0" for r in rows), out
        # The sets lie around the point, at distances of the cube's size (1 at the origin, else
        # the largest coordinate), not all on it.
        vertices = np.array([corner] * 3, np.float32)
        side = max(np.abs(corner)) or 1.0
        sets = point_bench.point_sets(np.random.default_rng(0), vertices, 200)
        for kind, (points, _) in sets.items():
            distance = np.linalg.norm(points.astype(np.float64) - np.asarray(corner), axis=1)
            assert distance.max() > 1e-3 * side and distance.max() < 2.0 * side, kind


def test_bench_pairs_moves_a_mesh_near_float32s_limit_without_overflow(device, tmp_path, capsys):
    # A finite mesh spanning -2e38..2e38: its float32 box diagonal overflowed, the moved copy came
    # out [inf, nan, nan] and the build blamed the file. The move is computed in float64 now; the
    # oracle is the move's own definition: a rigid turn (float64 distances between vertices kept)
    # and a shift of the centre by a tenth of the box diagonal along x.
    from hlbvh_warp import cli
    from hlbvh_warp.pair_bench import moved_copy

    vertices = np.array([[-2e38, 0, 0], [2e38, 1e37, 0], [0, 0, 1e37], [-1e38, 1e37, 1e37]], np.float32)
    moved = moved_copy(vertices)
    assert moved.dtype == np.float32 and np.isfinite(moved).all()
    v, m = vertices.astype(np.float64), moved.astype(np.float64)
    pairwise = np.linalg.norm(v[:, None] - v[None], axis=-1)
    np.testing.assert_allclose(np.linalg.norm(m[:, None] - m[None], axis=-1), pairwise, rtol=1e-6)
    np.testing.assert_array_equal(m[:, 1], v[:, 1])  # turned about y, shifted along x
    # Less the shift, the vertices' mean sits as far from the box centre as before, 30 degrees
    # round it in the xz-plane.
    centre = 0.5 * (v.min(0) + v.max(0))
    before = v.mean(0) - centre
    after = m.mean(0) - np.array([0.1 * np.linalg.norm(v.max(0) - v.min(0)), 0.0, 0.0]) - centre
    assert np.linalg.norm(after) == pytest.approx(np.linalg.norm(before), rel=1e-6)
    turn = np.arctan2(after[0], after[2]) - np.arctan2(before[0], before[2])
    assert np.degrees(np.abs(np.angle(np.exp(1j * turn)))) == pytest.approx(30.0, rel=1e-5)

    path = tmp_path / "huge.obj"
    path.write_text("".join(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in vertices) + "f 1 2 3\nf 2 3 4\n")
    rc = cli.main(["bench-pairs", "--mesh", str(path), "--repeats", "1", "--device", device])
    captured = capsys.readouterr()
    assert rc == 0 and "disagreements in total: 0" in captured.out, captured

    # Corners near +-3.3e38 along x and z: turned by 30 degrees they pass float32's limit. The
    # error says the benchmark's move overflowed, not that the (finite) file holds NaN or Inf.
    over = tmp_path / "over.obj"
    over.write_text("v 3.3e38 0 3.3e38\nv -3.3e38 0 -3.3e38\nv 0 1e37 0\nf 1 2 3\n")
    rc = cli.main(["bench-pairs", "--mesh", str(over), "--repeats", "1", "--device", device])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err and "NaN or Inf" not in err, err
    assert f"{over}: the benchmark's moved copy of the mesh" in err and "overflows float32" in err, err
