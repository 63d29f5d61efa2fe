# Mesh contact: particles fall onto a mesh that bends under them. Every frame the mesh bends a
# little further (the "Bending Armadillo" motion of Pantaleoni & Luebke 2010), a `Builder` with the
# adaptive policy refits or rebuilds its tree, and a user kernel keeps each particle out of the
# surface: `query.bvh_closest_point`, bounded by the particle's radius, finds the nearest point of
# the mesh, and a particle closer than its radius is pushed back out along the separation and
# loses the velocity that took it in. The table lists each frame's tree decision, the particles
# touching the mesh after its last substep, and the time of the build and of the contact queries.
# Writes a side view of the last frame (mesh_contact.png in --out): the mesh grey, the particles
# blue, those touching the mesh red.
#
#   python examples/example_mesh_contact.py [--mesh PATH] [--num-particles 20000] [--num-frames 24]
#       [--headless]

import argparse
import os
import time

import numpy as np
import warp as wp

from hlbvh_warp import query
from hlbvh_warp.builder import Builder
from hlbvh_warp.cli import HelpFormatter
from hlbvh_warp.cli import (argument_errors, check_out_folder, device_name, mesh_file, positive_int, query_count,
                            read_mesh, scene_tris)
from hlbvh_warp.dynamic import BendingMesh
# Largest finite float32: the particles, their velocities and gravity go to the kernel in float32.
from hlbvh_warp.reference import FLOAT32_MAX
from hlbvh_warp.render import FIGURE_DPI, legend_below, save_figure
from hlbvh_warp.scenes import scene

# Projections per substep: a particle pushed out of one triangle may sit within its radius of a
# neighbour in a crease; a second pass settles nearly all of those.
CONTACT_PASSES = 2
# Substeps per frame, all against the frame's tree: a particle then moves about its radius per
# substep at most, so it does not pass through a thin part of the mesh between two queries (no
# continuous collision detection here).
SUBSTEPS = 4
#: Gravity, in box diagonals per second squared, and the frames per second of the simulation.
GRAVITY = 2.0
FPS = 30.0
#: Pixels per inch of the picture.


def diagonal(vertices) -> float:
    """The length of the box diagonal, in float64: float32's squares overflow past 1.8e19."""
    v = np.asarray(vertices, dtype=np.float64)
    return float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))


def particle_reach(vertices, num_frames: int) -> float:
    """An upper bound, in float64, on every coordinate, velocity and gravity the particles reach
    over ``num_frames`` frames: they start within a box diagonal of the mesh, and one that misses
    the mesh falls at most GRAVITY * T^2 diagonals in T seconds (the substeps' Euler steps never
    move it more than that), at a speed of at most GRAVITY * T diagonals a second."""
    seconds = max(int(num_frames), 1) / FPS
    diag = diagonal(vertices)
    largest = float(np.abs(np.asarray(vertices, dtype=np.float64)).max())
    return largest + diag * (1.0 + GRAVITY * (1.0 + seconds + seconds * seconds))


@wp.kernel
def contact_kernel(bvh: query.BvhView, positions: wp.array(dtype=wp.vec3), velocities: wp.array(dtype=wp.vec3),
                   gravity: wp.vec3, dt: float, radius: float, touching: wp.array(dtype=wp.int32)):
    i = wp.tid()
    v = velocities[i] + gravity * dt
    x = positions[i] + v * dt
    touched = int(0)
    for _ in range(CONTACT_PASSES):
        c = query.bvh_closest_point(bvh, x, radius)
        if c.prim >= 0 and c.distance < radius:
            touched = 1
            n = wp.vec3(0.0)
            if c.distance > 1.0e-6 * radius:
                n = (x - c.point) / c.distance
            else:
                # On the surface: leave along the triangle's normal, on the side the particle came from.
                a = bvh.vertices[bvh.faces[c.prim, 0]]
                b = bvh.vertices[bvh.faces[c.prim, 1]]
                n = wp.normalize(wp.cross(b - a, bvh.vertices[bvh.faces[c.prim, 2]] - a))
                if wp.dot(n, positions[i] - a) < 0.0:
                    n = -n
            x = c.point + n * radius
            # Keep the tangential velocity, drop the part into the surface.
            v = v - wp.min(wp.dot(v, n), 0.0) * n
    positions[i] = x
    velocities[i] = v
    touching[i] = touched


