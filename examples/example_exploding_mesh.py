# Exploding mesh (Pantaleoni & Luebke 2010, "Exploding Turbine Blade"): the mesh is blasted into
# its triangles, each flying with a random velocity and spin, and the BVH is rebuilt every frame
# with resorting (each build is fed the primitives in the previous frame's tree order).
#
#   python examples/example_exploding_mesh.py [--mesh PATH] [--num-frames 24] [--headless]
#       [--view front|right|back|left]

import argparse

import warp as wp

from hlbvh_warp.builder import PIPELINE_METHODS, Builder
from hlbvh_warp.cli import HelpFormatter
from hlbvh_warp.cli import (argument_errors, check_animation_pixels, check_out_folder, device_name, image_side,
                            mesh_file, positive_int, read_mesh, scene_tris)
from hlbvh_warp.dynamic import Animation, ExplodingMesh
from hlbvh_warp.render import VIEWS, Camera
from hlbvh_warp.scenes import scene


class Example:
    def __init__(self, mesh=None, num_tris=60000, method="hlbvh", policy="rebuild", resort=True, fps=24.0,
                 image_size=256, headless=False, speed=0.5, view="front"):
        vertices, faces = scene(mesh, num_tris)
        self.frame_dt = 1.0 / fps
        self.mesh = ExplodingMesh(vertices, faces, seed=0, speed=speed)
        builder = Builder(len(faces), method=method, policy=policy, resort=resort)
        # A wider view than the intact mesh: the pieces fly outwards. None headless: the camera
        # refuses a mesh too large to frame in float32, which a run without images can take.
        camera = None if headless else Camera.framing(vertices, zoom=0.7, view=view)
        self.animation = Animation(self.mesh, builder, lambda frame: frame * self.frame_dt, camera,
                                   image_size=0 if headless else image_size)
        # The intact mesh first in the GIF, as the demo's: the explosion is seen from its start.
        self.animation.render()

    def step(self):
        return self.animation.step()

    def render(self):
        self.animation.render()

    def save(self, out_dir):
        return self.animation.save(out_dir, "exploding_mesh")


def main(argv=None):
    parser = argparse.ArgumentParser(formatter_class=HelpFormatter)
    parser.add_argument("--device", type=device_name, default=None, help="Override the default Warp device.")
    parser.add_argument("--headless", action="store_true", help="Build only: no ray-cast images.")
    parser.add_argument("--num-frames", type=positive_int, default=24, help="Total number of frames.")
    parser.add_argument("--mesh", type=mesh_file, default=None,
                        help="Mesh file; the generated default scene if absent.")
    parser.add_argument("--num-tris", type=scene_tris, default=60000, help="Size of the generated scene.")
    parser.add_argument("--method", choices=PIPELINE_METHODS, default="hlbvh", help="Build method.")
    parser.add_argument("--policy", choices=("rebuild", "refit", "auto"), default="rebuild",
                        help="Per frame: rebuild, refit, or let the builder decide.")
    parser.add_argument("--no-resort", action="store_true", help="Rebuild from scratch (input in face order).")
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
            example = Example(mesh, args.num_tris, args.method, args.policy, not args.no_resort,
                              image_size=args.image_size, headless=args.headless, view=args.view)
        for _ in range(args.num_frames):
            example.step()
            example.render()
        print(example.animation.table())
        print(example.animation.legend())
        for path in example.save(args.out):
            print(f"wrote {path}")


if __name__ == "__main__":
    main()
