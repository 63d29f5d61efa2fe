"""``python -m hlbvh_warp bench``: build time against tree quality for every builder.

For each mesh and builder: check a batch of rays against the float64 brute force (reference.py)
before anything is timed, then time the build (median, min, max of ``--repeats`` runs after a
warm-up), record the per-stage breakdown, the SAH cost of Pantaleoni & Luebke 2010 (eq. 1) and
its ratio to the greedy full-sweep SAH tree (their Table 3 reference), the node count and the
bytes of device buffers per triangle. A second time, "rebuild", times per-frame rebuilds on
buffers allocated once (our reusable pipelines against ``wp.Bvh.rebuild``): a one-shot build
also pays for first touching fresh memory, which on some machines costs as much as the build
itself. One fixed-format row per builder is printed and all rows
are written as JSON. Peers on the same device: ``wp.Bvh`` with the "sah", "median" and "lbvh"
constructors and ``wp.Mesh`` (time only: their nodes are not readable here).

``--sweep`` adds the knobs that trade build time for quality (m, p, n, bins, leaf size) and
draws build time (log x) against SAH ratio (y), one point per builder and setting, with the
Pareto frontier marked.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import pathlib
import statistics
import sys
import time
import warnings

import numpy as np
import warp as wp

from . import api, inputs, reference, scenes
from .cli import (MAX_TRIS, TRIS_LIMIT, argument_errors, check_out_file, command_prog, device_name, int_in_range,
                  mesh_file, non_negative_int, positive_int, query_count_or_zero, quiet_warp, read_meshes, tris_count)
from .config import BuildConfig
from .hlbvh import StageTimer
from .kernels import morton
from .launches import RecordedLaunches
from .metrics import sah_cost

#: Our builders, in the order the table lists them.
OUR_BUILDERS = ("hlbvh", "lbvh", "hlbvh_sah", "sweep_sah", "binned_sah", "median")
#: Warp's own builders: wp.Bvh constructors and wp.Mesh.
PEERS = ("wp.Bvh:sah", "wp.Bvh:median", "wp.Bvh:lbvh", "wp.Mesh")
#: The quality reference every SAH ratio is taken against (at the same leaf size).
REFERENCE = "sweep_sah"

ROW_FORMAT = "{mesh:>{mesh_width}s} {tris:>9d} {builder:>14s} {setting:>12s} {median:>10.2f} {min:>9.2f} {max:>9.2f} " \
             "{rebuild:>10s} {sah:>9s} {ratio:>7s} {nodes:>9s} {bytes:>8s} {rays:>6s}"
HEADER_FORMAT = "{:>{w}s} {:>9s} {:>14s} {:>12s} {:>10s} {:>9s} {:>9s} {:>10s} {:>9s} {:>7s} {:>9s} {:>8s} {:>6s}"
HEADER_FIELDS = ("mesh", "tris", "builder", "setting", "median ms", "min ms", "max ms", "rebuild ms", "SAH", "ratio",
                 "nodes", "B/tri", "rays")
#: Most times --subdivide may split a triangle into four: 4^15 = 2^30 triangles of a single one
#: would be more than a tree holds. A mesh's own face count lowers the bound (`subdivided_meshes`).
MAX_SUBDIVIDE = (MAX_TRIS.bit_length() - 1) // 2
#: The mesh column is at least this wide, and as wide as the longest mesh name (never cut).
MESH_WIDTH = 12


def header(mesh_width: int = MESH_WIDTH) -> str:
    return HEADER_FORMAT.format(*HEADER_FIELDS, w=mesh_width)


def generated_scene(num_tris: int = 60000, seed: int = 7):
    """A clustered test scene: spheres of several sizes over a ground grid (uneven density,
    empty space between objects, which is where SAH and Morton splits differ)."""
    import trimesh

    rng = np.random.default_rng(seed)
    parts = []
    ground = trimesh.creation.box(extents=(40.0, 0.2, 40.0))
    parts.append(ground.subdivide().subdivide().subdivide())
    budget = max(num_tris - len(parts[0].faces), 320)
    while budget > 0:
        level = int(rng.integers(1, 5))
        sphere = trimesh.creation.icosphere(subdivisions=level, radius=float(rng.uniform(0.3, 3.0)))
        sphere.apply_translation(rng.uniform((-18, 0.5, -18), (18, 8, 18)))
        parts.append(sphere)
        budget -= len(sphere.faces)
    scene = trimesh.util.concatenate(parts)
    return np.asarray(scene.vertices, np.float32), np.asarray(scene.faces, np.int32)


def sweep_settings(builders) -> list[tuple[str, str, dict]]:
    """(builder, label, BuildConfig overrides): the default of every builder, plus with --sweep
    the knobs that trade time for quality."""
    out = [(b, "default", {}) for b in builders]
    for b in builders:
        if b in ("hlbvh", "hlbvh_sah"):
            out += [(b, f"m={m}", {"coarse_bits": m}) for m in (3, 4, 5, 7, 8)]
            out += [(b, f"n={n}", {"bits_per_axis": n, "coarse_bits": min(6, n)}) for n in (6, 8)]
        if b == "hlbvh_sah":
            # The automatic grid coarsens small clusters (BuildConfig.cluster_min_prims).
            out += [(b, "m=6", {"coarse_bits": 6})]
            out += [(b, f"cluster>={k}", {"cluster_min_prims": k}) for k in (0.0, 3.0, 12.0, 24.0)]
        if b == "hlbvh":
            out += [(b, f"p={p}", {"planes_per_pass": p}) for p in (1, 2, 4)]
            # The same tree by either sort: the paper's compress-sort-decompress on every input,
            # or one radix sort of the full codes on every input (the default picks by the
            # run-length encoding's compression, `BuildConfig.global_sort_runs`).
            out += [(b, "csd", {"global_sort_runs": 1.0}), (b, "global sort", {"global_sort_runs": 0.0})]
        if b == "binned_sah":
            out += [(b, f"bins={k}", {"sah_bins": k}) for k in (4, 8, 32, 64)]
        if b in ("hlbvh", "sweep_sah", "binned_sah", "median", "hlbvh_sah"):
            out += [(b, f"leaf={k}", {"max_leaf_size": k}) for k in (4,)]
    return out


@contextlib.contextmanager
def collector_paused():
    """As timeit does: collect garbage first, keep the collector off inside (a full collection
    costs tens of ms and would land in one random timed run), restore it after."""
    collect_after = gc.isenabled()
    gc.collect()
    gc.disable()
    try:
        yield
    finally:
        if collect_after:
            gc.enable()


def turn_order(labels, turn: int) -> list:
    """The order in which timed modes run in turn `turn` (a frame): the rows of a Williams Latin
    square (Williams 1949), so that each mode runs first, and right after every other mode,
    equally often: once each over ``len(labels)`` turns for an even count, twice each over twice
    that many for an odd one (whose square needs its mirrored rows too).

    What runs just before a build sets its caches: the first after the animation wrote the
    vertices ran about 4% slower here, and one right after ``wp.Bvh`` (which sweeps megabytes)
    slower again. Rotating a fixed order left each mode behind the same one in most turns: in
    ``scratch, resorted, auto, wp.Bvh`` scratch ran after ``wp.Bvh`` three turns in four and
    resorted after scratch, on the same warm vertices, which put resorted at 0.90-0.96 of
    scratch on moving frames where the two ran the same stages (1.02 with the two alone)."""
    labels = list(labels)
    n = len(labels)
    if n < 2:
        return labels
    # First row 0, 1, n-1, 2, n-2, ...: its steps (differences mod n) are all distinct, so its
    # cyclic shifts put each ordered pair side by side once; an odd n needs the mirrored rows too.
    first, low, high = [0], 1, n - 1
    while len(first) < n:
        if len(first) % 2:
            first.append(low)
            low += 1
        else:
            first.append(high)
            high -= 1
    rows = n if n % 2 == 0 else 2 * n
    row = turn % rows
    order = [(x + row) % n for x in first]
    if row >= n:
        order = [(x + row - n) % n for x in first][::-1]
    return [labels[i] for i in order]


class _RecordingLogger:
    """A Warp logger that keeps the warnings (Warp 1.19 sends them through its logger, whose
    default prints them past ``warnings.catch_warnings(record=True)``) and passes the rest on."""

    def __init__(self, inner):
        self.inner, self.messages = inner, []

    def debug(self, message):
        self.inner.debug(message)

    def info(self, message):
        self.inner.info(message)

    def warning(self, message, category=None, stacklevel=1):
        self.messages.append(str(message))

    def error(self, message):
        self.inner.error(message)


@contextlib.contextmanager
def _warp_warnings_recorded():
    """The messages of Warp's logger inside the block (none recorded where Warp has no logger)."""
    if not (hasattr(wp, "get_logger") and hasattr(wp, "set_logger")):
        yield []
        return
    previous = wp.get_logger()
    recorder = _RecordingLogger(previous)
    wp.set_logger(recorder)
    try:
        yield recorder.messages
    finally:
        wp.set_logger(previous)


