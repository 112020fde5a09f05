"""`slamkit mode=localize map=RUN_DIR dataset=... [dataset.start=N]`: tracking in a saved map.

The map (a run's checkpoint, `slamkit.run.checkpoint`) is read once and never changed: no
Gaussian is added or trained. The run's tracker aligns each frame to the map's trackable
Gaussians (its target is taken once). The first frame's pose is unknown: it is found by global
registration of the frame's points against the map's trackable Gaussian centres
(`slamkit.geometry.registration`: FPFH + RANSAC, then G-ICP), from which the tracker aligns the
frame; a frame is localised when at least `localize.min_inlier_fraction` of its trackable points
have a map Gaussian within the tracker's correspondence distance. When a frame is not, it is
registered globally again (up to `localize.attempts` RANSAC seeds), as is every frame until one
is. Outputs in the run folder: trajectory.txt (the localised frames' poses, TUM format),
frames.csv (per frame: localised, relocalised, inlier fraction, times),
metrics.json (localised frames, relocalisations, ATE over the localised frames SE(3)-aligned
and in the map's own frame, frames/s, `status`); trajectory.txt and metrics.json are written
atomically, also when a signal (SIGINT, SIGTERM: between two frames) or an error stops the run.
"""

from __future__ import annotations

import csv
import json
import logging
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from slamkit.errors import DataError, OutputError
from slamkit.formats.atomic import write_atomic
from slamkit.formats.checkpoint import checkpoint_path
from slamkit.formats.tum import write_tum_trajectory
from slamkit.geometry.registration import GlobalRegistration
from slamkit.geometry.transforms import backproject
from slamkit.metrics import trajectory as evaluation
from slamkit.native import available_threads
from slamkit.registry.discovery import Registry
from slamkit.registry.schema import RunConfig
from slamkit.run import checkpoint
from slamkit.run.prefetch import prefetched
from slamkit.run.lifecycle import Phase, StopSignals, pause_point
from slamkit.run.ownership import check_localization_folder
from slamkit.run.state import COMPLETED, FAILED, INTERRUPTED
from slamkit.types import Frame, TrackingResult

log = logging.getLogger(__name__)

#: Pixel stride of the frame points given to global registration (they are voxel-downsampled).
REGISTRATION_PIXEL_STRIDE = 4


@dataclass
class LocalizedFrame:
    """One frame's outcome: its pose (camera-to-world), whether it was localised and relocalised
    (globally registered), its inlier fraction, and times in seconds."""

    index: int
    timestamp: float
    pose: np.ndarray
    gt_pose: np.ndarray | None
    localized: bool
    relocalized: bool
    inlier_fraction: float | None
    tracking_s: float
    registration_s: float


def localize_arguments(argv: list[str]) -> list[str]:
    """`map=RUN_DIR` on the command line is `localize.map=RUN_DIR` (`map.` keys are the map
    growth settings)."""
    return [re.sub(r"^map=", "localize.map=", a) for a in argv]


def inlier_fraction(result: TrackingResult) -> float | None:
    """The fraction of the frame's trackable points with a map Gaussian within the tracker's
    correspondence distance (None when the tracker reports no per-point distances)."""
    g = result.gaussians
    if g is None or g.sq_dist_to_map is None:
        return None
    trackable = np.asarray(g.trackable, dtype=bool)
    return float(np.isfinite(np.asarray(g.sq_dist_to_map)[trackable]).mean()) if trackable.any() else 0.0


