"""The package's grouped float64 reference (benchmarks, demo, stress report) against the tests'
plain one, which tests every ray against every triangle: the grouping is a speed-up only, so
the two must agree exactly, to the bit and to the face id on ties."""

from __future__ import annotations

import numpy as np
import pytest
from oracles import brute_force_closest_hit as every_pair

from hlbvh_warp.reference import brute_force_closest_hit


def _scene(seed):
    rng = np.random.default_rng(seed)
    num_tris = int(rng.integers(1, 1500))
    num_rays = int(rng.integers(1, 200))
    scale = float(rng.uniform(0.01, 100.0))
    v = rng.normal(size=(3 * num_tris, 3)) * scale
    if seed % 4 == 1:
        # On a lattice: axis-aligned faces, shared edges and vertices, exact ties.
        v = np.round(v / scale * 3.0)
    f = rng.permutation(3 * num_tris).reshape(num_tris, 3)
    if seed % 5 == 2:
        f[: num_tris // 3, 2] = f[: num_tris // 3, 1]  # degenerate triangles
    extent = float(np.abs(v).max()) or 1.0
    o = rng.normal(size=(num_rays, 3)) * 3.0 * extent
    d = -o + rng.normal(size=(num_rays, 3)) * extent
    if seed % 3 == 0:
        d[:, rng.integers(0, 3)] = 0.0  # parallel to a slab of every box
    if seed % 7 == 3:
        k = min(num_rays, num_tris)
        o[:k] = v[f[:k, 0]]  # starting on a vertex
    t_max = np.inf if seed % 2 else 2.0 * extent
    return v, f, o, d, t_max


@pytest.mark.parametrize("seed", range(24))
@pytest.mark.parametrize("group_size, pair_budget", [(None, 1 << 21), (1, 7), (5, 300), (64, 1 << 12)])
def test_grouped_reference_equals_every_pair(seed, group_size, pair_budget):
    v, f, o, d, t_max = _scene(seed)
    t_ref, p_ref = every_pair(v, f, o, d, t_max=t_max)
    t, p = brute_force_closest_hit(v, f, o, d, t_max=t_max, group_size=group_size, pair_budget=pair_budget)
    np.testing.assert_array_equal(p, p_ref)
    np.testing.assert_array_equal(t, t_ref)


def test_grouped_reference_on_a_mesh():
    from hlbvh_warp.reference import rays_at_box
    from hlbvh_warp.scenes import default_scene

    # A closed surface, where each ray crosses few groups: most groups are skipped.
    v, f = default_scene(num_tris=6000)
    o, d = rays_at_box(np.random.default_rng(3), v, 200)
    t_ref, p_ref = every_pair(v, f, o, d)
    t, p = brute_force_closest_hit(v, f, o, d)
    assert (p_ref >= 0).sum() > 50
    np.testing.assert_array_equal(p, p_ref)
    np.testing.assert_array_equal(t, t_ref)


def test_grouped_reference_empty_inputs():
    v = np.zeros((3, 3))
    t, p = brute_force_closest_hit(v, np.zeros((0, 3), dtype=np.int64), np.zeros((4, 3)), np.ones((4, 3)))
    assert np.isinf(t).all() and (p == -1).all()
    t, p = brute_force_closest_hit(v, np.array([[0, 1, 2]]), np.zeros((0, 3)), np.zeros((0, 3)))
    assert t.shape == (0,) and p.shape == (0,)


@pytest.mark.parametrize("group_size, pair_budget", [(None, 1 << 21), (2, 16), (64, 1 << 12)])
def test_ties_go_to_the_lowest_face_id(group_size, pair_budget):
    # Every triangle twice, the copies far apart in face order (and so in different groups and
    # pieces): each hit is an exact tie, which both oracles give to the lower face id.
    v, f, o, d, _ = _scene(7)
    rng = np.random.default_rng(7)
    copies = np.concatenate([f, f[::-1]])
    shuffle = rng.permutation(len(copies))
    faces = copies[shuffle]
    t_ref, p_ref = every_pair(v, faces, o, d)
    t, p = brute_force_closest_hit(v, faces, o, d, group_size=group_size, pair_budget=pair_budget)
    assert (p_ref >= 0).sum() >= 5
    np.testing.assert_array_equal(p, p_ref)
    np.testing.assert_array_equal(t, t_ref)
    # The winner is the lower of the two copies' ids.
    hit = p >= 0
    original = np.where(shuffle < len(f), shuffle, 2 * len(f) - 1 - shuffle)
    by_original = {}
    for face_id, k in enumerate(original):
        by_original.setdefault(int(k), []).append(face_id)
    for prim in p[hit]:
        assert prim == min(by_original[int(original[prim])])


def test_slab_test_counts_touching_and_parallel_rays():
    from hlbvh_warp.reference import _boxes_met

    lower = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    upper = np.array([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0]])  # a cube and a flat square on its top
    origins = np.array([
        [-1.0, 0.5, 1.0],  # along the top face, parallel to z: touches both
        [-1.0, 0.0, 0.5],  # along the y = 0 face, parallel to y and z
        [0.5, 0.5, 2.0],  # straight down onto the square: near == far for the flat box
        [-1.0, 0.5, 1.5],  # parallel to z, above both
        [2.0, 0.5, 0.5],  # pointing away
    ])
    directions = np.array([[1.0, 0.0, 0.0], [1.0, -0.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0],
                           [1.0, 1e-320, 0.0]])
    met = _boxes_met(lower, upper, origins, directions)
    expected = np.array([[True, True], [True, False], [True, True], [False, False], [False, False]])
    np.testing.assert_array_equal(met, expected)


