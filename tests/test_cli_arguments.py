"""Bad arguments of the measuring commands: one line naming the problem and exit status 2, before
any mesh is built (every case here stops in argument parsing or the mesh load, in well under a second)."""

from __future__ import annotations

import re

import numpy as np
import pytest

from hlbvh_warp import bench, cli, quality, wide_bench


def error_of(argv, capsys) -> str:
    """The stderr of ``python -m hlbvh_warp argv``, which must exit with status 2 without a traceback."""
    try:
        rc = cli.main(argv)
    except SystemExit as exit_:  # argparse's own errors
        rc = exit_.code
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err, (argv, rc, err)
    return err


@pytest.fixture
def no_builds(monkeypatch):
    from hlbvh_warp import api

    def no_work(*args, **kwargs):
        raise AssertionError("built before the arguments were checked")

    monkeypatch.setattr(api, "build", no_work)


@pytest.mark.parametrize("command", ["quality", "bench-wide", "bench"])
def test_json_path_is_checked_before_the_run(command, tmp_path, capsys, no_builds):
    # --json /dev/null/q.json said "[Errno 17] File exists: '/dev/null'" after the whole run.
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    cases = [(a_file / "q.json", f"--json {a_file / 'q.json'}: cannot make the folder, {a_file} is a file"),
             (a_file / "sub" / "q.json", f"--json {a_file / 'sub' / 'q.json'}: cannot make the folder, {a_file} "
                                         "is a file"),
             (tmp_path, f"--json {tmp_path} is a folder, not a file")]
    for path, message in cases:
        assert message in error_of([command, "--json", str(path)], capsys)
    if command == "bench":
        assert f"--plot {a_file / 'p.png'}: cannot make the folder" in error_of(
            [command, "--json", str(tmp_path / "b.json"), "--plot", str(a_file / "p.png")], capsys)
    # Nothing is made by the check: the command makes the folder when it writes.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"] and a_file.read_text() == ""


def test_bench_checks_the_default_plot_beside_the_json_before_the_run(tmp_path, capsys, no_builds):
    # Without --plot the plot goes beside the JSON (b.json -> b.png): a folder there was found
    # only after every builder was timed, "[Errno 21] Is a directory", the JSON already written.
    (tmp_path / "b.png").mkdir()
    err = error_of(["bench", "--json", str(tmp_path / "b.json")], capsys)
    assert f"--plot {tmp_path / 'b.png'} is a folder, not a file" in err
    assert not (tmp_path / "b.json").exists()


@pytest.mark.parametrize("extra", [[], ["--plot", "SAME"]])
def test_bench_refuses_a_plot_that_would_overwrite_the_json(extra, tmp_path, capsys, no_builds):
    # --json b.png put the plot beside it at b.png itself: the plot replaced the rows, and the
    # run ended "wrote b.png and b.png".
    json_path = tmp_path / "b.png"
    argv = ["bench", "--json", str(json_path)] + [str(json_path) if a == "SAME" else a for a in extra]
    err = error_of(argv, capsys)
    assert f"--plot {json_path} is the --json file" in err


def test_json_check_accepts_new_folders_and_existing_files(tmp_path):
    for parse in (quality.parse_args, wide_bench.parse_args, bench.parse_args):
        parse(["--json", str(tmp_path / "new" / "deeper" / "x.json")])
        existing = tmp_path / "x.json"
        existing.write_text("{}")
        parse(["--json", str(existing)])
    assert not (tmp_path / "new").exists()


@pytest.mark.parametrize("builders", ["", " ", " , "])
def test_quality_rejects_an_empty_builder_list(builders, capsys):
    # It ran the reference (sweep_sah) alone and exited 0, where bench rejects the same list.
    with pytest.raises(SystemExit) as exit_:
        quality.parse_args(["--builders", builders])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and f"--builders {builders!r} names no builder" in err, err


@pytest.mark.parametrize("option,value", [("--ct", "nan"), ("--ct", "inf"), ("--ci", "nan"), ("--ci", "-inf"),
                                          ("--ci", "1e999")])
def test_quality_rejects_costs_that_are_not_finite(option, value, capsys):
    # "--ct nan" passed the "--ct >= 0" check (every comparison with NaN is false) and failed mid-run.
    with pytest.raises(SystemExit) as exit_:
        quality.parse_args([f"{option}={value}"])  # "=": argparse reads a lone "-inf" as an option
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and f"argument {option}: must be a finite number, got {value}" in err, err


