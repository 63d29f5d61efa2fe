"""Saving a BVH to a file and loading it back: for the offline builders (``sbvh``, seconds at
100k triangles; ``recursive_sah``, minutes), whose trees are worth building once.

The file is NumPy's ``.npz``: the used part of every node array (`hlbvh_warp.bvh.Bvh`'s layout),
``prim_order``, the primitive boxes of a tree over bare boxes, the vertices and faces of a mesh
tree, and a JSON record of the method, the primitive count and the `BuildConfig`. No pickles:
loading a file never runs code from it.

A loaded file is input like any other, and a tree whose child ids or ranges point outside its
arrays would send the traversal kernels out of bounds: `load` checks the whole structure (every
child id, range, parent link and primitive id) and the boxes (finite, children inside their
parents, primitives inside their leaves; for a mesh, the primitive boxes are the triangles'),
and names the first problem in a ValueError. A spatial-split tree's triangles cut across leaves
are checked at ten points each (`_check_parts_covered`): a sample, not a proof, so a crafted file
whose leaves leave a gap in such a triangle between those points still loads, and rays through
the gap miss the triangle.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import reprlib
import stat
import sys
import threading
import zipfile

import numpy as np
import warp as wp

from . import inputs
from .bvh import NODE_FIELDS, Bvh, holding_tree, not_a_bvh
from .config import BuildConfig

#: What a file says it is, and the layout version this module writes and reads.
FORMAT = "hlbvh_warp.bvh"
VERSION = 1
_INT_FIELDS = ("node_left", "node_right", "node_parent", "node_begin", "node_end")
_BOX_FIELDS = ("node_lowers", "node_uppers")


def _binary_file(file, mode: str):
    """Refuse a file object opened in text mode, which NumPy would fail on half way (``save``
    leaving an empty file) with a TypeError or UnicodeDecodeError."""
    if isinstance(file, io.TextIOBase):
        raise ValueError(f"a file object in text mode: open it in binary mode ('{mode}') or use io.BytesIO")
    return file


def _file_name(file) -> str:
    """What to call a file object in messages: its name when that is a path (not a descriptor)."""
    name = getattr(file, "name", None)
    return os.fsdecode(name) if isinstance(name, (str, bytes, os.PathLike)) else "<file object>"


@holding_tree
def save(bvh: Bvh, path, compressed: bool = False) -> None:
    """Write ``bvh`` to ``path`` (an ``.npz`` file; the suffix is added if it is missing), or to an
    open binary file (``open(..., "wb")``, ``io.BytesIO``), as ``np.savez`` takes either.

    A file already at the path is replaced whole, never left half written; a pipe or a device
    there (or behind a link) is written into, as ``np.savez`` does, and stays what it was.

    ``compressed``: zlib the arrays: for the armadillo's ``sbvh`` tree (100k triangles) 5.8 MB
    written in about 0.6 s, against 11.7 MB in 20 ms uncompressed; either loads in under 0.1 s.
    """
    if not isinstance(bvh, Bvh):
        raise ValueError(not_a_bvh("save_bvh", bvh))
    if hasattr(path, "write"):
        file = _binary_file(path, "wb")
    elif isinstance(path, (str, bytes, os.PathLike)):
        file = None
        path = os.fsdecode(path)
        if not path.endswith(".npz"):
            path += ".npz"  # as NumPy names a file it is given by name
    else:
        raise ValueError(f"save() writes to a path or an open binary file, got {type(path).__name__}")
    tree = bvh.to_numpy()
    # A Builder frame given as Warp arrays is not checked: a NaN or Inf in a triangle's vertex (its
    # box skips it) or in a box would be written, and `load` refuses the file. Refused here,
    # before a file is written that could not be read back.
    for name in _BOX_FIELDS + ("prim_lowers", "prim_uppers"):
        if not np.isfinite(tree[name]).all():
            raise ValueError(f"save() takes a tree with finite boxes: its {name} hold a NaN or Inf (a frame with "
                             "one), which load_bvh would refuse")
    arrays = {name: tree[name] for name in NODE_FIELDS + ("prim_order",)}
    if bvh.vertices is not None and bvh.faces is not None:
        arrays["vertices"] = bvh.vertices.numpy()
        arrays["faces"] = bvh.faces.numpy().reshape(-1, 3)
        bad = ~np.isfinite(arrays["vertices"][arrays["faces"]]).all(axis=(1, 2))
        if bad.any():
            raise ValueError(f"save() takes a tree with finite triangles: face {int(np.argmax(bad))} has a NaN or "
                             "Inf vertex (a frame with one), which load_bvh would refuse")
    else:
        arrays["prim_lowers"] = tree["prim_lowers"]
        arrays["prim_uppers"] = tree["prim_uppers"]
    meta = {"format": FORMAT, "version": VERSION, "method": bvh.method, "num_prims": bvh.num_prims,
            "config": dataclasses.asdict(bvh.config)}
    # A 0-d unicode array: read back without allow_pickle.
    arrays["meta"] = np.array(json.dumps(meta))
    write = np.savez_compressed if compressed else np.savez
    if file is not None:
        write(file, **arrays)
        return
    target = os.path.realpath(path)
    try:
        mode = os.stat(target).st_mode
    except OSError:
        mode = None  # nothing there yet; what else keeps the path from being written, open() names
    if mode is not None and not stat.S_ISREG(mode):
        # A pipe, a device or a socket, or a link to one, is written into, as np.savez does:
        # renaming a file over it would put a plain file where the pipe or device node was. Such
        # a target holds no old file that a reader could see half replaced. A folder fails to
        # open, and is named.
        try:
            file = open(target, "wb")
        except OSError as error:
            raise type(error)(error.errno, f"cannot write {path}: {error.strerror}") from None
        with file:
            write(file, **arrays)
        return
    # A file (or nothing yet) is written beside the target and renamed over it: a reader (another
    # thread, another process) sees the old file or the new one, never one half written.
    # A link's target is what gets replaced (the link stays), an existing file keeps its
    # permissions, and the short name (process and thread) fits wherever the target's does.
    # Errors name the path as asked for, not the temporary file or the link's target.
    temporary = os.path.join(os.path.dirname(target), f".{os.getpid()}-{threading.get_ident()}.partial")
    try:
        file = open(temporary, "wb")
    except OSError as error:
        raise type(error)(error.errno, f"cannot write {path}: {error.strerror}") from None
    try:
        with file:
            write(file, **arrays)
        if os.path.exists(target):
            os.chmod(temporary, stat.S_IMODE(os.stat(target).st_mode))
        try:
            os.replace(temporary, target)
        except OSError as error:
            raise type(error)(error.errno, f"cannot write {path}: {error.strerror}") from None
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(temporary)
        raise


def load(path, device=None) -> Bvh:
    """The BVH saved in ``path``, on ``device`` (default: Warp's default device). A name without
    the ``.npz`` suffix that `save` added finds the file it wrote. An open binary file (or
    ``io.BytesIO``) is read from its position to its end, which must hold one archive; so is a
    pipe or a device at the path (what `save` wrote into it).

    Raises:
        ValueError: the file is not a saved BVH, or its tree is not a valid one (named).
    """
    if hasattr(path, "read"):
        data = _binary_file(path, "rb").read()
        if not isinstance(data, (bytes, bytearray)):
            raise ValueError(f"a file object whose read() gave {type(data).__name__}: open it in binary mode ('rb')")
        source, path = io.BytesIO(data), _file_name(path)
    elif isinstance(path, (bytearray, memoryview)) or (isinstance(path, bytes) and (
            path.startswith(b"PK\x03\x04") or b"\0" in path)):
        raise ValueError(f"load() reads a path or an open binary file, got {len(path)} bytes of data: "
                         "wrap them in io.BytesIO")
    elif not isinstance(path, (str, bytes, os.PathLike)):
        raise ValueError(f"load() reads a path or an open binary file, got {type(path).__name__}")
    else:
        name = os.fsdecode(path)
        if not name.endswith(".npz") and not os.path.lexists(name) and os.path.isfile(name + ".npz"):
            path = name + ".npz"  # save(bvh, "tree") wrote tree.npz
        source = os.fspath(path)
    try:
        # np.load takes any other file for a pickle and says so: name what the file is not instead.
        if isinstance(source, io.BytesIO):
            head = source.getvalue()[:4]
        else:
            with open(source, "rb") as file:
                head = file.read(4)
                if head == b"PK\x03\x04" and not stat.S_ISREG(os.fstat(file.fileno()).st_mode):
                    # A pipe or a device (a FIFO, /dev/stdin) is read once, here, as an open file
                    # is: opened again by NumPy, it waited for a writer that had already gone
                    # (the process hung), or gave the stream without its head, which NumPy
                    # cannot seek back to. Read only after the head: /dev/zero never ends.
                    source = io.BytesIO(head + file.read())
        if head != b"PK\x03\x04":
            raise ValueError("not a saved BVH (not an .npz archive)")
        _check_member_sizes(source)
        with np.load(source, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
        # NumPy hands a member whose name lacks ".npy" back as its raw bytes, which the checks of
        # the arrays below met with an AttributeError.
        raw = next((name for name, value in arrays.items() if not isinstance(value, np.ndarray)), None)
        if raw is not None:
            raise ValueError(f"its member {raw!r} is not a NumPy array")
    except FileNotFoundError:
        raise
    except ValueError as error:
        if str(error).startswith("not a saved BVH"):
            raise ValueError(f"{path}: {error}") from None
        raise ValueError(f"{path}: not a saved BVH ({error})") from None
    except MemoryError:
        raise
    except Exception as error:
        # A truncated zip, a pickled member (never unpickled: allow_pickle=False), a folder, a
        # corrupt compressed member (zlib.error) or .npy header (tokenize.TokenError): whatever
        # NumPy's reader raises, the file is no saved BVH.
        raise ValueError(f"{path}: not a saved BVH ({type(error).__name__}: {error})") from None
    try:
        return _from_arrays(arrays, device)
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None


def _check_member_sizes(source) -> None:
    """Raise a ValueError naming the first ``.npy`` member of the archive whose header declares more
    data than the member holds. NumPy allocates the array its header declares before reading any
    data, so a few hundred bytes declaring 2**44 entries raised MemoryError ("unable to allocate
    64 TiB"), the error of a machine short of memory, not of a damaged file."""
    with zipfile.ZipFile(os.fsdecode(source) if isinstance(source, bytes) else source) as archive:
        for info in archive.infolist():
            if not info.filename.endswith(".npy"):
                continue
            with archive.open(info) as member:
                version = np.lib.format.read_magic(member)
                read = {(1, 0): np.lib.format.read_array_header_1_0,
                        (2, 0): np.lib.format.read_array_header_2_0}.get(version)
                if read is None:
                    continue  # a layout np.load reads, or names as one it does not
                shape, _, dtype = read(member)
                declared = dtype.itemsize
                for extent in shape:
                    declared *= int(extent)
                held = info.file_size - member.tell()
            if declared > held:
                raise ValueError(f"its member {info.filename} declares {declared} bytes of data and holds {held}")
    if isinstance(source, io.BytesIO):
        source.seek(0)


def _meta(arrays: dict) -> dict:
    if "meta" not in arrays or arrays["meta"].dtype.kind != "U" or arrays["meta"].ndim != 0:
        raise ValueError("not a saved BVH (no meta record)")
    try:
        meta = json.loads(str(arrays["meta"]))
    except json.JSONDecodeError as error:
        raise ValueError(f"the meta record is not JSON ({error})") from None
    except RecursionError:
        # json's parser recurses once per level of nesting; no meta record is nested that deep.
        raise ValueError("the meta record is not one (JSON nested too deeply to read)") from None
    except ValueError as error:
        if "digits" not in str(error):
            raise ValueError(f"the meta record could not be read ({error})") from None
        # Python converts no integer literal longer than its limit (sys.set_int_max_str_digits,
        # Python 3.10.7 on), and its message would suggest raising the limit; no count or setting
        # is that long.
        limit = getattr(sys, "get_int_max_str_digits", lambda: 4300)()
        raise ValueError(f"the meta record holds an integer of more than {limit} digits") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ValueError("not a saved BVH (the meta record names another format)")
    # Values from the file are shown shortened (reprlib): a message need not quote a long one whole.
    if meta.get("version") != VERSION:
        raise ValueError(f"saved in layout version {reprlib.repr(meta.get('version'))}; "
                         f"this version reads {VERSION}")
    num_prims = meta.get("num_prims")
    if isinstance(num_prims, bool) or not isinstance(num_prims, int) or not 1 <= num_prims < inputs.MAX_PRIMS:
        raise ValueError(f"num_prims must be an integer in [1, {inputs.MAX_PRIMS}), got {reprlib.repr(num_prims)}")
    if not isinstance(meta.get("method"), str):
        raise ValueError(f"method must be a string, got {reprlib.repr(meta.get('method'))}")
    config = meta.get("config")
    if not isinstance(config, dict):
        raise ValueError("the meta record has no config")
    known = {field.name for field in dataclasses.fields(BuildConfig)}
    unknown = sorted(set(config) - known)
    if unknown:
        raise ValueError(f"unknown BuildConfig fields {unknown}")
    meta["config"] = BuildConfig(**config)  # its own checks name a bad value (a ValueError)
    return meta


def _array(arrays: dict, name: str, kind: str, shape_tail: tuple) -> np.ndarray:
    if name not in arrays:
        raise ValueError(f"no {name} array")
    a = arrays[name]
    if a.dtype.kind not in kind or a.ndim != 1 + len(shape_tail) or a.shape[1:] != shape_tail:
        raise ValueError(f"{name} must be a {'(n, 3) float' if shape_tail else '(n,) integer'} array, "
                         f"got {a.dtype} {a.shape}")
    return a


def check_tree(tree: dict, num_prims: int, duplicates: bool, triangles: np.ndarray | None = None) -> None:
    """Raise a ValueError naming the first way ``tree`` (`Bvh.to_numpy`'s arrays) is not a valid
    BVH over ``num_prims`` primitives: the conditions every traversal kernel relies on.

    ``duplicates``: ``prim_order`` may list a primitive more than once (a spatial-split tree),
    whose leaf boxes bound parts of ``triangles`` (their vertices, ``(num_prims, 3, 3)``), not
    their whole boxes; without ``triangles`` every leaf must hold its primitives' whole boxes.
    """
    left, right, parent = tree["node_left"], tree["node_right"], tree["node_parent"]
    begin, end, order = tree["node_begin"], tree["node_end"], tree["prim_order"]
    lo, hi = tree["node_lowers"], tree["node_uppers"]
    n, refs = left.shape[0], order.shape[0]
    if n == 0:
        raise ValueError("the tree has no nodes")
    if any(tree[name].shape[0] != n for name in NODE_FIELDS):
        raise ValueError(f"the node arrays differ in length: {[tree[name].shape[0] for name in NODE_FIELDS]}")
    ids = np.arange(n)
    leaf = left < 0
    if not np.array_equal(leaf, right < 0) or not ((left == -1) == leaf).all() or not ((right == -1) == leaf).all():
        raise ValueError("a node has exactly one child, or a child id below -1")
    interior = np.nonzero(~leaf)[0]
    kids_l, kids_r = left[interior].astype(np.int64), right[interior].astype(np.int64)
    # Children after their parents (the layout's rule, which also rules out cycles), inside the arrays.
    if not ((kids_l > interior) & (kids_l < n) & (kids_r > interior) & (kids_r < n)).all():
        raise ValueError("a child id is not after its parent's, or past the last node")
    times = np.bincount(np.concatenate([kids_l, kids_r]), minlength=n)
    if times[0] != 0 or not (times[1:] == 1).all():
        raise ValueError("some node is not the child of exactly one node (or the root is a child)")
    expected_parent = np.full(n, -1, dtype=np.int64)
    expected_parent[kids_l], expected_parent[kids_r] = interior, interior
    if not np.array_equal(parent, expected_parent):
        first = int(ids[parent != expected_parent][0])
        raise ValueError(f"node_parent disagrees with the child links (first at node {first})")
    if refs < num_prims or (not duplicates and refs != num_prims):
        raise ValueError(f"prim_order has {refs} entries for {num_prims} primitives")
    if begin[0] != 0 or end[0] != refs or not (begin < end).all():
        raise ValueError(f"the root must cover [0, {refs}) and every node a non-empty range")
    # Each interior range is its children's, adjacent: with the root covering every position,
    # the leaves then partition prim_order.
    adjacent = (begin[kids_l] == begin[interior]) & (end[kids_l] == begin[kids_r]) & (end[kids_r] == end[interior])
    if not adjacent.all():
        raise ValueError("an interior node's range is not its two children's ranges side by side")
    if refs and (order.min() < 0 or order.max() >= num_prims):
        raise ValueError(f"prim_order holds an id outside [0, {num_prims})")
    seen = np.bincount(order, minlength=num_prims)
    if (seen == 0).any():
        raise ValueError(f"primitive {int(np.argmin(seen))} is in no leaf")
    for name, box in (("node boxes", (lo, hi)), ("primitive boxes", (tree["prim_lowers"], tree["prim_uppers"]))):
        if not (np.isfinite(box[0]).all() and np.isfinite(box[1]).all()) or (box[0] > box[1]).any():
            raise ValueError(f"the {name} must be finite, lowers <= uppers")
    for kids in (kids_l, kids_r):
        if (lo[kids] < lo[interior]).any() or (hi[kids] > hi[interior]).any():
            raise ValueError("a child's box is not inside its parent's")
    if not duplicates or triangles is None:
        # A tree over bare boxes has no triangle for a spatial split to cut, so a primitive listed
        # twice there stands for its whole box each time, as in any object split.
        # The leaf holding each position of prim_order: the leaves' ranges in order of their begin.
        leaves = np.nonzero(leaf)[0]
        leaves = leaves[np.argsort(begin[leaves], kind="stable")]
        leaf_of = np.repeat(leaves, (end - begin)[leaves])
        p_lo, p_hi = tree["prim_lowers"][order], tree["prim_uppers"][order]
        if (p_lo < lo[leaf_of]).any() or (p_hi > hi[leaf_of]).any():
            raise ValueError("a primitive's box is not inside its leaf's")
    elif triangles is not None:
        _check_parts_covered(lo, hi, leaf, begin, end, order, triangles, tree["prim_lowers"], tree["prim_uppers"])


# Barycentric weights of the points checked on each triangle of a spatial-split tree: the corners,
# the edge midpoints, the centroid and three points between centroid and corners.
_SAMPLE_WEIGHTS = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0.5, 0], [0, 0.5, 0.5], [0.5, 0, 0.5],
                            [1 / 3, 1 / 3, 1 / 3], [2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3]])


