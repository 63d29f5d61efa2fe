"""Command line: ``python -m hlbvh_warp <command> [options]``.

Each command lives in its own module with a ``main(argv)``; this file only dispatches.
"""

from __future__ import annotations

import importlib
import sys

COMMANDS = {
    "demo": ("hlbvh_warp.demo", "build a generated scene with each method, check rays, print timings"),
    "bench": ("hlbvh_warp.bench", "build time against tree quality for every builder (JSON + plot)"),
    "bench-rays": ("hlbvh_warp.ray_bench", "closest-hit rays per second against wp.Mesh"),
    "bench-wide": ("hlbvh_warp.wide_bench", "closest-hit rays through wide BVHs (k = 2, 4, 8, 16)"),
    "quality": ("hlbvh_warp.quality", "SAH, end-point overlap and measured ray cost of every builder"),
    "stress": ("hlbvh_warp.stress_report", "disagreements with the float64 oracle per scene family"),
}


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in COMMANDS:
        print("usage: python -m hlbvh_warp <command> [options]\n\ncommands:")
        for name, (_, text) in COMMANDS.items():
            print(f"  {name:12s} {text}")
        return 0 if not argv or argv[0] in ("-h", "--help") else 2
    module = importlib.import_module(COMMANDS[argv[0]][0])
    return int(module.main(argv[1:]) or 0)


if __name__ == "__main__":
    sys.exit(main())
