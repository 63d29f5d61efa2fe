"""The quality command: SAH, EPO and measured ray cost per builder, and the rays it traces."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

import hlbvh_warp as hw
from hlbvh_warp import quality
from oracles import brute_force_closest_hit, numpy_end_point_overlap, random_soup
from test_metrics import numpy_sah


def test_quality_rows_against_the_oracles(tmp_path, rng):
    v, f = random_soup(rng, 60, scale=0.3)
    mesh_path = tmp_path / "soup.ply"
    trimesh.Trimesh(v, f, process=False).export(mesh_path)
    out = tmp_path / "quality.json"
    code = quality.main(["--mesh", str(mesh_path), "--builders", "hlbvh,median", "--views", "2", "--side", "12",
                         "--device", "cpu", "--json", str(out)])
    assert code == 0
    data = json.loads(out.read_text())
    rows = {r["builder"]: r for r in data["rows"]}
    # The reference joins when not asked for: every ratio needs it.
    assert set(rows) == {"hlbvh", "median", "sweep_sah"}
    for name, row in rows.items():
        tree = hw.build(v, f, method=name, device="cpu").to_numpy()
        assert row["sah"] == pytest.approx(numpy_sah(tree, 1.2, 1.0), rel=1e-6)
        assert row["epo"] == pytest.approx(numpy_end_point_overlap(tree, v, f, 1.2, 1.0)[0], rel=1e-9)
        assert row["disagree"] == 0
        for kind in ("primary", "diffuse"):
            r = row[kind]
            assert r["num_rays"] > 0 and r["n_s"] >= 1.0
            assert r["m"] == pytest.approx(1.2 * r["n_s"] + 1.0 * r["n_t"])
            assert r["m_ratio"] == pytest.approx(r["m"] / rows["sweep_sah"][kind]["m"])
        assert row["epo_ratio"] == pytest.approx(row["epo"] / rows["sweep_sah"]["epo"])
    assert rows["sweep_sah"]["sah_ratio"] == 1.0


def test_orbit_cameras_look_at_the_mesh():
    v = np.array([[-1, -2, -3], [3, 2, 1]], dtype=np.float32)
    origins, directions = quality.orbit_rays(v, views=5, side=9)
    assert origins.shape == directions.shape == (5 * 81, 3)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0, rtol=1e-6)
    center = np.array([1.0, 0.0, -1.0])
    for k in range(5):
        # The middle pixel of each image points at the box's center.
        middle = k * 81 + 40
        to_center = center - origins[middle]
        np.testing.assert_allclose(directions[middle], to_center / np.linalg.norm(to_center), atol=1e-6)
    # Five distinct cameras at one distance from the center.
    eyes = origins[::81]
    assert len(np.unique(np.round(eyes, 4), axis=0)) == 5
    np.testing.assert_allclose(np.linalg.norm(eyes - center, axis=1), np.linalg.norm(eyes[0] - center), rtol=1e-5)


def test_diffuse_rays_leave_the_seen_side_cosine_distributed():
    # A large square of two triangles facing +z, seen from above and (for half the rays) below.
    v = np.array([[-10, -10, 0], [10, -10, 0], [10, 10, 0], [-10, 10, 0]], dtype=np.float32)
    f = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)
    rng = np.random.default_rng(3)
    count = 20000
    origins = np.concatenate([rng.uniform(-5, 5, (count, 3)) * [1, 1, 0] + [0, 0, 4],
                              rng.uniform(-5, 5, (count, 3)) * [1, 1, 0] + [0, 0, -4]]).astype(np.float32)
    directions = np.tile(np.array([[0, 0, -1]], np.float32), (2 * count, 1))
    directions[count:] *= -1
    t, prim = brute_force_closest_hit(v, f, origins, directions)
    assert (prim >= 0).all()
    out_o, out_d = quality.diffuse_rays(rng, v, f, origins, directions, t.astype(np.float32), prim)
    side = np.sign(origins[:, 2])
    # Each ray starts just off the hit point, on the side its camera ray came from.
    np.testing.assert_allclose(out_o[:, :2], origins[:, :2], atol=1e-5)
    assert np.all(out_o[:, 2] * side > 0) and np.all(np.abs(out_o[:, 2]) < 1e-3)
    cos = out_d[:, 2] * side
    np.testing.assert_allclose(np.linalg.norm(out_d, axis=1), 1.0, rtol=1e-5)
    assert cos.min() >= 0.0
    # Cosine-weighted: E[cos] = 2/3 and E[cos^2] = 1/2 (uniform would give 1/2 and 1/3).
    assert cos.mean() == pytest.approx(2 / 3, abs=0.01)
    assert (cos ** 2).mean() == pytest.approx(1 / 2, abs=0.01)
    # Azimuths spread evenly: no preferred tangent direction.
    assert abs(out_d[:, 0].mean()) < 0.01 and abs(out_d[:, 1].mean()) < 0.01


def test_quality_rejects_bad_arguments():
    for argv in (["--builders", "nope"], ["--views", "0"], ["--ci", "0"], ["--ct", "-1"]):
        with pytest.raises(SystemExit):
            quality.parse_args(argv)


def test_epo_weight_recovers_a_known_mix():
    rng = np.random.default_rng(5)
    sah, epo = rng.uniform(50, 90, 7), rng.uniform(4, 16, 7)
    rows = [{"sah": a, "epo": b, "diffuse": {"m": 3.0 + 0.4 * a + 0.6 * b * 7.0}} for a, b in zip(sah, epo)]
    # m = 3 + 0.4 SAH + 4.2 EPO is a multiple of SAH (1 - a) + EPO a at a = 4.2 / 4.6.
    fit = quality.epo_weight(rows, "diffuse", steps=4601)
    assert fit["alpha"] == pytest.approx(4.2 / 4.6, abs=1e-3)
    assert fit["r"] == pytest.approx(1.0, abs=1e-9)
    assert fit["r_sah"] < fit["r"]
    # The same tree twice counts once; fewer than three distinct trees give no fit.
    assert quality.epo_weight(rows + rows[:1], "diffuse", steps=4601)["trees"] == 7
    assert np.isnan(quality.epo_weight(rows[:2], "diffuse")["alpha"])


@pytest.mark.parametrize("scale", [1e200, 1e-200])
def test_epo_weight_does_not_depend_on_the_costs_scale(scale):
    # Every measure scales with --ct and --ci, and a correlation does not change with the scale.
    # corrcoef squared the values: at costs of 1e200 its sums overflowed, at 1e-200 they vanished,
    # every r came out NaN, and `quality --ct 1.2e200 --ci 1e200` ended, after every build, in
    # "error: All-NaN slice encountered".
    rng = np.random.default_rng(5)
    sah, epo = rng.uniform(50, 90, 7), rng.uniform(4, 16, 7)
    rows = [{"sah": a, "epo": b, "diffuse": {"m": 3.0 + 0.4 * a + 0.6 * b * 7.0}} for a, b in zip(sah, epo)]
    scaled = [{"sah": r["sah"] * scale, "epo": r["epo"] * scale, "diffuse": {"m": r["diffuse"]["m"] * scale}}
              for r in rows]
    fit, fit_scaled = quality.epo_weight(rows, "diffuse", steps=4601), quality.epo_weight(scaled, "diffuse", steps=4601)
    assert fit_scaled["alpha"] == pytest.approx(fit["alpha"], abs=1e-3)
    assert fit_scaled["r"] == pytest.approx(fit["r"], abs=1e-9)
    assert fit_scaled["r_sah"] == pytest.approx(fit["r_sah"], abs=1e-9)


def test_epo_weight_of_trees_alike_in_sah_and_epo_is_no_fit():
    # Three trees of one SAH and one EPO that trace differently: no mix of the two tells them
    # apart, so there is no fit (NumPy's nanargmax raised on the all-NaN correlations).
    rows = [{"sah": 60.0, "epo": 9.0, "diffuse": {"m": m}} for m in (20.0, 21.0, 23.0)]
    fit = quality.epo_weight(rows, "diffuse")
    assert np.isnan(fit["alpha"]) and np.isnan(fit["r"]) and fit["trees"] == 3


def test_spatial_splits_in_the_quality_table(tmp_path):
    """The generated scene with large triangles across it: sbvh's row beats the sweep on every
    measure the table reports (Stich et al.'s case), and its rays agree with the brute force."""
    out = tmp_path / "quality.json"
    code = quality.main(["--scene", "knot+large", "--scene-tris", "3000", "--builders", "sbvh", "--views", "2",
                         "--side", "16", "--device", "cpu", "--json", str(out)])
    assert code == 0
    rows = {r["builder"]: r for r in json.loads(out.read_text())["rows"]}
    assert set(rows) == {"sbvh", "sweep_sah"}
    row = rows["sbvh"]
    assert row["disagree"] == 0
    assert row["sah_ratio"] < 0.95 and row["epo_ratio"] < 0.5
    assert row["primary"]["m_ratio"] < 1.0 and row["diffuse"]["m_ratio"] < 1.0


def test_quality_on_a_flat_mesh_and_ties_in_the_last_bits(tmp_path):
    """A flat mesh: every diffuse ray leaves its plane and no ray enters the root box (m = 0), so
    there is no diffuse ratio, not a ZeroDivisionError. And the same tree whose SAH and EPO were
    summed in another order (differing in the last bits) counts once in the EPO fit."""
    path = tmp_path / "square.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 1 3 4\n")
    out = tmp_path / "quality.json"
    code = quality.main(["--mesh", str(path), "--builders", "hlbvh", "--views", "2", "--side", "8",
                         "--device", "cpu", "--json", str(out)])
    assert code == 0
    rows = {r["builder"]: r for r in json.loads(out.read_text())["rows"]}
    for row in rows.values():
        assert row["diffuse"]["m"] == 0.0 and np.isnan(row["diffuse"]["m_ratio"])
        assert row["primary"]["m_ratio"] == pytest.approx(1.0)

    rng = np.random.default_rng(5)
    sah, epo = rng.uniform(50, 90, 7), rng.uniform(4, 16, 7)
    rows = [{"sah": a, "epo": b, "diffuse": {"m": 3.0 + 0.4 * a + 0.6 * b * 7.0}} for a, b in zip(sah, epo)]
    twin = {"sah": np.nextafter(sah[0], np.inf), "epo": np.nextafter(epo[0], -np.inf), "diffuse": rows[0]["diffuse"]}
    assert quality.epo_weight(rows + [twin], "diffuse")["trees"] == 7


