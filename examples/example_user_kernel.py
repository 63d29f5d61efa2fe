"""Queries from a user's own kernel: shade a mesh with closest-hit, shadow and box queries.

A `hlbvh_warp.query.BvhView` is passed to the kernel like any struct; inside, the ``@wp.func``
queries `bvh_closest_hit` (t, primitive, barycentrics), `bvh_occluded` (a shadow ray over the range
from 0 to the light that ignores the triangle it starts on) and `bvh_aabb_count` (triangles whose
box overlaps a box around the hit) do the work. Each frame moves the light and renders a small
image; ``render`` saves it with matplotlib unless headless (``user_kernel_000.png``, ... in
``--out``).

    python examples/example_user_kernel.py --headless --num-frames 4
"""

from __future__ import annotations

import argparse
import os

import numpy as np
import warp as wp

import hlbvh_warp
from hlbvh_warp import query
from hlbvh_warp.cli import HelpFormatter
from hlbvh_warp.cli import argument_errors, check_out_folder, device_name, image_side, positive_int


@wp.kernel
def shade_kernel(
    bvh: query.BvhView,
    eye: wp.vec3,
    light: wp.vec3,
    width: int,
    height: int,
    half_extent: float,
    neighbourhood: float,
    image: wp.array2d(dtype=float),
    crowding: wp.array2d(dtype=wp.int32),
):
    i, j = wp.tid()
    # A pinhole camera looking down -z.
    x = (2.0 * (float(j) + 0.5) / float(width) - 1.0) * half_extent
    y = (1.0 - 2.0 * (float(i) + 0.5) / float(height)) * half_extent
    direction = wp.normalize(wp.vec3(x, y, -1.0))
    hit = query.bvh_closest_hit(bvh, eye, direction, 1.0e30)
    value = float(0.0)
    count = int(0)
    if hit.prim >= 0:
        a = bvh.vertices[bvh.faces[hit.prim, 0]]
        b = bvh.vertices[bvh.faces[hit.prim, 1]]
        c = bvh.vertices[bvh.faces[hit.prim, 2]]
        # The hit point from the barycentrics, on the triangle rather than along the ray.
        p = (1.0 - hit.u - hit.v) * a + hit.u * b + hit.v * c
        n = wp.normalize(wp.cross(b - a, c - a))
        if wp.dot(n, direction) > 0.0:
            n = -n
        to_light = light - p
        dist = wp.length(to_light)
        to_light = to_light / dist
        # The shadow ray starts on the surface and ignores the triangle it leaves, which rounding
        # would otherwise let it hit at t near 0; no offset to tune to the scene's scale.
        lit = 1.0 - float(query.bvh_occluded(bvh, p, to_light, 0.0, dist, hit.prim))
        value = 0.1 + 0.9 * lit * wp.max(wp.dot(n, to_light), 0.0)
        r = wp.vec3(neighbourhood)
        count = query.bvh_aabb_count(bvh, p - r, p + r)
    image[i, j] = value
    crowding[i, j] = count


class Example:
    def __init__(self, mesh=None, resolution: int = 64):
        import trimesh

        if mesh is None:
            mesh = trimesh.creation.icosphere(subdivisions=3)
            floor = trimesh.creation.box(extents=(4.0, 4.0, 0.1)).apply_translation((0, 0, -1.2))
            mesh = trimesh.util.concatenate([mesh, floor])
        self.bvh = hlbvh_warp.build(mesh)
        self.view = query.view(self.bvh)
        self.center = np.asarray(mesh.bounds.mean(axis=0), dtype=np.float32)
        self.radius = float(np.linalg.norm(mesh.extents)) * 0.5
        self.resolution = resolution
        self.image = wp.zeros((resolution, resolution), dtype=float)
        self.crowding = wp.zeros((resolution, resolution), dtype=wp.int32)
        self.frame = 0

    def step(self):
        angle = 0.5 * self.frame
        eye = self.center + np.array([0.0, 0.0, 2.5 * self.radius], dtype=np.float32)
        light = self.center + self.radius * np.array([2.0 * np.cos(angle), 2.0 * np.sin(angle), 2.0], dtype=np.float32)
        wp.launch(
            shade_kernel,
            dim=(self.resolution, self.resolution),
            inputs=[self.view, wp.vec3(*eye), wp.vec3(*light), self.resolution, self.resolution, 0.45,
                    0.05 * self.radius, self.image, self.crowding],
        )
        self.frame += 1

    def render(self, path=None):
        if path is None:
            return
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        plt.imsave(path, self.image.numpy(), cmap="gray", vmin=0.0, vmax=1.0)


def main(argv=None):
    parser = argparse.ArgumentParser(formatter_class=HelpFormatter)
    parser.add_argument("--device", type=device_name, default=None, help="Override the default Warp device.")
    parser.add_argument("--num-frames", type=positive_int, default=8, help="Total number of frames.")
    # Bounded as the command line's images: an unbounded size ended in Warp's allocation error.
    parser.add_argument("--resolution", type=image_side, default=128, help="Image width and height in pixels.")
    parser.add_argument("--headless", action="store_true", help="Run without writing images.")
    parser.add_argument("--out", type=str, default="hlbvh_example_out",
                        help="Folder for the frames (user_kernel_000.png, ...).")
    args = parser.parse_args(argv)
    # The output folder before the first frame, not after it.
    if not args.headless:
        with argument_errors(parser):
            check_out_folder(args.out)

    with wp.ScopedDevice(args.device):
        example = Example(resolution=args.resolution)
        for k in range(args.num_frames):
            example.step()
            example.render(None if args.headless else os.path.join(args.out, f"user_kernel_{k:03d}.png"))
        print(f"{args.num_frames} frames, lit fraction {float((example.image.numpy() > 0.15).mean()):.3f}")


if __name__ == "__main__":
    main()
