"""The CPU device's Morton and triangle-bounds kernels (a spread-bit table, chunks per thread,
comparisons without NaN tests) against float64 NumPy oracles and, bit for bit, against the
one-thread-per-primitive kernels they replace, on adversarial inputs: cell boundaries, 1e18
scales, NaN, infinities, signed zeros and centroids far outside a fixed grid."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import hlbvh_warp as hb
from hlbvh_warp.hlbvh import CPU_MORTON_CHUNK, PARALLEL_BOUNDS_MIN_PRIMS, PARALLEL_MIN_PRIMS, HlbvhPipeline
from hlbvh_warp.kernels import morton


def morton_on_grid(centroids, lo, hi, bits):
    """Morton codes (Morton 1966) of float32 centroids on the grid over [lo, hi], quantized in
    float64 as (c - lo) / extent * cells, clamped before the integer conversion; NaN takes cell 0."""
    c = centroids.astype(np.float64)
    lo, hi = np.asarray(lo, np.float32).astype(np.float64), np.asarray(hi, np.float32).astype(np.float64)
    extent = hi - lo
    cells = 1 << bits
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t = (c - lo) / np.where(extent > 0, extent, 1.0) * cells
    q = np.zeros(c.shape, dtype=np.int64)
    inside = (t > 0) & (t < cells - 1)
    q[inside] = t[inside].astype(np.int64)
    q[t >= cells - 1] = cells - 1
    q[:, ~(extent > 0)] = 0
    code = np.zeros(len(c), dtype=np.int64)
    for bit in range(bits):
        for axis in range(3):  # x is the most significant of each triple
            code |= ((q[:, axis] >> bit) & 1) << (3 * bit + 2 - axis)
    return code


def adversarial_points(rng, n, lo, hi, bits):
    """Points on, and one float32 step either side of, cell boundaries of the grid over [lo, hi],
    mixed with uniform points and a few NaN, infinite and far-away coordinates."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    cells = 1 << bits
    k = rng.integers(0, cells + 1, size=(n, 3))
    on = (lo + (hi - lo) * k / cells).astype(np.float32)
    step = rng.integers(-1, 2, size=(n, 3))
    pts = np.where(step < 0, np.nextafter(on, np.float32(-np.inf)),
                   np.where(step > 0, np.nextafter(on, np.float32(np.inf)), on)).astype(np.float32)
    uniform = (lo + (hi - lo) * rng.random((n, 3))).astype(np.float32)
    pts = np.where(rng.random((n, 1)) < 0.3, uniform, pts)
    for value in (np.nan, np.inf, -np.inf, 1e30, -1e30, 0.0, -0.0):
        rows = rng.integers(0, n, size=max(n // 200, 1))
        pts[rows, rng.integers(0, 3, size=rows.size)] = value
    return pts


def old_codes(lowers, uppers, bounds, bits, device):
    """The one-thread-per-primitive kernel the CPU pipeline ran before, on the same boxes and grid."""
    codes = wp.empty(lowers.shape[0], dtype=wp.int32, device=device)
    wp.launch(morton.morton_codes_kernel, dim=lowers.shape[0], inputs=[lowers, uppers, bounds, bits, codes],
              device=device)
    return codes.numpy()


GRIDS = {
    "unit": ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
    "1e18": ((1e18, -3e18, 2e17), (4e18, 1e18, 2.5e17)),
    "tiny": ((1e-30, -1e-30, 0.0), (3e-30, 1e-30, 1e-38)),
    "flat": ((-5.0, 2.0, 7.0), (5.0, 2.0, 9.0)),
    # Extents 3 * 2^m: a point on a cell boundary divides exactly to k / cells, the quotient
    # on the edge between two cells.
    "thirds": ((0.0, -6.0, 0.75), (3.0, 0.0, 1.5)),
}


@pytest.mark.parametrize("grid", sorted(GRIDS))
@pytest.mark.parametrize("bits", [10, 7])
@pytest.mark.parametrize("n, threads", [(2 * PARALLEL_MIN_PRIMS + 77, 0), (2 * PARALLEL_MIN_PRIMS + 77, 1),
                                        (CPU_MORTON_CHUNK + 1, 1), (5, 1)])
def test_morton_codes_on_a_fixed_grid_match_float64(device, rng, grid, bits, n, threads):
    lo, hi = GRIDS[grid]
    pts = adversarial_points(rng, n, lo, hi, bits)
    # Boxes of zero size: the centroid is the point itself, to the bit.
    cfg = hb.BuildConfig(bits_per_axis=bits, coarse_bits=min(bits, 6), morton_bounds=(lo, hi), cpu_threads=threads)
    boxes = wp.array(pts, dtype=wp.vec3, device=device)
    pipe = HlbvhPipeline(n, cfg, device, boxes, boxes)
    pipe.compute_morton_codes()
    codes = pipe.morton_codes.numpy()
    np.testing.assert_array_equal(codes, morton_on_grid(pts, lo, hi, bits))
    np.testing.assert_array_equal(codes, old_codes(boxes, boxes, pipe.scene_bounds, bits, device))


@pytest.mark.parametrize("scale", [1.0, 1e18, 1e-20])
def test_morton_codes_on_the_centroid_bounds_match_float64(device, rng, scale):
    # The per-frame grid: the reduced centroid bounds, NaN centroids left out of the reduction.
    n = 3 * CPU_MORTON_CHUNK + 5
    lo = (scale * rng.standard_normal((n, 3))).astype(np.float32)
    hi = (lo + scale * rng.random((n, 3))).astype(np.float32)
    lo[rng.integers(0, n, 20), rng.integers(0, 3, 20)] = np.nan
    pipe = HlbvhPipeline(n, hb.BuildConfig(), device, wp.array(lo, dtype=wp.vec3, device=device),
                         wp.array(hi, dtype=wp.vec3, device=device))
    pipe.compute_morton_codes()
    centroids = (np.float32(0.5) * (lo + hi)).astype(np.float32)
    grid = np.nanmin(centroids, axis=0), np.nanmax(centroids, axis=0)
    np.testing.assert_array_equal(pipe.scene_bounds.numpy(), np.stack(grid))
    codes = pipe.morton_codes.numpy()
    np.testing.assert_array_equal(codes, morton_on_grid(centroids, *grid, 10))
    np.testing.assert_array_equal(codes, old_codes(pipe.prim_lowers, pipe.prim_uppers, pipe.scene_bounds, 10, device))


@pytest.mark.parametrize("n, threads", [(1000, 1), (PARALLEL_BOUNDS_MIN_PRIMS + 5, 2)])
@pytest.mark.parametrize("mesh", [False, True])
def test_centroid_bounds_past_3_4e38(device, rng, n, threads, mesh):
    """Centroids beyond 3.4e38 on x, below -3.4e38 on y (finite float32 up to 3.4028e38, which the
    input checks accept): the reductions started from +-3.4e38 kept that as the grid's corner,
    a grid wider than the centroids, so the codes and the tree's order were not the stable sort
    of the codes on the centroid bounds."""
    top = np.float64(np.finfo(np.float32).max)
    rows = 3 * n if mesh else n
    pts = (top * (1.0 - 0.0004 * rng.random((rows, 3)))).astype(np.float32)
    pts[:, 1] *= -1
    pts[:, 2] = rng.standard_normal(rows).astype(np.float32)
    if mesh:
        faces = np.arange(3 * n, dtype=np.int32).reshape(n, 3)
        lo, hi = pts[faces].min(axis=1), pts[faces].max(axis=1)
    else:
        lo, hi = pts, pts
    centroids = (0.5 * (lo.astype(np.float64) + hi)).astype(np.float32)
    grid = centroids.min(axis=0), centroids.max(axis=0)
    assert grid[0][0] > 3.4e38 and grid[1][1] < -3.4e38  # the scene does what the test means
    config = hb.BuildConfig(cpu_threads=threads)
    pipe = HlbvhPipeline(n, config, device)
    if mesh:
        pipe.compute_triangle_bounds(wp.array(pts, dtype=wp.vec3, device=device),
                                     wp.array(faces, dtype=wp.int32, device=device))
    else:
        pipe.prim_lowers.assign(lo)
        pipe.prim_uppers.assign(hi)
        pipe.compute_centroid_bounds()
    np.testing.assert_array_equal(pipe.scene_bounds.numpy(), np.stack(grid))
    expected = np.argsort(morton_on_grid(centroids, *grid, 10), kind="stable")
    bvh = hb.build(pts, faces, device=device, config=config) if mesh else \
        hb.build_from_bounds(lo, hi, device=device, config=config)
    np.testing.assert_array_equal(bvh.to_numpy()["prim_order"], expected)


def test_spread_table_is_spread_bits_10():
    values = np.arange(1024)
    expected = np.zeros(1024, dtype=np.int64)
    for bit in range(10):
        expected |= ((values >> bit) & 1) << (3 * bit)
    np.testing.assert_array_equal(morton.spread_table_values(), expected)


def test_triangle_bounds_keep_nan_and_signed_zero_bits(device, rng):
    """The boxes and centroid bounds of the per-frame pass, bit for bit as the one-thread-per-triangle
    kernel computes them, and as NumPy's NaN-skipping fmin/fmax, on vertices with NaN, infinities and
    both zeros (a NaN's bits and the choice between +0 and -0 included)."""
    n = 3 * 4096 + 11
    verts = rng.standard_normal((n, 3)).astype(np.float32)
    rows = rng.integers(0, n, 400)
    verts[rows, rng.integers(0, 3, 400)] = rng.choice(
        np.array([np.nan, np.inf, -np.inf, 0.0, -0.0, 1e38, -1e38], dtype=np.float32), 400)
    verts[:50] = rng.choice(np.array([0.0, -0.0], dtype=np.float32), (50, 3))
    verts[50] = np.nan
    faces = rng.integers(0, n, size=(n, 3)).astype(np.int32)
    faces[:40] = rng.integers(0, 51, size=(40, 3))
    v = wp.array(verts, dtype=wp.vec3, device=device)
    f = wp.array(faces, dtype=wp.int32, device=device)
    pipe = HlbvhPipeline(n, hb.BuildConfig(), device)
    pipe.compute_triangle_bounds(v, f)

    old_lowers = wp.empty(n, dtype=wp.vec3, device=device)
    old_uppers = wp.empty(n, dtype=wp.vec3, device=device)
    old_bounds = wp.empty(2, dtype=wp.vec3, device=device)
    wp.launch(morton.reset_bounds_kernel, dim=1, inputs=[old_bounds], device=device)
    wp.launch(morton.triangle_bounds_centroids_kernel, dim=n, inputs=[n, 1, v, f, old_lowers, old_uppers, old_bounds],
              device=device)
    for new, old in ((pipe.prim_lowers, old_lowers), (pipe.prim_uppers, old_uppers), (pipe.scene_bounds, old_bounds)):
        np.testing.assert_array_equal(new.numpy().view(np.uint32), old.numpy().view(np.uint32))

    tri = verts[faces]
    lo = np.fmin(np.fmin(tri[:, 0], tri[:, 1]), tri[:, 2])
    hi = np.fmax(np.fmax(tri[:, 0], tri[:, 1]), tri[:, 2])
    np.testing.assert_array_equal(pipe.prim_lowers.numpy(), lo)  # NaN where NaN, +0 == -0
    np.testing.assert_array_equal(pipe.prim_uppers.numpy(), hi)
    with np.errstate(invalid="ignore", over="ignore"):
        centroids = (np.float32(0.5) * (lo + hi)).astype(np.float32)
    grid = np.stack([np.nanmin(centroids, axis=0), np.nanmax(centroids, axis=0)])
    np.testing.assert_array_equal(pipe.scene_bounds.numpy(), grid)
