"""Every kernel module compiles for CUDA, on any machine whose Warp can compile CUDA code.

The tests that launch kernels run on CUDA only where a GPU is present. Compiling for a GPU needs
no GPU: Warp's NVRTC turns each module into PTX ahead of time (`wp.compile_aot_module`). So a
construct that the CPU's C++ accepts and CUDA does not is caught on a CPU-only machine too.
"""

from __future__ import annotations

import importlib
import importlib.util
import pathlib

import pytest
import warp as wp

from conftest import REPO_ROOT

KERNEL_MODULES = ["block_sort", "bounds", "collide", "compress", "dynamic", "merge", "metrics", "morton", "proximity",
                  "recursive_sah", "sah", "spatial_split", "traversal", "treelets", "upper_sah", "wide"]
# The examples and tests with kernels of their own: users' kernels calling the library's queries.
SCRIPT_MODULES = ["examples/example_user_kernel.py", "examples/example_particle_collisions.py",
                  "examples/example_scene_builds.py", "examples/example_mesh_contact.py"]
# Turing, the oldest architecture current CUDA toolkits target, and Hopper.
ARCHES = [75, 90]
# Every module compiles for the oldest (an intrinsic or instruction a newer architecture added
# fails there first); the newest only for the modules whose PTX the tests below read, since
# NVRTC's front end is the same for both and each compile of a big module takes seconds (the
# file took 2 min 20 s compiling every module for both and the traversal five more times).
NEWEST_ARCH_MODULES = ["bounds", "metrics", "traversal", "wide"]


def cuda_compiler_present() -> bool:
    return bool(wp._src.context.runtime.core.wp_is_cuda_enabled())


pytestmark = pytest.mark.skipif(not cuda_compiler_present(), reason="this Warp build cannot compile CUDA code")


def load_script(relative: str):
    path = REPO_ROOT / relative
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def kernel_count(module) -> int:
    """Entry points the module compiles to: one per kernel, one per declared overload of a
    generic one (such as the closest-point kernel's one bound or one per point)."""
    kernels = [value for value in vars(module).values() if isinstance(value, wp.Kernel)]
    # An overload kept under its own name is one of its generic kernel's entries, counted there.
    return sum(len(k.overloads) if k.is_generic else 1 for k in kernels if k.generic_parent is None)


def compile_for_cuda(module, arch: int, out_dir: pathlib.Path) -> str:
    """The PTX of `module` for `arch`, compiled into `out_dir` (not Warp's cache, so it compiles)."""
    paths = wp.compile_aot_module(module, arch=arch, module_dir=str(out_dir), use_ptx=True)
    ptx = [p for p in paths if str(p).endswith(".ptx")]
    assert len(ptx) == 1, paths
    return pathlib.Path(ptx[0]).read_text()


@pytest.fixture(scope="module")
def kernel_ptx(tmp_path_factory):
    """``kernel_ptx(name, arch)``: the PTX of ``hlbvh_warp.kernels.<name>`` for ``arch``, compiled
    once for the whole file (several tests read the same module's PTX)."""
    done = {}

    def compiled(name: str, arch: int) -> str:
        if (name, arch) not in done:
            module = importlib.import_module(f"hlbvh_warp.kernels.{name}")
            done[name, arch] = compile_for_cuda(module, arch, tmp_path_factory.mktemp(f"{name}_{arch}"))
        return done[name, arch]

    return compiled


@pytest.mark.parametrize("name,arch", [(name, ARCHES[0]) for name in KERNEL_MODULES]
                         + [(name, ARCHES[-1]) for name in NEWEST_ARCH_MODULES])
def test_kernel_module_compiles_for_cuda(name, arch, kernel_ptx):
    module = importlib.import_module(f"hlbvh_warp.kernels.{name}")
    ptx = kernel_ptx(name, arch)
    # One entry point per kernel (the kernels modules turn the backward pass off).
    assert ptx.count(".entry ") == kernel_count(module)
    assert f".target sm_{arch}" in ptx


@pytest.mark.parametrize("relative", SCRIPT_MODULES)
def test_user_kernels_calling_the_queries_compile_for_cuda(relative, tmp_path):
    module = load_script(relative)
    assert kernel_count(module) > 0
    ptx = compile_for_cuda(module, ARCHES[0], tmp_path)
    assert ptx.count(".entry ") >= kernel_count(module)


def test_the_kernel_list_is_complete():
    """A new kernel module must join the list above, or it would go unchecked."""
    on_disk = {p.stem for p in (REPO_ROOT / "kernels").glob("*.py") if p.stem != "__init__"}
    assert on_disk == set(KERNEL_MODULES)
    # The tests reading PTX compile for the newest architecture: their modules must be checked there.
    assert {name for name, _ in CLIMB_KERNELS + WATERTIGHT_KERNELS} <= set(NEWEST_ARCH_MODULES)


# The bottom-up climbs (Karras 2012): the first child to reach a parent writes its box (or cost)
# and leaves through an atomic visit counter; the second reads it. On CUDA that needs a fence
# before the atomic (the writer's stores ordered before its visit) and one after it (the
# reader's loads after the visit, not from a stale L1 line), as Warp's own refit (bvh.cu) has.
CLIMB_KERNELS = [("bounds", "node_bounds_kernel"), ("metrics", "sah_cost_kernel"),
                 ("metrics", "bounds_and_cost_kernel")]


