"""The benchmark command end to end on a small generated scene (no timing is asserted)."""

from __future__ import annotations

import json

import numpy as np

import pytest

from hlbvh_warp import bench


def test_bench_rows_are_checked_and_priced(tmp_path):
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


def _rows(out: str, mesh: str) -> list[list[str]]:
    """A bench command's rows of one mesh, split into columns. bench-rays, bench-points and
    bench-pairs share the middle ones: 3 the kind of query, 6 checked against the brute force, 7
    ours wrong among them, 8 where wp.Mesh differs from ours; 5 is the hits or points found."""
    return [line.split() for line in out.splitlines() if line.startswith(f"{mesh} ")]


def test_bench_rays_fails_on_its_own_wrong_hits_not_on_wp_meshs(tmp_path, monkeypatch, capsys):
    """bench-rays checks its hits against the float64 brute force before timing and exits 1 when
    one is wrong; where wp.Mesh differs, it says so and the status stays 0. It had taken its
    status from wp.Mesh's disagreements alone."""
    import trimesh

    from hlbvh_warp import api, cli, ray_bench

    path = tmp_path / "ball.ply"
    trimesh.creation.icosphere(2).export(path)
    argv = ["bench-rays", "--mesh", str(path), "--rays", "64", "--repeats", "1"]
    assert cli.main(argv) == 0
    out = capsys.readouterr().out
    # Random rays and an 8 x 8 camera, all 64 of each checked (fewer than the even sample's 256).
    rows = _rows(out, "ball")
    assert [r[3] for r in rows] == ["random", "camera"]
    assert all(r[4] == "64" and r[6:9] == ["64", "0", "0"] for r in rows), out
    assert "ours against the float64 brute force: 0 wrong of 128 rays checked; wp.Mesh differs from ours on 0 " \
           "rays (reported, not the exit status)" in out, out

    # wp.Mesh differing on every ray is reported, as wp.Mesh's, and does not fail the run.
    monkeypatch.setattr(ray_bench, "disagreeing", lambda t_a, *args, **kwargs: np.ones(len(t_a), bool))
    assert cli.main(argv) == 0
    out = capsys.readouterr().out
    assert all(r[6:9] == ["64", "0", "64"] for r in _rows(out, "ball")), out
    assert "0 wrong of 128 rays checked; wp.Mesh differs from ours on 128 rays (reported" in out, out
    monkeypatch.undo()

    # Our hits on another mesh (the tree built over the ball moved by a tenth of its radius)
    # while wp.Mesh is made to agree everywhere: wrong by the brute force, and the run fails.
    real_build = api.build
    monkeypatch.setattr(api, "build", lambda vertices, faces, **kwargs: real_build(vertices + 0.1, faces, **kwargs))
    monkeypatch.setattr(ray_bench, "disagreeing", lambda t_a, *args, **kwargs: np.zeros(len(t_a), bool))
    assert cli.main(argv) == 1
    out = capsys.readouterr().out
    rows = _rows(out, "ball")
    assert all(int(r[7]) > 16 and r[8] == "0" for r in rows), out
    assert "0 wrong of" not in out and "wp.Mesh differs from ours on 0 rays" in out, out


def test_bench_rays_far_rays_are_checked(tmp_path, capsys):
    """``--far-distance`` adds rays from that many diagonals away, checked like the others: the
    float64 brute force (the tests' own, on the run's rays) agrees with every hit the row counts."""
    import trimesh
    from oracles import brute_force_closest_hit

    from hlbvh_warp import cli, ray_bench

    ball = trimesh.creation.icosphere(2)
    path = tmp_path / "ball.ply"
    ball.export(path)
    assert cli.main(["bench-rays", "--mesh", str(path), "--rays", "64", "--repeats", "1", "--far-distance",
                     "1e7"]) == 0
    out = capsys.readouterr().out
    rows = _rows(out, "ball")
    assert [r[3] for r in rows] == ["random", "camera", "far"] and rows[2][7] == "0", out
    vertices = np.asarray(ball.vertices, np.float32)
    rng = np.random.default_rng(0)
    ray_bench.random_rays(rng, vertices, 64)  # the run's first kind, drawn from the same generator
    o, d = ray_bench.far_rays(rng, vertices, 64, 1e7)
    _, prim = brute_force_closest_hit(vertices, np.asarray(ball.faces), o, d)
    assert int((prim >= 0).sum()) == int(rows[2][5]) > 0
    _check_far_distance_errors("bench-rays", "--rays", path, tmp_path, capsys)