class Localizer:
    """Tracks frames in a fixed map, registering globally where the pose is unknown or lost."""

    def __init__(self, cfg: RunConfig, tracker, gaussian_map):
        self.cfg, self.tracker, self.map = cfg.localize, tracker, gaussian_map
        tracker.update_target(gaussian_map)
        target = gaussian_map.tracking_target(0.0, "entry")
        if len(target.means) == 0:
            raise DataError(f"map {cfg.localize.map}: no trackable Gaussian to localise against")
        self.registration = GlobalRegistration(target.means, self.cfg.voxel, self.cfg.ransac_iterations,
                                               self.cfg.ransac_confidence)
        self.lost = True  # no pose yet
        self.relocalizations = 0

    def localized(self, result: TrackingResult) -> bool:
        fraction = inlier_fraction(result)
        return not result.lost and (fraction is None or fraction >= self.cfg.min_inlier_fraction)

    def step(self, frame: Frame) -> LocalizedFrame:
        start = time.perf_counter()
        registration_s, relocalized = 0.0, False
        result = None if self.lost else self.tracker.track(frame, self.map)
        if result is None or not self.localized(result):
            t0 = time.perf_counter()
            result = self.relocalize(frame) or result
            registration_s, relocalized = time.perf_counter() - t0, True
        ok = result is not None and self.localized(result)
        self.lost = not ok
        pose = result.pose if result is not None else np.full((4, 4), np.nan)
        return LocalizedFrame(frame.index, frame.timestamp, pose, frame.gt_pose, ok, relocalized,
                              None if result is None else inlier_fraction(result),
                              time.perf_counter() - start - registration_s, registration_s)

    def relocalize(self, frame: Frame) -> TrackingResult | None:
        """Register `frame` globally (one RANSAC seed per attempt) and track it from there; the
        first localised result, else the best one (None without depth)."""
        depth = np.nan_to_num(np.asarray(frame.depth, dtype=np.float32))
        points, _ = backproject(np.where(depth <= frame.depth_trunc, depth, 0), frame.camera,
                                REGISTRATION_PIXEL_STRIDE)
        if len(points) < 3:
            return None
        best, best_fraction = None, -1.0
        for attempt in range(self.cfg.attempts):
            self.relocalizations += 1
            found = self.registration.register(points, seed=attempt)
            self.tracker.initialize(found.pose)
            result = self.tracker.track(frame, self.map)
            fraction = inlier_fraction(result)
            if self.localized(result):
                return result
            if fraction is not None and fraction > best_fraction:
                best, best_fraction = result, fraction
        return best


def run(cfg: RunConfig, registry: Registry, names: dict[str, str], out_dir: Path,
        stop: StopSignals | None = None) -> dict[str, Any]:
    """Localise the dataset's frames in `cfg.localize.map`; write the outputs into `out_dir` and
    return the metrics (`status`: completed, or interrupted: SIGINT and SIGTERM stop it between
    two frames, `slamkit.run.lifecycle.StopSignals`, and it writes what it has)."""
    stop = stop or StopSignals()
    with stop.installed():
        return _run(cfg, registry, names, out_dir, stop)


def _run(cfg: RunConfig, registry: Registry, names: dict[str, str], out_dir: Path, stop: StopSignals) -> dict[str, Any]:
    check_localization_folder(out_dir, cfg.localize.map)  # never into the map's run folder
    out_dir.mkdir(parents=True, exist_ok=True)
    gaussian_map, saved = checkpoint.load_map(cfg.localize.map)
    dataset = registry.create("dataset", names["dataset"], cfg.dataset)
    if len(dataset) == 0:
        raise DataError(f"dataset {names['dataset']!r} at {cfg.dataset.path!r}: no frames selected")
    tracker = registry.create("tracker", names["tracker"], cfg.tracker, dataset.sensor)
    tracker.use_threads(available_threads())
    start = time.perf_counter()
    localizer = Localizer(cfg, tracker, gaussian_map)
    setup_s = time.perf_counter() - start
    log.info("localising %d frames in %s (%d Gaussians, features in %.1f s)", len(dataset),
             checkpoint_path(cfg.localize.map), len(gaussian_map), setup_s)
    frames: list[LocalizedFrame] = []
    status, error = COMPLETED, None
    try:
        stop.enter(Phase.stream)
        with open(out_dir / "frames.csv", "w", newline="") as log_file:
            writer = csv.writer(log_file)
            writer.writerow(["index", "timestamp", "localized", "relocalized", "inlier_fraction", "tracking_ms",
                             "registration_ms"])
            for frame in prefetched(dataset, cfg.dataset.prefetch):
                stop.check()
                done = localizer.step(frame)
                frames.append(done)
                writer.writerow([done.index, f"{done.timestamp:.6f}", int(done.localized), int(done.relocalized),
                                 "" if done.inlier_fraction is None else f"{done.inlier_fraction:.4f}",
                                 f"{1e3 * done.tracking_s:.2f}", f"{1e3 * done.registration_s:.2f}"])
                pause_point(f"stream@{len(frames)}", stop)
        stop.check()
    except KeyboardInterrupt as exc:
        status, error = INTERRUPTED, f"interrupted ({str(exc) or 'SIGINT'}) during {stop.phase.value}"
        log.warning("localisation interrupted after %d frames; writing what it has", len(frames))
    except Exception as exc:
        status, error = FAILED, f"{type(exc).__name__}: {exc}"
        log.error("localisation failed after %d frames: %s; writing what it has", len(frames), error)
        if isinstance(exc, OSError):  # the environment (a full disk): exit status 1, naming the file
            raise OutputError(f"localisation stopped: {exc.filename or out_dir}: {exc.strerror or exc}") from exc
        raise
    finally:
        with stop.writing():
            metrics = _metrics(frames, localizer, time.perf_counter() - start, setup_s,
                               str(checkpoint_path(cfg.localize.map)), len(gaussian_map), status, error)
            try:
                _write(out_dir, frames, metrics)
            except OSError as exc:  # a full disk: exit status 1, naming the file
                raise OutputError(f"could not write {exc.filename or out_dir}: {exc.strerror or exc}") from exc
    return metrics


