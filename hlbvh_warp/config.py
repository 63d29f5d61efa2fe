"""Build settings: one documented dataclass, no module-level knobs."""

from __future__ import annotations

import dataclasses

import numpy as np

# The traversal stack's depth, the kernels' own, for the callers that weigh a tree's depth against it.
from .kernels.traversal import TRAVERSAL_STACK_SIZE  # noqa: F401

#: Morton codes live in int32 (the radix sort's key type): 3 * 10 = 30 bits at most.
MAX_BITS_PER_AXIS = 10
#: A treelet pass keeps its 2^p - 1 split slots in a fixed-size local vector.
MAX_PLANES_PER_PASS = 4
#: Schedules of the hierarchy emission (stage 6); "auto" picks by device.
EMISSIONS = ("auto", "treelets", "depth_first")


def _shown(value) -> str:
    """A setting's value for a message: Python refuses to print an integer of more than 4300
    digits (its int_max_str_digits), so one that long is described instead, inside a tuple or
    list too (a ``morton_bounds`` corner)."""
    if isinstance(value, int) and value.bit_length() > 1000:
        return f"an integer of about {int(value.bit_length() * 0.30103)} digits"
    if isinstance(value, (tuple, list)):
        inner = ", ".join(_shown(x) for x in value)
        return f"({inner}{',' if len(value) == 1 else ''})" if isinstance(value, tuple) else f"[{inner}]"
    return repr(value)


