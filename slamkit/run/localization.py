"""`slamkit mode=localize map=RUN_DIR dataset=... [dataset.start=N]`: tracking in a saved map.

The map (a run's checkpoint) is read once and never changed. The first frame's pose is found by
global registration of its points against the map's trackable Gaussian centres
(`slamkit.geometry.registration`: FPFH + RANSAC, then G-ICP); the run's tracker aligns each frame
from there. A frame is localised when the map explains it (`MapFit`): enough of its trackable
points lie on the map (`localize.min_inlier_fraction`), and the map lies on the frame's observed
surface (`localize.min_surface_agreement`) with correlated colours
(`localize.min_color_correlation`); the first alone is met by a frame of another scene aligned to
a wall. A frame not localised is registered again (up to `localize.attempts` RANSAC seeds), as is
every frame until one is; a run with no localised frame has failed (exit status 3). Outputs
(trajectory.txt, frames.csv, metrics.json) go to the run's own folder, written atomically also
when a signal or an error stops it: docs/checkpoints.md, "Localisation".
"""

from __future__ import annotations

import csv
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from slamkit.config import RunContext
from slamkit.errors import DataError, OutputError
from slamkit.formats.atomic import write_atomic
from slamkit.formats.checkpoint import checkpoint_path
from slamkit.formats.tum import write_tum_trajectory
from slamkit.geometry.registration import GlobalRegistration
from slamkit.geometry.surface import surface_cells
from slamkit.geometry.transforms import backproject
from slamkit.metrics import trajectory as evaluation
from slamkit.native import available_threads
from slamkit.registry.discovery import Registry
from slamkit.registry.schema import RunConfig
from slamkit.run import checkpoint
from slamkit.run.lifecycle import Phase, StopSignals, pause_point
from slamkit.run.ownership import check_localization_folder
from slamkit.run.prefetch import prefetched
from slamkit.run.state import COMPLETED, FAILED, INTERRUPTED
from slamkit.types import Camera, Frame, TrackingResult

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
    fit: MapFit
    tracking_s: float
    registration_s: float


def inlier_fraction(result: TrackingResult) -> float | None:
    """The fraction of the frame's trackable points with a map Gaussian within the tracker's
    correspondence distance (None when the tracker reports no per-point distances)."""
    g = result.gaussians
    if g is None or g.sq_dist_to_map is None:
        return None
    trackable = np.asarray(g.trackable, dtype=bool)
    return float(np.isfinite(np.asarray(g.sq_dist_to_map)[trackable]).mean()) if trackable.any() else 0.0


@dataclass
class MapFit:
    """How well the map seen from a pose explains a frame. surface_agreement: of the image cells
    where a map centre projects onto valid depth, the fraction whose nearest such centre lies on
    the observed surface (`slamkit.geometry.surface`): a frame placed wrongly, or in another
    scene, sees map centres in front of or behind its surface, and centres hidden behind others
    do not count against it (only each cell's nearest is compared).
    color_correlation: over the cells that agree, the correlation of the map centres' luminance
    with the frame's at their pixels (gain and offset do not matter, so exposure does not): a
    pose that puts the map's shapes on the frame's but not its appearance scores near 0. Each is
    None when there is nothing to judge (no centre on valid depth; fewer than MIN_COLOR_CELLS
    agreeing cells or a frame without contrast there)."""

    surface_agreement: float | None
    color_correlation: float | None


#: Agreeing cells needed to judge colour, and the luminance spread (std, in [0, 1]) below which
#: a view has no contrast to compare.
MIN_COLOR_CELLS, MIN_LUMINANCE_STD = 20, 0.02
#: Rec. 601 luma weights of R, G, B.
LUMA = np.array([0.299, 0.587, 0.114])


def map_fit(frame: Frame, pose: np.ndarray, centres: np.ndarray, colors: np.ndarray) -> MapFit:
    """`MapFit` of the map's centres ((N,3) world metres) and colours ((N,3) RGB in [0, 1]) seen
    from `pose` (camera-to-world) by the frame's camera."""
    cells = surface_cells(centres, frame.depth, frame.camera, pose)
    if cells.agreement is None:
        return MapFit(None, None)
    on = cells.on
    if on.sum() < MIN_COLOR_CELLS:
        return MapFit(cells.agreement, None)
    pixels = np.asarray(frame.rgb[cells.row[on], cells.col[on]], dtype=np.float64) / 255.0
    seen_luma, map_luma = pixels @ LUMA, np.clip(colors[cells.index[on]], 0.0, 1.0) @ LUMA
    if seen_luma.std() < MIN_LUMINANCE_STD or map_luma.std() < MIN_LUMINANCE_STD:
        return MapFit(cells.agreement, None)
    return MapFit(cells.agreement, float(np.corrcoef(seen_luma, map_luma)[0, 1]))


