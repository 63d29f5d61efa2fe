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
#: those files). They inline the library's walks, and at clang's default -O2 (with Warp's raised
#: inlining thresholds) the CPU compiled test_queries' five kernels in 25 s, test_ray_range's two
#: in 20 s; at -O0, in 5 s and 3.4 s. CI starts from an empty kernel cache, where those compiles
#: were over a minute of the suite. Floating point is unchanged: Warp emits one operation per
#: statement and the CPU contracts none at either level. With a GPU present the tests keep the
#: defaults, as CUDA users compile them.
TEST_KERNEL_OPTIONS = {} if wp.get_cuda_devices() else {"optimization_level": 0}


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