@pytest.mark.parametrize("option", ["--ct", "--ci"])
def test_quality_rejects_costs_that_overflow_the_measures(option, capsys):
    # "--ct 1e308" was accepted, and the SAH, EPO and m came out inf or NaN in every row, exit 0.
    with pytest.raises(SystemExit) as exit_:
        quality.parse_args([option, "1e308"])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and "need --ct and --ci <= 1e+200" in err and "1e+308" in err, err
    assert quality.parse_args([option, "1e200"])  # the bound itself is accepted


def test_quality_costs_at_the_bound_keep_the_measures_finite(device):
    # Through the metrics at the bound, on a mesh near float32's limit, where the areas are largest.
    from hlbvh_warp import api
    from hlbvh_warp.metrics import end_point_overlap, sah_cost

    vertices = np.array([[-3e38, -3e38, -3e38], [3e38, -3e38, 3e38], [-3e38, 3e38, 3e38], [3e38, 3e38, -3e38]],
                        np.float32)
    faces = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]], np.int32)
    bvh = api.build(vertices, faces, method="sweep_sah", device=device)
    cost = quality.MAX_COST
    assert np.isfinite(sah_cost(bvh, cost, cost)) and np.isfinite(end_point_overlap(bvh, cost, cost))


def test_quality_still_rejects_negative_costs(capsys):
    with pytest.raises(SystemExit):
        quality.parse_args(["--ci", "0"])
    assert "need --ct >= 0 and --ci > 0, got --ct 1.2 and --ci 0.0" in capsys.readouterr().err


@pytest.mark.parametrize("command,defaults", [
    ("bench", [("--repeats", "5"), ("--warmup", "1"), ("--rays", "128"), ("--json", "out/bench.json"),
               ("--scene-tris", "60000")]),
    ("quality", [("--scene-tris", "20000"), ("--ct", "1.2"), ("--ci", "1.0"), ("--json", "out/quality.json")]),
    ("bench-wide", [("--repeats", "5"), ("--widths", "2,4,8,16"), ("--json", "out/bench_wide.json")]),
    ("bench-pairs", [("--repeats", "3")]),
])
def test_help_shows_the_defaults(command, defaults, capsys):
    # --help said "timed runs per builder" and "where to write the rows", not how many or where.
    with pytest.raises(SystemExit) as exit_:
        cli.main([command, "--help"])
    out = " ".join(capsys.readouterr().out.split())  # argparse wraps lines where it likes
    assert exit_.value.code == 0
    for option, default in defaults:
        # The option's own help line (up to the next option) ends with its default.
        metavar = option[2:].upper().replace("-", "_")
        assert re.search(rf"{option} {metavar} (?:(?! --).)*?default: {re.escape(default)}\)", out), (option, out)


def test_bench_pairs_refuses_spatial_split_trees_first(tmp_path, capsys, no_builds):
    # sbvh lists some triangles in several leaves; the pair queries refuse such trees, which
    # ended in a NumPy broadcast error in the disagreement count after the build.
    mesh = tmp_path / "tri.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    err = error_of(["bench-pairs", "--mesh", str(mesh), "--repeats", "1", "--method", "hlbvh", "--method", "sbvh"],
                   capsys)
    assert "--method sbvh: spatial-split trees list a triangle in several leaves" in err, err
    err = error_of(["bench-pairs", "--mesh", str(mesh), "--repeats", "1", "--method", "nosuch"], capsys)
    assert "unknown method(s) ['nosuch'] in --method" in err, err


def test_mesh_file_errors_name_the_file(tmp_path, capsys, no_builds):
    # trimesh's own messages ("file_type 'txt' not supported", "Not a ply file!") named no file,
    # which with several --mesh options left the user to guess which.
    text = tmp_path / "notes.txt"
    text.write_text("not a mesh\n")
    garbage = tmp_path / "garbage.ply"
    garbage.write_text("garbage\n")
    for command in ("quality", "bench-wide", "bench"):
        for path, problem in ((text, "file_type 'txt' not supported"), (garbage, "Not a ply file")):
            err = error_of([command, "--mesh", str(path), "--json", str(tmp_path / "x.json")], capsys)
            assert f"python -m hlbvh_warp {command}: error: {path}: {problem}" in err, err


