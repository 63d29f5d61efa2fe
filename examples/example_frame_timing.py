# Per-frame BVH rebuild timing for dynamic scenes, like Table 1 of Pantaleoni & Luebke 2010
# (worst and average ms per frame per method), for the exploding and the bending sequences (and
# "static", the mesh at rest, the paper's resorting of an already sorted model): from scratch,
# resorted (fed the previous frame's tree order) and the auto policy, for HLBVH and for
# SAH-optimized HLBVH (the paper's HLBVH+SAH rows), and wp.Bvh rebuilt every frame as the peer.
# Writes a plot of ms per frame (PNG).
#
#   python examples/example_frame_timing.py [--mesh PATH] [--num-frames 24] [--headless]
#       [--sequences explode,bend,static] [--face-order file|shuffled] [--fixed-grid]
#       [--cpu-threads N] [--subdivide K]

import argparse
import os
import time

import numpy as np
import warp as wp

from hlbvh_warp.bench import MAX_SUBDIVIDE, WarpBvhPeer, collector_paused, turn_order
from hlbvh_warp.builder import Builder
from hlbvh_warp.cli import HelpFormatter
from hlbvh_warp.cli import (MAX_TRIS, TRIS_LIMIT, argument_errors, check_out_folder, device_name, int_in_range,
                            mesh_file, non_negative_float, non_negative_int, positive_int, read_mesh, scene_tris)
from hlbvh_warp.config import BuildConfig
from hlbvh_warp import host_morton
from hlbvh_warp.dynamic import BendingMesh, ExplodingMesh
from hlbvh_warp.scenes import scene, subdivide

#: label -> Builder options; "wp.Bvh <constructor>" entries are Warp's own BVH, rebuilt per frame.
MODES = {
    "hlbvh scratch": dict(method="hlbvh", resort=False, policy="rebuild"),
    "hlbvh resorted": dict(method="hlbvh", resort=True, policy="rebuild"),
    "hlbvh auto": dict(method="hlbvh", resort=True, policy="auto"),
    "hlbvh_sah scratch": dict(method="hlbvh_sah", resort=False, policy="rebuild"),
    "hlbvh_sah resorted": dict(method="hlbvh_sah", resort=True, policy="rebuild"),
    "hlbvh_sah auto": dict(method="hlbvh_sah", resort=True, policy="auto"),
    "lbvh scratch": dict(method="lbvh", resort=False, policy="rebuild"),
    "lbvh resorted": dict(method="lbvh", resort=True, policy="rebuild"),
    "wp.Bvh sah": "sah",
    "wp.Bvh lbvh": "lbvh",
}


#: The plot's colour per builder and line style per way of running it (matplotlib's tab10).
PLOT_STYLES = {
    "hlbvh scratch": ("tab:blue", "-"), "hlbvh resorted": ("tab:blue", "--"), "hlbvh auto": ("tab:blue", ":"),
    "hlbvh_sah scratch": ("tab:red", "-"), "hlbvh_sah resorted": ("tab:red", "--"),
    "hlbvh_sah auto": ("tab:red", ":"),
    "lbvh scratch": ("tab:green", "-"), "lbvh resorted": ("tab:green", "--"),
    "wp.Bvh sah": ("tab:gray", "-"), "wp.Bvh lbvh": ("black", "-"),
}


#: The stages of a frame that sort the primitives, resorting's check and gather with them: what
#: feeding the previous tree's order can shorten (the rest costs the same in any order).
SORT_STAGES = ("resort_check", "resort_gather", "order_check", "run_length_encode", "top_level_sort",
               "run_length_decode", "voxel_sort", "global_sort")


def sequence_bounds(anim, param, num_frames):
    """Bounds of the triangle-box centroids over frames 0..num_frames of an animation (its
    ``update`` is a pure function of the frame's parameter)."""
    lower, upper = np.full(3, np.inf), np.full(3, -np.inf)
    for frame in range(num_frames + 1):
        tri = anim.update(param(frame)).numpy()[anim.faces]
        centroids = 0.5 * (tri.min(axis=1) + tri.max(axis=1))
        lower, upper = np.minimum(lower, centroids.min(axis=0)), np.maximum(upper, centroids.max(axis=0))
    anim.update(param(0))
    return (tuple(lower), tuple(upper))


