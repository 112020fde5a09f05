"""Rasteriser backends: the torch reference against analytic images, a dense brute-force
renderer, finite differences and occlusion; backend selection. On CUDA (gsplat against torch,
the torch backend on the GPU): tests/e2e/test_cuda.py."""

from __future__ import annotations

import math

import pytest
import torch

import slamkit_plugins.mappers.gaussian_splatting.rasterizer.gsplat_rasterizer as gsplat_module
import slamkit_plugins.mappers.gaussian_splatting.rasterizer.torch_rasterizer as torch_module
from slamkit.errors import ConfigError
from slamkit.geometry.transforms import covariance_from_scales
from slamkit.registry.discovery import Registry, create_rasterizer
from slamkit.types import Camera
from slamkit_plugins.mappers.gaussian_splatting.rasterizer.torch_rasterizer import (
    TorchRasterizer,
    TorchRasterizerConfig,
)

from support.render_scenes import F64, a_pose, as_tuple, random_scene, random_weights, weighted_loss


def brute_force_render(means, quats, scales, opacities, colors, w2c, cam, background):
    """Every pixel against every Gaussian, composited in a Python loop over depth order, with
    plain autograd: the conventions of `slamkit.roles.rendering` written as directly as possible."""
    R, t = w2c[:3, :3], w2c[:3, 3]
    x, y, z = (means @ R.T + t).unbind(-1)
    u, v = cam.fx * x / z + cam.cx, cam.fy * y / z + cam.cy
    lim_x = (0.15 * cam.width + cam.cx + 0.5) / cam.fx, (1.15 * cam.width - cam.cx - 0.5) / cam.fx
    lim_y = (0.15 * cam.height + cam.cy + 0.5) / cam.fy, (1.15 * cam.height - cam.cy - 0.5) / cam.fy
    tx, ty = torch.clamp(x / z, -lim_x[0], lim_x[1]), torch.clamp(y / z, -lim_y[0], lim_y[1])
    zero = torch.zeros_like(z)
    J = torch.stack([cam.fx / z, zero, -cam.fx * tx / z, zero, cam.fy / z, -cam.fy * ty / z], -1).reshape(-1, 2, 3)
    cov2d = J @ R @ covariance_from_scales(quats, scales) @ R.T @ J.mT + 0.3 * torch.eye(2, dtype=means.dtype)
    rows, cols = torch.meshgrid(torch.arange(cam.height, dtype=F64), torch.arange(cam.width, dtype=F64), indexing="ij")
    d = torch.stack([cols.reshape(-1, 1) - u, rows.reshape(-1, 1) - v], -1)  # (pixels, N, 2)
    q = torch.einsum("pni,nij,pnj->pn", d, torch.linalg.inv(cov2d), d)
    raw = opacities * torch.exp(-0.5 * q)
    alpha = torch.where((raw >= 1 / 255) & (z > 0.01), torch.clamp(raw, max=0.99), torch.zeros_like(raw))
    npix = cam.height * cam.width
    T = torch.ones(npix, dtype=F64)
    done = torch.zeros(npix, dtype=torch.bool)
    color, depth, acc = torch.zeros(npix, 3, dtype=F64), torch.zeros(npix, dtype=F64), torch.zeros(npix, dtype=F64)
    for i in torch.argsort(z.detach()).tolist():
        a = alpha[:, i]
        after = T * (1 - a)
        done = done | ((a > 0) & (after < 1e-4))
        w = torch.where(~done & (a > 0), a * T, torch.zeros_like(a))
        color, depth, acc = color + w[:, None] * colors[i], depth + w * z[i], acc + w
        T = torch.where(~done & (a > 0), after, T)
    color = color + (1 - acc)[:, None] * background
    return color.view(cam.height, cam.width, 3), depth.view(cam.height, cam.width), acc.view(cam.height, cam.width)


# ---------------------------------------------------------------------------------------------


