"""Drop-ins for ``trimesh.ray.ray_triangle.RayMeshIntersector`` and
``trimesh.proximity.ProximityQuery`` backed by an HLBVH.

Same methods, arguments and return conventions as trimesh 5.2 (``intersects_id``,
``intersects_location``, ``intersects_first``, ``intersects_any``, ``contains_points``), with two
documented differences that follow from the watertight test (Woop et al. 2013) instead of
trimesh's tolerance-based one: a hit needs t > 0 (trimesh also accepts hits up to 1e-6 behind the
origin), and zero-area triangles are never hit. A ray lying in a triangle's plane misses it where
the plane is axis-aligned; in a tilted plane the float32 shear decides, and it may hit. A ray's
hit locations merge within trimesh's 1e-8 times the mesh's size, where trimesh's own merge (1e-8
absolute) lost crossings on meshes past about 1e11 or below about 1e-8 across.

`ProximityQuery` answers ``on_surface`` and ``signed_distance`` as trimesh 5.2 does, without
trimesh's r-tree dependency (``rtree``, which trimesh needs for them and this package does not),
except that a point whose closest triangle has zero area is signed by ray parity (trimesh's sign
of its zero normal gives -0.0), and a single ``(3,)`` point is one row (trimesh refuses it).
"""

from __future__ import annotations

import numpy as np

from . import api, inputs, query


def _check_mesh(mesh, caller: str):
    """Refused at construction, not at the first query (where hashing a list fails without
    saying why)."""
    inputs.refuse_several_meshes(mesh, caller)
    if not (hasattr(mesh, "vertices") and hasattr(mesh, "faces")):
        raise ValueError(f"{caller} takes a trimesh.Trimesh, got {type(mesh).__name__}")



def _real_float64(values, name: str) -> np.ndarray:
    """``values`` as float64, once they are known to hold real numbers, as the library's queries
    require: cast first, a complex point lost its imaginary part, a bool one read as 0 and 1 and
    an object one holding None as NaN, all without a word."""
    array = inputs._to_numpy(values, name)
    if array.dtype.kind not in "fiu":
        raise ValueError(f"{name} must hold real numbers, got dtype {array.dtype}")
    return array.astype(np.float64, copy=False)

