"""Trajectory evaluation: Umeyama, ATE, RPE (checked against evo) and the trajectory plot."""

import copy

import numpy as np
import pytest

from slamkit.geometry.transforms import make_pose, so3_exp
from slamkit.metrics.trajectory import ate, rpe, umeyama_alignment


def random_rotation(rng):
    return so3_exp(rng.normal(size=3))


def smooth_trajectory(n=50):
    """Camera-to-world poses on a helix, turning slowly (metres)."""
    s = np.linspace(0, 2 * np.pi, n)
    return np.stack([
        make_pose(so3_exp(np.array([0.1 * np.sin(t), t / 3, 0.05 * t])),
                  [np.cos(t), 0.3 * np.sin(2 * t), np.sin(t) + 0.2 * t])
        for t in s
    ])


def perturbed(gt, rng, drift=0.01):
    """gt with per-frame noise (~1 cm, ~0.6 deg) and a slowly growing drift, moved by a rigid T."""
    T = make_pose(random_rotation(rng), rng.normal(size=3))
    est = []
    for k, P in enumerate(gt):
        noise = make_pose(so3_exp(0.01 * rng.normal(size=3)),
                          0.01 * rng.normal(size=3) + drift * k * np.array([1, 0.5, 0]))
        est.append(T @ P @ noise)
    return np.stack(est)


@pytest.mark.parametrize("with_scale", [False, True])
def test_umeyama_recovers_known_transform(with_scale):
    rng = np.random.default_rng(0)
    src = rng.normal(size=(100, 3))
    R, t, s = random_rotation(rng), rng.normal(size=3), 2.5 if with_scale else 1.0
    dst = s * src @ R.T + t
    R_est, t_est, s_est = umeyama_alignment(src, dst, with_scale=with_scale)
    np.testing.assert_allclose(R_est, R, atol=1e-12)
    np.testing.assert_allclose(t_est, t, atol=1e-12)
    assert s_est == pytest.approx(s, rel=1e-12)


def test_ate_zero_under_rigid_transform():
    rng = np.random.default_rng(1)
    gt = smooth_trajectory()
    T = make_pose(random_rotation(rng), rng.normal(size=3) * 5)
    res = ate(T @ gt, gt)
    assert res.num == len(gt)
    assert res.rmse_m < 1e-12 and res.max_m < 1e-12
    np.testing.assert_allclose(res.est_aligned, gt[:, :3, 3], atol=1e-12)
    # Unaligned, the error is the rigid offset; sim3 also recovers a scaled trajectory.
    assert ate(T @ gt, gt, align="none").rmse_m > 0.1
    scaled = gt.copy()
    scaled[:, :3, 3] *= 0.3
    assert ate(T @ scaled, gt, align="sim3").rmse_m < 1e-12


def test_matches_evo():
    pytest.importorskip("evo")
    from evo.core import metrics
    from evo.core.metrics import PoseRelation, StatisticsType, Unit
    from evo.core.trajectory import PoseTrajectory3D

    rng = np.random.default_rng(2)
    gt = smooth_trajectory()
    est = perturbed(gt, rng)
    stamps = np.arange(len(gt)) * 0.1
    traj_gt = PoseTrajectory3D(poses_se3=list(gt), timestamps=stamps)
    traj_est = PoseTrajectory3D(poses_se3=list(est), timestamps=stamps)

    def close(ours, theirs):
        assert ours == pytest.approx(theirs, rel=1e-9, abs=0)

    for align, scale in (("se3", False), ("sim3", True)):
        aligned = copy.deepcopy(traj_est)
        aligned.align(traj_gt, correct_scale=scale)
        ape = metrics.APE(PoseRelation.translation_part)
        ape.process_data((traj_gt, aligned))
        ours = ate(est, gt, align=align)
        close(ours.rmse_m, ape.get_statistic(StatisticsType.rmse))
        close(ours.mean_m, ape.get_statistic(StatisticsType.mean))
        close(ours.median_m, ape.get_statistic(StatisticsType.median))
        close(ours.max_m, ape.get_statistic(StatisticsType.max))
        close(ours.std_m, ape.get_statistic(StatisticsType.std))
        np.testing.assert_allclose(ours.est_aligned, aligned.positions_xyz, rtol=0, atol=1e-9)

    for delta in (1, 3):
        ours = rpe(est, gt, delta=delta)
        for relation, key in ((PoseRelation.translation_part, "trans_{}_m"),
                              (PoseRelation.rotation_angle_deg, "rot_{}_deg")):
            r = metrics.RPE(relation, delta=delta, delta_unit=Unit.frames, all_pairs=False)
            r.process_data((traj_gt, traj_est))
            assert ours["num"] == len(r.error)
            close(ours[key.format("rmse")], r.get_statistic(StatisticsType.rmse))
            close(ours[key.format("mean")], r.get_statistic(StatisticsType.mean))
            close(ours[key.format("max")], r.get_statistic(StatisticsType.max))


def test_missing_ground_truth_excluded():
    rng = np.random.default_rng(3)
    gt = smooth_trajectory(20)
    est = perturbed(gt, rng, drift=0.0)
    keep = np.ones(len(gt), bool)
    keep[[0, 5, 6, 19]] = False
    gt_list = [P if k else None for P, k in zip(gt, keep)]
    res = ate(est, gt_list)
    ref = ate(est[keep], gt[keep])
    assert res.num == keep.sum() == ref.num
    assert res.rmse_m == pytest.approx(ref.rmse_m, rel=1e-12)
    assert np.isnan(res.gt_positions[~keep]).all() and res.valid.tolist() == keep.tolist()
    gt_nan = gt.copy()
    gt_nan[~keep] = np.nan
    assert ate(est, gt_nan).rmse_m == pytest.approx(ref.rmse_m, rel=1e-12)
    # RPE skips pairs touching a missing frame: 19 pairs minus those touching 0, 5, 6, 19.
    assert rpe(est, gt_list)["num"] == 19 - 5

    few = [None] * len(gt)
    few[3], few[4] = gt[3], gt[4]
    res = ate(est, few)
    assert res.num == 2
    assert all(v is None for k, v in res.as_dict().items() if k != "num")
    assert rpe(est, [None] * len(gt))["trans_rmse_m"] is None


def test_plot_writes_png(tmp_path):
    rng = np.random.default_rng(4)
    from slamkit.formats.plots import plot_trajectory

    gt = smooth_trajectory(30)
    res = ate(perturbed(gt, rng), gt)
    gt_pos = res.gt_positions.copy()
    gt_pos[10:12] = np.nan
    for name, ref in (("with_gt.png", gt_pos), ("no_gt.png", None)):
        path = plot_trajectory(tmp_path / name, res.est_aligned, ref, "test", ate_rmse_m=res.rmse_m)
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 1000


def test_plot_draws_the_loops_closed_in_red(tmp_path):
    from PIL import Image

    from slamkit.formats.plots import plot_trajectory

    gt = smooth_trajectory(30)
    res = ate(gt, gt)

    def red_pixels(name: str, loops) -> int:
        path = plot_trajectory(tmp_path / name, res.est_aligned, res.gt_positions, "test", loops=loops)
        rgb = np.asarray(Image.open(path).convert("RGB")).astype(int)
        # matplotlib's tab:red (214, 39, 40)
        return int(((abs(rgb[..., 0] - 214) < 20) & (rgb[..., 1] < 80) & (rgb[..., 2] < 80)).sum())

    assert red_pixels("plain.png", []) == 0
    assert red_pixels("loops.png", [(29, 0), (20, 5)]) > 50
