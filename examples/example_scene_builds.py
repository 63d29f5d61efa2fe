# A scene of several meshes, each moved and built again every frame: one-shot
# `hlbvh_warp.build` per mesh, a reusable `Builder` per mesh (allocated once, the per-frame path),
# and `wp.Bvh(..., "sah")` per mesh constructed in the same process as the peer. Prints ms per
# frame (average / worst) and the ratio to the peer. "Builder, plain launches" is the same
# `Builder` packing every launch's arguments anew each frame (`wp.launch`), where a `Builder`
# replays the launches it recorded on the first frame (`hlbvh_warp.launches`).
#
# One-shot builds of meshes of different sizes each get their pipeline's scratch back from
# `hlbvh_warp.memory` (one set per mesh); `--scratch-sets 2` limits that cache to two sets, so
# with more meshes than that every build allocates its pipeline anew.
#
#   python examples/example_scene_builds.py [--mesh PATH ...] [--num-frames 24] [--headless]
#       [--scratch-sets N]

import argparse
import time

import numpy as np
import warp as wp

import hlbvh_warp
from hlbvh_warp import memory
from hlbvh_warp.bench import WarpBvhPeer, collector_paused, turn_order
from hlbvh_warp.builder import Builder
from hlbvh_warp.cli import HelpFormatter
from hlbvh_warp.cli import argument_errors, device_name, mesh_file, non_negative_int, positive_int, read_mesh
from hlbvh_warp.scenes import scene

MODES = ("hlbvh_warp.build", "Builder", "Builder, plain launches", "wp.Bvh sah")


@wp.kernel
def spin_kernel(rest: wp.array(dtype=wp.vec3), angle: float, center: wp.vec3, out: wp.array(dtype=wp.vec3)):
    # Each mesh turns about the y axis through its own center: every vertex moves every frame.
    i = wp.tid()
    p = rest[i] - center
    c = wp.cos(angle)
    s = wp.sin(angle)
    out[i] = center + wp.vec3(c * p[0] + s * p[2], p[1], -s * p[0] + c * p[2])


class Example:
    def __init__(self, meshes=None, num_tris=(40000, 20000, 6000, 1000), num_frames=24, headless=False,
                 scratch_sets=None):
        if scratch_sets is not None:
            memory.set_scratch_cache_sets(scratch_sets)
        loaded = [scene(path) for path in meshes] if meshes else [scene(None, n) for n in num_tris]
        self.headless = headless
        self.num_frames = max(int(num_frames), 1)
        self.frame = 0
        device = wp.get_device()
        self.objects = []
        for vertices, faces in loaded:
            rest = wp.array(vertices, dtype=wp.vec3, device=device)
            center = wp.vec3(*((vertices.min(axis=0) + vertices.max(axis=0)) * 0.5))
            obj = {"rest": rest, "center": center, "vertices": wp.empty_like(rest), "faces_np": faces,
                   "builder": Builder(len(faces), device=device, resort=True),
                   "plain": Builder(len(faces), device=device, resort=True, record_launches=False),
                   "peer": WarpBvhPeer(len(faces), "sah", device)}
            self._move(obj, 0.0)
            obj["builder"].build(obj["vertices"], faces)
            obj["plain"].build(obj["vertices"], faces)
            obj["peer"].build(obj["vertices"], faces)
            self.objects.append(obj)
        self.ms = {mode: [] for mode in MODES}
        self.bvhs = {}
        # Warm-up: kernel loads and first allocations stay out of the timed frames.
        self._run_frame(record=False)

    def _move(self, obj, angle):
        wp.launch(spin_kernel, dim=obj["rest"].shape[0], inputs=[obj["rest"], angle, obj["center"], obj["vertices"]],
                  device=obj["rest"].device)

    def _build(self, mode):
        for obj in self.objects:
            if mode == "hlbvh_warp.build":
                self.bvhs[id(obj)] = hlbvh_warp.build(obj["vertices"], obj["faces_np"], method="hlbvh")
            elif mode == "Builder":
                obj["builder"].rebuild(obj["vertices"])
            elif mode == "Builder, plain launches":
                obj["plain"].rebuild(obj["vertices"])
            else:
                obj["peer"].update(obj["vertices"])

    def _run_frame(self, record=True):
        # The warm-up (frame 0) turns the meshes to 0.25, and every frame after it turns them on.
        angle = 0.25 * (self.frame + 1)
        for obj in self.objects:
            self._move(obj, angle)
        # Each mode runs first, and right after every other mode, equally often (`turn_order`).
        order = turn_order(MODES, self.frame)
        with collector_paused():
            for mode in order:
                wp.synchronize()
                start = time.perf_counter()
                self._build(mode)
                wp.synchronize()
                if record:
                    self.ms[mode].append((time.perf_counter() - start) * 1e3)

    def step(self):
        # Advanced first: frame 1 must not rebuild the warm-up's vertices (a resorted Builder
        # would find its codes in order and skip its sorts, where the peer does all its work).
        self.frame += 1
        self._run_frame()

    def render(self):
        if self.headless:
            return
        row = "  ".join(f"{mode} {ms[-1]:.1f} ms" for mode, ms in self.ms.items() if ms)
        print(f"frame {self.frame}: {row}")

    def table(self) -> str:
        peer = float(np.mean(self.ms["wp.Bvh sah"]))
        sizes = ", ".join(str(len(obj["faces_np"])) for obj in self.objects)
        lines = [f"{len(self.objects)} meshes ({sizes} triangles), {len(self.ms['Builder'])} frames",
                 "| mode | avg ms / frame | worst | x wp.Bvh sah |", "|---|---|---|---|"]
        for mode, ms in self.ms.items():
            lines.append(f"| {mode} | {np.mean(ms):.1f} | {np.max(ms):.1f} | {np.mean(ms) / peer:.2f} |")
        lines.append("ms / frame: all meshes built once; x wp.Bvh sah: the mode's average over wp.Bvh sah's "
                     "(below 1: faster than the peer)")
        return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(formatter_class=HelpFormatter)
    parser.add_argument("--device", type=device_name, default=None, help="Override the default Warp device.")
    parser.add_argument("--mesh", action="append", default=None, type=mesh_file,
                        help="A mesh file (repeatable); generated meshes of 40k, 20k, 6k and 1k triangles if absent.")
    parser.add_argument("--num-frames", type=positive_int, default=24, help="Total number of frames.")
    parser.add_argument("--headless", action="store_true", help="Run without printing every frame.")
    parser.add_argument("--scratch-sets", type=non_negative_int, default=None,
                        help="One-shot pipeline scratch sets kept; the library's 16 if absent.")
    args = parser.parse_args(argv)
    # Every mesh file before the first build: one that is no mesh is an argument error naming it.
    with argument_errors(parser):
        meshes = [read_mesh(path) for path in args.mesh] if args.mesh else None
    with wp.ScopedDevice(args.device):
        example = Example(meshes, num_frames=args.num_frames, headless=args.headless,
                          scratch_sets=args.scratch_sets)
        for _ in range(example.num_frames):
            example.step()
            example.render()
        print(example.table())


if __name__ == "__main__":
    main()
