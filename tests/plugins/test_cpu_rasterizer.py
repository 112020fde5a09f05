"""The compiled CPU rasteriser (`rasterizer=cpu`) against the `torch` reference backend:
images and every gradient on hard random scenes, exact pair selection, determinism across
thread counts, edge cases, plugin registration, and the build / fallback behaviour."""

from __future__ import annotations

import math
import os
import shutil
import threading

import pytest
import torch

import slamkit_plugins.mappers.gaussian_splatting.rasterizer.cpu_rasterizer as cpu_module
from slamkit.errors import ConfigError
from slamkit.registry.discovery import create_rasterizer
from slamkit.types import Camera
from slamkit_plugins.mappers.gaussian_splatting.rasterizer.cpu_rasterizer import CPURasterizer, CPURasterizerConfig
from slamkit_plugins.mappers.gaussian_splatting.rasterizer.torch_rasterizer import TorchRasterizer

from support.hard_scenes import CAM, hard_scene, rel_err, render_and_grads

F32, F64 = torch.float32, torch.float64
NAMES = ("color", "depth", "alpha", "means", "quats", "scales", "opacities", "colors", "background")
TOL = 1e-4  # relative error (Frobenius norm of the difference / norm of the reference)


@pytest.fixture
def cpu() -> CPURasterizer:
    try:
        return CPURasterizer()  # built once per process (in the session's SLAMKIT_CACHE)
    except ConfigError as exc:
        if shutil.which(os.environ.get("CXX", "c++")):  # a compiler is there: a failed build is a bug
            pytest.fail(f"cpu rasteriser failed to build: {exc}")
        pytest.skip(f"no C++ compiler on this machine ({exc}); the auto fallback is tested separately")


def errors(out, ref) -> dict[str, float]:
    return {name: rel_err(a, b) for name, a, b in zip(NAMES, out, ref)}


# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed,n,anisotropy", [(0, 400, 1.0), (1, 700, 1.0), (2, 500, 2.0)])
def test_matches_torch_backend_on_hard_scenes(cpu, seed, n, anisotropy):
    """Colour, depth, alpha and the gradients w.r.t. means, quats, scales, opacities and
    colours agree with the torch backend in float32 (and both with its float64 result)."""
    scene = hard_scene(n, seed, anisotropy=anisotropy)
    background = torch.tensor([0.2, 0.5, 0.1], dtype=F64)
    ours = render_and_grads(cpu, scene, CAM, background, F32)
    ref32 = render_and_grads(TorchRasterizer(), scene, CAM, background, F32)
    ref64 = render_and_grads(TorchRasterizer(), scene, CAM, background, F64)
    vs32, vs64 = errors(ours, ref32), errors(ours, ref64)
    assert cpu.last_num_pairs > 10_000  # the scene is not trivially empty
    for name in NAMES[:-1]:
        assert vs32[name] < TOL, (name, vs32)
        assert vs64[name] < TOL, (name, vs64)
    # d colour / d background = the final transmittance: where most pixels are saturated it is a
    # small sum that one transmittance cut-off decided differently (T ~ 1e-4) moves by ~1e-4
    # relative; the float32 reference is itself ~2e-4 off its float64 result on these scenes
    assert vs64["background"] < 1e-3, vs64


def test_same_pixel_gaussian_pairs_as_the_torch_backend(cpu):
    """The covered pixels of each Gaussian are the torch backend's, to the pair: the row
    intervals are computed with the same float32 operations."""
    for seed in range(3):
        scene = hard_scene(600, 10 + seed)
        means, quats, scales, opacities, colors, w2c = (x.to(F32) for x in scene)
        reference = TorchRasterizer()
        with torch.no_grad():
            cpu.render(means, quats, scales, opacities, colors, w2c, CAM)
            reference.render(means, quats, scales, opacities, colors, w2c, CAM)
        # the projection is computed in float64 here and in float32 there: a pair right on an
        # ellipse's edge (alpha = 1/255) may differ, very rarely
        assert abs(cpu.last_num_pairs - reference.last_num_pairs) <= 2, (cpu.last_num_pairs, reference.last_num_pairs)


