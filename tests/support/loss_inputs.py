"""Inputs for the RGB-D mapping loss's tests: a random render near a keyframe's colour and depth
(with a depth validity mask), and a loss function's value with its gradients w.r.t. the
rendered colour and depth."""

from __future__ import annotations

import torch


def loss_and_grads(fn, inputs, dtype=torch.float32, **kw):
    """fn's loss and its gradients w.r.t. colour and depth (zeros where the loss ignores one)."""
    color, depth, image, observed = (t.to(dtype) for t in inputs)
    color, depth = color.detach().requires_grad_(), depth.detach().requires_grad_()
    loss = fn(color, depth, image, observed, **kw)
    gc, gd = torch.autograd.grad(loss, [color, depth], allow_unused=True)
    gc = torch.zeros_like(color) if gc is None else gc
    gd = torch.zeros_like(depth) if gd is None else gd
    return loss.detach(), gc, gd


def random_inputs(H: int, W: int, seed: int, valid: float = 0.8):
    """A rendered colour / depth near a keyframe's, with a random validity mask on the depth."""
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(H, W, 3, generator=g)
    color = (image + 0.1 * torch.randn(H, W, 3, generator=g)).clamp(0, 1)
    observed = 0.5 + 4 * torch.rand(H, W, generator=g)
    observed[torch.rand(H, W, generator=g) > valid] = 0
    depth = observed + 0.05 * torch.randn(H, W, generator=g)
    return color, depth, image, observed
