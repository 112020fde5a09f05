"""The mapping loss (`loss=l1_ssim_depth`): the paper's formula, its weights and masks."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from pytorch_msssim import ssim

from slamkit.roles import TrainingView
from slamkit.roles.rendering import RenderOutput
from slamkit.types import Camera
from slamkit_plugins.mappers.gaussian_splatting.loss.l1_ssim_depth import L1SSIMDepthConfig, L1SSIMDepthLoss

H, W = 24, 32


def view_and_render(seed: int = 0, invalid: float = 0.3):
    g = torch.Generator().manual_seed(seed)
    image, color = torch.rand(H, W, 3, generator=g), torch.rand(H, W, 3, generator=g)
    depth = 1 + 2 * torch.rand(H, W, generator=g)
    depth[torch.rand(H, W, generator=g) < invalid] = 0
    rendered = 1 + 2 * torch.rand(H, W, generator=g)
    view = TrainingView(0, 0, np.eye(4), torch.eye(4), Camera(W, H, 30, 30, 15.5, 11.5), image, depth)
    return view, RenderOutput(color, rendered, torch.ones(H, W))


def test_the_value_is_the_papers_formula_over_valid_depth_pixels():
    view, render = view_and_render()
    m = (view.depth > 0).float()
    n = m.sum()
    l1 = ((render.color - view.image).abs() * m[..., None]).sum() / (3 * n)
    s = ssim((render.color * m[..., None]).permute(2, 0, 1)[None], (view.image * m[..., None]).permute(2, 0, 1)[None],
             data_range=1.0, win_size=11, win_sigma=1.5)
    ld = ((render.depth - view.depth).abs() * m).sum() / n / 10
    loss = L1SSIMDepthLoss(L1SSIMDepthConfig())(render, view)
    assert float(loss) == pytest.approx(float(0.8 * l1 + 0.2 * (1 - s) + 0.1 * ld), rel=1e-6)
    only_depth = L1SSIMDepthLoss(L1SSIMDepthConfig(weight_l1=0, weight_ssim=0, weight_depth=1, depth_unit=1))
    assert float(only_depth(render, view)) == pytest.approx(float(10 * ld), rel=1e-6)


def test_without_valid_depth_the_colour_terms_use_every_pixel_and_depth_drops_out():
    view, render = view_and_render(invalid=1.1)
    loss = L1SSIMDepthLoss(L1SSIMDepthConfig(weight_ssim=0))(render, view)
    assert float(loss) == pytest.approx(float(0.8 * (render.color - view.image).abs().mean()), rel=1e-6)


def test_gradients_reach_colour_and_depth():
    view, render = view_and_render()
    color, depth = render.color.requires_grad_(True), render.depth.requires_grad_(True)
    L1SSIMDepthLoss(L1SSIMDepthConfig())(RenderOutput(color, depth, render.alpha), view).backward()
    assert color.grad.abs().sum() > 0 and depth.grad.abs().sum() > 0
    assert not depth.grad[view.depth == 0].any()  # invalid pixels have no depth gradient


@pytest.mark.parametrize("seed, invalid", [(0, 0.3), (1, 0.0), (2, 1.1)])
def test_the_compiled_backend_is_the_same_loss(seed, invalid):
    """mapper.loss.backend=compiled (one kernel call, analytic gradients) against backend=torch
    (autograd through pytorch-msssim): value and gradients to float precision."""
    from slamkit_plugins.mappers.gaussian_splatting.loss.l1_ssim_depth import Backend

    view, render = view_and_render(seed, invalid)
    results = {}
    for backend in (Backend.torch, Backend.compiled):
        color, depth = render.color.clone().requires_grad_(True), render.depth.clone().requires_grad_(True)
        loss = L1SSIMDepthLoss(L1SSIMDepthConfig(backend=backend))(RenderOutput(color, depth, render.alpha), view)
        loss.backward()
        no_grad = torch.zeros_like(depth)  # no depth term (no valid depth): torch leaves depth out of the graph
        results[backend] = (float(loss.detach()), color.grad, no_grad if depth.grad is None else depth.grad)
    (a, ca, da), (b, cb, db) = results.values()
    assert b == pytest.approx(a, rel=1e-6)
    torch.testing.assert_close(cb, ca, rtol=1e-4, atol=1e-7)
    torch.testing.assert_close(db, da, rtol=1e-5, atol=1e-9)
