"""Morton codes on the host (NumPy), for ordering batches: a query batch before its launch
(`query.closest_point`) and the triangles of a brute-force reference (`reference`). The build's own
codes are computed on the device (``kernels/morton.py``)."""

from __future__ import annotations

import numpy as np

#: The code of a point with a NaN or Inf coordinate: after every 30-bit code.
INVALID_CODE = 1 << 33


def spread_bits(x: np.ndarray) -> np.ndarray:
    """10-bit integers with two zero bits after each bit (the Morton interleave of one axis)."""
    x = np.asarray(x).astype(np.int64) & 0x3FF
    x = (x | (x << 16)) & 0x30000FF
    x = (x | (x << 8)) & 0x300F00F
    x = (x | (x << 4)) & 0x30C30C3
    return (x | (x << 2)) & 0x9249249


def morton_codes(points: np.ndarray) -> np.ndarray:
    """30-bit Morton codes (Morton 1966) of the points over their bounding box (10 bits per axis), as int64;
    `INVALID_CODE` for a point with a NaN or Inf coordinate."""
    finite = np.isfinite(points).all(axis=1)
    codes = np.full(points.shape[0], INVALID_CODE, dtype=np.int64)
    if finite.any():
        pts = points[finite].astype(np.float64)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        extent = np.where(hi > lo, hi - lo, 1.0)
        cells = np.clip(((pts - lo) / extent * 1024.0).astype(np.int64), 0, 1023)
        codes[finite] = (spread_bits(cells[:, 0]) << 2) | (spread_bits(cells[:, 1]) << 1) | spread_bits(cells[:, 2])
    return codes


def morton_order(points: np.ndarray) -> np.ndarray:
    """The stable permutation that puts the points in Morton order (invalid points last)."""
    return np.argsort(morton_codes(points), kind="stable")
