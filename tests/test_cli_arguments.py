"""Bad arguments of the measuring commands: one line naming the problem and exit status 2, before
any mesh is built (every case here stops in argument parsing or the mesh load, in well under a second)."""

from __future__ import annotations

import re

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
            assert f"hlbvh_warp {command}: error: {path}: {problem}" in err, err


# ----------------------------------------------------------------- pinned by the third mutation audit
def test_a_mesh_must_be_a_regular_file(capsys, no_builds):
    # /dev/null exists but holds no mesh (and a FIFO would block trimesh's read): refused by
    # argparse like a missing file, before any work.
    import os

    err = error_of(["quality", "--mesh", os.devnull], capsys)
    assert f"argument --mesh: no such mesh file: {os.devnull}" in err, err


@pytest.mark.parametrize("error", [OSError(28, "No space left on device"), NotImplementedError("no such format"),
                                   ValueError("an empty scene")])
def test_a_commands_input_errors_end_in_one_line(error, capsys, monkeypatch):
    # Bad input the library names ends a command in one line and status 2, whatever its kind.
    def failing(argv):
        raise error

    monkeypatch.setattr(quality, "main", failing)
    err = error_of(["quality"], capsys)
    assert err.strip() == f"hlbvh_warp quality: error: {error}", err


def test_a_commands_bug_keeps_its_traceback(monkeypatch):
    def failing(argv):
        raise RuntimeError("a bug")

    monkeypatch.setattr(quality, "main", failing)
    with pytest.raises(RuntimeError, match="a bug"):
        cli.main(["quality"])