# ----------------------------------------------------------------- pinned by the third mutation audit
def test_a_mesh_must_be_a_regular_file(capsys, no_builds):
    # /dev/null exists but holds no mesh (and a FIFO would block trimesh's read): refused by
    # argparse like a missing file, before any work.
    import os

    err = error_of(["quality", "--mesh", os.devnull], capsys)
    assert f"argument --mesh: no such mesh file: {os.devnull}" in err, err


@pytest.mark.parametrize("command", ["bench-rays", "bench-points", "bench-pairs"])
def test_a_device_or_pipe_as_mesh_is_named_as_such(command, tmp_path, capsys, no_builds):
    # bench-rays, bench-points and bench-pairs check only that a --mesh exists: /dev/null or a
    # named pipe reached trimesh, whose "string is not a file: `/dev/null`" told the user nothing.
    import os

    pipe = tmp_path / "mesh.ply"
    os.mkfifo(pipe)
    for path in (os.devnull, str(pipe)):
        err = error_of([command, "--mesh", path], capsys)
        assert f"{path} is not a regular file" in err and "string is not a file" not in err, err


@pytest.mark.parametrize("error", [OSError(28, "No space left on device"), NotImplementedError("no such format"),
                                   ValueError("an empty scene")])
def test_a_commands_input_errors_end_in_one_line(error, capsys, monkeypatch):
    # Bad input the library names ends a command in one line and status 2, whatever its kind.
    def failing(argv):
        raise error

    monkeypatch.setattr(quality, "main", failing)
    err = error_of(["quality"], capsys)
    assert err.strip() == f"python -m hlbvh_warp quality: error: {error}", err


@pytest.mark.parametrize("error,message", [
    (MemoryError("Unable to allocate 7.28 TiB for an array with shape (1000000, 1000000) and data type float64"),
     "out of memory (Unable to allocate 7.28 TiB for an array with shape (1000000, 1000000) and data type float64); "
     "choose smaller sizes"),
    (MemoryError(), "out of memory; choose smaller sizes"),
])
def test_a_run_that_does_not_fit_in_memory_ends_in_one_line(error, message, capsys, monkeypatch):
    # Sizes within their bounds can still be more than a machine holds: NumPy's MemoryError was a
    # traceback.
    def failing(argv):
        raise error

    monkeypatch.setattr(quality, "main", failing)
    err = error_of(["quality"], capsys)
    assert err.strip() == f"python -m hlbvh_warp quality: error: {message}", err


def test_a_commands_bug_keeps_its_traceback(monkeypatch):
    def failing(argv):
        raise RuntimeError("a bug")

    monkeypatch.setattr(quality, "main", failing)
    with pytest.raises(RuntimeError, match="a bug"):
        cli.main(["quality"])


# ----------------------------------------------------------------- upper bounds on sizes
def passes_the_argument_checks(argv):
    """True when ``python -m hlbvh_warp argv`` gets past its argument checks to the first build,
    which `no_builds` turns into an AssertionError: the bounds accept their own limit."""
    with pytest.raises(AssertionError, match="built before the arguments were checked"):
        cli.main(argv)
    return True


def small_mesh(tmp_path, num_tris: int):
    """An OBJ of ``num_tris`` separate triangles, written to tmp_path."""
    path = tmp_path / f"tris{num_tris}.obj"
    lines = [f"v {k} 0 0\nv {k} 1 0\nv {k} 0 1\n" for k in range(num_tris)]
    lines += [f"f {3 * k + 1} {3 * k + 2} {3 * k + 3}\n" for k in range(num_tris)]
    path.write_text("".join(lines))
    return path


