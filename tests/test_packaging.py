"""The device code ships inside the package: `kernels/` is installed as `hlbvh_warp.kernels`."""

from __future__ import annotations

import subprocess
import sys
import zipfile

import pytest

from conftest import REPO_ROOT


def test_wheel_maps_kernels_into_the_package(tmp_path):
    try:
        subprocess.run(
            [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(tmp_path),
             str(REPO_ROOT)],
            check=True, capture_output=True, timeout=300,
        )
    except subprocess.CalledProcessError as exc:  # e.g. setuptools too old for package-dir editable
        pytest.skip(f"could not build a wheel here: {exc.stderr.decode()[-300:]}")
    wheel = next(tmp_path.glob("*.whl"))
    names = set(zipfile.ZipFile(wheel).namelist())
    for module in ("__init__", "morton", "compress", "block_sort", "treelets", "bounds", "traversal"):
        assert f"hlbvh_warp/kernels/{module}.py" in names
    assert not any(n.startswith("kernels/") for n in names), "kernels/ must not install as a top-level package"
