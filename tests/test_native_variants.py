"""The compiled kernels' vector code has one variant per instruction set (slamkit/csrc/slk_vec16.h:
AVX-512 registers, or pairs of AVX2 / portable vectors); a machine runs only the variant its CPU
selects, so the others are at least compiled here, with the flags slamkit builds with."""

from __future__ import annotations

import shutil
import subprocess

import pytest

from slamkit.native import BASE_FLAGS, INCLUDE_DIR
from slamkit_plugins.losses.fused_rgbd_loss import SOURCE as LOSS_SOURCE
from slamkit_plugins.rasterizers.cpu_rasterizer import SOURCE as RASTERIZER_SOURCE

COMPILER = shutil.which("c++")
X86 = COMPILER is not None and "x86_64" in subprocess.run([COMPILER, "-dumpmachine"], capture_output=True,
                                                           text=True).stdout

# target flags -> the variant they select (the portable build has neither AVX nor FMA)
VARIANTS = {"avx512": ["-mavx512f"], "avx2": ["-mavx2", "-mfma"], "avx": ["-mavx"], "portable": []}


@pytest.mark.skipif(not X86, reason="needs an x86-64 C++ compiler")
@pytest.mark.parametrize("variant", sorted(VARIANTS))
@pytest.mark.parametrize("source", [RASTERIZER_SOURCE, LOSS_SOURCE], ids=lambda p: p.stem)
def test_every_vector_variant_compiles(tmp_path, source, variant):
    out = tmp_path / "lib.so"
    proc = subprocess.run([COMPILER, *BASE_FLAGS, *VARIANTS[variant], f"-I{INCLUDE_DIR}", str(source), "-o", str(out)],
                          capture_output=True, text=True, timeout=600)
    errors = [line for line in proc.stderr.splitlines() if "error" in line]
    assert proc.returncode == 0 and out.exists(), errors[:5]