def frame_codes(anim) -> np.ndarray:
    """The 30-bit Morton codes (Morton 1966) of the current frame's triangle-box centroids over their
    bounds, in face order, computed on the host (`hlbvh_warp.host_morton`)."""
    tri = anim.vertices.numpy()[anim.faces]
    return host_morton.morton_codes(0.5 * (tri.min(axis=1) + tri.max(axis=1)))


def order_disorder(codes: np.ndarray, last_codes: np.ndarray) -> tuple:
    """How far from sorted `codes` are in the order that sorts `last_codes` (the input a resorted
    frame feeds its sort, Pantaleoni & Luebke 2010, section 2.2): the fraction of adjacent pairs
    that descend, and the median, mean and 99th percentile of the number of places each primitive
    sits from its place in the stable sorted order."""
    fed = codes[np.argsort(last_codes, kind="stable")]
    descending = float(np.mean(fed[1:] < fed[:-1])) if len(fed) > 1 else 0.0
    place = np.empty(len(fed), dtype=np.int64)
    place[np.argsort(fed, kind="stable")] = np.arange(len(fed))
    distance = np.abs(place - np.arange(len(fed)))
    return descending, float(np.median(distance)), float(distance.mean()), float(np.percentile(distance, 99))


def _cell(value: float, width: int, spec: str) -> str:
    """A table cell, or "-" where a ratio has no reference in this run (no scratch or resorted
    mode of that method was asked for): a NaN column reads as a failure."""
    return f"{value:{width}{spec}}" if np.isfinite(value) else f"{'-':>{width}}"


