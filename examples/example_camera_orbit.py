"""A camera orbit rendered through every builder's tree at every branching factor.

Garczorz (2026) renders a 36-frame camera orbit through BVHs of branching factor k = 2, 4, 8
and 16 from several builders, and requires the images to be identical. Here each frame's primary
rays go through the wide trees (`hlbvh_warp.wide`) of every builder in ``--methods`` at every
width in ``--widths``. The reference is the library's own binary traversal of the first
builder's tree. Each tree's hits are compared with the reference's ray by ray. Two triangles hit
at the same distance count as agreeing: a ray through a shared edge may report either. The shaded
pixels are compared too. The table gives ms per frame per tree, and the disagreements, which must
be 0.

    python examples/example_camera_orbit.py --headless --num-frames 36
"""

from __future__ import annotations

import argparse
import pathlib
import time

import numpy as np
import warp as wp

import hlbvh_warp
from hlbvh_warp import api, query, reference, render, scenes, wide
from hlbvh_warp.cli import HelpFormatter
from hlbvh_warp.cli import (argument_errors, check_animation_pixels, check_out_folder, device_name, image_side,
                            mesh_file, positive_int, read_mesh, scene_tris)
from hlbvh_warp.kernels import traversal


class Example:
    def __init__(self, mesh_path=None, num_tris: int = 20000, methods=("hlbvh", "hlbvh_sah", "sweep_sah", "median"),
                 widths=(2, 4, 8, 16), resolution: int = 128, num_frames: int = 36, headless: bool = False):
        self.vertices, self.faces = scenes.scene(mesh_path, num_tris)
        self.resolution = resolution
        self.num_frames = num_frames
        self.headless = headless
        self.binaries = {m: hlbvh_warp.build(self.vertices, self.faces, method=m) for m in methods}
        self.reference_method = methods[0]
        self.trees = {(m, k): wide.collapse(bvh, k) for m, bvh in self.binaries.items() for k in widths}
        self.lower, self.upper = self.vertices.min(axis=0), self.vertices.max(axis=0)
        # Every frame's camera made once before the first frame: one refuses a mesh too large to
        # frame in float32, whose images were all sky.
        for frame in range(num_frames):
            self.camera(frame)
        n = resolution * resolution
        self.hit_t = wp.empty(n, dtype=float)
        self.hit_prim = wp.empty(n, dtype=wp.int32)
        self.no_counts = wp.empty(0, dtype=wp.vec3i)
        self.ms = {key: [] for key in [("binary", self.reference_method)] + list(self.trees)}
        self.disagree = {key: 0 for key in self.trees}
        self.pixels_differ = {key: 0 for key in self.trees}
        self.images = []
        self.image = None
        self.frame = 0

    def camera(self, frame: int) -> render.Camera:
        angle = 2.0 * np.pi * frame / self.num_frames
        return render.Camera(self.lower, self.upper, direction=(np.sin(angle), 0.35, np.cos(angle)))

    def _trace(self, launch) -> tuple:
        wp.synchronize_device()
        start = time.perf_counter()
        launch()
        wp.synchronize_device()
        return 1e3 * (time.perf_counter() - start), self.hit_t.numpy(), self.hit_prim.numpy()

    def step(self):
        origins, directions = self.camera(self.frame).rays(self.resolution, self.resolution)
        o = wp.array(origins, dtype=wp.vec3)
        d = wp.array(directions, dtype=wp.vec3)
        n = len(origins)
        view = query.view(self.binaries[self.reference_method])
        ms, t_ref, prim_ref = self._trace(lambda: wp.launch(
            traversal.closest_hit_kernel, dim=n, inputs=[view, o, d, float("inf"), self.hit_t, self.hit_prim]))
        self.ms[("binary", self.reference_method)].append(ms)
        size = self.resolution
        self.image = render.shade(self.vertices, self.faces, prim_ref, directions, size, size)
        for key, tree in self.trees.items():
            kernel, inputs = wide.launch_args(tree, o, d, float("inf"), self.hit_t, self.hit_prim, self.no_counts)
            ms, t, prim = self._trace(lambda kernel=kernel, inputs=inputs: wp.launch(kernel, dim=n, inputs=inputs))
            self.ms[key].append(ms)
            self.disagree[key] += reference.count_mismatches(t, prim, t_ref, prim_ref)
            image = render.shade(self.vertices, self.faces, prim, directions, size, size)
            self.pixels_differ[key] += int((image != self.image).any(axis=-1).sum())
        self.frame += 1

    def render(self):
        if not self.headless and self.image is not None:
            self.images.append(self.image)

    def save(self, out_dir) -> list:
        if self.headless or not self.images:
            return []
        out_dir = pathlib.Path(out_dir)
        return [render.save_png(self.images[-1], out_dir / "camera_orbit.png"),
                render.save_gif(self.images, out_dir / "camera_orbit.gif")]

    def table(self) -> str:
        """Mean ms per frame of each tree (the first frame, which compiles, left out when there
        are more), against the binary traversal of the reference tree."""
        def mean(values):
            return float(np.mean(values[1:] if len(values) > 1 else values))

        base = mean(self.ms[("binary", self.reference_method)])
        lines = [f"{'tree':>24s} {'ms/frame':>9s} {'x binary':>9s} {'disagree':>9s} {'pixels':>7s}",
                 f"{'binary ' + self.reference_method:>24s} {base:9.2f} {1.0:9.2f} {0:9d} {0:7d}"]
        for (method, k), values in ((key, v) for key, v in self.ms.items() if key in self.trees):
            ms = mean(values)
            lines.append(f"{f'{method} k={k}':>24s} {ms:9.2f} {base / ms:9.2f} {self.disagree[(method, k)]:9d} "
                         f"{self.pixels_differ[(method, k)]:7d}")
        lines.append(f"ms/frame: mean over the frames (the first, which compiles, left out); x binary: the binary "
                     f"traversal's ms/frame over this tree's (above 1: faster than binary); disagree: rays whose "
                     f"hit differs from binary {self.reference_method}'s; pixels: shaded pixels that differ")
        return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(formatter_class=HelpFormatter)
    parser.add_argument("--device", type=device_name, default=None, help="Override the default Warp device.")
    parser.add_argument("--num-frames", type=positive_int, default=36, help="Frames of the orbit.")
    parser.add_argument("--mesh", type=mesh_file, default=None, help="A mesh file; the generated scene if absent.")
    parser.add_argument("--num-tris", type=scene_tris, default=20000, help="Triangles of the generated scene.")
    parser.add_argument("--methods", type=str, default="hlbvh,hlbvh_sah,sweep_sah,median", help="Builders.")
    parser.add_argument("--widths", type=str, default="2,4,8,16", help="Branching factors.")
    # Bounded as the command line's images: an unbounded size ended in Warp's array-shape error.
    parser.add_argument("--resolution", type=image_side, default=128, help="Image width and height in pixels.")
    parser.add_argument("--headless", action="store_true", help="Run without writing images.")
    parser.add_argument("--out", type=str, default="hlbvh_example_out", help="Folder for the PNG and GIF.")
    args = parser.parse_args(argv)
    if not args.headless:
        check_animation_pixels(parser, args.num_frames, args.resolution, "--resolution")
    widths = tuple(int(k) for k in args.widths.split(",") if k.strip().isdigit())
    if len(widths) != len(args.widths.split(",")) or not all(k in wide.WIDTHS for k in widths):
        parser.error(f"--widths takes branching factors from {wide.WIDTHS[0]} to {wide.WIDTHS[-1]}, got {args.widths}")
    # Every builder name before the first build: a wrong one failed in build() and an empty list
    # in indexing no methods, both as tracebacks.
    api._load_optional_builders()
    methods = tuple(dict.fromkeys(m.strip() for m in args.methods.split(",") if m.strip()))
    if not methods:
        parser.error(f"--methods {args.methods!r} names no builder; choose from {sorted(api.BUILDERS)}")
    unknown = [m for m in methods if m not in api.BUILDERS]
    if unknown:
        parser.error(f"unknown builder(s) {unknown} in --methods; choose from {sorted(api.BUILDERS)}")
    # The mesh file and the output folder before the first frame, not after the last.
    with argument_errors(parser):
        mesh = read_mesh(args.mesh) if args.mesh else None
        if not args.headless:
            check_out_folder(args.out)

    with wp.ScopedDevice(args.device):
        # A mesh too large to render (the camera past float32's reach) is one line, as a bad option.
        with argument_errors(parser):
            example = Example(mesh, args.num_tris, methods, widths, args.resolution, args.num_frames, args.headless)
        for _ in range(args.num_frames):
            example.step()
            example.render()
        print(example.table())
        for path in example.save(args.out):
            print(f"wrote {path}")


if __name__ == "__main__":
    main()