def _time_interleaved(fns, device, repeats: int, warmup: int) -> list[list[float]]:
    """Times of every callable in `fns`, `repeats` rounds of one run each, in turn. Interleaving
    puts every builder and peer under the same machine load: on a shared machine whose speed
    drifts by tens of percent over a minute, timing one builder after another would move the
    ratios by as much."""
    for fn in fns:
        for _ in range(warmup):
            fn()
    wp.synchronize_device(device)
    times = [[] for _ in fns]
    # Every builder and peer is timed the same way.
    with collector_paused():
        for _ in range(repeats):
            for fn, out in zip(fns, times):
                start = time.perf_counter()
                fn()
                wp.synchronize_device(device)
                out.append((time.perf_counter() - start) * 1e3)
    return times


class WarpBvhPeer:
    """The per-frame peer of the examples: `wp.Bvh` over the triangle boxes, constructed from
    scratch every frame (`build` once with the faces, then `update` with new vertices)."""

    def __init__(self, num_prims, constructor, device):
        self.constructor = constructor
        self.device = wp.get_device(device)
        self.lowers = wp.empty(num_prims, dtype=wp.vec3, device=self.device)
        self.uppers = wp.empty(num_prims, dtype=wp.vec3, device=self.device)
        self.faces = None
        self.bvh = None

    def build(self, vertices, faces):
        self.faces = wp.array(np.asarray(faces, dtype=np.int32), dtype=wp.int32, device=self.device)
        self.update(vertices)

    def update(self, vertices):
        wp.launch(morton.triangle_bounds_kernel, dim=self.lowers.shape[0],
                  inputs=[vertices, self.faces, self.lowers, self.uppers], device=self.device)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # wp.Bvh on the CPU falls back from "lbvh" to "sah"
            self.bvh = wp.Bvh(self.lowers, self.uppers, constructor=self.constructor)
        return {"decision": "rebuild"}