def test_gaussians_around_the_image_border_are_kept_exactly_when_they_cover_a_pixel(cpu):
    """The cheap off-screen cull before the projection drops only Gaussians that cover no
    pixel: centres scattered within a few extents outside the border, elongated and turned
    every way, render the torch backend's pairs and image."""
    g = torch.Generator().manual_seed(5)
    n = 800
    z = 0.5 + 2.5 * torch.rand(n, generator=g, dtype=F64)
    scales = torch.exp(math.log(0.002) + math.log(40.0) * torch.rand(n, 3, generator=g, dtype=F64))
    extent_px = 3.0 * scales.max(1).values * CAM.fx / z  # ~3 sigma in pixels
    side = torch.randint(0, 4, (n,), generator=g)
    along = torch.rand(n, generator=g, dtype=F64)
    out = extent_px * (2.0 * torch.rand(n, generator=g, dtype=F64) - 0.5)  # -0.5 .. 1.5 extents outside
    u = torch.where(side == 0, -out, torch.where(side == 1, CAM.width - 1 + out, along * CAM.width))
    v = torch.where(side == 2, -out, torch.where(side == 3, CAM.height - 1 + out, along * CAM.height))
    pc = torch.stack([(u - CAM.cx) / CAM.fx * z, (v - CAM.cy) / CAM.fy * z, z], -1)
    quats = torch.randn(n, 4, generator=g, dtype=F64)
    opacities = 0.02 + 0.97 * torch.rand(n, generator=g, dtype=F64)
    colors = torch.rand(n, 3, generator=g, dtype=F64)
    w2c = torch.eye(4, dtype=F64)
    args = [x.to(F32) for x in (pc, quats, scales, opacities, colors, w2c)]
    reference = TorchRasterizer()
    with torch.no_grad():
        ours = cpu.render(*args, CAM)
        ref = reference.render(*args, CAM)
    assert reference.last_num_pairs > 1000  # many of them reach into the image
    assert abs(cpu.last_num_pairs - reference.last_num_pairs) <= 2, (cpu.last_num_pairs, reference.last_num_pairs)
    assert rel_err(ours.color.double(), ref.color.double()) < TOL


def test_deterministic_across_thread_counts(cpu):
    scene = hard_scene(700, 3)
    background = torch.tensor([0.3, 0.3, 0.3], dtype=F64)
    runs = [render_and_grads(CPURasterizer(CPURasterizerConfig(num_threads=k)), scene, CAM, background, F32)
            for k in (1, 2, 5)]
    for other in runs[1:]:
        for name, a, b in zip(NAMES, runs[0], other):
            assert torch.equal(a, b), name


@pytest.mark.parametrize("stored", ["none", "some"])
def test_backward_is_the_same_with_the_alphas_recomputed(cpu, stored):
    """The forward keeps its alphas for the backward up to `stored_alphas_mb` (the default holds
    them all here); the backward recomputes the rest: none kept (0 MiB), or some kept and some
    not (the smallest budget that keeps part of them on this CPU: the unit a budget counts in
    follows the vector width, 8 or 16 lanes)."""
    scene = hard_scene(700, 5)
    background = torch.tensor([0.2, 0.5, 0.1], dtype=F64)
    reference = render_and_grads(cpu, scene, CAM, background, F32)
    assert cpu.last_num_rows_stored == cpu.last_num_rows > 0
    for budget_mb in [0.0] if stored == "none" else [0.01, 0.02, 0.05, 0.1, 0.2]:
        budget = CPURasterizer(CPURasterizerConfig(num_threads=1, stored_alphas_mb=budget_mb))
        other = render_and_grads(budget, scene, CAM, background, F32)
        if stored == "none" or 0 < budget.last_num_rows_stored:
            break
    if stored == "none":
        assert budget.last_num_rows_stored == 0
    else:
        assert 0 < budget.last_num_rows_stored < budget.last_num_rows
    for name, a, b in zip(NAMES, reference, other):
        assert torch.equal(a, b), name


def test_a_render_without_gradients_keeps_no_alphas(cpu):
    scene = hard_scene(300, 6)
    with torch.no_grad():
        cpu.render(*[x.float() for x in scene], CAM, torch.zeros(3))
    assert cpu.last_num_rows > 0 and cpu.last_num_rows_stored == 0


