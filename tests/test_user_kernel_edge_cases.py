"""The user-kernel API at its edges, against a float64 NumPy brute force of this file's own: the
exported ``@wp.func`` ray queries called several times per thread, from a ``wp.func`` of the
user's, with the view inside a struct of the user's; and the mistakes a user is likely to make."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from conftest import TEST_KERNEL_OPTIONS

import hlbvh_warp as hb
from hlbvh_warp import wide

wp.set_module_options(TEST_KERNEL_OPTIONS)  # quick CPU compiles of this file's kernels (conftest)


@wp.struct
class _Scene:
    """A user's own struct carrying the views, as a renderer passes its scene."""

    bvh: hb.BvhView
    wide: wide.WideView


@wp.func
def _trace(scene: _Scene, origin: wp.vec3, direction: wp.vec3, t_min: float, t_max: float, ignore: int):
    return hb.bvh_closest_hit(scene.bvh, origin, direction, t_min, t_max, ignore)


@wp.kernel
def _ranged_rays_kernel(
    scene: _Scene,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    t_min: wp.array(dtype=float),
    t_max: wp.array(dtype=float),
    ignore: wp.array(dtype=wp.int32),
    out: wp.array2d(dtype=float),
):
    i = wp.tid()
    # Each call twice in one thread: a second call must see nothing left over from the first.
    for rep in range(2):
        h = _trace(scene, origins[i], directions[i], t_min[i], t_max[i], ignore[i])
        out[i, 0] = h.t
        out[i, 1] = float(h.prim)
        out[i, 2] = float(hb.bvh_any_hit(scene.bvh, origins[i], directions[i], t_min[i], t_max[i], ignore[i]).prim)
        out[i, 3] = float(hb.bvh_occluded(scene.bvh, origins[i], directions[i], t_min[i], t_max[i], ignore[i]))
        w = wide.bvh_wide_closest_hit(scene.wide, origins[i], directions[i], t_min[i], t_max[i], ignore[i])
        out[i, 4] = w.t
        out[i, 5] = float(w.prim)


def _brute_force(vertices, faces, origin, direction, t_min, t_max, ignore):
    """Closest hit with t in the open (t_min, t_max) on any triangle but ``ignore`` (an index outside
    the mesh ignores nothing), Moller-Trumbore in float64; (inf, -1) on a miss, and whether some
    triangle is met within 1e-6 of an edge (where float32 may decide either way)."""
    a, b, c = (vertices[faces[:, k]].astype(np.float64) for k in range(3))
    o, d = origin.astype(np.float64), direction.astype(np.float64)
    if not (np.isfinite(o).all() and np.isfinite(d).all() and d.any() and t_min >= 0.0 and t_max > t_min):
        return np.inf, -1, False
    e1, e2 = b - a, c - a
    with np.errstate(all="ignore"):
        p = np.cross(d, e2)
        det = (p * e1).sum(1)
        s = o - a
        u = (s * p).sum(1) / det
        q = np.cross(s, e1)
        v = (q * d).sum(1) / det
        t = (q * e2).sum(1) / det
        margin = np.minimum(np.minimum(u, v), 1.0 - u - v)
    ok = (det != 0) & np.isfinite(t) & (margin >= 0) & (t > t_min) & (t < t_max)
    if 0 <= ignore < len(faces):
        ok[ignore] = False
    near_edge = bool((np.abs(margin[np.isfinite(t)]) < 1e-6).any())
    if not ok.any():
        return np.inf, -1, near_edge
    best = int(np.argmin(np.where(ok, t, np.inf)))
    return t[best], best, near_edge