def _check_parts_covered(lo, hi, leaf, begin, end, order, triangles, prim_lo, prim_hi) -> None:
    """A spatial-split tree's leaves bound parts of triangles (Stich et al. 2009), so no single leaf
    need hold a split triangle's box; what a ray needs is every point of the triangle inside some
    leaf that lists it. A triangle listed once was never cut: its leaf holds its whole box. A
    split one is checked at ten points; the points are a sample, not a proof, that still names a
    leaf box shrunk or moved off its triangles.

    Both checks are exact, with no slack: the builder rounds every clipped part's box outward (by
    a float32 unit and the clip's own error, ``kernels/spatial_split.py``), and a once-listed
    triangle's leaf box is the minimum and maximum of float32 vertices. A slack of a few float32
    units of the triangle's largest coordinate, as this check once allowed, let a crafted file
    whose leaf and ancestor boxes stopped short of a thin triangle (half its height, for one
    2000 wide and 0.001 high) load, and rays through the part left out missed it."""
    leaves = np.nonzero(leaf)[0]
    leaves = leaves[np.argsort(begin[leaves], kind="stable")]
    leaf_of = np.repeat(leaves, (end - begin)[leaves])
    split = np.bincount(order, minlength=triangles.shape[0])[order] > 1
    # The triangles listed once, by their boxes (float32, as the boxes are).
    whole, at = order[~split], leaf_of[~split]
    outside = ((prim_lo[whole] < lo[at]) | (prim_hi[whole] > hi[at])).any(axis=1)
    if outside.any():
        raise ValueError(f"triangle {int(whole[np.argmax(outside)])}, in one leaf only, is not inside that leaf's box")
    # The split ones, point by point in float64. A point is clamped to its triangle's box, where
    # the exact point lies: weights that sum to 1 only in rounding (a third of each of three equal
    # z) may put it a float64 unit outside that box, whose bound a part's box may share (the
    # builder clamps each part to the box it was cut from).
    parts, at = order[split], leaf_of[split]
    tri = triangles[parts].astype(np.float64)
    tri_lo, tri_hi = tri.min(axis=1), tri.max(axis=1)
    box_lo, box_hi = lo[at].astype(np.float64), hi[at].astype(np.float64)
    listed = np.bincount(parts, minlength=triangles.shape[0]) > 0
    for w in _SAMPLE_WEIGHTS:
        point = np.clip(w[0] * tri[:, 0] + w[1] * tri[:, 1] + w[2] * tri[:, 2], tri_lo, tri_hi)
        inside = ((point >= box_lo) & (point <= box_hi)).all(axis=1)
        missed = listed & ~(np.bincount(parts, weights=inside, minlength=triangles.shape[0]) > 0)
        if missed.any():
            raise ValueError(f"a point of triangle {int(np.argmax(missed))} is in none of the leaves that list it")