def _check_far_distance_errors(command: str, count_option: str, path, tmp_path, capsys):
    """``--far-distance`` out of its bounds is an argument error; within them but past float32's
    range for the mesh, one line naming it (exit 2), not a row of NaN queries."""
    import trimesh

    from hlbvh_warp import cli

    for bad in ("-1", "0.5", "1e31", "nan"):
        with pytest.raises(SystemExit):
            cli.main([command, "--mesh", str(path), "--far-distance", bad])
    assert "--far-distance" in capsys.readouterr().err
    big = tmp_path / "big.ply"
    trimesh.creation.icosphere(1).apply_scale(1e20).export(big)
    assert cli.main([command, "--mesh", str(big), count_option, "16", "--far-distance", "1e30"]) == 2
    assert "past float32's range" in capsys.readouterr().err


def test_bench_points_far_points_are_checked(tmp_path, capsys):
    """``--far-distance`` adds a ``far`` set from that many diagonals away, checked against the
    float64 brute force like the others (the tests' own, on the run's points: every point found),
    and its node count shows the float64 walk: as from 1e3 diagonals."""
    import trimesh
    from test_proximity import oracle_closest

    from hlbvh_warp import cli, point_bench

    ball = trimesh.creation.icosphere(2)
    path = tmp_path / "ball.ply"
    ball.export(path)
    assert cli.main(["bench-points", "--mesh", str(path), "--points", "64", "--repeats", "1", "--far-distance",
                     "1e7"]) == 0
    out = capsys.readouterr().out
    rows = _rows(out, "ball")
    assert [r[3] for r in rows] == ["box", "near", "near-bounded", "far"] and rows[3][5:8] == ["64", "64", "0"], out
    vertices = np.asarray(ball.vertices, np.float32)
    rng = np.random.default_rng(0)
    point_bench.point_sets(rng, vertices, 64)  # the run's first sets, drawn from the same generator
    far = point_bench.far_points(rng, vertices, 64, 1e7)
    d_ref, prim_ref, _ = oracle_closest(vertices, np.asarray(ball.faces), far)
    assert (prim_ref >= 0).all() and np.linalg.norm(far.astype(np.float64), axis=1).min() > 1e6
    # The same directions from 1e3 diagonals (the generator's draws do not depend on the distance):
    # as many nodes per point, to 10%. The float32 walk opened 1.4 times as many from 1e7.
    assert cli.main(["bench-points", "--mesh", str(path), "--points", "64", "--repeats", "1", "--far-distance",
                     "1e3"]) == 0
    near_rows = _rows(capsys.readouterr().out, "ball")
    assert float(rows[3][13]) <= 1.1 * float(near_rows[3][13]), (out, near_rows)
    _check_far_distance_errors("bench-points", "--points", path, tmp_path, capsys)


@pytest.mark.parametrize("scale", [1e-20, 1e30])
def test_bench_rays_passes_on_tiny_and_huge_meshes_wp_mesh_misses(scale, tmp_path, capsys):
    # A sphere of radius 1e-20 or 1e30 (valid input): wp.Mesh misses every ray, and a verdict
    # taken from its disagreements failed the run although our hits were right. At 1e30 the
    # benchmark's own rays were NaN (float32's squares overflowed in the box diagonal) and nothing
    # was hit. The oracle here is the tests' own brute force (tests/oracles.py) on the very rays
    # of the run (seed 0).
    import trimesh
    from oracles import assert_hits_match, brute_force_closest_hit

    from hlbvh_warp import api, cli, query, ray_bench

    ball = trimesh.creation.icosphere(2)
    ball.apply_scale(scale)
    path = tmp_path / "ball.ply"
    ball.export(path)
    assert cli.main(["bench-rays", "--mesh", str(path), "--rays", "64", "--repeats", "1"]) == 0
    out = capsys.readouterr().out
    rows = _rows(out, "ball")
    # Every ray we hit is one wp.Mesh missed, and each is checked.
    assert [r[3] for r in rows] == ["random", "camera"]
    assert all(int(r[5]) > 0 and r[7] == "0" and r[8] == r[5] and int(r[6]) >= 64 for r in rows), out
    assert "ours against the float64 brute force: 0 wrong of" in out and "wp.Mesh differs from ours on 0" not in out

    vertices, faces = np.asarray(ball.vertices, np.float32), np.asarray(ball.faces, np.int32)
    bvh = api.build(vertices, faces, device="cpu")
    kinds = (ray_bench.random_rays(np.random.default_rng(0), vertices, 64), ray_bench.camera_rays(vertices, 64))
    for (o, d), row in zip(kinds, rows):
        t, prim = query.intersect(bvh, o, d)
        assert_hits_match(t, prim, *brute_force_closest_hit(vertices, faces, o, d))
        assert int((prim >= 0).sum()) == int(row[5])