def test_single_gaussian_is_the_analytic_image():
    cam = Camera(width=40, height=30, fx=50.0, fy=40.0, cx=12.0, cy=19.0)  # off-centre on purpose
    z, sigma, o = 2.0, 0.1, 0.8
    angle = 0.7  # a disc facing the camera, turned about the optical axis: still isotropic
    quat = torch.tensor([[math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)]], dtype=F64)
    color = torch.tensor([[0.9, 0.4, 0.1]], dtype=F64)
    bg = torch.tensor([0.0, 0.2, 1.0], dtype=F64)
    out = TorchRasterizer().render(
        torch.tensor([[0.0, 0.0, z]], dtype=F64), quat, torch.tensor([[sigma, sigma, 1e-4]], dtype=F64),
        torch.tensor([o], dtype=F64), color, torch.eye(4, dtype=F64), cam, bg,
    )
    rows, cols = torch.meshgrid(torch.arange(30, dtype=F64), torch.arange(40, dtype=F64), indexing="ij")
    var_u, var_v = (cam.fx * sigma / z) ** 2 + 0.3, (cam.fy * sigma / z) ** 2 + 0.3
    expected = o * torch.exp(-0.5 * ((cols - cam.cx) ** 2 / var_u + (rows - cam.cy) ** 2 / var_v))
    expected = torch.where(expected >= 1 / 255, expected, torch.zeros_like(expected))
    torch.testing.assert_close(out.alpha, expected, rtol=0, atol=1e-12)
    peak = int(torch.argmax(out.alpha))
    assert divmod(peak, cam.width) == (19, 12) and out.alpha[19, 12].item() == pytest.approx(o, abs=1e-12)
    torch.testing.assert_close(out.depth, z * expected, rtol=0, atol=1e-12)
    expected_color = expected[..., None] * color[0] + (1 - expected[..., None]) * bg
    torch.testing.assert_close(out.color, expected_color, rtol=0, atol=1e-12)
    assert out.alpha[0, 39] == 0  # far corner: below 1/255, not composited


def test_matches_brute_force_with_occlusion_clamping_and_chunks():
    # many overlapping Gaussians, some nearly opaque: the transmittance cut-off and the 0.99
    # clamp both occur; small chunks so several bands are used
    cam = Camera(width=28, height=22, fx=26.0, fy=24.0, cx=13.2, cy=10.6)
    scene = random_scene(60, seed=3, opacity=(0.5, 0.999), size=(0.08, 0.3), spread=(0.8, 0.6))
    means, quats, scales, opac, colors = scene
    means[0, 2] = -0.5  # behind the camera
    means[1, 0] = 40.0  # far off-screen
    bg = torch.tensor([0.3, 0.6, 0.1], dtype=F64)
    w2c = a_pose()
    params = [p.clone().requires_grad_(True) for p in (means, quats, scales, opac, colors, bg)]
    rast = TorchRasterizer(TorchRasterizerConfig(max_pairs_per_chunk=1024))
    out = as_tuple(rast.render(*params[:5], w2c, cam, params[5]))
    ref = brute_force_render(*params[:5], w2c, cam, params[5])
    for mine, theirs in zip(out, ref):
        torch.testing.assert_close(mine, theirs, rtol=0, atol=1e-12)
    assert (ref[2] > 0.9999 - 1e-6).any(), "the scene should saturate some pixels"
    weights = random_weights(cam)
    mine = torch.autograd.grad(weighted_loss(out, weights), params)
    theirs = torch.autograd.grad(weighted_loss(ref, weights), params)
    for name, g1, g2 in zip(("means", "quats", "scales", "opacities", "colors", "background"), mine, theirs):
        torch.testing.assert_close(g1, g2, rtol=1e-9, atol=1e-9 * (1 + g2.abs().max().item()), msg=name)


def test_gradients_match_finite_differences():
    cam = Camera(width=24, height=20, fx=22.0, fy=21.0, cx=11.7, cy=9.3)
    means, quats, scales, opac, colors = random_scene(6, seed=11, size=(0.1, 0.25), spread=(0.6, 0.5))
    bg = torch.tensor([0.2, 0.1, 0.4], dtype=F64)
    w2c = a_pose()
    weights = random_weights(cam)
    rast = TorchRasterizer()
    params = [p.clone() for p in (means, quats, scales, opac, colors, bg)]

    def loss(ps):
        return weighted_loss(as_tuple(rast.render(*ps[:5], w2c, cam, ps[5])), weights)

    leaves = [p.clone().requires_grad_(True) for p in params]
    grads = torch.autograd.grad(loss(leaves), leaves)
    h = 1e-6
    for k, (name, p) in enumerate(zip(("means", "quats", "scales", "opacities", "colors", "background"), params)):
        fd = torch.zeros_like(p)
        for i in range(p.numel()):
            plus = [q.clone() for q in params]
            minus = [q.clone() for q in params]
            plus[k].view(-1)[i] += h
            minus[k].view(-1)[i] -= h
            with torch.no_grad():
                fd.view(-1)[i] = (loss(plus) - loss(minus)) / (2 * h)
        scale = grads[k].abs().max().item()
        assert scale > 0, name
        torch.testing.assert_close(grads[k], fd, rtol=1e-4, atol=1e-6 * scale, msg=name)


