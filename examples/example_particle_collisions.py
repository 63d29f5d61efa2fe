# Particle collisions: a simulation's broad phase rebuilt every frame. Spheres fly inside a unit
# box and bounce off its walls; each frame their boxes go to a `Builder` set up with
# `build_from_bounds` (the HLBVH build over bare boxes, resorted), a user kernel lists the
# candidate pairs whose boxes overlap (`query.bvh_aabb_pairs`), and a second kernel keeps the
# spheres that touch. `wp.Bvh` over the same boxes, rebuilt every frame (`wp.Bvh.rebuild`), is
# timed beside it as the peer. Writes a picture of the last frame (particle_collisions.png in
# --out: a slab of the box seen from above, the particles blue, those in contact red).
#
#   python examples/example_particle_collisions.py [--num-particles 100000] [--num-frames 24]
#       [--headless] [--policy rebuild|auto] [--no-peer]

import argparse
import os
import time

import numpy as np
import warp as wp

from hlbvh_warp import query
from hlbvh_warp.bench import collector_paused
from hlbvh_warp.builder import PIPELINE_METHODS, Builder
from hlbvh_warp.cli import HelpFormatter
from hlbvh_warp.cli import argument_errors, check_out_folder, device_name, positive_int, query_count


#: The picture: half the depth of the slab of the box it shows (about z = 0.5), and the colours
#: of a particle touching no other and of one in contact.
SLAB_HALF_DEPTH = 0.05
FREE_COLOR = (0.3, 0.4, 0.8)
CONTACT_COLOR = (0.9, 0.1, 0.1)


@wp.kernel
def move_kernel(centers: wp.array(dtype=wp.vec3), velocities: wp.array(dtype=wp.vec3), radii: wp.array(dtype=float),
                dt: float, lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3)):
    # Fly, bounce off the walls of the unit box, and write the sphere's box.
    i = wp.tid()
    r = radii[i]
    c = centers[i] + velocities[i] * dt
    v = velocities[i]
    for k in range(3):
        if c[k] < r:
            c[k] = 2.0 * r - c[k]
            v[k] = wp.abs(v[k])
        if c[k] > 1.0 - r:
            c[k] = 2.0 * (1.0 - r) - c[k]
            v[k] = -wp.abs(v[k])
    centers[i] = c
    velocities[i] = v
    extent = wp.vec3(r, r, r)
    lowers[i] = c - extent
    uppers[i] = c + extent


@wp.kernel
def broad_phase_kernel(bvh: query.BvhView, lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3),
                       pairs: wp.array(dtype=wp.vec2i), pair_count: wp.array(dtype=wp.int32)):
    # Every (i, j) whose boxes overlap, j != i included and each pair found from both sides.
    i = wp.tid()
    query.bvh_aabb_pairs(bvh, lowers[i], uppers[i], i, pairs, pair_count)


@wp.kernel
def narrow_phase_kernel(pairs: wp.array(dtype=wp.vec2i), pair_count: wp.array(dtype=wp.int32),
                        centers: wp.array(dtype=wp.vec3), radii: wp.array(dtype=float),
                        contacts: wp.array(dtype=wp.int32), touching: wp.array(dtype=wp.int32)):
    # A pair counts once (i < j) when the spheres overlap; both spheres are marked as touching.
    k = wp.tid()
    if k >= pair_count[0]:
        return
    p = pairs[k]
    i = p[0]
    j = p[1]
    if i >= j:
        return
    reach = radii[i] + radii[j]
    if wp.length_sq(centers[i] - centers[j]) < reach * reach:
        wp.atomic_add(contacts, 0, 1)
        touching[i] = 1
        touching[j] = 1