def test_bench_points_fails_on_its_own_wrong_answers_not_on_wp_meshs(tmp_path, monkeypatch, capsys):
    """bench-points checks its answers against the float64 brute force before timing and exits 1
    when one is wrong; where wp.Mesh differs, it says so and the status stays 0."""
    import trimesh

    from hlbvh_warp import api, cli, point_bench

    path = tmp_path / "ball.ply"
    trimesh.creation.icosphere(2).export(path)
    argv = ["bench-points", "--mesh", str(path), "--points", "64", "--repeats", "1"]
    assert cli.main(argv) == 0
    out = capsys.readouterr().out
    # One row per point set, every point found (no bound, or 5% of the diagonal around vertices
    # moved by about 1%: a miss there would be a 5-sigma offset, seed fixed), all 64 checked
    # (fewer than the even sample's 256).
    rows = _rows(out, "ball")
    assert [r[3] for r in rows] == ["box", "near", "near-bounded"]
    assert all(r[5] == "64" and r[6:9] == ["64", "0", "0"] for r in rows), out
    assert "ours against the float64 brute force: 0 wrong of 192 points checked; wp.Mesh differs from ours on 0 " \
           "points (reported, not the exit status)" in out, out

    # wp.Mesh differing everywhere is reported, as wp.Mesh's, and does not fail the run.
    monkeypatch.setattr(point_bench, "disagreeing", lambda d_a, *args, **kwargs: np.ones(len(d_a), bool))
    assert cli.main(argv) == 0
    out = capsys.readouterr().out
    assert all(r[6:9] == ["64", "0", "64"] for r in _rows(out, "ball")), out
    assert "0 wrong of 192 points checked; wp.Mesh differs from ours on 192 points (reported" in out, out
    monkeypatch.undo()

    # Our answers for another mesh (the tree built over the ball moved by a tenth of its size):
    # wrong by the brute force, and the run fails. wp.Mesh differs too: it answers for the ball.
    real_build = api.build
    monkeypatch.setattr(api, "build", lambda vertices, faces, **kwargs: real_build(vertices + 0.1, faces, **kwargs))
    assert cli.main(argv) == 1
    out = capsys.readouterr().out
    rows = _rows(out, "ball")
    assert all(int(r[7]) > 32 and int(r[8]) > 32 for r in rows), out
    assert "0 wrong of" not in out, out


