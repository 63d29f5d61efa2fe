"""Stress suite: every builder in api.BUILDERS on adversarial scenes, against a float64 oracle.

Run with ``-s`` to see one row per (family, builder): depth, nodes, disagreements and the ones
that are not near-ties (see ``hlbvh_warp.stress_report`` for the documented tolerance).
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from conftest import shared_mesh
from handmade_trees import caterpillar
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from oracles import brute_force_closest_hit

from hlbvh_warp import api, query, stress_report, wide
from hlbvh_warp.config import TRAVERSAL_STACK_SIZE, BuildConfig

api._load_optional_builders()
METHODS = sorted(api.BUILDERS)
#: Minutes at 100k triangles: left out of the 100k-triangle tests (``sbvh``, the other offline
#: builder, takes seconds and stays in).
SLOW_METHODS = ("recursive_sah",)
#: Binned splits peel one exponent of the exponential scene per level: 77 levels at N = 2,000.
#: Traversal stays exact past the stack (its fallback); only its speed suffers.
UNBOUNDED_DEPTH = ("recursive_sah",)
#: The builders whose depth bound config.py states (3n + ceil(log2 N) < 64).
PIPELINE_METHODS = ("hlbvh", "lbvh")
_REFERENCE_CACHE: dict = {}


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("family", list(stress_report.SCENE_FAMILIES))
def test_scene_family(device, family, method):
    row = stress_report.run_family(family, method, device, seed=0, reference_cache=_REFERENCE_CACHE)
    print("\n" + stress_report.format_row(row), row["per_rays"])
    assert row["unexplained"] == 0, f"{row['unexplained']} rays disagree with the float64 oracle beyond near-ties"


def _inside_origin(mesh, bvh):
    """A point inside the closed mesh: odd crossing counts along three axes (ray parity)."""
    step = max(1, len(mesh.faces) // 50)
    below_faces = mesh.triangles_center[::step] - 1e-3 * mesh.scale * mesh.face_normals[::step]
    candidates = [mesh.bounds.mean(axis=0), mesh.vertices.mean(axis=0)] + list(below_faces)
    axes = np.array([[1, 0.1, 0.2], [-0.3, 1, 0.1], [0.2, -0.1, -1]], dtype=np.float64)
    for c in candidates:
        o = np.repeat(np.asarray(c, dtype=np.float32)[None], 3, axis=0)
        ray_id, _, _ = query.intersect_all(bvh, o, axes)
        if (np.bincount(ray_id, minlength=3) % 2 == 1).all():
            return np.asarray(c, dtype=np.float64)
    pytest.skip("no interior point found")


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("mesh_name", ["icosphere", "armadillo"])
def test_closed_mesh_from_inside_never_escapes(device, method, mesh_name):
    """Watertightness (Woop et al. 2013): rays from inside exactly at vertices and edge midpoints all hit."""
    if mesh_name == "icosphere":
        mesh = trimesh.creation.icosphere(subdivisions=4)
    else:
        if method in SLOW_METHODS:
            pytest.skip(f"{method} takes minutes at 100k triangles")
        mesh = shared_mesh("armadillo")
        assert mesh.is_watertight
    bvh = api.build(mesh, method=method, device=device)
    origin = _inside_origin(mesh, bvh)
    v = np.asarray(mesh.vertices, dtype=np.float32).astype(np.float64)
    edges = mesh.edges_unique
    targets = np.concatenate([v, 0.5 * (v[edges[:, 0]] + v[edges[:, 1]])])
    d = targets - origin
    t, prim = query.intersect(bvh, np.repeat(origin[None], len(d), axis=0), d)
    escaped = int((prim < 0).sum())
    print(f"\n{mesh_name:10s} {method:10s} rays {len(d):7d} escaped {escaped}")
    assert escaped == 0, f"{escaped} of {len(d)} rays through vertices/edges escaped the closed mesh"
    assert np.isfinite(t).all()
    # The shadow-ray query agrees.
    assert query.occluded(bvh, np.repeat(origin[None], len(d), axis=0), d).all()


def _depth_scenes(num_prims):
    dup_lo = np.zeros((num_prims, 3), np.float32)
    dup_hi = np.ones((num_prims, 3), np.float32)
    # Centroids 2^-k: Morton codes collapse at the origin while the extent spans 2^120.
    k = np.arange(num_prims) % 120
    exp_pts = np.exp2(-k).astype(np.float32)[:, None] * np.array([[1.0, 0.5, 0.25]], np.float32)
    return {"duplicates": (dup_lo, dup_hi), "exponential": (exp_pts, exp_pts * 1.0001)}


@pytest.mark.parametrize("method", METHODS)
def test_deepest_trees_stay_within_the_stack(device, method):
    """The deepest trees a builder makes: all-duplicate boxes and an exponential distribution, leaf 1."""
    # Reference builders are host-side and may be quadratic on duplicates: a smaller N for them.
    if api.needs_mesh(method):
        pytest.skip(f"{method} builds over triangles only (tested with meshes in test_spatial_split.py)")
    num_prims = 100_000 if method in PIPELINE_METHODS else 2_000
    config = BuildConfig(max_leaf_size=1)
    too_deep = []
    for name, (lo, hi) in _depth_scenes(num_prims).items():
        bvh = api.build_from_bounds(lo, hi, method=method, device=device, config=config)
        depth = bvh.depth
        print(f"\n{name:12s} {method:10s} N {num_prims:7d} depth {depth}")
        # Box queries stay exact whatever the depth (the stack never overflows).
        q_lo, q_hi = lo[:50] - 1e-3, hi[:50] + 1e-3
        counts = query.query_aabb(bvh, q_lo, q_hi)
        ref = ((lo[None] <= q_hi[:, None]) & (hi[None] >= q_lo[:, None])).all(-1).sum(1)
        assert np.array_equal(counts, ref)
        if depth >= TRAVERSAL_STACK_SIZE and method not in UNBOUNDED_DEPTH:
            too_deep.append(f"{name}: depth {depth}")
    assert not too_deep, f"{method} exceeds the traversal stack depth {TRAVERSAL_STACK_SIZE}: {too_deep}"


def test_traversal_exact_on_a_chain_deeper_than_the_stack(device, rng):
    """A caterpillar tree of depth 299: the full-stack fallback keeps every query exact."""
    n = 300
    verts, faces = stress_report.scene_soup(rng)[0][: 3 * n], np.arange(3 * n, dtype=np.int32).reshape(-1, 3)
    # Node 2k is interior (k < n - 1) with a leaf left child 2k + 1 and the rest of the chain right.
    bvh = caterpillar(verts, faces, device, deep="right")
    tri = verts.reshape(-1, 3, 3)
    assert bvh.depth == n - 1 > TRAVERSAL_STACK_SIZE
    rays = stress_report.ray_families(rng, verts, faces, num_rays=200)
    o, d = rays["random"]
    t, prim = query.intersect(bvh, o, d)
    t_ref, prim_ref = brute_force_closest_hit(verts, faces, o, d)
    assert stress_report.classify(verts, faces, o, d, t, prim, t_ref, prim_ref)[1] == 0
    assert np.array_equal(query.occluded(bvh, o, d), prim_ref >= 0)
    counts = query.query_aabb(bvh, tri.min(1), tri.max(1))
    assert (counts >= 1).all()


DEEP_CHAIN_DEBUG_SCRIPT = r"""
import sys
import numpy as np
import warp as wp

