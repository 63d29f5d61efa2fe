"""`python -m hlbvh_warp demo` end to end on a small scene."""

from __future__ import annotations

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