@pytest.mark.parametrize("command,option,limit,why", [
    ("bench", "--scene-tris", (1 << 30) - 1, "a tree holds fewer than 2^30 triangles"),
    ("bench", "--subdivide", 14, "4^15 triangles of one would be more than a tree holds"),
    ("bench", "--rays", 1 << 24, "memory"),
    ("demo", "--num-tris", (1 << 30) - 1, "a tree holds fewer than 2^30 triangles"),
    ("demo", "--image-size", 4096, "memory"),
    ("demo", "--rays", 1 << 24, "memory"),
    ("quality", "--scene-tris", (1 << 30) - 1, "a tree holds fewer than 2^30 triangles"),
    ("quality", "--side", 4096, "memory"),
    ("quality", "--views", 1 << 24, "memory"),
    ("bench-wide", "--scene-tris", (1 << 30) - 1, "a tree holds fewer than 2^30 triangles"),
    ("bench-wide", "--side", 4096, "memory"),
    ("bench-rays", "--rays", 1 << 24, "memory"),
    ("bench-points", "--points", 1 << 24, "memory"),
    ("bench-points", "--max-leaf-size", 1 << 16, "BuildConfig's limit"),
])
def test_sizes_past_their_bound_are_argument_errors(command, option, limit, why, capsys, no_builds):
    # `bench --subdivide 30` was killed at 21 GB; `--image-size 1000000` and the like ended in a
    # MemoryError traceback, `--points 99999999999999999999` in NumPy's "Maximum allowed dimension
    # exceeded", naming no option. The limits: fewer than 2^30 triangles in a tree (the library's
    # MAX_PRIMS, int32 node ids), 2^24 rays or points (gigabytes of memory), 4096^2 pixels.
    for value in (limit + 1, 99999999999999999999):
        last = error_of([command, option, str(value)], capsys).strip().splitlines()[-1]  # after argparse's usage
        prefix = f"python -m hlbvh_warp {command}: error: argument {option}: must be at most {limit} ("
        assert last.startswith(prefix), last
        assert why in last and last.endswith(f"), got {value}"), last


def test_the_bounds_are_the_librarys_limits():
    from hlbvh_warp import inputs
    from hlbvh_warp.config import BuildConfig

    # A tree holds fewer than MAX_PRIMS primitives: the largest scene is one less.
    assert cli.MAX_TRIS == inputs.MAX_PRIMS - 1 == (1 << 30) - 1
    assert 4 ** bench.MAX_SUBDIVIDE <= cli.MAX_TRIS < 4 ** (bench.MAX_SUBDIVIDE + 1)
    BuildConfig(max_leaf_size=cli.MAX_LEAF_SIZE)
    with pytest.raises(ValueError, match="max_leaf_size"):
        BuildConfig(max_leaf_size=cli.MAX_LEAF_SIZE + 1)


def test_a_bound_accepts_its_own_limit(tmp_path, monkeypatch, no_builds):
    from hlbvh_warp import scenes

    onetri = small_mesh(tmp_path, 1)
    # The scenes stay small whatever size is asked for: only the argument checks are under test.
    monkeypatch.setattr(scenes, "subdivide", lambda vertices, faces, times: (vertices, faces))
    monkeypatch.setattr(scenes, "default_scene", lambda num_tris: scenes.torus_knot(rings=3, sides=3))
    monkeypatch.setitem(scenes.GENERATED, "knot", scenes.default_scene)
    # (bench draws its --rays before the first build: the limit is taken by bench-points below.)
    assert passes_the_argument_checks(["bench", "--mesh", str(onetri), "--subdivide", "14",
                                       "--json", str(tmp_path / "b.json")])
    assert passes_the_argument_checks(["demo", "--num-tris", str((1 << 30) - 1), "--image-size", "4096",
                                       "--num-frames", "7", "--out", str(tmp_path / "d")])
    assert passes_the_argument_checks(["quality", "--views", "1", "--side", "4096", "--scene-tris",
                                       str((1 << 30) - 1), "--json", str(tmp_path / "q.json")])
    assert passes_the_argument_checks(["bench-points", "--mesh", str(onetri), "--points", str(1 << 24),
                                       "--max-leaf-size", str(1 << 16)])


def test_subdivide_is_bounded_by_the_meshs_own_size(tmp_path, monkeypatch, capsys, no_builds):
    # 4^k x faces must stay below 2^30, checked when the face count is known and before any split:
    # the split itself ran out of memory first. Three triangles split 14 times are 3 x 2^28, fine;
    # four are 2^30, one too many.
    from hlbvh_warp import scenes

    split = []
    monkeypatch.setattr(scenes, "subdivide", lambda vertices, faces, times: split.append(len(faces)) or
                        (vertices, faces))
    three, four = small_mesh(tmp_path, 3), small_mesh(tmp_path, 4)
    json_path = str(tmp_path / "b.json")
    err = error_of(["bench", "--mesh", str(three), "--mesh", str(four), "--subdivide", "14", "--json", json_path],
                   capsys)
    assert err.strip() == (f"python -m hlbvh_warp bench: error: --subdivide 14: {four} has 4 triangles, "
                           "1073741824 once split; a tree holds fewer than 2^30 triangles"), err
    assert split == []  # not even the first mesh, which was small enough
    assert passes_the_argument_checks(["bench", "--mesh", str(three), "--subdivide", "14", "--json", json_path])
    assert split == [3]


