"""``python -m hlbvh_warp bench-build``: per-stage build times against wp.Bvh and wp.Mesh.

Every builder runs in this one process on one device on the same boxes, after a warm-up that
compiles all kernels; the table gives the median of `--repeats` runs. Before any time is
reported, each tree is checked on a batch of rays against a float64 brute force.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np
import warp as wp

STAGES = ("prim_bounds", "morton", "run_length_encode", "top_level_sort", "run_length_decode", "voxel_sort",
          "global_sort", "hierarchy", "bbox")


def _median_ms(fn, repeats, device):
    times = []
    for _ in range(repeats):
        wp.synchronize_device(device)
        start = time.perf_counter()
        fn()
        wp.synchronize_device(device)
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times), min(times), max(times)


def pipeline_bytes(pipe) -> int:
    """Bytes held by a pipeline's device buffers: the build's peak footprint on the device."""
    return sum(a.capacity for a in vars(pipe).values() if isinstance(a, wp.array))


def bench_mesh(name, mesh, device, repeats, out):
    import hlbvh_warp as hb
    from hlbvh_warp import reference
    from hlbvh_warp.hlbvh import HlbvhPipeline

    verts = np.ascontiguousarray(mesh.vertices, dtype=np.float32)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.int32)
    n = len(faces)
    tri = verts[faces]
    lowers = wp.array(tri.min(1), dtype=wp.vec3, device=device)
    uppers = wp.array(tri.max(1), dtype=wp.vec3, device=device)
    points = wp.array(verts, dtype=wp.vec3, device=device)
    indices = wp.array(faces.ravel(), dtype=wp.int32, device=device)

    rng = np.random.default_rng(0)
    origins, directions = reference.random_rays(rng, verts, 256)
    t_ref, p_ref = reference.brute_force_closest_hit(verts, faces, origins, directions)

    rows = []
    for method in ("hlbvh", "lbvh"):
        bvh = hb.build(verts, faces, method=method, device=device)  # warm-up: compiles kernels
        t, p = hb.intersect(bvh, origins, directions)
        bad = reference.count_disagreements(t, p, t_ref, p_ref)
        med, lo, hi = _median_ms(lambda m=method: hb.build(verts, faces, method=method, device=device), repeats,
                                 device)
        stage_runs = [hb.build(verts, faces, method=method, device=device, timings=True).timings
                      for _ in range(repeats)]
        stages = {s: statistics.median(r.get(s, 0.0) for r in stage_runs) for s in STAGES if s in stage_runs[0]}
        mem = pipeline_bytes(HlbvhPipeline(n, hb.BuildConfig(), device))
        rows.append(dict(mesh=name, builder=method, tris=n, ms=med, ms_min=lo, ms_max=hi, stages=stages,
                         bytes_per_tri=mem / n, nodes=bvh.num_nodes, ray_disagreements=bad))

    for constructor in ("sah", "median", "lbvh"):
        wp.Bvh(lowers, uppers, constructor=constructor)
        med, lo, hi = _median_ms(lambda c=constructor: wp.Bvh(lowers, uppers, constructor=c), repeats, device)
        rows.append(dict(mesh=name, builder=f"wp.Bvh/{constructor}", tris=n, ms=med, ms_min=lo, ms_max=hi))
    wp.Mesh(points, indices)
    med, lo, hi = _median_ms(lambda: wp.Mesh(points, indices), repeats, device)
    rows.append(dict(mesh=name, builder="wp.Mesh", tris=n, ms=med, ms_min=lo, ms_max=hi))

    sah_ms = next(r["ms"] for r in rows if r["builder"] == "wp.Bvh/sah")
    for r in rows:
        r["ratio_to_wp_bvh_sah"] = r["ms"] / sah_ms
        stages = " ".join(f"{k}={v:.2f}" for k, v in r.get("stages", {}).items())
        mem = f"{r['bytes_per_tri']:6.0f}" if "bytes_per_tri" in r else "     -"
        bad = r.get("ray_disagreements", "-")
        out(f"{name:10s} {r['builder']:14s} {n:8d} {r['ms']:9.2f} {r['ms_min']:9.2f} {r['ms_max']:9.2f} "
            f"{r['ratio_to_wp_bvh_sah']:7.3f} {mem} {bad!s:>4s}  {stages}")
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hlbvh_warp bench-build", description=__doc__)
    parser.add_argument("--mesh", action="append", default=[], help="mesh file (repeatable); default: generated")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--json", default=None, help="write the rows to this JSON file")
    args = parser.parse_args(argv)

    import trimesh

    wp.config.quiet = True
    wp.init()
    meshes = []
    if args.mesh:
        for path in args.mesh:
            meshes.append((path.rsplit("/", 1)[-1].rsplit(".", 1)[0], trimesh.load(path, process=False)))
    else:
        from hlbvh_warp import scenes

        meshes.append(("generated", scenes.default_scene()))
    print(f"{'mesh':10s} {'builder':14s} {'tris':>8s} {'med_ms':>9s} {'min_ms':>9s} {'max_ms':>9s} "
          f"{'x_sah':>7s} {'B/tri':>6s} {'bad':>4s}  stages (median ms)")
    rows = []
    with wp.ScopedDevice(args.device):
        for name, mesh in meshes:
            rows += bench_mesh(name, mesh, args.device, args.repeats, print)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
    return 0
