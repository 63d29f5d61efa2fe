"""Builders at the edges of their inputs (SAH constants the config must refuse, scenes near
float32's range), each against an oracle written here in float64 NumPy.

The SAH is eq. (1) of Pantaleoni & Luebke 2010 with the configured T1 and T2; the reference
topology of ``hlbvh``/``lbvh`` is the LBVH radix tree (Lauterbach et al. 2009) over the Morton
codes of the centroids, split at the highest differing bit, equal codes at the index median.
"""

from __future__ import annotations

import numpy as np
import pytest

import hlbvh_warp as hw


def _area(lo, hi):
    d = np.maximum(np.asarray(hi, np.float64) - np.asarray(lo, np.float64), 0.0)
    return 2.0 * (d[..., 0] * d[..., 1] + d[..., 1] * d[..., 2] + d[..., 2] * d[..., 0])


def _sah(tree, t1, t2):
    """C(root) of eq. (1), bottom-up over the returned tree (children follow their parent)."""
    left, right = tree["node_left"], tree["node_right"]
    size = tree["node_end"] - tree["node_begin"]
    area = _area(tree["node_lowers"], tree["node_uppers"])
    cost = np.zeros(len(left))
    for i in range(len(left) - 1, -1, -1):
        if left[i] < 0:
            cost[i] = t2 * size[i]
        elif area[i] > 0:
            cost[i] = 2 * t1 + (cost[left[i]] * area[left[i]] + cost[right[i]] * area[right[i]]) / area[i]
        else:
            cost[i] = 2 * t1 + cost[left[i]] + cost[right[i]]
    return cost[0]


@pytest.mark.parametrize("field", ["sah_traversal_cost", "sah_intersection_cost"])
def test_infinite_sah_cost_is_refused_by_the_config(field):
    # metrics.check_costs refuses infinite SAH constants, so a config holding one built (with
    # every cluster weight and split cost infinite: a recursive_sah tree 5x the SAH of the default)
    # and then broke Builder(policy="auto") at its first update, when it priced the tree.
    with pytest.raises(ValueError, match=field):
        hw.BuildConfig(**{field: float("inf")})


def test_finite_sah_costs_still_price_the_builders_trees(device):
    # The other side of the check above: finite non-default constants stay accepted, and the cost
    # metrics.sah_cost reports for each builder's tree is eq. (1) with those constants.
    from hlbvh_warp import metrics

    rng = np.random.default_rng(3)
    centres = rng.random((40, 3))
    lowers, uppers = centres - 0.05, centres + 0.05
    config = hw.BuildConfig(sah_traversal_cost=1.2, sah_intersection_cost=0.7)
    for method in ("sweep_sah", "recursive_sah", "hlbvh_sah"):
        bvh = hw.build_from_bounds(lowers, uppers, method=method, device=device, config=config)
        expected = _sah(bvh.to_numpy(), 1.2, 0.7)
        assert metrics.sah_cost(bvh, 1.2, 0.7) == pytest.approx(expected, rel=1e-9)


@pytest.mark.parametrize("method", ["recursive_sah", "sbvh", "sweep_sah", "binned_sah", "hlbvh"])
def test_a_huge_scene_gets_the_tree_of_the_same_scene_at_unit_scale(device, method):
    # Scaling by a power of two is exact in float32 and leaves every split rule unchanged, so the
    # SAH of eq. (1) (scale-free) must come out the same. recursive_sah (Wodniok & Goesele 2016)
    # binned its centroids as num_bins * (c - lower) / extent in float32: at 2^123 (about 1e37,
    # well inside float32) the product overflowed to inf, every centroid fell into bin 0 and the
    # tree's SAH was 2.9x that of the unit-scale build; sbvh (Stich et al. 2009) shares that
    # binning for its temporary builds and changed too.
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=3)
    vertices = np.asarray(sphere.vertices, np.float32)
    faces = np.asarray(sphere.faces)
    costs = []
    for scale in (1.0, 2.0 ** 123):
        bvh = hw.build(vertices * np.float32(scale), faces, method=method, device=device)
        costs.append(_sah(bvh.to_numpy(), 1.0, 1.0))
    assert costs[1] == pytest.approx(costs[0], rel=1e-9)


