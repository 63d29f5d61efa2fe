# Mesh collision: a copy of a mesh, turned a quarter turn, passes through the mesh. The moving
# copy's tree is kept by a `Builder` with the adaptive policy, which decides per frame (the copy
# moves a tenth of the mesh's diagonal a frame, large motion: it rebuilds); the resting mesh is
# built once.
# Every frame, `hlbvh_warp.intersecting_pairs` finds the triangle pairs that intersect: a broad
# phase of each triangle's box through the other tree, then the exact triangle-triangle test.
# The table lists each frame's tree decision, the candidate and intersecting pairs, and the time
# of the update and of the query. Writes a side view of the frame with the most contact
# (mesh_collision.png in --out): the resting mesh grey, the moving copy blue, the triangles in
# contact red.
#
#   python examples/example_mesh_collision.py [--mesh PATH] [--num-tris 20000] [--num-frames 24]
#       [--headless]

import argparse
import os
import time

import numpy as np
import warp as wp

import hlbvh_warp as hb
from hlbvh_warp.builder import Builder
from hlbvh_warp.cli import HelpFormatter
from hlbvh_warp.cli import (argument_errors, check_out_folder, device_name, mesh_file, positive_int, read_mesh,
                            scene_tris)
# Largest finite float32: the moving copy's vertices go to the Builder in float32.
from hlbvh_warp.reference import FLOAT32_MAX
from hlbvh_warp.render import FIGURE_DPI, legend_below, save_figure
from hlbvh_warp.scenes import scene

# The copy starts and ends this many box diagonals from the mesh's centre along x: clear of it.
TRAVEL = 1.2
#: Pixels per inch of the picture.


def quarter_turn(vertices: np.ndarray) -> np.ndarray:
    """The mesh turned by 90 degrees about x through its box centre."""
    center = 0.5 * (vertices.min(0) + vertices.max(0))
    turn = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    return (vertices - center) @ turn.T + center


def diagonal(vertices) -> float:
    """The length of the box diagonal, in float64: float32's squares overflow past 1.8e19."""
    v = np.asarray(vertices, dtype=np.float64)
    return float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))


def copy_reach(vertices) -> float:
    """An upper bound on the moving copy's coordinates over the whole pass, in float64: the turned
    mesh's largest one plus its travel."""
    return float(np.abs(quarter_turn(np.asarray(vertices, dtype=np.float64))).max()) + TRAVEL * diagonal(vertices)


