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

KERNEL_MODULES = ["block_sort", "bounds", "compress", "dynamic", "metrics", "morton", "recursive_sah", "sah", "spatial_split",
                  "traversal", "treelets", "upper_sah", "wide"]
# The examples and tests with kernels of their own: users' kernels calling the library's queries.
SCRIPT_MODULES = ["examples/example_user_kernel.py", "examples/example_particle_collisions.py",
                  "examples/example_scene_builds.py"]
# Turing, the oldest architecture current CUDA toolkits target, and Hopper.
ARCHES = [75, 90]


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
    return sum(isinstance(value, wp.Kernel) for value in vars(module).values())


def compile_for_cuda(module, arch: int, out_dir: pathlib.Path) -> str:
    """The PTX of `module` for `arch`, compiled into `out_dir` (not Warp's cache, so it compiles)."""
    paths = wp.compile_aot_module(module, arch=arch, module_dir=str(out_dir), use_ptx=True)
    ptx = [p for p in paths if str(p).endswith(".ptx")]
    assert len(ptx) == 1, paths
    return pathlib.Path(ptx[0]).read_text()


@pytest.mark.parametrize("arch", ARCHES)
@pytest.mark.parametrize("name", KERNEL_MODULES)
def test_kernel_module_compiles_for_cuda(name, arch, tmp_path):
    module = importlib.import_module(f"hlbvh_warp.kernels.{name}")
    ptx = compile_for_cuda(module, arch, tmp_path)
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
