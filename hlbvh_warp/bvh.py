"""The one canonical BVH layout every builder produces, and its host-side accessors."""

from __future__ import annotations

import contextlib
import functools
import inspect

import numpy as np
import warp as wp

from .config import BuildConfig

#: How long `held` first waits for a second tree's lock while holding the first one (then twice
#: as long each round).
LOCK_WAIT_S = 0.001


class Bvh:
    """A binary BVH as structure-of-arrays on the build device.

    Node layout (root is node 0; children are always numbered after their parent):

    ==============  ===================================================================
    ``node_lowers``  vec3, lower corner of the node's box
    ``node_uppers``  vec3, upper corner
    ``node_left``    int32, left child; -1 marks a leaf
    ``node_right``   int32, right child; -1 for a leaf
    ``node_parent``  int32, parent; -1 for the root
    ``node_begin``   int32, first position in ``prim_order`` covered by the node's subtree
    ``node_end``     int32, one past the last position (half-open): a leaf holds exactly
                     ``prim_order[node_begin:node_end]``, an interior node the union of its
                     children's ranges, which are adjacent
    ==============  ===================================================================

    ``prim_order[k]`` is the input index of the k-th primitive in tree order. The arrays have the
    arena's capacity (2N - 1, or more for a spatial-split tree, whose leaves may reference a
    triangle several times); ``num_nodes`` entries are used, a count kept on the device and read
    only when asked for.

    A spatial-split tree (``method="sbvh"``) references a triangle from every leaf that holds a
    part of it: its ``prim_order`` has ``num_refs`` >= ``num_prims`` entries and its node boxes
    bound those parts, not whole triangles. Every other builder's ``prim_order`` is a permutation
    (``num_refs == num_prims``).
    """

    def __init__(self, **arrays):  # _setup's keywords, shown as __init__'s signature (end of the class)
        """A tree over arrays made by the caller: ``method`` (a name), ``config`` (a `BuildConfig`),
        ``device``, the arrays of the layout above (``vec3`` boxes, ``int32`` ids, all 1-D),
        ``node_count`` (one ``int32``: the nodes in use), optionally ``vertices`` (``vec3``) with
        ``faces`` (``int32``, shape ``(num_prims, 3)``) for a tree over a mesh, ``timings`` and
        ``num_prims`` (default: the length of ``prim_order``; less for a spatial-split tree).

        The arrays are checked as a loaded file is (`hlbvh_warp.load_bvh`), since the traversal
        kernels index with their contents: types, devices and lengths, then, read back to the
        host, the node count, the tree's structure, its boxes, the face indices and, for a mesh,
        that the primitive boxes are its triangles' (a loaded file's are derived from them). The library's
        builders make their trees through `_trusted`, unchecked.

        Raises:
            ValueError: an argument of the wrong type, dtype, device or length, or arrays that are
                not a valid tree (the first problem named).
        """
        self._setup(**arrays)
        _check_arrays(self)
        _check_contents(self)

    @classmethod
    def _trusted(cls, **arrays) -> Bvh:
        """A tree over arrays a builder of this library made, unchecked: they are a valid tree by
        construction, and the check would read the whole tree back to the host on every build."""
        bvh = cls.__new__(cls)
        bvh._setup(**arrays)
        return bvh

    def _setup(
        self,
        *,
        method: str,
        config: BuildConfig,
        device,
        prim_lowers: wp.array,
        prim_uppers: wp.array,
        prim_order: wp.array,
        node_lowers: wp.array,
        node_uppers: wp.array,
        node_left: wp.array,
        node_right: wp.array,
        node_parent: wp.array,
        node_begin: wp.array,
        node_end: wp.array,
        node_count: wp.array,
        vertices: wp.array | None = None,
        faces: wp.array | None = None,
        timings: dict | None = None,
        num_prims: int | None = None,
    ):
        self.method = method
        self._num_prims = num_prims
        self.config = config
        self.device = wp.get_device(device)
        self.prim_lowers = prim_lowers
        self.prim_uppers = prim_uppers
        self.prim_order = prim_order
        self.node_lowers = node_lowers
        self.node_uppers = node_uppers
        self.node_left = node_left
        self.node_right = node_right
        self.node_parent = node_parent
        self.node_begin = node_begin
        self.node_end = node_end
        self.node_count = node_count
        self.vertices = vertices
        self.faces = faces
        #: Milliseconds per stage, filled when the build was asked to time itself.
        self.timings = timings if timings is not None else {}
        #: How many times `invalidate` has run: the trees derived from this one (`wide.collapse`)
        #: record it, and refuse host calls once the tree has changed under them.
        self.generation = 0
        self._cache = {}
        #: The lock of the `Builder` that rebuilds this tree in place (None: nothing does). Host
        #: queries hold it, so that one never reads a tree another thread is rewriting.
        self._lock = None

    @property
    def num_prims(self) -> int:
        """Primitives (triangles or boxes) the tree was built over."""
        return self.prim_order.shape[0] if self._num_prims is None else self._num_prims

    @property
    def num_refs(self) -> int:
        """Entries of ``prim_order``: ``num_prims``, or more where spatial splits duplicated some."""
        return self.prim_order.shape[0]

    @property
    def has_duplicates(self) -> bool:
        """True where ``prim_order`` lists a primitive more than once (spatial splits)."""
        return self.num_refs != self.num_prims

    @property
    def num_nodes(self) -> int:
        """Nodes in use, read from the device-side count (a wait for the device on CUDA)."""
        return int(self.node_count.numpy()[0])

    @property
    def num_leaves(self) -> int:
        """Leaves (``node_left`` -1), counted on the host copy (`to_numpy`)."""
        return int((self.to_numpy()["node_left"] < 0).sum())

    @property
    def depth(self) -> int:
        """Edges on the longest root-to-leaf path (a single leaf has depth 0)."""
        # Held from the host copy to the store: let go in between, an update on another thread
        # emptied the cache there, and this frame's depth was stored as the next one's.
        with held(self):
            if "depth" not in self._cache:
                self._cache["depth"] = int(node_depths(self.to_numpy()).max())
            return self._cache["depth"]

    def to_numpy(self) -> dict:
        """The used part of every array as NumPy, keyed by the attribute names above.

        One host copy serves every call until `invalidate` (and `depth`, `num_leaves` and
        `hlbvh_warp.save_bvh` read it too), so its arrays are read-only: an edit in place
        (``tree["prim_order"].sort()``, ``tree["node_lowers"] *= 2``) raises NumPy's ValueError
        that the array is read-only. Copy to edit (``tree["prim_order"].copy()``). The dict itself
        is new on each call.
        """
        key = "numpy"
        with held(self):
            if key not in self._cache:
                n = self.num_nodes
                out = {name: getattr(self, name).numpy()[:n].copy() for name in NODE_FIELDS}
                out["prim_order"] = self.prim_order.numpy().copy()
                out["prim_lowers"] = self.prim_lowers.numpy().copy()
                out["prim_uppers"] = self.prim_uppers.numpy().copy()
                for array in out.values():
                    array.flags.writeable = False
                self._cache[key] = out
            # Views of the read-only copies: a view's flag cannot be set back to writeable while
            # its base is read-only, where the copy's own could.
            return {name: array.view() for name, array in self._cache[key].items()}

    def hold(self):
        """A context in which the `Builder` that rebuilds this tree in place waits: ``with
        bvh.hold(): wp.launch(my_kernel, inputs=[bvh.view(), ...])`` reads one frame's whole tree
        while another thread updates it (and after a graph replay, ``invalidate`` inside it). The
        library's own queries hold it already; a tree no builder owns has nothing to hold."""
        return held(self)

    def view(self):
        """A `BvhView` struct of this tree for user kernels (``bvh_closest_hit`` and friends)."""
        from .query import view

        return view(self)

    def __ctype__(self):
        """Refuse to be a kernel argument, naming the view to pass instead. Warp packs a struct
        argument by calling its value's ``__ctype__``: without this, a tree passed where a kernel
        takes its `BvhView` failed with an AttributeError that named nothing the user wrote."""
        raise TypeError("a Warp kernel takes the tree's view, not the Bvh: pass bvh.view() "
                        "(hlbvh_warp.view(bvh)) as the BvhView argument")

    def invalidate(self):
        """Forget host copies after the device arrays changed (refit, rebuild).

        The ray traversal layout, once `view` has made one, is derived from the node boxes and the
        vertices: it is rewritten in place (launches only), so views handed out earlier stay valid.
        """
        # A query on another thread reads the layout: not while it is rewritten. An unfinished
        # tree is invalidated too (its builder's next frame does so before it is whole again).
        with held(self, finished=False):
            self.generation += 1
            layout = self._cache.get("traversal_layout")
            # A new dict, the layout already in it: emptied first, a `view` made in between (from
            # another thread) made a layout of its own that no later refit refreshed.
            self._cache = {} if layout is None else {"traversal_layout": layout}
            if layout is not None:
                layout.refresh(self)

    def __repr__(self) -> str:
        return (f"Bvh(method={self.method!r}, num_prims={self.num_prims}, num_nodes={self.num_nodes}, "
                f"device={self.device})")

    # help() and editors show the keywords __init__ hands on to _setup.
    __init__.__signature__ = inspect.signature(_setup)


