"""Running SLAM on a dataset: building the roles from config, then the run's phases
(`slamkit.run.lifecycle.Phase`): the stream (the frame loop, sequential or beside a mapping thread
and a loop-closure thread, paced like a camera, with the progress bar, the viewer and the
per-frame log), the refinement, the map and the evaluation, each phase's outputs written as soon
as it ends (`slamkit.run.outputs`), and what the run has kept when a signal or an error stops it.

The algorithm itself is `slamkit.run.slam.SLAM`; this module is the I/O around it.
"""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from slamkit import progress
from slamkit.errors import OutputError
from slamkit.metrics import trajectory as evaluation
from slamkit.progress import Progress
from slamkit.registry.discovery import Registry
from slamkit.registry.schema import Mode, RunConfig
from slamkit.run import checkpoint
from slamkit.run.build import build
from slamkit.run.frame_log import FrameLog
from slamkit.run.lifecycle import Phase, StopSignals, pause_point
from slamkit.run.live import LiveClock
from slamkit.run.loop_closing import LoopThread
from slamkit.run.metrics import folder_mb, summary
from slamkit.run.outputs import RunOutputs
from slamkit.run.prefetch import LoadCost, UnreadableFrame, prefetched
from slamkit.run.slam import SLAM, MappingThread
from slamkit.run.state import COMPLETED, FAILED, INTERRUPTED, RunState
from slamkit.run.viewing import ViewerFeed
from slamkit.scheduling import thread_schedule
from slamkit.types import Frame

__all__ = ["run", "summary", "mapping_threads", "InputClock"]

log = logging.getLogger(__name__)


def run(cfg: RunConfig, registry: Registry, names: dict[str, str], out_dir: Path,
        stop: StopSignals | None = None) -> dict[str, Any]:
    """Run SLAM as configured, writing the outputs into `out_dir` phase by phase
    (`slamkit.run.outputs`); return the final metrics (`status`: completed, interrupted, or
    failed when tracking failed). SIGINT and SIGTERM stop the run at a safe point
    (`slamkit.run.lifecycle.StopSignals`) and it keeps what it has. OutputError when a file
    could not be written (a full disk): the others were, metrics.json where space allowed."""
    threads_before = torch.get_num_threads()
    torch.set_num_threads(mapping_threads(cfg))
    stop = stop or StopSignals()
    try:
        with stop.installed():
            return _run(cfg, registry, names, out_dir, stop)
    finally:
        torch.set_num_threads(threads_before)


def _run(cfg: RunConfig, registry: Registry, names: dict[str, str], out_dir: Path, stop: StopSignals) -> dict[str, Any]:
    out_dir.mkdir(parents=True, exist_ok=True)
    np.random.seed(cfg.seed)
    progress.configure(cfg.progress)
    built = build(cfg, registry, names)
    dataset, slam, cfg = built.dataset, built.slam, built.config
    viewer = ViewerFeed(built.viewer, names["viewer"], slam.gaussian_map, slam.mapper)
    log.info("%s: %d frames, camera %s; tracker %s, mapper %s, keyframes %s", names["dataset"], len(dataset),
             dataset.camera, names["tracker"], names["mapper"], names["keyframe"])
    if (done := checkpoint.finished(cfg, names, len(dataset))) is not None:  # resume= of a completed run: nothing to do
        return done
    state = RunState()
    first = checkpoint.resume(cfg, names, slam, state, dataset)  # checkpoint: continue a saved run (resume=RUN_DIR)
    checkpoints = checkpoint.CheckpointWriter(cfg, names, slam, state, dataset, out_dir)
    outputs = RunOutputs(cfg, slam, state, out_dir, checkpoints, stop)
    try:
        _phases(cfg, dataset, slam, state, outputs, viewer, stop, first)
    except KeyboardInterrupt as exc:
        state.stop(INTERRUPTED, f"interrupted ({str(exc) or 'SIGINT'}) during {state.phase.value}")
        log.warning("run interrupted during %s after %d frames; writing what it has", state.phase.value,
                    len(state.poses))
    except OSError as exc:  # the environment: a full disk, a folder gone
        state.stop(FAILED, f"{type(exc).__name__}: {exc}")
        if not outputs.unwritten:  # not one of the outputs' writes: name the file the error names
            outputs.unwritten[Path(exc.filename).name if exc.filename else "outputs"] = exc.strerror or str(exc)
        log.error("run failed during %s: %s; writing what it has", state.phase.value, state.error)
    except Exception as exc:
        state.stop(FAILED, f"{type(exc).__name__}: {exc}")
        log.error("run failed during %s after %d frames: %s; writing what it has", state.phase.value,
                  len(state.poses), state.error)
        raise
    finally:
        with stop.writing():
            try:
                metrics = outputs.save_all()
            finally:
                viewer.close()
                slam.loop_closer.close()
    if outputs.unwritten:
        name, why = next(iter(outputs.unwritten.items()))
        more = f" (and {len(outputs.unwritten) - 1} more)" if len(outputs.unwritten) > 1 else ""
        raise OutputError(f"could not write {out_dir / name}{more}: {why}; kept in {out_dir}: "
                          f"{', '.join(outputs.kept) or 'nothing'}")
    metrics["run_folder_mb"] = folder_mb(out_dir)  # the summary's, not metrics.json's: written by now
    if (starved := starved_mapping(cfg, names["mapper"], metrics)) is not None:
        log.warning("%s", starved)
    log.info("%s", summary(metrics))
    return metrics