class Example:
    def __init__(self, mesh=None, num_tris=20000, num_frames=24, headless=False):
        vertices, faces = scene(mesh, num_tris)
        self.vertices = vertices.astype(np.float64)
        self.faces = faces
        self.num_frames = max(int(num_frames), 1)
        self.resting = hb.build(vertices, faces, method="hlbvh")
        self.diag = diagonal(self.vertices)
        self.turned = quarter_turn(self.vertices)
        self.builder = Builder(len(faces), policy="auto")
        self.builder.build(self.position(0).astype(np.float32), faces)
        self.headless = headless
        self.frame = 0
        self.rows = []
        self.pairs = np.zeros((0, 2), np.int64)
        # (pair count, moving vertices, pairs, frame) of the frame with the most contact.
        self.most = (0, None, None, 0)

    def position(self, frame: int) -> np.ndarray:
        """The moving copy's vertices at ``frame``: from -TRAVEL to +TRAVEL diagonals along x."""
        s = frame / self.num_frames
        return self.turned + np.array([(2.0 * s - 1.0) * TRAVEL * self.diag, 0.0, 0.0])

    def step(self):
        self.frame += 1
        start = time.perf_counter()
        moving = self.position(self.frame).astype(np.float32)
        self.builder.update(moving)
        wp.synchronize_device()
        built = time.perf_counter()
        candidates = len(hb.overlapping_pairs(self.resting, self.builder.bvh))
        self.pairs = hb.intersecting_pairs(self.resting, self.builder.bvh)
        done = time.perf_counter()
        self.rows.append({
            "frame": self.frame,
            "decision": self.builder.last_report["decision"],
            "candidates": candidates,
            "intersecting": len(self.pairs),
            "update_ms": 1e3 * (built - start),
            "query_ms": 1e3 * (done - built),
        })
        if len(self.pairs) > self.most[0]:
            self.most = (len(self.pairs), moving, self.pairs, self.frame)

    def figure(self):
        """A side view (along y: x across, z up) of the frame with the most contact, as a matplotlib
        figure whose title says the frame and the counts and whose legend says the colours: the
        resting mesh's vertices grey, the moving copy's blue, and in red the centroid of every
        triangle, of either mesh, in an intersecting pair. The red is drawn last, over the rest."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        _, moving, pairs, frame = self.most
        if moving is None:
            moving, pairs, frame = self.position(self.frame), self.pairs, self.frame
        fig = plt.figure(figsize=(7.0, 5.0), dpi=FIGURE_DPI)
        # A fixed layout (no tight box at the save): the title above, the legend below, and the
        # data's pixels where the axes' transform puts them.
        ax = fig.add_axes((0.02, 0.12, 0.96, 0.74))
        ax.scatter(self.vertices[:, 0], self.vertices[:, 2], s=0.2, c="0.6", linewidths=0,
                   label="resting mesh (its vertices)")
        ax.scatter(moving[:, 0], moving[:, 2], s=0.2, c="tab:blue", linewidths=0,
                   label="moving copy, turned a quarter turn (its vertices)")
        resting_hit, moving_hit = np.unique(pairs[:, 0]), np.unique(pairs[:, 1])
        centroids = np.concatenate([self.vertices[self.faces[resting_hit]].mean(axis=1),
                                    moving[self.faces[moving_hit]].mean(axis=1)])
        ax.scatter(centroids[:, 0], centroids[:, 2], s=4, c="tab:red", linewidths=0,
                   label="triangles intersecting the other mesh (their centroids)")
        ax.set_aspect("equal")
        ax.set_axis_off()
        fig.suptitle(f"Mesh collision, frame {frame} of {self.num_frames} (the most contact), side view along y\n"
                     f"{len(pairs)} intersecting triangle pairs: {len(resting_hit)} resting and "
                     f"{len(moving_hit)} moving triangles", fontsize=10)
        legend_below(fig, ax)
        return fig

    def render(self, path=None):
        """Write `figure` as a PNG to ``path`` (its folder made); None headless or without a path."""
        if self.headless or path is None:
            return
        save_figure(self.figure(), path)
        return path

    def table(self) -> str:
        lines = [f"{'frame':>5s} {'tree':8s} {'candidates':>10s} {'intersecting':>12s} {'update ms':>9s} "
                 f"{'query ms':>8s}"]
        for r in self.rows:
            lines.append(f"{r['frame']:5d} {r['decision']:8s} {r['candidates']:10d} {r['intersecting']:12d} "
                         f"{r['update_ms']:9.2f} {r['query_ms']:8.2f}")
        return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(formatter_class=HelpFormatter)
    parser.add_argument("--device", type=device_name, default=None, help="Override the default Warp device.")
    parser.add_argument("--headless", action="store_true", help="Run without writing the picture.")
    parser.add_argument("--num-frames", type=positive_int, default=24, help="Total number of frames.")
    parser.add_argument("--mesh", type=mesh_file, default=None,
                        help="Mesh file; the generated default scene if absent.")
    parser.add_argument("--num-tris", type=scene_tris, default=20000, help="Size of the generated scene.")
    parser.add_argument("--out", type=str, default="hlbvh_example_out",
                        help="Folder for the picture of the frame with the most contact (mesh_collision.png).")
    args = parser.parse_args(argv)
    # The mesh file and the picture's path before the first frame, not after the last.
    with argument_errors(parser):
        mesh = read_mesh(args.mesh) if args.mesh else None
        # A finite mesh whose copy leaves float32's range on its pass (coordinates near 3e38) is
        # named here, not by the Builder's "NaN or Inf coordinate" for vertices the example made.
        if mesh is not None and not copy_reach(mesh[0]) <= FLOAT32_MAX:
            raise ValueError(f"{args.mesh}: the moving copy, turned and carried {TRAVEL} box diagonals to either side, "
                             f"reaches {copy_reach(mesh[0]):.3g}, past float32's largest {FLOAT32_MAX:.3g}; scale "
                             "the mesh down")
        if not args.headless:
            check_out_folder(args.out)

    with wp.ScopedDevice(args.device):
        example = Example(mesh, args.num_tris, args.num_frames, headless=args.headless)
        print(f"self-intersections of the resting mesh: {len(hb.intersecting_pairs(example.resting))}")
        for _ in range(args.num_frames):
            example.step()
        print(example.table())
        print("tree: what the moving copy's Builder (auto policy) did this frame; candidates: triangle pairs "
              "whose boxes overlap; intersecting: those whose triangles intersect; update ms: the Builder's update; "
              "query ms: both pair queries")
        written = example.render(os.path.join(args.out, "mesh_collision.png"))
        if written:
            print(f"wrote {written}")


if __name__ == "__main__":
    main()