INTERRUPTED_SETUP_SCRIPT = r"""
import sys

import numpy as np
import warp as wp

wp.config.quiet = True
sys.path.insert(0, sys.argv[2])
import hlbvh_warp as hw
from oracles import assert_hits_match, brute_force_closest_hit, random_rays, random_soup

device, n = sys.argv[1], 2000
rng = np.random.default_rng(0)
old_v, old_f = random_soup(rng, n)  # 3n vertices
# The mesh the interrupted set-up was given: as many faces, fewer vertices (a strip).
new_v = rng.uniform(-1, 1, (n + 2, 3)).astype(np.float32)
new_f = np.stack([np.arange(n), np.arange(n) + 1, np.arange(n) + 2], 1).astype(np.int32)
builder = hw.Builder(n, device=device)
builder.build(old_v, old_f)
copy = wp.array.assign


def interrupted(array, values):
    # Ctrl-C while the set-up copies the new vertices in.
    wp.array.assign = copy
    raise KeyboardInterrupt


wp.array.assign = interrupted
try:
    builder.build(new_v, new_f)
    raise AssertionError("not interrupted")
except KeyboardInterrupt:
    pass
# The builder still has the mesh it was set up with: its next frame is that mesh's tree...
builder.update(old_v)
o, d = random_rays(rng, old_v, 200)
t, prim = hw.intersect(builder.bvh, o, d)
assert_hits_match(t, prim, *brute_force_closest_hit(old_v, old_f, o, d))
# ... and the new mesh's vertices, without the set-up that failed, are refused by their count.
try:
    builder.update(new_v)
    raise AssertionError("a frame of the other vertex count was taken")
except ValueError as error:
    assert "rows" in str(error), error
print("done", flush=True)
"""


def test_a_set_up_interrupted_while_copying_a_mesh_of_another_vertex_count_keeps_the_old_one(device):
    """`Builder.build` with another vertex count replaced the builder's vertex and face buffers
    before copying the new mesh into them. Interrupted in between (Ctrl-C during the vertex
    copy, or an allocation failing), the builder was left with the new vertex count and faces
    never written: the old mesh's frames were refused, and a frame of the new mesh's vertices
    built over uninitialized face indices and crashed the process. The new buffers are now the
    builder's only once the mesh is in them. In a child process, so a crash fails this alone."""
    import pathlib
    import subprocess
    import sys

    tests = str(pathlib.Path(__file__).resolve().parent)
    result = subprocess.run([sys.executable, "-c", INTERRUPTED_SETUP_SCRIPT, device, tests], capture_output=True,
                            text=True, timeout=300)
    assert result.returncode == 0 and "done" in result.stdout, (result.returncode, result.stderr[-2000:])


@pytest.mark.parametrize("before", ["triangles", "boxes"])
def test_frames_after_a_set_up_interrupted_at_its_first_launch_answer_for_the_new_mesh(device, monkeypatch, before):
    """`Builder.build` points its tree at the new vertex and face buffers in its first build,
    after the launch that resets the order. Interrupted at that launch (Ctrl-C), the next frame
    rebuilt the tree over the new mesh while the tree still read the old mesh's triangles (or,
    set up with boxes before, none): rays hit the old mesh (4% of the new mesh's hits right).
    An unfinished frame now points the tree at the buffers the builder is set up with first."""
    import warp as wp

    from hlbvh_warp.kernels import compress
    from oracles import assert_hits_match, brute_force_closest_hit, random_rays, random_soup

    n = 500
    rng = np.random.default_rng(8)
    old_v, old_f = random_soup(rng, n)
    new_v = rng.uniform(-1, 1, (n + 2, 3)).astype(np.float32)
    new_f = np.stack([np.arange(n), np.arange(n) + 1, np.arange(n) + 2], 1).astype(np.int32)
    builder = hw.Builder(n, device=device)
    if before == "triangles":
        builder.build(old_v, old_f)
        hw.intersect(builder.bvh, old_v[:1], old_v[1:2] - old_v[:1])  # the ray layout made
    else:
        tri = old_v[old_f]
        builder.build_from_bounds(tri.min(1), tri.max(1))
    launch = wp.launch

    def interrupted(kernel, *args, **kwargs):
        launch(kernel, *args, **kwargs)
        if kernel is compress.iota_kernel:
            monkeypatch.setattr(wp, "launch", launch)
            raise KeyboardInterrupt

    monkeypatch.setattr(wp, "launch", interrupted)
    with pytest.raises(KeyboardInterrupt):
        builder.build(new_v, new_f)
    builder.update(new_v)
    o, d = random_rays(rng, new_v, 200)
    t, prim = hw.intersect(builder.bvh, o, d)
    assert_hits_match(t, prim, *brute_force_closest_hit(new_v, new_f, o, d))
