"""Generated scenes that ship with the package: no downloads, no files from outside it.

`default_scene` is a closed, bumpy torus-knot tube, deterministic for a given size, with a
Morton-unfriendly mix of long thin and round parts. `load_mesh` reads a mesh file instead, and
`subdivide` scales a mesh up to the sizes of the paper's scenes.
"""

from __future__ import annotations

import numpy as np


def torus_knot(p: int = 2, q: int = 3, rings: int = 600, sides: int = 50, knot_radius: float = 1.0,
               tube_radius: float = 0.18, bumps: float = 0.25, bump_frequency: tuple[int, int] = (41, 7)):
    """A closed tube around a (p, q) torus knot: ``2 * rings * sides`` triangles.

    The tube radius is modulated by ``1 + bumps * sin(a u) * sin(b v)`` so the surface has
    detail at every scale. Returns ``(vertices float32 (V, 3), faces int32 (F, 3))``.
    """
    if rings < 3 or sides < 3:
        raise ValueError(f"torus_knot needs rings >= 3 and sides >= 3, got {rings}, {sides}")
    t = np.linspace(0.0, 2.0 * np.pi, rings, endpoint=False)

    def curve(s):
        r = knot_radius * (2.0 + np.cos(q * s)) / 3.0
        return np.stack([r * np.cos(p * s), r * np.sin(p * s), -knot_radius * np.sin(q * s) / 3.0], axis=-1)

    # Frenet frame from finite differences of the analytic curve (its curvature never vanishes).
    h = 1e-4
    c0, cp, cm = curve(t), curve(t + h), curve(t - h)
    d1 = (cp - cm) / (2 * h)
    d2 = (cp - 2 * c0 + cm) / (h * h)
    tangent = d1 / np.linalg.norm(d1, axis=1, keepdims=True)
    binormal = np.cross(d1, d2)
    binormal /= np.linalg.norm(binormal, axis=1, keepdims=True)
    normal = np.cross(binormal, tangent)

    v = np.linspace(0.0, 2.0 * np.pi, sides, endpoint=False)
    a, b = bump_frequency
    radius = tube_radius * (1.0 + bumps * np.sin(a * t)[:, None] * np.sin(b * v)[None, :])
    ring = np.cos(v)[None, :, None] * normal[:, None, :] + np.sin(v)[None, :, None] * binormal[:, None, :]
    vertices = (c0[:, None, :] + radius[:, :, None] * ring).reshape(-1, 3)

    i, j = np.meshgrid(np.arange(rings), np.arange(sides), indexing="ij")
    a00 = i * sides + j
    a10 = ((i + 1) % rings) * sides + j
    a01 = i * sides + (j + 1) % sides
    a11 = ((i + 1) % rings) * sides + (j + 1) % sides
    faces = np.concatenate([np.stack([a00, a10, a11], -1).reshape(-1, 3),
                            np.stack([a00, a11, a01], -1).reshape(-1, 3)])
    return vertices.astype(np.float32), faces.astype(np.int32)


#: The fewest triangles `default_scene` makes (a knot of 3 rings of 3 sides, two triangles per quad).
MIN_SCENE_TRIS = 18


def default_scene(num_tris: int = 60000):
    """The package's default scene: a bumpy torus knot with about ``num_tris`` triangles."""
    if num_tris < MIN_SCENE_TRIS:
        raise ValueError(f"default_scene needs at least {MIN_SCENE_TRIS} triangles, got {num_tris}")
    # rings : sides about 12 : 1 keeps the quads roughly square along the tube.
    sides = max(3, int(round(np.sqrt(num_tris / 24.0))))
    rings = max(3, int(round(num_tris / (2.0 * sides))))
    return torus_knot(rings=rings, sides=sides)


def knot_with_large_triangles(num_tris: int = 60000, num_large: int = 8, seed: int = 0):
    """The default scene with `num_large` of its triangles replaced by large ones spanning its
    bounds (corners drawn uniformly in its box): small and large triangles mixed, as in the
    architectural scenes spatial splits were made for (Stich et al. 2009), where every object
    split holding a large triangle gets a box as large as the scene's."""
    vertices, faces = default_scene(max(num_tris - num_large, 18))
    rng = np.random.default_rng(seed)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    corners = (lo + (hi - lo) * rng.uniform(0.0, 1.0, (num_large * 3, 3))).astype(np.float32)
    large = len(vertices) + np.arange(num_large * 3, dtype=np.int32).reshape(-1, 3)
    return np.concatenate([vertices, corners]), np.concatenate([faces, large])


