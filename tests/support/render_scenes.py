"""Random Gaussian scenes for the rasteriser tests, float64: a scene in front of a slightly
turned camera (`random_scene`, `a_pose`), and a random linear loss of a render's outputs whose
gradients the backends must agree on (`random_weights`, `weighted_loss`)."""

from __future__ import annotations

import math

import torch

F64 = torch.float64


def rotation_y(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=F64)


def random_scene(n: int, seed: int, opacity=(0.1, 0.9), depth=(1.5, 3.5), spread=(1.0, 0.8), size=(0.03, 0.13)):
    g = torch.Generator().manual_seed(seed)

    def rand(*shape):
        return torch.rand(*shape, generator=g, dtype=F64)

    x, y = (rand(n) * 2 - 1) * spread[0], (rand(n) * 2 - 1) * spread[1]
    means = torch.stack([x, y, depth[0] + rand(n) * (depth[1] - depth[0])], -1)
    quats = torch.randn(n, 4, generator=g, dtype=F64)
    scales = size[0] + (size[1] - size[0]) * rand(n, 3)
    opacities = opacity[0] + (opacity[1] - opacity[0]) * rand(n)
    colors = rand(n, 3)
    return means, quats, scales, opacities, colors


def a_pose() -> torch.Tensor:
    w2c = torch.eye(4, dtype=F64)
    w2c[:3, :3] = rotation_y(0.1)
    w2c[:3, 3] = torch.tensor([0.05, -0.02, 0.1], dtype=F64)
    return w2c


def weighted_loss(out, weights):
    return sum((o * w).sum() for o, w in zip(out, weights))


def random_weights(cam, seed=7):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(cam.height, cam.width, 3, generator=g, dtype=F64),
            torch.randn(cam.height, cam.width, generator=g, dtype=F64),
            torch.randn(cam.height, cam.width, generator=g, dtype=F64))


def as_tuple(out):
    return out.color, out.depth, out.alpha
