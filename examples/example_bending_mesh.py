# Bending mesh (Pantaleoni & Luebke 2010, "Bending Armadillo"): the mesh's longest extent is bent
# progressively into an arc. With --policy auto (the default) each frame is skipped, refitted or
# rebuilt as the motion and the SAH cost growth require; a rebuild-every-frame builder runs beside
# it to show the time saved and the SAH cost ratio on every frame.
#
#   python examples/example_bending_mesh.py [--mesh PATH] [--num-frames 24] [--headless]
#       [--view front|right|back|left]

import argparse

import numpy as np
import warp as wp

from hlbvh_warp.builder import PIPELINE_METHODS, Builder
from hlbvh_warp.cli import HelpFormatter
from hlbvh_warp.cli import (argument_errors, check_animation_pixels, check_out_folder, device_name, image_side,
                            mesh_file, non_negative_float, positive_int, read_mesh, scene_tris)
from hlbvh_warp.dynamic import Animation, BendingMesh
from hlbvh_warp.render import VIEWS, Camera
from hlbvh_warp.scenes import scene

# Bend amounts sampled to frame the whole motion: a frame's pose lies within 1/64 of the bend of
# a sampled one, closer than the camera's margin.
SWEEP_SAMPLES = 33


def sweep_camera(mesh: BendingMesh, view: str = "front") -> Camera:
    """A camera framing the mesh over its whole bend, from rest to ``update(1.0)``. The bend
    stretches every layer outside the inner face, so the bent mesh leaves its rest box: a camera
    framing the rest pose cut it off at the image's edges from a third of the bend on. Leaves
    the mesh at rest. ``view`` names the side it looks from (`hlbvh_warp.render.VIEWS`)."""
    lower, upper = np.full(3, np.inf), np.full(3, -np.inf)
    for amount in np.linspace(0.0, 1.0, SWEEP_SAMPLES):
        v = mesh.update(float(amount)).numpy().astype(np.float64)
        lower, upper = np.minimum(lower, v.min(axis=0)), np.maximum(upper, v.max(axis=0))
    mesh.update(0.0)
    return Camera(lower, upper, view=view)


class Example:
    def __init__(self, mesh=None, num_tris=60000, num_frames=24, method="hlbvh", policy="auto", resort=True,
                 image_size=256, headless=False, compare=True, sah_growth_limit=0.10, view="front"):
        vertices, faces = scene(mesh, num_tris)
        self.num_frames = max(int(num_frames), 1)
        self.mesh = BendingMesh(vertices, faces)
        builder = Builder(len(faces), method=method, policy=policy, resort=resort,
                          sah_growth_limit=sah_growth_limit)
        reference = Builder(len(faces), method=method, policy="rebuild", resort=resort) if compare else None
        # None headless: the camera refuses a mesh too large to frame in float32, which a run
        # without images can take.
        camera = None if headless else sweep_camera(self.mesh, view)
        self.animation = Animation(self.mesh, builder, lambda frame: min(frame / self.num_frames, 1.0), camera,
                                   image_size=0 if headless else image_size, reference=reference)
        # The rest pose first in the GIF: the bend is seen from its start.
        self.animation.render()

    def step(self):
        return self.animation.step()

    def render(self):
        self.animation.render()

    def save(self, out_dir):
        return self.animation.save(out_dir, "bending_mesh")


def main(argv=None):
    parser = argparse.ArgumentParser(formatter_class=HelpFormatter)
    parser.add_argument("--device", type=device_name, default=None, help="Override the default Warp device.")
    parser.add_argument("--headless", action="store_true", help="Build only: no ray-cast images.")
    parser.add_argument("--num-frames", type=positive_int, default=24, help="Total number of frames.")
    parser.add_argument("--mesh", type=mesh_file, default=None,
                        help="Mesh file; the generated default scene if absent.")
    parser.add_argument("--num-tris", type=scene_tris, default=60000, help="Size of the generated scene.")
    parser.add_argument("--method", choices=PIPELINE_METHODS, default="hlbvh", help="Build method.")
    parser.add_argument("--policy", choices=("rebuild", "refit", "auto"), default="auto",
                        help="Per frame: rebuild, refit, or let the builder decide.")
    parser.add_argument("--no-resort", action="store_true", help="Rebuild from scratch (input in face order).")
    parser.add_argument("--sah-growth-limit", type=non_negative_float, default=0.10,
                        help="Auto policy: rebuild once refits grow the SAH cost by this fraction.")
    # Bounded as the command line's images: an unbounded size ended in NumPy's MemoryError.
    parser.add_argument("--image-size", type=image_side, default=256, help="Image width and height in pixels.")
    parser.add_argument("--view", choices=tuple(VIEWS), default="front",
                        help="The side of the mesh the camera looks from: front +z, right +x, back -z, left -x "
                             "(a mesh is taken to stand y up facing +z; the armadillo scan faces -z).")
    parser.add_argument("--out", type=str, default="hlbvh_example_out", help="Folder for the PNG and GIF.")
    args = parser.parse_args(argv)
    if not args.headless:
        check_animation_pixels(parser, args.num_frames, args.image_size)
    # The mesh file and the output folder before the first frame, not after the last.
    with argument_errors(parser):
        mesh = read_mesh(args.mesh) if args.mesh else None
        if not args.headless:
            check_out_folder(args.out)

    with wp.ScopedDevice(args.device):
        # A mesh too large to render (the camera past float32's reach) is one line, as a bad option.
        with argument_errors(parser):
            example = Example(mesh, args.num_tris, args.num_frames, args.method, args.policy,
                              not args.no_resort, image_size=args.image_size, headless=args.headless,
                              sah_growth_limit=args.sah_growth_limit, view=args.view)
        for _ in range(args.num_frames):
            example.step()
            example.render()
        print(example.animation.table())
        print(example.animation.legend())
        for path in example.save(args.out):
            print(f"wrote {path}")


if __name__ == "__main__":
    main()
