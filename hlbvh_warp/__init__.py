"""hlbvh_warp: HLBVH (Pantaleoni & Luebke, HPG 2010) built with NVIDIA Warp kernels."""

import warp as wp

from .api import build, build_from_bounds
from .query import intersect
from .bvh import Bvh
from .config import BuildConfig

__all__ = ["Bvh", "BuildConfig", "build", "build_from_bounds", "intersect"]
__version__ = "0.1.0"