@pytest.mark.parametrize("near_first", [True, False])
def test_near_opaque_gaussian_hides_far_one(near_first):
    cam = Camera(width=20, height=16, fx=20.0, fy=20.0, cx=9.0, cy=7.0)
    near = ([0.0, 0.0, 1.0], [1.0, 0.0, 0.0])  # red
    far = ([0.0, 0.0, 3.0], [0.0, 0.0, 1.0])  # blue, larger on screen
    order = [near, far] if near_first else [far, near]
    means = torch.tensor([m for m, _ in order], dtype=F64)
    colors = torch.tensor([c for _, c in order], dtype=F64)
    scales = torch.tensor([[0.1, 0.1, 0.1] if m[2] == 1.0 else [2.0, 2.0, 2.0] for m, _ in order], dtype=F64)
    quats = torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=F64)
    opac = torch.tensor([0.99, 0.99], dtype=F64)
    out = TorchRasterizer().render(means, quats, scales, opac, colors, torch.eye(4, dtype=F64), cam)
    torch.testing.assert_close(out.color[7, 9], torch.tensor([0.99, 0.0, 0.01 * 0.99], dtype=F64))  # both centres
    assert out.depth[7, 9].item() == pytest.approx(0.99 * 1.0 + 0.01 * 0.99 * 3.0)
    # far from the small red one, only blue shows
    assert out.color[0, 0, 2] > 0.5 and out.color[0, 0, 0] < 1e-6


def test_culled_gaussians_contribute_nothing_and_empty_scene_is_background():
    cam = Camera(width=20, height=16, fx=20.0, fy=20.0, cx=9.5, cy=7.5)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=F64)
    rast = TorchRasterizer()
    visible = torch.tensor([[0.1, -0.1, 2.0]], dtype=F64)
    # behind, at the camera centre, inside the near plane, far off-screen to the right and above
    culled = torch.tensor(
        [[0.0, 0.0, -1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.005], [300.0, 0.0, 2.0], [0.0, -500.0, 1.0]], dtype=F64
    )
    n = 1 + len(culled)
    g = torch.Generator().manual_seed(0)
    quats, scales = torch.randn(n, 4, generator=g, dtype=F64), torch.full((n, 3), 0.1, dtype=F64)
    opac, colors = torch.full((n,), 0.7, dtype=F64), torch.rand(n, 3, generator=g, dtype=F64)
    params = [p.clone().requires_grad_(True) for p in (torch.cat([visible, culled]), quats, scales, opac, colors)]
    both = rast.render(*params, torch.eye(4, dtype=F64), cam, bg)
    alone = rast.render(*(p[:1] for p in params), torch.eye(4, dtype=F64), cam, bg)
    for a, b in zip(as_tuple(both), as_tuple(alone)):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    grads = torch.autograd.grad(weighted_loss(as_tuple(both), random_weights(cam)), params)
    for grad in grads:
        assert torch.isfinite(grad).all() and (grad[1:] == 0).all()
    assert (grads[0][0] != 0).any()

    empty = [torch.zeros(0, 3, dtype=F64), torch.zeros(0, 4, dtype=F64), torch.zeros(0, 3, dtype=F64),
             torch.zeros(0, dtype=F64), torch.zeros(0, 3, dtype=F64)]
    for scene in (empty, [p[1:].detach() for p in params]):
        out = rast.render(*scene, torch.eye(4, dtype=F64), cam, bg)
        assert out.color.shape == (16, 20, 3) and out.depth.shape == out.alpha.shape == (16, 20)
        torch.testing.assert_close(out.color, bg.expand(16, 20, 3), rtol=0, atol=0)
        assert (out.depth == 0).all() and (out.alpha == 0).all()
    assert TorchRasterizer().render(*empty, torch.eye(4, dtype=F64), cam).color.abs().max() == 0  # black default


