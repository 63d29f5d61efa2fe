"""Public entry points: build a BVH from a mesh or from boxes, and cast rays against it."""

from __future__ import annotations

import warp as wp

from . import inputs, memory
from .bvh import Bvh
from .config import BuildConfig
from .hlbvh import HlbvhPipeline, StageTimer

#: method name -> ``fn(prim_lowers, prim_uppers, config, device, timer)`` returning a `Bvh`; the
#: reference builders (`builders`) add themselves.
BUILDERS = {}
#: Offline quality references, seconds (``sbvh``) to minutes (``recursive_sah``) at 100k
#: triangles: the demo and the default tables leave them out unless asked for.
OFFLINE_BUILDERS = ("recursive_sah", "sbvh")


def needs_mesh(method: str) -> bool:
    """True for builders that cut triangles (spatial splits): they take a mesh, not bare boxes."""
    _load_optional_builders()
    return getattr(BUILDERS.get(method), "needs_triangles", False)


def _pipeline_builder(method: str):
    def run(prim_lowers: wp.array, prim_uppers: wp.array, config: BuildConfig, device, timer: StageTimer,
            triangles: tuple | None = None) -> Bvh:
        """``triangles``: (vertices, faces) on the device, whose boxes are to fill the (empty)
        ``prim_lowers/uppers``: computed in the pass that reduces the centroid bounds, as a
        `Builder` frame does, instead of a pass for the boxes and another for the bounds."""
        n = prim_lowers.shape[0]
        pipe = HlbvhPipeline.one_shot(n, config, device, prim_lowers, prim_uppers)
        ready = "boxes"
        if triangles is not None:
            pipe.compute_triangle_bounds(*triangles)
            ready = "bounds"
        pipeline_timings = pipe.build(method, timer, inputs_ready=ready)
        bvh = bvh_from_pipeline(pipe, method, pipeline_timings)
        pipe.give_back()
        return bvh

    run.fuses_triangle_bounds = True
    return run


def bvh_from_pipeline(pipe: HlbvhPipeline, method: str, timings: dict, prim_order: wp.array | None = None) -> Bvh:
    """A `Bvh` over a finished pipeline's output arrays, without copying them (the pipeline renews
    its outputs before it builds again). ``prim_order``: the tree's order where the pipeline keeps
    it elsewhere than in its sorted ids (the HLBVH + SAH pipeline's join writes its own)."""
    return Bvh._trusted(
        method=method,
        config=pipe.config,
        device=pipe.device,
        prim_lowers=pipe.prim_lowers,
        prim_uppers=pipe.prim_uppers,
        prim_order=pipe.sorted_prim_ids[:pipe.num_prims] if prim_order is None else prim_order,
        node_lowers=pipe.node_lowers,
        node_uppers=pipe.node_uppers,
        node_left=pipe.node_left,
        node_right=pipe.node_right,
        node_parent=pipe.node_parent,
        node_begin=pipe.node_begin,
        node_end=pipe.node_end,
        node_count=pipe.node_count,
        timings=timings,
    )


BUILDERS["hlbvh"] = _pipeline_builder("hlbvh")
BUILDERS["lbvh"] = _pipeline_builder("lbvh")


def _resolve(method: str, config: BuildConfig | None, device):
    if config is None:
        config = BuildConfig()
    elif not isinstance(config, BuildConfig):
        raise ValueError(f"config must be a BuildConfig, got {type(config).__name__}")
    _load_optional_builders()
    if not isinstance(method, str) or method not in BUILDERS:
        raise ValueError(f"unknown method {method!r}; choose one of {sorted(BUILDERS)}")
    return config, wp.get_device(device)


def _load_optional_builders():
    # Reference builders register themselves on import; imported lazily to keep `import` cheap.
    # They are part of the package: an import error is a bug to show, not "unknown method".
    from . import builders  # noqa: F401


def build(mesh, faces=None, *, method: str = "hlbvh", device=None, config: BuildConfig | None = None,
          timings: bool = False) -> Bvh:
    """Build a BVH over the triangles of a mesh.

    Args:
        mesh: a ``trimesh.Trimesh``, or vertices ``(V, 3)`` (NumPy or Warp; float64 is converted).
        faces: ``(F, 3)`` vertex indices of any integer width when ``mesh`` is vertices.
        method: ``"hlbvh"`` (Pantaleoni & Luebke 2010), ``"lbvh"`` (one global radix sort, the
            paper's Table 1 baseline), or a reference builder (``"sweep_sah"``, ``"binned_sah"``,
            ``"median"``, ``"hlbvh_sah"``, the offline ``"recursive_sah"`` and ``"sbvh"``).
        device: Warp device; the current default device when ``None``.
        config: `BuildConfig`; defaults when ``None``.
        timings: when True, synchronize around every stage and fill ``Bvh.timings`` (ms).

    Raises:
        ValueError: NaN/Inf coordinates, out-of-range face indices, wrong shapes or dtypes, an
            empty mesh, or an unknown method.
    """
    config, device = _resolve(method, config, device)
    verts_np, faces_np = inputs.mesh_arrays(mesh, faces)
    vertices = memory.empty(verts_np.shape[0], dtype=wp.vec3, device=device)
    vertices.assign(verts_np)
    face_arr = memory.empty(faces_np.shape, dtype=wp.int32, device=device)
    face_arr.assign(faces_np)
    timer = StageTimer(device, timings)
    timer.stage("prim_bounds")
    n = faces_np.shape[0]
    lowers = memory.empty(n, dtype=wp.vec3, device=device)
    uppers = memory.empty(n, dtype=wp.vec3, device=device)
    builder = BUILDERS[method]
    if getattr(builder, "fuses_triangle_bounds", False):
        bvh = builder(lowers, uppers, config, device, timer, triangles=(vertices, face_arr))
    else:
        from .kernels import morton

        wp.launch(morton.triangle_bounds_kernel, dim=n, inputs=[vertices, face_arr, lowers, uppers], device=device)
        if getattr(builder, "needs_triangles", False):
            bvh = builder(lowers, uppers, config, device, timer, triangles=(vertices, face_arr))
        else:
            bvh = builder(lowers, uppers, config, device, timer)
    bvh.vertices = vertices
    bvh.faces = face_arr
    return bvh


def build_from_bounds(lowers, uppers, *, method: str = "hlbvh", device=None, config: BuildConfig | None = None,
                      timings: bool = False) -> Bvh:
    """Build a BVH over arbitrary primitives given by their boxes ``(N, 3)`` lowers and uppers."""
    config, device = _resolve(method, config, device)
    if needs_mesh(method):
        raise ValueError(f"method {method!r} splits triangles and needs a mesh: use build(), not build_from_bounds()")
    lo, hi = inputs.bounds_arrays(lowers, uppers)
    timer = StageTimer(device, timings)
    return BUILDERS[method](
        wp.array(lo, dtype=wp.vec3, device=device), wp.array(hi, dtype=wp.vec3, device=device), config, device, timer
    )