#: A real-time run whose mapping got less than this share of the steps sequential mode gives the
#: same frames is warned about: its map is barely trained (1 step for 40 frames on 2 loaded cores).
STARVED_SHARE = 0.1


def starved_mapping(cfg: RunConfig, mapper: str, m: dict[str, Any]) -> str | None:
    """One line when real-time mapping got far fewer steps than the method trains (sequential
    mode's `iterations_per_frame` a frame): the figures and the two ways out; None otherwise."""
    if cfg.mode is not Mode.realtime or mapper == "none" or not m.get("num_frames") or m.get("status") != COMPLETED:
        return None
    wanted = cfg.iterations_per_frame * m["num_frames"]
    got = (m.get("mapping_iterations") or 0) + (m.get("refine_iterations") or 0)
    if got >= STARVED_SHARE * wanted:
        return None
    psnr = f" (PSNR {m['psnr']:.2f} dB)" if m.get("psnr") is not None else ""
    return (f"real-time mapping got {got} mapping steps for {m['num_frames']} frames, where the method trains "
            f"{cfg.iterations_per_frame} a frame ({wanted}): this machine cannot map at this input rate and the "
            f"map is barely trained{psnr}; for the method's full training run mode=sequential (not real time), "
            f"or keep real time and train after the stream with final_iterations={wanted}")


def _phases(cfg: RunConfig, dataset, slam: SLAM, state: RunState, outputs: RunOutputs, viewer: ViewerFeed,
            stop: StopSignals, first: int = 0) -> None:
    """The run after start-up, each phase's outputs written as soon as it ends: the stream, then
    the trajectory and the tracking metrics; the refinement, then the map and the checkpoint; the
    evaluation, then the metrics with it. A run whose tracking failed stops after the stream. A
    resumed run streams from frame `first` and extends frames.csv."""
    _enter(Phase.stream, state, stop)
    outputs.save_camera(dataset.camera, dataset.depth_trunc)
    viewer.start(dataset.camera, outputs.out_dir)
    if first < len(dataset):  # frames to stream: the refinement after them starts over
        state.refine_iterations, state.refine_time_s = 0, 0.0
    with FrameLog(outputs.out_dir / "frames.csv", resume_from=first) as frames_log:
        _loop(cfg, dataset, slam, state, frames_log, viewer, stop, outputs.checkpoints, first)
    failure = state.tracking_failure(cfg.eval.max_lost_fraction)
    if failure:
        state.stop(FAILED, failure)
        log.error("%s", failure)
        return
    _close_remaining_loops(slam, state, viewer, stop)
    _enter(Phase.refine, state, stop)
    outputs.save_trajectory()
    _refine(slam, cfg.refinement_iterations(), state, stop)
    slam.finish()
    state.slam_time_s = time.perf_counter() - outputs.start
    _enter(Phase.map, state, stop)
    outputs.save_map()
    _enter(Phase.evaluate, state, stop)
    outputs.save_metrics()
    state.evaluation = slam.evaluate(dataset, state.poses, outputs.out_dir)
    state.stop(COMPLETED, None)


def _enter(phase: Phase, state: RunState, stop: StopSignals) -> None:
    stop.check()  # a signal noted during the phase before
    state.phase = phase
    stop.enter(phase)


