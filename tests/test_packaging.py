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


def test_the_submodules_the_readme_uses_are_attributes_of_the_package():
    """The README writes ``hlbvh_warp.wide.collapse(...)`` and ``metrics.sah_cost``: after a plain
    ``import hlbvh_warp as hb`` (a fresh process, where no other import has loaded them),
    ``hb.wide`` raised AttributeError."""
    code = "import hlbvh_warp as hb; print(hb.wide.collapse.__name__, hb.metrics.sah_cost.__name__, " \
           "hb.memory.clear_host_cache.__name__)"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO_ROOT)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.split() == ["collapse", "sah_cost", "clear_host_cache"]
