"""The GPU path's choices, tested on any machine with a fake CUDA and a fake gsplat:
`torch.cuda.is_available` patched to True and a stand-in `gsplat` module in `sys.modules`
(monkeypatched, so neither outlives its test). The fake gsplat computes on the CPU
(`gsplat_rasterizer.DEVICE = "cpu"`).

The three defects of issue 16: a gsplat whose CUDA extension cannot be built is found when the
backend is built (a one-line ConfigError; `rasterizer=auto` falls back to cpu, saying why);
`rasterizer.tile_size` is bounded (tile_size^2 CUDA threads per block); `rasterizer=auto` on a
CUDA machine without gsplat falls back to cpu. And where the map lives (`mapping_device`)."""

from __future__ import annotations

import logging
import sys
import types

import pytest
import torch

import slamkit_plugins.mappers.gaussian_splatting.rasterizer.gsplat_rasterizer as gsplat_module
from slamkit.errors import ConfigError
from slamkit.registry.compose import compose_run
from slamkit.registry.discovery import create_rasterizer
from slamkit.run.build import build_run
from slamkit.types import Camera
from slamkit_plugins.mappers.gaussian_splatting.rasterizer.cpu_rasterizer import CPURasterizer
from slamkit_plugins.mappers.gaussian_splatting.rasterizer.gsplat_rasterizer import GsplatRasterizer

BUILD_ERROR = "Error building extension 'gsplat_cuda'"


def fake_gsplat(calls: list[dict] | None = None, broken: bool = False) -> types.ModuleType:
    """A stand-in for the gsplat package. `rasterization` raises like gsplat 1.5.3 whose CUDA
    extension fails to build at its first call (`broken`), or records its keyword arguments in
    `calls` and returns gsplat's outputs, (1,H,W,4) RGB+D and (1,H,W,1) alpha: flat images of
    the mean colour, depth and opacity, differentiable in every input."""
    module = types.ModuleType("gsplat")

    def rasterization(**kw):
        if broken:
            raise RuntimeError(BUILD_ERROR)
        if calls is not None:
            calls.append(kw)
        zero = sum(kw[k].sum() for k in ("means", "quats", "scales", "opacities", "colors")) * 0
        rgbd = torch.cat([kw["colors"].mean(0), kw["means"][:, 2].mean()[None]]) + zero
        alpha = kw["opacities"].mean()[None] + zero
        shape = (1, kw["height"], kw["width"])
        return rgbd.expand(*shape, 4), alpha.expand(*shape, 1), {}

    module.rasterization = rasterization
    return module