class Example:
    def __init__(self, mesh=None, num_tris=20000, num_particles=20000, num_frames=24, radius=0.01, seed=0,
                 headless=False):
        vertices, faces = scene(mesh, num_tris)
        self.num_frames = max(int(num_frames), 1)
        self.mesh = BendingMesh(vertices, faces)
        self.builder = Builder(len(faces), policy="auto")
        self.builder.build(self.mesh.vertices, self.mesh.faces)
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        # In float64: float32's squares overflowed past a diagonal of 1.8e19, and a NaN gravity
        # left every particle NaN, touching nothing.
        diag = diagonal(vertices)
        # Gravity against the bend axis, so the particles land on the side that curls.
        self.down = -self.mesh.bend_axis
        rng = np.random.default_rng(seed)
        # A slab from the mesh's middle to a mesh's depth above its top, along the bend axis: the
        # few particles that start inside the mesh's box show contacts from the first frame.
        start = lo + rng.random((num_particles, 3)) * (hi - lo)
        start += (hi - lo) * self.mesh.bend_axis * (0.5 * rng.random((num_particles, 1)) + 0.5)
        self.radius = radius * diag
        self.dt = 1.0 / FPS
        self.gravity = wp.vec3(*(self.down * GRAVITY * diag))
        self.positions = wp.array(start.astype(np.float32), dtype=wp.vec3)
        self.velocities = wp.zeros(num_particles, dtype=wp.vec3)
        self.touching = wp.zeros(num_particles, dtype=wp.int32)
        self.headless = headless
        self.frame = 0
        self.rows = []
        # The contact kernel (with the closest-point query it inlines) compiled now, untimed: a first
        # run compiled it inside frame 1, whose contact time read 6 s against 30 ms.
        wp.load_module(contact_kernel.module, device=wp.get_device())

    def step(self):
        self.frame += 1
        start = time.perf_counter()
        vertices = self.mesh.update(min(self.frame / self.num_frames, 1.0))
        self.builder.update(vertices)
        wp.synchronize_device()
        built = time.perf_counter()
        view = query.view(self.builder.bvh)
        for _ in range(SUBSTEPS):
            wp.launch(contact_kernel, dim=self.positions.shape[0],
                      inputs=[view, self.positions, self.velocities, self.gravity, self.dt / SUBSTEPS, self.radius,
                              self.touching])
        wp.synchronize_device()
        done = time.perf_counter()
        self.rows.append({
            "frame": self.frame,
            "decision": self.builder.last_report["decision"],
            # The contact kernel rewrites `touching` every substep: this is the frame's last.
            "touching": int(self.touching.numpy().sum()),
            "build_ms": 1e3 * (built - start),
            "contact_ms": 1e3 * (done - built),
        })

    def figure(self):
        """A side view of the current frame (the mesh's length axis across, its bend axis up) as a
        matplotlib figure whose title says the frame and the counts and whose legend says the
        colours: the mesh's vertices grey, the particles clear of it blue, and those that touched
        it in the frame's last substep red (drawn last, over the rest)."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        across, up = self.mesh.length_axis, self.mesh.bend_axis
        verts = self.mesh.vertices.numpy()
        pts = self.positions.numpy()
        touching = self.touching.numpy().astype(bool)
        fig = plt.figure(figsize=(7.0, 5.0), dpi=FIGURE_DPI)
        # A fixed layout (no tight box at the save): the title above, the legend below.
        ax = fig.add_axes((0.02, 0.12, 0.96, 0.74))
        ax.scatter(verts @ across, verts @ up, s=0.2, c="0.6", linewidths=0, label="bending mesh (its vertices)")
        ax.scatter(pts[~touching] @ across, pts[~touching] @ up, s=1, c="tab:blue", linewidths=0,
                   label="particles clear of the mesh")
        ax.scatter(pts[touching] @ across, pts[touching] @ up, s=1, c="tab:red", linewidths=0,
                   label="particles touching the mesh (pushed out in the frame's last substep)")
        ax.set_aspect("equal")
        ax.set_axis_off()
        fig.suptitle(f"Mesh contact, frame {self.frame} of {self.num_frames}, side view (bend axis up)\n"
                     f"{int(touching.sum())} of {len(pts)} particles touching the mesh", fontsize=10)
        legend_below(fig, ax)
        return fig

    def render(self, path=None):
        """Write `figure` as a PNG to ``path`` (its folder made); None headless or without a path."""
        if self.headless or path is None:
            return
        save_figure(self.figure(), path)
        return path

    def table(self) -> str:
        lines = [f"{'frame':>5s} {'tree':8s} {'touching':>8s} {'build ms':>8s} {'contact ms':>10s}"]
        for r in self.rows:
            lines.append(f"{r['frame']:5d} {r['decision']:8s} {r['touching']:8d} {r['build_ms']:8.2f} "
                         f"{r['contact_ms']:10.2f}")
        return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(formatter_class=HelpFormatter)
    parser.add_argument("--device", type=device_name, default=None, help="Override the default Warp device.")
    parser.add_argument("--headless", action="store_true", help="Run without writing the picture.")
    parser.add_argument("--num-frames", type=positive_int, default=24, help="Total number of frames.")
    parser.add_argument("--mesh", type=mesh_file, default=None,
                        help="Mesh file; the generated default scene if absent.")
    parser.add_argument("--num-tris", type=scene_tris, default=20000, help="Size of the generated scene.")
    # Bounded as the command line's query counts: an unbounded count ended in NumPy's MemoryError.
    parser.add_argument("--num-particles", type=query_count, default=20000, help="Falling particles.")
    parser.add_argument("--out", type=str, default="hlbvh_example_out",
                        help="Folder for the picture of the last frame (mesh_contact.png).")
    args = parser.parse_args(argv)
    # The mesh file and the picture's path before the first frame, not after the last.
    with argument_errors(parser):
        mesh = read_mesh(args.mesh) if args.mesh else None
        # A finite mesh near float32's limit (coordinates of 3e38) left the particles Inf and NaN:
        # named here, before any frame.
        if mesh is not None and not particle_reach(mesh[0], args.num_frames) <= FLOAT32_MAX:
            raise ValueError(f"{args.mesh}: over --num-frames {args.num_frames} the falling particles may reach "
                             f"{particle_reach(mesh[0], args.num_frames):.3g}, past float32's largest "
                             f"{FLOAT32_MAX:.3g}; scale the mesh down or choose fewer frames")
        if not args.headless:
            check_out_folder(args.out)

    with wp.ScopedDevice(args.device):
        example = Example(mesh, args.num_tris, args.num_particles, args.num_frames, headless=args.headless)
        for _ in range(args.num_frames):
            example.step()
        print(example.table())
        print("tree: what the mesh's Builder (auto policy) did this frame; touching: particles pushed out of the "
              "mesh in the frame's last substep; build ms: the bend and the Builder's update; contact ms: the "
              f"{SUBSTEPS} substeps of the contact kernel")
        written = example.render(os.path.join(args.out, "mesh_contact.png"))
        if written:
            print(f"wrote {written}")


if __name__ == "__main__":
    main()
