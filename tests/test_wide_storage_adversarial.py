"""Adversarial cases of wide trees and of saved trees: crafted files that must be refused, and
every builder's tree answering as the brute force does, collapsed or saved and loaded."""

from __future__ import annotations

import dataclasses
import io
import json
import zipfile

import numpy as np
import pytest
from oracles import brute_force_closest_hit

import hlbvh_warp as hb
from hlbvh_warp.config import BuildConfig


def _sbvh_file(vertices, faces, order, left, right, begin, end, lowers, uppers) -> io.BytesIO:
    """A hand-made spatial-split tree (``prim_order`` lists a triangle twice) in `save_bvh`'s format."""
    left, right = np.asarray(left, np.int32), np.asarray(right, np.int32)
    parent = np.full(len(left), -1, np.int32)
    for node in np.nonzero(left >= 0)[0]:
        parent[left[node]] = parent[right[node]] = node
    meta = {"format": "hlbvh_warp.bvh", "version": 1, "method": "sbvh", "num_prims": len(faces),
            "config": dataclasses.asdict(BuildConfig())}
    file = io.BytesIO()
    np.savez(file, node_left=left, node_right=right, node_parent=parent, node_begin=np.int32(begin),
             node_end=np.int32(end), node_lowers=np.float32(lowers), node_uppers=np.float32(uppers),
             prim_order=np.int32(order), vertices=np.float32(vertices), faces=np.int32(faces),
             meta=np.array(json.dumps(meta)))
    file.seek(0)
    return file


# A thin triangle, 2000 wide and 0.001 high in z (standing in the plane y = 0), and a small one
# far off; one of them is listed twice, which makes the file a spatial-split tree.
_THIN = np.array([[-1000, 0, 0], [1000, 0, 0], [0, 0, 1e-3], [5000, 0, 0], [5001, 0, 0], [5000, 1, 0]], np.float32)
_THIN_FACES = np.array([[0, 1, 2], [3, 4, 5]], np.int32)
_SHORT = 6e-4  # where the crafted boxes stop, 40% below the thin triangle's apex


def _thin_triangle_files():
    """(what, file) pairs whose leaf boxes, and every ancestor's, stop at z = 0.0006 below the
    thin triangle's apex: the once-listed triangle's leaf, or both leaves of a triangle split at
    x = 0. Each loaded when the check allowed a slack of 4 float32 units of a triangle's largest
    coordinate (here 4.8e-4, from x = 1000), and rays through the top of the triangle missed."""
    far_lo, far_hi = [5000, 0, 0], [5001, 1, 0]
    once = _sbvh_file(_THIN, _THIN_FACES, [0, 1, 1], [1, -1, -1], [2, -1, -1], [0, 0, 1], [3, 1, 3],
                      [[-1000, 0, 0], [-1000, 0, 0], far_lo], [[5001, 1, _SHORT], [1000, 0, _SHORT], far_hi])
    split = _sbvh_file(_THIN, _THIN_FACES, [0, 0, 1], [1, 3, -1, -1, -1], [2, 4, -1, -1, -1], [0, 0, 2, 0, 1],
                       [3, 2, 3, 1, 2],
                       [[-1000, 0, 0], [-1000, 0, 0], far_lo, [-1000, 0, 0], [0, 0, 0]],
                       [[5001, 1, _SHORT], [1000, 0, _SHORT], far_hi, [0, 0, _SHORT], [1000, 0, _SHORT]])
    return [("in one leaf only", once), ("in none of the leaves that list it", split)]


@pytest.mark.parametrize("case", [0, 1])
def test_a_spatial_split_file_a_few_units_short_of_its_triangles_is_refused(device, case):
    words, file = _thin_triangle_files()[case]
    # Rays across the top of the thin triangle, above the crafted boxes: the brute force hits it.
    o = np.array([[x, -1.0, z] for x in (-50.0, 10.0, 50.0) for z in (6.5e-4, 9e-4)], np.float32)
    d = np.tile(np.float32([0, 1, 0]), (len(o), 1))
    t_ref, prim_ref = brute_force_closest_hit(_THIN, _THIN_FACES, o, d)
    assert (prim_ref == 0).all() and np.allclose(t_ref, 1.0)
    with pytest.raises(ValueError, match=words):
        hb.load_bvh(file, device=device)