class Example:
    def __init__(self, mesh=None, num_tris=60000, num_frames=24, sequences=("explode", "bend"), modes=None,
                 headless=False, cpu_threads=0, fixed_grid=False, face_order="file", subdivide_times=0,
                 stages=False, global_sort_runs=None, order_stats=False):
        vertices, faces = subdivide(*scene(mesh, num_tris), subdivide_times)
        if face_order == "shuffled":
            # Scanned meshes list their faces in scan order, already about as coherent as a Morton
            # order, which leaves resorting little to gain; many meshes (merged, decimated or
            # re-meshed ones) keep no such order. A fixed seed keeps runs comparable.
            faces = faces[np.random.default_rng(0).permutation(len(faces))]
        elif face_order != "file":
            raise ValueError(f"face_order must be 'file' or 'shuffled', got {face_order!r}")
        self.num_frames = max(int(num_frames), 1)
        self.num_tris = len(faces)
        self.headless = headless
        self.stages = bool(stages)
        self.order_stats = bool(order_stats)
        self.frame = 0
        device = wp.get_device()
        self.sequences = {}
        for name in sequences:
            if name == "explode":
                anim = ExplodingMesh(vertices, faces, seed=0)
                param = lambda frame: frame / 24.0  # noqa: E731  (24 frames per second)
            elif name == "bend":
                anim = BendingMesh(vertices, faces)
                param = lambda frame, n=self.num_frames: min(frame / n, 1.0)  # noqa: E731
            elif name == "static":
                # The mesh at rest every frame: the paper's Table 1 times its static scenes both
                # from scratch and "resorting", rebuilt once the model is already sorted.
                anim = BendingMesh(vertices, faces)
                param = lambda _frame: 0.0  # noqa: E731  (the same pose every frame)
            else:
                raise ValueError(f"unknown sequence {name!r}")
            config = BuildConfig(cpu_threads=cpu_threads)
            if global_sort_runs is not None:
                config = config.replace(global_sort_runs=global_sort_runs)
            if fixed_grid:
                # One Morton grid for the whole sequence: the bounds of every frame's centroids.
                config = config.replace(morton_bounds=sequence_bounds(anim, param, self.num_frames))
            runners = {}
            for label in modes or MODES:
                options = MODES[label]
                if isinstance(options, str):
                    runner = WarpBvhPeer(len(faces), options, device)
                else:
                    runner = Builder(len(faces), config, device=device, timings=self.stages, **options)
                runner.build(anim.vertices, anim.faces)  # setup and kernel compilation: not timed
                runners[label] = runner
            self.sequences[name] = {"anim": anim, "param": param, "runners": runners,
                                    "ms": {label: [] for label in runners}, "sah": {label: [] for label in runners},
                                    "decisions": {label: [] for label in runners},
                                    "inputs": {label: [] for label in runners},
                                    "stages": {label: [] for label in runners},
                                    "order": [], "last_codes": frame_codes(anim) if self.order_stats else None}

    def step(self):
        """One frame of every sequence, every mode timed on the same vertices (synchronized)."""
        self.frame += 1
        for seq in self.sequences.values():
            vertices = seq["anim"].update(seq["param"](self.frame))
            if self.order_stats:
                # Outside the timed region: how far from sorted this frame's codes are in the
                # order of the last frame's (what resorting would feed the sort).
                codes = frame_codes(seq["anim"])
                seq["order"].append(order_disorder(codes, seq["last_codes"]))
                seq["last_codes"] = codes
            # Each mode runs first, and right after every other mode, equally often: what ran
            # just before a build sets its caches (`turn_order`).
            labels = turn_order(seq["runners"], self.frame)
            # A full garbage collection (75-160 ms here) would land in one random mode's frame.
            with collector_paused():
                for label in labels:
                    runner = seq["runners"][label]
                    wp.synchronize_device()
                    start = time.perf_counter()
                    report = runner.update(vertices)
                    wp.synchronize_device()
                    seq["ms"][label].append((time.perf_counter() - start) * 1e3)
                    seq["decisions"][label].append(report["decision"])
                    # A resorted Builder's rebuild: fed the previous tree's order, or the faces'.
                    seq["inputs"][label].append(report.get("input_order"))
                    seq["stages"][label].append(report.get("stages_ms") or {})
            for label, runner in seq["runners"].items():
                # Tree quality, outside the timed region (Builders only).
                seq["sah"][label].append(runner.sah_cost() if isinstance(runner, Builder) else float("nan"))

    def render(self):
        if self.headless:
            return
        parts = []
        for name, seq in self.sequences.items():
            parts.append(name + ": " + ", ".join(f"{label} {ms[-1]:.1f}" for label, ms in seq["ms"].items()))
        print(f"frame {self.frame:3d} ms  " + " | ".join(parts))

    def table(self) -> str:
        lines = [f"{'sequence':8}  {'mode':18}  {'average ms':>10}  {'worst ms':>8}  {'best ms':>8}  "
                 f"{'vs scratch':>10}  {'worst SAH vs rebuild':>20}  decisions"]
        for name, seq in self.sequences.items():
            for label, ms in seq["ms"].items():
                # Each builder method against itself: from scratch for time, rebuilt every frame
                # (resorted) for tree quality. A mode with no scratch run of its own method (the
                # wp.Bvh peer) is timed against hlbvh scratch, as the footnote says.
                method = label.split()[0]
                base = np.mean(seq["ms"].get(f"{method} scratch", seq["ms"].get("hlbvh scratch", [np.nan])))
                ref_sah = np.asarray(seq["sah"].get(f"{method} resorted", [np.nan] * self.frame))
                ms = np.asarray(ms)
                sah = np.asarray(seq["sah"][label])
                ratio = np.nanmax(sah / ref_sah) if np.isfinite(sah).any() and np.isfinite(ref_sah).any() else np.nan
                counts = {d: seq["decisions"][label].count(d) for d in ("rebuild", "refit", "none")}
                decisions = " ".join(f"{k} {v}" for k, v in counts.items() if v)
                inputs = seq["inputs"][label]
                if any(inputs):
                    decisions += f" (resorted {inputs.count('previous tree')})"
                lines.append(f"{name:8}  {label:18}  {ms.mean():10.2f}  {ms.max():8.2f}  {ms.min():8.2f}  "
                             f"{_cell(ms.mean() / base, 10, '.2f')}  {_cell(ratio, 20, '.3f')}  {decisions}")
        lines.append("vs scratch: average over the same method's scratch average (hlbvh scratch for a method "
                     "run no other way, such as wp.Bvh); worst SAH vs rebuild: against that method resorted")
        if any(any(seq["inputs"][label]) for seq in self.sequences.values() for label in seq["inputs"]):
            lines.append("decisions: frames rebuilt, refitted, left as they were (none); (resorted N): of the "
                         "rebuilt frames, those fed the last frame's tree order (the rest were fed the faces' order: "
                         "lbvh's always, hlbvh's where a sample showed the tree order would not compress)")
        return "\n".join(lines)

    def order_table(self) -> str:
        """Per sequence, the mean over its frames of `order_disorder` (`--order-stats`)."""
        lines = [f"{'sequence':8}  {'descending pairs':>16}  {'median distance':>15}  {'mean distance':>13}  "
                 f"{'99th percentile':>15}"]
        for name, seq in self.sequences.items():
            if seq["order"]:
                mean = np.mean(np.asarray(seq["order"], dtype=np.float64), axis=0)
                lines.append(f"{name:8}  {mean[0]:16.3f}  {mean[1]:15.1f}  {mean[2]:13.1f}  {mean[3]:15.1f}")
        lines.append("the last frame's tree order fed this frame's codes: the fraction of adjacent codes that "
                     "descend, and how many places a primitive sits from its sorted place (means over the frames)")
        return "\n".join(lines)

    def stage_table(self) -> str:
        """Mean ms per frame of each stage of every `Builder` mode (`--stages`), over all frames (a
        stage a frame skipped counts 0 there), and the share of the sort stages: the part of a
        frame resorting can shorten (Pantaleoni & Luebke 2010, section 2.2). A resorted frame whose
        sort cost nothing would take the frame less that share."""
        lines = []
        for name, seq in self.sequences.items():
            for label, frames in seq["stages"].items():
                if not any(frames):
                    continue  # the wp.Bvh peer: no stages
                names = list(dict.fromkeys(stage for frame in frames for stage in frame))
                means = {stage: float(np.mean([frame.get(stage, 0.0) for frame in frames])) for stage in names}
                total = sum(means.values())
                sort = sum(means.get(stage, 0.0) for stage in SORT_STAGES)
                share = sort / total if total > 0.0 else float("nan")
                lines.append(f"{name:8}  {label:18}  stages {total:6.2f} ms, sort stages {sort:5.2f} "
                             f"({_cell(share, 4, '.0%').strip()}): "
                             + " ".join(f"{stage} {ms:.2f}" for stage, ms in means.items()))
        lines.append("stages: mean ms per frame (0 in a frame that skipped it); sort stages: "
                     + ", ".join(SORT_STAGES))
        return "\n".join(lines)

    def plot(self, path):
        """Ms per frame of every mode, one panel per sequence. A colour per builder and a line
        style per way of running it (scratch, resorted, auto), so ten curves read apart; the one
        legend sits right of the panels, where it covers no curve."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, len(self.sequences), figsize=(5.5 * len(self.sequences) + 2.2, 4),
                                 squeeze=False)
        for ax, (name, seq) in zip(axes[0], self.sequences.items()):
            for label, ms in seq["ms"].items():
                color, style = PLOT_STYLES.get(label, (None, "-"))
                ax.plot(np.arange(1, len(ms) + 1), ms, marker=".", color=color, linestyle=style, label=label)
            ax.set_title(f"{name}: {self.num_tris} triangles on {wp.get_device()}")
            ax.set_xlabel("frame")
            ax.set_ylabel("BVH update time per frame (ms)")
            ax.set_ylim(bottom=0)
            ax.grid(True, alpha=0.3)
        handles, labels = axes[0][0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="center right", fontsize=8, title="mode")
        # Room on the right for the legend: tight_layout alone lays the panels under it.
        fig.tight_layout(rect=(0.0, 0.0, 1.0 - 2.0 / fig.get_figwidth(), 1.0))
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        fig.savefig(path, dpi=100)
        plt.close(fig)
        return path


def main(argv=None):
    parser = argparse.ArgumentParser(formatter_class=HelpFormatter)
    parser.add_argument("--device", type=device_name, default=None, help="Override the default Warp device.")
    parser.add_argument("--headless", action="store_true", help="No per-frame progress lines.")
    parser.add_argument("--num-frames", type=positive_int, default=24, help="Total number of frames.")
    parser.add_argument("--mesh", type=mesh_file, default=None,
                        help="Mesh file; the generated default scene if absent.")
    parser.add_argument("--num-tris", type=scene_tris, default=60000, help="Size of the generated scene.")
    parser.add_argument("--sequences", type=str, default="explode,bend",
                        help="Comma-separated: explode, bend, static (the mesh at rest every frame).")
    parser.add_argument("--modes", type=str, default=",".join(MODES), help="Comma-separated subset of the modes.")
    parser.add_argument("--out", type=str, default="hlbvh_example_out", help="Folder for the plot.")
    parser.add_argument("--fixed-grid", action="store_true",
                        help="One Morton grid for the whole sequence (BuildConfig.morton_bounds) instead of "
                             "the centroid bounds of each frame.")
    parser.add_argument("--face-order", choices=("file", "shuffled"), default="file",
                        help="The mesh's faces in their file order, or shuffled (a mesh without a spatial "
                             "face order).")
    parser.add_argument("--cpu-threads", type=non_negative_int, default=0,
                        help="BuildConfig.cpu_threads of the Builders (0: every core; wp.Bvh uses one).")
    # Bounded as bench's: past what a tree holds the split ran out of memory, as a traceback.
    parser.add_argument("--subdivide", type=int_in_range(0, MAX_SUBDIVIDE, f"4^{MAX_SUBDIVIDE + 1} triangles of one "
                                                          "would be more than a tree holds"), default=0,
                        help="Split every triangle into four this many times (a mesh at the paper's sizes).")
    parser.add_argument("--global-sort-runs", type=non_negative_float, default=None,
                        help="BuildConfig.global_sort_runs of the Builders (default: the library's); 1 gives "
                             "every build the paper's compress-sort-decompress, as the paper compares resorting.")
    parser.add_argument("--order-stats", action="store_true",
                        help="Also print how far from sorted each frame's Morton codes are in the last frame's "
                             "order, the input a resorted frame sorts (computed on the host, not timed).")
    parser.add_argument("--stages", action="store_true",
                        help="Time every stage of the Builders' frames and print their means and the share "
                             "of the sort stages (a clock read per stage).")
    args = parser.parse_args(argv)
    unknown = [m for m in args.modes.split(",") if m not in MODES]
    if unknown:
        parser.error(f"unknown mode(s) {unknown}; the modes are {list(MODES)}")
    unknown = [q for q in args.sequences.split(",") if q not in ("explode", "bend", "static")]
    if unknown:
        parser.error(f"unknown sequence(s) {unknown}; the sequences are explode, bend, static")
    # The mesh file and the plot's folder (written even headless) before the first frame, not
    # after the last.
    with argument_errors(parser):
        mesh = read_mesh(args.mesh) if args.mesh else None
        check_out_folder(args.out)
        if args.subdivide:
            # The split's size before the split, on the mesh itself (the generated scene made here
            # and handed on): one triangle becomes 4^k.
            mesh = scene(mesh, args.num_tris)
            count = len(mesh[1]) * 4 ** args.subdivide
            if count > MAX_TRIS:
                raise ValueError(f"--subdivide {args.subdivide}: the mesh has {len(mesh[1])} triangles, {count} once "
                                 f"split; {TRIS_LIMIT}")

    with wp.ScopedDevice(args.device):
        example = Example(mesh, args.num_tris, args.num_frames, args.sequences.split(","),
                          args.modes.split(","), headless=args.headless, cpu_threads=args.cpu_threads,
                          fixed_grid=args.fixed_grid, face_order=args.face_order, subdivide_times=args.subdivide,
                          stages=args.stages, global_sort_runs=args.global_sort_runs,
                          order_stats=args.order_stats)
        for _ in range(args.num_frames):
            example.step()
            example.render()
        print(example.table())
        if args.stages:
            print(example.stage_table())
        if args.order_stats:
            print(example.order_table())
        print(f"wrote {example.plot(os.path.join(args.out, 'frame_timing.png'))}")


if __name__ == "__main__":
    main()