wp.config.mode = "debug"  # bounds-checked vector indexing: a write past a local stack aborts
wp.config.log_level = wp.LOG_WARNING
sys.path.insert(0, sys.argv[2])
from handmade_trees import caterpillar
from oracles import brute_force_closest_hit, brute_overlaps
import hlbvh_warp as hw
from hlbvh_warp import query

device, n = sys.argv[1], 150
base = np.array([[-1, -1, 0], [2, -1, 0], [-1, 2, 0]], np.float32)
verts = np.concatenate([base + np.float32([0, 0, z]) for z in range(n)])
faces = np.arange(3 * n, dtype=np.int32).reshape(-1, 3)
tri = verts[faces]
lo, hi = tri.min(1), tri.max(1)


@wp.kernel
def user_boxes(bvh: query.BvhView, lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3),
               counts: wp.array(dtype=int), pairs: wp.array(dtype=wp.vec2i), pair_count: wp.array(dtype=wp.int32)):
    i = wp.tid()
    counts[i] = query.bvh_aabb_count(bvh, lowers[i], uppers[i])
    query.bvh_aabb_pairs(bvh, lowers[i], uppers[i], i, pairs, pair_count)


for deep in ("left", "right"):
    bvh = caterpillar(verts, faces, device, deep=deep)
    assert bvh.depth == n - 1
    # One ray through every triangle, and random ones.
    o = np.float32([[0.1, 0.1, -1], [0.1, 0.1, n + 1]])
    d = np.float32([[0, 0, 1], [0, 0, -1]])
    rid, prim, t = query.intersect_all(bvh, o, d)
    for r in range(2):
        assert sorted(prim[rid == r].tolist()) == list(range(n)), (deep, r)
    t, prim = query.intersect(bvh, o, d)
    assert prim.tolist() == [0, n - 1], prim
    # Boxes that each meet every triangle, and each triangle's own box.
    q_lo = np.concatenate([np.float32([[0, 0, -1]]), lo])
    q_hi = np.concatenate([np.float32([[0.5, 0.5, n]]), hi])
    ref = brute_overlaps(lo, hi, q_lo, q_hi)
    counts, pairs = query.query_aabb(bvh, q_lo, q_hi, return_pairs=True)
    assert np.array_equal(counts, ref.sum(1)) and np.array_equal(pairs, np.argwhere(ref))
    out = wp.zeros(len(q_lo), dtype=int, device=device)
    found = wp.zeros(int(ref.sum()), dtype=wp.vec2i, device=device)
    found_count = wp.zeros(1, dtype=wp.int32, device=device)
    wp.launch(user_boxes, dim=len(q_lo), device=device,
              inputs=[query.view(bvh), wp.array(q_lo, dtype=wp.vec3, device=device),
                      wp.array(q_hi, dtype=wp.vec3, device=device), out, found, found_count])
    assert np.array_equal(out.numpy(), ref.sum(1))
    got = found.numpy()
    assert found_count.numpy()[0] == len(got)
    assert np.array_equal(got[np.lexsort((got[:, 1], got[:, 0]))], np.argwhere(ref))
    self_pairs = hw.overlapping_pairs(bvh)
    assert np.array_equal(self_pairs, np.argwhere(np.triu(brute_overlaps(lo, hi, lo, hi), 1)))
    points = np.float32([[0.2, 0.2, 0.4], [0.2, 0.2, n + 3]])
    _, dist, prim = hw.closest_point(bvh, points)
    assert prim.tolist() == [0, n - 1] and np.allclose(dist, [0.4, 4.0]), (prim, dist)
    # The same chain over bare boxes: the canonical walks.
    boxes = caterpillar(verts, faces, device, deep=deep, boxes_only=True)
    counts, pairs = query.query_aabb(boxes, q_lo, q_hi, return_pairs=True)
    assert np.array_equal(counts, ref.sum(1)) and np.array_equal(pairs, np.argwhere(ref))
    assert np.array_equal(hw.overlapping_pairs(boxes), np.argwhere(np.triu(brute_overlaps(lo, hi, lo, hi), 1)))