def _mesh_arrays(arrays: dict) -> tuple[np.ndarray, np.ndarray]:
    """The file's vertices and faces, checked as a build checks them, except that a vertex no
    face uses may hold a NaN or Inf: a `Builder` frame given as a Warp array is not checked, and
    such a tree is right (queries read only the triangles), so `save` writes it and `Bvh(...)`
    over the same arrays takes it. Those rows are checked as zeros and kept as written."""
    raw = inputs._to_numpy(arrays.get("vertices", np.zeros((0, 3))), "vertices")
    faces = arrays.get("faces", [])
    stand_in, unused = raw, None
    if raw.dtype.kind == "f" and raw.ndim == 2 and raw.shape[1] == 3 and not np.isfinite(raw).all():
        f = inputs._to_numpy(faces, "faces")
        if f.dtype.kind in "iu":
            f = f.ravel()
            unused = np.ones(raw.shape[0], dtype=bool)
            unused[f[(f >= 0) & (f < raw.shape[0])]] = False
            stand_in = np.where(unused[:, None], 0, raw).astype(raw.dtype)
    vertices, faces = inputs.mesh_arrays(stand_in, faces)
    if unused is not None:
        with np.errstate(over="ignore"):  # a wider float past float32's range is Inf, as it was
            vertices[unused] = raw[unused]
    return vertices, faces


