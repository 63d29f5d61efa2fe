"""hlbvh_warp: HLBVH (Pantaleoni & Luebke, HPG 2010) built with NVIDIA Warp kernels."""

import os as _os

# The device code lives in the top-level `kernels/` folder and is installed as
# `hlbvh_warp.kernels` (a setuptools package-dir mapping). Run from a source checkout, where
# `python -m` puts the checkout first on sys.path, the folder sits beside this package instead.
_checkout = _os.path.dirname(_os.path.dirname(_os.path.abspath(__file__)))
if not _os.path.isdir(_os.path.join(_os.path.dirname(__file__), "kernels")) and _os.path.isfile(
    _os.path.join(_checkout, "kernels", "__init__.py")
):
    __path__.append(_checkout)  # noqa: F821 (package __path__)

from . import memory, metrics, wide  # noqa: E402  (hb.wide.collapse, hb.metrics.sah_cost: no second import)
from .api import build, build_from_bounds  # noqa: E402
from .builder import Builder  # noqa: E402
from .bvh import Bvh  # noqa: E402
from .collide import intersecting_pairs, overlapping_pairs, triangles_intersect  # noqa: E402
from .config import BuildConfig  # noqa: E402
from .kernels.collide import neighbours_meet, triangles_meet  # noqa: E402  (for user kernels)
from .query import (  # noqa: E402
    BvhView,
    ClosestPoint,
    RayHit,
    TraversalStats,
    bvh_aabb_count,
    bvh_aabb_pairs,
    bvh_any_hit,
    bvh_closest_hit,
    bvh_closest_point,
    bvh_occluded,
    closest_point,
    intersect,
    intersect_all,
    occluded,
    query_aabb,
    view,
)
from .storage import load as load_bvh  # noqa: E402
from .storage import save as save_bvh  # noqa: E402
from .trimesh_adapter import ProximityQuery, RayMeshIntersector  # noqa: E402

__all__ = [
    "memory",
    "metrics",
    "wide",
    "Builder",
    "Bvh",
    "BvhView",
    "BuildConfig",
    "ClosestPoint",
    "ProximityQuery",
    "RayHit",
    "RayMeshIntersector",
    "TraversalStats",
    "build",
    "build_from_bounds",
    "closest_point",
    "bvh_aabb_count",
    "bvh_aabb_pairs",
    "bvh_any_hit",
    "bvh_closest_hit",
    "bvh_closest_point",
    "bvh_occluded",
    "intersect",
    "intersect_all",
    "intersecting_pairs",
    "load_bvh",
    "neighbours_meet",
    "occluded",
    "overlapping_pairs",
    "query_aabb",
    "save_bvh",
    "triangles_intersect",
    "triangles_meet",
    "view",
]
__version__ = "0.1.0"