def test_a_built_tree_over_the_thin_triangles_loads_and_answers_right(device):
    # The exact check still takes what the builder writes: its parts' boxes are rounded outward.
    verts = np.concatenate([_THIN, _THIN + np.float32([0, 0, 1e-3])])
    faces = np.concatenate([_THIN_FACES, _THIN_FACES + 6])
    bvh = hb.build(verts, faces, method="sbvh", device=device, config=BuildConfig(sbvh_alpha=0.0))
    file = io.BytesIO()
    hb.save_bvh(bvh, file)
    file.seek(0)
    loaded = hb.load_bvh(file, device=device)
    o = np.array([[x, -1.0, z] for x in (-50.0, 10.0, 50.0) for z in (6.5e-4, 9e-4)], np.float32)
    d = np.tile(np.float32([0, 1, 0]), (len(o), 1))
    t_ref, prim_ref = brute_force_closest_hit(verts, faces, o, d)
    t, prim = hb.intersect(loaded, o, d)
    np.testing.assert_array_equal(prim, prim_ref)
    np.testing.assert_allclose(t, t_ref, rtol=1e-6)


def _box_tree_file(leaf_lowers, leaf_uppers) -> io.BytesIO:
    """A tree over two bare boxes, the first listed twice (one leaf lists it twice, the other once
    beside the second box), its leaves' boxes as given and the root's the union of theirs."""
    lo = np.float32([[0, 0, 0], [5, 5, 5]])
    leaf_lowers, leaf_uppers = np.float32(leaf_lowers), np.float32(leaf_uppers)
    meta = {"format": "hlbvh_warp.bvh", "version": 1, "method": "binned_sah", "num_prims": 2,
            "config": dataclasses.asdict(BuildConfig())}
    file = io.BytesIO()
    np.savez(file, node_left=np.int32([1, -1, -1]), node_right=np.int32([2, -1, -1]),
             node_parent=np.int32([-1, 0, 0]), node_begin=np.int32([0, 0, 2]), node_end=np.int32([4, 2, 4]),
             node_lowers=np.concatenate([leaf_lowers.min(axis=0, keepdims=True), leaf_lowers]),
             node_uppers=np.concatenate([leaf_uppers.max(axis=0, keepdims=True), leaf_uppers]),
             prim_order=np.int32([0, 0, 0, 1]), prim_lowers=lo, prim_uppers=lo + 1, meta=np.array(json.dumps(meta)))
    file.seek(0)
    return file


def test_a_box_tree_listing_a_box_twice_has_its_leaves_checked(device):
    # No triangle to cut, so nothing but whole boxes for the leaves to bound: a file whose leaf
    # box was a point far from the box it lists loaded unchecked (only spatial-split trees over
    # triangles were exempt from the whole-box check, and they are checked point by point).
    good = hb.load_bvh(_box_tree_file([[0, 0, 0], [0, 0, 0]], [[1, 1, 1], [6, 6, 6]]), device=device)
    assert good.num_refs == 4
    with pytest.raises(ValueError, match="a primitive's box is not inside its leaf's"):
        hb.load_bvh(_box_tree_file([[5, 5, 5], [0, 0, 0]], [[5, 5, 5], [6, 6, 6]]), device=device)


def _archive(members: dict) -> io.BytesIO:
    """A zip archive of these raw members (name -> bytes), as a hand-made or damaged .npz."""
    file = io.BytesIO()
    with zipfile.ZipFile(file, "w") as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    file.seek(0)
    return file


def _npy_header(shape) -> bytes:
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<i4", "fortran_order": False, "shape": shape})
    return header.getvalue()


def test_a_member_declaring_more_data_than_it_holds_is_refused_by_name():
    # NumPy allocates what a header declares before reading: 2**44 int32 entries (64 TiB) in a
    # file of a few hundred bytes raised MemoryError, as if the machine were short of memory.
    bomb = _archive({"node_left.npy": _npy_header((2**44,)) + bytes(64)})
    with pytest.raises(ValueError, match="not a saved BVH .*node_left.npy declares 70368744177664 bytes"):
        hb.load_bvh(bomb)
    # One declaring no more than it holds reaches the checks of the arrays as before.
    whole = _archive({"node_left.npy": _npy_header((16,)) + bytes(64)})
    with pytest.raises(ValueError, match="no meta record"):
        hb.load_bvh(whole)


def test_a_member_that_is_no_npy_array_is_refused_by_name():
    # np.load gives a member named without ".npy" as its raw bytes: an AttributeError came out.
    raw = _archive({"meta": b"{}", "node_left": bytes(16)})
    with pytest.raises(ValueError, match="not a saved BVH \\(its member 'meta' is not a NumPy array\\)"):
        hb.load_bvh(raw)