def test_bench_pairs_fails_on_its_own_wrong_pairs_not_on_wp_meshs(tmp_path, monkeypatch, capsys):
    """bench-pairs checks its counts and its pair listing against an exact brute force before
    timing and exits 1 when one is wrong; where wp.Mesh differs, it says so and the status stays 0.
    It had taken its status from wp.Mesh's disagreements alone."""
    import trimesh
    import warp as wp

    from hlbvh_warp import cli, pair_bench

    path = tmp_path / "ball.ply"
    trimesh.creation.icosphere(2).export(path)
    argv = ["bench-pairs", "--mesh", str(path), "--repeats", "1"]
    assert cli.main(argv) == 0
    out = capsys.readouterr().out
    rows = _rows(out, "ball")
    assert [r[3] for r in rows] == ["self", "moved"]
    # 256 of the 320 queries checked, none wrong, none differing from wp.Mesh. An icosphere has
    # no self-intersections; the moved copy passes through it.
    assert all(r[4] == "320" and r[6:9] == ["256", "0", "0"] for r in rows), out
    assert rows[0][-1] == "0" and int(rows[1][-1]) > 0, out
    assert "ours against the exact brute force: 0 wrong of 512 queries checked; wp.Mesh's disagreements with " \
           "ours: 0 (reported, not the exit status)" in out, out

    # wp.Mesh disagreeing is reported, as wp.Mesh's, and does not fail the run.
    monkeypatch.setattr(pair_bench, "count_disagreements", lambda *args, **kwargs: 4)
    assert cli.main(argv) == 0
    out = capsys.readouterr().out
    assert all(r[6:9] == ["256", "0", "4"] for r in _rows(out, "ball")), out
    assert "0 wrong of 512 queries checked; wp.Mesh's disagreements with ours: 8 (reported" in out, out
    monkeypatch.undo()

    # The self rule turned round in the timed count pass (self queries keep every partner, moved
    # ones only those later in the tree's order) while wp.Mesh is made to agree: the counts are
    # wrong by the brute force, and the run fails.
    real_launch = pair_bench.launch_box_pairs
    monkeypatch.setattr(pair_bench, "launch_box_pairs",
                        lambda queries, tree, self_pairs, *args: real_launch(queries, tree, not self_pairs, *args))
    monkeypatch.setattr(pair_bench, "count_disagreements", lambda *args, **kwargs: 0)
    monkeypatch.setattr(pair_bench, "differing_queries", lambda *args: np.zeros(0, np.int64))
    assert cli.main(argv) == 1
    out = capsys.readouterr().out
    assert all(int(r[7]) > 64 and r[8] == "0" for r in _rows(out, "ball")), out
    assert "0 wrong of" not in out and "wp.Mesh's disagreements with ours: 0" in out, out
    monkeypatch.undo()

    # Right counts, but every listed pair names the next face as its partner: the listing is
    # checked too.
    real_candidates = pair_bench._candidates

    def shifted(queries, tree, self_pairs):
        pairs = real_candidates(queries, tree, self_pairs).numpy().reshape(-1, 2)
        pairs[:, 1] = (pairs[:, 1] + 1) % tree.num_prims
        return wp.array(pairs, dtype=wp.vec2i, device=tree.device)

    monkeypatch.setattr(pair_bench, "_candidates", shifted)
    assert cli.main(argv) == 1
    out = capsys.readouterr().out
    assert all(int(r[7]) > 64 and r[8] == "0" for r in _rows(out, "ball")), out


def test_pair_bench_brute_force_matches_the_tests_oracle(rng):
    """The command's brute force of box overlap against the tests' own (tests/oracles.py), on
    boxes snapped to a coarse grid so that many only touch (touching counts)."""
    from oracles import brute_overlaps

    from hlbvh_warp.pair_bench import brute_force_partners

    lo = np.floor(rng.random((300, 3)) * 8).astype(np.float32)
    hi = lo + np.floor(rng.random((300, 3)) * 3).astype(np.float32)
    # Queries: some of the boxes, moved by half a cell along some axes (flat ones included).
    shift = np.float32(0.5) * (rng.random((70, 3)) < 0.3)
    q_lo, q_hi = lo[:70] + shift, hi[:70] + shift
    expected = brute_overlaps(lo, hi, q_lo, q_hi)
    touching = expected & ((lo[None] == q_hi[:, None]) | (hi[None] == q_lo[:, None])).any(axis=2)
    assert touching.sum() > 100 and expected.sum() > touching.sum() and not expected.all()
    found = brute_force_partners(q_lo, q_hi, lo, hi, chunk=16)
    assert len(found) == 70
    for row, partners in zip(expected, found):
        np.testing.assert_array_equal(partners, np.flatnonzero(row))


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
    from hlbvh_warp.point_bench import disagreeing

    d_a = np.array([1.0, 1.0, 2.0, np.inf, 0.5], np.float32)
    d_b = np.array([1.0 + 0.9e-5, 1.0 + 1.1e-5, 2.0, np.inf, np.inf], np.float32)
    p_a = np.array([0, 1, 2, -1, 3], np.int32)
    p_b = np.array([5, 1, 2, -1, -1], np.int32)
    # Row 0 agrees (another triangle at the same distance), row 1 is past the tolerance, row 2
    # agrees, row 3 both found nothing, row 4 one found nothing.
    assert disagreeing(d_a, p_a, d_b, p_b, scale=1.0).tolist() == [False, True, False, False, True]
    assert disagreeing(d_a, p_a, d_b, p_b, scale=10.0).tolist() == [False, False, False, False, True]


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
        rows = _rows(out, "degenerate")
        assert rc == 0 and "0 wrong of 192 points checked; wp.Mesh differs from ours on 0 points" in out, out
        assert [r[3] for r in rows] == ["box", "near", "near-bounded"]
        assert all(r[5] == "64" and r[6:9] == ["64", "0", "0"] for r in rows), out
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
    assert rc == 0 and "ours against the exact brute force: 0 wrong of 4 queries checked" in captured.out, captured

    # Corners near +-3.3e38 along x and z: turned by 30 degrees they pass float32's limit. The
    # error says the benchmark's move overflowed, not that the (finite) file holds NaN or Inf.
    over = tmp_path / "over.obj"
    over.write_text("v 3.3e38 0 3.3e38\nv -3.3e38 0 -3.3e38\nv 0 1e37 0\nf 1 2 3\n")
    rc = cli.main(["bench-pairs", "--mesh", str(over), "--repeats", "1", "--device", device])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err and "NaN or Inf" not in err, err
    assert f"{over}: the benchmark's moved copy of the mesh" in err and "overflows float32" in err, err