def _refine(slam: SLAM, iterations: int, state: RunState, stop: StopSignals) -> None:
    """The map's refinement after the stream: up to `iterations` mapping steps in all (a resumed
    run does those its checkpoint had not), timed apart, stopping between two steps on a signal."""
    if state.refine_iterations >= iterations:
        return
    start, before = time.perf_counter(), state.refine_time_s
    bar = Progress("refinement", iterations, "step", initial=state.refine_iterations)
    try:
        while state.refine_iterations < iterations:
            stop.check()
            if not slam.optimize(1):
                break
            state.refine_iterations += 1
            bar.update(1)
    finally:
        bar.close()
        state.refine_time_s = before + time.perf_counter() - start
    log.info("refinement: %d mapping steps in %.1f s", state.refine_iterations, state.refine_time_s)


def mapping_threads(cfg: RunConfig) -> int:
    """Torch threads for mapping: `cfg.mapping_threads`, else torch's default (every CPU, or
    $OMP_NUM_THREADS), less one in real-time mode for the tracking thread (on 2 cores, sharing
    both made the tracker wait)."""
    if cfg.mapping_threads:
        return cfg.mapping_threads
    default = torch.get_num_threads()
    return max(1, default - 1) if cfg.mode is Mode.realtime else default


class InputClock:
    """Paces input like a live camera: frame i arrives `i / fps` seconds after the first."""

    def __init__(self, fps: float | None):
        self.period = 1.0 / fps if fps else 0.0
        self.start: float | None = None

    def late_after(self, i: int) -> float | None:
        """When tracking frame i, started now, is late (time.perf_counter() seconds): once frame
        i+1 has arrived, or one period from now when that was already so (a tracker behind its
        input is late only on a frame slower than the input rate); None without an input rate or
        before frame 0 has arrived."""
        if not self.period or self.start is None:
            return None
        return max(self.start + (i + 1) * self.period, time.perf_counter() + self.period)

    def arrival(self, i: int) -> float | None:
        """When frame i arrived (time.perf_counter() seconds); None without an input rate."""
        return self.start + i * self.period if self.period and self.start is not None else None

    def wait(self, i: int) -> bool:
        """Sleep until frame i has arrived; True if frame i+1 has arrived too (we are late)."""
        if not self.period:
            return False
        now = time.perf_counter()
        if self.start is None:
            self.start = now
        arrival = self.start + i * self.period
        if now < arrival:
            time.sleep(arrival - now)
            return False
        return now >= arrival + self.period


def _loop(cfg: RunConfig, dataset, slam: SLAM, state: RunState, frames_log: FrameLog, viewer: ViewerFeed,
          stop: StopSignals, checkpoints: checkpoint.CheckpointWriter, first: int = 0) -> None:
    """The stream: frames `first`.. (a resumed run starts after its checkpoint's last frame)
    tracked (and mapped, in sequential mode; beside a mapping thread in real-time mode), logged to
    frames.csv and shown, the checkpoint written every N keyframes; a signal stops it between
    two frames."""
    realtime = cfg.mode is Mode.realtime
    clock = LiveClock(dataset) if getattr(dataset, "live", False) else InputClock(cfg.fps_limit if realtime else None)
    mapping = MappingThread(slam, cfg.switch_interval, cfg.mapping_priority) if realtime else None
    loops = LoopThread(slam.loop_closer) if realtime and slam.loop_closer.active else None
    bar = Progress("stream", None if getattr(dataset, "live", False) else len(dataset), "frame", initial=first)
    start, cpu_start, loading = time.perf_counter(), time.thread_time(), LoadCost()
    process_cpu_start = time.process_time()  # every thread: the kernels' workers too
    schedule_start = thread_schedule()
    try:
        if mapping:
            mapping.start()
        if loops:
            loops.start()
        skip_errors = cfg.dataset.on_error.value == "skip"
        for frame in prefetched(dataset, cfg.dataset.prefetch, skip_errors, first, loading):
            stop.check()
            if isinstance(frame, UnreadableFrame):
                log.warning("frame %d skipped: %s", frame.index, frame.error)
                state.record_unreadable(frame.timestamp)
                frames_log.unreadable(frame.index, frame.timestamp, frame.error)
            elif ((clock.wait(frame.index - first) and cfg.drop_frames or cfg.in_forced_gap(frame.index - first))
                  and state.poses):
                state.record_dropped(frame)
                frames_log.dropped(frame)
            else:
                # a frame arrives at its time with an input rate, else when the loop takes it
                arrival = clock.arrival(frame.index - first) or time.perf_counter()
                if mapping and cfg.mapping_yields:
                    mapping.yield_to_tracking(clock.late_after(frame.index - first))
                _track(frame, slam, state, frames_log, viewer, mapping, loops, realtime and cfg.keyframe_thread,
                       arrival)
                if mapping:
                    mapping.yield_to_tracking(None)
                checkpoints.after_frame(frames_log.flush)  # checkpoint: every N keyframes
            bar.update(1)
            every = cfg.eval.running_ate_every
            if every and len(state.poses) % every == 0:
                bar.set_postfix(_running_ate(state))
                frames_log.flush()
            pause_point(f"stream@{len(state.poses)}", stop)
    finally:
        handover_error = _settle(slam, state)  # the mapper has the last keyframe before what follows
        state.stream_time_s += time.perf_counter() - start
        state.tracking_cpu_s += time.thread_time() - cpu_start
        state.stream_cpu_s += time.process_time() - process_cpu_start
        schedule_end = thread_schedule()
        if schedule_start is not None and schedule_end is not None:
            waited = schedule_end.cpu_wait_s - schedule_start.cpu_wait_s
            state.tracking_cpu_wait_s = (state.tracking_cpu_wait_s or 0.0) + waited
        bar.close()
        try:  # mapping first: a loop closure's call in progress then has the CPUs to end
            if mapping:
                _stop_mapping(mapping, state)
        finally:
            if loops:
                loops.stop()
        state.loading_cpu_s += loading.cpu_s
        if handover_error is not None and sys.exc_info()[1] is None:
            raise handover_error
        if handover_error is not None:  # the stream failed first: that error goes on, this one is logged
            log.error("the last keyframe's handover failed too: %s", handover_error)