def _summary(times: list[float]) -> dict:
    return {"median": statistics.median(times), "min": min(times), "max": max(times), "runs": times}


def _rebuild_runner(builder, lowers, uppers, config, device):
    """A per-frame rebuild on buffers allocated once (what `Builder` does every frame), to be
    timed like the one-shot builds; None for builders without reusable buffers."""
    from .builders import HlbvhSahPipeline
    from .hlbvh import HlbvhPipeline

    n = lowers.shape[0]
    if builder in ("hlbvh", "lbvh"):
        pipe = HlbvhPipeline(n, config, device)

        def run():
            pipe.build(builder)
    elif builder == "hlbvh_sah":
        pipe = HlbvhSahPipeline(n, config, device)

        def run():
            pipe.build_sah(StageTimer(device, False))
    else:
        return None
    pipe.launches = RecordedLaunches(device)  # as a Builder records its per-frame launches
    wp.copy(pipe.prim_lowers, lowers)
    wp.copy(pipe.prim_uppers, uppers)
    return run


def _bytes_per_tri(bvh, builder: str, num_tris: int, config: BuildConfig, device) -> float | None:
    """Device buffers of the build (pipeline scratch and the tree) plus the primitive boxes, each
    counted once (a builder's ``buffer_bytes`` leaves out the boxes it reads); None for a builder
    that does not count its buffers."""
    from .builders import pipeline_buffer_bytes

    total = getattr(bvh, "buffer_bytes", None)
    if total is None:
        if builder not in ("hlbvh", "lbvh"):
            return None
        total = pipeline_buffer_bytes(num_tris, config, device)
    return (total + 2 * 12 * num_tris) / num_tris