print("ok")
"""


def test_walks_past_the_stack_write_in_bounds(device, tmp_path):
    """Every walk on a chain deeper than its fixed stack, compiled in Warp's debug mode, where
    indexing a local stack out of range aborts the process: the answers must be right and no
    push may go past the last slot. (A mutation audit moved the all-hits guard one slot: the
    answers stayed right in release builds, silently writing past the stack.) In a child
    process, since debug mode is a global setting and an abort would end the test run."""
    import subprocess
    import sys
    from pathlib import Path

    script = tmp_path / "deep_chain_debug.py"
    script.write_text(DEEP_CHAIN_DEBUG_SCRIPT)
    tests_dir = str(Path(__file__).resolve().parent)
    result = subprocess.run([sys.executable, str(script), device, tests_dir], capture_output=True, text=True,
                            timeout=600)
    output = result.stdout[-2000:] + result.stderr[-4000:]
    assert result.returncode == 0 and result.stdout.strip().endswith("ok"), output


def test_tiny_triangles_at_every_scale(device, rng):
    # Between about 1e-19 and 1e-22 the float32 edge functions and their sum fall among the
    # subnormals: 1 / det overflowed and every ray missed, while 1e-18 (the tiny scene family)
    # and 1e-25 (products of exactly zero, decided in float64) were hit.
    for exponent in range(-26, -14):
        scale = 10.0**exponent
        verts, faces = stress_report._soup(rng, 40, scale=scale, offset=rng.normal() * scale)
        bvh = api.build(verts, faces, method="hlbvh", device=device)
        for kind, (o, d) in stress_report.ray_families(rng, verts, faces, num_rays=60).items():
            t, prim = query.intersect(bvh, o, d)
            t_ref, prim_ref = brute_force_closest_hit(verts, faces, o, d)
            assert (prim_ref >= 0).any() or kind != "random"
            _, unexplained = stress_report.classify(verts, faces, o, d, t, prim, t_ref, prim_ref)
            assert unexplained == 0, (scale, kind)
            assert np.array_equal(query.occluded(bvh, o, d), prim >= 0), (scale, kind)


def test_huge_triangles_up_to_the_float32_limit(device, rng):
    # Above about 2.7e38 the watertight test's shear overflowed float32 (a sheared coordinate is
    # a difference of two such values): rays from the centre of a sphere that large missed it,
    # 46 of 256 at 3e38. Hits are found as long as their distance is a float32.
    mesh = trimesh.creation.icosphere(subdivisions=2)
    d = rng.normal(size=(256, 3))
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    o = np.zeros_like(d)
    for scale in (1e30, 2.6e38, 3e38, 3.3e38):
        verts = (mesh.vertices * scale).astype(np.float32)
        faces = np.asarray(mesh.faces, np.int32)
        bvh = api.build(verts, faces, device=device)
        t, prim = query.intersect(bvh, o, d)
        t_ref, prim_ref = brute_force_closest_hit(verts, faces, o, d)
        assert (prim_ref >= 0).all()
        _, unexplained = stress_report.classify(verts, faces, o, d, t, prim, t_ref, prim_ref)
        assert unexplained == 0, scale
        assert query.occluded(bvh, o, d).all(), scale


@pytest.mark.parametrize("method", ["hlbvh", "sbvh"])
def test_tiny_directions_find_what_the_same_ray_scaled_up_finds(device, rng, method):
    # Below about 3e-39 in every component, 1 / d overflowed and every box test missed: rays
    # into a 1e-30 scene whose hits lie at t = 1e12 found nothing. The query now scales such a
    # direction by a power of two, exactly, so a ray must give the same triangle as the ray
    # with 2^100 times its direction, at exactly 2^100 times the distance.
    mesh = trimesh.creation.icosphere(subdivisions=3)
    scale = 1e-30
    verts = (mesh.vertices * scale).astype(np.float32)
    faces = np.asarray(mesh.faces, np.int32)
    o = (rng.normal(size=(256, 3)) * 3 * scale).astype(np.float32)
    aim = verts[rng.integers(0, len(verts), 256)].astype(np.float64) * 0.5
    bvh = api.build(verts, faces, method=method, device=device)
    w = wide.collapse(bvh, 8)
    for shrink in (1e-9, 1e-12, 1e-15):
        d = ((aim - o) * shrink).astype(np.float32)
        assert (np.abs(d).max(axis=1) < 1.17e-38).all()  # float32 subnormals only
        d_up = (d.astype(np.float64) * 2.0**100).astype(np.float32)
        assert (d_up.astype(np.float64) == d.astype(np.float64) * 2.0**100).all()
        t_up, prim_up = query.intersect(bvh, o, d_up)
        assert (prim_up >= 0).mean() > 0.5, shrink  # subnormal directions keep few bits: some turn aside
        t, prim = query.intersect(bvh, o, d)
        np.testing.assert_array_equal(prim, prim_up)
        hit = prim >= 0
        np.testing.assert_array_equal(t[hit].astype(np.float64), t_up[hit].astype(np.float64) * 2.0**100)
        np.testing.assert_array_equal(query.occluded(bvh, o, d), hit)
        wide_t, wide_prim = wide.intersect(w, o, d)
        np.testing.assert_array_equal(wide_t, t)
        ray, all_prim, all_t = query.intersect_all(bvh, o, d)
        ray_up, all_prim_up, all_t_up = query.intersect_all(bvh, o, d_up)
        np.testing.assert_array_equal(ray, ray_up)
        np.testing.assert_array_equal(all_prim, all_prim_up)
        np.testing.assert_array_equal(all_t.astype(np.float64), all_t_up.astype(np.float64) * 2.0**100)
    # A NaN or non-positive t_max is still no range at all for a scaled ray.
    d = ((aim - o) * 1e-12).astype(np.float32)
    for bad in (float("nan"), 0.0, -1.0):
        assert (query.intersect(bvh, o, d, t_max=bad)[1] == -1).all(), bad
    # A hit whose distance is past float32's range is still a miss, scaled or not.
    d = ((aim - o) * 1e-12).astype(np.float32)
    t, prim = query.intersect(bvh, o * np.float32(1e30), d)
    assert (prim == -1).all() and np.isinf(t).all()


def test_nan_inf_rays_miss_and_bad_shapes_raise(device, rng):
    verts, faces = stress_report.scene_soup(rng)
    bvh = api.build(verts, faces, device=device)
    o = np.array([[np.nan, 0, 0], [0, np.inf, 0], [0.5, 0.5, -1], [0.5, 0.5, -1], [0.5, 0.5, -1], [0, 0, -np.inf]],
                 np.float32)
    d = np.array([[0, 0, 1], [0, 0, 1], [np.nan, 0, 1], [0, -np.inf, 1], [0, 0, 0], [0, 0, 1]], np.float32)
    t, prim = query.intersect(bvh, o, d)
    assert (prim == -1).all() and np.isinf(t).all()
    assert not query.occluded(bvh, o, d).any()
    t, prim = query.intersect(bvh, o[2:3], np.array([[0, 0, 1]]), t_max=float("nan"))
    assert prim[0] == -1
    with pytest.raises(ValueError):
        query.intersect(bvh, np.zeros((4, 2)), np.zeros((4, 2)))
    with pytest.raises(ValueError):
        query.intersect(bvh, np.zeros((4, 3)), np.zeros((5, 3)))
    with pytest.raises(ValueError):
        query.occluded(bvh, np.zeros((4, 3)), np.ones((4, 3)), t_max=np.ones(3))
    with pytest.raises(ValueError):
        query.query_aabb(bvh, np.zeros((4, 3)), np.zeros((4, 4)))


def test_edge_line_graze_on_small_soup_is_a_near_tie(device):
    """Found by the fuzzed family: ray 4 of the edge family grazes triangle 1, whose plane it meets
    2e-7 inside an edge, but passes 9e-12 (3e-9 relative) from that edge's line. The watertight
    test's float32 edge function cannot tell the side at that distance: a near-tie, not a miss."""
    rng = np.random.default_rng(1659468)
    verts, faces = stress_report._soup(rng, 7, scale=1e-3, offset=rng.normal() * 1e-3)
    bvh = api.build(verts, faces, method="binned_sah", device=device)
    o, d = stress_report.ray_families(rng, verts, faces, num_rays=40)["edge"]
    t, prim = query.intersect(bvh, o, d)
    t_ref, prim_ref = brute_force_closest_hit(verts, faces, o, d)
    assert stress_report.classify(verts, faces, o, d, t, prim, t_ref, prim_ref)[1] == 0
    # The graze is explained by the edge-line distance alone: the in-plane distance of the hit
    # point from the edge (2e-7) is 8x the tolerance.
    assert stress_report.is_marginal(verts, faces, 1, o[4], d[4])
    assert not stress_report.is_marginal(verts, faces, 1, o[4], d[4], tol=1e-11)


