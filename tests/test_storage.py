"""Saved and loaded BVHs: the same tree back, queries against the brute force, and every corrupted
file refused with a ValueError naming the problem (a bad id would send the traversal out of bounds)."""

from __future__ import annotations

import io
import json
import os
import zipfile

import numpy as np
import pytest
import trimesh
import warp as wp
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from oracles import assert_hits_match, brute_force_closest_hit, brute_overlaps, check_tree_invariants, random_rays

import hlbvh_warp as hb
from hlbvh_warp import metrics, storage
from hlbvh_warp.bvh import NODE_FIELDS
from hlbvh_warp.config import BuildConfig


def _mesh():
    mesh = trimesh.creation.icosphere(subdivisions=2)
    box = trimesh.creation.box(extents=(0.4, 0.4, 0.4)).apply_translation((1.5, 0, 0))
    mesh = trimesh.util.concatenate([mesh, box])
    return np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)


@pytest.mark.parametrize("method, config", [("hlbvh", None), ("sweep_sah", BuildConfig(max_leaf_size=4)),
                                            ("sbvh", BuildConfig(sbvh_alpha=0.0, morton_bounds=((-2, -2, -2),
                                                                                                (2, 2, 2))))])
def test_a_mesh_tree_comes_back_the_same(device, rng, tmp_path, method, config):
    verts, faces = _mesh()
    bvh = hb.build(verts, faces, method=method, device=device, config=config)
    path = tmp_path / "tree.npz"
    hb.save_bvh(bvh, path)
    loaded = hb.load_bvh(path, device=device)
    before, after = bvh.to_numpy(), loaded.to_numpy()
    for name in NODE_FIELDS + ("prim_order", "prim_lowers", "prim_uppers"):
        np.testing.assert_array_equal(after[name], before[name], err_msg=name)
    assert (loaded.method, loaded.config, loaded.num_prims, loaded.num_refs) == \
        (method, bvh.config, bvh.num_prims, bvh.num_refs)
    np.testing.assert_array_equal(loaded.vertices.numpy(), verts)
    np.testing.assert_array_equal(loaded.faces.numpy(), faces)
    if method != "sbvh":
        check_tree_invariants(after, len(faces), max_leaf_size=bvh.config.max_leaf_size)
    else:
        assert loaded.has_duplicates
    o, d = random_rays(rng, verts, 300)
    t, prim = hb.intersect(loaded, o, d)
    assert_hits_match(t, prim, *brute_force_closest_hit(verts, faces, o, d))
    assert metrics.sah_cost(loaded) == metrics.sah_cost(bvh)


def test_a_box_tree_comes_back_the_same(device, rng, tmp_path):
    lo = rng.random((400, 3)).astype(np.float32)
    hi = lo + np.float32(0.05)
    bvh = hb.build_from_bounds(lo, hi, method="binned_sah", device=device)
    hb.save_bvh(bvh, tmp_path / "boxes")  # NumPy adds .npz
    loaded = hb.load_bvh(tmp_path / "boxes.npz", device=device)
    # The name it was saved under finds the file too, as str, path or bytes.
    for name in (str(tmp_path / "boxes"), tmp_path / "boxes", os.fsencode(tmp_path / "boxes"),
                 os.fsencode(tmp_path / "boxes.npz")):
        np.testing.assert_array_equal(hb.load_bvh(name, device=device).to_numpy()["node_left"],
                                      loaded.to_numpy()["node_left"])
    # Where a file sits at the name itself, that file is the one read, not the .npz beside it.
    other = hb.build_from_bounds(lo[:10], hi[:10], device=device)
    hb.save_bvh(other, tmp_path / "ten")
    os.replace(tmp_path / "ten.npz", tmp_path / "boxes")
    assert hb.load_bvh(tmp_path / "boxes", device=device).num_prims == 10
    assert loaded.vertices is None and loaded.faces is None
    np.testing.assert_array_equal(loaded.to_numpy()["prim_lowers"], lo)
    q_lo, q_hi = lo[:50] - 0.01, hi[:50] + 0.01
    counts, pairs = hb.query_aabb(loaded, q_lo, q_hi, return_pairs=True)
    assert np.array_equal(counts, brute_overlaps(lo, hi, q_lo, q_hi).sum(axis=1))
    ref_counts, ref_pairs = hb.query_aabb(bvh, q_lo, q_hi, return_pairs=True)
    assert np.array_equal(pairs, ref_pairs)


def _saved(tmp_path, device):
    verts, faces = _mesh()
    path = tmp_path / "tree.npz"
    hb.save_bvh(hb.build(verts, faces, device=device, config=BuildConfig(max_leaf_size=2)), path)
    with np.load(path) as data:
        return {name: data[name].copy() for name in data.files}


def _write(tmp_path, arrays, name="bad.npz"):
    path = tmp_path / name
    np.savez(path, **arrays)
    return path