@dataclass
class Verdict:
    """A tracking result and the figures that say whether it localises the frame."""

    result: TrackingResult
    inlier_fraction: float | None
    fit: MapFit
    localized: bool


class Localizer:
    """Tracks frames in a fixed map, registering globally where the pose is unknown or lost.
    `best`: the highest of each figure any frame reached (inlier_fraction, surface_agreement,
    color_correlation)."""

    def __init__(self, cfg: RunConfig, tracker, gaussian_map):
        self.cfg, self.tracker, self.map = cfg.localize, tracker, gaussian_map
        tracker.update_target(gaussian_map)
        target = gaussian_map.tracking_target(0.0, "entry")
        if len(target.means) == 0:
            raise DataError(f"map {cfg.map}: no trackable Gaussian to localise against")
        rows = gaussian_map.rows()
        trackable = rows.trackable.numpy()
        self.centres = rows.entry_means.numpy()[trackable].astype(np.float64)  # what the tracker aligns to
        self.colors = rows.colors.numpy()[trackable]
        self.registration = GlobalRegistration(target.means, self.cfg.voxel, self.cfg.ransac_iterations,
                                               self.cfg.ransac_confidence)
        self.lost = True  # no pose yet
        self.relocalizations = 0
        self.best: dict[str, float] = {}

    def judge(self, frame: Frame, result: TrackingResult) -> Verdict:
        """Whether `result` localises `frame` (see the module docstring)."""
        fraction = inlier_fraction(result)
        fit = MapFit(None, None) if result.lost else map_fit(frame, result.pose, self.centres, self.colors)
        figures = {"inlier_fraction": fraction, "surface_agreement": fit.surface_agreement,
                   "color_correlation": fit.color_correlation}
        for name, value in figures.items():
            if value is not None:
                self.best[name] = max(value, self.best.get(name, -np.inf))
        c = self.cfg
        ok = (not result.lost and (fraction is None or fraction >= c.min_inlier_fraction)
              and fit.surface_agreement is not None and fit.surface_agreement >= c.min_surface_agreement
              and (fit.color_correlation is None or fit.color_correlation >= c.min_color_correlation))
        return Verdict(result, fraction, fit, ok)

    def step(self, frame: Frame) -> LocalizedFrame:
        start = time.perf_counter()
        registration_s, relocalized = 0.0, False
        verdict = None if self.lost else self.judge(frame, self.tracker.track(frame))
        if verdict is None or not verdict.localized:
            t0 = time.perf_counter()
            verdict = self.relocalize(frame) or verdict
            registration_s, relocalized = time.perf_counter() - t0, True
        ok = verdict is not None and verdict.localized
        self.lost = not ok
        pose = verdict.result.pose if verdict is not None else np.full((4, 4), np.nan)
        return LocalizedFrame(frame.index, frame.timestamp, pose, frame.gt_pose, ok, relocalized,
                              None if verdict is None else verdict.inlier_fraction,
                              MapFit(None, None) if verdict is None else verdict.fit,
                              time.perf_counter() - start - registration_s, registration_s)

    def relocalize(self, frame: Frame) -> Verdict | None:
        """Register `frame` globally (one RANSAC seed per attempt) and track it from there; the
        first localised result, else the one whose map agrees best with the frame (None without
        depth)."""
        depth = np.nan_to_num(np.asarray(frame.depth, dtype=np.float32))
        points, _ = backproject(np.where(depth <= frame.depth_trunc, depth, 0), frame.camera,
                                REGISTRATION_PIXEL_STRIDE)
        if len(points) < 3:
            return None
        best = None
        for attempt in range(self.cfg.attempts):
            self.relocalizations += 1
            found = self.registration.register(points, seed=attempt)
            self.tracker.initialize(found.pose)
            verdict = self.judge(frame, self.tracker.track(frame))
            if verdict.localized:
                return verdict
            if best is None or (verdict.fit.surface_agreement or -1.0) > (best.fit.surface_agreement or -1.0):
                best = verdict
        return best

    def failure(self, frames: int, map_source: str, scene_note: str) -> str:
        """Why no frame of `frames` was localised, in one line."""
        def figure(name: str) -> str:
            value = self.best.get(name)
            least = getattr(self.cfg, f"min_{name}")
            return f"{name.replace('_', ' ')} {'none' if value is None else f'{value:.2f}'} (needs {least:g})"

        figures = ", ".join(figure(n) for n in ("inlier_fraction", "surface_agreement", "color_correlation"))
        return (f"localisation failed: no frame was localised in the map {map_source} ({frames} frames; best "
                f"{figures}){scene_note}")