@pytest.mark.parametrize("exponent", [0, 120])
def test_bench_points_passes_on_a_line_mesh_wp_mesh_finds_nothing_on(exponent, tmp_path, capsys):
    # Five triangles on one line (zero area, valid input): wp.Mesh finds nothing for any point,
    # and bench-points exited 1 on those "disagreements" although its own answers were right.
    # The oracle here is the closed form: every triangle is the segment [0, 2 s] of the x axis.
    from hlbvh_warp import api, cli, point_bench, query

    s = 2.0 ** exponent
    path = tmp_path / "line.obj"
    path.write_text("".join(f"v {x!r} 0 0\n" for x in (0.0, s, 2.0 * s)) + "f 1 2 3\n" * 5)
    assert cli.main(["bench-points", "--mesh", str(path), "--points", "64", "--repeats", "1"]) == 0
    out = capsys.readouterr().out
    rows = _rows(out, "line")
    assert [r[3] for r in rows] == ["box", "near", "near-bounded"]
    assert all(r[6:9] == ["64", "0", "64"] for r in rows), out  # 64 points where wp.Mesh found nothing
    assert "0 wrong of 192 points checked; wp.Mesh differs from ours on 192 points (reported" in out, out

    # Our answers on the very points of the run (seed 0), against the closed form.
    vertices = np.array([[0.0, 0.0, 0.0], [s, 0.0, 0.0], [2.0 * s, 0.0, 0.0]], np.float32)
    faces = np.array([[0, 1, 2]] * 5, np.int32)
    bvh = api.build(vertices, faces, device="cpu")
    for kind, (points, max_dist) in point_bench.point_sets(np.random.default_rng(0), vertices, 64).items():
        p = points.astype(np.float64)
        outside = np.maximum(np.maximum(-p[:, 0], p[:, 0] - 2.0 * s), 0.0)
        exact = np.sqrt(outside ** 2 + p[:, 1] ** 2 + p[:, 2] ** 2)
        _, distance, prim = query.closest_point(bvh, points, max_dist=max_dist)
        assert (prim >= 0).all() and (exact <= max_dist).all(), kind
        np.testing.assert_allclose(distance, exact, rtol=0, atol=1e-6 * np.abs(p).max())


def test_bench_points_passes_on_a_mesh_near_float32s_limit(tmp_path, capsys):
    # An icosphere scaled by 2^127 (coordinates up to 1.7e38): wp.Mesh finds nothing, and
    # bench-points exited 1. The oracle: at scale 1 wp.Mesh agrees with every answer of ours, and a
    # power of two scales float32 and float64 arithmetic exactly, so our answers at 2^127 must be
    # the scale-1 answers times 2^127, bit for bit.
    import trimesh

    from hlbvh_warp import api, cli, point_bench, query

    sphere = trimesh.creation.icosphere(1)
    unit = np.asarray(sphere.vertices, np.float32)
    faces = np.asarray(sphere.faces, np.int32)
    big = unit * np.float32(2.0 ** 127)
    outputs = {}
    for name, vertices, differ in (("unit", unit, "0"), ("big", big, "64")):
        path = tmp_path / f"{name}.ply"
        trimesh.Trimesh(vertices, faces, process=False).export(path)
        assert cli.main(["bench-points", "--mesh", str(path), "--points", "64", "--repeats", "1"]) == 0
        out = capsys.readouterr().out
        assert all(r[6:9] == ["64", "0", differ] for r in _rows(out, name)), out
        bvh = api.build(vertices, faces, device="cpu")
        sets = point_bench.point_sets(np.random.default_rng(0), vertices, 64)
        outputs[name] = [(points, *query.closest_point(bvh, points, max_dist=max_dist)[1:])
                         for points, max_dist in sets.values()]
    for (p_unit, d_unit, prim_unit), (p_big, d_big, prim_big) in zip(outputs["unit"], outputs["big"]):
        np.testing.assert_array_equal(p_big, p_unit * np.float32(2.0 ** 127))
        np.testing.assert_array_equal(prim_big, prim_unit)
        np.testing.assert_array_equal(d_big, d_unit * np.float32(2.0 ** 127))