#: Why a query refuses a tree its `Builder` left half written (`held`).
UNFINISHED_TREE = ("this tree is unfinished: its Builder's last frame raised partway, so its nodes mix two "
                   "frames; the Builder's next build, rebuild, refit or update builds it from scratch")


def _refuse_unfinished(trees):
    # Set by the Builder under its lock when a frame raised partway (`Builder._one_call_at_a_time`);
    # read here with the lock taken, so a frame in progress on another thread is waited for first.
    for tree in trees:
        if getattr(tree, "_unfinished", False):
            raise RuntimeError(UNFINISHED_TREE)


def not_a_bvh(name: str, obj) -> str:
    """The message of the ValueError a function `name` raises when given `obj`, not a `Bvh`.

    None is nearly always a `Builder`'s ``bvh`` read before its first build, which "got
    NoneType" alone did not say."""
    if obj is None:
        return (f"{name}() takes a Bvh, got None (a Builder's bvh is None until its first "
                "build() or build_from_bounds())")
    return f"{name}() takes a Bvh, got {type(obj).__name__}"


@contextlib.contextmanager
def held(*trees, finished: bool = True):
    """Hold the locks of the given trees that a `Builder` rebuilds in place (one per builder): a
    query then reads one frame's whole tree, never one another thread is halfway through
    rewriting. Without it, the two-pass queries (count, then write) met a tree that had changed
    between their passes and wrote fewer pairs than they had counted: garbage ids, and in
    `intersecting_pairs` a crash.

    Two locks are taken as ``std::lock`` takes them: wait for one, then for the other a while,
    and when that one stays busy let go and wait for it first, each wait twice as long as the
    last. A fixed order alone deadlocked a thread already inside one tree's `hold()` against
    another taking both in that order; and trying both without waiting (let go and try again
    after a short random sleep) never found both free while their builders updated frame after
    frame in other threads, each lock free only between two frames: the query hung.

    With ``finished`` (every query), a tree whose `Builder` left its last frame half written is
    refused (`UNFINISHED_TREE`): read, it gave wrong hit ids and a fraction of the pairs."""
    locks = []
    for tree in trees:
        lock = getattr(tree, "_lock", None)
        if lock is not None and all(lock is not other for other in locks):
            locks.append(lock)
    if len(locks) <= 1:
        with locks[0] if locks else contextlib.nullcontext():
            if finished:
                _refuse_unfinished(trees)
            yield
        return
    first, wait = 0, LOCK_WAIT_S
    taken = []
    try:
        while True:
            locks[first].acquire()
            taken = [locks[first]]
            busy = None
            for index, lock in enumerate(locks):
                if index != first:
                    if not lock.acquire(timeout=wait):
                        busy = index
                        break
                    taken.append(lock)
            if busy is None:
                break
            for lock in reversed(taken):
                lock.release()
            taken = []
            # Let go before waiting for the busy one: a thread inside `hold()` on it may be
            # waiting for the one taken here. The longer waits let two builders' frames, each
            # longer than the last wait, end while one lock is held.
            first, wait = busy, 2.0 * wait
    except BaseException:
        # An interrupt (Ctrl-C) in the wait for the second lock: kept, the first one stayed taken
        # for good, and its builder's next frame on another thread hung.
        for lock in reversed(taken):
            lock.release()
        raise
    try:
        if finished:
            _refuse_unfinished(trees)
        yield
    finally:
        for lock in reversed(taken):
            lock.release()