def _meta(arrays, **changes):
    meta = json.loads(str(arrays["meta"]))
    meta.update(changes)
    return np.array(json.dumps(meta))


def _interior(arrays):
    return np.nonzero(arrays["node_left"] >= 0)[0]


def _leaves(arrays):
    return np.nonzero(arrays["node_left"] < 0)[0]


def _corruptions(arrays):
    """(what, changed arrays, words the error must contain) for each way a file can be wrong."""
    i = _interior(arrays)[3]
    leaf = _leaves(arrays)[5]
    n = len(arrays["node_left"])

    def changed(name, index, value):
        a = {k: v.copy() for k, v in arrays.items()}
        a[name][index] = value
        return a

    def without(name):
        return {k: v for k, v in arrays.items() if k != name}

    swapped = {k: v.copy() for k, v in arrays.items()}
    swapped["node_left"][i], swapped["node_right"][i] = arrays["node_right"][i], arrays["node_left"][i]
    other = _interior(arrays)[4]
    stolen = changed("node_left", other, arrays["node_left"][i])
    return [
        ("child past the last node", changed("node_left", i, n), "past the last node"),
        ("child before its parent", changed("node_right", i, 0), "not after its parent"),
        ("one child only", changed("node_right", i, -1), "exactly one child"),
        ("child id below -1", changed("node_left", leaf, -7), "exactly one child"),
        ("a node with two parents", stolen, "exactly one node"),
        ("parent link", changed("node_parent", leaf, 0), "node_parent"),
        ("children swapped (ranges no longer side by side)", swapped, "side by side"),
        ("range end", changed("node_end", leaf, arrays["node_end"][leaf] + 1), "side by side"),
        ("empty range", changed("node_end", leaf, arrays["node_begin"][leaf]), "non-empty"),
        ("root range", changed("node_end", 0, len(arrays["prim_order"]) + 1), "root"),
        ("primitive id", changed("prim_order", 7, 10**6), "outside"),
        ("negative primitive id", changed("prim_order", 7, -1), "outside"),
        ("primitive listed twice", changed("prim_order", 7, arrays["prim_order"][8]), "in no leaf"),
        ("NaN node box", changed("node_lowers", leaf, np.nan), "finite"),
        ("inverted node box", changed("node_lowers", leaf, arrays["node_uppers"][leaf] + 1), "lowers <= uppers"),
        ("child outside its parent", changed("node_uppers", leaf, arrays["node_uppers"][0] + 1), "inside its parent"),
        ("leaf too small for its triangles", changed("node_uppers", leaf, arrays["node_lowers"][leaf]),
         "inside its leaf"),
        ("face index", changed("faces", 3, [0, 1, 10**6]), "out of range"),
        ("NaN vertex", changed("vertices", 3, np.nan), "NaN or Inf"),
        ("fewer faces", {**arrays, "faces": arrays["faces"][:-1]}, "rows for"),
        ("node arrays of different lengths", {**arrays, "node_end": arrays["node_end"][:-1]}, "differ in length"),
        ("float ids", {**arrays, "node_left": arrays["node_left"].astype(np.float32)}, "node_left"),
        ("ids past int32", {**arrays, "prim_order": arrays["prim_order"].astype(np.int64) + (1 << 32)}, "int32"),
        ("2-D boxes", {**arrays, "node_lowers": arrays["node_lowers"][:, :2]}, "node_lowers"),
        ("missing array", without("node_begin"), "no node_begin"),
        ("missing meta", without("meta"), "no meta"),
        ("other format", {**arrays, "meta": _meta(arrays, format="something")}, "another format"),
        ("newer version", {**arrays, "meta": _meta(arrays, version=99)}, "version 99"),
        ("unknown config field", {**arrays, "meta": _meta(arrays, config={"bogus": 1})}, "bogus"),
        ("bad config value", {**arrays, "meta": _meta(arrays, config={"bits_per_axis": 99})}, "bits_per_axis"),
        ("bad primitive count", {**arrays, "meta": _meta(arrays, num_prims=0)}, "num_prims"),
        ("meta not JSON", {**arrays, "meta": np.array("{")}, "JSON"),
    ]