def test_point_bench_brute_force_on_hand_worked_cases():
    from hlbvh_warp.point_bench import brute_force_closest

    # The right triangle (0,0,0) (1,0,0) (0,1,0), a segment-shaped one on the x axis from 3 to 5,
    # and a point-shaped one at (0, 0, 10). Distances worked by hand.
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [3, 0, 0], [5, 0, 0], [4, 0, 0], [0, 0, 10]], np.float32)
    faces = np.array([[0, 1, 2], [3, 4, 5], [6, 6, 6]])
    cases = [((0.25, 0.25, 2.0), 2.0, 0),            # above the face
             ((-1.0, -1.0, 0.0), np.sqrt(2.0), 0),   # beyond a vertex
             ((0.5, -1.0, 1.0), np.sqrt(2.0), 0),    # beyond an edge
             ((1.0, 1.0, 0.0), np.sqrt(0.5), 0),     # beyond the long edge, in the plane
             ((4.5, 2.0, 0.0), 2.0, 1),              # beside the segment
             ((6.0, 0.0, 0.0), 1.0, 1),              # beyond its end
             ((0.0, 0.0, 12.0), 2.0, 2),             # above the point
             ((2.0, 0.0, 0.0), 1.0, 0),              # as far from the face as from the segment: the lower id
             ((np.nan, 0.0, 0.0), np.inf, -1), ((np.inf, 0.0, 0.0), np.inf, -1)]
    points = np.array([c[0] for c in cases], np.float32)
    distance, prim = brute_force_closest(vertices, faces, points)
    np.testing.assert_allclose(distance, [c[1] for c in cases], rtol=1e-15)
    assert prim.tolist() == [c[2] for c in cases]


def test_point_bench_brute_force_groups_change_no_answer():
    # Against every pair tested, on a soup of triangles of every size (a thousand, so the points
    # prune most of its 16 groups) and points near and far.
    from hlbvh_warp.point_bench import brute_force_closest, point_triangle_d2

    rng = np.random.default_rng(5)
    centers = rng.uniform(-10, 10, (1000, 1, 3))
    vertices = (centers + rng.normal(0, 1, (1000, 3, 3)) * 10.0 ** rng.uniform(-3, 0.5, (1000, 1, 1))).reshape(-1, 3)
    vertices = vertices.astype(np.float32)
    faces = np.arange(3000).reshape(-1, 3)
    points = np.concatenate([rng.uniform(-15, 15, (100, 3)), vertices[:300:3] + rng.normal(0, 0.01, (100, 3)),
                             rng.uniform(-1e3, 1e3, (20, 3))]).astype(np.float32)
    distance, prim = brute_force_closest(vertices, faces, points)
    v = vertices.astype(np.float64)[faces]
    every = point_triangle_d2(points.astype(np.float64)[:, None], v[None, :, 0], v[None, :, 1], v[None, :, 2])
    np.testing.assert_array_equal(distance, np.sqrt(every.min(axis=1)))
    np.testing.assert_array_equal(prim, every.argmin(axis=1))


