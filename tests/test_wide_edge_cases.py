"""Wide BVHs (`hlbvh_warp.wide`) and updates of their binary tree: a wide host call waits for one in progress."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

import hlbvh_warp as hb
from hlbvh_warp import wide


def _soup(rng, n=40):
    vertices = (rng.random((3 * n, 3)) * 2.0 - 1.0).astype(np.float32)
    return vertices, np.arange(3 * n, dtype=np.int32).reshape(n, 3)


@pytest.mark.parametrize("width", [4, 8, 16])
def test_wide_queries_wait_for_an_update_of_their_binary_tree(device, rng, width):
    # A wide tree reads its binary tree's prim_order and packed triangles, which a Builder's update
    # rewrites in place. The binary queries wait for an update in progress (`Bvh.hold`); the wide
    # ones checked the tree's generation once and then launched on it, so a wide query that
    # overlapped an update read a half-written tree instead of waiting and refusing the stale
    # wide tree. Here another thread holds the tree as an update does and updates it before it
    # lets go: the wide query must wait, then refuse.
    vertices, faces = _soup(rng)
    builder = hb.Builder(len(faces), device=device)
    builder.build(vertices, faces)
    w = wide.collapse(builder.bvh, width)
    origins = np.array([[0.0, 0.0, -5.0]], np.float32)
    directions = np.array([[0.0, 0.0, 1.0]], np.float32)
    holding = threading.Event()

    def update():
        with builder.bvh.hold():
            holding.set()
            time.sleep(0.3)
            builder.update(vertices[::-1].copy())

    worker = threading.Thread(target=update)
    worker.start()
    try:
        assert holding.wait(10.0)
        for call in (lambda: wide.intersect(w, origins, directions), lambda: wide.sah_cost(w)):
            with pytest.raises(ValueError, match="collapse it again"):
                call()
    finally:
        worker.join()