def test_quality_counts_a_wrong_triangle_at_the_right_distance(tmp_path, rng, monkeypatch):
    """The disagree column took a different triangle at the same distance as a tie, so a walk
    that reported the right t under another triangle's id passed. It now accepts such a tie only
    where the ray meets the named triangle there, as the bench's check does."""
    from hlbvh_warp import query

    v, f = random_soup(rng, 60, scale=0.3)
    mesh_path = tmp_path / "soup.ply"
    trimesh.Trimesh(v, f, process=False).export(mesh_path)
    true_intersect = query.intersect

    def misnaming_intersect(bvh, *args, **kwargs):
        t, prim, *rest = true_intersect(bvh, *args, **kwargs)
        if bvh.method == "median":
            # The right distance under the next triangle's id.
            prim = np.where(prim >= 0, (prim + 1) % len(f), prim)
        return (t, prim, *rest)

    monkeypatch.setattr(query, "intersect", misnaming_intersect)
    out = tmp_path / "quality.json"
    # The command exits 1 when a builder disagrees.
    assert quality.main(["--mesh", str(mesh_path), "--builders", "hlbvh,median", "--views", "2", "--side", "12",
                         "--device", "cpu", "--json", str(out)]) == 1
    rows = {r["builder"]: r for r in json.loads(out.read_text())["rows"]}
    assert rows["hlbvh"]["disagree"] == 0
    assert rows["median"]["disagree"] > 0
