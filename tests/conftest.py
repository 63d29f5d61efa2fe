"""Shared fixtures: every test that can runs once per available Warp device."""

from __future__ import annotations

import os
import pathlib

import numpy as np
import pytest
import warp as wp

wp.config.quiet = True
wp.init()

DEVICES = ["cpu"] + [str(d) for d in wp.get_cuda_devices()]
REPO_ROOT = pathlib.Path(__file__).resolve().parents[1]
SHARED_MESHES = REPO_ROOT.parent / "shared" / "meshes"

#: Module options for the kernels the tests define themselves (`wp.set_module_options` at the top of
#: those files). They inline the library's walks, and Warp's default CPU flags raise LLVM's inlining
#: thresholds (to 9000), which doubled their compile: test_queries' five kernels took 21 s, with
#: LLVM's own thresholds 11 s, and the files ran no slower (the library's functions are inlined by
#: Warp's hint either way). CI starts from an empty kernel cache. -O0 compiled faster still, but
#: its kernels made test_proximity's bunny walks 5x slower. CUDA compiles are unaffected.
TEST_KERNEL_OPTIONS = {"cpu_compiler_flags": "-march=native"}


@pytest.fixture(params=DEVICES)
def device(request):
    return request.param


def shared_mesh(name: str):
    """A mesh from ../shared/meshes, or a skip when that folder is absent (a plain clone)."""
    import trimesh

    path = SHARED_MESHES / f"{name}.ply"
    if not path.exists():
        pytest.skip(f"{path} not found: the shared benchmark meshes sit beside the repository")
    return trimesh.load(path, process=False)


@pytest.fixture
def rng():
    return np.random.default_rng(int(os.environ.get("HLBVH_TEST_SEED", "1234")))
