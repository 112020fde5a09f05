"""Maps that outlive a run: what a run's checkpoint holds, writing it, and continuing from it.

A checkpoint (`RUN_DIR/checkpoint.zip`, the file format is `slamkit.formats.checkpoint`) holds

- `map`: every row of the shared GaussianMap (the 3DGS parameters, the trackable flags, the
  keyframe of origin and the entry geometry the tracker aligns to), and its version;
- `slam`: the keyframe count and the last pose; `tracker`, `keyframe`, `mapper`: each role's
  `state_dict()` (G-ICP: its target and motion model; the 3DGS mapper: its keyframes with their
  training images, the optimiser's moments, the strategy's statistics, the sampler's random state);
- `run`: the trajectory so far (timestamps, poses, ground truth), keyframe rows and counters,
  and what its sessions measured of themselves in all (`sessions`: count, CPU seconds, peak
  memory; `slamkit.run.state.EarlierSessions`);
- in meta.json: the resolved config, the command-line overrides and plugins of the run, the
  camera, the dataset selection, the last frame index and why it was written (`end`,
  `keyframes`, `interrupted`).

`CheckpointWriter` writes it every `checkpoint.every_keyframes` keyframes during the stream
(`slamkit.run.pipeline`), and where the run saves its map (`RunOutputs.save_map`): after the
refinement, and when a signal stops the run at a safe point; `restore` puts a run back where
its checkpoint left it (`slamkit resume=RUN_DIR`, see `resume_arguments`), once it has checked
that the dataset's frames up to there are the checkpoint's (their timestamps: a frame list that
changed would otherwise shift every frame after the change without a word); `finished` says when
there is nothing to resume (the run completed every frame: its files stay as they are);
`load_map` reads the map alone (`mode=localize`, slamkit-export).
"""

from __future__ import annotations

import dataclasses
import enum
import json
import logging
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np
import torch

from slamkit.formats.checkpoint import (
    CHECKPOINT_NAME,
    CheckpointError,
    checkpoint_path,
    read_checkpoint,
    read_meta,
    write_checkpoint,
)
from slamkit.map.gaussian_map import ROW_WIDTHS, GaussianMap
from slamkit.run.metrics import peak_memory_mb
from slamkit.run.state import SESSION_FIGURES, EarlierSessions
from slamkit.types import Camera

log = logging.getLogger(__name__)

#: RunState's counters kept in a checkpoint.
RUN_COUNTERS = ("num_keyframes", "lost_frames", "dropped_frames", "mapping_iterations", "tracking_time_s",
                "mapping_time_s", "stream_time_s", "refine_iterations", "refine_time_s")
#: The dataset settings a resumed run must share with the run it continues.
SAME_SELECTION = ("path", "start", "stride", "passes")
#: Seconds two timestamps of one frame may differ by (the checkpoint's and the dataset's).
TIMESTAMP_TOLERANCE_S = 1e-6


