"""Image quality metrics for rendered views: PSNR, SSIM and depth L1, optionally masked.

Images are torch tensors (H,W,3) (or (H,W) for one channel) with values in [0, 1]; depths
(H,W) in metres; a mask (H,W) bool marks the pixels that count (e.g. valid ground-truth depth,
as GS-ICP SLAM's evaluation does). SSIM is pytorch-msssim's (Gaussian window 11, sigma 1.5,
data range 1, K = (0.01, 0.03)); it is window-based, so a mask is applied the way the reference
code applies it: pixels outside the mask are set to 0 in both images before SSIM. Depth L1
averages over the masked pixels only; PSNR does by default (`pixels="valid"`), or, as the
reference code does, over every pixel with the ones outside the mask set to 0 in both images
(`pixels="all"`), which raises PSNR by 10 log10(1 / valid fraction); the two are identical when
every pixel is valid, as on Replica.
"""

from __future__ import annotations

import math

import torch
from pytorch_msssim import ssim as _ms_ssim

from slamkit.config import PsnrPixels

#: SSIM window (pixels) and Gaussian sigma used everywhere in slamkit (3DGS / GS-ICP SLAM).
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5


def _check(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None) -> None:
    if a.shape != b.shape:
        raise ValueError(f"image shapes differ: {tuple(a.shape)} vs {tuple(b.shape)}")
    if mask is not None and tuple(mask.shape) != tuple(a.shape[:2]):
        raise ValueError(f"mask shape {tuple(mask.shape)} does not match the image's {tuple(a.shape[:2])}")


def zero_outside(img: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """`img` (H,W) or (H,W,C) as float with the pixels outside `mask` (H,W) set to 0 (unchanged
    when mask is None)."""
    img = img.float()
    if mask is None:
        return img
    m = mask.to(img.dtype)
    return img * (m if img.dim() == 2 else m[..., None])


def _nchw(img: torch.Tensor) -> torch.Tensor:
    """(H,W) or (H,W,C) -> (1,C,H,W) float32."""
    img = img.float()
    if img.dim() == 2:
        img = img[..., None]
    return img.permute(2, 0, 1)[None]


def mse(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean squared error over all channels of the masked pixels (all pixels when mask is None).
    A mask with no pixel gives NaN."""
    _check(a, b, mask)
    sq = (a.float() - b.float()) ** 2
    if sq.dim() == 2:
        sq = sq[..., None]
    if mask is None:
        return sq.mean()
    m = mask.to(sq.dtype)[..., None]
    return (sq * m).sum() / (m.sum() * sq.shape[-1])


def psnr(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None,
         pixels: PsnrPixels | str = PsnrPixels.valid) -> float:
    """Peak signal-to-noise ratio in dB for images in [0, 1]: over the masked pixels
    (`pixels="valid"`), or over all pixels with those outside the mask zeroed in both images
    (`pixels="all"`, see PsnrPixels). inf for identical images, NaN for an empty mask with
    valid."""
    if PsnrPixels(pixels) is PsnrPixels.all:
        _check(a, b, mask)
        a, b, mask = zero_outside(a, mask), zero_outside(b, mask), None
    e = float(mse(a, b, mask))
    if math.isnan(e):
        return float("nan")
    return float("inf") if e <= 0 else -10.0 * math.log10(e)


def ssim(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None, differentiable: bool = False):
    """Structural similarity (window 11, sigma 1.5, data range 1), pixels outside `mask` set to 0
    in both images. Returns a float, or a 0-d tensor with gradients when `differentiable`.
    Images must be at least 11 pixels on each side."""
    _check(a, b, mask)
    x, y = _nchw(zero_outside(a, mask)), _nchw(zero_outside(b, mask))
    value = _ms_ssim(x, y, data_range=1.0, size_average=True, win_size=SSIM_WINDOW, win_sigma=SSIM_SIGMA)
    return value if differentiable else float(value)


def l1_depth(rendered: torch.Tensor, observed: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """Mean absolute depth difference in metres over `mask` (default: observed depth > 0).
    NaN when no pixel counts."""
    _check(rendered, observed, mask)
    if mask is None:
        mask = observed > 0
    n = int(mask.sum())
    if n == 0:
        return float("nan")
    return float((rendered.float() - observed.float()).abs()[mask].sum() / n)