@pytest.mark.parametrize("arch", ARCHES)
@pytest.mark.parametrize("name,kernel", CLIMB_KERNELS)
def test_climb_kernels_fence_around_their_visit_counters(name, kernel, arch, kernel_ptx):
    import re

    ptx = kernel_ptx(name, arch)
    body = re.search(r"\.entry %s_[0-9a-f]+_cuda_kernel_forward\(.*?\n}\n" % kernel, ptx, re.S)
    assert body is not None, kernel
    lines = body.group(0).splitlines()
    fence = re.compile(r"\b(membar\.gl|fence\.(sc|acq_rel)\.gpu)\b")
    atoms = [i for i, line in enumerate(lines) if "atom.global.add" in line]
    assert len(atoms) == 1, kernel
    assert any(fence.search(line) for line in lines[: atoms[0]]), f"{kernel}: no fence before the visit counter"
    assert any(fence.search(line) for line in lines[atoms[0] + 1 :]), f"{kernel}: no fence after the visit counter"


# Kernels whose rays meet triangles through `traversal.intersect_triangle_watertight`.
WATERTIGHT_KERNELS = [("traversal", "closest_hit_kernel"), ("traversal", "all_hits_kernel"),
                      ("wide", "wide_closest_hit_range_kernel")]


def _kernel_ptx(name: str, kernel: str, kernel_ptx) -> str:
    """The PTX of one kernel's forward entry in module ``kernels.<name>``, for the newest arch."""
    import re

    ptx = kernel_ptx(name, ARCHES[-1])
    body = re.search(r"\.entry %s_[0-9a-f]+_cuda_kernel_forward\(.*?\n}\n" % kernel, ptx, re.S)
    assert body is not None, kernel
    return body.group(0)


@pytest.mark.parametrize("name,kernel", WATERTIGHT_KERNELS)
def test_edge_functions_are_never_fused_into_multiply_adds(name, kernel, kernel_ptx):
    """Woop et al.'s watertight test needs the two triangles at an edge to compute its edge
    function as exact negatives: each product rounded, then the difference. PTX's plain
    ``mul.f32`` / ``sub.f32`` let the assembler fuse them into an ``fma`` (NVRTC's default
    --fmad=true), which breaks that, so rays leaked through edges; ``.rn`` forbids it."""
    import re

    body = _kernel_ptx(name, kernel, kernel_ptx)
    # u, v and w: two products rounded apart, then their difference rounded.
    edge = re.compile(r"mul\.rn\.f32[^\n]*\n\s*mul\.rn\.f32[^\n]*\n\s*sub\.rn\.f32")
    assert len(edge.findall(body)) >= 3, f"{kernel}: edge functions left free to fuse"


@pytest.mark.parametrize("name,kernel", WATERTIGHT_KERNELS)
def test_shear_products_are_never_fused_into_multiply_adds(name, kernel, kernel_ptx):
    """The shear of Woop et al. 2013, p[kx] - sx * p[kz], gives a point the ray passes through
    exactly a zero edge function only with the product rounded before the difference; fused into
    an ``fma``, rays aimed at a cube's silhouette edge missed it. Six per triangle test: a
    ``sub.rn.f32`` from a coordinate (not a product) of a ``mul.rn.f32`` just before it."""
    import re

    body = _kernel_ptx(name, kernel, kernel_ptx)
    products = set(re.findall(r"mul\.rn\.f32\s+(%f\d+),", body))
    shears = [(x, y) for x, y in re.findall(r"sub\.rn\.f32\s+%f\d+,\s*(%f\d+),\s*(%f\d+);", body)
              if y in products and x not in products]
    assert len(shears) >= 6, f"{kernel}: shear products left free to fuse"


def test_veltkamp_split_of_a_far_origins_start_is_never_fused(kernel_ptx):
    """`traversal.point_on_ray` splits s as c = 134217729 s, head = c - (c - s): with c left as a
    plain ``mul.f64`` the assembler may fuse it into either difference (NVRTC's --fmad=true), the
    head keeps every bit, and a far origin's start point leaves the ray. Every product by the
    split constant (0d41A0000002000000) must be a ``mul.rn.f64``, which forbids that."""
    import re

    ptx = kernel_ptx("traversal", ARCHES[-1])
    # The constant as an immediate operand (a plain product), or moved to a register first.
    immediate = re.findall(r"(mul(?:\.rn)?\.f64)\s+%fd\d+,\s*%fd\d+,\s*0d41A0000002000000;", ptx, re.I)
    moved = re.findall(r"mov\.f64\s+(%fd\d+),\s*0d41A0000002000000;\s*\n\s*(mul(?:\.rn)?\.f64)\s+%fd\d+,\s*\1,",
                       ptx, re.I)
    products = immediate + [op for _, op in moved]
    assert products, "no product by the split constant found"
    assert all(op == "mul.rn.f64" for op in products), f"the split's product left free to fuse: {products}"
