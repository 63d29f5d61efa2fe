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
