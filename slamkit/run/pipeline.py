"""Running SLAM on a dataset (`Pipeline`): building the roles from config, then the run's phases
(`slamkit.run.lifecycle.Phase`): the stream (each frame given to the SLAM by the mode's runner,
`slamkit.run.runner`, with the progress bar, the viewer and the per-frame log), the refinement,
the map and the evaluation, each phase's outputs written as soon as it ends
(`slamkit.run.outputs`), and what the run has kept when a signal or an error stops it.

The algorithm itself is `slamkit.run.slam.SLAM`; the runner decides when a frame is taken and
what runs beside it; this module is the I/O around them.
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
from slamkit.run.metrics import folder_mb, summary
from slamkit.run.outputs import RunOutputs
from slamkit.run.prefetch import LoadCost, UnreadableFrame, prefetched
from slamkit.run.runner import InputClock, RealtimeRunner, Runner
from slamkit.run.state import COMPLETED, FAILED, INTERRUPTED, RunState
from slamkit.run.viewing import ViewerFeed
from slamkit.scheduling import thread_schedule
from slamkit.types import Frame

__all__ = ["run", "Pipeline", "summary", "mapping_threads"]

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
            return Pipeline(cfg, registry, names, out_dir, stop).run()
    finally:
        torch.set_num_threads(threads_before)


class Pipeline:
    """One run, built: the dataset, the SLAM and the viewer from the config (`build`), the
    checkpoint it resumes from (`resume=`: the stream starts at `first`), its state, outputs and
    runner. `run()` runs its phases once (`phases`: the stream, the refinement, the map, the
    evaluation) and writes what it has whatever stops it. `done` holds the metrics when a
    resumed run had nothing left to do."""

    def __init__(self, cfg: RunConfig, registry: Registry, names: dict[str, str], out_dir: Path,
                 stop: StopSignals):
        out_dir.mkdir(parents=True, exist_ok=True)
        np.random.seed(cfg.seed)
        progress.configure(cfg.output.progress)
        built = build(cfg, registry, names)
        self.names, self.stop, self.out_dir = names, stop, out_dir
        self.dataset, self.slam, self.cfg = built.dataset, built.slam, built.config
        self.viewer = ViewerFeed(built.viewer, names["viewer"], self.slam.gaussian_map, self.slam.mapper)
        log.info("%s: %d frames, camera %s; tracker %s, mapper %s, keyframes %s", names["dataset"], len(self.dataset),
                 self.dataset.camera, names["tracker"], names["mapper"], names["keyframe"])
        # resume= of a completed run: nothing to do
        self.done = checkpoint.finished(self.cfg, names, len(self.dataset))
        self.state = RunState()
        self.first = 0
        self.outputs: RunOutputs | None = None  # with the runner, None when there is nothing to do
        self.runner: Runner | None = None
        if self.done is not None:
            return
        # checkpoint: continue a saved run (resume=RUN_DIR)
        self.first = checkpoint.resume(self.cfg, names, self.slam, self.state, self.dataset)
        checkpoints = checkpoint.CheckpointWriter(self.cfg, names, self.slam, self.state, self.dataset, out_dir)
        self.outputs = RunOutputs(self.cfg, self.slam, self.state, out_dir, checkpoints, stop)
        cfg = self.cfg
        realtime = cfg.mode is Mode.realtime
        # a live source's frames arrive on its own clock; a recording's at realtime.fps_limit in real time
        clock = (LiveClock(self.dataset) if self.dataset.live
                 else InputClock(cfg.realtime.fps_limit if realtime else None))
        self.runner = (RealtimeRunner(self.slam, clock, cfg.realtime.switch_interval, cfg.realtime.mapping_priority,
                                      cfg.realtime.mapping_yields)
                       if realtime else Runner(self.slam, clock))

    def run(self) -> dict[str, Any]:
        """The phases, then the outputs (whatever stopped them) and the summary line; the metrics."""
        if self.done is not None:
            self.dataset.close()
            return self.done
        state, outputs = self.state, self.outputs
        try:
            self.phases()
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
            with self.stop.writing():
                try:
                    metrics = outputs.save_all()
                finally:
                    self.viewer.close()
                    self.slam.loop_closer.close()
                    # a camera's or a recording's threads stopped here, not at interpreter exit
                    self.dataset.close()
        if outputs.unwritten:
            name, why = next(iter(outputs.unwritten.items()))
            more = f" (and {len(outputs.unwritten) - 1} more)" if len(outputs.unwritten) > 1 else ""
            raise OutputError(f"could not write {self.out_dir / name}{more}: {why}; kept in {self.out_dir}: "
                              f"{', '.join(outputs.kept) or 'nothing'}")
        metrics["run_folder_mb"] = folder_mb(self.out_dir)  # the summary's, not metrics.json's: written by now
        if (starved := starved_mapping(self.cfg, self.names["mapper"], metrics)) is not None:
            log.warning("%s", starved)
        log.info("%s", summary(metrics))
        return metrics

    def phases(self) -> None:
        """The run after start-up, each phase's outputs written as soon as it ends: the stream,
        then the trajectory and the tracking metrics; the refinement, then the map and the
        checkpoint; the evaluation, then the metrics with it. A run whose tracking failed stops
        after the stream. A resumed run streams from frame `first` and extends frames.csv."""
        cfg, dataset, slam, state, outputs = self.cfg, self.dataset, self.slam, self.state, self.outputs
        self.enter(Phase.stream)
        outputs.save_camera(dataset.camera, dataset.depth_trunc)
        self.viewer.start(dataset.camera, outputs.out_dir)
        if self.first < len(dataset):  # frames to stream: the refinement after them starts over
            state.refine_iterations, state.refine_time_s = 0, 0.0
        with FrameLog(outputs.out_dir / "frames.csv", resume_from=self.first) as frames_log:
            self.stream(frames_log)
        failure = state.tracking_failure(cfg.eval.max_lost_fraction)
        if failure:
            state.stop(FAILED, failure)
            log.error("%s", failure)
            return
        self.close_remaining_loops()
        self.enter(Phase.refine)
        outputs.save_trajectory()
        self.refine(cfg.refinement_iterations())
        slam.finish()
        state.slam_time_s = time.perf_counter() - outputs.start
        self.enter(Phase.map)
        outputs.save_map()
        self.enter(Phase.evaluate)
        outputs.save_metrics()
        state.evaluation = slam.evaluate(dataset, state.poses, outputs.out_dir)
        state.stop(COMPLETED, None)

    def enter(self, phase: Phase) -> None:
        self.stop.check()  # a signal noted during the phase before
        self.state.phase = phase
        self.stop.enter(phase)

    def refine(self, iterations: int) -> None:
        """The map's refinement after the stream: up to `iterations` mapping steps in all (a
        resumed run does those its checkpoint had not), timed apart, stopping between two steps
        on a signal."""
        state = self.state
        if state.refine_iterations >= iterations:
            return
        start, before = time.perf_counter(), state.refine_time_s
        bar = Progress("refinement", iterations, "step", initial=state.refine_iterations)
        try:
            while state.refine_iterations < iterations:
                self.stop.check()
                if not self.slam.optimize(1):
                    break
                state.refine_iterations += 1
                bar.update(1)
        finally:
            bar.close()
            state.refine_time_s = before + time.perf_counter() - start
        log.info("refinement: %d mapping steps in %.1f s", state.refine_iterations, state.refine_time_s)

    def stream(self, frames_log: FrameLog) -> None:
        """The stream: frames `first`.. (a resumed run starts after its checkpoint's last frame)
        given to the SLAM by the runner, logged to frames.csv and shown, the checkpoint written
        every N keyframes; a signal stops it between two frames."""
        cfg, state, runner, first = self.cfg, self.state, self.runner, self.first
        bar = Progress("stream", None if self.dataset.live else len(self.dataset), "frame", initial=first)
        start, cpu_start, loading = time.perf_counter(), time.thread_time(), LoadCost()
        process_cpu_start = time.process_time()  # every thread: the kernels' workers too
        schedule_start = thread_schedule()
        try:
            runner.start()
            skip_errors = cfg.dataset.on_error.value == "skip"
            for frame in prefetched(self.dataset, cfg.dataset.prefetch, skip_errors, first, loading):
                self.stop.check()
                if isinstance(frame, UnreadableFrame):
                    log.warning("frame %d skipped: %s", frame.index, frame.error)
                    state.record_unreadable(frame.timestamp)
                    frames_log.unreadable(frame.index, frame.timestamp, frame.error)
                elif ((runner.wait(frame.index - first) and cfg.realtime.drop_frames
                       or cfg.eval.in_forced_gap(frame.index - first)) and state.poses):
                    state.record_dropped(frame)
                    frames_log.dropped(frame)
                else:
                    self.track(frame, frames_log)
                    runner.frame_done()
                    self.outputs.checkpoints.after_frame(frames_log.flush)  # checkpoint: every N keyframes
                bar.update(1)
                every = cfg.eval.running_ate_every
                if every and len(state.poses) % every == 0:
                    bar.set_postfix(_running_ate(state))
                    frames_log.flush()
                pause_point(f"stream@{len(state.poses)}", self.stop)
        finally:
            handover_error = runner.settle(state)  # the mapper has the last keyframe before what follows
            state.stream_time_s += time.perf_counter() - start
            state.tracking_cpu_s += time.thread_time() - cpu_start
            state.stream_cpu_s += time.process_time() - process_cpu_start
            schedule_end = thread_schedule()
            if schedule_start is not None and schedule_end is not None:
                waited = schedule_end.cpu_wait_s - schedule_start.cpu_wait_s
                state.tracking_cpu_wait_s = (state.tracking_cpu_wait_s or 0.0) + waited
            bar.close()
            runner.stop(state)
            state.loading_cpu_s += loading.cpu_s
            if handover_error is not None and sys.exc_info()[1] is None:
                raise handover_error
            if handover_error is not None:  # the stream failed first: that error goes on, this one is logged
                log.error("the last keyframe's handover failed too: %s", handover_error)

    def track(self, frame: Frame, frames_log: FrameLog) -> None:
        """One frame through the runner into the SLAM, then recorded, logged and shown. Its delay
        runs from its arrival (its time on the input clock, else now) to its pose, out of the
        tracker with its keyframe handed over (mapping steps after it not counted)."""
        i = frame.index - self.first
        arrival = self.runner.arrival(i)
        started = time.perf_counter()
        step = self.runner.process(frame, i)
        delay_s = started - arrival + step.tracking_time_s
        if step.correction is not None:  # a loop closed: the frames so far follow their keyframes
            self.state.follow(step.correction)
            self.viewer.follow(step.correction)
        self.state.record(frame, step, delay_s)
        frames_log.frame(frame, step, len(self.slam.gaussian_map), delay_s)
        if step.tracking.lost:
            log.warning("frame %d lost: %s", frame.index, step.tracking.stats.get("lost_reason", "?"))
        self.viewer.show(frame, step.tracking.pose, step.keyframe, step.tracking.lost,
                         self.slam.loop_closer.loop_segments)

    def close_remaining_loops(self) -> None:
        """After the stream: the keyframes the real-time loop thread had not taken yet are
        decided on now, one at a time (a stop signal ends it between two: those left stay
        queued), and the decisions not applied yet are, so that the trajectory written and the
        map refined are the corrected ones."""
        slam = self.slam
        if slam.loop_closer.waiting():
            pause_point("loops", self.stop)
        slam.loop_closer.finish_stream(self.stop.check)
        correction = slam.correct(stream_ended=True)
        if correction is not None:
            self.state.follow(correction)
            self.viewer.follow(correction)


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


def mapping_threads(cfg: RunConfig) -> int:
    """Torch threads for mapping: `cfg.mapping_threads`, else torch's default (every CPU, or
    $OMP_NUM_THREADS), less one in real-time mode for the tracking thread (on 2 cores, sharing
    both made the tracker wait)."""
    if cfg.mapping_threads:
        return cfg.mapping_threads
    default = torch.get_num_threads()
    return max(1, default - 1) if cfg.mode is Mode.realtime else default


def _running_ate(state: RunState) -> str:
    result = evaluation.ate(state.trajectory(), state.gt_poses)
    return "ATE n/a" if result.rmse_m is None else f"ATE {100 * result.rmse_m:.2f} cm"
