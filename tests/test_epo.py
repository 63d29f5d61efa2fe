"""End-point overlap (Aila, Karras & Laine 2013) against a float64 brute force over every
(node, triangle) pair whose areas come from convex hulls, not from a polygon clipper."""

from __future__ import annotations

import numpy as np
import pytest

import hlbvh_warp as hw
from hlbvh_warp.metrics import end_point_overlap, sah_cost
from handmade_trees import caterpillar
from oracles import numpy_end_point_overlap, random_soup, triangle_box_area

BUILDERS = ["hlbvh", "lbvh", "hlbvh_sah", "sweep_sah", "binned_sah", "median"]


@pytest.mark.parametrize("method", BUILDERS)
def test_epo_matches_the_brute_force(device, rng, method):
    v, f = random_soup(rng, 36, scale=0.3)
    bvh = hw.build(v, f, method=method, device=device)
    epo, per_node = end_point_overlap(bvh, per_node=True)
    expected, expected_nodes = numpy_end_point_overlap(bvh.to_numpy(), v, f)
    assert expected > 0.0  # the soup's triangles overlap: the test can see a wrong sum
    assert epo == pytest.approx(expected, rel=1e-9)
    np.testing.assert_allclose(per_node, expected_nodes, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("t1, t2", [(1.2, 1.0), (0.0, 2.5)])
def test_epo_weights_and_leaf_sizes(device, rng, t1, t2):
    v, f = random_soup(rng, 40, scale=0.4)
    bvh = hw.build(v, f, method="sweep_sah", device=device, config=hw.BuildConfig(max_leaf_size=4))
    tree = bvh.to_numpy()
    leaves = tree["node_left"][: bvh.num_nodes] < 0
    assert (tree["node_end"] - tree["node_begin"])[: bvh.num_nodes][leaves].max() > 1
    epo = end_point_overlap(bvh, t1, t2)
    assert epo == pytest.approx(numpy_end_point_overlap(bvh.to_numpy(), v, f, t1, t2)[0], rel=1e-9)


def test_hand_computed_epo(device):
    # A: the slanted triangle (0,0,0), (2,0,0), (0,2,2), in the plane z = y, box [0,2]^3, area 2 sqrt 2.
    # B: a triangle of area 0.5 in the plane z = 1, wholly inside A's box. A meets B's flat box
    # [0.5,1.5]^2 x [1,1] in a segment only. So only leaf A pays: EPO = 1 * 0.5 / (2 sqrt 2 + 0.5).
    v = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 2], [0.5, 0.5, 1], [1.5, 0.5, 1], [0.5, 1.5, 1]], dtype=np.float32)
    f = np.array([[0, 1, 2], [3, 4, 5]], dtype=np.int32)
    bvh = hw.build(v, f, method="median", device=device)
    epo, per_node = end_point_overlap(bvh, per_node=True)
    assert epo == pytest.approx(0.5 / (2 * np.sqrt(2) + 0.5), rel=1e-12)
    tree = bvh.to_numpy()
    leaf_a = [n for n in range(3) if tree["node_left"][n] < 0 and tree["prim_order"][tree["node_begin"][n]] == 0]
    assert per_node[leaf_a[0]] == pytest.approx(0.5, rel=1e-12)


def test_duplicated_faces_overlap_wholly(device):
    # Each copy of an axis-aligned (flat-boxed) triangle lies in the other's leaf box: every
    # leaf pays the full area of its twin, the root nothing. EPO = 2a / 2a = 1.
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float32)
    f = np.array([[0, 1, 2], [0, 2, 1]], dtype=np.int32)
    for method in ("median", "hlbvh"):
        assert end_point_overlap(hw.build(v, f, method=method, device=device)) == pytest.approx(1.0, rel=1e-12)


def test_separated_triangles_have_no_overlap(device):
    grid = np.stack(np.meshgrid(np.arange(6), np.arange(6), np.arange(2), indexing="ij"), -1).reshape(-1, 3)
    corners = np.array([[0, 0, 0], [0.5, 0, 0], [0, 0.5, 0.5]])
    v = (grid[:, None, :] * 2.0 + corners[None]).reshape(-1, 3).astype(np.float32)
    f = np.arange(len(v), dtype=np.int32).reshape(-1, 3)
    bvh = hw.build(v, f, method="sweep_sah", device=device)
    # Disjoint boxes, but interior nodes' boxes hold other triangles only where the sweep left gaps.
    epo, per_node = end_point_overlap(bvh, per_node=True)
    assert epo == pytest.approx(numpy_end_point_overlap(bvh.to_numpy(), v, f)[0], rel=1e-9, abs=1e-12)
    tree = bvh.to_numpy()
    leaves = tree["node_left"][: bvh.num_nodes] < 0
    assert np.all(per_node[leaves] == 0.0)


