"""Brute-force references for checking builds from package code (benchmarks, demos).

Float64 NumPy and nothing of the BVH: a benchmark checks a batch of rays against this before it
reports a time (the tests keep their own copy in tests/oracles.py, independent of the package).
"""

from __future__ import annotations

import numpy as np

#: Barycentric slack of the float64 reference, far below float32 traversal error.
BARYCENTRIC_EPS = 1e-12


def brute_force_closest_hit(vertices, faces, origins, directions, t_max=np.inf, chunk=64):
    """Closest hit of every ray against every triangle (Moller-Trumbore, float64).

    Returns ``(t, prim)``; a miss is ``(inf, -1)``. Rays are processed ``chunk`` at a time, so
    memory stays at chunk * F.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    e1, e2 = b - a, c - a
    o_all = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d_all = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    t_out = np.full(len(o_all), np.inf)
    p_out = np.full(len(o_all), -1, dtype=np.int64)
    with np.errstate(all="ignore"):
        for s in range(0, len(o_all), chunk):
            o = o_all[s : s + chunk, None, :]
            d = d_all[s : s + chunk, None, :]
            p = np.cross(d, e2[None])
            det = np.einsum("rfk,fk->rf", p, e1)
            inv = 1.0 / det
            tv = o - a[None]
            u = np.einsum("rfk,rfk->rf", tv, p) * inv
            q = np.cross(tv, e1[None])
            w = np.einsum("rk,rfk->rf", d[:, 0], q) * inv
            t = np.einsum("rfk,fk->rf", q, e2) * inv
            eps = BARYCENTRIC_EPS
            ok = (det != 0) & (u >= -eps) & (w >= -eps) & (u + w <= 1 + eps) & (t > 0) & (t < t_max) & np.isfinite(t)
            t = np.where(ok, t, np.inf)
            idx = np.argmin(t, axis=1)
            best = t[np.arange(len(idx)), idx]
            t_out[s : s + chunk] = best
            p_out[s : s + chunk] = np.where(np.isfinite(best), idx, -1)
    return t_out, p_out


def rays_at_box(rng, vertices, num_rays):
    """Rays from a sphere around the bounding box aimed at random points inside it."""
    v = np.asarray(vertices, dtype=np.float64)
    lo, hi = v.min(0), v.max(0)
    center, radius = 0.5 * (lo + hi), 0.5 * np.linalg.norm(hi - lo) + 1e-6
    dirs = rng.normal(size=(num_rays, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origins = center - 2.0 * radius * dirs
    targets = lo + rng.random((num_rays, 3)) * (hi - lo)
    d = targets - origins
    return origins.astype(np.float32), (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


def count_mismatches(t, prim, t_ref, prim_ref, rtol=1e-5) -> int:
    """Rays whose hit disagrees with the reference: hit/miss differs, or a different primitive at
    a different distance (ties between primitives at the same t are accepted)."""
    t = np.asarray(t, dtype=np.float64)
    hit, hit_ref = np.asarray(prim) >= 0, np.asarray(prim_ref) >= 0
    same = np.asarray(prim) == np.asarray(prim_ref)
    close = np.isclose(t, t_ref, rtol=rtol, atol=0.0)
    bad = (hit != hit_ref) | (hit & ~(same | close))
    return int(bad.sum())
