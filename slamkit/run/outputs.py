"""The run's output files (`RunOutputs`), from what it has produced so far (`slamkit.run.state`)
and its metrics (`slamkit.run.metrics`), each written atomically as soon as what it holds is
known, in the order of their value: camera.json at start-up; trajectory.txt, keyframes.txt,
groundtruth.txt, with a loop closure loops.csv and pose_graph.g2o, the tracking metrics
(metrics.json) and trajectory.png when the stream ends; the
map (the mapper's `save_map`, map.ply) and the checkpoint (checkpoint.zip) after the refinement,
or as the run stops early; the evaluation merged into metrics.json last.

A file that cannot be written (a full disk) is logged and noted (`RunOutputs.unwritten`), and the
others are still tried: metrics.json is small and is written where space allows."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from slamkit.formats.atomic import write_atomic
from slamkit.formats.checkpoint import CHECKPOINT_NAME
from slamkit.formats.g2o import to_g2o
from slamkit.formats.loops import GROUND_TRUTH_COLUMNS, with_ground_truth, write_loops_csv
from slamkit.formats.tum import write_tum_trajectory
from slamkit.metrics import trajectory as evaluation
from slamkit.registry.schema import RunConfig
from slamkit.run.checkpoint import CheckpointWriter
from slamkit.run.lifecycle import Phase, StopSignals
from slamkit.run.loop_closing import LOOPS_COLUMNS
from slamkit.run.metrics import headline, run_metrics
from slamkit.run.slam import SLAM
from slamkit.run.state import FAILED, RUNNING, RunState

log = logging.getLogger(__name__)


def write_camera(path: Path, camera, depth_trunc: float) -> None:
    """The run's camera as JSON: width, height (pixels), fx, fy, cx, cy (pixels) and
    depth_trunc (metres, null = none), for tools that render the map later (slamkit-export)."""
    data = {"width": camera.width, "height": camera.height, "fx": camera.fx, "fy": camera.fy, "cx": camera.cx,
            "cy": camera.cy, "depth_trunc": depth_trunc if np.isfinite(depth_trunc) else None}
    _write_json_atomic(path, data)


class RunOutputs:
    """The files of one run in `out_dir` (see the module docstring). `kept` lists the files
    written, `unwritten` the ones that could not be (name -> why). With `checkpoints`, the map's
    save also writes the run's checkpoint (`slamkit.run.checkpoint`); `stop` says whether a
    signal cut a step in half (then no checkpoint is written from that state)."""

    def __init__(self, cfg: RunConfig, slam: SLAM, state: RunState, out_dir: Path,
                 checkpoints: CheckpointWriter | None = None, stop: StopSignals | None = None):
        self.cfg, self.slam, self.state, self.out_dir = cfg, slam, state, out_dir
        self.checkpoints, self.stop = checkpoints, stop
        self.kept: list[str] = []
        self.unwritten: dict[str, str] = {}
        self.start = time.perf_counter()  # the first frame's
        self.trajectory_saved = self.map_saved = False

    def keep(self, name: str, write: Callable[[], Any]) -> bool:
        """Run `write` (which writes `name`). An OSError (a full disk, a read-only folder) is
        logged and noted in `unwritten`; it is raised while the run is going (the run stops
        and keeps what it can), not once it is stopping (the other files are still tried)."""
        try:
            write()
        except OSError as exc:
            self._unwritten(name, exc)
            if self.state.status == RUNNING:
                raise
            return False
        if name not in self.kept:
            self.kept.append(name)
        return True

    def save_camera(self, camera, depth_trunc: float) -> None:
        self.keep("camera.json", lambda: write_camera(self.out_dir / "camera.json", camera, depth_trunc))

    def save_trajectory(self) -> None:
        """When the stream ends: trajectory.txt, keyframes.txt, groundtruth.txt, the tracking
        metrics (metrics.json) and trajectory.png."""
        state, out = self.state, self.out_dir
        self.trajectory_saved = True
        poses = state.trajectory()
        self.keep("trajectory.txt", lambda: write_tum_trajectory(out / "trajectory.txt", state.timestamps, poses))
        rows = state.keyframe_rows
        self.keep("keyframes.txt", lambda: write_tum_trajectory(
            out / "keyframes.txt", [state.timestamps[i] for i in rows], poses[rows].reshape(-1, 4, 4)))
        has_gt = [i for i, p in enumerate(state.gt_poses) if p is not None and np.all(np.isfinite(p))]
        if has_gt:  # beside the estimate, for evo and slamkit-report
            self.keep("groundtruth.txt", lambda: write_tum_trajectory(
                out / "groundtruth.txt", [state.timestamps[i] for i in has_gt],
                np.array([state.gt_poses[i] for i in has_gt])))
        self.save_loops()
        metrics = self.save_metrics()
        if self.cfg.output.plot and len(poses):
            self.keep("trajectory.png", lambda: self._plot(poses, metrics))

    def save_loops(self) -> None:
        """With a loop closure: loops.csv (every candidate verified, `slamkit.formats.loops`) and
        pose_graph.g2o (the pose graph as it stands, `slamkit.formats.g2o`)."""
        closer, out = self.slam.loop_closer, self.out_dir
        if not closer.active:
            return
        self.keep("loops.csv", lambda: write_loops_csv(out / "loops.csv", (*LOOPS_COLUMNS, *GROUND_TRUTH_COLUMNS),
                                                       [with_ground_truth(r, *self._keyframe_truth(r))
                                                        for r in closer.rows()]))
        self.keep("pose_graph.g2o", lambda: write_atomic(out / "pose_graph.g2o", to_g2o(closer.pose_graph())))

    def _keyframe_truth(self, row: dict) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The ground-truth poses of a loops.csv row's keyframe and match (None where unknown):
        keyframe ids count the run's keyframes, `keyframe_rows` holds their trajectory rows."""
        rows, gt = self.state.keyframe_rows, self.state.gt_poses
        return tuple(gt[rows[k]] if 0 <= k < len(rows) and rows[k] < len(gt) else None
                     for k in (int(row["keyframe"]), int(row["match_keyframe"])))

    def save_map(self) -> None:
        """The map trained so far (the mapper's `save_map`: map.ply), once the mapper has stopped
        changing it, then the checkpoint: the run's one place for what it keeps of its map. A run
        already stopping (interrupted twice, failed) logs a map it cannot write instead of raising."""
        self.map_saved = True
        self._save_map_ply()
        self._save_checkpoint()

    def _save_map_ply(self) -> None:
        try:
            written = self.slam.save_map(self.out_dir)
        except OSError as exc:
            self._unwritten(Path(exc.filename).name if exc.filename else "map.ply", exc)
            if self.state.status == RUNNING:
                raise
            return
        except Exception as exc:
            if self.state.status == RUNNING:
                raise
            log.error("the map could not be written: %s: %s", type(exc).__name__, exc)
            return
        self.kept += [Path(p).name for p in written]

    def _save_checkpoint(self) -> None:
        """checkpoint.zip: `end` after the refinement, `interrupted` when a signal stopped the run
        at a safe point, `failed` when a plugin failed after the stream (its frames were all
        tracked: the run can be resumed, or its map localised in). None when tracking failed or a
        plugin failed during the stream, nor from a state a second signal cut in half (the last
        checkpoint written, every N keyframes, stays)."""
        status = self.state.status
        after_stream = self.state.phase not in (Phase.startup, Phase.stream)  # tracking failures end the stream
        if self.checkpoints is None or (status == FAILED and not after_stream):
            return
        if self.stop is not None and self.stop.cut_short:
            log.warning("no checkpoint from this state: a second signal stopped the run in the middle of a step")
            return
        reason = {RUNNING: "end", FAILED: "failed"}.get(status, "interrupted")
        try:
            path = self.checkpoints.save(reason)
        except OSError as exc:
            self._unwritten(Path(exc.filename).name if exc.filename else CHECKPOINT_NAME, exc)
            if status == RUNNING:
                raise
            return
        except Exception as exc:  # a failed run's plugin that cannot give its state either
            if status != FAILED:
                raise
            log.error("no checkpoint from this failed run: %s: %s", type(exc).__name__, exc)
            return
        if path is not None and path.name not in self.kept:
            self.kept.append(path.name)

    def save_metrics(self) -> dict[str, Any]:
        """metrics.json as the run stands; returns the metrics."""
        metrics = run_metrics(self.cfg, self.slam, self.state, time.perf_counter() - self.start)
        metrics.update(self.slam.loop_closer.metrics())
        self.keep("metrics.json", lambda: _write_json_atomic(self.out_dir / "metrics.json", metrics))
        return metrics

    def save_all(self) -> dict[str, Any]:
        """What the run has not written yet (its trajectory, its map), then metrics.json as it
        ends; returns the metrics."""
        if not self.trajectory_saved:
            self.save_trajectory()
        if not self.map_saved:
            self.save_map()
        return self.save_metrics()

    def _unwritten(self, name: str, exc: OSError) -> None:
        self.unwritten[name] = exc.strerror or str(exc)
        log.error("could not write %s: %s", self.out_dir / name, self.unwritten[name])

    def _plot(self, poses: np.ndarray, metrics: dict[str, Any]) -> None:
        from slamkit.formats.plots import plot_trajectory

        ate = evaluation.ate(poses, self.state.gt_poses)
        has_gt = ate.rmse_m is not None
        plot_trajectory(self.out_dir / "trajectory.png", ate.est_aligned if has_gt else poses[:, :3, 3],
                        ate.gt_positions if has_gt else None, title=headline(metrics, stream_rate=True),
                        loops=self._closed_loops())

    def _closed_loops(self) -> list[tuple[int, int]]:
        """The loops closed so far as pairs of trajectory rows (loops.csv's accepted keyframes;
        a keyframe's id is its place among the run's keyframes)."""
        closer, rows = self.slam.loop_closer, self.state.keyframe_rows
        if not closer.active:
            return []
        pairs = [(int(r["keyframe"]), int(r["match_keyframe"])) for r in closer.rows() if r["accepted"]]
        return [(rows[a], rows[b]) for a, b in pairs if 0 <= a < len(rows) and 0 <= b < len(rows)]


def _write_json_atomic(path: Path, data: dict) -> None:
    write_atomic(path, json.dumps(data, indent=2, default=float) + "\n")
