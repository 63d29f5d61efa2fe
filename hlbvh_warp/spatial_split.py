"""``"sbvh"``: the spatial-split BVH of Stich, Friedrich & Dietrich (HPG 2009).

A greedy top-down SAH builder whose nodes may split space as well as the primitive set: a triangle
that straddles the chosen plane is referenced from both children, each reference boxed by its
side's part of the triangle. Where long or diagonal triangles make object splits overlap, that
removes the overlap at the price of duplicated references; Wodniok & Goesele (GI 2016) measured it
14.4% below a plane-sweep BVH in SAH and 64.3% below in EPO on average over ten scenes.

The tree is built one level at a time: one thread per node searches its binned object and
spatial splits (``kernels/spatial_split.py``); the host keeps each node's cheaper split within the
reference budget (``BuildConfig.sbvh_max_duplication``), numbers the children and scans the
output offsets; a second launch writes every node's references into the next level's arrays,
leaves included, so each level's array holds every reference in tree order and the last one is
``prim_order``. Reads back a few words per node per level: an offline builder.

The result is a `Bvh` whose ``prim_order`` may list a triangle more than once
(``Bvh.num_refs >= Bvh.num_prims``). Closest-hit, any-hit and all-hit ray queries, the SAH and
EPO metrics and wide collapses take it as it is. Box queries do not (a reference's box bounds
a part of its triangle, not the triangle's box) and raise. A refit bounds every reference by its
whole triangle again: still a correct tree, no longer the spatial splits' boxes.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from . import threads as threads_module
from .bvh import Bvh
from .config import BuildConfig
from .hlbvh import StageTimer
from .kernels import spatial_split as kernels

#: Segments per CPU slice when a level has many nodes (sizes vary by orders of magnitude).
CPU_SLICES_PER_THREAD = 16


def _launch(kernel, num: int, args: list, config: BuildConfig, device):
    threads = threads_module.resolved_threads(config, device)
    if threads > 1 and num > 1:
        cuts = threads_module.split_bounds(num, min(num, CPU_SLICES_PER_THREAD * threads))
        parts = [(hi - lo, [lo] + args) for lo, hi in zip(cuts, cuts[1:]) if hi > lo]
        threads_module.launch_parts(kernel, device, parts, threads)
    else:
        wp.launch(kernel, dim=num, inputs=[0] + args, device=device)


def build_sbvh(prim_lowers: wp.array, prim_uppers: wp.array, config: BuildConfig, device, timer: StageTimer,
               triangles: tuple) -> Bvh:
    """The SBVH of the triangles ``(vertices, faces)`` (device arrays) whose boxes are
    ``prim_lowers/uppers``. Splits down to ``config.max_leaf_size`` references per leaf."""
    device = wp.get_device(device)
    vertices, faces = triangles
    n = prim_lowers.shape[0]
    num_bins = config.sbvh_bins
    # (1 + d) N overflows float64 to inf for a finite d near its largest value (1e308, which the
    # config takes), and int(inf) raises: capped far past any tree's references instead.
    max_refs = int(min(np.floor((1.0 + config.sbvh_max_duplication) * n), 2.0**62))
    timer.stage("top_down")
    lowers_np = prim_lowers.numpy()
    uppers_np = prim_uppers.numpy()
    root_area = _area(lowers_np.min(axis=0), uppers_np.max(axis=0))
    alpha = float(config.sbvh_alpha)

    ref_tri = wp.array(np.arange(n, dtype=np.int32), dtype=wp.int32, device=device)
    ref_lo = wp.clone(prim_lowers)
    ref_hi = wp.clone(prim_uppers)
    # Host bookkeeping of the level: one segment per node, open (to be split) or a finished leaf.
    seg_node = np.zeros(1, np.int64)
    seg_begin = np.zeros(1, np.int64)
    seg_end = np.full(1, n, np.int64)
    seg_open = np.ones(1, bool)
    arena = []  # per level: (split nodes, their left children)
    # Room for the tree without duplicates (2n - 1 nodes), grown as levels need more: the budget
    # bounds the tree at 2 max_refs - 1 nodes, but a large budget (meant as "no limit") is
    # rarely spent, and allocating for it up front could ask for terabytes.
    node_left = np.full(max(2 * n - 1, 1), -1, np.int32)
    node_lo = np.zeros((len(node_left), 3), np.float32)
    node_hi = np.zeros((len(node_left), 3), np.float32)
    num_nodes = 1
    while True:
        num_seg = len(seg_node)
        dev = _SegmentArrays(num_seg, device)
        dev.upload(begin=seg_begin, end=seg_end, open=seg_open)
        _launch(kernels.split_search_kernel, num_seg,
                [dev.begin, dev.end, dev.open, ref_tri, ref_lo, ref_hi, vertices, faces, num_bins,
                 config.max_leaf_size, wp.float64(root_area), wp.float64(alpha), dev.lo, dev.hi, dev.cen_lo,
                 dev.cen_hi, dev.obj_axis, dev.obj_bin, dev.obj_left, dev.obj_cost, dev.sp_axis, dev.sp_bin,
                 dev.sp_left, dev.sp_right, dev.sp_cost], config, device)
        found = dev.download()
        node_lo[seg_node[seg_open]] = found["lo"][seg_open]
        node_hi[seg_node[seg_open]] = found["hi"][seg_open]
        sizes = seg_end - seg_begin
        split = seg_open & (sizes > config.max_leaf_size)
        if not split.any():
            break
        kind = np.full(num_seg, int(kernels.KIND_LEAF), np.int32)
        axis = np.zeros(num_seg, np.int32)
        bin_ = np.zeros(num_seg, np.int32)
        left_count = sizes.astype(np.int64).copy()
        right_count = np.zeros(num_seg, np.int64)
        has_obj = split & (found["obj_axis"] >= 0)
        has_sp = split & (found["sp_axis"] >= 0)
        prefer_sp = has_sp & (~has_obj | (found["sp_cost"] < found["obj_cost"]))
        # The reference budget, spent in node order: past it a node takes its object split.
        extra = np.where(prefer_sp, found["sp_left"] + found["sp_right"] - sizes, 0)
        total_refs = int(sizes.sum())
        prefer_sp &= np.cumsum(extra) <= max_refs - total_refs
        use_obj = has_obj & ~prefer_sp
        halve = split & ~has_obj & ~prefer_sp
        kind[use_obj] = kernels.KIND_OBJECT
        axis[use_obj] = found["obj_axis"][use_obj]
        bin_[use_obj] = found["obj_bin"][use_obj]
        left_count[use_obj] = found["obj_left"][use_obj]
        kind[prefer_sp] = kernels.KIND_SPATIAL
        axis[prefer_sp] = found["sp_axis"][prefer_sp]
        bin_[prefer_sp] = found["sp_bin"][prefer_sp]
        left_count[prefer_sp] = found["sp_left"][prefer_sp]
        kind[halve] = kernels.KIND_HALVE
        left_count[halve] = sizes[halve] // 2
        right_count[split] = np.where(prefer_sp[split], found["sp_right"][split], sizes[split] - left_count[split])
        out_count = np.where(split, left_count + right_count, sizes)
        out_begin = np.concatenate([[0], np.cumsum(out_count)[:-1]])
        num_refs = int(out_count.sum())

        out_tri = wp.empty(num_refs, dtype=wp.int32, device=device)
        out_lo = wp.empty(num_refs, dtype=wp.vec3, device=device)
        out_hi = wp.empty(num_refs, dtype=wp.vec3, device=device)
        dev.upload(kind=kind, axis=axis, bin=bin_, left=left_count, out=out_begin)
        _launch(kernels.distribute_kernel, num_seg,
                [dev.begin, dev.end, dev.kind, dev.axis, dev.bin, dev.left, dev.out, dev.lo, dev.hi, dev.cen_lo,
                 dev.cen_hi, num_bins, ref_tri, ref_lo, ref_hi, vertices, faces, out_tri, out_lo, out_hi],
                config, device)
        ref_tri, ref_lo, ref_hi = out_tri, out_lo, out_hi

        # Children are numbered after every node so far, two per split node, in segment order.
        parents = seg_node[split]
        first_child = num_nodes + 2 * np.arange(len(parents))
        arena.append((parents, first_child))
        if num_nodes + 2 * len(parents) > len(node_left):
            grow = max(num_nodes + 2 * len(parents), 2 * len(node_left)) - len(node_left)
            node_left = np.concatenate([node_left, np.full(grow, -1, np.int32)])
            node_lo = np.concatenate([node_lo, np.zeros((grow, 3), np.float32)])
            node_hi = np.concatenate([node_hi, np.zeros((grow, 3), np.float32)])
        node_left[parents] = first_child
        num_nodes += 2 * len(parents)
        # The next level's segments: a leaf stays one, a split node becomes its two children.
        reps = np.where(split, 2, 1)
        new_node = np.repeat(seg_node, reps)
        new_begin = np.repeat(out_begin, reps)
        new_end = np.repeat(out_begin + out_count, reps)
        new_open = np.repeat(split, reps)
        first = np.concatenate([[0], np.cumsum(reps)[:-1]])[split]
        new_node[first] = first_child
        new_node[first + 1] = first_child + 1
        new_end[first] = out_begin[split] + left_count[split]
        new_begin[first + 1] = out_begin[split] + left_count[split]
        seg_node, seg_begin, seg_end, seg_open = new_node, new_begin, new_end, new_open

    timer.stage("bbox")
    left = node_left[:num_nodes]
    right = np.where(left >= 0, left + 1, -1).astype(np.int32)
    begin = np.zeros(num_nodes, np.int64)
    end = np.zeros(num_nodes, np.int64)
    begin[seg_node] = seg_begin
    end[seg_node] = seg_end
    for parents, first_child in reversed(arena):
        begin[parents] = begin[first_child]
        end[parents] = end[first_child + 1]
    parent = np.full(num_nodes, -1, np.int32)
    interior = np.nonzero(left >= 0)[0]
    parent[left[interior]] = interior
    parent[right[interior]] = interior

    def ints(a):
        return wp.array(np.ascontiguousarray(a, dtype=np.int32), dtype=wp.int32, device=device)

    return Bvh._trusted(
        method="sbvh",
        config=config,
        device=device,
        prim_lowers=prim_lowers,
        prim_uppers=prim_uppers,
        prim_order=ref_tri,
        node_lowers=wp.array(node_lo[:num_nodes], dtype=wp.vec3, device=device),
        node_uppers=wp.array(node_hi[:num_nodes], dtype=wp.vec3, device=device),
        node_left=ints(left),
        node_right=ints(right),
        node_parent=ints(parent),
        node_begin=ints(begin),
        node_end=ints(end),
        node_count=ints([num_nodes]),
        num_prims=n,
        timings=timer.finish(),
    )


def root_split_costs(vertices, faces, config: BuildConfig | None = None, device=None) -> dict:
    """The root's cheapest object split and cheapest spatial split as the split search prices them
    (A(L) N(L) + A(R) N(R), ``inf`` where there is none), and their axes and bin boundaries: what
    `build_sbvh` chooses between at the top of the tree, the SBVH's choice of Stich, Friedrich &
    Dietrich (HPG 2009). For tests and diagnostics."""
    from . import inputs

    config = config or BuildConfig()
    device = wp.get_device(device)
    verts_np, faces_np = inputs.mesh_arrays(vertices, faces)
    tris = verts_np[faces_np]
    lo, hi = tris.min(axis=1), tris.max(axis=1)
    n = len(faces_np)
    dev = _SegmentArrays(1, device)
    dev.upload(begin=[0], end=[n], open=[1])
    ref_prims = wp.array(np.arange(n, dtype=np.int32), dtype=wp.int32, device=device)
    wp.launch(kernels.split_search_kernel, dim=1, device=device,
              inputs=[0, dev.begin, dev.end, dev.open, ref_prims,
                      wp.array(lo, dtype=wp.vec3, device=device), wp.array(hi, dtype=wp.vec3, device=device),
                      wp.array(verts_np, dtype=wp.vec3, device=device),
                      wp.array(faces_np, dtype=wp.int32, device=device), config.sbvh_bins, config.max_leaf_size,
                      wp.float64(_area(lo.min(axis=0), hi.max(axis=0))), wp.float64(config.sbvh_alpha), dev.lo,
                      dev.hi, dev.cen_lo, dev.cen_hi, dev.obj_axis, dev.obj_bin, dev.obj_left, dev.obj_cost,
                      dev.sp_axis, dev.sp_bin, dev.sp_left, dev.sp_right, dev.sp_cost])
    found = {name: value[0] for name, value in dev.download().items()}
    return {
        "object": float(found["obj_cost"]) if found["obj_axis"] >= 0 else np.inf,
        "object_axis": int(found["obj_axis"]), "object_bin": int(found["obj_bin"]),
        "spatial": float(found["sp_cost"]) if found["sp_axis"] >= 0 else np.inf,
        "spatial_axis": int(found["sp_axis"]), "spatial_bin": int(found["sp_bin"]),
    }


def _area(lower: np.ndarray, upper: np.ndarray) -> float:
    d = upper.astype(np.float64) - lower.astype(np.float64)
    return float(2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0]))


class _SegmentArrays:
    """The device side of one level's segments: inputs, the split search's outputs, the choice."""

    def __init__(self, num: int, device):
        def ints():
            return wp.zeros(num, dtype=wp.int32, device=device)

        def vecs():
            return wp.zeros(num, dtype=wp.vec3, device=device)

        self.device = device
        self.begin, self.end, self.open = ints(), ints(), ints()
        self.lo, self.hi, self.cen_lo, self.cen_hi = vecs(), vecs(), vecs(), vecs()
        self.obj_axis, self.obj_bin, self.obj_left = ints(), ints(), ints()
        self.obj_cost = wp.zeros(num, dtype=wp.float64, device=device)
        self.sp_axis, self.sp_bin, self.sp_left, self.sp_right = ints(), ints(), ints(), ints()
        self.sp_cost = wp.zeros(num, dtype=wp.float64, device=device)
        self.kind, self.axis, self.bin, self.left, self.out = ints(), ints(), ints(), ints(), ints()

    def _put(self, name: str, values):
        getattr(self, name).assign(np.ascontiguousarray(values, dtype=np.int32))

    def upload(self, **values):
        """Copy host values into the named int32 arrays, e.g. ``upload(begin=..., end=...)``."""
        for name, v in values.items():
            self._put(name, v)

    def download(self) -> dict:
        """The split search's outputs as NumPy, keyed by name (side counts as int64)."""
        names = ("lo", "hi", "obj_axis", "obj_bin", "obj_left", "obj_cost", "sp_axis", "sp_bin", "sp_left",
                 "sp_right", "sp_cost")
        out = {name: getattr(self, name).numpy() for name in names}
        for name in ("obj_left", "sp_left", "sp_right"):
            out[name] = out[name].astype(np.int64)
        return out