#: The generated scenes of the measuring commands, by name.
GENERATED = {"knot": default_scene, "knot+large": knot_with_large_triangles}


def named_meshes(paths, num_tris: int = 60000, generated: str = "knot") -> list:
    """``(name, vertices, faces)`` of each mesh file (named by its stem), or of the generated
    scene `generated` (`GENERATED`) when no path is given: the mesh list of the measuring commands."""
    import pathlib

    if not paths:
        if generated not in GENERATED:
            raise ValueError(f"unknown generated scene {generated!r}; choose one of {sorted(GENERATED)}")
        return [("generated" if generated == "knot" else generated, *GENERATED[generated](num_tris))]
    return [(pathlib.Path(p).stem, *load_mesh(p)) for p in paths]


def progress(text: str):
    """One status line on stderr, rewritten in place (the measuring commands' progress)."""
    import sys

    print(f"\r\033[K{text}", end="", file=sys.stderr, flush=True)


def load_mesh(path):
    """``(vertices float32, faces int32)`` of a mesh file (anything trimesh reads), unprocessed.

    Raises:
        ValueError: ``path`` is a folder, trimesh fails to read the file (its reason and the file
            named), or the mesh has no triangles. Face indices are checked later, by the build.
    """
    import os

    import trimesh

    if os.path.isdir(path):
        # trimesh reads a folder's name as a mesh's text and says "string is not a file".
        raise ValueError(f"{path} is a directory, not a mesh file")
    if os.path.exists(path) and not os.path.isfile(path):
        # A device or a named pipe (/dev/null): trimesh says "string is not a file", naming no cause.
        raise ValueError(f"{path} is not a regular file (a device or a pipe), not a mesh file")
    try:
        mesh = trimesh.load(path, process=False, force="mesh")
    except (ValueError, OSError, NotImplementedError) as error:
        # trimesh's own message names the problem but seldom the file ("file_type 'txt' not
        # supported", "Not a ply file!"): with several --mesh options, which one?
        message = str(error)
        raise ValueError(message if str(path) in message else f"{path}: {message}") from None
    except Exception as error:
        # trimesh's parsers index with the file's numbers before checking them (an OBJ face
        # naming vertex 9 of 3 is an IndexError inside its loader): whatever fails in there is
        # the file's problem, named as such, not a traceback.
        hint = "; a face refers to a vertex the file does not have, or the file is cut short?" \
            if isinstance(error, IndexError) else ""
        raise ValueError(f"{path}: trimesh could not read the mesh ({type(error).__name__}: {error}{hint})") from None
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), dtype=np.int32).reshape(-1, 3)
    if faces.shape[0] == 0:
        # Named here, before a command computes bounds or rays over it (NumPy's reductions over
        # no rows end in an error about reductions, not about the file).
        raise ValueError(f"{path}: the mesh has no triangles")
    return np.asarray(mesh.vertices, dtype=np.float32), faces


def scene(mesh_path=None, num_tris: int = 60000):
    """A mesh file when a path is given, else the generated default scene. A ``(vertices,
    faces)`` pair is taken as it is: the examples read their ``--mesh`` before any work, to name
    a file that is no mesh as an argument error, and hand the arrays on."""
    if isinstance(mesh_path, tuple):
        return mesh_path
    return load_mesh(mesh_path) if mesh_path else default_scene(num_tris)


def subdivide(vertices, faces, times: int = 1):
    """Every triangle split into four, `times` times (``trimesh.remesh.subdivide``): a mesh at the
    sizes of Pantaleoni & Luebke's scenes from a smaller one (the shared armadillo is decimated to
    100k triangles, the paper's has 345k). A triangle's four are listed in a row, so the face
    order stays as coherent as the original's."""
    import trimesh

    if int(times) < 0:
        raise ValueError(f"subdivide times must be >= 0, got {times}")
    for _ in range(int(times)):
        vertices, faces = trimesh.remesh.subdivide(vertices, faces)
    return np.ascontiguousarray(vertices, dtype=np.float32), np.ascontiguousarray(faces, dtype=np.int32)