def test_degenerate_triangles_add_nothing(device, rng):
    v, f = random_soup(rng, 30, scale=0.4)
    # Points and segments among the triangles: zero area, inside many boxes.
    extra_v = np.array([[0.5, 0.5, 0.5], [0.2, 0.2, 0.2], [0.8, 0.8, 0.8]], dtype=np.float32)
    v2 = np.concatenate([v, extra_v])
    n = len(v)
    f2 = np.concatenate([f, np.array([[n, n, n], [n + 1, n + 2, n + 1], [n + 1, n, n + 2]], dtype=np.int32)])
    bvh = hw.build(v2, f2, method="hlbvh", device=device)
    epo = end_point_overlap(bvh)
    assert np.isfinite(epo)
    assert epo == pytest.approx(numpy_end_point_overlap(bvh.to_numpy(), v2, f2)[0], rel=1e-9)


def test_a_tree_deeper_than_the_stack(device, rng):
    # 70 levels: past the walk's 64-entry stack, where it tests a node's whole range instead.
    v, f = random_soup(rng, 70, scale=0.25)
    bvh = caterpillar(v, f, device)
    assert hw.metrics.tree_stats(bvh)["depth"] == 69
    epo, per_node = end_point_overlap(bvh, per_node=True)
    expected, expected_nodes = numpy_end_point_overlap(bvh.to_numpy(), v, f)
    assert epo == pytest.approx(expected, rel=1e-9)
    np.testing.assert_allclose(per_node, expected_nodes, rtol=1e-9, atol=1e-12)


def test_full_sweep_has_less_overlap_than_morton_builders(device, rng):
    """Aila et al.'s observation on a real-ish surface: the greedy top-down SAH sweep keeps EPO
    lower than a Morton-order build of the same triangles."""
    u, w = np.meshgrid(np.linspace(0, 2 * np.pi, 40), np.linspace(0.2, np.pi - 0.2, 20), indexing="ij")
    pts = np.stack([np.cos(u) * np.sin(w), np.sin(u) * np.sin(w), np.cos(w)], -1).reshape(-1, 3)
    idx = np.arange(40 * 20).reshape(40, 20)
    quads = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
    f = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]]).astype(np.int32)
    v = pts.astype(np.float32)
    sweep = end_point_overlap(hw.build(v, f, method="sweep_sah", device=device))
    lbvh = end_point_overlap(hw.build(v, f, method="lbvh", device=device))
    assert 0.0 < sweep < lbvh


def test_triangle_box_oracle_on_known_shapes():
    # The oracle itself: a half-cut right triangle, a regular hexagon across a cube, a miss.
    tri = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    assert triangle_box_area(tri, [-1, -1, -1], [0.5, 2, 2]) == pytest.approx(0.375)
    big = [[4.5, -1.5, -1.5], [-1.5, 4.5, -1.5], [-1.5, -1.5, 4.5]]
    assert triangle_box_area(big, [0, 0, 0], [1, 1, 1]) == pytest.approx(3 * np.sqrt(3) / 4)
    assert triangle_box_area(tri, [2, 2, 2], [3, 3, 3]) == 0.0
    # At any scale (powers of two: the scaled shapes are exact): the area scales with its square.
    for k in (-100, -40, -17, 17, 60):
        s = 2.0**k
        assert triangle_box_area(np.multiply(tri, s), np.multiply([-1, -1, -1], s),
                                 np.multiply([0.5, 2, 2], s)) == pytest.approx(0.375 * s * s, rel=1e-12, abs=0.0)
        assert triangle_box_area(np.multiply(big, s), [0, 0, 0], [s, s, s]) == pytest.approx(
            3 * np.sqrt(3) / 4 * s * s, rel=1e-12, abs=0.0)


def test_epo_rejects_box_trees_and_bad_costs(device):
    lo = np.zeros((4, 3), dtype=np.float32) + np.arange(4, dtype=np.float32)[:, None]
    box_bvh = hw.build_from_bounds(lo, lo + 0.5, device=device)
    with pytest.raises(ValueError, match="mesh"):
        end_point_overlap(box_bvh)
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float32)
    bvh = hw.build(v, np.array([[0, 1, 2]], dtype=np.int32), device=device)
    with pytest.raises(ValueError, match="t_intersect"):
        end_point_overlap(bvh, 1.0, 0.0)
    with pytest.raises(ValueError, match="takes a Bvh"):
        end_point_overlap("not a tree")
    # A single triangle overlaps nothing; its SAH cost is still defined.
    assert end_point_overlap(bvh) == 0.0
    assert sah_cost(bvh) == pytest.approx(1.0)


def test_the_oracles_triangle_area_in_a_box_far_from_the_origin():
    """The oracle's on-triangle test had a slack growing with the coordinates squared: in a box
    of side 2^-10 at 1e4 a box corner off the triangle counted as on it, and the area came out
    twice the triangle's. The triangle fills exactly half the box's face: its whole area, at
    the origin and at 1e4 alike."""
    from oracles import triangle_box_area

    d = 2.0**-10
    for offset in (0.0, 1e4):
        tri = np.array([[0.0, d, 0.0], [0.0, 0.0, 0.0], [d, 0.0, 0.0]]) + offset
        area = triangle_box_area(tri, np.full(3, offset), np.full(3, offset + d))
        assert area == pytest.approx(0.5 * d * d, rel=1e-9), offset