@pytest.mark.parametrize("command", ["quality", "bench-wide"])
def test_views_times_pixels_are_bounded(command, tmp_path, capsys, no_builds):
    # Each option within its own bound, the rays they make together past 2^24.
    err = error_of([command, "--views", "2", "--side", "4096", "--json", str(tmp_path / "q.json")], capsys)
    assert "--views 2 of --side 4096 make 33554432 primary rays, more than 16777216" in err, err


def test_demo_bounds_the_pixels_it_keeps_for_the_gif(tmp_path, monkeypatch, capsys, no_builds):
    # Every frame is kept for the GIF (the first one too: num_frames + 1 images), 7 bytes a pixel
    # by the time it is saved: 2^27 pixels at most.
    from hlbvh_warp import scenes

    monkeypatch.setattr(scenes, "default_scene", lambda num_tris: scenes.torus_knot(rings=3, sides=3))
    out = str(tmp_path / "d")
    err = error_of(["demo", "--num-frames", "2048", "--out", out], capsys)
    assert ("--num-frames 2048 at --image-size 256 keeps 134283264 pixels of frames for the GIF, more than "
            "134217728") in err, err
    assert passes_the_argument_checks(["demo", "--num-frames", "2047", "--out", out])


@pytest.mark.parametrize("command", ["bench", "quality", "bench-wide", "bench-rays", "bench-points", "bench-pairs",
                                     "stress"])
def test_a_negative_seed_is_an_argument_error(command, tmp_path, capsys, no_builds):
    # NumPy's generators take no negative seed: "--seed -1" printed its "expected non-negative
    # integer", which named no option.
    mesh = small_mesh(tmp_path, 1)
    extra = ["--mesh", str(mesh)] if command != "stress" else []
    err = error_of([command, *extra, "--seed", "-1"], capsys)
    assert f"python -m hlbvh_warp {command}: error: argument --seed: must be at least 0, got -1" in err, err


# ----------------------------------------------------------------- invalid meshes name their file
def ply(path, vertices: str, faces: str, num_vertices: int, num_faces: int):
    path.write_text("ply\nformat ascii 1.0\n"
                    f"element vertex {num_vertices}\nproperty float x\nproperty float y\nproperty float z\n"
                    f"element face {num_faces}\nproperty list uchar int vertex_indices\nend_header\n"
                    f"{vertices}{faces}")
    return path


@pytest.mark.parametrize("command", ["bench-rays", "bench-points", "bench-pairs", "bench", "quality", "bench-wide"])
def test_an_invalid_mesh_is_named_before_any_work(command, tmp_path, capsys, no_builds):
    # The build's own checks said "vertices has a NaN or Inf coordinate" or "face index 9 out of
    # range", naming no file; bench-pairs blamed float32's range for a NaN ("the mesh is finite,
    # but too near float32's limit", "shifted by nan"). Every file is now read and checked before
    # the first is measured: the good first mesh is not built (no_builds).
    good = small_mesh(tmp_path, 2)
    nan = ply(tmp_path / "nan.ply", "0 0 0\n1 nan 0\n0 1 0\n", "3 0 1 2\n", 3, 1)
    out_of_range = ply(tmp_path / "oob.ply", "0 0 0\n1 0 0\n0 1 0\n", "3 0 1 2\n3 0 1 9\n", 3, 2)
    extra = ["--json", str(tmp_path / "x.json")] if command in ("bench", "quality", "bench-wide") else []
    for path, problem in ((nan, "vertices has a NaN or Inf coordinate (first at row 1: [1.0, nan, 0.0])"),
                          (out_of_range, "face index 9 out of range [0, 3) (first at face 1)")):
        err = error_of([command, "--mesh", str(good), "--mesh", str(path), *extra], capsys)
        assert err.strip().splitlines()[-1] == f"python -m hlbvh_warp {command}: error: {path}: {problem}", err
        assert "finite" not in err and "float32" not in err, err


