"""The `Bvh` object itself: its host copy (`to_numpy`) cannot be edited under the queries that read it."""

from __future__ import annotations

import io

import numpy as np
import pytest
import trimesh

import hlbvh_warp as hb
from hlbvh_warp.bvh import NODE_FIELDS


def _mesh():
    mesh = trimesh.creation.icosphere(subdivisions=2)
    return np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)


def _device_tree(bvh) -> dict:
    """The tree's used arrays read straight from the device, not through `to_numpy`."""
    n = int(bvh.node_count.numpy()[0])
    tree = {name: getattr(bvh, name).numpy()[:n].copy() for name in NODE_FIELDS}
    tree.update({name: getattr(bvh, name).numpy().copy() for name in ("prim_order", "prim_lowers", "prim_uppers")})
    return tree


def _oracle_depth(parent: np.ndarray) -> int:
    depth = 0
    for node in range(len(parent)):
        steps = 0
        while parent[node] >= 0:
            node, steps = parent[node], steps + 1
        depth = max(depth, steps)
    return depth


def test_to_numpy_arrays_cannot_be_edited_under_the_tree(device):
    # The cached dict was handed out itself: sorting prim_order or scaling node_lowers in the
    # caller's "copy" changed what num_leaves, depth and save_bvh read (save then wrote a file
    # load_bvh refused).
    verts, faces = _mesh()
    bvh = hb.build(verts, faces, device=device)
    expected = _device_tree(bvh)
    tree = bvh.to_numpy()
    edits = [lambda: tree["prim_order"].sort(), lambda: tree["node_lowers"].__imul__(2.0),
             lambda: tree["node_left"].__setitem__(0, -1), lambda: tree["prim_lowers"].fill(0.0)]
    for edit in edits:
        with pytest.raises(ValueError, match="read-only"):
            edit()
    with pytest.raises(ValueError):
        tree["node_lowers"].flags.writeable = True
    del tree["node_left"]  # the dict is the caller's own
    tree = bvh.to_numpy()
    for name, array in expected.items():
        np.testing.assert_array_equal(tree[name], array, err_msg=name)
    copied = tree["prim_order"].copy()  # a copy edits freely
    copied.sort()
    np.testing.assert_array_equal(bvh.to_numpy()["prim_order"], expected["prim_order"])
    # What reads the host copy still sees the tree on the device.
    assert bvh.num_leaves == int((expected["node_left"] < 0).sum())
    assert bvh.depth == _oracle_depth(expected["node_parent"])
    buffer = io.BytesIO()
    hb.save_bvh(bvh, buffer)
    buffer.seek(0)
    loaded = hb.load_bvh(buffer, device=device).to_numpy()
    for name, array in expected.items():
        np.testing.assert_array_equal(loaded[name], array, err_msg=name)