def test_a_nan_in_a_vertex_no_face_uses_saves_and_loads(device, rng):
    # A Builder frame given as a Warp array is not checked: a NaN in a vertex no face uses left a
    # right tree that save_bvh wrote and load_bvh refused ("vertices has a NaN or Inf coordinate").
    verts, faces = _mesh()
    verts = np.concatenate([verts, [[7, 7, 7], [8, 8, 8]]]).astype(np.float32)
    builder = hb.Builder(len(faces), device=device)
    builder.build(verts, faces)
    frame = verts.copy()
    frame[-2, 1], frame[-1, 0] = np.nan, np.inf
    builder.update(wp.array(frame, dtype=wp.vec3, device=device))
    buffer = io.BytesIO()
    hb.save_bvh(builder.bvh, buffer)
    buffer.seek(0)
    loaded = hb.load_bvh(buffer, device=device)
    np.testing.assert_array_equal(loaded.vertices.numpy(), frame)  # kept as written, NaN and Inf too
    o, d = random_rays(rng, verts[:-2], 200)
    t, prim = hb.intersect(loaded, o, d)
    assert_hits_match(t, prim, *brute_force_closest_hit(verts[:-2], faces, o, d))
    # A NaN in a vertex a face uses is still refused by name.
    buffer.seek(0)
    with np.load(buffer) as data:
        arrays = {name: data[name].copy() for name in data.files}
    arrays["vertices"][5, 0] = np.nan
    edited = io.BytesIO()
    np.savez(edited, **arrays)
    edited.seek(0)
    with pytest.raises(ValueError, match=r"NaN or Inf coordinate \(first at row 5"):
        hb.load_bvh(edited, device=device)


def test_save_refuses_a_tree_load_would_refuse(device, tmp_path):
    # A NaN in a triangle's vertex (or in a box) from an unchecked Warp frame: save_bvh wrote the
    # file, and load_bvh refused it ("vertices has a NaN or Inf coordinate", "the primitive boxes
    # must be finite").
    verts, faces = _mesh()
    builder = hb.Builder(len(faces), device=device)
    builder.build(verts, faces)
    frame = verts.copy()
    frame[faces[7, 1], 2] = np.nan
    builder.update(wp.array(frame, dtype=wp.vec3, device=device))
    first = int(np.nonzero((faces == faces[7, 1]).any(axis=1))[0][0])
    with pytest.raises(ValueError, match=f"finite triangles: face {first} has a NaN"):
        hb.save_bvh(builder.bvh, tmp_path / "nan.npz")
    assert not (tmp_path / "nan.npz").exists()
    lo = np.zeros((5, 3), np.float32)
    boxes = hb.Builder(5, device=device)
    boxes.build_from_bounds(lo, lo + 1)
    lo[2, 0] = np.inf
    boxes.update(bounds=(wp.array(lo, dtype=wp.vec3, device=device), wp.array(lo + 1, dtype=wp.vec3, device=device)))
    with pytest.raises(ValueError, match="finite boxes"):
        hb.save_bvh(boxes.bvh, io.BytesIO())


def test_every_corrupted_file_is_refused_by_name(device, tmp_path):
    arrays = _saved(tmp_path, device)
    hb.load_bvh(_write(tmp_path, arrays, "good.npz"), device=device)  # the unchanged file loads
    for what, bad, words in _corruptions(arrays):
        path = _write(tmp_path, bad)
        with pytest.raises(ValueError, match=words) as error:
            hb.load_bvh(path, device=device)
        assert str(path) in str(error.value), what


def test_a_spatial_split_file_whose_leaves_miss_their_triangles_is_refused(device, rng, tmp_path):
    # Such a tree's leaves bound parts of triangles, so the whole-box check above does not apply;
    # a file with every leaf box shrunk to a point loaded, and every ray then missed.
    c = rng.uniform(0.0, 1.0, (120, 1, 3))
    tris = np.concatenate([c + 0.03 * rng.normal(size=(120, 3, 3)), rng.uniform(0.0, 1.0, (8, 3, 3))])
    verts = tris.reshape(-1, 3).astype(np.float32)
    faces = np.arange(len(verts), dtype=np.int32).reshape(-1, 3)
    bvh = hb.build(verts, faces, method="sbvh", device=device, config=BuildConfig(sbvh_alpha=0.0))
    assert bvh.has_duplicates
    path = tmp_path / "sbvh.npz"
    hb.save_bvh(bvh, path)
    with np.load(path) as data:
        arrays = {name: data[name].copy() for name in data.files}
    hb.load_bvh(_write(tmp_path, arrays, "good.npz"), device=device)
    leaves = _leaves(arrays)
    counts = np.bincount(arrays["prim_order"])
    ends = arrays["node_end"][leaves]
    begins = arrays["node_begin"][leaves]
    # A leaf listing only triangles that other leaves list too, and one listing a triangle no other does.
    split_only = next(f for f, b, e in zip(leaves, begins, ends) if (counts[arrays["prim_order"][b:e]] > 1).all())
    has_whole = next(f for f, b, e in zip(leaves, begins, ends) if (counts[arrays["prim_order"][b:e]] == 1).any())
    for leaf, words in ((split_only, "none of the leaves that list it"), (has_whole, "in one leaf only")):
        bad = {k: v.copy() for k, v in arrays.items()}
        bad["node_uppers"][leaf] = bad["node_lowers"][leaf]
        with pytest.raises(ValueError, match=words):
            hb.load_bvh(_write(tmp_path, bad), device=device)


