"""``python -m hlbvh_warp demo``: build the generated scene with every method, check rays against
a float64 brute force, print per-stage timings; then run the exploding-mesh animation (a full
rebuild every frame, resorted where it pays, as in Pantaleoni & Luebke 2010), print the
per-frame table and write the images (PNG + GIF) and the ms-per-frame plot into ``--out``."""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import warp as wp

from .cli import HelpFormatter
from .cli import (check_out_folder, command_prog, device_name, image_side, mesh_file, positive_int,
                  query_count_or_zero, quiet_warp, scene_tris)
from .reference import FLOAT32_MAX, brute_force_closest_hit
from .render import VIEWS

#: Pixels of all the animation's frames together: every frame is kept for the GIF, and the save
#: holds about 7 bytes a pixel (the RGB frames, Pillow's copies, the palette images), under 1 GB
#: here; 2047 frames of the default 256^2, or 7 of 4096^2.
MAX_ANIMATION_PIXELS = 1 << 27
#: The exploding mesh's speed, in box diagonals per unit of time (`ExplodingMesh`'s default), and
#: the animation's frames per unit of time.
EXPLOSION_SPEED = 0.5
FRAMES_PER_TIME_UNIT = 24.0
#: Relative tolerance of "the same t" in `check_rays`: float32 hits against float64 ones.
RAY_RTOL = 1e-4


def check_rays(bvh, vertices, faces, origins, directions, reference) -> int:
    """Rays whose hit disagrees with the reference: another primitive at another t (`RAY_RTOL`),
    another primitive at the same t that the ray does not meet there (`unmet_ties`), or hit/miss
    (but for a hit at float32's largest distance, `past_range_ties`)."""
    from .query import intersect
    from .reference import past_range_ties, unmet_ties

    t, prim = intersect(bvh, origins, directions)
    t_ref, prim_ref = reference
    hit, hit_ref = prim >= 0, prim_ref >= 0
    same = (prim == prim_ref) | (hit & hit_ref & np.isclose(t, t_ref, rtol=RAY_RTOL, atol=0.0))
    same &= ~unmet_ties(vertices, faces, origins, directions, t, prim, t_ref, prim_ref, RAY_RTOL)
    # A hit against a miss at float32's largest distance: rounding decides whether it overflows.
    same |= past_range_ties(t, prim, t_ref, prim_ref, RAY_RTOL)
    return int((~same).sum())