def test_torch_only_code_path_matches(monkeypatch):
    """The path used on CUDA (torch sort, unbounded bands) gives the same render on CPU."""
    cam = Camera(width=30, height=20, fx=28.0, fy=27.0, cx=14.1, cy=9.8)
    scene = random_scene(40, seed=5, opacity=(0.3, 0.99), size=(0.05, 0.2))
    rast = TorchRasterizer(TorchRasterizerConfig(max_pairs_per_chunk=1500))
    ref = as_tuple(rast.render(*scene, a_pose(), cam))
    monkeypatch.setattr(torch_module, "USE_NUMPY_ON_CPU", False)
    for a, b in zip(as_tuple(rast.render(*scene, a_pose(), cam)), ref):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-14)


def test_float32_matches_float64():
    cam = Camera(width=64, height=48, fx=60.0, fy=60.0, cx=31.5, cy=23.5)
    scene = random_scene(300, seed=2, size=(0.02, 0.08))
    w2c = a_pose()
    ref = as_tuple(TorchRasterizer().render(*scene, w2c, cam))
    out = as_tuple(TorchRasterizer().render(*(x.float() for x in scene), w2c.float(), cam))
    assert all(o.dtype == torch.float32 for o in out)
    for a, b in zip(out, ref):
        assert (a.double() - b).abs().max() < 1e-4


def test_config_is_validated():
    with pytest.raises(ConfigError, match="max_pairs_per_chunk"):
        TorchRasterizerConfig(max_pairs_per_chunk=10)


def _registry_with_backends() -> Registry:
    from slamkit_plugins.mappers.gaussian_splatting.rasterizer import auto as auto_module

    registry = Registry()
    registry.add_module(torch_module, "torch_rasterizer (test)")
    registry.add_module(gsplat_module, "gsplat_rasterizer (test)")
    registry.add_module(auto_module, "auto_rasterizer (test)")
    return registry


def test_auto_takes_the_first_backend_it_can_build(monkeypatch):
    from slamkit_plugins.mappers.gaussian_splatting.rasterizer.auto import AutoRasterizer, AutoRasterizerConfig

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    registry = _registry_with_backends()
    auto = registry.create("rasterizer", "auto", AutoRasterizerConfig(prefer=["gsplat", "torch"]))  # no CUDA: no gsplat
    assert isinstance(auto, AutoRasterizer) and auto.name == "torch" and isinstance(auto.backend, TorchRasterizer)
    with pytest.raises(ConfigError, match="rasterizer auto: no backend could be built"):
        registry.create("rasterizer", "auto", AutoRasterizerConfig(prefer=["gsplat"]))
    with pytest.raises(ConfigError, match="rasterizer auto: built outside a run"):
        AutoRasterizer(AutoRasterizerConfig())  # a backend comes from the run's registry only
    with pytest.raises(ConfigError, match="mapper.rasterizer.prefer"):
        AutoRasterizerConfig(prefer=[])


def test_gsplat_without_cuda_is_a_config_error(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ConfigError, match=r"needs CUDA and the gsplat package \(pip install 'slamkit\[cuda\]'\)"):
        create_rasterizer("gsplat", registry=_registry_with_backends())


def test_max_pairs_per_chunk_bounds_the_bands_without_changing_the_image():
    """`rasterizer.max_pairs_per_chunk` set through the CLI's composition: a small bound renders the
    same image in more bands of rows (less memory at once)."""
    from slamkit.run.build import build_run

    cam = Camera(width=64, height=48, fx=60.0, fy=58.0, cx=31.5, cy=23.5)
    scene = random_scene(300, seed=5, size=(0.05, 0.2))
    outs, bands = [], []
    for limit in (2_000_000, 1024):
        rast = build_run(["mapper=gaussian_splatting", "mapper/rasterizer=torch",
                          f"mapper.rasterizer.max_pairs_per_chunk={limit}"])[1].mapper.rasterizer
        outs.append(rast.render(*scene, a_pose(), cam))
        bands.append(rast.last_num_bands)
    assert bands[0] == 1 and bands[1] > 5
    for a, b in zip(as_tuple(outs[0]), as_tuple(outs[1])):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-11)  # float64 sums in another order