def test_files_that_are_no_saved_tree(tmp_path):
    text = tmp_path / "text.npz"
    text.write_text("not a zip")
    with pytest.raises(ValueError, match="not a saved BVH \\(not an .npz archive\\)"):  # not "pickled data"
        hb.load_bvh(text)
    pickled = tmp_path / "pickled.npz"
    np.savez(pickled, meta=np.array([{"format": storage.FORMAT}], dtype=object))
    with pytest.raises(ValueError, match="not a saved BVH"):  # never unpickled
        hb.load_bvh(pickled)
    truncated = tmp_path / "truncated.npz"
    good = tmp_path / "good.npz"
    hb.save_bvh(hb.build(*_mesh(), device="cpu"), good)
    truncated.write_bytes(good.read_bytes()[:200])
    with pytest.raises(ValueError, match="not a saved BVH"):
        hb.load_bvh(truncated)
    assert zipfile.is_zipfile(good)
    with pytest.raises(FileNotFoundError):
        hb.load_bvh(tmp_path / "absent.npz")
    with pytest.raises(ValueError, match="takes a Bvh"):
        hb.save_bvh("tree", tmp_path / "x.npz")


_SAVED: dict = {}


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(field=st.sampled_from(["node_left", "node_right", "node_parent", "node_begin", "node_end", "prim_order"]),
       position=st.integers(0, 10**6), value=st.integers(-3, 1200))
def test_a_loaded_tree_is_refused_or_answers_right(tmp_path, field, position, value):
    """One integer of the file changed at random: either the load names a problem, or the tree is
    a valid one (the change kept it consistent) and its rays match the brute force."""
    if "arrays" not in _SAVED:  # one build for every example
        _SAVED["arrays"] = _saved(tmp_path, "cpu")
    arrays = _SAVED["arrays"]
    bad = {k: v.copy() for k, v in arrays.items()}
    bad[field][position % len(bad[field])] = value
    path = _write(tmp_path, bad)
    try:
        tree = hb.load_bvh(path, device="cpu")
    except ValueError:
        return
    verts, faces = arrays["vertices"], arrays["faces"]
    o, d = random_rays(np.random.default_rng(position), verts, 64)
    t, prim = hb.intersect(tree, o, d)
    assert_hits_match(t, prim, *brute_force_closest_hit(verts, faces, o, d))



def test_a_damaged_compressed_file_is_a_value_error(device, tmp_path):
    # A flipped byte inside a compressed member raised zlib.error (and a damaged .npy header
    # tokenize.TokenError) through load_bvh, past the ValueError it promises.
    verts, faces = _mesh()
    path = tmp_path / "tree.npz"
    hb.save_bvh(hb.build(verts, faces, device=device), path, compressed=True)
    data = path.read_bytes()
    kinds = set()
    for position in np.linspace(40, len(data) - 40, 60).astype(int):
        damaged = bytearray(data)
        damaged[position] ^= 0xFF
        bad = tmp_path / "damaged.npz"
        bad.write_bytes(bytes(damaged))
        try:
            hb.load_bvh(bad, device=device)
        except ValueError as error:
            kinds.add(str(error).split("(")[1].split(":")[0] if "not a saved BVH (" in str(error) else "checked")
        # Anything else escapes and fails the test; a file that still loads passed every check.
    assert kinds, "no damage was noticed at all"


def test_save_replaces_the_file_whole_or_not_at_all(device, tmp_path, monkeypatch):
    # Written in place, a file being saved could be read half written (by another thread or
    # process); it is written beside and renamed over the old one now.
    verts, faces = _mesh()
    path = tmp_path / "tree.npz"
    first = hb.build(verts, faces, device=device)
    hb.save_bvh(first, path)
    before = path.read_bytes()

    def failing_savez(file, **arrays):
        file.write(b"PK\x03\x04 half a file")
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", failing_savez)
    with pytest.raises(OSError, match="disk full"):
        hb.save_bvh(hb.build(verts * np.float32(2.0), faces, device=device), path)
    monkeypatch.undo()
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["tree.npz"]
    hb.save_bvh(first, tmp_path / "named")  # NumPy's suffix, as before
    assert hb.load_bvh(tmp_path / "named.npz", device=device).num_prims == len(faces)