def test_the_moved_copy_names_a_nan_as_a_nan():
    from hlbvh_warp.pair_bench import moved_copy

    vertices = np.array([[0.0, 0.0, 0.0], [1.0, np.nan, 0.0], [0.0, 1.0, 0.0]])
    with pytest.raises(ValueError) as error:
        moved_copy(vertices)
    assert str(error.value) == "the mesh has a NaN or Inf coordinate (first at vertex 1: [1.0, nan, 0.0])"
    # A finite mesh whose copy leaves float32's range is still told apart from a NaN.
    with pytest.raises(ValueError, match="the mesh is finite, but too near float32's limit"):
        moved_copy(np.array([[-3.4e38, 0.0, 0.0], [3.4e38, 0.0, 0.0], [0.0, 3.4e38, 0.0]]))


# ------------------------------------------------------------- the default meshes of the query benches
@pytest.mark.parametrize("command", ["bench-rays", "bench-points", "bench-pairs"])
def test_default_meshes_are_read_from_shared_meshes_beside_the_current_folder(command, tmp_path, monkeypatch, capsys):
    # Without --mesh the help says "bunny and armadillo from ../shared/meshes"; the path was taken
    # beside the package's own folder only, so an installed package looked beside site-packages.
    # Two small stand-ins, told apart by their triangle counts, must be the ones measured.
    import trimesh

    from hlbvh_warp import ray_bench

    shared = tmp_path / "shared" / "meshes"
    shared.mkdir(parents=True)
    expected = {"bunny": trimesh.creation.icosphere(subdivisions=1), "armadillo": trimesh.creation.box()}
    for name, mesh in expected.items():
        mesh.export(shared / f"{name}.ply")
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    monkeypatch.setattr(ray_bench, "SHARED_MESHES", tmp_path / "nowhere")
    count = {"bench-rays": ["--rays", "8"], "bench-points": ["--points", "8"], "bench-pairs": []}[command]
    assert cli.main([command, *count, "--repeats", "1"]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines()]
    measured = {row[0]: int(row[1]) for row in rows if row and row[0] in expected}
    assert measured == {name: len(mesh.faces) for name, mesh in expected.items()}, rows


def test_missing_default_meshes_are_one_line_that_names_the_option(tmp_path, monkeypatch, capsys, no_builds):
    from hlbvh_warp import ray_bench

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(ray_bench, "SHARED_MESHES", tmp_path / "nowhere")
    for command in ("bench-rays", "bench-points", "bench-pairs"):
        err = error_of([command], capsys)
        assert "default meshes (bunny.ply and armadillo.ply) are not in" in err and "pass --mesh FILE" in err, err


@pytest.mark.parametrize("command, option", [("demo", "--num-tris"), ("quality", "--scene-tris"),
                                             ("bench-wide", "--scene-tris")])
def test_a_generated_scene_too_small_is_an_argument_error(command, option, capsys, no_builds):
    # The generated knot needs 18 triangles: below that these commands accepted the argument,
    # started Warp and failed in the scene generator, after the argument checks.
    err = error_of([command, option, "5"], capsys)
    assert f"{command}: error: argument {option}: must be at least 18, got 5" in err, err


@pytest.mark.parametrize("argv0, program", [("/usr/local/bin/hlbvh-warp", "hlbvh-warp"),
                                            ("/src/hlbvh_warp/__main__.py", "python -m hlbvh_warp")])
def test_usage_and_errors_name_the_program_the_user_ran(argv0, program, capsys, monkeypatch):
    # The installed script printed "usage: python -m hlbvh_warp ..." and errors prefixed with
    # either form, so a script user was shown a command line they had not typed.
    monkeypatch.setattr("sys.argv", [argv0])
    err = error_of(["bench-pairs", "--no-such-option"], capsys)
    assert err.splitlines()[-1].startswith(f"{program} bench-pairs: error: unrecognized arguments"), err
    assert cli.main(["--help"]) == 0
    assert capsys.readouterr().out.startswith(f"usage: {program} <command>")
    err = error_of(["no-such-command"], capsys)
    assert err.startswith(f"{program}: unknown command 'no-such-command'"), err


def test_stress_checks_its_method_names_before_any_build(capsys, no_builds):
    # An unknown --method after a known one was found only when the loop reached it, after the
    # known one had been built and traced (the other commands check every name first).
    err = error_of(["stress", "--method", "hlbvh", "--method", "foo", "--family", "one"], capsys)
    assert "unknown method(s) ['foo'] in --method" in err, err
