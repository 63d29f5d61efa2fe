"""No query is called out of line with a view: the compiled CPU code of the query modules holds no
function of their own that takes a `BvhView` or `WideView` by value.

A Warp function receives a struct by value. Once the ray walk grew past the C++ compiler's
inlining threshold, the query taking the view became a real call, and every ray copied the
view's thirteen arrays first: 10-20% of a ray, unnoticed for a round, since every answer stayed
right. The queries taking a view are now marked for inlining; this reads the object code, where
the compiler's decision shows.
"""

from __future__ import annotations

import inspect
import shutil
import subprocess
import warnings

import pytest
import warp as wp

from hlbvh_warp.kernels import proximity, traversal, wide

pytestmark = [
    pytest.mark.skipif(shutil.which("nm") is None, reason="needs nm (binutils) to read the object code"),
    pytest.mark.skipif("inline" not in inspect.signature(wp.func).parameters,
                       reason="this Warp has no inlining hint, and its compiler decides alone"),
]


@pytest.mark.parametrize("module", [traversal, wide, proximity], ids=lambda m: m.__name__.rsplit(".", 1)[-1])
def test_no_local_function_takes_a_view_by_value(module, tmp_path):
    with warnings.catch_warnings():
        # The object is compiled for this CPU (-march=native), which Warp warns about: only read here.
        warnings.simplefilter("ignore")
        paths = wp.compile_aot_module(module, device="cpu", module_dir=str(tmp_path))
    objects = [p for p in paths if str(p).endswith(".o")]
    assert len(objects) == 1, paths
    symbols = subprocess.run(["nm", "-C", str(objects[0])], capture_output=True, text=True, check=True).stdout
    # Local text symbols ("t"): the module's own functions left out of line.
    local = [line.split(" ", 2)[2] for line in symbols.splitlines() if line.split(" ")[1:2] == ["t"]]
    assert any("_cpu_block_thunk_forward" in name for name in local), "no kernel found: the listing changed form"
    by_value = [name for name in local if "BvhView_" in name or "WideView_" in name]
    assert not by_value, f"out of line, copying a view per call: {by_value}"
