"""The GPU path, on a machine with CUDA: every test here is marked `cuda` and is skipped with the
reason "CUDA not available" elsewhere (tests/conftest.py). benchmarks/gpu_check.sh runs them
(`pytest -m cuda`) on a lent GPU machine: docs/gpu.md.

- the torch backend on CUDA against itself on the CPU, and gsplat against the torch reference
  (a random scene, then a map built from a real Replica keyframe's depth);
- the cpu backend with a map on the GPU (what `rasterizer=auto` falls back to without gsplat);
- a few frames of the whole pipeline with the map on the GPU (torch and gsplat backends) against
  the CPU path (map on the CPU, cpu backend): same trajectory, PSNR within 0.3 dB;
- the mapping step's phases on the GPU (the mapper's own timer, synchronised: benchmarks/step_phases.py),
  and `mode=realtime` mapping on the GPU by default.

The tolerances for gsplat follow from its alpha clamp (0.999, the reference's 0.99: scenes keep
opacities <= 0.95) and its float32 fast-math arithmetic: a pixel where a Gaussian's alpha sits at
the 1/255 cut-off or where the transmittance reaches 1e-4 can differ by a few 1e-2 (the float32
torch backend differs from its float64 self that much at ~0.1% of the pixels of the Replica
keyframe scene), so images are compared by mean, by the share of differing pixels and by PSNR.
"""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from slamkit.geometry.transforms import invert_pose
from slamkit.registry.compose import compose_run
from slamkit.registry.discovery import create_rasterizer, default_registry
from slamkit.run import pipeline
from slamkit.run.build import build_run
from slamkit.types import Camera
from slamkit_plugins.mappers.gaussian_splatting.keyframes import resize_rgbd
from slamkit_plugins.mappers.gaussian_splatting.rasterizer.torch_rasterizer import TorchRasterizer

from support.data import REPLICA, REPO, require_data
from support.render_scenes import F64, a_pose, as_tuple, random_scene, random_weights, weighted_loss

pytestmark = pytest.mark.cuda

_spec = importlib.util.spec_from_file_location(
    "step_phases", REPO / "benchmarks" / "step_phases.py")
step_phases = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(step_phases)


def gsplat_rasterizer():
    """The gsplat backend, or a skip where the package is not installed (a gsplat that is
    installed but whose extension cannot be built fails the test, in one line)."""
    pytest.importorskip("gsplat", reason="gsplat not installed (pip install 'slamkit[cuda]')")
    return create_rasterizer("gsplat")


# -- rasterisers ------------------------------------------------------------------------------


def _gpu_scene():
    cam = Camera(width=96, height=72, fx=80.0, fy=78.0, cx=45.3, cy=37.9)
    # opacities <= 0.95: gsplat clamps alpha at 0.999 and the reference at 0.99
    scene = random_scene(400, seed=21, opacity=(0.05, 0.95), size=(0.02, 0.1), spread=(1.2, 0.9))
    bg = torch.tensor([0.2, 0.3, 0.4], dtype=F64)
    return scene, a_pose(), cam, bg


def _render_with_grads(rast, scene, w2c, cam, bg, device, dtype, weights=None):
    params = [p.to(device=device, dtype=dtype).requires_grad_(True) for p in scene]
    out = as_tuple(rast.render(*params, w2c.to(device=device, dtype=dtype), cam,
                               None if bg is None else bg.to(device=device, dtype=dtype)))
    weights = [w.to(device=device, dtype=dtype) for w in (weights or random_weights(cam))]
    grads = torch.autograd.grad(weighted_loss(out, weights), params)
    return [o.detach().double().cpu() for o in out], [g.double().cpu() for g in grads]


def test_torch_backend_on_cuda_matches_cpu():
    scene, w2c, cam, bg = _gpu_scene()
    rast = TorchRasterizer()
    out_gpu, grads_gpu = _render_with_grads(rast, scene, w2c, cam, bg, "cuda", F64)
    out_cpu, grads_cpu = _render_with_grads(rast, scene, w2c, cam, bg, "cpu", F64)
    for a, b in zip(out_gpu, out_cpu):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-10)
    for a, b in zip(grads_gpu, grads_cpu):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-8 * (1 + b.abs().max().item()))


def test_gsplat_matches_torch_backend():
    rast = gsplat_rasterizer()
    scene, w2c, cam, bg = _gpu_scene()
    out_ref, grads_ref = _render_with_grads(TorchRasterizer(), scene, w2c, cam, bg, "cpu", F64)
    out, grads = _render_with_grads(rast, scene, w2c, cam, bg, "cuda", torch.float32)
    for name, a, b in zip(("color", "depth", "alpha"), out, out_ref):
        assert (a - b).abs().max() < 1e-3, name
    for name, a, b in zip(("means", "quats", "scales", "opacities", "colors"), grads, grads_ref):
        assert (a - b).norm() <= 1e-3 * b.norm(), name


