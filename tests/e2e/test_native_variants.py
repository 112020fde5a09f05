"""The compiled kernels' vector code has one variant per instruction set (slamkit/csrc/slk_vec16.h:
AVX-512 registers, or pairs of AVX2 / portable vectors); a machine runs only the variant its CPU
selects, so every variant is compiled here with the flags slamkit builds with, and those this CPU
can run are checked lane by lane (tests/e2e/vec16_probe.cpp)."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from slamkit.native import BASE_FLAGS, INCLUDE_DIR, NativeLibrary
from slamkit_plugins.mappers.gaussian_splatting.loss.fused_rgbd_loss import SOURCE as LOSS_SOURCE
from slamkit_plugins.mappers.gaussian_splatting.rasterizer.cpu_rasterizer import SOURCE as RASTERIZER_SOURCE

PROBE = Path(__file__).resolve().parent / "vec16_probe.cpp"
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


def _cpu_flags() -> set[str]:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return set()
    line = next((ln for ln in text.splitlines() if ln.startswith("flags")), "")
    return set(line.split(":", 1)[-1].split())


CPU_NEEDS = {"avx512": {"avx512f"}, "avx2": {"avx2", "fma"}, "avx": {"avx"}, "portable": set()}


def _probe(tmp_path, variant: str) -> dict[str, np.ndarray]:
    """tests/e2e/vec16_probe.cpp built for `variant` and run: its lines as arrays."""
    exe = tmp_path / f"probe_{variant}"
    flags = [f for f in BASE_FLAGS if f not in ("-shared", "-fPIC")]
    proc = subprocess.run([COMPILER, *flags, *VARIANTS[variant], f"-I{INCLUDE_DIR}", str(PROBE), "-o", str(exe)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = subprocess.run([str(exe)], capture_output=True, text=True, timeout=60, check=True).stdout
    return {name: np.array([float.fromhex(x) for x in values.split()]) for name, values in
            (line.split(":", 1) for line in out.splitlines())}  # %a: exact


@pytest.mark.skipif(not X86, reason="needs an x86-64 C++ compiler")
@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_every_vector_variant_this_cpu_runs_computes_lane_by_lane(tmp_path, variant):
    """Each operation of slk_vec16.h, in every variant this CPU can run, against numpy: lane
    order (halves, widen / narrow, 8-lane loads and stores), masks (lane_bits, selects of whole
    vectors and of blocks), conversions, and the fixed order of the double sum."""
    if not CPU_NEEDS[variant] <= _cpu_flags():
        pytest.skip(f"this CPU lacks {sorted(CPU_NEEDS[variant])}")
    got = _probe(tmp_path, variant)
    f32 = np.float32
    i = np.arange(16)
    a = np.array([f32(0.37) * f32(k - 7) + f32(0.011) * f32(k * k) for k in i], dtype=f32)
    b = np.array([f32(1.5) + f32(0.25) * f32((k * 5) % 16) for k in i], dtype=f32)
    d = np.array([1e8 * (1.0 if k % 2 else -1.0) + 0.1 * k for k in range(8)])
    exact = {
        "a": a, "b": b, "lane": i, "add": a + b, "sub_scalar": f32(2) - a, "mul": a * b, "div_scalar": a / f32(3),
        "neg": -a, "lt": -(a < b).astype(int), "ge_scalar": -(a >= 0).astype(int), "select": np.where(a < 0, b, a),
        "to_vi": np.trunc(a * f32(4)), "to_vf": 3 * i - 20, "bits": a.view(np.int32) & 0x7FFFFFFF,
        "shift": (i + 1) << 3, "sqrt": np.sqrt(b), "any_none": [0], "any_one": [1], "all_but_one": [0], "all": [1],
        "widen_lo": a[:8].astype(float), "widen_hi": a[8:].astype(float), "narrow": np.concatenate([a[8:], a[:8]]),
        "ld8": a[4:12].astype(float), "st8": np.concatenate([[0, 0, 0], (d * 1e-8).astype(f32), [0] * 5]),
        "dsum": [((d[0] + d[4]) + (d[1] + d[5])) + ((d[2] + d[6]) + (d[3] + d[7]))],
        "blocks": a * f32(2) + (i if variant == "avx512" else i % 8).astype(f32),
        "lane_bits": [1 + 2**9 + 2**15], "block_select": np.where(a < 0, b, a),
        "block_select_int": np.where(a < 0, 2 * i, i),
    }
    for name, want in exact.items():
        np.testing.assert_array_equal(got[name], np.asarray(want, dtype=float), err_msg=name)
    # fused or not, and summed in a variant's own order: within rounding
    np.testing.assert_allclose(got["fma"], a.astype(float) * b + 0.5, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(got["hsum"], [a.astype(float).sum()], rtol=1e-6)


@pytest.mark.skipif(COMPILER is None, reason="needs a C++ compiler")
def test_a_changed_header_beside_the_source_rebuilds(monkeypatch, tmp_path):
    """A library split into headers beside its source (the rasteriser's parts) is rebuilt when
    one of them changes, not loaded stale from the cache."""
    monkeypatch.setenv("SLAMKIT_CACHE", str(tmp_path / "cache"))
    source = tmp_path / "kernel.cpp"
    source.write_text('#include "part.h"\nextern "C" int slk_abi_version() { return PART; }\n')

    def build(part: int):
        (tmp_path / "part.h").write_text(f"#pragma once\n#define PART {part}\n")
        library = NativeLibrary(source, "test kernel", part, lambda lib: None, native=False)
        assert library.get() is not None, library.error
        return library.path

    first, second = build(1), build(2)
    assert first != second and first.exists() and second.exists()


CLANG = shutil.which("clang++")


def _is_clang(compiler: str | None) -> bool:
    if compiler is None or shutil.which(compiler) is None:
        return False
    version = subprocess.run([compiler, "--version"], capture_output=True, text=True).stdout
    return "clang" in version.lower()


@pytest.mark.skipif(CLANG is None, reason="clang++ is not installed (make setup-test installs it)")
@pytest.mark.skipif(_is_clang(os.environ.get("CXX", "c++")), reason="the default build is Clang's already")
def test_clang_builds_every_kernel_and_computes_what_the_default_build_does(monkeypatch, tmp_path):
    """The kernels are plain C++17 for GCC or Clang (macOS has only Clang): every one builds
    with clang++ (-march=native), and the rasteriser's and the fused loss's results (values and
    gradients) are those of the default compiler's (GCC's) builds."""
    import slamkit_plugins.mappers.gaussian_splatting.loss.fused_rgbd_loss as loss_module
    import slamkit_plugins.mappers.gaussian_splatting.optimizer.visible_adam as adam_module
    import slamkit_plugins.mappers.gaussian_splatting.rasterizer.cpu_rasterizer as raster_module
    import slamkit_plugins.trackers.gicp.kernels as gicp_module

    from support.hard_scenes import CAM, hard_scene, rel_err, render_and_grads
    from support.loss_inputs import loss_and_grads, random_inputs

    scene, background = hard_scene(300, seed=5), torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    loss_inputs = random_inputs(40, 52, seed=3)
    default_render = render_and_grads(raster_module.CPURasterizer(), scene, CAM, background, torch.float32)
    default_loss = loss_and_grads(loss_module.fused_rgbd_loss, loss_inputs)

    monkeypatch.setenv("CXX", CLANG)
    monkeypatch.setenv("SLAMKIT_CACHE", str(tmp_path))
    libraries = {module.__name__: module.new_library()
                 for module in (raster_module, loss_module, gicp_module, adam_module)}
    for name, library in libraries.items():
        assert library.get() is not None, f"{name}: {library.error}"
        assert "-march=native" in library.built_flags and library.path.parent.parent == tmp_path, name

    monkeypatch.setattr(raster_module, "get_library", lambda native=True: libraries[raster_module.__name__])
    clang_rasterizer = raster_module.CPURasterizer()
    assert clang_rasterizer.library.path.parent.parent == tmp_path  # the clang build renders
    clang_render = render_and_grads(clang_rasterizer, scene, CAM, background, torch.float32)
    for clang, default in zip(clang_render, default_render):
        assert rel_err(clang, default) < 1e-6
    monkeypatch.setattr(loss_module, "LIBRARY", libraries[loss_module.__name__])
    for clang, default in zip(loss_and_grads(loss_module.fused_rgbd_loss, loss_inputs), default_loss):
        assert rel_err(clang, default) < 1e-6