def test_point_bench_wrong_answers_are_counted():
    from hlbvh_warp.point_bench import ORACLE_RTOL, brute_force_closest, count_wrong

    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 5], [1, 0, 5], [0, 1, 5]], np.float32)
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    points = np.array([[0.2, 0.2, 1.0], [0.2, 0.2, 2.0], [np.nan, 0, 0]], np.float32)
    reference = brute_force_closest(vertices, faces, points)
    assert reference[0].tolist() == [1.0, 2.0, np.inf] and reference[1].tolist() == [0, 0, -1]
    tol = ORACLE_RTOL * 2.0  # the largest coordinate: the second point's z

    def wrong(distance, prim, max_dist=np.inf):
        return count_wrong(vertices, faces, points, np.array(distance, np.float32), np.array(prim, np.int32),
                           max_dist, reference)

    assert wrong([1.0, 2.0, np.inf], [0, 0, -1]) == 0
    assert wrong([1.0, 2.0 + 0.5 * tol, np.inf], [0, 0, -1]) == 0   # within the tolerance
    assert wrong([1.0, 2.0 + 2.0 * tol, np.inf], [0, 0, -1]) == 1   # past it
    assert wrong([1.0, 3.0, np.inf], [0, 1, -1]) == 1               # the farther triangle, at its distance
    assert wrong([1.0, 2.0, np.inf], [0, 1, -1]) == 1               # a triangle not at the distance given
    assert wrong([1.0, 2.0, np.inf], [0, 2, -1]) == 1               # no triangle of the mesh
    assert wrong([1.0, np.inf, np.inf], [0, -1, -1]) == 1           # nothing found, unbounded
    assert wrong([1.0, 2.0, 0.0], [0, 0, 0]) == 1                   # something found for a NaN point
    assert wrong([1.0, np.inf, np.inf], [0, -1, -1], max_dist=1.5) == 0  # the second lies past the bound
    assert wrong([1.0, 2.0, np.inf], [0, 0, -1], max_dist=1.5) == 1
    assert wrong([1.0, 2.0, np.inf], [0, 0, -1], max_dist=2.0 - 0.5 * tol) == 0  # at the bound: either way
    assert wrong([1.0, np.inf, np.inf], [0, -1, -1], max_dist=2.0 + 0.5 * tol) == 0


@pytest.mark.parametrize("count", range(1, 9))
def test_turn_order_balances_what_runs_first_and_before(count):
    """Over one cycle of turns (count turns, 2 count for an odd count) every mode runs first
    equally often and right after every other mode equally often, each turn a permutation:
    counted here, pair by pair, from the orders themselves."""
    from collections import Counter

    from hlbvh_warp.bench import turn_order

    labels = [f"mode {i}" for i in range(count)]
    cycle = count if count % 2 == 0 else 2 * count
    firsts, pairs = Counter(), Counter()
    for turn in range(cycle):
        order = turn_order(labels, turn)
        assert sorted(order) == sorted(labels)
        assert order == turn_order(labels, turn + cycle)  # the cycle repeats
        firsts[order[0]] += 1
        pairs.update(zip(order, order[1:]))
    assert set(firsts) == set(labels) and len(set(firsts.values())) == 1
    if count > 1:
        assert len(pairs) == count * (count - 1) and len(set(pairs.values())) == 1, pairs


def _plate_past_float32s_reach(path):
    """A square plate at z = -3e38 and a small triangle at the origin, written to ``path``: the
    commands' rays from above start near z = 2e38 and meet the plate more than float32's largest
    value (3.4e38) away, a distance the library documents as a miss."""
    import trimesh

    w = 5e37
    vertices = np.array([[-w, -w, -3e38], [w, -w, -3e38], [w, w, -3e38], [-w, w, -3e38], [0, 0, 0], [1e30, 0, 0],
                         [0, 1e30, 0]], np.float32)
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6]], np.int32)
    trimesh.Trimesh(vertices, faces, process=False).export(path)
    return vertices, faces