def _from_arrays(arrays: dict, device) -> Bvh:
    meta = _meta(arrays)
    num_prims, config = meta["num_prims"], meta["config"]
    tree = {name: _array(arrays, name, "iu", ()) for name in _INT_FIELDS + ("prim_order",)}
    tree.update({name: _array(arrays, name, "f", (3,)) for name in _BOX_FIELDS})
    mesh = "vertices" in arrays or "faces" in arrays
    if mesh:
        vertices, faces = _mesh_arrays(arrays)
        if faces.shape[0] != num_prims:
            raise ValueError(f"faces has {faces.shape[0]} rows for {num_prims} primitives")
        tri = vertices[faces]
        tree["prim_lowers"], tree["prim_uppers"] = tri.min(axis=1), tri.max(axis=1)
    else:
        tri = None
        tree["prim_lowers"] = _array(arrays, "prim_lowers", "f", (3,))
        tree["prim_uppers"] = _array(arrays, "prim_uppers", "f", (3,))
        if tree["prim_lowers"].shape[0] != num_prims or tree["prim_uppers"].shape[0] != num_prims:
            raise ValueError(f"the primitive boxes must have {num_prims} rows")
    # Ids past int32 would wrap when narrowed below, and uint64 ones past int64 already when
    # widened to it (2**64 - 1 became -1, a leaf's mark): range-check them as Python ints first.
    for name in _INT_FIELDS + ("prim_order",):
        a = tree[name]
        if a.size and (int(a.min()) < -(1 << 31) or int(a.max()) >= 1 << 31):
            raise ValueError(f"{name} holds an id outside int32")
        tree[name] = a.astype(np.int64)
    for name in _BOX_FIELDS + ("prim_lowers", "prim_uppers"):
        tree[name] = np.ascontiguousarray(tree[name], dtype=np.float32)
    check_tree(tree, num_prims, duplicates=tree["prim_order"].shape[0] != num_prims, triangles=tri)

    device = wp.get_device(device)

    def ints(a):
        return wp.array(np.ascontiguousarray(a, dtype=np.int32), dtype=wp.int32, device=device)

    def vecs(a):
        return wp.array(a, dtype=wp.vec3, device=device)

    # Checked above, as a whole; Bvh() would read the arrays back to check them again.
    return Bvh._trusted(
        method=meta["method"], config=config, device=device,
        prim_lowers=vecs(tree["prim_lowers"]), prim_uppers=vecs(tree["prim_uppers"]),
        prim_order=ints(tree["prim_order"]),
        node_lowers=vecs(tree["node_lowers"]), node_uppers=vecs(tree["node_uppers"]),
        node_left=ints(tree["node_left"]), node_right=ints(tree["node_right"]),
        node_parent=ints(tree["node_parent"]),
        node_begin=ints(tree["node_begin"]), node_end=ints(tree["node_end"]),
        node_count=ints([tree["node_left"].shape[0]]),
        vertices=vecs(vertices) if mesh else None, faces=ints(faces) if mesh else None,
        num_prims=num_prims,
    )
