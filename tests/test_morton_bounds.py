"""A fixed Morton grid (BuildConfig.morton_bounds): validation, equivalence with the per-frame
grid when the boxes agree, clamping of centroids outside the box, and resorted rebuilds over a
fixed grid against builds from scratch."""

from __future__ import annotations

import numpy as np
import pytest

import hlbvh_warp as hw
from hlbvh_warp.builder import Builder
from hlbvh_warp.dynamic import BendingMesh
from hlbvh_warp.metrics import sah_cost
from hlbvh_warp.scenes import default_scene
from oracles import assert_hits_match, brute_force_closest_hit, check_tree_invariants, random_rays, random_soup


def centroid_box(v, f):
    tri = v[f]
    c = 0.5 * (tri.min(axis=1) + tri.max(axis=1))
    return tuple(map(float, c.min(axis=0))), tuple(map(float, c.max(axis=0)))


@pytest.mark.parametrize("bad, match", [
    (((0, 0), (1, 1)), "morton_bounds must be"),
    ("box", "morton_bounds must be"),
    (((0, 0, np.nan), (1, 1, 1)), "finite"),
    (((0, 2, 0), (1, 1, 1)), "lower corner exceeds"),
    # Finite, but infinite as the kernels' float32: every centroid then fell in cell 0 (an SAH
    # cost 10x the same grid at +-3.4e38 on boxes spread over +-3e38).
    (((-1e39, 0, 0), (1, 1, 1)), "float32"),
    (((0, 0, 0), (1, 1, 3.5e38)), "float32"),
])
def test_bad_bounds_are_rejected(bad, match):
    with pytest.raises(ValueError, match=match):
        hw.BuildConfig(morton_bounds=bad)


@pytest.mark.parametrize("method", ["hlbvh", "lbvh", "hlbvh_sah"])
def test_fixed_grid_on_the_centroid_box_is_the_default_tree(device, rng, method):
    # The per-frame grid is the centroid box: giving that same box must change nothing.
    v, f = random_soup(rng, 2000)
    default = hw.build(v, f, method=method, device=device).to_numpy()
    fixed = hw.build(v, f, method=method, device=device,
                     config=hw.BuildConfig(morton_bounds=centroid_box(v, f))).to_numpy()
    for key in ("prim_order", "node_left", "node_right", "node_begin", "node_end"):
        assert np.array_equal(default[key], fixed[key]), key


def test_centroids_outside_the_box_clamp_to_border_cells(device, rng):
    # A box covering only the middle of the soup: most centroids clamp to the border cells.
    # The tree stays exact (it only loses Morton resolution out there).
    v, f = random_soup(rng, 1500)
    lo, hi = centroid_box(v, f)
    mid = 0.5 * (np.array(lo) + np.array(hi))
    cfg = hw.BuildConfig(morton_bounds=(tuple(mid - 0.05), tuple(mid + 0.05)))
    bvh = hw.build(v, f, method="hlbvh", device=device, config=cfg)
    check_tree_invariants(bvh.to_numpy(), 1500, 1, exact_node_count=2 * 1500 - 1)
    origins, directions = random_rays(rng, v, 128)
    t, prim = hw.intersect(bvh, origins, directions)
    assert_hits_match(t, prim, *brute_force_closest_hit(v, f, origins, directions))


def test_centroids_millions_of_cells_outside_take_the_border_cells(device, rng):
    # Debris flown 1e7 grid widths past a fixed grid: its cell index passed int32 before the
    # clamp, and the conversion (undefined there; INT_MIN on x86) put it in cell 0 of an axis
    # where it lies past the upper border. The codes must be those of the clamped cells.
    from hlbvh_warp.hlbvh import HlbvhPipeline
    import warp as wp

    n, bits = 1000, 10
    lo = rng.random((n, 3)).astype(np.float32)
    lo[: n // 2] *= np.float32(1e7)
    lo[n // 2: n // 2 + 50] -= np.float32(1e7)
    hi = lo + np.float32(0.01)
    cfg = hw.BuildConfig(morton_bounds=((0, 0, 0), (1, 1, 1)), global_sort_runs=1.0)
    pipe = HlbvhPipeline(n, cfg, device, wp.array(lo, dtype=wp.vec3, device=device),
                         wp.array(hi, dtype=wp.vec3, device=device))
    pipe.compute_morton_codes()
    # Reference: float64 cell positions clamped to the grid before they become integers.
    c = (np.float32(0.5) * (lo + hi)).astype(np.float64)
    q = np.clip(np.floor(c * (1 << bits)), 0, (1 << bits) - 1).astype(np.int64)
    code = np.zeros(n, np.int64)
    for bit in range(bits):
        for axis in range(3):
            code |= ((q[:, axis] >> bit) & 1) << (3 * bit + 2 - axis)
    np.testing.assert_array_equal(pipe.morton_codes.numpy(), code)
    tree = hw.build_from_bounds(lo, hi, config=cfg, device=device).to_numpy()
    np.testing.assert_array_equal(tree["prim_order"], np.argsort(code, kind="stable"))


def test_resorted_rebuilds_on_a_fixed_grid_equal_scratch(device):
    # Bending frames over one grid for the whole sequence: every resorted rebuild has the SAH
    # cost of a build from scratch with the same config.
    vertices, faces = default_scene(3000)
    anim = BendingMesh(vertices, faces, device=device)
    frames = [anim.update(k / 4).numpy().copy() for k in range(5)]
    tri = np.stack([fr[faces] for fr in frames])
    c = 0.5 * (tri.min(axis=2) + tri.max(axis=2))
    box = (tuple(c.min(axis=(0, 1))), tuple(c.max(axis=(0, 1))))
    cfg = hw.BuildConfig(morton_bounds=box)
    builder = Builder(len(faces), cfg, device=device, resort=True)
    builder.build(frames[0], faces)
    for frame in frames[1:]:
        bvh = builder.rebuild(frame)
        scratch = hw.build(frame, faces, method="hlbvh", device=device, config=cfg)
        assert sah_cost(bvh) == pytest.approx(sah_cost(scratch), rel=1e-6)
        check_tree_invariants(bvh.to_numpy(), len(faces), 1, exact_node_count=2 * len(faces) - 1)
