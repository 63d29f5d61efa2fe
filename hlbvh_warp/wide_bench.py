"""``python -m hlbvh_warp bench-wide``: closest-hit rays through wide BVHs, k = 2, 4, 8, 16.

Garczorz (2026) measures serial CPU closest-hit traversal of BVHs with branching factor k against
k = 2. Here each mesh's binary tree (``--method``) is collapsed to every width of ``--widths``
(`hlbvh_warp.wide.collapse`) and the same rays are traced through each: primary rays from
``--views`` cameras on an orbit and one cosine-distributed diffuse bounce per primary hit (as
``python -m hlbvh_warp quality`` makes them). Width 2 is the binary tree in the wide layout and
the same traversal code, so its row is the baseline that changes nothing but k; the library's
own binary traversal (`hlbvh_warp.intersect`, packed nodes and prefetching) is timed beside them.

Hits are checked before timing: width 2's primary hits against the float64 brute force on a
sample, and every width's hits against width 2's. Each traversal is timed as the best of
``--repeats`` launches, all of them taking turns, in one process.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import numpy as np
import warp as wp

from .cli import (argument_errors, check_out_file, check_ray_count, command_prog, device_name, image_side, mesh_file,
                  non_negative_int, positive_int, query_count, quiet_warp, read_meshes, scene_tris)

#: Primary rays checked against the float64 brute force per mesh.
ORACLE_RAYS = 256

HEADER = (f"{'mesh':>10s} {'method':>10s} {'k':>3s} {'inner':>7s} {'depth':>5s} {'collapse':>8s} {'SAH':>7s} "
          f"{'rays':>7s} {'Mrays/s':>8s} {'x k=2':>6s} {'n_s':>6s} {'boxes':>6s} {'n_t':>5s} {'disagree':>8s}")


def measure_mesh(name, vertices, faces, method, args, device, progress) -> list:
    from . import api, quality, reference, wide
    from .ray_bench import best_times
    from .config import TRAVERSAL_STACK_SIZE, BuildConfig
    from .kernels import traversal
    from .query import intersect, view

    bvh = api.build(vertices, faces, method=method, device=device, config=BuildConfig(cpu_threads=args.cpu_threads))
    tree = bvh.to_numpy()
    leaves = tree["node_left"] < 0
    single_leaves = bool((tree["node_end"][leaves] - tree["node_begin"][leaves] == 1).all()) and \
        bvh.depth <= TRAVERSAL_STACK_SIZE
    rng = np.random.default_rng(args.seed)
    primary = quality.orbit_rays(vertices, args.views, args.side)
    widths = sorted(set(args.widths) | {2})
    trees = {}
    for k in widths:
        progress(f"[{name} {method}] collapsing to k = {k}")
        wp.synchronize_device(device)
        start = time.perf_counter()
        trees[k] = wide.collapse(bvh, k)
        wp.synchronize_device(device)
        trees[k].collapse_ms = 1e3 * (time.perf_counter() - start)
    t2, prim2 = wide.intersect(trees[2], *primary)
    sample = np.linspace(0, len(t2) - 1, min(ORACLE_RAYS, len(t2))).astype(np.int64)
    t_bf, prim_bf = reference.brute_force_closest_hit(vertices, faces, primary[0][sample], primary[1][sample])
    wrong = reference.count_mismatches(t2[sample], prim2[sample], t_bf, prim_bf,
                                       rays=(vertices, faces, primary[0][sample], primary[1][sample]))
    if wrong:
        raise RuntimeError(f"{name}: {wrong} of {len(sample)} primary rays through k = 2 disagree with the "
                           "float64 brute force")
    diffuse = quality.diffuse_rays(rng, vertices, faces, *primary, t2, prim2)
    # Width 2's hits, each set traced once: the reference every width is checked against.
    reference_hits = {"primary": (t2, prim2), "diffuse": wide.intersect(trees[2], *diffuse)}
    rows = []
    for kind, (o_np, d_np) in (("primary", primary), ("diffuse", diffuse)):
        n = len(o_np)
        o = wp.array(o_np, dtype=wp.vec3, device=device)
        d = wp.array(d_np, dtype=wp.vec3, device=device)
        out_t = wp.empty(n, dtype=float, device=device)
        out_p = wp.empty(n, dtype=wp.int32, device=device)
        no_counts = wp.empty(0, dtype=wp.vec3i, device=device)
        ref_t, ref_p = reference_hits[kind]
        fns, entries = [], []
        for k in widths:
            w = trees[k]
            t, prim, stats = wide.intersect(w, o_np, d_np, stats=True)
            kernel, inputs = wide.launch_args(w, o, d, float("inf"), out_t, out_p, no_counts)
            fns.append(lambda kernel=kernel, inputs=inputs: wp.launch(kernel, dim=n, inputs=inputs, device=device))
            summary = stats.summary()
            entries.append({"k": k, "nodes": w.num_nodes, "depth": w.depth, "collapse_ms": w.collapse_ms,
                            "sah": wide.sah_cost(w), "n_s": summary["mean_nodes_visited"],
                            "boxes": summary["mean_boxes_tested"], "n_t": summary["mean_prims_tested"],
                            "disagree": reference.count_mismatches(t, prim, ref_t, ref_p,
                                                                   rays=(vertices, faces, o_np, d_np))})
        # The library's own binary traversal over the same tree.
        t, prim, stats = intersect(bvh, o_np, d_np, stats=True)
        bvh_view = view(bvh)
        fns.append(lambda: wp.launch(traversal.closest_hit_kernel, dim=n, device=device,
                                     inputs=[bvh_view, o, d, float("inf"), out_t, out_p]))
        summary = stats.summary(1.0, 1.0)
        # Interior nodes visited and child boxes tested, as the wide rows count them: the binary
        # traversal's n_s also counts every leaf it pops, which tests no box. Where every leaf
        # holds one triangle and the stack never overflows, the leaves popped are the triangles
        # tested; elsewhere the split is not known and the row leaves both out.
        n_s = boxes = None
        if single_leaves:
            n_s = float((stats.nodes_visited - stats.prims_tested).mean()) if len(t) else 0.0
            boxes = 2.0 * n_s
        # Interior nodes, as the wide rows count them: a full binary tree has (nodes - 1) / 2.
        entries.append({"k": "bin", "nodes": (bvh.num_nodes - 1) // 2, "depth": None, "collapse_ms": None, "sah": None,
                        "n_s": n_s, "boxes": boxes, "n_t": summary["mean_prims_tested"],
                        "disagree": reference.count_mismatches(t, prim, ref_t, ref_p,
                                                                   rays=(vertices, faces, o_np, d_np))})
        progress(f"[{name} {method}] timing {kind} rays")
        times = best_times(fns, args.repeats, device)
        base = times[widths.index(2)]
        for entry, seconds in zip(entries, times):
            rows.append({"mesh": name, "num_tris": int(len(faces)), "method": method, "rays": kind, "num_rays": n,
                         **entry, "mrays_per_s": n / seconds / 1e6, "speedup": base / seconds})
    return rows


def format_row(r: dict) -> str:
    def opt(value, fmt):
        return "-" if value is None else format(value, fmt)

    return (f"{r['mesh']:>10s} {r['method']:>10s} {str(r['k']):>3s} {r['nodes']:7d} {opt(r['depth'], 'd'):>5s} "
            f"{opt(r['collapse_ms'], '.1f'):>8s} {opt(r['sah'], '.2f'):>7s} {r['rays']:>7s} {r['mrays_per_s']:8.3f} "
            f"{r['speedup']:6.2f} {opt(r['n_s'], '6.1f'):>6s} {opt(r['boxes'], '6.1f'):>6s} {r['n_t']:5.2f} "
            f"{r['disagree']:8d}")


def parse_args(argv):
    from . import wide

    parser = argparse.ArgumentParser(prog=command_prog("bench-wide"), description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", action="append", default=[], type=mesh_file,
                        help="mesh file (repeatable); default: a generated scene")
    parser.add_argument("--scene-tris", type=scene_tris, default=20000,
                        help="triangles of the generated scene (default: %(default)s)")
    parser.add_argument("--method", action="append", default=None,
                        help="binary builder to collapse (repeatable; default: hlbvh_sah)")
    parser.add_argument("--widths", default="2,4,8,16",
                        help="comma-separated branching factors, 2 to 16 (default: %(default)s)")
    parser.add_argument("--views", type=query_count, default=8, help="cameras on the orbit (default: %(default)s)")
    parser.add_argument("--side", type=image_side, default=128, help="pixels per image side (default: %(default)s)")
    parser.add_argument("--repeats", type=positive_int, default=5,
                        help="launches timed per traversal; the best is kept (default: %(default)s)")
    parser.add_argument("--device", type=device_name, default=None, help="Warp device (default: Warp's default device)")
    parser.add_argument("--cpu-threads", type=non_negative_int, default=0,
                        help="BuildConfig.cpu_threads (0: every core; default: %(default)s)")
    parser.add_argument("--json", default="out/bench_wide.json",
                        help="where to write the rows (default: %(default)s)")
    parser.add_argument("--seed", type=non_negative_int, default=1,
                        help="seed of the diffuse rays (default: %(default)s)")
    args = parser.parse_args(argv)
    check_ray_count(parser, args.views, args.side)
    try:
        args.widths = [int(k) for k in args.widths.split(",") if k.strip()]
    except ValueError:
        parser.error(f"--widths must be integers, got {args.widths!r}")
    if not args.widths or any(k not in wide.WIDTHS for k in args.widths):
        parser.error(f"--widths must lie in [2, {max(wide.WIDTHS)}], got {args.widths}")
    args.method = args.method or ["hlbvh_sah"]
    from . import api

    unknown = [m for m in args.method if m not in api.BUILDERS]
    if unknown:
        parser.error(f"unknown methods {unknown}; choose from {sorted(api.BUILDERS)}")
    # Before the run: a path that cannot be written failed only after every traversal was timed.
    with argument_errors(parser):
        check_out_file(args.json, "--json")
    return args


def main(argv=None) -> int:
    from . import scenes

    args = parse_args(list(sys.argv[1:] if argv is None else argv))
    quiet_warp()
    wp.init()
    device = wp.get_device(args.device)
    meshes = read_meshes(args.mesh) or scenes.named_meshes([], args.scene_tris)
    progress = scenes.progress
    print(f"device: {device}  rays: {args.views} views of {args.side}^2 and one diffuse bounce; best of "
          f"{args.repeats}; x k=2 = time at k = 2 / time (> 1: faster); bin = the library's binary traversal")
    print(HEADER)
    rows = []
    with wp.ScopedDevice(device):
        for name, vertices, faces in meshes:
            for method in args.method:
                mesh_rows = measure_mesh(name, vertices, faces, method, args, device, progress)
                progress("")
                for row in mesh_rows:
                    print(format_row(row), flush=True)
                rows += mesh_rows
    path = pathlib.Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"device": str(device), "repeats": args.repeats, "rows": rows}, indent=1))
    print(f"inner: interior nodes; n_s: nodes visited per ray, boxes: child boxes tested, n_t: triangles tested; "
          f"wrote {path}")
    return 1 if any(r["disagree"] for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