def bench_mesh(name, vertices, faces, args, device, progress) -> list[dict]:
    rng = np.random.default_rng(args.seed)
    verts, tris = inputs.mesh_arrays(vertices, faces)
    n = tris.shape[0]
    lowers_np = verts[tris].min(axis=1)
    uppers_np = verts[tris].max(axis=1)
    lowers = wp.array(lowers_np, dtype=wp.vec3, device=device)
    uppers = wp.array(uppers_np, dtype=wp.vec3, device=device)
    origins, directions = reference.rays_at_box(rng, verts, args.rays)
    t_ref, prim_ref = reference.brute_force_closest_hit(verts, tris, origins, directions)

    ours = [b for b in args.builders if b in api.BUILDERS]
    settings = sweep_settings(ours) if args.sweep else [(b, "default", {}) for b in ours]
    peers = [b for b in args.builders if b in PEERS]
    # Builders that cut triangles (sbvh) take the mesh as well as the boxes, on the device once.
    triangles = (wp.array(verts, dtype=wp.vec3, device=device), wp.array(tris, dtype=wp.int32, device=device))
    rows = []
    reference_cost = {}
    # The reference first, at every leaf size a setting uses, so each ratio has its denominator.
    leaf_sizes = sorted({overrides.get("max_leaf_size", 1) for _, _, overrides in settings})
    for leaf in leaf_sizes:
        ref_bvh = api.build(verts, tris, method=REFERENCE, device=device, config=BuildConfig(max_leaf_size=leaf))
        reference_cost[leaf] = sah_cost(ref_bvh)
    total = len(settings) + len(peers)
    # Every row gets its one-shot runner (and rebuild runner); all are then timed in turn.
    entries = []
    for step, (builder, label, overrides) in enumerate(settings, 1):
        progress(f"[{name} {step}/{total}] {builder} {label}")
        config = BuildConfig(**{"cpu_threads": args.cpu_threads, **overrides})
        # Correctness before speed: a batch of rays against the float64 brute force.
        bvh = api.build(verts, tris, method=builder, device=device, config=config, timings=True)
        t, prim = api_intersect(bvh, origins, directions)
        mismatches = reference.count_mismatches(t, prim, t_ref, prim_ref, rays=(verts, tris, origins, directions))
        if mismatches:
            print(f"error: {builder} {label} on {name}: {mismatches} of {len(t)} rays disagree with the brute "
                  "force; not timed", file=sys.stderr)
            rows.append({"mesh": name, "builder": builder, "setting": label, "error": f"{mismatches} ray mismatches"})
            continue
        fn = api.BUILDERS[builder]
        extra = {"triangles": triangles} if getattr(fn, "needs_triangles", False) else {}

        def run(fn=fn, config=config, extra=extra):
            fn(lowers, uppers, config, device, StageTimer(device, False), **extra)

        cost = sah_cost(bvh, config.sah_traversal_cost, config.sah_intersection_cost)
        row = {
            "mesh": name, "num_tris": n, "builder": builder, "setting": label, "config": overrides,
            "stages_ms": {k: v for k, v in bvh.timings.items() if k != "skipped"},
            "sah": cost, "sah_ratio": cost / reference_cost[config.max_leaf_size],
            "num_nodes": bvh.num_nodes, "bytes_per_tri": _bytes_per_tri(bvh, builder, n, config, device),
            "rays_checked": int(len(t)),
        }
        entries.append((row, run, _rebuild_runner(builder, lowers, uppers, config, device)))
    for step, peer in enumerate(peers, len(settings) + 1):
        progress(f"[{name} {step}/{total}] {peer}")
        rebuild = None
        if peer == "wp.Mesh":
            points = wp.array(verts, dtype=wp.vec3, device=device)
            indices = wp.array(tris.reshape(-1), dtype=wp.int32, device=device)

            def run():
                wp.Mesh(points, indices)
        else:
            constructor = peer.split(":")[1]

            def run(constructor=constructor):
                wp.Bvh(lowers, uppers, constructor=constructor)

        row = {"mesh": name, "num_tris": n, "builder": peer, "setting": "default", "config": {}, "stages_ms": {},
               "sah": None, "sah_ratio": None, "num_nodes": None, "bytes_per_tri": None, "rays_checked": 0}
        try:
            with warnings.catch_warnings(record=True) as caught, _warp_warnings_recorded() as logged:
                warnings.simplefilter("always")
                run()
                if peer != "wp.Mesh":
                    # In-place rebuild on the same buffers: the peer of our reused pipelines.
                    peer_bvh = wp.Bvh(lowers, uppers, constructor=constructor)

                    def rebuild(peer_bvh=peer_bvh, constructor=constructor):
                        peer_bvh.rebuild(constructor)

                    rebuild()
        except Exception as exc:  # a constructor this device lacks (e.g. lbvh on some versions)
            rows.append({"mesh": name, "builder": peer, "setting": "default", "error": str(exc)})
            continue
        # e.g. wp.Bvh's lbvh constructor falls back to sah on the CPU: say so in the row.
        row["notes"] = sorted({str(w.message) for w in caught} | set(logged))
        entries.append((row, run, rebuild))

    progress(f"[{name}] timing {len(entries)} builders in turn, {args.repeats} rounds")
    fns = [run for _, run, _ in entries]
    rebuild_fns = [rebuild for _, _, rebuild in entries if rebuild is not None]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        times = _time_interleaved(fns + rebuild_fns, device, args.repeats, args.warmup)
    rebuild_times = iter(times[len(fns):])
    for (row, _, rebuild), one_shot in zip(entries, times):
        row["time_ms"] = _summary(one_shot)
        row["rebuild_ms"] = _summary(next(rebuild_times)) if rebuild is not None else None
        rows.append(row)
    return rows