@pytest.mark.parametrize("compressed", [False, True])
def test_open_files_and_buffers_as_numpy_takes_them(device, rng, tmp_path, compressed):
    """save_bvh writes to an open binary file or an in-memory buffer (as np.savez does), and
    load_bvh reads from one, with the same checks as from a path."""
    import io

    verts, faces = _mesh()
    bvh = hb.build(verts, faces, device=device)
    buffer = io.BytesIO()
    hb.save_bvh(bvh, buffer, compressed=compressed)
    buffer.seek(0)
    from_buffer = hb.load_bvh(buffer, device=device)
    with open(tmp_path / "tree.npz", "wb") as file:
        hb.save_bvh(bvh, file, compressed=compressed)
    with open(tmp_path / "tree.npz", "rb") as file:
        from_file = hb.load_bvh(file, device=device)
    for loaded in (from_buffer, from_file):
        for name in NODE_FIELDS + ("prim_order",):
            np.testing.assert_array_equal(loaded.to_numpy()[name], bvh.to_numpy()[name], err_msg=name)
    o, d = random_rays(rng, verts, 200)
    assert_hits_match(*hb.intersect(from_buffer, o, d), *brute_force_closest_hit(verts, faces, o, d))
    # Damage is refused by name from a buffer too, the buffer's own name when it has one.
    with pytest.raises(ValueError, match="<file object>: not a saved BVH"):
        hb.load_bvh(io.BytesIO(b"not a zip at all"), device=device)
    arrays = {name: np.asarray(value) for name, value in np.load(tmp_path / "tree.npz").items()}
    arrays["node_left"][0] = len(arrays["node_left"]) + 5
    damaged = io.BytesIO()
    np.savez(damaged, **arrays)
    damaged.seek(0)
    with pytest.raises(ValueError, match="<file object>: a child id"):
        hb.load_bvh(damaged, device=device)
    with open(tmp_path / "tree.npz", "rb") as file:
        file.read(1)  # not at the archive's start
        with pytest.raises(ValueError, match="tree.npz: not a saved BVH"):
            hb.load_bvh(file, device=device)


def test_saving_into_a_missing_folder_names_the_path_asked_for(device, tmp_path):
    # The error named the temporary file written beside the target.
    verts, faces = _mesh()
    bvh = hb.build(verts, faces, device=device)
    with pytest.raises(FileNotFoundError, match=r"cannot write .*missing.tree\.npz") as error:
        hb.save_bvh(bvh, tmp_path / "missing" / "tree")
    assert ".partial" not in str(error.value)
    assert list(tmp_path.iterdir()) == []


def test_text_files_bytes_and_descriptors_are_named_as_such(device, tmp_path):
    """Text-mode files failed half way inside NumPy (save left an empty file); an archive's bytes
    passed as a path put the whole archive in the message; a file opened from a descriptor was
    named by its number."""
    import io

    verts, faces = _mesh()
    bvh = hb.build(verts, faces, device=device)
    with open(tmp_path / "text.npz", "w") as file:
        with pytest.raises(ValueError, match="binary mode"):
            hb.save_bvh(bvh, file)
    assert (tmp_path / "text.npz").read_bytes() == b""
    with pytest.raises(ValueError, match="binary mode"):
        hb.save_bvh(bvh, io.StringIO())
    hb.save_bvh(bvh, os.fsencode(tmp_path / "tree"))  # a bytes path, as load takes
    for encoding in ("utf-8", "latin-1"):
        with open(tmp_path / "tree.npz", encoding=encoding) as file:
            with pytest.raises(ValueError, match="binary mode"):
                hb.load_bvh(file, device=device)
    data = (tmp_path / "tree.npz").read_bytes()
    for data_form in (data, bytearray(data), memoryview(data)):
        with pytest.raises(ValueError, match=r"bytes of data: wrap them in io\.BytesIO") as error:
            hb.load_bvh(data_form, device=device)
        assert len(str(error.value)) < 200
    with pytest.raises(ValueError, match="writes to a path or an open binary file"):
        hb.save_bvh(bvh, 42)
    descriptor = os.open(tmp_path / "text.npz", os.O_RDONLY)
    with open(descriptor, "rb") as file:
        with pytest.raises(ValueError, match="^<file object>: not a saved BVH"):
            hb.load_bvh(file, device=device)
    assert hb.load_bvh(os.fsencode(tmp_path / "tree"), device=device).num_prims == len(faces)


