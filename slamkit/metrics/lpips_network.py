"""LPIPS v0.1's network with the AlexNet trunk (Zhang et al. 2018): its architecture, the
shapes of the weights it takes, and the distance (the formula in `slamkit.metrics.lpips`).
The weights come from `slamkit.metrics.lpips_weights`."""

from __future__ import annotations

from collections.abc import Mapping

import torch
import torch.nn.functional as F

from slamkit.errors import DataError
from slamkit.metrics.images import zero_outside

#: AlexNet's five convolutions as torchvision's `features` holds them: (index in `features`,
#: in channels, out channels, kernel, stride, padding, max-pool 3x3 / 2 before it). Each is
#: followed by a ReLU, whose output is an LPIPS layer.
ALEXNET_CONVS = (
    (0, 3, 64, 11, 4, 2, False),
    (3, 64, 192, 5, 1, 2, True),
    (6, 192, 384, 3, 1, 1, True),
    (8, 384, 256, 3, 1, 1, False),
    (10, 256, 256, 3, 1, 1, False),
)
#: lpips v0.1's ScalingLayer, applied to the image in [-1, 1].
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
#: Added to the channel norm before dividing by it (lpips' normalize_tensor).
NORM_EPS = 1e-10


def backbone_shapes() -> dict[str, tuple[int, ...]]:
    """The state-dict keys and shapes the AlexNet checkpoint must hold (torchvision's names)."""
    shapes = {}
    for index, c_in, c_out, k, _, _, _ in ALEXNET_CONVS:
        shapes[f"features.{index}.weight"] = (c_out, c_in, k, k)
        shapes[f"features.{index}.bias"] = (c_out,)
    return shapes


def linear_shapes() -> dict[str, tuple[int, ...]]:
    """The state-dict keys and shapes of lpips' linear layers (`lin{l}.model.1.weight`; index 1
    because lpips puts a dropout layer at 0)."""
    return {f"lin{layer}.model.1.weight": (1, conv[2], 1, 1) for layer, conv in enumerate(ALEXNET_CONVS)}


def min_image_side() -> int:
    """The smallest image side (pixels) for which every AlexNet layer has at least one pixel."""
    side = 1
    for _, _, _, k, stride, pad, pool in reversed(ALEXNET_CONVS):
        side = (side - 1) * stride + k - 2 * pad
        if pool:
            side = (side - 1) * 2 + 3
    return max(side, 1)


class LPIPS:
    """LPIPS v0.1 (AlexNet) with its weights; `lpips(a, b, mask)` is the distance (see the module
    docstring). backbone, linear: state dicts with at least the keys of `backbone_shapes()` and
    `linear_shapes()` (other keys are ignored); a missing key or a wrong shape is a DataError
    naming `sources` (what the weights were read from: {"backbone": ..., "linear": ...}).
    device: where the network runs. provenance: the files and their SHA-256, for the record."""

    def __init__(self, backbone: Mapping[str, torch.Tensor], linear: Mapping[str, torch.Tensor],
                 device: torch.device | str | None = None, sources: Mapping[str, str] | None = None,
                 provenance: Mapping[str, str] | None = None):
        sources = dict(sources or {})
        self.device = torch.device(device or "cpu")
        self.convs = _checked(backbone, backbone_shapes(), sources.get("backbone", "the AlexNet weights"), self.device)
        self.lins = _checked(linear, linear_shapes(), sources.get("linear", "the LPIPS linear weights"), self.device)
        self.shift = torch.tensor(SHIFT, device=self.device).view(1, 3, 1, 1)
        self.scale = torch.tensor(SCALE, device=self.device).view(1, 3, 1, 1)
        self.provenance = dict(provenance or {})

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The five ReLU outputs of AlexNet's features for images x (N,3,H,W) already scaled."""
        out = []
        for index, _, _, _, stride, pad, pool in ALEXNET_CONVS:
            if pool:
                x = F.max_pool2d(x, kernel_size=3, stride=2)
            x = F.relu(F.conv2d(x, self.convs[f"features.{index}.weight"], self.convs[f"features.{index}.bias"],
                                stride=stride, padding=pad))
            out.append(x)
        return out

    @torch.no_grad()
    def __call__(self, a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> float:
        """LPIPS between two RGB images (H,W,3) in [0, 1] (0 for identical images; lower is more
        alike); pixels outside `mask` (H,W) set to 0 in both first. Each side must be at least
        `min_image_side()` pixels."""
        if a.shape != b.shape or a.dim() != 3 or a.shape[-1] != 3:
            raise ValueError(f"LPIPS needs two (H,W,3) images of one shape: got {tuple(a.shape)} and {tuple(b.shape)}")
        if mask is not None and tuple(mask.shape) != tuple(a.shape[:2]):
            raise ValueError(f"mask shape {tuple(mask.shape)} does not match the image's {tuple(a.shape[:2])}")
        if min(a.shape[:2]) < min_image_side():
            raise ValueError(f"LPIPS needs images at least {min_image_side()} pixels on each side: got "
                             f"{tuple(a.shape[:2])}")
        x = torch.stack([zero_outside(a, mask), zero_outside(b, mask)]).to(self.device).permute(0, 3, 1, 2)
        x = (2 * x - 1 - self.shift) / self.scale
        total = torch.zeros((), dtype=torch.float64)
        for layer, f in enumerate(self.features(x)):
            n = f / (f.norm(dim=1, keepdim=True) + NORM_EPS)
            diff = (n[0] - n[1]) ** 2  # (C,h,w)
            w = self.lins[f"lin{layer}.model.1.weight"].view(-1)
            total += float(torch.einsum("c,chw->hw", w, diff).mean())
        return float(total)


def _checked(state: Mapping[str, torch.Tensor], shapes: dict[str, tuple[int, ...]], source: str,
             device: torch.device) -> dict[str, torch.Tensor]:
    """The tensors of `state` named in `shapes`, checked and as float32 on `device`."""
    out = {}
    for key, shape in shapes.items():
        if key not in state:
            raise DataError(f"{source}: no {key!r} in it (expected a {shape} tensor)")
        value = state[key]
        if not isinstance(value, torch.Tensor) or tuple(value.shape) != shape:
            got = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
            raise DataError(f"{source}: {key!r} is {got}, expected {shape}")
        if not torch.isfinite(value).all():
            raise DataError(f"{source}: {key!r} has non-finite values")
        out[key] = value.detach().to(device=device, dtype=torch.float32)
    return out