def holding_tree(fn):
    """`held` around a query whose first argument is the tree."""

    @functools.wraps(fn)
    def locked(*args, **kwargs):
        tree = args[0] if args else kwargs.get("bvh")
        with held(tree):
            return fn(*args, **kwargs)

    return locked


NODE_FIELDS = ("node_lowers", "node_uppers", "node_left", "node_right", "node_parent", "node_begin", "node_end")
_VEC3_FIELDS = ("prim_lowers", "prim_uppers", "node_lowers", "node_uppers")
_INT32_FIELDS = ("prim_order", "node_left", "node_right", "node_parent", "node_begin", "node_end", "node_count")


def _check_arrays(bvh: Bvh) -> None:
    """Raise a ValueError naming the first argument of a caller-made tree (`Bvh.__init__`) of the
    wrong type, dtype, device or length: what can be seen without reading the device."""
    from .inputs import MAX_PRIMS

    if not isinstance(bvh.method, str):
        raise ValueError(f"Bvh: method must be a string, got {type(bvh.method).__name__}")
    if not isinstance(bvh.config, BuildConfig):
        raise ValueError(f"Bvh: config must be a BuildConfig, got {type(bvh.config).__name__}")
    if not isinstance(bvh.timings, dict):
        raise ValueError(f"Bvh: timings must be a dict or None, got {type(bvh.timings).__name__}")
    if (bvh.vertices is None) != (bvh.faces is None):
        raise ValueError("Bvh: vertices and faces come together (a tree over a mesh) or not at all (over boxes)")
    fields = [(name, wp.vec3, 1) for name in _VEC3_FIELDS] + [(name, wp.int32, 1) for name in _INT32_FIELDS]
    if bvh.vertices is not None:
        fields += [("vertices", wp.vec3, 1), ("faces", wp.int32, 2)]
    for name, dtype, ndim in fields:
        array = getattr(bvh, name)
        if not isinstance(array, wp.array):
            raise ValueError(f"Bvh: {name} must be a warp array, got {type(array).__name__}")
        if array.dtype != dtype or array.ndim != ndim:
            raise ValueError(f"Bvh: {name} must be a {ndim}-D array of {wp.types.type_repr(dtype)}, got a "
                             f"{array.ndim}-D array of {wp.types.type_repr(array.dtype)}")
        if array.device != bvh.device:
            raise ValueError(f"Bvh: {name} is on {array.device}, the tree on {bvh.device}")
    num_prims = bvh._num_prims
    if num_prims is not None:
        if isinstance(num_prims, bool) or not isinstance(num_prims, (int, np.integer)):
            raise ValueError(f"Bvh: num_prims must be an integer or None, got {type(num_prims).__name__}")
        bvh._num_prims = num_prims = int(num_prims)
    num_prims, num_refs = bvh.num_prims, bvh.num_refs
    if not 1 <= num_prims < MAX_PRIMS:
        raise ValueError(f"Bvh: num_prims must be in [1, {MAX_PRIMS}), got {num_prims}")
    if num_refs < num_prims:
        raise ValueError(f"Bvh: prim_order has {num_refs} entries for num_prims {num_prims}")
    for name in ("prim_lowers", "prim_uppers"):
        if getattr(bvh, name).shape[0] != num_prims:
            raise ValueError(f"Bvh: {name} has {getattr(bvh, name).shape[0]} entries for num_prims {num_prims} "
                             "(a spatial-split tree passes num_prims)")
    lengths = [getattr(bvh, name).shape[0] for name in NODE_FIELDS]
    if min(lengths) == 0 or len(set(lengths)) > 1:
        raise ValueError(f"Bvh: the node arrays must share one length of at least 1, got "
                         f"{dict(zip(NODE_FIELDS, lengths))}")
    if bvh.node_count.shape[0] != 1:
        raise ValueError(f"Bvh: node_count must hold one entry (the nodes in use), got {bvh.node_count.shape[0]}")
    if bvh.faces is not None and bvh.faces.shape != (num_prims, 3):
        raise ValueError(f"Bvh: faces must have shape ({num_prims}, 3), got {bvh.faces.shape}")