def test_save_errors_name_the_path_as_given(device, tmp_path, monkeypatch):
    # Not the temporary file beside it, and not the path with its links resolved.
    verts, faces = _mesh()
    bvh = hb.build(verts, faces, device=device)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "link").symlink_to(tmp_path)
    for asked in ("missing/tree.npz", str(tmp_path / "link" / "missing" / "tree.npz")):
        with pytest.raises(FileNotFoundError) as error:
            hb.save_bvh(bvh, asked)
        assert f"cannot write {asked}:" in str(error.value)
    # The rename fails (a folder sits at the name): named, and nothing left beside it.
    (tmp_path / "folder.npz").mkdir()
    with pytest.raises(OSError, match="cannot write folder.npz") as error:
        hb.save_bvh(bvh, "folder")
    assert ".partial" not in str(error.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["folder.npz", "link"]

def test_save_through_a_link_keeps_the_link_and_the_files_permissions(device, tmp_path):
    # Renaming a new file over the path replaced a symbolic link with a plain file (its target
    # unchanged) and gave a private file the default permissions.
    verts, faces = _mesh()
    bvh = hb.build(verts, faces, device=device)
    target = tmp_path / "target.npz"
    hb.save_bvh(bvh, target)
    target.chmod(0o600)
    link = tmp_path / "link.npz"
    link.symlink_to(target)
    hb.save_bvh(hb.build(verts * np.float32(2.0), faces, device=device), link)
    assert link.is_symlink() and (target.stat().st_mode & 0o777) == 0o600
    np.testing.assert_array_equal(hb.load_bvh(target, device=device).vertices.numpy(), verts * np.float32(2.0))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.npz", "target.npz"]
    long_name = tmp_path / ("t" * 240 + ".npz")  # the temporary name is short, whatever the target's
    hb.save_bvh(bvh, long_name)
    assert hb.load_bvh(long_name, device=device).num_prims == len(faces)


# ----------------------------------------------------------------- pinned by the second mutation audit
def _arrays_of(bvh, tmp_path):
    path = tmp_path / "source.npz"
    hb.save_bvh(bvh, path)
    with np.load(path) as data:
        return {name: data[name].copy() for name in data.files}


def _sbvh_arrays(tmp_path, device, leaf=1):
    rng = np.random.default_rng(1)
    c = rng.uniform(0.0, 1.0, (120, 1, 3))
    tris = np.concatenate([c + 0.03 * rng.normal(size=(120, 3, 3)), rng.uniform(0.0, 1.0, (8, 3, 3))])
    verts = tris.reshape(-1, 3).astype(np.float32)
    faces = np.arange(len(verts), dtype=np.int32).reshape(-1, 3)
    bvh = hb.build(verts, faces, method="sbvh", device=device, config=BuildConfig(sbvh_alpha=0.0, max_leaf_size=leaf))
    assert bvh.has_duplicates
    return _arrays_of(bvh, tmp_path)


def _whole_triangle_leaf(arrays):
    """A leaf of a spatial-split tree listing only triangles no other leaf lists."""
    order, counts = arrays["prim_order"], np.bincount(arrays["prim_order"])
    return next(int(f) for f in _leaves(arrays)
                if (counts[order[arrays["node_begin"][f]:arrays["node_end"][f]]] == 1).all())


def _more_corruptions(tmp_path, device):
    """(what, arrays) for checks of box trees and spatial-split trees the mesh file above cannot
    reach; each such file loaded (queries then missed boxes or triangles) or raised another error
    when its check was taken out."""
    rng = np.random.default_rng(2)
    lo = rng.random((64, 3)).astype(np.float32)
    boxes = _arrays_of(hb.build_from_bounds(lo, lo + np.float32(0.05), method="binned_sah", device=device), tmp_path)
    out = []

    def box_case(what, edit):
        a = {k: v.copy() for k, v in boxes.items()}
        edit(a)
        out.append((what, a))

    leaf = next(int(f) for f in _leaves(boxes) if boxes["node_parent"][f] > 0)
    prim = int(boxes["prim_order"][boxes["node_begin"][leaf]])
    outside = np.float32(boxes["node_lowers"][0][0] - 1.0)
    box_case("NaN primitive box", lambda a: a["prim_lowers"].__setitem__((5, 0), np.nan))
    box_case("inverted primitive box", lambda a: a.update(prim_lowers=boxes["prim_uppers"].copy(),
                                                          prim_uppers=boxes["prim_lowers"].copy()))
    box_case("primitive box below its leaf", lambda a: a["prim_lowers"].__setitem__((prim, 0), outside))

    def leaf_below_parent(a):
        a["prim_lowers"][prim, 0] = outside
        a["node_lowers"][leaf, 0] = outside  # the leaf holds its box; it leaves its parent
    box_case("child below its parent", leaf_below_parent)
    box_case("one primitive box short", lambda a: a.update(prim_lowers=boxes["prim_lowers"][:-1],
                                                           prim_uppers=boxes["prim_uppers"][:-1]))
    box_case("method not a name", lambda a: a.update(meta=_meta(boxes, method={"not": "a name"})))

    split = _sbvh_arrays(tmp_path, device)
    order, counts = split["prim_order"], np.bincount(split["prim_order"])
    whole = _whole_triangle_leaf(split)

    def split_case(what, edit, arrays=split):
        a = {k: v.copy() for k, v in arrays.items()}
        edit(a)
        out.append((what, a))

    duplicated = int(np.nonzero(counts[order] > 1)[0][0])
    split_case("split tree: primitive id equal to the count",
               lambda a: a["prim_order"].__setitem__(duplicated, len(split["faces"])))
    split_case("split tree: whole-triangle leaf's lower corner raised",
               lambda a: a["node_lowers"].__setitem__(whole, split["node_uppers"][whole]))
    upper = split["node_uppers"][whole]
    split_case("split tree: whole-triangle leaf cut 100 ulps inside",
               lambda a: a["node_uppers"].__setitem__(
                   whole, upper - np.float32(100 * np.finfo(np.float32).eps) * np.abs(upper).max()))
    wide_leaves = _sbvh_arrays(tmp_path, device, leaf=4)
    assert wide_leaves["node_end"][wide_leaves["node_begin"] == 0].min() > 1
    split_case("split tree: the root's range begins at 1",
               lambda a: a["node_begin"].__setitem__(wide_leaves["node_begin"] == 0, 1), wide_leaves)

    # By hand: ten boxes on a line whose children's ranges are not side by side (the right child
    # of the root ends at 9, not 10): box 9 is in no walk's range, and box 5 in two.
    lo = np.stack([np.arange(10), np.zeros(10), np.zeros(10)], 1).astype(np.float32)
    hi = lo + np.float32(0.5)
    begin = np.array([0, 0, 5, 0, 3, 5, 7], np.int32)
    end = np.array([10, 5, 9, 3, 6, 7, 9], np.int32)
    node_lo, node_hi = np.zeros((7, 3), np.float32), np.zeros((7, 3), np.float32)
    for n, ps in {3: [0, 1, 2], 4: [3, 4, 5], 5: [5, 6, 7], 6: [7, 8, 9]}.items():
        node_lo[n], node_hi[n] = lo[ps].min(0), hi[ps].max(0)
    for n, (left, right) in {1: (3, 4), 2: (5, 6), 0: (1, 2)}.items():
        node_lo[n], node_hi[n] = np.minimum(node_lo[left], node_lo[right]), np.maximum(node_hi[left], node_hi[right])
    meta = {"format": json.loads(str(boxes["meta"]))["format"], "version": json.loads(str(boxes["meta"]))["version"],
            "method": "binned_sah", "num_prims": 10, "config": {}}
    out.append(("ranges not side by side at the right end", dict(
        node_left=np.array([1, 3, 5, -1, -1, -1, -1], np.int32),
        node_right=np.array([2, 4, 6, -1, -1, -1, -1], np.int32),
        node_parent=np.array([-1, 0, 0, 1, 1, 2, 2], np.int32), node_begin=begin, node_end=end,
        node_lowers=node_lo, node_uppers=node_hi, prim_order=np.arange(10, dtype=np.int32), prim_lowers=lo,
        prim_uppers=hi, meta=np.array(json.dumps(meta)))))
    return out


def test_box_and_spatial_split_files_are_refused_by_name(device, tmp_path):
    for what, bad in _more_corruptions(tmp_path, device):
        path = _write(tmp_path, bad)
        with pytest.raises(ValueError) as error:
            hb.load_bvh(path, device=device)
        assert str(path) in str(error.value), (what, str(error.value))


# ----------------------------------------------------------------- pinned by the third mutation audit
def test_the_npz_fallback_only_for_a_name_with_nothing_at_it(device, tmp_path):
    # load_bvh("tree") reads tree.npz only where nothing at all sits at "tree" and a file sits at
    # "tree.npz"; otherwise the name is opened as given, and its error names it.
    rng = np.random.default_rng(3)
    lo = rng.random((40, 3)).astype(np.float32)
    hb.save_bvh(hb.build_from_bounds(lo, lo + np.float32(0.1), device=device), tmp_path / "tree")
    assert hb.load_bvh(tmp_path / "tree", device=device).num_prims == 40
    # A dangling link at the name is something there: its own error, not the .npz beside it.
    os.symlink(tmp_path / "nowhere", tmp_path / "link")
    os.replace(tmp_path / "tree.npz", tmp_path / "link.npz")
    with pytest.raises(FileNotFoundError) as error:
        hb.load_bvh(tmp_path / "link", device=device)
    assert error.value.filename == str(tmp_path / "link")
    # A folder named name.npz is no file to fall back on: the name's own FileNotFoundError.
    (tmp_path / "folder.npz").mkdir()
    with pytest.raises(FileNotFoundError) as error:
        hb.load_bvh(tmp_path / "folder", device=device)
    assert error.value.filename == str(tmp_path / "folder")
    # Nothing at either name: the error names the name asked for.
    with pytest.raises(FileNotFoundError) as error:
        hb.load_bvh(tmp_path / "missing", device=device)
    assert error.value.filename == str(tmp_path / "missing")
    # A name that has the suffix is never given another: save_bvh(bvh, "t.npz") writes t.npz.
    os.replace(tmp_path / "link.npz", tmp_path / "t.npz.npz")
    with pytest.raises(FileNotFoundError):
        hb.load_bvh(tmp_path / "t.npz", device=device)


# ----------------------------------------------------------------- pinned by the robustness review
def _read_fifo_in_thread(path):
    """Start a thread that reads the FIFO at ``path`` to its end; returns (thread, received)."""
    import threading

    received = []

    def read():
        with open(path, "rb") as fifo:
            received.append(fifo.read())

    thread = threading.Thread(target=read, daemon=True)  # left blocked, not waited for, if no writer comes
    thread.start()
    return thread, received


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="FIFOs are POSIX")
def test_save_into_a_pipe_writes_into_it(device, tmp_path):
    # A temporary file renamed over the path replaced the pipe by a plain file (and the reader
    # got nothing); through a link to a device node it would replace the device node.
    import io
    import stat

    verts, faces = _mesh()
    bvh = hb.build(verts, faces, device=device)
    pipe = tmp_path / "pipe.npz"
    os.mkfifo(pipe)
    link = tmp_path / "link.npz"
    link.symlink_to(pipe)
    for path in (pipe, link):
        thread, received = _read_fifo_in_thread(pipe)
        hb.save_bvh(bvh, path)
        thread.join(timeout=30)
        assert stat.S_ISFIFO(os.lstat(pipe).st_mode), f"saving to {path.name} replaced the pipe"
        assert link.is_symlink()
        assert received, f"the reader of {path.name} received nothing"
        loaded = hb.load_bvh(io.BytesIO(received[0]), device=device)
        for name in NODE_FIELDS + ("prim_order",):
            np.testing.assert_array_equal(loaded.to_numpy()[name], bvh.to_numpy()[name], err_msg=name)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.npz", "pipe.npz"]