class CheckpointWriter:
    """Writes the run's checkpoint (atomically) at the points the pipeline calls it at."""

    def __init__(self, cfg, names: dict[str, str], slam, state, dataset, out_dir: Path):
        self.cfg, self.names, self.slam, self.state, self.dataset = cfg, names, slam, state, dataset
        self.path = Path(out_dir) / CHECKPOINT_NAME
        self.overrides = _hydra_overrides(Path(out_dir))
        self.started = time.perf_counter()
        self.saved_keyframes = slam.num_keyframes

    def after_frame(self, flush_logs: Callable[[], None] = lambda: None) -> None:
        """Every `checkpoint.every_keyframes` keyframes (0: never); `flush_logs` first, so that
        the logs on disk reach the frame the checkpoint does (a resumed run logs from there)."""
        every = self.cfg.checkpoint.every_keyframes
        if every and self.slam.num_keyframes - self.saved_keyframes >= every:
            flush_logs()
            self.save("keyframes")

    def save(self, reason: str) -> Path | None:
        """Write the checkpoint now (`reason`: end | keyframes | interrupted | failed); None when
        it was not asked for (end, keyframes: `checkpoint.save`, `every_keyframes` or a checkpoint
        already there; interrupted, failed: those or `on_interrupt`) or nothing was tracked yet. A
        default run writes none at its end: a checkpoint holds the whole map and the tracker's
        target (~100 MB for a tracking-only 7-Scenes run of 700 frames)."""
        ck = self.cfg.checkpoint
        # a checkpoint already in the folder (a resumed run's) is kept current: a stale one would be resumed again
        asked = ck.save or ck.every_keyframes > 0 or self.path.exists()
        if not {"end": asked, "keyframes": asked, "interrupted": asked or ck.on_interrupt,
                "failed": asked or ck.on_interrupt}[reason]:
            return None
        if not self.state.poses:
            return None
        start = time.perf_counter()
        self.slam.settle()  # a keyframe entering the map beside tracking is in it first
        with self.slam.gaussian_map.lock:
            state = capture(self.slam, self.state, time.perf_counter() - self.started)
        n = len(self.state.poses)
        camera = self.dataset.camera
        meta = {"created": datetime.now(timezone.utc).isoformat(timespec="seconds"), "reason": reason,
                "last_frame_index": n - 1, "num_frames": n, "completed": reason == "end",
                "plugins": dict(self.names), "overrides": self.overrides, "config": config_dict(self.cfg),
                "camera": {"width": int(camera.width), "height": int(camera.height),
                           **{k: float(getattr(camera, k)) for k in ("fx", "fy", "cx", "cy")}},
                "depth_trunc": _finite_or_none(self.dataset.depth_trunc),
                "dataset": {k: getattr(self.cfg.dataset, k) for k in SAME_SELECTION},
                "settings_changes": self.state.settings_changes}
        size = write_checkpoint(self.path, meta, state)
        self.saved_keyframes = self.slam.num_keyframes
        log.info("checkpoint (%s) after frame %d: %s, %.1f MB in %.2f s", reason, n - 1, self.path, size / 2**20,
                 time.perf_counter() - start)
        return self.path


def capture(slam, run_state, wall_s: float) -> dict[str, Any]:
    """The state of `slam` and the run (call under the map's lock)."""
    gm = slam.gaussian_map
    return {"map": gm.columns(), "map_version": gm.version,
            "slam": {"num_keyframes": slam.num_keyframes, "keyframes_in_target": slam.keyframes_in_target,
                     "last_pose": slam.last_pose},
            **slam.plugin_states(), "run": _run_state(run_state, wall_s)}


def _run_state(s, wall_s: float) -> dict[str, Any]:
    n = len(s.poses)
    gt = np.full((n, 4, 4), np.nan)
    has_gt = np.array([p is not None for p in s.gt_poses], dtype=bool)
    for i in np.flatnonzero(has_gt):
        gt[i] = s.gt_poses[i]
    earlier_peak = s.earlier.peak_memory_mb
    sessions = {"count": s.sessions, "frames": n, **{k: s.whole_run(k) for k in SESSION_FIGURES},
                "peak_memory_mb": None if earlier_peak is None else max(earlier_peak, peak_memory_mb())}
    return {"timestamps": np.asarray(s.timestamps, dtype=np.float64), "poses": np.array(s.poses).reshape(n, 4, 4),
            "gt_poses": gt, "has_gt": has_gt, "keyframe_rows": np.asarray(s.keyframe_rows, dtype=np.int64),
            "wall_time_s": s.previous_wall_s + wall_s, "sessions": sessions,
            **{k: getattr(s, k) for k in RUN_COUNTERS}}


def load(source: str | Path) -> dict[str, Any]:
    """A checkpoint (RUN_DIR or the file), its contents checked: CheckpointError (one line)."""
    path = checkpoint_path(source)
    checkpoint = read_checkpoint(path)
    _check(path, checkpoint)
    return checkpoint


def _check(path: Path, checkpoint: dict[str, Any]) -> None:
    """What every use of a checkpoint relies on: the meta keys, the map's rows and the run's
    trajectory, consistent in shape."""
    def fail(what: str):
        raise CheckpointError(f"checkpoint {path}: {what} (the file was edited or written by another program)")

    for key in ("last_frame_index", "plugins", "config", "camera"):
        if key not in checkpoint:
            fail(f"meta.json has no {key!r}")
    state = checkpoint.get("state")
    if not isinstance(state, dict) or not all(k in state for k in ("map", "slam", "run", "tracker", "mapper")):
        fail("its state lacks map, slam, run, tracker or mapper")
    rows = state["map"]
    n = None
    for name, width in ROW_WIDTHS.items():
        value = rows.get(name) if isinstance(rows, dict) else None
        if not isinstance(value, torch.Tensor):
            fail(f"map field {name!r} is missing")
        shape = tuple(value.shape)
        n = shape[0] if n is None and shape else n
        if shape != ((n, width) if width else (n,)):
            fail(f"map field {name!r} has shape {shape}, expected {(n, width) if width else (n,)}")
    run = state["run"]
    frames = checkpoint["last_frame_index"] + 1 if isinstance(checkpoint["last_frame_index"], int) else None
    for key in ("timestamps", "poses", "gt_poses", "has_gt"):
        value = run.get(key) if isinstance(run, dict) else None
        if not isinstance(value, np.ndarray) or frames is None or len(value) != frames:
            fail(f"run.{key} does not hold one entry per frame up to last_frame_index")
    try:
        Camera(**checkpoint["camera"])
    except TypeError:
        fail("its camera is not width, height, fx, fy, cx, cy")