def _check_contents(bvh: Bvh) -> None:
    """Raise a ValueError naming the first way a caller-made tree's contents, read back to the
    host, would send a query wrong or out of bounds: the node count past the arrays, a face
    index past the vertices, or what a loaded file is refused for (`storage.check_tree`)."""
    from .storage import check_tree  # deferred: storage imports this module

    capacity = bvh.node_left.shape[0]
    count = int(bvh.node_count.numpy()[0])
    if not 1 <= count <= capacity:
        raise ValueError(f"Bvh: node_count says {count} nodes are in use; the node arrays hold {capacity}")
    triangles = None
    if bvh.vertices is not None:
        vertices, faces = bvh.vertices.numpy(), bvh.faces.numpy()
        if faces.min() < 0 or faces.max() >= vertices.shape[0]:
            raise ValueError(f"Bvh: faces hold a vertex index outside [0, {vertices.shape[0]})")
        # Rays test the triangles, box queries these boxes, and the leaves were checked against
        # these boxes only: boxes other than the triangles' (vertices moved after the build) let
        # a tree through whose leaves miss its triangles. A loaded file's boxes are derived
        # from its triangles, so it cannot differ; a builder's are the same min and max.
        # (A NaN matches a NaN here: the check of the boxes below names it.)
        tri = vertices[faces]
        differs = np.zeros(faces.shape[0], dtype=bool)
        for given, own in ((bvh.prim_lowers.numpy(), tri.min(axis=1)), (bvh.prim_uppers.numpy(), tri.max(axis=1))):
            differs |= ((given != own) & ~(np.isnan(given) & np.isnan(own))).any(axis=1)
        if differs.any():
            raise ValueError(f"Bvh: prim_lowers / prim_uppers are not the boxes of its triangles "
                             f"(first at primitive {int(np.argmax(differs))})")
        if bvh.has_duplicates:  # only a spatial-split tree's leaves are checked against the triangles
            triangles = tri
    tree = {name: getattr(bvh, name).numpy()[:count] for name in NODE_FIELDS}
    tree.update({name: getattr(bvh, name).numpy() for name in ("prim_order", "prim_lowers", "prim_uppers")})
    try:
        check_tree(tree, bvh.num_prims, duplicates=bvh.has_duplicates, triangles=triangles)
    except ValueError as error:
        raise ValueError(f"Bvh: {error}") from None


