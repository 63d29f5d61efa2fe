"""Animated test scenes after the paper's dynamic benchmarks (Pantaleoni & Luebke 2010, section 4,
Fig. 7).

- `ExplodingMesh`: the "Exploding Turbine Blade" setup: the mesh is blasted into its
  triangles, each flying with a random velocity (as in the paper) and spinning about a random
  axis (an addition of ours).
- `BendingMesh`: the "Bending Armadillo" setup: the mesh is bent progressively around an
  axis, a smooth deformation that keeps the topology and the neighbourhoods.

Both keep their vertices in one preallocated device array (``.vertices``) updated by a kernel
each frame, so a `hlbvh_warp.Builder` can rebuild from device memory.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .inputs import mesh_arrays
from .kernels import dynamic


class ExplodingMesh:
    """Triangles of a mesh flying apart: ``vertices(t)`` for t >= 0 (t = 0 is the intact mesh).

    The triangles are unwelded (3 vertices each), so ``faces`` is ``arange(3F).reshape(F, 3)``.
    Speeds are in units of the mesh's bounding-box diagonal per unit time.
    """

    def __init__(self, vertices, faces, device=None, seed: int = 0, speed: float = 0.5, spin: float = 6.0):
        self.device = wp.get_device(device)
        # The checks of `hlbvh_warp.build`: NumPy would wrap a face index of -1 and truncate 2.7.
        v, f = mesh_arrays(vertices, faces)
        v, f = v.astype(np.float64), f.astype(np.int64)
        corners = v[f]  # (F, 3, 3)
        centroids = corners.mean(axis=1)
        offsets = corners - centroids[:, None, :]
        rng = np.random.default_rng(seed)
        lo, hi = v.min(axis=0), v.max(axis=0)
        diagonal = float(np.linalg.norm(hi - lo)) or 1.0
        center = 0.5 * (lo + hi)
        # Blast outwards from the centre, with a random component, at a random speed.
        outward = centroids - center
        outward /= np.maximum(np.linalg.norm(outward, axis=1, keepdims=True), 1e-12)
        direction = outward + 0.5 * rng.normal(size=outward.shape)
        direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-12)
        velocities = direction * (speed * diagonal * rng.uniform(0.25, 1.0, size=(len(f), 1)))
        axes = rng.normal(size=(len(f), 3))
        axes /= np.maximum(np.linalg.norm(axes, axis=1, keepdims=True), 1e-12)
        spins = spin * rng.uniform(-1.0, 1.0, size=len(f))

        def dev(a, dtype=wp.vec3):
            return wp.array(np.ascontiguousarray(a, dtype=np.float32), dtype=dtype, device=self.device)

        self.num_tris = len(f)
        self.faces = np.arange(3 * len(f), dtype=np.int32).reshape(-1, 3)
        self._centroids = dev(centroids)
        self._offsets = dev(offsets.reshape(-1, 3))
        self._velocities = dev(velocities)
        self._axes = dev(axes)
        self._spins = dev(spins, wp.float32)
        self.vertices = wp.empty(3 * len(f), dtype=wp.vec3, device=self.device)
        self.update(0.0)

    def update(self, time: float) -> wp.array:
        """Move every triangle to its position at ``time``; returns ``self.vertices``."""
        wp.launch(dynamic.explode_kernel, dim=self.num_tris,
                  inputs=[self._centroids, self._offsets, self._velocities, self._axes, self._spins, float(time),
                          self.vertices], device=self.device)
        return self.vertices


class BendingMesh:
    """A mesh bent around an axis, progressively: ``update(amount)`` bends the mesh's longest
    extent into an arc of ``amount * max_angle`` radians (0 is the rest pose).

    The surface that keeps its length is the mesh's face on the inside of the bend; every other
    layer lies farther from the arc's centre and is stretched along the arc by
    ``1 + depth * curvature``. A neutral surface through the middle would fold the inner layers
    through the arc's centre (pinched to a line, turned inside out) once the radius falls below
    half the mesh's thickness: past about two thirds of the bend for the bunny, the armadillo and
    the generated knot.
    """

    def __init__(self, vertices, faces, device=None, max_angle: float = np.pi):
        self.device = wp.get_device(device)
        v, faces = mesh_arrays(vertices, faces)  # the checks of `hlbvh_warp.build`
        v = v.astype(np.float64)
        lo, hi = v.min(axis=0), v.max(axis=0)
        extent = hi - lo
        order = np.argsort(extent)[::-1]
        self.length_axis = np.eye(3)[order[0]]
        self.bend_axis = np.eye(3)[order[1]]
        self.length = float(extent[order[0]]) or 1.0
        self.origin = 0.5 * (lo + hi)
        # Where the neutral surface crosses the bend axis, for a bend towards +bend_axis (positive
        # amounts) and towards -bend_axis (negative): the mesh's face on the inside of the bend.
        self._inner = (float(hi[order[1]]), float(lo[order[1]]))
        self.max_angle = float(max_angle)
        self.faces = np.ascontiguousarray(faces, dtype=np.int32)
        self._rest = wp.array(np.ascontiguousarray(v, dtype=np.float32), dtype=wp.vec3, device=self.device)
        self.vertices = wp.empty(len(v), dtype=wp.vec3, device=self.device)
        self.update(0.0)

    def update(self, amount: float) -> wp.array:
        """Bend by ``amount`` (0..1) of ``max_angle``; returns ``self.vertices``."""
        curvature = float(amount) * self.max_angle / self.length
        # Every point then lies at least the radius from the arc's centre: none folds through it.
        inner = self._inner[0 if curvature >= 0.0 else 1]
        origin = self.origin + (inner - self.origin @ self.bend_axis) * self.bend_axis
        wp.launch(dynamic.bend_kernel, dim=self.vertices.shape[0],
                  inputs=[self._rest, wp.vec3(*origin), wp.vec3(*self.length_axis), wp.vec3(*self.bend_axis),
                          wp.float64(curvature), self.vertices], device=self.device)
        return self.vertices


class Animation:
    """One animated scene driven frame by frame through a `Builder`: times each frame's update,
    optionally ray-casts it, and keeps the per-frame reports (the examples and the demo share it).

    ``scene`` is an `ExplodingMesh` or a `BendingMesh`; ``param(frame)`` gives the argument of
    ``scene.update`` for a frame (a time or a bend amount).
    """

    def __init__(self, scene, builder, param, camera=None, image_size: int = 256, reference=None):
        from .render import Camera

        self.scene = scene
        self.builder = builder
        self.param = param
        self.image_size = int(image_size)
        # A rebuild-every-frame builder run beside `builder` to compare SAH costs with, or None.
        self.reference = reference
        self.builder.build(scene.vertices, scene.faces)
        if reference is not None:
            reference.build(scene.vertices, scene.faces)
        # Only where frames are rendered: a camera refuses a mesh too large to frame in float32,
        # which a headless run (builds only) can still take.
        self.camera = camera or (Camera.framing(scene.vertices.numpy()) if self.image_size > 0 else None)
        self.frame = 0
        self.rows: list[dict] = []
        self.images: list[np.ndarray] = []

    def step(self):
        """Advance one frame: deform on the device, then update the BVH (timed, synchronized)."""
        import time

        self.frame += 1
        device = self.builder.device
        vertices = self.scene.update(self.param(self.frame))
        wp.synchronize_device(device)
        start = time.perf_counter()
        report = self.builder.update(vertices)
        wp.synchronize_device(device)
        row = {"frame": self.frame, "decision": report["decision"], "ms": (time.perf_counter() - start) * 1e3,
               "reason": report["reason"], "skipped": report["stages_skipped"]}
        if "input_order" in report:
            # A resorted builder's rebuild: which order it was fed, and the sample behind that.
            note = "resorted" if report["input_order"] == "previous tree" else "face order"
            if report.get("sampled_run_fraction") is not None:
                note += f" (sampled M/N {report['sampled_run_fraction']:.2f})"
            row["input"] = note
        if self.reference is not None:
            start = time.perf_counter()
            self.reference.rebuild(vertices)
            wp.synchronize_device(device)
            row["rebuild_ms"] = (time.perf_counter() - start) * 1e3
            row["sah"] = report.get("sah", None) or self.builder.sah_cost()
            row["rebuild_sah"] = self.reference.sah_cost()
            row["sah_ratio"] = row["sah"] / row["rebuild_sah"]
        self.rows.append(row)
        return row

    def render(self):
        """Ray-cast the current frame with `hlbvh_warp.intersect` (kept for `save`)."""
        from .render import render

        if self.image_size > 0:
            self.images.append(render(self.builder.bvh, self.camera, self.image_size, self.image_size))

    def table(self) -> str:
        """The per-frame rows as a fixed-width text table, with a summary line."""
        lines = []
        compare = self.reference is not None
        head = f"{'frame':>5}  {'decision':8}  {'ms':>8}"
        if compare:
            head += f"  {'rebuild ms':>10}  {'SAH / rebuild SAH':>17}"
        lines.append(head + "  reason")
        for r in self.rows:
            line = f"{r['frame']:>5}  {r['decision']:8}  {r['ms']:8.2f}"
            if compare:
                line += f"  {r['rebuild_ms']:10.2f}  {r['sah_ratio']:17.3f}"
            lines.append(line + "  " + r["reason"] + (f"; {r['input']}" if "input" in r else ""))
        ms = np.array([r["ms"] for r in self.rows]) if self.rows else np.zeros(1)
        summary = (f"{len(self.rows)} frames: average {ms.mean():.2f} ms, worst {ms.max():.2f} ms, "
                   f"total {ms.sum():.1f} ms")
        if compare and self.rows:
            ref = np.array([r["rebuild_ms"] for r in self.rows])
            ratio = np.array([r["sah_ratio"] for r in self.rows])
            summary += (f"; rebuild every frame: total {ref.sum():.1f} ms; worst SAH ratio {ratio.max():.3f}")
        lines.append(summary)
        return "\n".join(lines)

    def legend(self) -> str:
        """The line printed under `table`, saying what its terms mean (those it shows).

        "sampled M/N" is the fraction of a resorting `Builder`'s sample (``resort_samples`` evenly
        spaced adjacent pairs in the last frame's tree order, their Morton codes computed from this
        frame's boxes) whose codes differ in their high 3m bits: an estimate of M / N, the runs per
        primitive of the run-length encoding that HLBVH's compress step would get from that order
        (Pantaleoni & Luebke 2010, sections 2.2 and 3.1). Past ``BuildConfig.global_sort_runs``, unless
        no sampled pair descends, the frame is fed in the faces' order (`Builder._resorting_pays`)."""
        rows = self.rows
        parts = ["ms: the Builder's update of the frame"]
        if any("sah_ratio" in r for r in rows):
            parts.append("rebuild ms, SAH / rebuild SAH: a tree rebuilt from scratch on the same frame, its time and "
                         "this tree's SAH cost over its")
        inputs = " ".join(r.get("input", "") for r in rows)
        if "resorted" in inputs or "face order" in inputs:
            parts.append("resorted: fed in the last frame's tree order; face order: in the order the faces are listed")
        if "sampled M/N" in inputs:
            builder = self.builder
            parts.append(f"sampled M/N: of {builder.resort_samples} evenly spaced adjacent pairs in the last tree's "
                         "order, the fraction whose Morton codes differ in their high 3m bits, an estimate of the runs "
                         "per primitive that order gives HLBVH's compress step; past "
                         f"{builder.config.global_sort_runs:g} (global_sort_runs) the faces' order is fed instead")
        return "; ".join(parts)

    def save(self, out_dir, stem: str) -> list:
        """The last frame as PNG and all rendered frames as an animated GIF; returns the paths."""
        from .render import save_gif, save_png

        if not self.images:
            return []
        return [save_png(self.images[-1], f"{out_dir}/{stem}.png"), save_gif(self.images, f"{out_dir}/{stem}.gif")]