def test_concurrent_renders_from_threads(cpu):
    """The compiled code runs without the GIL; each render owns its state (the buffers of stored
    alphas it takes from a shared pool included)."""
    scene = hard_scene(500, 4)
    background = torch.tensor([0.3, 0.3, 0.3], dtype=F64)
    expected = render_and_grads(cpu, scene, CAM, background, F32)
    results = [None] * 4

    def work(i):
        results[i] = render_and_grads(CPURasterizer(CPURasterizerConfig(num_threads=2)), scene, CAM, background, F32)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for result in results:
        for name, a, b in zip(NAMES, expected, result):
            assert torch.equal(a, b), name


def test_empty_culled_and_offscreen_scenes_are_background(cpu):
    background = torch.tensor([0.1, 0.2, 0.3])
    empty = [torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 3)]
    behind = [torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 0.005]]), torch.tensor([[1.0, 0, 0, 0]] * 2),
              torch.full((2, 3), 0.1), torch.tensor([0.9, 0.9]), torch.rand(2, 3)]
    offscreen = [torch.tensor([[50.0, 0.0, 1.0], [0.0, 0.0, 2.0]]), torch.tensor([[1.0, 0, 0, 0]] * 2),
                 torch.full((2, 3), 0.01), torch.tensor([0.9, 0.003]), torch.rand(2, 3)]  # the 2nd: opacity < 1/255
    for params in (empty, behind, offscreen):
        leaves = [p.clone().requires_grad_(True) for p in params]
        out = cpu.render(*leaves, torch.eye(4), CAM, background)
        assert torch.equal(out.color, background.expand(CAM.height, CAM.width, 3))
        assert not out.depth.any() and not out.alpha.any()
        (out.color.sum() + out.depth.sum() + out.alpha.sum()).backward()
        assert all(not leaf.grad.any() for leaf in leaves)
        assert cpu.last_num_pairs == 0


def test_float64_inputs_and_output_dtype(cpu):
    means, quats, scales, opacities, colors, w2c = hard_scene(300, 5)
    leaves = [x.clone().requires_grad_(True) for x in (means, quats, scales, opacities, colors)]
    out = cpu.render(*leaves, w2c, CAM)
    assert out.color.dtype == out.depth.dtype == out.alpha.dtype == F64
    (out.color.sum() + out.depth.sum()).backward()
    assert all(leaf.grad is not None and leaf.grad.dtype == F64 for leaf in leaves)
    with torch.no_grad():  # forward only: no state is kept
        again = cpu.render(*[x.to(F32) for x in (means, quats, scales, opacities, colors)], w2c, CAM)
    assert torch.equal(again.color, out.color.detach().to(F32))


def test_shapes_and_devices_are_checked(cpu):
    means, quats, scales, opacities, colors, w2c = (x.to(F32) for x in hard_scene(10, 6))
    with pytest.raises(ValueError, match="quats"):
        cpu.render(means, quats[:, :3], scales, opacities, colors, w2c, CAM)
    with pytest.raises(ValueError, match="colors"):
        cpu.render(means, quats, scales, opacities, colors[:5], w2c, CAM)
    out = cpu.render(means, quats, scales, opacities[:, None], colors, w2c, CAM)  # (N, 1) opacities are fine
    assert out.color.shape == (CAM.height, CAM.width, 3)


def test_config_is_validated():
    with pytest.raises(ConfigError, match="num_threads"):
        CPURasterizerConfig(num_threads=-1)
    with pytest.raises(ConfigError, match="stored_alphas_mb"):
        CPURasterizerConfig(stored_alphas_mb=-1.0)


def test_registered_as_cpu_and_picked_by_auto_without_cuda(monkeypatch, cpu):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert isinstance(create_rasterizer("cpu"), CPURasterizer)
    auto = create_rasterizer("auto")
    assert auto.name == "cpu" and isinstance(auto.backend, CPURasterizer)


def _fresh_library(monkeypatch):
    """Every CPURasterizer gets a library not built yet (so that it builds under the test's $CXX)."""
    monkeypatch.setattr(cpu_module, "get_library", cpu_module.new_library)