@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="FIFOs are POSIX")
def test_load_from_a_pipe_reads_it_once(device, tmp_path):
    # What save_bvh writes into a pipe, load_bvh reads from one: the pipe was opened twice, once
    # for the archive's first bytes and again by NumPy, which then waited for a writer that had
    # gone (the process hung) or got the stream without its head and refused it as no saved tree.
    import io
    import threading

    verts, faces = _mesh()
    bvh = hb.build(verts, faces, device=device)
    buffer = io.BytesIO()
    hb.save_bvh(bvh, buffer)
    pipe = tmp_path / "pipe.npz"
    os.mkfifo(pipe)
    for attempt in range(3):
        def write():
            with open(pipe, "wb") as fifo:
                fifo.write(buffer.getvalue())

        writer = threading.Thread(target=write, daemon=True)
        writer.start()
        result = []

        def load():
            try:
                result.append(hb.load_bvh(pipe, device=device))
            except Exception as error:  # reported below, in the test's thread
                result.append(error)

        reader = threading.Thread(target=load, daemon=True)
        reader.start()
        reader.join(timeout=30)
        if reader.is_alive():
            with open(pipe, "wb"):  # a writer that closes at once: the waiting open gets end of file
                pass
            reader.join(timeout=30)
            pytest.fail(f"load_bvh of a pipe waited for a second writer (attempt {attempt})")
        writer.join(timeout=30)
        assert isinstance(result[0], hb.Bvh), result[0]
        for name in NODE_FIELDS + ("prim_order",):
            np.testing.assert_array_equal(result[0].to_numpy()[name], bvh.to_numpy()[name], err_msg=name)
    # A device that streams forever is refused by its first bytes, not read to its end.
    if os.path.exists("/dev/zero"):
        with pytest.raises(ValueError, match="not an .npz archive"):
            hb.load_bvh("/dev/zero", device=device)