class RayMeshIntersector:
    """Ray queries on a ``trimesh.Trimesh`` through a BVH built once on ``device``.

    Args:
        mesh: a ``trimesh.Trimesh``; the BVH is rebuilt when its vertices or faces change.
        device: Warp device; the current default device when ``None``.
        method: the builder (see `hlbvh_warp.api.build`).
    """

    def __init__(self, mesh, device=None, method: str = "hlbvh"):
        _check_mesh(mesh, "RayMeshIntersector")
        self.mesh = mesh
        self.device = device
        self.method = method
        self._bvh = None
        self._key = None

    @property
    def bvh(self):
        # trimesh's hash changes with the geometry: rebuild then, as trimesh drops its r-tree.
        key = hash(self.mesh)
        if self._bvh is None or key != self._key:
            self._bvh = api.build(self.mesh, method=self.method, device=self.device)
            self._key = key
        return self._bvh

    def _locations(self, index_ray, index_tri, t, ray_origins, ray_directions):
        """Hit points in float64, each on its triangle's plane, as trimesh computes them. The
        traversal's float32 t of two triangles meeting at an edge the ray crosses can differ by a
        unit in the last place, which puts o + d t about 6e-8 apart on a unit mesh, past the 1e-8
        at which trimesh merges a ray's equal locations: the edge crossing was listed twice. Where
        the plane's distance is ill-conditioned (a ray nearly in the plane, a degenerate
        triangle) the traversal's t stands."""
        o = np.asarray(ray_origins, dtype=np.float64)[index_ray]
        d = np.asarray(ray_directions, dtype=np.float64)[index_ray]
        t = np.asarray(t, dtype=np.float64)
        tri = np.asarray(self.mesh.vertices, dtype=np.float64)[np.asarray(self.mesh.faces)[index_tri]]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        with np.errstate(divide="ignore", invalid="ignore"):
            t_plane = np.einsum("ij,ij->i", normal, tri[:, 0] - o) / np.einsum("ij,ij->i", normal, d)
        # Within float32's error of the traversal's t (a few units of 2^-24): the same crossing.
        close = np.isfinite(t_plane) & (np.abs(t_plane - t) <= 1e-5 * np.abs(t))
        t = np.where(close, t_plane, t)
        return o + d * t[:, None]

    def intersects_id(self, ray_origins, ray_directions, return_locations=False, multiple_hits=True, **kwargs):
        """Triangles hit by each ray, as trimesh's.

        Returns:
            ``index_tri (h,) int64, index_ray (h,) int64`` and, when ``return_locations``,
            ``locations (h, 3) float64`` (then hits at the same location on one ray, such as a ray
            through a shared edge, are listed once, as trimesh does, sorted by ray and along it;
            "the same" is within 1e-8 of the mesh's size, `_distinct_locations`). With
            ``multiple_hits`` False, only the first hit of each ray.
        """
        # A single (3,) ray is one row, as `intersects_first` answers it: indexed as it came, it
        # broke the hit locations with a NumPy broadcast error.
        ray_origins = _real_float64(ray_origins, "origins")
        ray_directions = _real_float64(ray_directions, "directions")
        # An empty list is no rays, as the other calls take it, not one ray of no coordinates.
        if ray_origins.ndim == 1:
            ray_origins = ray_origins.reshape((0, 3) if ray_origins.size == 0 else (1, -1))
        if ray_directions.ndim == 1:
            ray_directions = ray_directions.reshape((0, 3) if ray_directions.size == 0 else (1, -1))
        if ray_origins.shape != ray_directions.shape and 1 in (len(ray_origins), len(ray_directions)) and \
                ray_origins.shape[1:] == ray_directions.shape[1:]:  # other shapes: the query names them
            # One origin (or direction) for every ray, as the queries take it: the hit locations
            # index the rays by their ids, so the rows are spelled out here too.
            ray_origins, ray_directions = np.broadcast_arrays(ray_origins, ray_directions)
        if multiple_hits:
            index_ray, index_tri, t = query.intersect_all(self.bvh, ray_origins, ray_directions)
        else:
            t_all, prim = query.intersect(self.bvh, ray_origins, ray_directions)
            index_ray = np.nonzero(prim >= 0)[0].astype(np.int64)
            index_tri = prim[index_ray].astype(np.int64)
            t = t_all[index_ray]
        locations = self._locations(index_ray, index_tri, t, ray_origins, ray_directions)
        if return_locations:
            unique = self._distinct_locations(index_ray, t, locations)
            return index_tri[unique], index_ray[unique], locations[unique]
        return index_tri, index_ray

    def _distinct_locations(self, index_ray, t, locations):
        """Indices of the hits to keep, by ray, then along it: one per location of each ray, hits
        within trimesh's ``tol.merge`` (1e-8) of the mesh's size (``mesh.scale``) of the previous
        one on the same ray merged into it.

        trimesh merges by rounding the locations to multiples of 1e-8 as int64
        (``grouping.unique_rows``): past about 9e10 the products overflow, every location of a
        ray became one row and the ray listed one crossing of two (a torus's hole read inside);
        on a mesh 1e-9 across the entry and exit fell in one cell. Relative to the mesh's size,
        the merge means at every scale what 1e-8 means for a unit mesh, where it is trimesh's."""
        from trimesh.constants import tol

        order = np.lexsort((t, index_ray))
        ray, where = index_ray[order], locations[order]
        new = np.ones(len(order), dtype=bool)
        new[1:] = (ray[1:] != ray[:-1]) | (np.abs(where[1:] - where[:-1]).max(axis=1) > tol.merge * self.mesh.scale)
        return order[new]

    def intersects_location(self, ray_origins, ray_directions, **kwargs):
        """Unique hit locations: ``locations (h, 3), index_ray (h,), index_tri (h,)``, as trimesh's."""
        index_tri, index_ray, locations = self.intersects_id(
            ray_origins=ray_origins, ray_directions=ray_directions, return_locations=True, **kwargs
        )
        return locations, index_ray, index_tri

    def intersects_first(self, ray_origins, ray_directions, **kwargs):
        """Index of the first triangle each ray hits, -1 on a miss: ``(n,) int64``."""
        _, prim = query.intersect(self.bvh, _real_float64(ray_origins, "origins"),
                                  _real_float64(ray_directions, "directions"))
        return prim.astype(np.int64)

    def intersects_any(self, ray_origins, ray_directions, **kwargs):
        """Whether each ray hits any triangle: ``(n,) bool`` (an any-hit traversal, stopping early)."""
        return query.occluded(self.bvh, _real_float64(ray_origins, "origins"),
                              _real_float64(ray_directions, "directions"))

    def contains_points(self, points):
        """Whether each point is inside the (watertight) mesh, by trimesh's ray-parity test."""
        from trimesh.ray.ray_util import contains_points

        self.bvh  # an empty mesh raises our ValueError here, not a TypeError inside trimesh
        return contains_points(self, _real_float64(points, "points"))