def test_ray_commands_take_hits_past_float32s_range_as_misses(tmp_path, capsys):
    # The float64 brute force of bench-rays and bench found the plate past float32's largest
    # distance where the library, as documented, misses: both commands reported the library's
    # misses as wrong. The tests' own oracle (tests/oracles.py) on the run's very rays: every ray
    # it finds within float32's range the library hits, and the ones it finds past it are misses.
    from oracles import assert_hits_match, brute_force_closest_hit

    from hlbvh_warp import api, cli, query, ray_bench, reference

    path = tmp_path / "plate.ply"
    vertices, faces = _plate_past_float32s_reach(path)
    limit = float(np.finfo(np.float32).max)
    bvh = api.build(vertices, faces, device="cpu")
    rng = np.random.default_rng(0)
    for o, d in (ray_bench.random_rays(rng, vertices, 64), ray_bench.camera_rays(vertices, 64),
                 reference.rays_at_box(np.random.default_rng(1), vertices, 64)):
        t_all, prim_all = brute_force_closest_hit(vertices, faces, o, d)
        assert ((prim_all >= 0) & (t_all > limit)).sum() >= 2  # the case this test is about
        t, prim = query.intersect(bvh, o, d)
        assert_hits_match(t, prim, *brute_force_closest_hit(vertices, faces, o, d, t_max=limit))
    assert cli.main(["bench-rays", "--mesh", str(path), "--rays", "64", "--repeats", "1"]) == 0, capsys.readouterr()
    out = capsys.readouterr().out
    assert all(r[7] == "0" for r in _rows(out, "plate")) and "0 wrong of" in out, out

    json_path = tmp_path / "bench.json"
    assert cli.main(["bench", "--mesh", str(path), "--builders", "hlbvh,lbvh", "--rays", "64", "--repeats", "1",
                     "--warmup", "0", "--json", str(json_path), "--plot", str(tmp_path / "bench.png")]) == 0
    rows = json.loads(json_path.read_text())["rows"]
    assert [r["builder"] for r in rows] == ["hlbvh", "lbvh"] and all("error" not in r for r in rows), rows
    # quality and bench-wide check their primary rays against the same brute force (quality ended
    # in a RuntimeError's traceback); every tree then agrees with the reference tree.
    for command in ("quality", "bench-wide"):
        json_path = tmp_path / f"{command}.json"
        extra = ["--builders", "hlbvh,lbvh"] if command == "quality" else ["--repeats", "1"]
        assert cli.main([command, "--mesh", str(path), "--views", "2", "--side", "16", "--json", str(json_path),
                         *extra]) == 0
        assert all(r["disagree"] == 0 for r in json.loads(json_path.read_text())["rows"])




@pytest.mark.parametrize("generator", ["random_rays", "rays_at_box", "camera_rays", "orbit_rays"])
def test_rays_of_a_mesh_near_float32s_limit_start_within_its_range(generator):
    # Origins past float32's range were cast to Inf with NumPy's "overflow encountered in cast"
    # warning, and those rays found nothing: every ray of a camera 2.5 radii out, and many of the
    # rays aimed at the box. Each is now moved along its ray into the range, hitting what it did.
    import warnings

    import trimesh
    from oracles import assert_hits_match, brute_force_closest_hit

    from hlbvh_warp import api, quality, query, ray_bench, reference

    make = {"random_rays": lambda v: ray_bench.random_rays(np.random.default_rng(0), v, 256),
            "rays_at_box": lambda v: reference.rays_at_box(np.random.default_rng(0), v, 256),
            "camera_rays": lambda v: ray_bench.camera_rays(v, 256),
            "orbit_rays": lambda v: quality.orbit_rays(v, 4, 8)}[generator]
    box = trimesh.creation.box(extents=(4.0, 2.0, 4.0))
    vertices, faces = (np.asarray(box.vertices) * 1e38).astype(np.float32), np.asarray(box.faces, np.int32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        origins, directions = make(vertices)
        t, prim = query.intersect(api.build(vertices, faces, device="cpu"), origins, directions)
    assert np.isfinite(directions).all()
    assert (prim >= 0).mean() > 0.2
    inside = np.isfinite(origins).all(axis=1)
    # Hits past float32's largest distance are misses, as documented (the box is 4e38 across).
    assert_hits_match(t[inside], prim[inside], *brute_force_closest_hit(
        vertices, faces, origins[inside], directions[inside], t_max=float(np.finfo(np.float32).max)))
    assert (prim[~inside] == -1).all()


def test_a_plot_of_wp_mesh_alone_has_no_empty_legend(tmp_path):
    # "bench --sweep --builders wp.Mesh" printed Matplotlib's "No artists with labels found to put
    # in legend": wp.Mesh has no SAH, so its panel has no labelled points.
    import warnings

    rows = [{"mesh": "m", "builder": "wp.Mesh", "setting": "default", "time_ms": {"median": 1.0}, "num_tris": 10}]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        bench.plot(rows, tmp_path / "plot.png")
    assert (tmp_path / "plot.png").stat().st_size > 0