def test_without_a_compiler_cpu_is_a_one_line_error_and_auto_renders_with_torch(monkeypatch, caplog):
    _fresh_library(monkeypatch)
    monkeypatch.setenv("CXX", "no-such-compiler-slamkit")
    with pytest.raises(ConfigError, match="rasterizer cpu: .*no C\\+\\+ compiler found") as err:
        CPURasterizer()
    assert "\n" not in str(err.value)
    with caplog.at_level("INFO"):
        auto = create_rasterizer("auto")
    assert auto.name == "torch" and "not using cpu" in caplog.text
    means, quats, scales, opacities, colors, w2c = (x.to(F32) for x in hard_scene(200, 7))
    out = auto.render(means, quats, scales, opacities, colors, w2c, CAM)
    expected = TorchRasterizer().render(means, quats, scales, opacities, colors, w2c, CAM)
    assert torch.equal(out.color, expected.color) and torch.equal(out.depth, expected.depth)


def test_a_failing_build_is_an_error_naming_the_compiler_message(monkeypatch, tmp_path):
    _fresh_library(monkeypatch)
    monkeypatch.setenv("SLAMKIT_CACHE", str(tmp_path))
    broken = tmp_path / "broken.cpp"
    broken.write_text("this is not C++\n")
    monkeypatch.setattr(cpu_module, "SOURCE", broken)
    with pytest.raises(ConfigError, match="compiling broken.cpp failed"):
        CPURasterizer()
    assert not list((tmp_path / "extensions").glob("*.so"))  # nothing half-built is left behind


def test_first_use_compiles_into_the_project_cache_and_says_so(monkeypatch, tmp_path, capfd):
    _fresh_library(monkeypatch)
    monkeypatch.setenv("SLAMKIT_CACHE", str(tmp_path))
    CPURasterizer(CPURasterizerConfig(native=False))
    err = capfd.readouterr().err
    assert "slamkit: compiling the CPU rasteriser (first use" in err
    built = list((tmp_path / "extensions").glob("slamkit_cpu_rasterizer_*.so"))
    assert len(built) == 1
    _fresh_library(monkeypatch)  # a new process: loads the cached build, silently
    CPURasterizer(CPURasterizerConfig(native=False))
    assert "compiling" not in capfd.readouterr().err


def test_native_chooses_whether_the_library_is_built_for_this_cpu(monkeypatch, tmp_path):
    """`rasterizer.native=false` loads a portable build (no -march=native), through the CLI's
    composition."""
    from slamkit.run.build import build_run

    _fresh_library(monkeypatch)
    monkeypatch.setenv("SLAMKIT_CACHE", str(tmp_path))
    portable = build_run(["mapper=gaussian_splatting", "mapper/rasterizer=cpu",
                          "mapper.rasterizer.native=false"])[1].mapper.rasterizer
    native = build_run(["mapper=gaussian_splatting", "mapper/rasterizer=cpu"])[1].mapper.rasterizer
    assert "-march=native" not in portable.library.built_flags
    assert "-march=native" in native.library.built_flags
    assert portable.library.path != native.library.path
    means, quats, scales, opacities, colors, w2c = (x.to(F32) for x in hard_scene(300, 4))
    a = portable.render(means, quats, scales, opacities, colors, w2c, CAM)
    b = native.render(means, quats, scales, opacities, colors, w2c, CAM)
    torch.testing.assert_close(a.color, b.color, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("threads", [1, 2])
def test_num_threads_is_how_many_threads_render(cpu, threads):
    """A large render (640x480, 20k Gaussians) composited by exactly `rasterizer.num_threads`
    threads."""
    from slamkit.run.build import build_run

    rasterizer = build_run(["mapper=gaussian_splatting", "mapper/rasterizer=cpu",
                            f"mapper.rasterizer.num_threads={threads}"])[1].mapper.rasterizer
    assert rasterizer.cfg.num_threads == threads
    big = Camera(640, 480, 500.0, 500.0, 319.5, 239.5)
    means, quats, scales, opacities, colors, w2c = (x.to(F32) for x in hard_scene(20_000, 5, big))
    rasterizer.render(means, quats, scales, opacities, colors, w2c, big)
    assert rasterizer.last_num_threads == threads