def test_near_tie_rule_rejects_clear_hits_and_misses():
    """The classifier may only excuse rays decided within rounding; it must flag the rest."""
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    faces = np.array([[0, 1, 2]])
    # Straight down through the middle, and clearly beside the triangle: both decided.
    assert not stress_report.is_marginal(tri, faces, 0, np.array([0.25, 0.25, 1.0]), np.array([0.0, 0.0, -1.0]))
    assert not stress_report.is_marginal(tri, faces, 0, np.array([0.6, 0.6, 1.0]), np.array([0.0, 0.0, -1.0]))
    # Grazing at 1e-3 rad, hit point well inside, every edge line >= 2e-4 from the ray: decided.
    d = np.array([0.0, 1.0, -1e-3])
    assert not stress_report.is_marginal(tri, faces, 0, np.array([0.3, 0.2, 0.0]) - d, d)
    # Crossing an edge's line far outside the triangle: the other edges decide a miss.
    assert not stress_report.is_marginal(tri, faces, 0, np.array([5.0, 0.0, 1.0]), np.array([0.1, 0.2, -1.0]))
    # Crossing an edge's line beside the triangle, 1e-12 from the edge itself: a tie.
    assert stress_report.is_marginal(tri, faces, 0, np.array([0.5, -1e-12, 1.0]), np.array([0.0, 0.0, -1.0]))


