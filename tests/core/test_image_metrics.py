"""PSNR, SSIM and depth L1, with and without a mask (slamkit.metrics.images)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from pytorch_msssim import ssim as ms_ssim

from slamkit.metrics import images as image_metrics


def test_psnr_ssim_l1_and_masks():
    rng = np.random.default_rng(0)
    a = torch.as_tensor(rng.uniform(size=(20, 24, 3)), dtype=torch.float32)
    b = a.clone()
    assert image_metrics.psnr(a, b) == math.inf
    assert image_metrics.ssim(a, b) == pytest.approx(1.0, abs=1e-6)
    b += 0.1
    assert image_metrics.psnr(a, b) == pytest.approx(20.0, abs=1e-4)
    mask = torch.zeros(20, 24, dtype=torch.bool)
    mask[:, :12] = True
    b[:, 12:] = 0.9  # outside the mask: does not count
    assert image_metrics.psnr(a, b, mask) == pytest.approx(20.0, abs=1e-4)
    # masked SSIM = SSIM of both images with the outside pixels zeroed (the reference's way)
    m = mask[..., None].float()
    expected = ms_ssim((a * m).permute(2, 0, 1)[None], (b * m).permute(2, 0, 1)[None], data_range=1.0)
    assert image_metrics.ssim(a, b, mask) == pytest.approx(float(expected), abs=1e-6)
    d_obs = torch.full((20, 24), 2.0)
    d_obs[0] = 0  # invalid
    d_ren = torch.full((20, 24), 2.05)
    d_ren[0] = 100.0
    assert image_metrics.l1_depth(d_ren, d_obs) == pytest.approx(0.05, abs=1e-6)
    assert math.isnan(image_metrics.psnr(a, b, torch.zeros_like(mask)))


def test_psnr_over_all_pixels_zeroes_the_invalid_ones_as_the_reference_code():
    """pixels="all": the pixels outside the mask are 0 in both images and count in the mean, so
    with half the pixels valid the error halves: PSNR rises by 10 log10(2) = 3.0103 dB."""
    rng = np.random.default_rng(1)
    a = torch.as_tensor(rng.uniform(size=(20, 24, 3)), dtype=torch.float32)
    b = a + 0.1
    mask = torch.zeros(20, 24, dtype=torch.bool)
    mask[:, :12] = True
    # outside the mask: zeroed, does not count
    b[:, 12:] = torch.as_tensor(rng.uniform(size=(20, 12, 3)), dtype=torch.float32)
    assert image_metrics.psnr(a, b, mask) == pytest.approx(20.0, abs=1e-4)
    assert image_metrics.psnr(a, b, mask, pixels="all") == pytest.approx(20.0 + 10 * math.log10(2), abs=1e-4)
    assert image_metrics.psnr(a, b, mask, pixels=image_metrics.PsnrPixels.all) == pytest.approx(23.0103, abs=1e-4)
    assert image_metrics.psnr(a, b, pixels="all") == image_metrics.psnr(a, b)  # no mask: the same pixels
    assert image_metrics.psnr(a, a, torch.zeros_like(mask), pixels="all") == math.inf  # all zeroed: identical
    with pytest.raises(ValueError, match="mask shape"):
        image_metrics.psnr(a, b, mask[:10], pixels="all")
    with pytest.raises(ValueError, match="'every'"):
        image_metrics.psnr(a, b, mask, pixels="every")
