"""The `Bvh` object itself: its host copy (`to_numpy`) cannot be edited under the queries that read
it, and a tree made by hand from the caller's arrays is checked before any kernel indexes with them."""

from __future__ import annotations

import io

import numpy as np
import pytest
import trimesh
import warp as wp
from oracles import assert_hits_match, brute_force_closest_hit, brute_overlaps, random_rays

import hlbvh_warp as hb
from hlbvh_warp.bvh import NODE_FIELDS
from hlbvh_warp.config import BuildConfig

FIELDS = ("prim_lowers", "prim_uppers", "prim_order") + NODE_FIELDS + ("node_count", "vertices", "faces")


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


def _fields(bvh, **changes) -> dict:
    fields = {name: getattr(bvh, name) for name in FIELDS}
    fields.update(method="by hand", config=bvh.config, device=bvh.device)
    fields.update(changes)
    return fields


def test_a_tree_made_from_valid_arrays_answers_queries(device, rng):
    verts, faces = _mesh()
    for method, config in (("hlbvh", None), ("sbvh", BuildConfig(sbvh_alpha=0.0))):
        built = hb.build(verts, faces, method=method, device=device, config=config)
        extra = {"num_prims": built.num_prims} if built.has_duplicates else {}
        bvh = hb.Bvh(**_fields(built, **extra))
        assert (bvh.num_prims, bvh.num_refs, bvh.num_nodes) == (built.num_prims, built.num_refs, built.num_nodes)
        o, d = random_rays(rng, verts, 200)
        assert_hits_match(*hb.intersect(bvh, o, d), *brute_force_closest_hit(verts, faces, o, d))
    lo = rng.random((300, 3)).astype(np.float32)
    hi = lo + np.float32(0.05)
    boxes = hb.Bvh(**_fields(hb.build_from_bounds(lo, hi, device=device), vertices=None, faces=None))
    counts = hb.query_aabb(boxes, lo[:40], hi[:40])
    np.testing.assert_array_equal(counts, brute_overlaps(lo, hi, lo[:40], hi[:40]).sum(axis=1))


def _int_array(values, device):
    return wp.array(np.asarray(values, dtype=np.int32), dtype=wp.int32, device=device)


def _bad_arguments(bvh, device):
    """(what, changed arguments, words the error must contain): each was taken unchecked, and a
    query on the first one killed the process (a segmentation fault)."""
    arena = bvh.node_left.shape[0]

    def edited(name, index, value):
        a = getattr(bvh, name).numpy().copy()
        a[index] = value
        return wp.array(a, dtype=getattr(bvh, name).dtype, device=device)

    return [
        ("node count past the arena", {"node_count": _int_array([arena + 1000], device)}, "node_count says"),
        ("no nodes in use", {"node_count": _int_array([0], device)}, "node_count says"),
        ("two counts", {"node_count": _int_array([arena, arena], device)}, "one entry"),
        ("child past the arena", {"node_left": edited("node_left", 0, arena + 5)}, "past the last node"),
        ("primitive id past the count", {"prim_order": edited("prim_order", 3, 10**6)}, "outside"),
        ("face index past the vertices", {"faces": edited("faces", (2, 1), 10**6)}, "vertex index outside"),
        ("node arrays of different lengths", {"node_end": bvh.node_end[:-1]}, "one length"),
        ("fewer primitive boxes", {"prim_lowers": bvh.prim_lowers[:-1]}, "prim_lowers has"),
        ("float ids", {"node_left": wp.array(bvh.node_left.numpy().astype(np.float32), device=device)},
         "node_left must be a 1-D array of int32"),
        ("NumPy array", {"node_right": bvh.node_right.numpy()}, "node_right must be a warp array"),
        ("vertices without faces", {"faces": None}, "vertices and faces"),
        ("faces flat", {"faces": wp.array(bvh.faces.numpy().ravel(), dtype=wp.int32, device=device)}, "faces must"),
        ("num_prims a bool", {"num_prims": True}, "num_prims must be an integer"),
        ("num_prims past prim_order", {"num_prims": bvh.num_prims + 1}, "prim_order has"),
        ("method not a name", {"method": 3}, "method must be a string"),
        ("config not a BuildConfig", {"config": {"max_leaf_size": 1}}, "config must be a BuildConfig"),
    ]


def test_a_tree_made_from_bad_arrays_is_refused_by_name(device):
    verts, faces = _mesh()
    bvh = hb.build(verts, faces, device=device)
    hb.Bvh(**_fields(bvh))  # the unchanged arguments make a tree
    for what, changes, words in _bad_arguments(bvh, device):
        with pytest.raises(ValueError, match=words):
            hb.Bvh(**_fields(bvh, **changes))
        # Nothing of the refused tree reached the built one.
        assert bvh.num_nodes == 2 * len(faces) - 1, what


def test_a_mesh_tree_whose_boxes_are_not_its_triangles_is_refused(device, rng):
    # Vertices moved off the primitive boxes the tree was built over: load_bvh derives those boxes
    # from the triangles and refuses such a tree, but Bvh(...) checked the boxes it was handed,
    # took it, and every ray then missed the triangles outside their leaves' boxes.
    verts, faces = _mesh()
    bvh = hb.build(verts, faces, device=device)
    moved = wp.array(verts + np.float32(10.0), dtype=wp.vec3, device=device)
    with pytest.raises(ValueError, match="not the boxes of its triangles"):
        hb.Bvh(**_fields(bvh, vertices=moved))
    # One primitive box grown past its triangle's (still inside its leaf) is refused too: box
    # queries read these boxes and would report the triangle where it is not.
    lowers = bvh.prim_lowers.numpy().copy()
    leaf = int(np.nonzero(bvh.to_numpy()["node_left"] < 0)[0][0])
    prim = int(bvh.to_numpy()["prim_order"][bvh.to_numpy()["node_begin"][leaf]])
    lowers[prim] = bvh.to_numpy()["node_lowers"][0]
    with pytest.raises(ValueError, match="not the boxes of its triangles"):
        hb.Bvh(**_fields(bvh, prim_lowers=wp.array(lowers, dtype=wp.vec3, device=device)))
    # The same tree over its own triangles is taken, and answers as the brute force.
    o, d = random_rays(rng, verts, 100)
    assert_hits_match(*hb.intersect(hb.Bvh(**_fields(bvh)), o, d), *brute_force_closest_hit(verts, faces, o, d))


@pytest.mark.skipif(not wp.get_cuda_device_count(), reason="needs a second device (CUDA) to mix")
def test_arrays_on_another_device_are_refused():
    verts, faces = _mesh()
    bvh = hb.build(verts, faces, device="cpu")
    on_gpu = wp.array(bvh.node_left.numpy(), dtype=wp.int32, device="cuda:0")
    with pytest.raises(ValueError, match="node_left is on cuda:0"):
        hb.Bvh(**_fields(bvh, node_left=on_gpu))