# Derandomized: CI runs the same examples every time; the case above is the one they once found.
@settings(max_examples=25, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    seed=st.integers(0, 2**32 - 1),
    num_tris=st.integers(1, 60),
    exponent=st.integers(-15, 15),
    duplicate=st.booleans(),
    flat_axis=st.sampled_from([None, 0, 1, 2]),
    method=st.sampled_from(METHODS),
)
def test_fuzzed_soups(device, seed, num_tris, exponent, duplicate, flat_axis, method):
    rng = np.random.default_rng(seed)
    verts, faces = stress_report._soup(rng, num_tris, scale=10.0**exponent, offset=rng.normal() * 10.0**exponent)
    if duplicate:
        faces = np.concatenate([faces, faces[: max(1, num_tris // 2)]])
    if flat_axis is not None:
        verts[:, flat_axis] = verts[0, flat_axis]
    bvh = api.build(verts, faces, method=method, device=device)
    for o, d in stress_report.ray_families(rng, verts, faces, num_rays=40).values():
        t, prim = query.intersect(bvh, o, d)
        t_ref, prim_ref = brute_force_closest_hit(verts, faces, o, d)
        _, unexplained = stress_report.classify(verts, faces, o, d, t, prim, t_ref, prim_ref)
        assert unexplained == 0


def test_classifier_flags_the_right_triangle_at_a_wrong_distance():
    """A hit on the reference's triangle is only the same answer at the same distance: a traversal
    that reported the right triangle with another triangle's (or a stale) t must be flagged."""
    rng = np.random.default_rng(0)
    verts, faces = stress_report.scene_closed(rng)
    o, d = stress_report.ray_families(rng, verts, faces)["random"]
    t_ref, prim_ref = brute_force_closest_hit(verts, faces, o, d)
    hit = prim_ref >= 0
    assert hit.sum() > 20
    # The right answers pass; float32 rounding of them passes.
    assert stress_report.classify(verts, faces, o, d, t_ref.astype(np.float32), prim_ref, t_ref, prim_ref) == (0, 0)
    # The right triangles at 1.5x their distance: every hit ray is wrong, and only a ray that grazes
    # its triangle (decided within rounding either way) may pass for a near-tie.
    wrong = np.where(hit, 1.5 * t_ref, t_ref)
    disagree, unexplained = stress_report.classify(verts, faces, o, d, wrong, prim_ref, t_ref, prim_ref)
    assert disagree == int(hit.sum())
    assert unexplained >= 0.9 * disagree


def test_classifier_flags_a_hit_beyond_a_near_tie_that_the_ray_does_not_meet():
    """A reference hit that is a near-tie (a ray grazing an edge) excuses missing that triangle,
    not whatever the traversal reported behind it: a hit on a triangle the ray never meets, or one
    past another triangle the ray plainly crosses, must be flagged."""
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [10, 0, 0], [11, 0, 0], [10, 1, 0],
                      [0, -1, -1], [1, -1, -1], [0.5, 1, -1]], np.float32)
    faces = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]], np.int32)
    # Down onto the edge y = 0 of triangle 0 (within rounding of it), then through triangle 2 at t = 2.
    o, d = np.array([[0.5, 1e-9, 1.0]], np.float32), np.array([[0.0, 0.0, -1.0]], np.float32)
    t_ref, prim_ref = brute_force_closest_hit(verts, faces, o, d)
    assert prim_ref[0] == 0 and stress_report.is_marginal(verts, faces, 0, o[0], d[0])
    # Missing the grazed triangle and reporting the next one is a near-tie.
    assert stress_report.classify(verts, faces, o, d, np.array([2.0]), np.array([2]), t_ref, prim_ref) == (1, 0)
    # Triangle 1 lies nowhere on the ray, and the ray meets triangle 2 at t = 2, not 3: wrong
    # answers, not ties.
    assert stress_report.classify(verts, faces, o, d, np.array([3.0]), np.array([1]), t_ref, prim_ref) == (1, 1)
    assert stress_report.classify(verts, faces, o, d, np.array([3.0]), np.array([2]), t_ref, prim_ref) == (1, 1)
    # Triangle 2 crossed at t = 2 and skipped for a hit behind it (triangle 3, at t = 4).
    verts4 = np.concatenate([verts, verts[6:9] - [0, 0, 2]]).astype(np.float32)
    faces4 = np.concatenate([faces, [[9, 10, 11]]]).astype(np.int32)
    assert stress_report.classify(verts4, faces4, o, d, np.array([4.0]), np.array([3]), t_ref, prim_ref) == (1, 1)
