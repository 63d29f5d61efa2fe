"""The device code ships inside the package: `kernels/` is installed as `hlbvh_warp.kernels`."""

from __future__ import annotations

import subprocess
import sys
import zipfile

from conftest import REPO_ROOT


def test_wheel_maps_kernels_into_the_package(tmp_path):
    # No build isolation: the test extra installs setuptools and wheel, and CI needs no download.
    result = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(tmp_path),
         str(REPO_ROOT)],
        capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, f"building the wheel failed:\n{result.stdout[-2000:]}\n{result.stderr[-2000:]}"
    wheel = next(tmp_path.glob("*.whl"))
    names = set(zipfile.ZipFile(wheel).namelist())
    for module in ("__init__", "morton", "compress", "block_sort", "treelets", "bounds", "traversal"):
        assert f"hlbvh_warp/kernels/{module}.py" in names
    assert not any(n.startswith("kernels/") for n in names), "kernels/ must not install as a top-level package"
