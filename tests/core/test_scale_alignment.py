"""Scale alignment of Gaussians entering the map (slamkit.map.growth): the paper's Eq. 4
(`growth.scale_alignment=eq4`) against today's z_pow, on known numbers."""

from __future__ import annotations

import numpy as np
import pytest

from slamkit.geometry.transforms import so3_exp
from slamkit.map.growth import MapGrowthConfig, ScaleAlignment, new_gaussians
from slamkit.types import FrameGaussians

#: Standard deviations (m) of the raw k-NN covariance along its three axes, largest first.
RAW_SCALES = np.array([0.02, 0.01, 0.001])
DEPTHS = np.array([2.0, 0.5])


def frame_gaussians() -> FrameGaussians:
    """Two Gaussians with the same raw covariance (RAW_SCALES, rotated) at camera depths 2 m
    and 0.5 m; the tracker's (regularised) covariances deliberately differ from Eq. 4's
    regularisation (a plane), so that the test shows which one the shapes come from."""
    R = so3_exp(np.array([0.4, -0.3, 0.9]))
    raw = R @ np.diag(RAW_SCALES**2) @ R.T
    plane = R @ np.diag([1.0, 1.0, 1e-3]) @ R.T
    return FrameGaussians(means=np.array([[0.0, 0.0, 2.0], [0.1, 0.0, 0.5]]), covariances=np.stack([plane, plane]),
                          colors=np.full((2, 3), 0.5), depths=DEPTHS, trackable=np.ones(2, bool),
                          shape_covariances=np.stack([raw, raw]))


def entry_scales(kind: ScaleAlignment, **cfg) -> np.ndarray:
    rows = new_gaussians(frame_gaussians(), 0, MapGrowthConfig(scale_alignment=kind, **cfg))
    return np.sort(np.exp(rows.log_scales.double().numpy()), axis=1)[:, ::-1]


def test_eq4_divides_the_ellipse_regularised_scales_by_z_to_the_p():
    # Eq. 4: Lambda'' = Lambda' / z^p, Lambda' = scales / their median = (2, 1, 0.1).
    expected = np.array([[2.0, 1.0, 0.1]]) / DEPTHS[:, None] ** 1.5
    # 2 m: (0.7071, 0.3536, 0.0354) m; 0.5 m: (5.657, 2.828, 0.2828) m (no floor on the divisor)
    np.testing.assert_allclose(entry_scales(ScaleAlignment.eq4), expected, rtol=1e-5)
    np.testing.assert_allclose(entry_scales(ScaleAlignment.eq4, scale_p=1.0), np.array([[1.0, 0.5, 0.05],
                                                                                        [4.0, 2.0, 0.2]]), rtol=1e-5)
    # scale_c plays no part in Eq. 4
    np.testing.assert_allclose(entry_scales(ScaleAlignment.eq4, scale_c=2.0), expected, rtol=1e-5)


def test_z_pow_divides_the_raw_scales_by_max_c_z_to_the_p_and_one():
    got = entry_scales(ScaleAlignment.z_pow, scale_c=2.0)
    expected = RAW_SCALES[None] / np.array([2.0 * 2.0**1.5, 1.0])[:, None]  # 2 * 0.5^1.5 = 0.71 -> 1
    np.testing.assert_allclose(got, expected, rtol=1e-5)


@pytest.mark.parametrize("kind", list(ScaleAlignment))
def test_every_alignment_keeps_the_raw_orientation(kind):
    rows = new_gaussians(frame_gaussians(), 0, MapGrowthConfig(scale_alignment=kind))
    q = rows.quats.double().numpy()
    raw = new_gaussians(frame_gaussians(), 0, MapGrowthConfig(scale_alignment=ScaleAlignment.none))
    ref = raw.quats.double().numpy()
    np.testing.assert_allclose(np.abs(np.sum(q * ref, axis=1)), 1.0, atol=1e-5)  # same rotation up to sign