def _settle(slam: SLAM, state: RunState) -> BaseException | None:
    """Wait for the keyframe going to the mapper beside tracking and count the stream's
    handovers (the run's SLAM streams once); its failure is returned, to be raised once the
    stream's threads are stopped."""
    try:
        slam.settle()
    except BaseException as exc:  # noqa: BLE001 - raised by the caller after its cleanup
        return exc
    finally:
        state.keyframe_handover_s += slam.handover_time_s
        state.keyframe_handover_wait_s += slam.handover_wait_s
    return None


def _track(frame: Frame, slam: SLAM, state: RunState, frames_log: FrameLog, viewer: ViewerFeed,
           mapping: MappingThread | None, loops: LoopThread | None = None, keyframe_thread: bool = False,
           arrival: float | None = None) -> None:
    """Track (and, in sequential mode, map) one frame; `arrival`: when it arrived
    (time.perf_counter() seconds; None: now). Its delay runs from there to its pose, out of
    the tracker with its keyframe handed over (mapping steps after it not counted)."""
    if slam.last_pose is None:  # the first frame tracked
        slam.initialize(frame.gt_pose if frame.gt_pose is not None else np.eye(4))
    started = time.perf_counter()
    step = slam.track(frame, defer_keyframe=keyframe_thread) if mapping else slam.step(frame)
    delay_s = started - (started if arrival is None else arrival) + step.tracking_time_s
    if mapping:
        mapping.check()
    if loops:
        loops.check()
    if step.correction is not None:  # a loop closed: the frames so far follow their keyframes
        state.follow(step.correction)
        viewer.follow(step.correction)
    state.record(frame, step, delay_s)
    frames_log.frame(frame, step, len(slam.gaussian_map), delay_s)
    if step.tracking.lost:
        log.warning("frame %d lost: %s", frame.index, step.tracking.stats.get("lost_reason", "?"))
    viewer.show(frame, step.tracking.pose, step.keyframe, step.tracking.lost, slam.loop_closer.loop_segments)


def _close_remaining_loops(slam: SLAM, state: RunState, viewer: ViewerFeed, stop: StopSignals) -> None:
    """After the stream: the keyframes the real-time loop thread had not taken yet are decided
    on now, one at a time (a stop signal ends it between two: those left stay queued), and the
    decisions not applied yet are, so that the trajectory written and the map refined are the
    corrected ones."""
    if slam.loop_closer.waiting():
        pause_point("loops", stop)
    slam.loop_closer.finish_stream(stop.check)
    correction = slam.correct()
    if correction is not None:
        state.follow(correction)
        viewer.follow(correction)


def _stop_mapping(mapping: MappingThread, state: RunState) -> None:
    try:
        mapping.stop()
    finally:
        state.mapping_iterations += mapping.iterations
        state.mapping_time_s += mapping.busy_time_s
        state.mapping_cpu_s = (state.mapping_cpu_s or 0.0) + mapping.cpu_time_s
        state.mapping_throttle = mapping.throttle


def _running_ate(state: RunState) -> str:
    result = evaluation.ate(state.trajectory(), state.gt_poses)
    return "ATE n/a" if result.rmse_m is None else f"ATE {100 * result.rmse_m:.2f} cm"