def test_ranged_ray_calls_in_a_users_struct_and_func_match_a_brute_force(device):
    # A sphere: a ray through it crosses two faces, so t_min, t_max and ignore_prim each decide
    # between the near crossing, the far one and none.
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=2)
    vertices, faces = mesh.vertices.astype(np.float32), np.asarray(mesh.faces, np.int32)
    num = len(faces)
    bvh = hb.build(vertices, faces, device=device)
    scene = _Scene()
    scene.bvh = bvh.view()
    scene.wide = wide.view(wide.collapse(bvh, 4))
    rng = np.random.default_rng(5)
    rows = []
    nan, inf = float("nan"), float("inf")
    for _ in range(40):
        target = rng.uniform(-0.4, 0.4, 3)
        direction = rng.normal(size=3)
        origin = target - 3.0 * direction / np.linalg.norm(direction)
        # The near crossing lies at about t = 2 / |d|, the far one at about 4 / |d|.
        scale = 1.0 / np.linalg.norm(direction)
        for t_min, t_max in [(0.0, inf), (3.0 * scale, inf), (0.0, 3.0 * scale), (nan, inf), (-1.0, inf),
                             (0.0, nan), (3.0 * scale, 3.0 * scale), (5.0 * scale, 1.0 * scale), (inf, inf)]:
            rows.append((origin, direction, t_min, t_max, -1))
        near = _brute_force(vertices, faces, origin.astype(np.float32), direction.astype(np.float32), 0.0, inf, -1)[1]
        for ignore in (near, -2, num, num + 7, 2**31 - 1, -(2**31)):
            rows.append((origin, direction, 0.0, inf, ignore))
    for origin, direction in [((nan, 0.0, -3.0), (0.0, 0.0, 1.0)), ((0.1, 0.1, -3.0), (0.0, 0.0, 0.0)),
                              ((0.1, 0.1, -3.0), (0.0, inf, 1.0))]:
        rows.append((np.array(origin), np.array(direction), 0.0, inf, -1))
    origins = np.array([r[0] for r in rows], np.float32)
    directions = np.array([r[1] for r in rows], np.float32)
    t_min = np.array([r[2] for r in rows], np.float32)
    t_max = np.array([r[3] for r in rows], np.float32)
    ignore = np.array([r[4] for r in rows], np.int32)
    out = wp.zeros((len(rows), 6), dtype=float, device=device)
    wp.launch(_ranged_rays_kernel, dim=len(rows), device=device,
              inputs=[scene] + [wp.array(x, dtype=wp.vec3, device=device) for x in (origins, directions)]
              + [wp.array(t_min, dtype=float, device=device), wp.array(t_max, dtype=float, device=device),
                 wp.array(ignore, dtype=wp.int32, device=device), out])
    out = out.numpy()
    checked = 0
    for i in range(len(rows)):
        t, prim, near_edge = _brute_force(vertices, faces, origins[i], directions[i], float(t_min[i]), float(t_max[i]),
                                          int(ignore[i]))
        if near_edge:
            continue  # float32 may take either triangle of an edge
        checked += 1
        found = prim >= 0
        assert (out[i, 1] >= 0) == found and (out[i, 5] >= 0) == found, (rows[i], out[i], t, prim)
        assert (out[i, 2] >= 0) == found and out[i, 3] == float(found), (rows[i], out[i])
        if found:
            assert out[i, 1] == prim and out[i, 5] == prim, (rows[i], out[i], prim)
            np.testing.assert_allclose(out[i, [0, 4]], t, rtol=1e-5)
            assert out[i, 2] != ignore[i]
        else:
            assert out[i, 0] == np.inf and out[i, 4] == np.inf
    assert checked > 0.9 * len(rows)


@wp.kernel
def _view_kernel(bvh: hb.BvhView, out: wp.array(dtype=wp.int32)):
    out[0] = hb.bvh_closest_hit(bvh, wp.vec3(0.0, 0.0, -5.0), wp.vec3(0.0, 0.0, 1.0), 1.0e30).prim


@wp.kernel
def _wide_view_kernel(view: wide.WideView, out: wp.array(dtype=wp.int32)):
    out[0] = wide.bvh_wide_closest_hit(view, wp.vec3(0.0, 0.0, -5.0), wp.vec3(0.0, 0.0, 1.0), 1.0e30).prim


def test_a_tree_passed_where_a_kernel_takes_its_view_names_the_mistake(device):
    # The likeliest slip of a user kernel's launch: the tree itself in place of its view. Warp
    # packs a struct argument by calling the value's __ctype__, and the tree had none: the launch
    # failed with "'Bvh' object has no attribute '__ctype__'", which names nothing the user wrote.
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=1)
    bvh = hb.build(mesh, device=device)
    w = wide.collapse(bvh, 4)
    out = wp.full(1, -7, dtype=wp.int32, device=device)
    with pytest.raises(TypeError, match=r"bvh\.view\(\)"):
        wp.launch(_view_kernel, dim=1, inputs=[bvh, out], device=device)
    with pytest.raises(TypeError, match=r"wide\.view\(w\)"):
        wp.launch(_wide_view_kernel, dim=1, inputs=[w, out], device=device)
    assert out.numpy()[0] == -7  # refused before anything ran
    # The views themselves launch, and the ray down the z axis hits the sphere.
    wp.launch(_view_kernel, dim=1, inputs=[bvh.view(), out], device=device)
    assert out.numpy()[0] >= 0