def node_depths(tree: dict) -> np.ndarray:
    """Depth of every node from the parent links (children are numbered after parents)."""
    parent = tree["node_parent"]
    depth = np.zeros(parent.shape[0], dtype=np.int64)
    ancestor = parent.astype(np.int64)
    # One step up per iteration for every node at once: as many NumPy passes as the tree is deep.
    alive = ancestor >= 0
    while alive.any():
        depth[alive] += 1
        ancestor[alive] = parent[ancestor[alive]]
        alive = ancestor >= 0
    return depth


def bvh_from_numpy(
    *,
    method: str,
    config: BuildConfig,
    device,
    prim_lowers: np.ndarray,
    prim_uppers: np.ndarray,
    prim_order: np.ndarray,
    node_left: np.ndarray,
    node_right: np.ndarray,
    node_begin: np.ndarray,
    node_end: np.ndarray,
    vertices=None,
    faces=None,
    timings=None,
) -> Bvh:
    """Wrap a topology computed on the host (reference builders) and compute its boxes on the device."""
    from . import hlbvh  # deferred: hlbvh imports this module

    num_nodes = node_left.shape[0]
    node_parent = np.full(num_nodes, -1, dtype=np.int32)
    interior = np.nonzero(node_left >= 0)[0]
    node_parent[node_left[interior]] = interior
    node_parent[node_right[interior]] = interior
    if not (node_parent[1:] < np.arange(1, num_nodes)).all():
        raise ValueError("children must be numbered after their parents")

    def dev(a, dtype=wp.int32):
        return wp.array(np.ascontiguousarray(a), dtype=dtype, device=device)

    bvh = Bvh._trusted(
        method=method,
        config=config,
        device=device,
        prim_lowers=prim_lowers if isinstance(prim_lowers, wp.array) else dev(prim_lowers, wp.vec3),
        prim_uppers=prim_uppers if isinstance(prim_uppers, wp.array) else dev(prim_uppers, wp.vec3),
        prim_order=dev(prim_order.astype(np.int32)),
        node_lowers=wp.zeros(num_nodes, dtype=wp.vec3, device=device),
        node_uppers=wp.zeros(num_nodes, dtype=wp.vec3, device=device),
        node_left=dev(node_left.astype(np.int32)),
        node_right=dev(node_right.astype(np.int32)),
        node_parent=dev(node_parent),
        node_begin=dev(node_begin.astype(np.int32)),
        node_end=dev(node_end.astype(np.int32)),
        node_count=dev(np.array([num_nodes], dtype=np.int32)),
        vertices=vertices,
        faces=faces,
        timings=timings,
    )
    hlbvh.refit_bounds(bvh)
    return bvh