def scene_note(saved: dict[str, Any], camera: Camera, dataset_name: str) -> str:
    """'; the map was made with ...' when the map's camera or dataset plugin is not the run's
    (logged as a warning), else ''."""
    made = saved.get("camera") or {}
    keys = ("width", "height", "fx", "fy", "cx", "cy")
    same_camera = all(np.isclose(float(made.get(k, np.nan)), float(getattr(camera, k)), rtol=1e-6) for k in keys)
    map_dataset = (saved.get("plugins") or {}).get("dataset")
    if same_camera and map_dataset in (None, dataset_name):
        return ""

    def text(c) -> str:
        return f"{int(c['width'])}x{int(c['height'])} fx {float(c['fx']):g}"

    note = (f"; the map was made with dataset={map_dataset}, camera {text(made) if made else '?'}, this run has "
            f"dataset={dataset_name}, camera {text({k: getattr(camera, k) for k in keys})}")
    log.warning("localising in a map made with another %s%s", "dataset" if same_camera else "camera", note)
    return note


def run(cfg: RunConfig, registry: Registry, names: dict[str, str], out_dir: Path,
        stop: StopSignals | None = None) -> dict[str, Any]:
    """Localise the dataset's frames in `cfg.map`; write the outputs into `out_dir` and
    return the metrics (`status`: completed; failed when no frame was localised; or interrupted:
    a signal stops it between two frames, `slamkit.run.lifecycle.StopSignals`, and it writes what
    it has)."""
    stop = stop or StopSignals()
    with stop.installed():
        return _run(cfg, registry, names, out_dir, stop)


def _run(cfg: RunConfig, registry: Registry, names: dict[str, str], out_dir: Path, stop: StopSignals) -> dict[str, Any]:
    check_localization_folder(out_dir, cfg.map)  # never into the map's run folder
    out_dir.mkdir(parents=True, exist_ok=True)
    gaussian_map, saved = checkpoint.load_map(cfg.map)
    dataset = registry.create("dataset", names["dataset"], cfg.dataset)
    if len(dataset) == 0:
        raise DataError(f"dataset {names['dataset']!r} at {cfg.dataset.path!r}: no frames selected")
    note = scene_note(saved, dataset.camera, names["dataset"])
    context = RunContext(tuning=dataset.tuning, tracking_threads=available_threads(), device=str(gaussian_map.device),
                         gaussian_map=gaussian_map)
    tracker = registry.create("tracker", names["tracker"], cfg.tracker, context)
    start = time.perf_counter()
    localizer = Localizer(cfg, tracker, gaussian_map)
    setup_s = time.perf_counter() - start
    log.info("localising %d frames in %s (%d Gaussians, features in %.1f s)", len(dataset),
             checkpoint_path(cfg.map), len(gaussian_map), setup_s)
    frames: list[LocalizedFrame] = []
    status, error = COMPLETED, None
    try:
        stop.enter(Phase.stream)
        with open(out_dir / "frames.csv", "w", newline="") as log_file:
            writer = csv.writer(log_file)
            writer.writerow(["index", "timestamp", "localized", "relocalized", "inlier_fraction",
                             "surface_agreement", "color_correlation", "tracking_ms", "registration_ms"])
            for frame in prefetched(dataset, cfg.dataset.prefetch):
                stop.check()
                done = localizer.step(frame)
                frames.append(done)
                writer.writerow([done.index, f"{done.timestamp:.6f}", int(done.localized), int(done.relocalized),
                                 "" if done.inlier_fraction is None else f"{done.inlier_fraction:.4f}",
                                 *("" if v is None else f"{v:.4f}" for v in (done.fit.surface_agreement,
                                                                                done.fit.color_correlation)),
                                 f"{1e3 * done.tracking_s:.2f}", f"{1e3 * done.registration_s:.2f}"])
                pause_point(f"stream@{len(frames)}", stop)
        stop.check()
        if frames and not any(f.localized for f in frames):  # an answer is not a result
            status, error = FAILED, localizer.failure(len(frames), str(checkpoint_path(cfg.map)), note)
            log.error("%s", error)
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
                               str(checkpoint_path(cfg.map)), len(gaussian_map), status, error)
            metrics["map_made_with"] = {"dataset": (saved.get("plugins") or {}).get("dataset"),
                                        "camera": saved.get("camera")}
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
        **{f"best_{name}": value for name, value in localizer.best.items()},
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
    if m["completed"]:
        return text
    return text + (f" (failed: {m['error']})" if m.get("status") == FAILED else f" (incomplete: {m['error']})")