@pytest.fixture
def fake_cuda(monkeypatch):
    """torch says CUDA is there; the gsplat backend computes on the CPU; no probe failure is
    remembered from another test. Returns a function that installs a gsplat module (None: an
    import of gsplat fails)."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(gsplat_module, "DEVICE", "cpu")
    monkeypatch.setattr(gsplat_module, "_probe_failure", None)

    def install(module: types.ModuleType | None) -> None:
        monkeypatch.setitem(sys.modules, "gsplat", module)

    return install


def test_unbuildable_extension_fails_at_construction_in_one_line(fake_cuda):
    fake_cuda(fake_gsplat(broken=True))
    with pytest.raises(ConfigError) as info:
        create_rasterizer("gsplat")
    message = str(info.value)
    assert message == ("rasterizer gsplat: its CUDA extension could not be built or loaded "
                       f"(RuntimeError: {BUILD_ERROR})")
    # remembered: gsplat would retry its whole build at every call
    calls = []
    fake_cuda(fake_gsplat(calls))
    with pytest.raises(ConfigError, match="could not be built"):
        create_rasterizer("gsplat")
    assert calls == []


def test_auto_falls_back_to_cpu_when_the_extension_cannot_be_built(fake_cuda, caplog):
    fake_cuda(fake_gsplat(broken=True))
    with caplog.at_level(logging.INFO, logger="slamkit_plugins.mappers.gaussian_splatting.rasterizer.auto"):
        auto = create_rasterizer("auto")
    assert auto.name == "cpu" and isinstance(auto.backend, CPURasterizer)
    skipped = [r for r in caplog.records if "not using gsplat" in r.getMessage()]
    assert len(skipped) == 1 and skipped[0].levelno == logging.WARNING  # a GPU left unused: shown
    assert BUILD_ERROR in skipped[0].getMessage()
    assert any(r.getMessage() == "rasterizer auto: using cpu" for r in caplog.records)


def test_auto_falls_back_to_cpu_on_a_cuda_machine_without_gsplat(fake_cuda, caplog):
    fake_cuda(None)  # `import gsplat` raises ImportError
    with caplog.at_level(logging.INFO, logger="slamkit_plugins.mappers.gaussian_splatting.rasterizer.auto"):
        auto = create_rasterizer("auto")
    assert auto.name == "cpu"
    (skipped,) = [r.getMessage() for r in caplog.records if "not using gsplat" in r.getMessage()]
    assert "needs CUDA and the gsplat package (pip install 'slamkit[cuda]')" in skipped
    assert "ImportError" in skipped or "ModuleNotFoundError" in skipped
    with pytest.raises(ConfigError, match=r"^mapper/rasterizer=gsplat needs CUDA and the gsplat package .*Error"):
        create_rasterizer("gsplat")


def test_without_cuda_auto_skips_gsplat_quietly(monkeypatch, caplog):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with caplog.at_level(logging.INFO, logger="slamkit_plugins.mappers.gaussian_splatting.rasterizer.auto"):
        assert create_rasterizer("auto").name == "cpu"
    assert [r.levelno for r in caplog.records if "not using gsplat" in r.getMessage()] == [logging.INFO]


def test_probe_renders_one_gaussian_through_gsplat(fake_cuda):
    calls = []
    fake_cuda(fake_gsplat(calls))
    rast = create_rasterizer("gsplat")
    assert isinstance(rast, GsplatRasterizer) and len(calls) == 1
    assert calls[0]["width"] == calls[0]["height"] == 8 and calls[0]["means"].shape == (1, 3)


def test_run_config_reaches_gsplat_as_documented(fake_cuda):
    """`rasterizer=gsplat rasterizer.tile_size=8` through the run's composition: gsplat gets
    tile_size 8, the principal point shifted by +0.5 px, RGB+D, classic mode, near plane 0.01 m,
    eps2d 0.3, the world-to-camera matrix; a few frames of mapping run through it."""
    calls = []
    fake_cuda(fake_gsplat(calls))
    dataset, slam, _ = build_run(["dataset.max_frames=2", "mapper=gaussian_splatting", "mapper/rasterizer=gsplat",
                                  "mapper.rasterizer.tile_size=8", "mapping_device=cpu", "iterations_per_frame=2"])
    rasterizer = slam.mapper.rasterizer
    assert isinstance(rasterizer, GsplatRasterizer) and rasterizer.cfg.tile_size == 8
    assert len(calls) == 1  # the probe, at construction
    slam.initialize(dataset[0].gt_pose)
    for i in range(len(dataset)):
        slam.process(dataset[i])
    assert slam.mapper.steps > 0 and len(calls) > 1
    kw = calls[-1]
    cam = slam.mapper.keyframes.training_camera(dataset.camera)
    expected_K = torch.tensor([[cam.fx, 0, cam.cx + 0.5], [0, cam.fy, cam.cy + 0.5], [0, 0, 1]])
    torch.testing.assert_close(kw["Ks"], expected_K[None])
    assert (kw["width"], kw["height"]) == (cam.width, cam.height)
    assert kw["tile_size"] == 8 and kw["render_mode"] == "RGB+D" and kw["rasterize_mode"] == "classic"
    assert kw["near_plane"] == 0.01 and kw["eps2d"] == 0.3 and kw["packed"] is False
    assert kw["viewmats"].shape == (1, 4, 4) and kw["viewmats"].dtype == torch.float32
    assert all(kw[k].dtype == torch.float32 for k in ("means", "quats", "scales", "opacities", "colors"))
    assert len(kw["means"]) == len(slam.gaussian_map)


def test_render_returns_the_inputs_dtype_and_passes_the_background(fake_cuda):
    calls = []
    fake_cuda(fake_gsplat(calls))
    rast = GsplatRasterizer()
    means = torch.tensor([[0.1, 0.0, 2.0], [0.0, 0.2, 3.0]], dtype=torch.float64, requires_grad=True)
    quats = torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=torch.float64)
    out = rast.render(means, quats, torch.full((2, 3), 0.1, dtype=torch.float64), torch.tensor([0.5, 0.7]).double(),
                      torch.rand(2, 3, dtype=torch.float64), torch.eye(4, dtype=torch.float64),
                      Camera(6, 4, 5.0, 5.0, 2.5, 1.5),
                      background=torch.tensor([0.1, 0.2, 0.3]))
    assert out.color.shape == (4, 6, 3) and out.depth.shape == out.alpha.shape == (4, 6)
    assert all(t.dtype == torch.float64 for t in (out.color, out.depth, out.alpha))
    assert out.depth[0, 0].item() == pytest.approx(2.5)
    torch.testing.assert_close(calls[-1]["backgrounds"], torch.tensor([[0.1, 0.2, 0.3]]))
    (grad,) = torch.autograd.grad(out.depth.sum(), [means])
    assert grad.dtype == torch.float64 and grad[:, 2].abs().sum() > 0


@pytest.mark.parametrize("tile_size", [0, 33, 64])
def test_tile_size_is_bounded(tile_size):
    with pytest.raises(ConfigError, match=r"mapper.rasterizer.tile_size: expected an integer in \[1, 32\]"):
        compose_run(["mapper=gaussian_splatting", "mapper/rasterizer=gsplat",
                     f"mapper.rasterizer.tile_size={tile_size}"])
    compose_run(["mapper=gaussian_splatting", "mapper/rasterizer=gsplat", "mapper.rasterizer.tile_size=32"])


def test_tile_size_64_is_a_one_line_error_of_the_command(monkeypatch, capsys, tmp_path):
    from slamkit.cli.main import main

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["slamkit", "mapper=gaussian_splatting", "mapper/rasterizer=gsplat",
                                      "mapper.rasterizer.tile_size=64"])
    with pytest.raises(SystemExit) as info:
        main()
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("slamkit: error: mapper.rasterizer.tile_size: expected an integer in [1, 32]")
    assert "64" in err[-1] and "Traceback" not in "\n".join(err)
    assert not (tmp_path / "outputs").exists()  # nothing ran


def test_mapping_device_auto_follows_cuda(monkeypatch):
    run, _ = compose_run([])
    assert run.mapping_device.value == "auto"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert run.device() == "cpu"
    with pytest.raises(ConfigError, match="mapping_device: expected cpu or auto on a machine without CUDA, got 'cuda'"):
        compose_run(["mapping_device=cuda"])[0].device()
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert run.device() == "cuda"  # the default on a GPU machine, in realtime mode as in sequential
    assert compose_run(["mode=realtime"])[0].device() == "cuda"
    assert compose_run(["mode=realtime", "mapping_device=cpu"])[0].device() == "cpu"