def rays_at(vertices, count: int):
    """Rays from outside the bounding box aimed at random points of it, the same ones every run."""
    rng = np.random.default_rng(0)
    v = np.asarray(vertices, dtype=np.float64)
    lo, hi = v.min(0), v.max(0)
    center, radius = 0.5 * (lo + hi), 0.5 * np.linalg.norm(hi - lo) + 1e-6
    dirs = rng.normal(size=(count, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origins = center - 2.0 * radius * dirs
    d = lo + rng.random((count, 3)) * (hi - lo) - origins
    return origins.astype(np.float32), (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


def animation_reach(vertices, num_frames: int) -> float:
    """An upper bound on every value the exploding-mesh animation computes over ``num_frames``
    frames, in float64: what must fit in float32 for its vertices to stay finite.

    A corner at time t is its triangle's centroid + velocity x t + its offset from the centroid,
    turned. Every centroid lies in the box (at most the largest coordinate), a velocity is at most
    EXPLOSION_SPEED diagonals per unit of time (one unit where the mesh is a single point, as
    `ExplodingMesh` takes it) and is itself stored in float32, and an offset is at most a diagonal,
    whose turn by ``wp.quat_rotate`` sums terms of up to twice its length, 5 times in all.
    """
    v = np.asarray(vertices, dtype=np.float64)
    diagonal = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    speed = EXPLOSION_SPEED * (diagonal or 1.0)
    return float(np.abs(v).max()) + 5.0 * diagonal + speed * (num_frames / FRAMES_PER_TIME_UNIT + 1.0)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog=command_prog("demo"), description=__doc__,
                                     formatter_class=HelpFormatter)
    parser.add_argument("--device", type=device_name, default=None, help="Warp device; Warp's default if absent.")
    parser.add_argument("--num-tris", type=scene_tris, default=60000, help="Triangles of the generated scene.")
    parser.add_argument("--mesh", type=mesh_file, default=None, help="A mesh file instead of the generated scene.")
    parser.add_argument("--rays", type=query_count_or_zero, default=256,
                        help="Rays checked against the float64 brute force.")
    parser.add_argument("--num-frames", type=positive_int, default=12, help="Frames of the exploding-mesh animation.")
    parser.add_argument("--image-size", type=image_side, default=256,
                        help="Rendered frames are this many pixels square.")
    parser.add_argument("--view", choices=tuple(VIEWS), default="front",
                        help="The side of the mesh the camera looks from: front +z, right +x, back -z, left -x "
                             "(a mesh is taken to stand y up facing +z; the armadillo scan faces -z).")
    parser.add_argument("--methods", type=str, default=None,
                        help="Comma-separated subset of the build methods; all of them if absent.")
    parser.add_argument("--out", type=str, default="hlbvh_demo_out", help="Output folder.")
    args = parser.parse_args(argv)
    # The first frame is rendered before the animation steps: num_frames + 1 images.
    pixels = (args.num_frames + 1) * args.image_size ** 2
    if pixels > MAX_ANIMATION_PIXELS:
        parser.error(f"--num-frames {args.num_frames} at --image-size {args.image_size} keeps {pixels} pixels of "
                     f"frames for the GIF, more than {MAX_ANIMATION_PIXELS} (about 7 bytes each in memory); choose "
                     "fewer frames or a smaller image")

    quiet_warp()
    wp.init()
    from . import api, inputs
    from .builder import Builder
    from .dynamic import Animation, ExplodingMesh
    from .render import Camera
    from .scenes import scene

    # Every method name checked before the first build, not when the loop reaches it.
    api._load_optional_builders()
    if args.methods is None:
        methods = [m for m in api.BUILDERS if m not in api.OFFLINE_BUILDERS]
    elif not args.methods.strip():
        # An empty list used to read as no list at all: every method ran.
        raise ValueError(f"--methods {args.methods!r} names no method; choose from {sorted(api.BUILDERS)}")
    else:
        methods = args.methods.split(",")
    unknown = [m for m in methods if m not in api.BUILDERS]
    if unknown:
        raise ValueError(f"unknown method(s) {unknown} in --methods; choose from {sorted(api.BUILDERS)}")
    # The output folder before any work: a path that cannot be a folder used to fail only after
    # every build and the whole animation had run.
    check_out_folder(args.out)

    failures = 0
    with wp.ScopedDevice(args.device):
        device = wp.get_device()
        vertices, faces = scene(args.mesh, args.num_tris)
        # The library's checks (face indices in range, finite coordinates) before the float64
        # reference below indexes the vertices with the faces: a PLY face naming vertex 9 of 3
        # ended in NumPy's IndexError there, not in build()'s message.
        try:
            vertices, faces = inputs.mesh_arrays(vertices, faces)
        except ValueError as error:
            raise ValueError(f"{args.mesh}: {error}" if args.mesh else str(error)) from None
        # Before any work: a finite mesh near float32's limit (coordinates of 3e38) passed the
        # builds, then its flying triangles overflowed to Inf and NaN, and the animation's builder
        # blamed the vertices for a NaN the demo had made.
        reach = animation_reach(vertices, args.num_frames)
        if not reach <= FLOAT32_MAX:
            largest = float(np.abs(vertices).max())
            raise ValueError(f"{args.mesh or 'the scene'}: coordinates up to {largest:.3g} are too large for the "
                             f"exploding-mesh animation: over --num-frames {args.num_frames} its float32 arithmetic "
                             f"may reach {reach:.3g}, past float32's largest {FLOAT32_MAX:.3g}; scale the mesh down "
                             f"by a factor of {reach / FLOAT32_MAX:.3g} or more")
        print(f"scene: {'generated torus knot' if not args.mesh else args.mesh}, {len(faces)} triangles, "
              f"device {device}")
        # Warp's own line per compiled module is off (quiet_warp): say why a first run waits.
        print("(a first run compiles the Warp kernels before the first build: about 20 s on the CPU)", flush=True)

        # 1. Every build method on the static scene, checked against a float64 brute force.
        origins, directions = rays_at(vertices, args.rays)
        reference = brute_force_closest_hit(vertices, faces, origins, directions)
        for method in methods:
            api.build(vertices, faces, method=method)  # first build compiles the kernels: not timed
            start = time.perf_counter()
            bvh = api.build(vertices, faces, method=method, timings=True)
            wall = (time.perf_counter() - start) * 1e3
            bad = check_rays(bvh, vertices, faces, origins, directions, reference)
            failures += bad > 0
            stages = ", ".join(f"{k} {v:.2f}" for k, v in bvh.timings.items() if isinstance(v, float) and k != "total")
            print(f"\n{method}: {wall:.1f} ms, {bvh.num_nodes} nodes, depth {bvh.depth}; "
                  f"{len(origins) - bad}/{len(origins)} rays match the float64 brute force")
            print(f"  stages (ms): {stages}")

        # 2. The exploding mesh, rebuilt every frame (resorted where it pays), rendered with intersect().
        print(f"\nexploding mesh, {args.num_frames} frames, HLBVH rebuild every frame "
              "(resorted where a sample shows it pays):")
        mesh = ExplodingMesh(vertices, faces, seed=0, speed=EXPLOSION_SPEED)
        builder = Builder(len(faces), method="hlbvh", policy="rebuild", resort=True)
        animation = Animation(mesh, builder, lambda frame: frame / FRAMES_PER_TIME_UNIT,
                              Camera.framing(vertices, zoom=0.7, view=args.view), image_size=args.image_size)
        animation.render()
        for _ in range(args.num_frames):
            animation.step()
            animation.render()
        print(animation.table())
        print(animation.legend())
        paths = animation.save(args.out, "exploding_mesh")
        paths.append(plot_frames(animation.rows, os.path.join(args.out, "exploding_frame_ms.png")))
        for path in paths:
            print(f"wrote {path}")
    if failures:
        print(f"\n{failures} method(s) disagreed with the brute force")
    return 1 if failures else 0


def plot_frames(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot([r["frame"] for r in rows], [r["ms"] for r in rows], marker=".",
            label="hlbvh rebuild (resorted where it pays)")
    ax.set_xlabel("frame")
    ax.set_ylabel("ms per frame")
    ax.set_ylim(bottom=0)
    ax.set_title("Exploding mesh: BVH rebuild per frame")
    ax.legend()
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