def test_a_tie_found_in_a_later_piece_still_goes_to_the_lower_id():
    # Two triangles sharing the edge (1,0,0)-(0,1,0); the ray hits the edge's midpoint, so both
    # at t = 1 exactly. The triangle met first (its group is first on the curve) has the higher
    # id; with one pair per piece the lower id arrives later and must still win the tie.
    v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    faces = np.array([[1, 3, 2], [0, 1, 2]])
    o, d = np.array([[0.5, 0.5, 1.0]]), np.array([[0.0, 0.0, -1.0]])
    assert every_pair(v, faces, o, d)[1][0] == 0
    t, p = brute_force_closest_hit(v, faces, o, d, group_size=1, pair_budget=1)
    assert p[0] == 0 and t[0] == 1.0


@pytest.mark.parametrize("eps, miss_by", [(1e-12, 1e-13), (1e-6, 1e-7)])
def test_hits_inside_the_barycentric_slack_are_kept(eps, miss_by):
    # The ray meets the triangle's plane just outside its edge x = 0, inside the accept test's
    # slack: a hit, though outside the triangle's box. The box test must not lose it.
    v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    faces = np.array([[0, 1, 2]])
    o, d = np.array([[-miss_by, 0.5, 1.0]]), np.array([[0.0, 0.0, -1.0]])
    t, p = brute_force_closest_hit(v, faces, o, d, eps=eps, group_size=1)
    assert p[0] == 0 and t[0] == 1.0
    t, p = brute_force_closest_hit(v, faces, o, d, eps=0.0, group_size=1)
    assert p[0] == -1


def test_a_tie_must_name_a_triangle_the_ray_meets(monkeypatch):
    """The commands' checks took another triangle at the same t as a tie on the distance alone: a
    traversal that reported every hit under a wrong id (the leaf's slot in ``prim_order`` instead
    of the face it holds) passed bench's, the demo's, bench-rays' and stress's checks with no
    ray wrong. A tie now names a triangle the ray meets at that t, or passes within rounding of
    (a shared edge), and a ray through a shared edge may still name either triangle."""
    import trimesh

    import hlbvh_warp as hb
    from hlbvh_warp import demo, query, ray_bench, reference, stress_report

    ball = trimesh.creation.icosphere(subdivisions=2)
    v, f = np.asarray(ball.vertices, np.float32), np.asarray(ball.faces, np.int32)
    rng = np.random.default_rng(3)
    o, d = reference.rays_at_box(rng, v, 64)
    t_ref, p_ref = every_pair(v, f, o, d)
    hit = p_ref >= 0
    assert hit.sum() > 20
    wrong = np.where(hit, (p_ref + 7) % len(f), -1)  # the right distance under another face's id
    t = t_ref.astype(np.float32)
    rays = (v, f, o, d)
    assert reference.count_mismatches(t, wrong, t_ref, p_ref, rays=rays) == hit.sum()
    assert reference.count_mismatches(t, p_ref, t_ref, p_ref, rays=rays) == 0
    assert stress_report.classify(v, f, o, d, t, wrong, t_ref, p_ref) == (hit.sum(), hit.sum())
    assert ray_bench.count_wrong(v, f, o, d, t, wrong) == hit.sum()
    bvh = hb.build(v, f)
    monkeypatch.setattr(query, "intersect", lambda *args, **kwargs: (t, wrong))
    assert demo.check_rays(bvh, v, f, o, d, (t_ref, p_ref)) == hit.sum()
    # A ray aimed at the midpoint of a shared edge: the triangle on the other side is a tie.
    a, b = f[0, 0], f[0, 1]
    other = next(i for i in range(1, len(f)) if {a, b} <= set(f[i].tolist()))
    mid = 0.5 * (v[a].astype(np.float64) + v[b])
    origin = (3.0 * mid).astype(np.float32)[None]
    direction = (-mid / np.linalg.norm(mid)).astype(np.float32)[None]
    t_edge, p_edge = every_pair(v, f, origin, direction)
    assert p_edge[0] in (0, other)
    swapped = np.array([other if p_edge[0] == 0 else 0])
    assert reference.count_mismatches(t_edge.astype(np.float32), swapped, t_edge, p_edge,
                                      rays=(v, f, origin, direction)) == 0
    assert stress_report.classify(v, f, origin, direction, t_edge, swapped, t_edge, p_edge)[1] == 0
