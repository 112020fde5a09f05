"""Trajectory evaluation: ATE after Umeyama alignment and RPE over frame pairs, as evo computes them.

Poses are 4x4 float64 camera-to-world matrices, translations in metres. Estimate and ground
truth are matched by frame index (both sequences have one entry per input frame). A frame whose
ground truth is missing (None) or non-finite (NaN) is left out, and so is one whose estimate is
non-finite. Statistics over the errors (rmse, mean, median, max, std) follow evo: std is the
population standard deviation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slamkit.geometry.transforms import invert_pose, rotation_angle_deg

ALIGNMENTS = ("se3", "sim3", "none")
MIN_ATE_POSES = 3


def umeyama_alignment(src: np.ndarray, dst: np.ndarray, with_scale: bool = False):
    """Least-squares similarity (Umeyama 1991) minimising sum ||dst - (s R src + t)||^2.

    src, dst: (N, 3) corresponding points. Returns (R 3x3 rotation, t (3,) translation in dst
    units, s scale; s = 1 unless with_scale). Degenerate inputs (collinear points) still get a
    proper rotation that attains the minimum; coincident source points get s = 1.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2:
        raise ValueError(f"src and dst must both be (N, 3); got {src.shape} and {dst.shape}")
    mu_src, mu_dst = src.mean(axis=0), dst.mean(axis=0)
    src_c, dst_c = src - mu_src, dst - mu_dst
    cov = dst_c.T @ src_c / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:  # reflection -> proper rotation (Kabsch)
        S[2, 2] = -1.0
    R = U @ S @ Vt
    var_src = np.mean(np.sum(src_c**2, axis=1))
    s = float(np.trace(np.diag(D) @ S) / var_src) if with_scale and var_src > 0 else 1.0
    t = mu_dst - s * R @ mu_src
    return R, t, s


def _stack_poses(poses) -> np.ndarray:
    """List of 4x4 poses (None allowed) or an (N,4,4) array to (N,4,4) float64, NaN for None."""
    if isinstance(poses, np.ndarray):
        return np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    nan = np.full((4, 4), np.nan)
    return np.stack([nan if p is None else np.asarray(p, dtype=np.float64) for p in poses]).reshape(-1, 4, 4)


def _valid_pairs(est, gt) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    est, gt = _stack_poses(est), _stack_poses(gt)
    if len(est) != len(gt):
        raise ValueError(f"estimate has {len(est)} poses but ground truth has {len(gt)}")
    valid = np.isfinite(est).all(axis=(1, 2)) & np.isfinite(gt).all(axis=(1, 2))
    return est, gt, valid


def _stats(errors: np.ndarray) -> dict:
    """rmse, mean, median, max, std of 1-D errors; all None when empty."""
    if len(errors) == 0:
        return dict(rmse=None, mean=None, median=None, max=None, std=None)
    return dict(
        rmse=float(np.sqrt(np.mean(errors**2))),
        mean=float(np.mean(errors)),
        median=float(np.median(errors)),
        max=float(np.max(errors)),
        std=float(np.std(errors)),
    )


@dataclass
class ATEResult:
    """Absolute trajectory error (metres) after aligning estimated positions to ground truth.

    Statistics are None when fewer than 3 frames have both poses (num says how many do).
    est_aligned: (N, 3) every estimated position with the alignment applied (NaN where the
    estimate is non-finite). gt_positions: (N, 3), NaN where ground truth is missing.
    valid: (N,) frames used. errors_m: per-frame error of the valid frames, in frame order.
    rotation, translation, scale: the alignment, est_aligned = scale * rotation @ p + translation
    (identity when align="none" or too few frames).
    """

    rmse_m: float | None
    mean_m: float | None
    median_m: float | None
    max_m: float | None
    std_m: float | None
    num: int
    align: str
    est_aligned: np.ndarray
    gt_positions: np.ndarray
    valid: np.ndarray
    errors_m: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    scale: float

    def as_dict(self) -> dict:
        """{'rmse', 'mean', 'median', 'max', 'std' (metres or None), 'num'}."""
        return dict(rmse=self.rmse_m, mean=self.mean_m, median=self.median_m,
                    max=self.max_m, std=self.std_m, num=self.num)


def ate(est_poses, gt_poses, align: str = "se3") -> ATEResult:
    """Absolute trajectory error of estimated vs ground-truth camera-to-world poses, per frame.

    est_poses, gt_poses: sequences of 4x4 poses of equal length (None entries or NaN arrays
    mark missing poses). align: "se3" (rigid Umeyama, the default, as evo_ape -a), "sim3"
    (with scale, evo_ape -as) or "none". The error of a frame is the distance in metres between
    its aligned estimated position and its ground-truth position (evo's APE translation_part).
    """
    if align not in ALIGNMENTS:
        raise ValueError(f"align must be one of {ALIGNMENTS}, got {align!r}")
    est, gt, valid = _valid_pairs(est_poses, gt_poses)
    p_est, p_gt = est[:, :3, 3], gt[:, :3, 3]
    num = int(valid.sum())
    R, t, s = np.eye(3), np.zeros(3), 1.0
    if align != "none" and num >= MIN_ATE_POSES:
        R, t, s = umeyama_alignment(p_est[valid], p_gt[valid], with_scale=align == "sim3")
    aligned = s * p_est @ R.T + t
    errors = np.linalg.norm(aligned[valid] - p_gt[valid], axis=1)
    stats = _stats(errors if num >= MIN_ATE_POSES else errors[:0])
    return ATEResult(
        **{f"{k}_m": v for k, v in stats.items()}, num=num, align=align,
        est_aligned=aligned, gt_positions=np.where(np.isfinite(gt).all(axis=(1, 2))[:, None], p_gt, np.nan),
        valid=valid, errors_m=errors, rotation=R, translation=t, scale=s,
    )


def _relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(M, 4, 4) relative poses a_k^-1 b_k of two (M, 4, 4) pose stacks."""
    return invert_pose(a) @ b


def rpe(est_poses, gt_poses, delta: int = 1, all_pairs: bool = False) -> dict:
    """Relative pose error over frame pairs (i, i + delta), as evo_rpe with delta in frames.

    Like evo, the pairs are consecutive, i = 0, delta, 2 delta, ... (all_pairs=False, the
    default), or start at every frame (all_pairs=True); the same for delta = 1. Per pair
    E = (gt_i^-1 gt_j)^-1 (est_i^-1 est_j); a pair is used only when all four poses are present
    and finite. Returns trans_{rmse,mean,median,max,std}_m (norm of E's
    translation, metres), rot_{rmse,mean,median,max,std}_deg (angle of E's rotation, degrees),
    num (pairs used) and delta (frames). Statistics are None when no pair is usable.
    """
    if delta < 1:
        raise ValueError(f"delta must be >= 1 frame, got {delta}")
    est, gt, valid = _valid_pairs(est_poses, gt_poses)
    i = np.arange(0, max(len(est) - delta, 0), 1 if all_pairs else delta)
    i = i[valid[i] & valid[i + delta]]
    j = i + delta
    E = _relative(_relative(gt[i], gt[j]), _relative(est[i], est[j]))
    trans = np.linalg.norm(E[:, :3, 3], axis=1)
    rot = rotation_angle_deg(E[:, :3, :3])
    out = {f"trans_{k}_m": v for k, v in _stats(trans).items()}
    out |= {f"rot_{k}_deg": v for k, v in _stats(rot).items()}
    return out | dict(num=int(len(i)), delta=int(delta))