@dataclasses.dataclass(frozen=True)
class BuildConfig:
    """Settings of the HLBVH build (Pantaleoni & Luebke, HPG 2010) and of the builders beside it.

    Attributes:
        bits_per_axis: n, Morton bits per axis; codes have 3n bits (paper: n = 10, 30-bit codes).
        coarse_bits: m, bits per axis of the coarse voxel grid whose 3m-bit codes are run-length
            encoded and sorted by compress-sort-decompress. ``None`` picks it from the primitive
            count after the paper, which used m = 6 for meshes up to 1M triangles and m = 7 for 10M
            (section 3.1): here m = 6 up to 2^21 (about 2M) primitives, m = 7 above.
        planes_per_pass: p, Morton bit planes consumed by one treelet-emission pass (1 to 4);
            each pass emits treelets of up to 2^p leaves.
        block_capacity: voxel segments are grouped into blocks of about this many primitives
            for the block-local sort by the low 3(n - m) bits (paper: 2000).
        max_leaf_size: segments of at most this many primitives become leaves. 1 gives the
            paper's setup of exactly 2N - 1 nodes. ``hlbvh_sah`` applies it inside its clusters
            only: its cluster tree splits down to one cluster per node whatever the primitive
            count, so its leaves can be smaller and its nodes more than the other builders' (with
            ``max_leaf_size >= N`` they give one leaf, it gives 2C - 1 nodes over C clusters).
        sah_traversal_cost: T1 of the paper's SAH cost (eq. 1), per child visited; finite, >= 0.
        sah_intersection_cost: T2 of the paper's SAH cost, per primitive in a leaf; finite, > 0.
        sah_bins: bins per axis of the ``binned_sah`` builder.
        recursive_sah_bins: bins per axis of the ``recursive_sah`` builder's own splits
            (Wodniok & Goesele 2016: 256 for RBVH, 64 for RBVH*).
        recursive_sah_temp_bins: bins per axis of its temporary BVHs (the paper: 32; at most 32).
        sbvh_bins: bins per axis of the ``sbvh`` builder (Stich et al. 2009), for its object splits
            (centroid bins) and its spatial splits (equal slabs of the node's box); at most 64.
        sbvh_alpha: the ``sbvh`` builder tries spatial splits only where the best object split's
            two boxes overlap by more than this fraction of the root's surface area (Stich et
            al.'s alpha; 1e-5 as they and Wodniok & Goesele use; ``inf`` turns spatial splits off).
        sbvh_max_duplication: the ``sbvh`` builder holds at most (1 + this) x N references: a
            memory bound. Spatial splits past it fall back to the node's object split (in node
            order within a level).
        cluster_min_prims: ``hlbvh_sah`` with an automatic m (``coarse_bits=None``) only: while
            its clusters (the non-empty coarse voxels) hold fewer primitives than this on
            average, they are merged into the voxels of the grid one bit coarser per axis.
            The paper's clusters hold 33-66 triangles (1M triangles in 15k-30k clusters at
            m = 6); on a small mesh m = 6 leaves a few triangles per cluster and the cluster tree
            becomes a full SAH build over a large share of the primitives. 0 keeps the m-bit
            voxels. The default is measured in the README (the knob sweep and the
            ``hlbvh_sah`` notes under "Build time against tree quality").
        emission: how the hierarchy emission is scheduled; both give the same tree, up to node
            numbering. ``"treelets"`` is the paper's: passes of p bit planes over every open
            segment at once, each pass a foreach over primitives, a scan of split counts and a
            foreach over segments (Fig. 4) -- data-parallel, for CUDA. ``"depth_first"`` gives
            one thread a whole subtree and walks it with a stack, splitting each range at its
            highest differing bit by binary search: for Warp's CPU device, which runs a launch's
            threads one after another, so that passes rescanning all N primitives cost time
            without buying parallelism. ``"auto"`` (default) picks ``"depth_first"`` on the CPU
            and ``"treelets"`` elsewhere.
        morton_bounds: ``None`` (default): the Morton grid spans the centroid bounds of the
            primitives being built, recomputed every build, as the paper does. Or a fixed box
            ``((x0, y0, z0), (x1, y1, z1))``, e.g. the bounds of a whole animation: centroids
            outside it fall into the border cells. Over a fixed grid a primitive's code changes
            only when it moves across cells, so the previous frame's tree order stays almost
            sorted (resorting, the paper's section 2.2); over a per-frame grid every code moves
            whenever the scene's bounds do (a bending or exploding mesh). The box must hold the
            geometry: the tree stays correct when centroids leave it, but those sharing a border
            cell share a code and split by input order, and the SAH cost grows (1.6-1.9x the cost
            over a per-frame grid, measured on a small mesh moved wholly outside the box).
        global_sort_runs: HLBVH's compress-sort-decompress pays off when the run-length
            encoding by the high 3m bits compresses (the paper's premise: M runs << N). Where it
            leaves more than this many runs per primitive (scattered fragments, faces in no
            spatial order), the build sorts the full codes in one radix sort instead, which gives
            the same order (both are stable sorts of the codes) for less work; its timings list
            ``global_sort`` and the three skipped stages. On the CPU, a sample of 1024 adjacent
            pairs of the codes (`HlbvhPipeline.sampled_run_fraction`) decides first, and a sample past
            this limit skips the encoding as well (its timings list all four skipped). Default
            0.1: on the CPU, Warp's radix sort of the full codes beat the paper's stages at every
            M / N from 0.2 to 1 on the 100k-triangle armadillo, in any face order (1.2 ms
            against 2.4-3.8 for the sort stages), and at 400k triangles down to a resorted
            frame's M / N of 0.1 (5.6 against 6.2 ms); only near-sorted input at M / N 0.03
            sorted faster the paper's way (5.4 against 5.7). At 0.3 a resorting `Builder` took
            the paper's sort on smoothly bending meshes (240 frames at 70k-100k triangles, 48
            at 400k; M / N 0.1-0.27 in the previous order) and spent 12-22% more a frame than
            from scratch; at 0.1, 0-2% more.
            1 keeps the paper's pipeline for every build, resorting included (`Builder`).
            Not for builds that need the voxels (``hlbvh_sah``'s clusters) or keep their counts
            on the device (sync-free CUDA).
        cpu_threads: on the CPU device, how many threads run the independent subtrees of the
            depth-first stages side by side (``hlbvh_warp.threads``); 0 (default) uses every core
            the process may run on, 1 runs them one after another; more than four per usable core
            count as four per core. The tree does not depend on it.
    """

    bits_per_axis: int = 10
    coarse_bits: int | None = None
    planes_per_pass: int = 3
    block_capacity: int = 2000
    max_leaf_size: int = 1
    sah_traversal_cost: float = 1.0
    sah_intersection_cost: float = 1.0
    sah_bins: int = 16
    recursive_sah_bins: int = 64
    recursive_sah_temp_bins: int = 32
    sbvh_bins: int = 32
    sbvh_alpha: float = 1e-5
    sbvh_max_duplication: float = 1.0
    cluster_min_prims: float = 6.0
    emission: str = "auto"
    cpu_threads: int = 0
    morton_bounds: tuple | None = None
    global_sort_runs: float = 0.1

    def __post_init__(self):
        # Types first, so a wrong one raises a ValueError naming the field, not a TypeError from a
        # comparison or a kernel launch that cannot pack a float into an int parameter.
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if field.name in ("coarse_bits", "morton_bounds") and value is None:
                continue
            if field.type.startswith("int"):
                if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                    raise ValueError(f"BuildConfig: {field.name} must be an integer (got {value!r})")
                # Kernels take these as int32, which wraps silently: a block_capacity of 2^32
                # reached the voxel sort as 0 and divided by it (SIGFPE, the process gone).
                if not -(1 << 31) <= int(value) < 1 << 31:
                    raise ValueError(f"BuildConfig: {field.name} must fit in int32 (got {_shown(value)})")
                object.__setattr__(self, field.name, int(value))
            elif field.type == "float":
                if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
                    raise ValueError(f"BuildConfig: {field.name} must be a number (got {value!r})")
                try:
                    object.__setattr__(self, field.name, float(value))
                except OverflowError:
                    # float() of an integer past float's range (10**400) raises, not a ValueError.
                    raise ValueError(f"BuildConfig: {field.name} is too large for a float "
                                     f"(got {_shown(value)})") from None
            elif field.type == "str" and not isinstance(value, str):
                raise ValueError(f"BuildConfig: {field.name} must be a string (got {value!r})")
        checks = [
            (1 <= self.bits_per_axis <= MAX_BITS_PER_AXIS, f"bits_per_axis must be in [1, {MAX_BITS_PER_AXIS}]"),
            (
                self.coarse_bits is None or 0 <= self.coarse_bits <= self.bits_per_axis,
                "coarse_bits must be None or in [0, bits_per_axis]",
            ),
            (1 <= self.planes_per_pass <= MAX_PLANES_PER_PASS,
             f"planes_per_pass must be in [1, {MAX_PLANES_PER_PASS}]"),
            (self.block_capacity >= 1, "block_capacity must be >= 1"),
            (1 <= self.max_leaf_size <= 1 << 16, "max_leaf_size must be in [1, 65536]"),
            # Finite, as metrics.check_costs requires: an infinite constant made every split and
            # cluster cost infinite (a tree far worse than the default's) and then failed the
            # first time a Builder priced its tree.
            (np.isfinite(self.sah_traversal_cost) and self.sah_traversal_cost >= 0.0,
             "sah_traversal_cost must be finite and >= 0"),
            (np.isfinite(self.sah_intersection_cost) and self.sah_intersection_cost > 0.0,
             "sah_intersection_cost must be finite and > 0"),
            (2 <= self.sah_bins <= 256, "sah_bins must be in [2, 256]"),
            (2 <= self.recursive_sah_bins <= 256, "recursive_sah_bins must be in [2, 256]"),
            (2 <= self.recursive_sah_temp_bins <= 32, "recursive_sah_temp_bins must be in [2, 32]"),
            (2 <= self.sbvh_bins <= 64, "sbvh_bins must be in [2, 64]"),
            (not np.isnan(self.sbvh_alpha) and self.sbvh_alpha >= 0.0, "sbvh_alpha must be >= 0"),
            (np.isfinite(self.sbvh_max_duplication) and self.sbvh_max_duplication >= 0.0,
             "sbvh_max_duplication must be finite and >= 0"),
            (self.cluster_min_prims >= 0.0, "cluster_min_prims must be >= 0"),
            (self.emission in EMISSIONS, f"emission must be one of {EMISSIONS}"),
            (self.cpu_threads >= 0, "cpu_threads must be >= 0"),
            (self.global_sort_runs >= 0.0, "global_sort_runs must be >= 0"),
        ]
        for ok, message in checks:
            if not ok:
                # The config as its repr shows it, but through `_shown`: morton_bounds is not checked
                # yet, and a corner of more than 4300 digits made the repr itself raise.
                shown = ", ".join(f"{f.name}={_shown(getattr(self, f.name))}" for f in dataclasses.fields(self))
                raise ValueError(f"BuildConfig: {message} (got BuildConfig({shown}))")
        if self.morton_bounds is not None:
            try:
                box = np.asarray(self.morton_bounds, dtype=np.float64)
            except (TypeError, ValueError):
                box = np.zeros(0)
            except OverflowError:
                # An integer past float64's range (10**400): NumPy raises an OverflowError, not the
                # ValueError every other bad setting gets.
                raise ValueError(f"BuildConfig: morton_bounds must lie within the float32 range "
                                 f"(got {_shown(self.morton_bounds)})") from None
            if box.shape != (2, 3):
                raise ValueError(f"BuildConfig: morton_bounds must be ((x0, y0, z0), (x1, y1, z1)) "
                                 f"(got {_shown(self.morton_bounds)})")
            # NumPy reads "0" and True as numbers; every other number field refuses them.
            if any(isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, float, np.integer, np.floating))
                   for row in self.morton_bounds for x in row):
                raise ValueError(f"BuildConfig: morton_bounds must hold numbers (got {self.morton_bounds!r})")
            if not np.all(np.isfinite(box)):
                raise ValueError(f"BuildConfig: morton_bounds must be finite (got {self.morton_bounds!r})")
            # The grid reaches the kernels as float32, where 1e39 is inf: every centroid then
            # quantized to cell 0 (a tree in input order), where the float64 box would not.
            if np.abs(box).max() > np.finfo(np.float32).max:
                raise ValueError(f"BuildConfig: morton_bounds must lie within the float32 range "
                                 f"(got {self.morton_bounds!r})")
            if np.any(box[0] > box[1]):
                raise ValueError(f"BuildConfig: morton_bounds lower corner exceeds the upper one "
                                 f"(got {self.morton_bounds!r})")
            # Plain floats, so the config stays hashable and prints the same either way.
            object.__setattr__(self, "morton_bounds", tuple(tuple(float(x) for x in row) for row in box))

    def resolved_coarse_bits(self, num_prims: int) -> int:
        """m for `num_prims` primitives: the paper uses m = 6 up to ~1M triangles and m = 7 for ~10M."""
        if self.coarse_bits is not None:
            return self.coarse_bits
        m = 6 if num_prims <= (1 << 21) else 7
        return min(m, self.bits_per_axis)

    def resolved_emission(self, device) -> str:
        """The emission schedule on `device` (a ``wp.Device``): ``"auto"`` resolved by device kind."""
        if self.emission != "auto":
            return self.emission
        return "depth_first" if device.is_cpu else "treelets"

    def replace(self, **changes) -> "BuildConfig":
        """A copy with the given fields changed (`dataclasses.replace`), validated like any new config."""
        return dataclasses.replace(self, **changes)