def test_cpu_backend_renders_a_cuda_map():
    """Outputs on the map's device, gradients back to its tensors, the same numbers as with a
    CPU map."""
    scene, w2c, cam, bg = _gpu_scene()
    rast = create_rasterizer("cpu")
    params = [p.float().cuda().requires_grad_(True) for p in scene]
    out = rast.render(*params, w2c.float().cuda(), cam, bg.float().cuda())
    assert all(t.device.type == "cuda" for t in as_tuple(out))
    weights = [w.float().cuda() for w in random_weights(cam)]
    grads = torch.autograd.grad(weighted_loss(as_tuple(out), weights), params)
    assert all(g.device.type == "cuda" and torch.isfinite(g).all() for g in grads)
    ref_out, ref_grads = _render_with_grads(rast, scene, w2c, cam, bg, "cpu", torch.float32)
    for a, b in zip(as_tuple(out), ref_out):
        torch.testing.assert_close(a.detach().double().cpu(), b, rtol=0, atol=1e-6)
    for a, b in zip(grads, ref_grads):
        torch.testing.assert_close(a.double().cpu(), b, rtol=1e-5, atol=1e-6 * (1 + b.abs().max().item()))


def keyframe_scene(replica_path: Path, seed: int = 0):
    """A map built from Replica room0's first frame (its depth and colours, through the run's
    map growth), with opacities spread over [0.3, 0.95] and scales doubled so that Gaussians
    overlap and occlude like a trained map's; its pose (world-to-camera) and the training camera
    (half resolution, 600x340)."""
    dataset, slam, _ = build_run(["dataset=replica", f"dataset.path={replica_path}", "dataset.max_frames=1",
                                  "mapper=none", "mapping_device=cpu", "output.progress=false"])
    frame = dataset[0]
    slam.initialize(frame.gt_pose)
    slam.process(frame)
    gm = slam.gaussian_map
    g = torch.Generator().manual_seed(seed)
    opacities = 0.3 + 0.65 * torch.rand(len(gm), generator=g, dtype=F64)
    scene = (gm.means.detach().double(), gm.quats.detach().double(), 2 * gm.scales.detach().double(), opacities,
             gm.colors.detach().double())
    _, _, camera = resize_rgbd(frame.rgb, frame.depth, frame.camera, 0.5)
    return scene, torch.as_tensor(invert_pose(frame.gt_pose)), camera


def test_gsplat_matches_torch_on_a_replica_keyframe(replica_path):
    rast = gsplat_rasterizer()
    scene, w2c, cam = keyframe_scene(replica_path)
    weights = random_weights(cam, seed=3)
    out_ref, grads_ref = _render_with_grads(TorchRasterizer(), scene, w2c, cam, None, "cuda", F64, weights)
    out, grads = _render_with_grads(rast, scene, w2c, cam, None, "cuda", torch.float32, weights)
    assert out_ref[2].mean() > 0.2, "the keyframe scene should cover the image"
    for name, a, b in zip(("color", "depth", "alpha"), out, out_ref):
        diff = (a - b).abs()
        assert diff.mean() < 1e-4, (name, diff.mean().item())
        assert (diff > 1e-3).double().mean() < 5e-3, (name, (diff > 1e-3).double().mean().item())
        assert diff.max() < 0.2, (name, diff.max().item())
    assert psnr(out[0], out_ref[0]) > 60
    for name, a, b in zip(("means", "quats", "scales", "opacities", "colors"), grads, grads_ref):
        cosine = torch.nn.functional.cosine_similarity(a.flatten(), b.flatten(), dim=0)
        assert cosine > 0.99 and (a - b).norm() < 0.1 * b.norm(), (name, cosine.item())


def psnr(image: torch.Tensor, reference: torch.Tensor) -> float:
    mse = float(((image - reference) ** 2).mean())
    return math.inf if mse == 0 else -10 * math.log10(mse)


# -- the pipeline -----------------------------------------------------------------------------

#: A few Replica frames of sequential GS-ICP SLAM, trained enough that the map's renders and the
#: tracker's targets (rebuilt every second frame, from the trained map) depend on the mapping.
PIPELINE = ["dataset=replica", "dataset.max_frames=6", "mapper=gaussian_splatting", "keyframe=every_n",
            "keyframe.tracking_every=2", "iterations_per_frame=10", "final_iterations=100",
            "mapper.eval_resolution_scale=0.5", "mapper.save_images=0", "output.progress=false", "output.plot=false"]


