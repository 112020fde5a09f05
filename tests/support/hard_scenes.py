"""Hard random scenes for the compiled CPU rasteriser against the torch reference (float64, in
the world frame of a tilted camera) and the outputs and input gradients of a random linear loss
of a render, compared by relative error."""

from __future__ import annotations

import math

import torch

from slamkit.types import Camera

from support.render_scenes import random_weights

F64 = torch.float64


def a_pose() -> torch.Tensor:
    c, s = math.cos(0.3), math.sin(0.3)
    w2c = torch.eye(4, dtype=F64)
    w2c[:3, :3] = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=F64) @ torch.tensor(
        [[1.0, 0.0, 0.0], [0.0, math.cos(0.2), -math.sin(0.2)], [0.0, math.sin(0.2), math.cos(0.2)]], dtype=F64)
    w2c[:3, 3] = torch.tensor([0.05, -0.02, 0.1], dtype=F64)
    return w2c


CAM = Camera(width=100, height=75, fx=80.0, fy=84.0, cx=47.3, cy=39.1)  # not tile multiples, off-centre


def hard_scene(n: int, seed: int, cam: Camera = CAM, w2c: torch.Tensor | None = None, anisotropy: float = 1.0):
    """Random Gaussians, in the camera frame: ~10 % behind the camera or at the near plane,
    ~1/3 off-screen (some far off, with huge extents), log-uniform scales per axis (ratios up
    to ~`30 * anisotropy`), 5 % needles (ratio 200), opacities from below 1/255 to 0.99.
    Returned in the world frame of `w2c` (default `a_pose()`), float64."""
    g = torch.Generator().manual_seed(seed)

    def rand(*shape):
        return torch.rand(*shape, generator=g, dtype=F64)

    w2c = a_pose() if w2c is None else w2c
    z = 0.3 + 3.7 * rand(n)
    k = torch.randperm(n, generator=g)
    z[k[: n // 20]] = -1.0 + 1.0 * rand(n // 20)  # behind the camera
    z[k[n // 20 : n // 10]] = 0.011 + 0.1 * rand(n // 10 - n // 20)  # just past the near plane
    x = ((rand(n) * 2 - 1) * 0.8 * cam.width / cam.fx) * z.abs()
    y = ((rand(n) * 2 - 1) * 0.8 * cam.height / cam.fy) * z.abs()
    far = k[n // 10 : n // 10 + n // 20]
    x[far] *= 4.0  # well off-screen
    pc = torch.stack([x, y, z], -1)
    scales = torch.exp(math.log(0.003) + (math.log(0.1) - math.log(0.003)) * anisotropy * rand(n, 3)).clamp(max=2.0)
    needles = k[n // 5 : n // 5 + n // 20]
    scales[needles] = torch.tensor([0.001, 0.2, 0.002], dtype=F64)
    quats = torch.randn(n, 4, generator=g, dtype=F64)
    opacities = 0.99 * rand(n)
    opacities[k[-n // 50 :]] = 0.003  # below 1/255: culled
    colors = rand(n, 3)
    R, t = w2c[:3, :3], w2c[:3, 3]
    means = (pc - t) @ R  # so that R m + t = pc
    return means, quats, scales, opacities, colors, w2c


def render_and_grads(rasterizer, scene, cam: Camera, background, dtype):
    """Outputs and the gradients of a random linear loss w.r.t. every input, as float64."""
    means, quats, scales, opacities, colors, w2c = scene
    leaves = [x.to(dtype).detach().requires_grad_(True) for x in (means, quats, scales, opacities, colors, background)]
    out = rasterizer.render(*leaves[:5], w2c.to(dtype), cam, leaves[5])
    loss = sum((o * w.to(dtype)).sum() for o, w in zip((out.color, out.depth, out.alpha), random_weights(cam)))
    loss.backward()
    return [x.detach().to(F64) for x in (out.color, out.depth, out.alpha)] + [x.grad.to(F64) for x in leaves]


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm().clamp(min=1e-30))