def _metrics(frames: list[LocalizedFrame], localizer: Localizer, wall_s: float, setup_s: float, map_path: str,
             map_gaussians: int, status: str, error: str | None) -> dict[str, Any]:
    n = len(frames)
    ok = np.array([f.localized for f in frames], dtype=bool)
    poses = np.array([f.pose if f.localized else np.full((4, 4), np.nan) for f in frames]).reshape(n, 4, 4)
    gt = [f.gt_pose for f in frames]
    aligned = evaluation.ate(poses, gt) if n else None
    in_map = evaluation.ate(poses, gt, align="none") if n else None
    tracking_s = sum(f.tracking_s for f in frames)
    return {
        "mode": "localize", "map": map_path, "map_gaussians": map_gaussians, "num_frames": n,
        "localized_frames": int(ok.sum()), "success_rate": float(ok.mean()) if n else None,
        "first_localized_index": int(frames[np.flatnonzero(ok)[0]].index) if ok.any() else None,
        "relocalizations": localizer.relocalizations,
        "registration_time_s": sum(f.registration_s for f in frames), "tracking_time_s": tracking_s,
        "map_features_time_s": setup_s, "wall_time_s": wall_s,
        "fps": n / wall_s if wall_s > 0 else None, "tracking_fps": n / tracking_s if tracking_s > 0 else None,
        "ate_rmse_m": aligned.rmse_m if aligned else None, "ate_mean_m": aligned.mean_m if aligned else None,
        "ate_frames": aligned.num if aligned else 0,
        "map_frame_rmse_m": in_map.rmse_m if in_map else None,
        "completed": status == COMPLETED, "status": status, "error": error,
    }


def _write(out_dir: Path, frames: list[LocalizedFrame], metrics: dict[str, Any]) -> None:
    done = [f for f in frames if f.localized]
    write_tum_trajectory(out_dir / "trajectory.txt", [f.timestamp for f in done],
                         np.array([f.pose for f in done]).reshape(-1, 4, 4))
    write_atomic(out_dir / "metrics.json", json.dumps(metrics, indent=2, default=float) + "\n")
    log.info("%s", summary(metrics))


def summary(m: dict[str, Any]) -> str:
    """One line for the terminal (and why the run stopped early)."""
    ate = "n/a" if m["ate_rmse_m"] is None else f"{100 * m['ate_rmse_m']:.2f} cm"
    fps = "n/a" if not m["fps"] else f"{m['fps']:.1f}"
    text = (f"localised {m['localized_frames']}/{m['num_frames']} frames, ATE RMSE {ate} over them, {fps} frames/s, "
            f"{m['relocalizations']} global registrations")
    return text if m["completed"] else text + f" (incomplete: {m['error']})"