def resume(cfg, names: dict[str, str], slam, run_state, dataset=None) -> int:
    """With `resume=` set, restore its checkpoint into `slam` and `run_state` and return the
    first frame still to process; 0 (nothing done) otherwise. With `dataset`, its frames up to
    the checkpoint's must be the checkpoint's (`check_frames`)."""
    if not cfg.resume:
        return 0
    checkpoint = load(cfg.resume)
    check_resumable(checkpoint, cfg, names, cfg.resume)
    if dataset is not None:
        check_frames(checkpoint, dataset, cfg.resume)
    first = restore(checkpoint, slam, run_state)
    run_state.settings_changes = settings_changes(checkpoint, cfg, names, first)
    log.info("resumed from %s (%s after frame %d): %d Gaussians, %d keyframes", checkpoint_path(cfg.resume),
             checkpoint.get("reason"), first - 1, len(slam.gaussian_map), slam.num_keyframes)
    return first


def restore(checkpoint: dict[str, Any], slam, run_state) -> int:
    """Put `slam` (built from the same config) and `run_state` (empty) back where the checkpoint
    left them; returns the index of the first frame still to process."""
    state = checkpoint["state"]
    slam.gaussian_map.restore(state["map"], int(state["map_version"]))
    slam.num_keyframes = int(state["slam"]["num_keyframes"])
    slam.keyframes_in_target = int(state["slam"].get("keyframes_in_target", 0))  # 0: every trackable row counts
    last_pose = state["slam"]["last_pose"]
    slam.last_pose = None if last_pose is None else np.asarray(last_pose, dtype=np.float64)
    slam.load_plugin_states(state)
    run = state["run"]
    run_state.timestamps = [float(t) for t in run["timestamps"]]
    run_state.poses = list(np.asarray(run["poses"], dtype=np.float64))
    run_state.gt_poses = [p if ok else None for p, ok in zip(np.asarray(run["gt_poses"]), run["has_gt"])]
    run_state.keyframe_rows = [int(i) for i in run["keyframe_rows"]]
    for key in RUN_COUNTERS:
        setattr(run_state, key, type(getattr(run_state, key))(run[key]))
    run_state.previous_wall_s = float(run["wall_time_s"])
    first = int(checkpoint["last_frame_index"]) + 1
    sessions = run.get("sessions")
    if isinstance(sessions, dict):
        run_state.earlier = EarlierSessions(int(sessions["count"]), first,
                                            {k: sessions.get(k) for k in SESSION_FIGURES},
                                            sessions.get("peak_memory_mb"))
    else:  # written before sessions were counted: at least one, its own figures unknown
        run_state.earlier = EarlierSessions(1, first, {k: None for k in SESSION_FIGURES}, None)
    return first


def check_frames(checkpoint: dict[str, Any], dataset, source: str | Path) -> None:
    """CheckpointError when the dataset's frames up to the checkpoint's last are not the ones
    the checkpoint's run processed (their timestamps differ: a frame added, removed or moved in
    the dataset's list since), or the dataset now has fewer frames."""
    saved = np.asarray(checkpoint["state"]["run"]["timestamps"], dtype=np.float64)
    if len(dataset) < len(saved):
        raise CheckpointError(f"resume={source}: the dataset selects {len(dataset)} frames, fewer than the "
                              f"{len(saved)} the checkpoint's run processed (a resumed run continues the same frames)")
    now = np.array([dataset.timestamp(i) for i in range(len(saved))], dtype=np.float64)
    moved = np.flatnonzero(~(np.abs(now - saved) <= TIMESTAMP_TOLERANCE_S))
    if len(moved):
        i = int(moved[0])
        raise CheckpointError(f"resume={source}: frame {i} of the dataset is at {now[i]:.6f} s, the checkpoint's "
                              f"frame {i} at {saved[i]:.6f} s: the dataset's frame list changed since that run (a "
                              "resumed run continues the same frames)")


