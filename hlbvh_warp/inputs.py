"""Validation and conversion of user input: every problem is a ValueError naming it."""

from __future__ import annotations

import numpy as np
import warp as wp


#: Primitives one tree can hold: node ids are int32 and the arena holds 2N - 1 nodes.
MAX_PRIMS = 1 << 30


def count_arg(value, name: str, minimum: int) -> int:
    """An integer argument of at least ``minimum``: 2.5 (or True) is a caller's mistake, not 2
    (or 1), refused as BuildConfig's integer fields are; NumPy integers count like any other."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _to_numpy(values, name: str) -> np.ndarray:
    # Any Warp array, wp.indexedarray too (no wp.array subclass): NumPy would wrap that as one
    # object, refused as "dtype object" though it holds numbers.
    if wp.types.is_array(values):
        return values.numpy()
    try:
        return np.asarray(values)
    except Exception as exc:  # ragged lists and the like
        raise ValueError(f"{name} could not be read as an array: {exc}") from exc


def _check_points(values, name: str) -> np.ndarray:
    arr = _to_numpy(values, name)
    if arr.dtype.kind not in "fiu":
        raise ValueError(f"{name} must hold real numbers, got dtype {arr.dtype}")
    if arr.ndim == 1 and arr.size % 3 == 0 and arr.dtype.kind == "f" and wp.types.is_array(values):
        arr = arr.reshape(-1, 3)  # a wp.array of vec3 comes back as (n, 3) already; flat floats too
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (n, 3), got {arr.shape}")
    if arr.dtype.kind in "iu":
        # Straight to float32, rounded once: through float64 a 64-bit integer past 2^53 would be
        # rounded twice. Every integer fits float32's range.
        return np.ascontiguousarray(arr.astype(np.float32))
    # Checked in the given dtype: a long double past float64's range would be inf once widened
    # (or narrowed) to float64, and refused as a NaN or Inf it is not.
    check_float32_range(arr, name)
    return np.ascontiguousarray(arr, dtype=np.float32)


def check_float32_range(arr: np.ndarray, name: str):
    """Raise if host coordinates hold a NaN or Inf, or would not fit in float32: every build
    narrows them to float32, where 1e39 would silently become Inf. `arr` is ``(n, 3)`` points
    (the first bad one named by row) or ``(K, 3, 3)`` triangles (named by triangle and vertex)."""
    if not np.isfinite(arr).all():
        at = tuple(int(x) for x in np.argwhere(~np.isfinite(arr))[0][:-1])
        where = f"triangle {at[0]}, vertex {at[1]}" if len(at) == 2 else f"row {at[0]}"
        raise ValueError(f"{name} has a NaN or Inf coordinate (first at {where}: {arr[at].tolist()})")
    # A finite float32 is in range by definition; wider input must fit before it is narrowed.
    if arr.dtype != np.float32 and arr.size and np.abs(arr).max() > np.finfo(np.float32).max:
        raise ValueError(f"{name} has a coordinate beyond the float32 range")


def refuse_several_meshes(mesh, caller: str):
    """A trimesh.Scene or a list of meshes, the natural things to pass, refused with how to make
    one mesh of them."""
    if hasattr(mesh, "geometry") and hasattr(mesh, "graph"):
        raise ValueError(f"{caller} takes one mesh, got a trimesh.Scene: make it one first (scene.to_mesh(), or "
                         "trimesh.util.concatenate(scene.dump())); face ids then run through its meshes in order")
    if isinstance(mesh, (list, tuple)) and mesh and all(hasattr(m, "faces") for m in mesh):
        raise ValueError(f"{caller} takes one mesh, got a {type(mesh).__name__} of {len(mesh)}: make them one "
                         "first (trimesh.util.concatenate(meshes)); face ids then run through them in order")


def mesh_arrays(mesh, faces=None) -> tuple[np.ndarray, np.ndarray]:
    """(vertices float32 (V, 3), faces int32 (F, 3)) from a trimesh.Trimesh or two arrays."""
    is_mesh = hasattr(mesh, "vertices") and hasattr(mesh, "faces")
    if faces is None:
        refuse_several_meshes(mesh, "build()")
        if not is_mesh:
            raise ValueError("build() takes a trimesh.Trimesh, or vertices with faces=")
        vertices, faces = mesh.vertices, mesh.faces
    elif is_mesh:
        raise ValueError("build() takes a trimesh.Trimesh alone, or vertices with faces=; got a mesh and faces=")
    else:
        vertices = mesh
    # An empty list reads as a float array of shape (0,): name the empty mesh, not the shape or dtype.
    if _to_numpy(vertices, "vertices").size == 0:
        raise ValueError("the mesh is empty: vertices has no rows")
    verts = _check_points(vertices, "vertices")
    tris = _to_numpy(faces, "faces")
    if tris.size == 0:
        raise ValueError("the mesh is empty: faces has no rows")
    if tris.dtype.kind not in "iu":
        raise ValueError(f"faces must hold integers, got dtype {tris.dtype}")
    if tris.ndim == 1 and tris.size % 3 == 0:
        tris = tris.reshape(-1, 3)
    if tris.ndim != 2 or tris.shape[1] != 3:
        raise ValueError(f"faces must have shape (F, 3), got {tris.shape}")
    if tris.shape[0] == 0:
        raise ValueError("the mesh is empty: faces has no rows")
    if verts.shape[0] == 0:
        raise ValueError("the mesh is empty: vertices has no rows")
    lo, hi = int(tris.min()), int(tris.max())
    if lo < 0 or hi >= verts.shape[0]:
        # The index named is one the named face holds: the smallest or largest index overall may sit
        # in another face, and a message pairing them sends the user to a face that looks right.
        row, col = (int(i) for i in np.argwhere((tris < 0) | (tris >= verts.shape[0]))[0])
        bad = int(tris[row, col])
        raise ValueError(f"face index {bad} out of range [0, {verts.shape[0]}) (first at face {row})")
    if tris.shape[0] >= MAX_PRIMS:
        raise ValueError(f"too many faces ({tris.shape[0]}): indices are int32 and the arena holds 2F - 1 nodes")
    return verts, np.ascontiguousarray(tris, dtype=np.int32)


def bounds_arrays(lowers, uppers) -> tuple[np.ndarray, np.ndarray]:
    """Primitive boxes as float32 ``(N, 3)`` lowers and uppers, after the checks of a build: real,
    finite and within float32, the same non-empty shape, fewer than `MAX_PRIMS`, lowers <= uppers.
    Raises a ValueError naming the first problem."""
    lo = _check_points(lowers, "lowers")
    hi = _check_points(uppers, "uppers")
    if lo.shape != hi.shape:
        raise ValueError(f"lowers and uppers differ in shape: {lo.shape} vs {hi.shape}")
    if lo.shape[0] == 0:
        raise ValueError("no primitives: lowers has no rows")
    if lo.shape[0] >= MAX_PRIMS:
        raise ValueError(f"too many boxes ({lo.shape[0]}): node ids are int32 and the arena holds 2N - 1 nodes")
    inverted = lo > hi
    if inverted.any():
        row = int(np.argwhere(inverted)[0][0])
        raise ValueError(f"box {row} has lowers > uppers: {lo[row].tolist()} vs {hi[row].tolist()}")
    return lo, hi


def query_array(values, name: str) -> np.ndarray:
    """Query rows (ray origins or directions, box bounds, points): ``(n, 3)`` or one ``(3,)`` row of
    real numbers, as contiguous float32. NaN or Inf is not an error here: such a query finds
    nothing; only shapes and dtypes are."""
    arr = _to_numpy(values, name)
    if arr.shape == (0,) and arr.dtype.kind in "fiu":
        arr = arr.reshape(0, 3).astype(np.float32)  # an empty list: no queries
    if arr.dtype.kind not in "fiu":
        raise ValueError(f"{name} must hold real numbers, got dtype {arr.dtype}")
    if arr.shape == (3,):
        arr = arr.reshape(1, 3)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (n, 3), got {arr.shape}")
    # A wider coordinate past float32's range rounds to the infinity a query takes (an unbounded
    # box side, a ray or point that finds nothing), quietly, as a huge t_max or max_dist does.
    with np.errstate(over="ignore"):
        return np.ascontiguousarray(arr, dtype=np.float32)


def ray_arrays(origins, directions) -> tuple[np.ndarray, np.ndarray]:
    """Rays may hold NaN or Inf (they miss); only shapes and dtypes are errors. One origin (a
    camera's) or one direction (a light's) serves every ray of the other."""
    o, d = query_array(origins, "origins"), query_array(directions, "directions")
    if o.shape != d.shape:
        if len(o) == 1:
            o = np.ascontiguousarray(np.broadcast_to(o, d.shape))
        elif len(d) == 1:
            d = np.ascontiguousarray(np.broadcast_to(d, o.shape))
        else:
            raise ValueError(f"origins and directions differ in shape: {o.shape} vs {d.shape}")
    return o, d
