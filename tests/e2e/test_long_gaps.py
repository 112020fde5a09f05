"""A bounded delay per frame (issue 47): each frame's delay from arrival to pose in frames.csv
and its median, p99 and maximum in metrics.json; forced gaps (eval.forced_gap_every,
eval.forced_gap_length) as a camera that does not wait makes them, and tracking across them."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from slamkit.errors import ConfigError
from slamkit.formats.tum import read_tum_trajectory
from slamkit.geometry.transforms import invert_pose
from slamkit.registry.schema import EvalConfig

from support.commands import run_slamkit
from support.data import SEVENSCENES, TUM, require_data

pytestmark = pytest.mark.slow  # every test here starts the slamkit command

SMALL = ("dataset=synthetic", "dataset.num_frames=10", "dataset.width=64", "dataset.height=48", "tracker=gicp",
         "keyframe=every_n", "keyframe.tracking_every=3", "mapper=none", "output.progress=false", "output.plot=false")


def rows(run) -> list[dict]:
    with open(run / "frames.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_forced_gaps_and_a_delay_per_frame(tmp_path):
    """eval.forced_gap_every=4 eval.forced_gap_length=2 drops stream positions 4, 5 and 8, 9; every
    tracked frame's delay is logged, at least its tracking time, and summarised."""
    gaps = EvalConfig(forced_gap_every=4, forced_gap_length=2)
    assert [p for p in range(12) if gaps.in_forced_gap(p)] == [4, 5, 8, 9]
    with pytest.raises(ConfigError, match="eval.forced_gap_length"):
        EvalConfig(forced_gap_every=4, forced_gap_length=4)
    out = tmp_path / "run"
    proc = run_slamkit(*SMALL, "eval.forced_gap_every=4", "eval.forced_gap_length=2", f"hydra.run.dir={out}",
                       cwd=tmp_path, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    table = rows(out)
    assert [int(r["index"]) for r in table if r["note"] == "dropped"] == [4, 5, 8, 9]
    tracked = [r for r in table if r["note"] != "dropped"]
    delays = [float(r["delay_ms"]) for r in tracked]
    assert len(delays) == 6 and all(d >= float(r["tracking_ms"]) - 0.01 for d, r in zip(delays, tracked))
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["dropped_frames"] == 4
    assert metrics["delay_median_ms"] <= metrics["delay_p99_ms"] <= metrics["delay_max_ms"]
    assert metrics["delay_max_ms"] == pytest.approx(max(delays), abs=0.01)


def relative_errors(out, frames: list[int], length: int = 20) -> dict[int, tuple[float, float]]:
    """For each frame after a gap of `length` frames (dataset index): its motion since the last
    frame before the gap against the ground truth's, as (metres, degrees); asserts it was tracked,
    not lost."""
    table = rows(out)
    stamps, poses = read_tum_trajectory(out / "trajectory.txt")
    estimate = dict(zip(np.round(stamps, 4), poses))
    stamps, poses = read_tum_trajectory(out / "groundtruth.txt")
    truth = dict(zip(np.round(stamps, 4), poses))
    at = [round(float(r["timestamp"]), 4) for r in table]
    errors = {}
    for after in frames:
        before = after - length - 1
        assert table[after]["note"] != "dropped" and table[after]["lost"] == "0", table[after]
        assert all(table[i]["note"] == "dropped" for i in range(before + 1, after))
        moved = invert_pose(estimate[at[before]]) @ estimate[at[after]]
        true = invert_pose(truth[at[before]]) @ truth[at[after]]
        error = invert_pose(true) @ moved
        angle = np.degrees(np.arccos(np.clip((np.trace(error[:3, :3]) - 1) / 2, -1, 1)))
        errors[after] = (float(np.linalg.norm(error[:3, 3])), float(angle))
    return errors


def run_with_gaps(tmp_path, *overrides: str, every: int = 50, length: int = 20):
    out = tmp_path / "run"
    proc = run_slamkit(*overrides, "tracker=gicp", "keyframe=overlap", "mapper=none",
                       f"eval.forced_gap_every={every}", f"eval.forced_gap_length={length}", "output.progress=false",
                       "output.plot=false", f"hydra.run.dir={out}", cwd=tmp_path, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return out


def test_tracking_across_long_gaps_on_tum(tmp_path):
    """TUM fr1/rpy 0-149 with 20 frames dropped after every 50 (the camera turns 50-60 degrees
    in a gap): the frame after each gap is tracked, not lost, within 12 cm and 6 degrees of the
    ground truth's motion since the frame before the gap (measured 9.9 and 7.2 cm; without
    the matched-fraction check and the global registration, 41 cm and 84 cm)."""
    out = run_with_gaps(tmp_path, "dataset=tum", f"dataset.path={require_data(TUM)}")
    for after, (metres, degrees) in relative_errors(out, [70, 120]).items():
        assert metres < 0.12 and degrees < 6.0, (after, metres, degrees)


def test_tracking_across_long_gaps_on_7scenes(tmp_path):
    """7-Scenes redkitchen, frames 0-479 with 20 frames dropped after every 50: frame 120 (whose
    right pose matches 0.70 of its points, against 0.87 before the gap) is tracked, and frame
    470, whose capped prediction converges 15 cm off, trusted, is placed by a later start
    (coarse to fine); every frame after a gap but 170 within 5 cm and 2 degrees of the ground truth's
    motion (measured at most 2.4 cm; before, 120 was lost and 470 12 cm off; 170 ends 5.8 cm
    off, where G-ICP started from the right pose itself ends 4.5 cm off: docs/results.md)."""
    out = run_with_gaps(tmp_path, "dataset=sevenscenes", f"dataset.path={require_data(SEVENSCENES)}",
                        "dataset.max_frames=480")
    for after, (metres, degrees) in relative_errors(out, [70, 120, 220, 270, 320, 370, 420, 470]).items():
        assert metres < 0.05 and degrees < 2.0, (after, metres, degrees)


def test_a_pose_on_a_surface_the_map_holds_twice_is_not_kept_after_a_long_gap(tmp_path):
    """7-Scenes redkitchen, frames 0-100 with 30 dropped after 70: at frame 100 the start from the
    previous pose converges 37.5 cm off, matching 0.60 of the frame's points, onto a surface the
    map holds twice, where the right pose matches 0.54 (the camera turned to surface the map does
    not hold yet; below 0.7 x the last frame's 0.81, so matched points alone do not trust it).
    Judged from the map's side, the right pose has the map on the frame's depth in 0.95 of the
    cells and the wrong one in 0.65 (it sees through the map): global registration's alignment is
    trusted and kept, within 5 cm and 2 degrees of the ground truth's motion (measured 1.9 cm,
    0.8 degrees; before, 37.5 cm, and the schedule's ATE 13.9 against 8.5 cm now: docs/results.md)."""
    out = run_with_gaps(tmp_path, "dataset=sevenscenes", f"dataset.path={require_data(SEVENSCENES)}",
                        "dataset.max_frames=101", every=70, length=30)
    assert rows(out)[100]["fallback"] == "global registration", rows(out)[100]
    metres, degrees = relative_errors(out, [100], length=30)[100]
    assert metres < 0.05 and degrees < 2.0, (metres, degrees)


def test_global_registration_draws_again_after_a_long_gap(tmp_path):
    """TUM fr1/rpy 0-80 with 20 frames dropped after 60: at frame 80 no local start converges
    (the camera turned tens of degrees) and RANSAC's first draw registers the frame 178 degrees
    off, matching too few points to be trusted; the next draw (`tracker.relocalize_restarts`)
    finds it within 7.4 cm and 4.4 degrees of the ground truth's motion (its floor, the map's
    own drift there: 8.2 cm)."""
    path = require_data(TUM)
    out = tmp_path / "run"
    proc = run_slamkit("dataset=tum", f"dataset.path={path}", "dataset.max_frames=81", "tracker=gicp",
                       "keyframe=overlap", "mapper=none", "eval.forced_gap_every=60", "eval.forced_gap_length=20",
                       "output.progress=false", "output.plot=false", f"hydra.run.dir={out}", cwd=tmp_path, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert rows(out)[80]["fallback"] == "global registration", rows(out)[80]
    metres, degrees = relative_errors(out, [80])[80]
    assert metres < 0.09 and degrees < 6.0, (metres, degrees)