class ProximityQuery:
    """Closest-point queries on a ``trimesh.Trimesh`` (trimesh's ``mesh.nearest``) through a BVH.

    Args:
        mesh: a ``trimesh.Trimesh``; the BVH is rebuilt when its vertices or faces change.
        device: Warp device; the current default device when ``None``.
        method: the builder (see `hlbvh_warp.api.build`).
    """

    def __init__(self, mesh, device=None, method: str = "hlbvh"):
        _check_mesh(mesh, "ProximityQuery")
        self._rays = RayMeshIntersector(mesh, device=device, method=method)

    @property
    def mesh(self):
        return self._rays.mesh

    @property
    def bvh(self):
        return self._rays.bvh

    def on_surface(self, points):
        """The closest point on the surface to each point, as trimesh's.

        Returns:
            ``closest (m, 3) float64, distance (m,) float64, triangle_id (m,) int64``. Equal
            distances go to the lowest triangle id; a point with a NaN or Inf coordinate gets NaN,
            inf and -1 (trimesh has no answer for one).
        """
        closest, distance, prim = query.closest_point(self.bvh, _real_float64(points, "points"))
        return closest.astype(np.float64), distance.astype(np.float64), prim.astype(np.int64)

    def signed_distance(self, points):
        """Distance to the surface, positive inside the mesh and within 1e-8 (trimesh's
        ``tol.merge``) of the surface, negative outside, decided as trimesh 5.2 decides it.

        Where the point's projection onto its closest triangle's plane falls inside that
        triangle, the triangle's normal gives the sign (so an open mesh has a side); elsewhere, a
        ray-parity test against the whole mesh (`contains_points`). A closest triangle of zero
        area has no normal (trimesh's is zero, its barycentrics NaN): the ray-parity test signs
        those points too, where trimesh multiplies the distance by the sign of zero. A point the
        normal cannot side (exactly in the triangle's plane) goes to the ray-parity test as well.
        The band is taken on the float32 point and mesh this package queries: a float64 point 1e-8
        from the surface may round to either side of it.

        Args:
            points: ``(m, 3)`` points, or a single ``(3,)`` point (answered as ``(1, 3)``, as
                `on_surface` answers it).

        Returns:
            ``(m,) float64``: the unsigned distance of `on_surface` with the sign above, never
            ``-0.0``. A point with a NaN or Inf coordinate gets NaN.
        """
        from trimesh.constants import tol
        from trimesh.triangles import points_to_barycentric

        closest, distance, triangle_id = self.on_surface(points)
        # on_surface checked the shape; a single (3,) point is one row, as its answers are (the
        # (3,) array broadcast against the (1, 3) closest point gave a sign from the wrong axis).
        points = _real_float64(points, "points").reshape(-1, 3)
        distance[triangle_id < 0] = np.nan
        far = np.nonzero((triangle_id >= 0) & (distance > tol.merge))[0]
        if len(far) == 0:
            return distance
        normals = self.mesh.face_normals[triangle_id[far]]
        # A zero-area triangle's normal is zero: its barycentrics are NaN, which no comparison
        # rejects, and the sign of zero would wipe out the distance.
        has_normal = np.einsum("ij,ij->i", normals, normals) > 0.0
        offset = np.einsum("ij,ij->i", points[far] - closest[far], normals)
        projection = points[far] - normals * offset[:, None]
        on_triangle = np.zeros(len(far), dtype=bool)
        if has_normal.any():
            barycentric = points_to_barycentric(self.mesh.triangles[triangle_id[far[has_normal]]],
                                                projection[has_normal])
            on_triangle[has_normal] = ~((barycentric < -tol.merge) | (barycentric > 1 + tol.merge)
                                        | ~np.isfinite(barycentric)).any(axis=1)
        facing = np.einsum("ij,ij->i", normals, points[far] - projection)
        # A point in the triangle's plane (facing 0) has no side by the normal either.
        by_normal = on_triangle & (facing != 0.0)
        # The normal's side is outside: negative there.
        outside = np.zeros(len(far), dtype=bool)
        outside[by_normal] = facing[by_normal] > 0.0
        rest = ~by_normal
        if rest.any():
            outside[rest] = ~self._rays.contains_points(points[far[rest]])
        magnitude = np.abs(distance[far])
        distance[far] = np.where(outside, -magnitude, magnitude)
        return distance

    def vertex(self, points):
        """The nearest vertex to each point: ``distance (m,) float64, vertex_id (m,) int64``.

        trimesh's own (a KD-tree over the vertices, SciPy's; no triangle is involved, so a BVH
        over the faces has nothing to add), here so that this class stands in for every method
        of ``mesh.nearest``. A single ``(3,)`` point is answered as one row, as `on_surface`
        answers it (SciPy's KD-tree alone gave two scalars).
        """
        from trimesh.proximity import ProximityQuery as TrimeshProximity

        points = _real_float64(points, "points")
        if points.shape == (3,):
            points = points.reshape(1, 3)
        return TrimeshProximity(self.mesh).vertex(points)