def _meta_text(arrays, text):
    return {**arrays, "meta": np.array(text)}


def _uint64_leaf_marks(arrays):
    # A leaf's -1 written as uint64 is 2**64 - 1, which became -1 again when widened to int64.
    return {**arrays, "node_left": arrays["node_left"].astype(np.uint64),
            "node_right": arrays["node_right"].astype(np.uint64)}


_LOAD_ERRORS = {
    "meta nested too deeply": (lambda a: _meta_text(a, "[" * 100000 + "]" * 100000), "nested too deeply"),
    "an integer of 5000 digits": (
        lambda a: _meta_text(a, str(a["meta"]).replace('"num_prims": ', '"num_prims": ' + "9" * 5000)),
        "an integer of more than"),
    "uint64 leaf marks": (_uint64_leaf_marks, "node_left holds an id outside int32"),
    "a float setting past float's range": (
        lambda a: {**a, "meta": _meta(a, config={"sah_traversal_cost": 10**400})}, "too large for a float"),
}


@pytest.mark.parametrize("what", sorted(_LOAD_ERRORS))
def test_more_corrupted_files_are_refused_by_name(device, tmp_path, what):
    # A RecursionError, Python's message on long integer literals (advising to raise its limit),
    # uint64 ids that wrapped to -1 so the file loaded, and an OverflowError from the config.
    arrays = _saved(tmp_path, device)
    edit, words = _LOAD_ERRORS[what]
    bad = edit(arrays)
    assert set(bad) == set(arrays) and any(not np.array_equal(bad[k], arrays[k]) for k in arrays)
    path = _write(tmp_path, bad)
    with pytest.raises(ValueError, match=words) as error:
        hb.load_bvh(path, device=device)
    assert str(error.value).startswith(f"{path}: ")


@pytest.mark.parametrize("source", [3, None, 1.5, ["tree.npz"]])
def test_load_takes_a_path_or_a_file_and_names_anything_else(source):
    # A TypeError from os.fsdecode, where save_bvh names the same mistake in a ValueError.
    words = rf"load\(\) reads a path or an open binary file, got {type(source).__name__}$"
    with pytest.raises(ValueError, match=words):
        hb.load_bvh(source)