class Example:
    def __init__(self, num_particles=100000, method="hlbvh", policy="rebuild", peer=True, headless=False,
                 seed=0, speed=0.3, radius=0.002, fps=24.0):
        rng = np.random.default_rng(seed)
        self.num = n = int(num_particles)
        self.dt = 1.0 / fps
        self.headless = headless
        radii = (radius * (0.5 + rng.random(n))).astype(np.float32)
        centers = (radii[:, None] + (1.0 - 2.0 * radii[:, None]) * rng.random((n, 3))).astype(np.float32)
        self.centers = wp.array(centers, dtype=wp.vec3)
        self.velocities = wp.array((speed * rng.standard_normal((n, 3))).astype(np.float32), dtype=wp.vec3)
        self.radii = wp.array(radii, dtype=float)
        self.lowers = wp.array(centers - radii[:, None], dtype=wp.vec3)
        self.uppers = wp.array(centers + radii[:, None], dtype=wp.vec3)
        self.builder = Builder(n, method=method, policy=policy)
        self.builder.build_from_bounds(self.lowers, self.uppers)
        self.view = query.view(self.builder.bvh)
        # The peer reads the same boxes; `rebuild` rebuilds over their current contents.
        self.peer = wp.Bvh(self.lowers, self.uppers, constructor="sah") if peer else None
        # Room for 32 candidates a particle; a frame that finds more grows the buffer once.
        self.pairs = wp.empty(32 * n, dtype=wp.vec2i)
        self.pair_count = wp.zeros(1, dtype=wp.int32)
        self.contacts = wp.zeros(1, dtype=wp.int32)
        self.touching = wp.zeros(n, dtype=wp.int32)
        self.rows = []
        self.image = None

    def step(self):
        wp.launch(move_kernel, dim=self.num,
                  inputs=[self.centers, self.velocities, self.radii, self.dt, self.lowers, self.uppers])
        ms = {}

        def timed(name, build):
            wp.synchronize()
            start = time.perf_counter()
            result = build()
            wp.synchronize()
            ms[name] = (time.perf_counter() - start) * 1e3
            return result

        with collector_paused():
            # The two take turns going first: the first build after the boxes were written runs
            # with colder caches.
            turns = ["ours", "peer"] if len(self.rows) % 2 == 0 else ["peer", "ours"]
            for name in turns:
                if name == "ours":
                    report = timed(name, lambda: self.builder.update(bounds=(self.lowers, self.uppers)))
                elif self.peer is not None:
                    timed(name, self.peer.rebuild)
        ours, peer = ms["ours"], ms.get("peer", float("nan"))
        start = time.perf_counter()
        candidates = self.collide()
        contacts = int(self.contacts.numpy()[0])
        # The queries' time shows what the tree is worth: a refit tree is cheap to make, but under
        # lasting motion its boxes swell and every query visits more of it.
        query_ms = (time.perf_counter() - start) * 1e3
        row = {"frame": len(self.rows), "decision": report["decision"], "ms": ours, "peer_ms": peer,
               "query_ms": query_ms, "candidates": candidates, "contacts": contacts}
        self.rows.append(row)
        return row

    def collide(self) -> int:
        """Broad phase through the BVH, then the sphere test; returns the candidate pair count."""
        while True:
            self.pair_count.zero_()
            wp.launch(broad_phase_kernel, dim=self.num,
                      inputs=[self.view, self.lowers, self.uppers, self.pairs, self.pair_count])
            found = int(self.pair_count.numpy()[0])
            if found <= self.pairs.shape[0]:
                break
            self.pairs = wp.empty(2 * found, dtype=wp.vec2i)
        self.contacts.zero_()
        self.touching.zero_()
        wp.launch(narrow_phase_kernel, dim=max(found, 1),
                  inputs=[self.pairs, self.pair_count, self.centers, self.radii, self.contacts, self.touching])
        return found

    def contact_pairs(self) -> np.ndarray:
        """The current frame's touching pairs (i < j), sorted, from the broad phase's candidates."""
        found = int(self.pair_count.numpy()[0])
        pairs = self.pairs.numpy()[:found].astype(np.int64)
        pairs = pairs[pairs[:, 0] < pairs[:, 1]]
        c = self.centers.numpy().astype(np.float64)
        r = self.radii.numpy().astype(np.float64)
        touch = ((c[pairs[:, 0]] - c[pairs[:, 1]]) ** 2).sum(1) < (r[pairs[:, 0]] + r[pairs[:, 1]]) ** 2
        pairs = pairs[touch]
        return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]

    def render(self):
        """A top view (x, y) of the slab 0.45 < z < 0.55 of the frame, a pixel per particle: blue,
        or red for a particle in contact (`figure` adds the title and legend)."""
        if self.headless:
            return
        size = 256
        c = self.centers.numpy()
        touching = self.touching.numpy().astype(bool)
        slab = np.abs(c[:, 2] - 0.5) < SLAB_HALF_DEPTH
        c, touching = c[slab], touching[slab]
        image = np.ones((size, size, 3), np.float32)
        px = np.clip((c[:, :2] * size).astype(int), 0, size - 1)
        image[size - 1 - px[~touching, 1], px[~touching, 0]] = FREE_COLOR
        image[size - 1 - px[touching, 1], px[touching, 0]] = CONTACT_COLOR
        self.image = image

    def table(self) -> str:
        lines = [f"{'frame':>5}  {'decision':8}  {'build ms':>8}  {'wp.Bvh ms':>9}  {'query ms':>8}  "
                 f"{'candidates':>10}  {'contacts':>8}"]
        for r in self.rows:
            lines.append(f"{r['frame']:5d}  {r['decision']:8}  {r['ms']:8.2f}  {r['peer_ms']:9.2f}  "
                         f"{r['query_ms']:8.2f}  {r['candidates']:10d}  {r['contacts']:8d}")
        ms = np.array([r["ms"] for r in self.rows[1:]] or [np.nan])
        peer = np.array([r["peer_ms"] for r in self.rows[1:]] or [np.nan])
        lines.append(f"average after the first frame: {ms.mean():.2f} ms against wp.Bvh.rebuild {peer.mean():.2f} ms "
                     f"({ms.mean() / peer.mean():.2f}x)")
        lines.append("build ms: the Builder's update over the boxes; wp.Bvh ms: wp.Bvh.rebuild over the same boxes; "
                     "query ms: both phases; candidates: pairs whose boxes overlap, each found from both sides; "
                     "contacts: pairs of spheres that touch, each counted once")
        return "\n".join(lines)

    def figure(self):
        """`render`'s picture as a matplotlib figure, with a title saying the frame and the counts
        and a legend saying the colours."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        centers = self.centers.numpy()
        touching = self.touching.numpy().astype(bool)
        slab = np.abs(centers[:, 2] - 0.5) < SLAB_HALF_DEPTH
        fig = plt.figure(figsize=(5.0, 5.6), dpi=100)
        ax = fig.add_axes((0.08, 0.16, 0.84, 0.72))
        ax.imshow(self.image, extent=(0.0, 1.0, 0.0, 1.0), interpolation="nearest")
        ax.set_xlabel("x")
        ax.set_ylabel("y")
        frame = self.rows[-1]["frame"] if self.rows else 0
        fig.suptitle(f"Particle collisions, frame {frame}: top view of the slab {0.5 - SLAB_HALF_DEPTH:g} < z < "
                     f"{0.5 + SLAB_HALF_DEPTH:g}\n{int(slab.sum())} of {self.num} particles in the slab, "
                     f"{int((slab & touching).sum())} of them touching another", fontsize=9)
        handles = [plt.Line2D([], [], marker="s", linestyle="", markersize=6, color=FREE_COLOR,
                              label="particle touching no other (its centre's pixel)"),
                   plt.Line2D([], [], marker="s", linestyle="", markersize=6, color=CONTACT_COLOR,
                              label="particle touching another sphere (anywhere in the box)")]
        fig.legend(handles=handles, loc="lower center", fontsize=8, frameon=False)
        return fig

    def save(self, out_dir) -> list:
        if self.image is None:
            return []
        import matplotlib.pyplot as plt

        os.makedirs(out_dir, exist_ok=True)
        path = os.path.join(out_dir, "particle_collisions.png")
        fig = self.figure()
        fig.savefig(path, dpi=fig.dpi)
        plt.close(fig)
        return [path]


def main(argv=None):
    parser = argparse.ArgumentParser(formatter_class=HelpFormatter)
    parser.add_argument("--device", type=device_name, default=None, help="Override the default Warp device.")
    parser.add_argument("--headless", action="store_true", help="No picture.")
    parser.add_argument("--num-frames", type=positive_int, default=24, help="Total number of frames.")
    # Bounded as the command line's query counts: an unbounded count ended in NumPy's MemoryError.
    parser.add_argument("--num-particles", type=query_count, default=100000, help="Particles.")
    parser.add_argument("--method", choices=PIPELINE_METHODS, default="hlbvh", help="Build method.")
    parser.add_argument("--policy", choices=("rebuild", "refit", "auto"), default="rebuild",
                        help="Per frame: rebuild, refit, or let the builder decide.")
    parser.add_argument("--no-peer", action="store_true", help="Do not time wp.Bvh beside it.")
    parser.add_argument("--out", type=str, default="hlbvh_example_out",
                        help="Folder for the picture of the last frame (particle_collisions.png).")
    args = parser.parse_args(argv)
    # The output folder before the first frame, not after the last.
    if not args.headless:
        with argument_errors(parser):
            check_out_folder(args.out)

    with wp.ScopedDevice(args.device):
        example = Example(args.num_particles, args.method, args.policy, peer=not args.no_peer,
                          headless=args.headless)
        for _ in range(args.num_frames):
            example.step()
            example.render()
        print(example.table())
        for path in example.save(args.out):
            print(f"wrote {path}")


if __name__ == "__main__":
    main()
