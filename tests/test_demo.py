"""`python -m hlbvh_warp demo` end to end on a small scene."""

from __future__ import annotations

import subprocess
import sys

import pytest
import warp as wp

from hlbvh_warp import cli


def test_demo_runs_and_writes_outputs(tmp_path, capsys):
    out = tmp_path / "demo"
    rc = cli.main(["demo", "--num-tris", "1500", "--rays", "48", "--num-frames", "2", "--image-size", "24",
                   "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "48/48 rays match" in text and "hlbvh:" in text and "lbvh:" in text
    assert "average" in text and "worst" in text
    for name in ("exploding_mesh.png", "exploding_mesh.gif", "exploding_frame_ms.png"):
        assert (out / name).stat().st_size > 0, name
    # The per-frame table is followed by a line saying what its terms mean, "sampled M/N" (which
    # the CPU's resorting builder reports on every rebuilt frame after the first) among them,
    # with the sample's size and the limit the builder compares it with.
    lines = text.splitlines()
    summary = next(i for i, line in enumerate(lines) if line.startswith("2 frames: average"))
    assert "sampled M/N" in "\n".join(lines[summary - 2:summary])
    legend = lines[summary + 1]
    assert legend.startswith("ms: the Builder's update of the frame") and "resorted: fed in the last frame's" in legend
    assert "sampled M/N: of 256 evenly spaced adjacent pairs in the last tree's order" in legend, legend
    assert "past 0.1 (global_sort_runs) the faces' order is fed instead" in legend, legend


def test_the_demo_prints_its_table_without_warps_messages(tmp_path):
    # Warp 1.19 logs its banner and a line per kernel module loaded at the info level, which
    # `config.quiet` no longer turns off: those lines fell between the demo's rows. Its own
    # process, so that Warp is initialized (and its modules loaded) by the demo itself.
    run = subprocess.run([sys.executable, "-m", "hlbvh_warp", "demo", "--num-tris", "800", "--rays", "16",
                          "--num-frames", "1", "--image-size", "16", "--methods", "hlbvh,median",
                          "--out", str(tmp_path / "out")], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    assert "16/16 rays match" in run.stdout
    for noise in ("Module ", "initialized", "Kernel cache"):
        assert noise not in run.stdout + run.stderr, noise


def test_bad_arguments_end_in_one_line_errors(tmp_path, capsys):
    # Each exits with status 2 and a message naming the problem on stderr, never a traceback.
    not_a_mesh = tmp_path / "notes.txt"
    not_a_mesh.write_text("not a mesh")
    cases = [
        (["demo", "--mesh", str(tmp_path / "missing.ply")], "no such mesh file"),
        (["demo", "--num-frames", "-3"], "--num-frames: must be at least 1"),
        (["bench", "--scene-tris", "-5"], "--scene-tris: must be at least 1"),
        (["bench", "--warmup", "-2"], "--warmup: must be at least 0"),
        (["quality", "--mesh", str(not_a_mesh)],
         f"python -m hlbvh_warp quality: error: {not_a_mesh}: file_type 'txt' not supported"),
        (["nosuch"], "unknown command 'nosuch'"),
    ]
    for argv, message in cases:
        try:
            rc = cli.main(argv)
        except SystemExit as exit_:  # argparse's own errors
            rc = exit_.code
        err = capsys.readouterr().err
        assert rc == 2 and message in err, (argv, rc, err)
        assert "Traceback" not in err


def test_mesh_files_with_several_objects_or_none_read_alike_in_every_command(tmp_path, capsys):
    # A file trimesh loads as a Scene (several objects) is one mesh for every command, bench-rays
    # included; a file with no triangles is one line naming it, not NumPy's error about
    # reductions over no rows (demo) or an AttributeError traceback (bench-rays).
    import trimesh

    two = tmp_path / "two.glb"
    trimesh.Scene([trimesh.creation.box(), trimesh.creation.icosphere(1).apply_translation((3, 0, 0))]).export(two)
    empty = tmp_path / "empty.obj"
    empty.write_text("")
    rc = cli.main(["bench-rays", "--mesh", str(two), "--rays", "64", "--repeats", "1"])
    out = capsys.readouterr().out
    assert rc == 0 and "0 wrong of 128 rays checked; wp.Mesh differs from ours on 0 rays" in out, out
    rc = cli.main(["bench-points", "--mesh", str(two), "--points", "64", "--repeats", "1"])
    out = capsys.readouterr().out
    assert rc == 0 and "0 wrong of 192 points checked; wp.Mesh differs from ours on 0 points" in out, out
    rc = cli.main(["bench-pairs", "--mesh", str(two), "--repeats", "1"])
    out = capsys.readouterr().out
    assert rc == 0 and " 0 wrong of " in out and "wp.Mesh's disagreements with ours: 0 " in out, out
    for argv in (["demo", "--mesh", str(empty), "--num-frames", "1", "--out", str(tmp_path / "out")],
                 ["bench-pairs", "--mesh", str(empty), "--repeats", "1"],
                 ["bench-rays", "--mesh", str(empty), "--rays", "8", "--repeats", "1"],
                 ["bench-points", "--mesh", str(empty), "--points", "8", "--repeats", "1"]):
        rc = cli.main(argv)
        err = capsys.readouterr().err
        assert rc == 2 and "the mesh has no triangles" in err and "Traceback" not in err, (argv, err)


@pytest.mark.skipif(bool(wp.get_cuda_devices()), reason="needs a machine without CUDA")
@pytest.mark.parametrize("command", ["demo", "bench", "bench-rays", "bench-points", "bench-pairs", "bench-wide",
                                     "quality", "stress"])
def test_cuda_device_without_cuda_is_a_one_line_error(command, capsys):
    # Warp raises a RuntimeError for "cuda" where there is none (a ValueError for "cuda:0"):
    # every command's --device names it in one line, before any work.
    try:
        rc = cli.main([command, "--device", "cuda"])
    except SystemExit as exit_:  # argparse's own errors
        rc = exit_.code
    err = capsys.readouterr().err
    assert rc == 2 and "--device" in err and "CUDA" in err, (command, rc, err)


def test_demo_checks_every_method_name_before_building(tmp_path, monkeypatch, capsys):
    # A trailing comma or a misspelt name used to fail only once the builds before it had run.
    from hlbvh_warp import api

    def no_build(*args, **kwargs):
        raise AssertionError("built before the names were checked")

    monkeypatch.setattr(api, "build", no_build)
    for methods in ("hlbvh,", "hlbvh,nosuch"):
        rc = cli.main(["demo", "--methods", methods, "--num-frames", "1", "--out", str(tmp_path / "out")])
        err = capsys.readouterr().err
        assert rc == 2 and "unknown method" in err and "Traceback" not in err, (methods, err)


def _exit_code(argv):
    """cli.main's status, argparse's own errors (SystemExit) included."""
    try:
        return cli.main(argv)
    except SystemExit as exit_:
        return exit_.code


def test_mesh_file_trimesh_cannot_read_is_one_line_in_every_command(tmp_path, capsys):
    # An OBJ face naming vertex 9 of 3 raised an IndexError inside trimesh's loader, a traceback
    # in every command; each names the file and the problem now (the load comes first: no work).
    bad = tmp_path / "bad_face.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")
    for command in ("demo", "bench", "bench-rays", "bench-points", "bench-pairs", "bench-wide", "quality"):
        argv = [command, "--mesh", str(bad), "--repeats", "1"] if command.startswith("bench-") else \
            [command, "--mesh", str(bad)]
        rc = _exit_code(argv + (["--out", str(tmp_path / "out")] if command == "demo" else []))
        err = capsys.readouterr().err
        assert rc == 2 and "Traceback" not in err, (command, rc, err)
        assert len(err.strip().splitlines()) == 1, (command, err)
        assert str(bad) in err and "IndexError" in err and "a vertex the file does not have" in err, (command, err)


def test_demo_checks_the_mesh_before_its_reference(tmp_path, monkeypatch, capsys):
    # A PLY face naming vertex 9 of 3 (trimesh reads it without a word) failed with NumPy's
    # IndexError in the float64 reference, which ran before build() validated the mesh.
    from hlbvh_warp import api

    def no_build(*args, **kwargs):
        raise AssertionError("built before the mesh was checked")

    monkeypatch.setattr(api, "build", no_build)
    ply = tmp_path / "bad_face.ply"
    ply.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                   "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
                   "0 0 0\n1 0 0\n0 1 0\n3 0 1 9\n")
    rc = _exit_code(["demo", "--mesh", str(ply), "--rays", "4", "--num-frames", "1", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err, err
    assert f"{ply}: face index 9 out of range [0, 3)" in err, err


def test_demo_refuses_bad_arguments_before_any_work(tmp_path, monkeypatch, capsys):
    # --out naming a file failed with "[Errno 17] File exists" after every build and the whole
    # animation; --methods "" ran every method; --mesh naming a folder said "no such mesh file".
    from hlbvh_warp import api, scenes

    def no_work(*args, **kwargs):
        raise AssertionError("worked before the arguments were checked")

    monkeypatch.setattr(api, "build", no_work)
    monkeypatch.setattr(scenes, "default_scene", no_work)
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    fast = ["--num-tris", "100", "--rays", "4", "--num-frames", "1", "--image-size", "8"]
    cases = [
        (["demo", *fast, "--out", str(a_file)], f"--out {a_file} is a file, not a folder"),
        (["demo", *fast, "--out", str(a_file / "inside")], f"--out {a_file / 'inside'}: cannot make the folder"),
        (["demo", *fast, "--methods", "", "--out", str(tmp_path / "out")], "--methods '' names no method"),
        (["demo", *fast, "--methods", " ", "--out", str(tmp_path / "out")], "--methods ' ' names no method"),
        (["demo", "--mesh", str(tmp_path)], f"{tmp_path} is a directory, not a mesh file"),
        (["bench", "--mesh", str(tmp_path)], f"{tmp_path} is a directory, not a mesh file"),
        (["quality", "--mesh", str(tmp_path)], f"{tmp_path} is a directory, not a mesh file"),
        (["bench-wide", "--mesh", str(tmp_path)], f"{tmp_path} is a directory, not a mesh file"),
        (["bench-points", "--mesh", str(tmp_path)], f"{tmp_path} is a directory, not a mesh file"),
    ]
    for argv, message in cases:
        rc = _exit_code(argv)
        err = capsys.readouterr().err
        assert rc == 2 and message in err and "Traceback" not in err, (argv, rc, err)
    assert a_file.is_file() and not (tmp_path / "out").exists()


def _icosphere_scaled_to(largest: float):
    """An icosphere (80 triangles) whose largest coordinate is ``largest``, as float32."""
    import numpy as np
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=1)
    vertices = np.asarray(sphere.vertices, np.float64)
    return (vertices * (largest / np.abs(vertices).max())).astype(np.float32), np.asarray(sphere.faces, np.int32)


def test_demo_refuses_a_mesh_too_large_for_its_animation(tmp_path, monkeypatch, capsys):
    # A finite mesh with coordinates of 3e38 passed the builds; its exploding triangles then
    # overflowed float32 and the animation's builder said "vertices has a NaN or Inf coordinate",
    # a NaN the demo had made, not the file. Refused before any work now, with the reason.
    import trimesh

    from hlbvh_warp import api

    def no_build(*args, **kwargs):
        raise AssertionError("built before the mesh was checked")

    monkeypatch.setattr(api, "build", no_build)
    path = tmp_path / "huge.ply"
    trimesh.Trimesh(*_icosphere_scaled_to(3e38), process=False).export(path)
    rc = _exit_code(["demo", "--mesh", str(path), "--num-frames", "1", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err and "NaN" not in err, err
    assert err.startswith(f"python -m hlbvh_warp demo: error: {path}: coordinates up to 3e+38 are too large for the "
                          "exploding-mesh animation: over --num-frames 1 its float32 arithmetic may reach "), err
    assert err.count("\n") == 1 and "scale the mesh down by a factor of" in err, err


@pytest.mark.parametrize("num_frames", [1, 12, 100])
def test_a_mesh_the_demo_accepts_animates_without_overflow(num_frames):
    # The oracle is the animation itself, run as the demo runs it (ExplodingMesh, seed 0, in
    # float32): a mesh scaled to just inside `animation_reach`'s bound stays finite on every frame,
    # and its largest coordinate stays within the bound; a mesh whose animation does overflow is
    # past the bound.
    import numpy as np

    from hlbvh_warp import demo, reference
    from hlbvh_warp.dynamic import ExplodingMesh

    unit_vertices, faces = _icosphere_scaled_to(1.0)
    scale = 0.999 * reference.FLOAT32_MAX / demo.animation_reach(unit_vertices, num_frames)
    vertices, _ = _icosphere_scaled_to(scale)
    assert demo.animation_reach(vertices, num_frames) <= reference.FLOAT32_MAX
    mesh = ExplodingMesh(vertices, faces, device="cpu", seed=0, speed=demo.EXPLOSION_SPEED)
    for frame in range(num_frames + 1):
        moved = mesh.update(frame / demo.FRAMES_PER_TIME_UNIT).numpy()
        assert np.isfinite(moved).all(), frame
        assert np.abs(moved.astype(np.float64)).max() <= demo.animation_reach(vertices, num_frames)

    # Coordinates of 3e38: the velocities alone (up to half the 1e39 diagonal per unit of time)
    # overflow float32, and every frame has Inf or NaN.
    big_vertices, _ = _icosphere_scaled_to(3e38)
    with np.errstate(over="ignore"):
        moved = ExplodingMesh(big_vertices, faces, device="cpu", seed=0, speed=demo.EXPLOSION_SPEED).update(
            num_frames / demo.FRAMES_PER_TIME_UNIT).numpy()
    assert not np.isfinite(moved).all()
    assert demo.animation_reach(big_vertices, num_frames) > reference.FLOAT32_MAX