def finished(cfg, names: dict[str, str], frames: int) -> dict[str, Any] | None:
    """With `resume=`: the metrics of the run it names when that run completed every one of the
    `frames` frames this run selects (its refinement and evaluation included): there is nothing
    to resume, and its files stay as they are. None otherwise (also without resume=).
    CheckpointError when this run could not resume it (`check_resumable`)."""
    if not cfg.resume:
        return None
    path = checkpoint_path(cfg.resume)
    meta = read_meta(path)
    check_resumable(meta, cfg, names, cfg.resume)
    metrics_path = path.parent / "metrics.json"
    try:
        metrics = json.loads(metrics_path.read_text())
    except (OSError, ValueError):
        return None  # its metrics are missing or damaged: resuming writes them again
    if not (meta.get("completed") and isinstance(metrics, dict) and metrics.get("status") == "completed"
            and meta.get("num_frames") == frames == metrics.get("num_frames")):
        return None
    log.warning("resume=%s: the run completed all %d frames of this selection; nothing to resume (its files are left "
                "as they are; raise dataset.max_frames to go further)", cfg.resume, frames)
    return metrics


def saved_settings(checkpoint: dict[str, Any], keys: Iterable[str]) -> dict[str, Any]:
    """The method settings `keys` (dotted, `slamkit.run.settings.marked_settings`) of the session
    that wrote the checkpoint, from its resolved config (a key its config lacks is left out). A
    checkpoint before 0.4 has some of them at their old keys (`fps_limit`: `realtime.fps_limit`)."""
    from slamkit.registry.compose import RENAMED_IN

    old_spelling = {new: old for old, new in RENAMED_IN["0.4"].items()}
    settings = {}
    for key in keys:
        for spelling in filter(None, (key, old_spelling.get(key))):
            node: Any = checkpoint.get("config") or {}
            for part in spelling.split("."):
                node = node.get(part, _ABSENT) if isinstance(node, dict) else _ABSENT
            if node is not _ABSENT:
                settings[key] = node
                break
    return settings


def settings_changes(checkpoint: dict[str, Any], cfg, names: dict[str, str], first: int) -> list[dict[str, Any]]:
    """The checkpoint's record of method-setting changes, plus this session's when its settings
    differ from the checkpoint's: {frame: the first frame run with them, before, after} (only
    the keys that changed); `names`: the plugin chosen for each role path. A resumed run is
    never labelled as one method when it is not."""
    from slamkit.run.settings import method_settings

    changes = list(checkpoint.get("settings_changes") or [])
    now = json.loads(json.dumps(method_settings(cfg, names)))
    before = saved_settings(checkpoint, now)
    changed = sorted(k for k in before if k in now and before[k] != now[k])
    if changed:
        change = {"frame": first, "before": {k: before[k] for k in changed}, "after": {k: now[k] for k in changed}}
        log.warning("resume: the method settings change at frame %d: %s (metrics.json records it under "
                    "settings_changes)", first, ", ".join(f"{k} {before[k]!r} -> {now[k]!r}" for k in changed))
        changes.append(change)
    return changes


_ABSENT = object()


def check_resumable(checkpoint: dict[str, Any], cfg, names: dict[str, str], source: str | Path) -> None:
    """ConfigError-like CheckpointError when this run cannot continue the checkpoint's: another
    preset, other plugins, or another frame selection of the dataset (its max_frames may
    differ). Other method settings may change: `settings_changes` records them."""
    saved_preset = (checkpoint.get("config") or {}).get("preset")
    if saved_preset is not None and saved_preset != cfg.preset:
        raise CheckpointError(f"resume={source}: the run was made with preset={saved_preset}, this one has "
                              f"preset={cfg.preset} (a resumed run keeps its preset and plugins: start a new run "
                              f"to change them)")
    for role, name in (checkpoint.get("plugins") or {}).items():
        role = current_path(role)  # a checkpoint before 0.3 names a mapper part by its key alone
        if names.get(role) != name:
            raise CheckpointError(f"resume={source}: the checkpoint was made with {role}={name}, this run has "
                                  f"{role}={names.get(role)} (a resumed run keeps its preset and plugins: start a "
                                  f"new run to change them)")
    saved = checkpoint.get("dataset", {})
    for key in SAME_SELECTION:
        if key in saved and saved[key] != getattr(cfg.dataset, key):
            raise CheckpointError(f"resume={source}: dataset.{key} is {getattr(cfg.dataset, key)!r}, the checkpoint's "
                                  f"run had {saved[key]!r} (raise dataset.max_frames to go further)")


