"""Fabricated LPIPS weight files (torchvision's AlexNet keys and shapes, and lpips' linear
layers'), for tests that load LPIPS through its real path without the real weights."""

from __future__ import annotations

import numpy as np
import torch

SHAPES_BACKBONE = {f"features.{i}.weight": s for i, s in
                   ((0, (64, 3, 11, 11)), (3, (192, 64, 5, 5)), (6, (384, 192, 3, 3)), (8, (256, 384, 3, 3)),
                    (10, (256, 256, 3, 3)))}
SHAPES_BACKBONE.update({k.replace("weight", "bias"): (s[0],) for k, s in list(SHAPES_BACKBONE.items())})
SHAPES_LINEAR = {f"lin{layer}.model.1.weight": (1, c, 1, 1) for layer, c in enumerate((64, 192, 384, 256, 256))}


def fabricated(shapes: dict, seed: int, positive: bool = False) -> dict[str, torch.Tensor]:
    """Random weights of the given keys and shapes (He-scaled, so that activations neither
    vanish nor explode; non-negative like lpips' linear weights when `positive`)."""
    g = torch.Generator().manual_seed(seed)
    out = {}
    for key, shape in shapes.items():
        if positive:
            out[key] = torch.rand(shape, generator=g)
        elif key.endswith("bias"):
            out[key] = 0.05 * torch.randn(shape, generator=g)
        else:
            fan_in = int(np.prod(shape[1:]))
            out[key] = torch.randn(shape, generator=g) * (2.0 / fan_in) ** 0.5
    return out