def api_intersect(bvh, origins, directions):
    from .query import intersect

    return intersect(bvh, origins, directions)


def format_row(row: dict, mesh_width: int = MESH_WIDTH) -> str:
    if "error" in row:
        return (f"{row['mesh']:>{mesh_width}s} {'':>9s} {row['builder']:>14s} {row['setting']:>12s}"
                f"  error: {row['error']}")

    def opt(value, fmt):
        return "-" if value is None else format(value, fmt)

    return ROW_FORMAT.format(
        mesh=row["mesh"], mesh_width=mesh_width, tris=row["num_tris"], builder=row["builder"],
        setting=row["setting"][:12],
        median=row["time_ms"]["median"], min=row["time_ms"]["min"], max=row["time_ms"]["max"],
        rebuild=opt((row.get("rebuild_ms") or {}).get("median"), ".2f"),
        sah=opt(row["sah"], ".2f"), ratio=opt(row["sah_ratio"], ".3f"), nodes=opt(row["num_nodes"], "d"),
        bytes=opt(row["bytes_per_tri"], ".0f"), rays="ok" if row["rays_checked"] else "-",
    )


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats in both time and ratio, by increasing time."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], float("inf")
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


def plot(rows: list[dict], path: pathlib.Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    meshes = sorted({r["mesh"] for r in rows})
    fig, axes = plt.subplots(1, len(meshes), figsize=(7 * len(meshes), 5.5), squeeze=False)
    for ax, mesh in zip(axes[0], meshes):
        pts = [r for r in rows if r["mesh"] == mesh and r.get("sah_ratio") is not None]
        builders = sorted({r["builder"] for r in pts})
        for k, builder in enumerate(builders):
            sel = [r for r in pts if r["builder"] == builder]
            ax.scatter([r["time_ms"]["median"] for r in sel], [r["sah_ratio"] for r in sel], label=builder,
                       color=f"C{k}", s=28)
            for r in sel:
                if r["setting"] != "default":
                    ax.annotate(r["setting"], (r["time_ms"]["median"], r["sah_ratio"]), fontsize=6,
                                xytext=(3, 2), textcoords="offset points")
        xy = [(r["time_ms"]["median"], r["sah_ratio"]) for r in pts]
        front = pareto_front(xy)
        if front:
            ax.plot([xy[i][0] for i in front], [xy[i][1] for i in front], "k--", lw=1, label="Pareto frontier")
        for r in rows:
            if r["mesh"] == mesh and r.get("sah_ratio") is None and "time_ms" in r:
                ax.axvline(r["time_ms"]["median"], color="0.6", lw=0.8, ls=":")
                ax.annotate(r["builder"], (r["time_ms"]["median"], 1.0), rotation=90, fontsize=6, color="0.4")
        ax.set_xscale("log")
        ax.set_xlabel("build time, median (ms, log)")
        ax.set_ylabel(f"SAH cost / {REFERENCE}")
        ax.set_title(f"{mesh} ({pts[0]['num_tris'] if pts else 0} triangles)")
        ax.grid(True, which="both", alpha=0.3)
        # Only wp.Mesh (no SAH, so no points): a legend of nothing, which Matplotlib warns about.
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def subdivided_meshes(paths, times: int) -> list:
    """``(name, vertices, faces)`` of every mesh file, each triangle split into four ``times``
    times. Every file is read and checked (`read_meshes`), and its size after the split checked,
    before the first is split: a split past what a tree holds ran out of memory (21 GB at
    ``--subdivide 30``) before the build could refuse it.

    Raises:
        ValueError: a file is no valid mesh, or the split would make more than `MAX_TRIS`
            triangles; the file is named.
    """
    read = read_meshes(paths)
    for (name, _, faces), path in zip(read, paths):
        count = faces.shape[0] * 4 ** times
        if count > MAX_TRIS:
            raise ValueError(f"--subdivide {times}: {path} has {faces.shape[0]} triangles, {count} once split; "
                             f"{TRIS_LIMIT}")
    suffix = f"_sub{times}" if times else ""
    return [(name + suffix, *scenes.subdivide(vertices, faces, times)) for name, vertices, faces in read]


def parse_args(argv):
    parser = argparse.ArgumentParser(prog=command_prog("bench"), description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", action="append", default=[], type=mesh_file,
                        help="mesh file (repeatable); default: a generated scene")
    parser.add_argument("--subdivide", type=int_in_range(0, MAX_SUBDIVIDE, f"4^{MAX_SUBDIVIDE + 1} triangles of one "
                                                          "would be more than a tree holds"), default=0,
                        help="split every triangle of each mesh into four this many times (the paper's sizes; "
                             "default: %(default)s)")
    parser.add_argument("--scene-tris", type=tris_count, default=60000,
                        help="triangles of the generated scene (default: %(default)s)")
    parser.add_argument("--builders", default=",".join(OUR_BUILDERS + PEERS),
                        help="comma-separated builders and peers (default: %(default)s; the offline recursive_sah and "
                             "sbvh on request)")
    parser.add_argument("--device", type=device_name, default=None, help="Warp device (default: Warp's default device)")
    parser.add_argument("--repeats", type=positive_int, default=5, help="timed runs per builder (default: %(default)s)")
    parser.add_argument("--warmup", type=non_negative_int, default=1,
                        help="untimed runs first (kernel compilation, caches; default: %(default)s)")
    parser.add_argument("--rays", type=query_count_or_zero, default=128,
                        help="rays checked against the brute force (default: %(default)s)")
    parser.add_argument("--sweep", action="store_true", help="also sweep m, p, n, bins and leaf size")
    parser.add_argument("--json", default="out/bench.json", help="where to write the rows (default: %(default)s)")
    parser.add_argument("--plot", default=None, help="PNG of time vs SAH ratio (default: beside the JSON)")
    parser.add_argument("--seed", type=non_negative_int, default=1,
                        help="seed of the generated scene and the checked rays (default: %(default)s)")
    parser.add_argument("--cpu-threads", type=non_negative_int, default=0,
                        help="BuildConfig.cpu_threads of our builders (0: every core; 1: one thread, like wp.Bvh; "
                             "default: %(default)s)")
    args = parser.parse_args(argv)
    args.builders = [b.strip() for b in args.builders.split(",") if b.strip()]
    api._load_optional_builders()
    if not args.builders:
        # Named here: an empty list used to reach the plot and end in matplotlib's "Number of
        # columns must be a positive integer, not 0".
        parser.error(f"--builders names no builder; choose from {sorted(api.BUILDERS) + list(PEERS)}")
    unknown = [b for b in args.builders if b not in api.BUILDERS and b not in PEERS]
    if unknown:
        parser.error(f"unknown builders {unknown}; choose from {sorted(api.BUILDERS) + list(PEERS)}")
    # Before the run: a path that cannot be written failed only after every builder was timed.
    with argument_errors(parser):
        check_out_file(args.json, "--json")
        # The default plot beside the JSON is checked as a given one: a folder there was found
        # only after every builder was timed.
        check_out_file(plot_path(args), "--plot")
        # The plot is written after the JSON: at the same path (--json b.png, whose plot goes
        # beside it at b.png itself) it replaced the rows.
        if plot_path(args).resolve() == pathlib.Path(args.json).resolve():
            raise ValueError(f"--plot {plot_path(args)} is the --json file; the plot would replace the rows "
                             "(give the JSON another name, or --plot another path)")
    return args


def plot_path(args) -> pathlib.Path:
    """Where the plot goes: ``--plot``, else beside the JSON with the suffix ``.png``."""
    return pathlib.Path(args.plot) if args.plot else pathlib.Path(args.json).with_suffix(".png")


def main(argv=None) -> int:
    args = parse_args(list(sys.argv[1:] if argv is None else argv))
    quiet_warp()
    wp.init()
    device = wp.get_device(args.device)
    meshes = subdivided_meshes(args.mesh, args.subdivide)
    if not meshes:
        meshes = [("generated", *generated_scene(args.scene_tris, args.seed))]

    progress = scenes.progress

    threads = args.cpu_threads or "all cores"
    print(f"device: {device}  repeats: {args.repeats}  warm-up: {args.warmup}  cpu_threads: {threads}")
    mesh_width = max([MESH_WIDTH] + [len(name) for name, _, _ in meshes])
    print(header(mesh_width))
    rows = []
    for name, vertices, faces in meshes:
        for row in bench_mesh(name, vertices, faces, args, device, progress):
            rows.append(row)
        progress("")
        for row in rows:
            if row["mesh"] == name:
                print(format_row(row, mesh_width), flush=True)
    json_path = pathlib.Path(args.json)
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps({"device": str(device), "repeats": args.repeats, "cpu_threads": args.cpu_threads,
                                     "rows": rows}, indent=1))
    png_path = plot_path(args)
    png_path.parent.mkdir(parents=True, exist_ok=True)
    plot(rows, png_path)
    print(f"wrote {json_path} and {png_path}")
    return 1 if any("error" in r and r["builder"] not in PEERS for r in rows) else 0