def load_map(source: str | Path, device: str | torch.device = "cpu") -> tuple[GaussianMap, dict[str, Any]]:
    """(the checkpoint's GaussianMap on `device`, the whole checkpoint) from RUN_DIR or the file."""
    checkpoint = load(source)
    state = checkpoint["state"]
    return GaussianMap.from_columns(state["map"], int(state.get("map_version", 0)), device), checkpoint


def keyframe_poses(checkpoint: dict[str, Any]) -> np.ndarray:
    """(K,4,4) camera-to-world poses of the checkpoint's keyframes (the run's trajectory rows)."""
    run = checkpoint["state"]["run"]
    return np.asarray(run["poses"], dtype=np.float64)[np.asarray(run["keyframe_rows"], dtype=np.int64)]


def current_path(role: str) -> str:
    """A role's path in a checkpoint's plugin list as 0.3 spells it (`rasterizer` ->
    `mapper.rasterizer`)."""
    from slamkit.roles import PARTS

    return next((part.path for part in PARTS if part.key == role), role)


def resume_arguments(argv: list[str]) -> list[str]:
    """The command line of `slamkit resume=RUN_DIR [overrides]`: the overrides of the run that
    wrote the checkpoint (respelled where slamkit 0.3 or 0.4 renamed their keys), then the new ones
    (which replace those of the same key), and `hydra.run.dir=RUN_DIR` so that the run's files
    are extended in place. `argv` unchanged without resume=. CheckpointError when the checkpoint
    cannot be read."""
    from slamkit.registry.compose import parse_overrides, renamed_key

    given = {o.key_or_group: o for o in parse_overrides([a for a in argv if not a.startswith("-")])}
    if "resume" not in given:
        return argv
    source = Path(str(given["resume"].value()))
    meta = read_meta(checkpoint_path(source))
    overrides = meta.get("overrides")
    if not isinstance(overrides, list):
        raise CheckpointError(f"resume={source}: the checkpoint has no command line to resume (it was written "
                              "outside the slamkit command)")
    _check_choices(meta, given, source)
    kept = []
    for saved in parse_overrides(overrides):
        key = saved.key_or_group
        new = renamed_key(key)
        if (new or key) not in given and not key.startswith(("hydra.", "hydra/")):
            kept.append(saved.input_line.replace(key, new, 1) if new else saved.input_line)
    out_dir = source if source.is_dir() else source.parent
    run_dir = [] if "hydra.run.dir" in given else [f"hydra.run.dir={out_dir}"]
    return kept + argv + run_dir


def _check_choices(meta: dict[str, Any], given: dict[str, Any], source: Path) -> None:
    """CheckpointError, in the terms of the command line, for a `preset=` or a plugin choice
    (`loop_closure=none`) other than the checkpoint's run's, before anything is composed (the
    checkpoint's keys of the plugin it had would not compose with another)."""
    saved = {"preset": (meta.get("config") or {}).get("preset"),
             **{role.replace(".", "/"): name for role, name in (meta.get("plugins") or {}).items()}}
    for key, override in given.items():
        key = key.removeprefix("+")
        if key not in saved or saved[key] is None or override.is_sweep_override() or override.is_delete():
            continue
        if str(override.value()) != str(saved[key]):
            raise CheckpointError(f"resume={source}: the run was made with {key}={saved[key]}, this one asks for "
                                  f"{key}={override.value()} (a resumed run keeps its preset and plugins: start a "
                                  f"new run to change them)")


def config_dict(cfg) -> dict[str, Any]:
    """The resolved run config as JSON values (enums by value)."""
    def default(value):
        return value.value if isinstance(value, enum.Enum) else str(value)

    return json.loads(json.dumps(dataclasses.asdict(cfg), default=default))


def _hydra_overrides(out_dir: Path) -> list[str] | None:
    """The command-line overrides Hydra recorded for this run (None outside the slamkit command)."""
    path = out_dir / ".hydra" / "overrides.yaml"
    if not path.is_file():
        return None
    import yaml

    overrides = yaml.safe_load(path.read_text())
    return [str(o) for o in overrides] if isinstance(overrides, list) else None


def _finite_or_none(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None
