"""Build (or load) gsplat's CUDA extension once, by building the `gsplat` rasteriser (its probe
renders one Gaussian), and say how long it took. Run by benchmarks/gpu_check.sh.

gsplat 1.5.3 compiles its extension with torch's JIT into $TORCH_EXTENSIONS_DIR/gsplat_cuda at
its first call, and a later process loads it from there in seconds. Before a build from scratch
gsplat deletes that folder; here that deletion is skipped, so that a build cut off by a time
limit leaves its compiled objects and the next run's ninja compiles only the rest.
"""

from __future__ import annotations

import os
import shutil
import sys
import time

BUILD_DIR_NAME = "gsplat_cuda"


def keep_partial_builds() -> None:
    """Make shutil.rmtree leave gsplat's build folder alone (this process only)."""
    remove = shutil.rmtree

    def rmtree(path, *args, **kwargs):
        if os.path.basename(os.path.normpath(str(path))) == BUILD_DIR_NAME:
            print(f"build_gsplat: keeping {path} (objects of an earlier, cut-off build are reused)", flush=True)
            return None
        return remove(path, *args, **kwargs)

    shutil.rmtree = rmtree


def main() -> int:
    from slamkit.errors import ConfigError
    from slamkit.registry.discovery import create_rasterizer

    folder = os.environ.get("TORCH_EXTENSIONS_DIR", "(torch's default)")
    print(f"build_gsplat: building or loading gsplat's CUDA extension in {folder}", flush=True)
    keep_partial_builds()
    start = time.perf_counter()
    try:
        create_rasterizer("gsplat")
    except ConfigError as exc:
        print(f"build_gsplat: FAILED after {time.perf_counter() - start:.1f} s: {exc}", flush=True)
        return 1
    print(f"build_gsplat: gsplat extension ready in {time.perf_counter() - start:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