def run_pipeline(replica_path: Path, out_dir: Path, *overrides: str) -> tuple[dict, np.ndarray]:
    """Metrics and the trajectory (TUM rows: t, tx, ty, tz, qx, qy, qz, qw) of a PIPELINE run."""
    cfg, names = compose_run([*PIPELINE, f"dataset.path={replica_path}", *overrides])
    metrics = pipeline.run(cfg, default_registry(), names, out_dir)
    assert metrics["completed"], metrics.get("error")
    return metrics, np.loadtxt(out_dir / "trajectory.txt")


@pytest.fixture(scope="module")
def cpu_run(replica_path_module, tmp_path_factory):
    """The CPU path: the map on the CPU, the cpu backend."""
    return run_pipeline(replica_path_module, tmp_path_factory.mktemp("cpu_run"), "mapping_device=cpu",
                        "mapper/rasterizer=cpu")


@pytest.fixture(scope="module")
def replica_path_module():
    return require_data(REPLICA)


@pytest.mark.parametrize("backend", ["torch", "gsplat"])
def test_pipeline_on_cuda_matches_the_cpu_path(backend, cpu_run, replica_path_module, tmp_path):
    if backend == "gsplat":
        gsplat_rasterizer()
    metrics, trajectory = run_pipeline(replica_path_module, tmp_path, "mapping_device=cuda",
                                       f"mapper/rasterizer={backend}")
    ref_metrics, ref_trajectory = cpu_run
    assert metrics["mapping_steps"] == ref_metrics["mapping_steps"] > 0
    assert trajectory.shape == ref_trajectory.shape
    np.testing.assert_allclose(trajectory[:, 1:4], ref_trajectory[:, 1:4], rtol=0, atol=5e-4)  # metres
    np.testing.assert_allclose(np.abs(np.sum(trajectory[:, 4:] * ref_trajectory[:, 4:], axis=1)), 1, atol=1e-6)
    assert abs(metrics["ate_rmse_m"] - ref_metrics["ate_rmse_m"]) < 5e-4
    assert abs(metrics["psnr"] - ref_metrics["psnr"]) < 0.3, (metrics["psnr"], ref_metrics["psnr"])


@pytest.mark.parametrize("backend", ["torch", "gsplat"])
def test_mapping_step_phases_on_cuda(backend, replica_path):
    if backend == "gsplat":
        gsplat_rasterizer()
    dataset, slam, _ = build_run(["dataset=replica", f"dataset.path={replica_path}", "dataset.max_frames=3",
                                  "mapper=gaussian_splatting", f"mapper/rasterizer={backend}", "mapping_device=cuda",
                                  "iterations_per_frame=0", "output.progress=false"])
    slam.initialize(dataset[0].gt_pose)
    for i in range(len(dataset)):
        slam.process(dataset[i])
    mapper = step_phases.unwrapped(slam.mapper)
    gm = slam.gaussian_map
    assert gm.means.device.type == "cuda" and len(mapper.keyframes) > 0
    view = mapper.keyframes[mapper.keyframes.ids[-1]].view("cuda")
    losses = []
    for _ in range(6):
        timer = step_phases.time_steps(mapper, 1, torch.cuda.synchronize, view)
        losses.append(mapper.last_loss)
        assert all(timer.wall[phase] > 0 for phase in step_phases.STEP_PHASES), dict(timer.wall)
    assert all(math.isfinite(v) for v in losses) and losses[-1] < losses[0]  # the same view, trained on
    timer = step_phases.time_steps(mapper, 4, torch.cuda.synchronize)  # the mapper's own choice of views
    ms = timer.per_step_ms()
    assert timer.steps == 4 and ms["view"] > 0 and ms["step"] >= sum(ms[p] for p in step_phases.STEP_PHASES)
    assert mapper.steps == 10 and all(torch.isfinite(p).all() for p in gm.parameters().values())
    assert all(p.device.type == "cuda" for p in gm.parameters().values())


def test_realtime_maps_on_the_gpu_by_default(replica_path, tmp_path):
    """mode=realtime with the default mapping_device (auto): the map and the keyframes on the
    GPU, the tracker on the CPU; the run completes and trains."""
    overrides = ["dataset=replica", f"dataset.path={replica_path}", "dataset.max_frames=5",
                 "mapper=gaussian_splatting", "mode=realtime", "realtime.fps_limit=30", "final_iterations=20",
                 "mapper.eval_resolution_scale=0.5", "mapper.save_images=0", "output.progress=false",
                 "output.plot=false"]
    _, slam, _ = build_run(overrides)
    assert slam.gaussian_map.device.type == "cuda"
    cfg, names = compose_run(overrides)
    metrics = pipeline.run(cfg, default_registry(), names, tmp_path)
    assert metrics["completed"] and metrics["mapping_steps"] >= 20 and math.isfinite(metrics["psnr"])
