"""The fault suite (issue 19, no traceback anywhere): bad inputs and faults, each run through a
console script's real entry point (`slamkit` = `slamkit.cli.main:main`, as installed) in this
process, asserting the exit status, the one-line message and what the run folder kept; then the
rules every config key shares, key by key (the checks themselves: tests/core/test_value_checks.py).

One row of `FAULTS` per case; to add one, append a `Fault`:
- argv: the command's arguments; `{out}` is the run folder (`hydra.run.dir={out}` is added to
  every `slamkit` row), `{data}` the case's input made by `make` (in its own temporary folder);
- program: the console script whose entry point runs (`slamkit` unless said);
- status: the expected exit status (2: bad input or config; 1: an environment failure; 0: the
  run goes on, e.g. a broken plugin that is not selected is only reported);
- message: a fragment of the one-line error (the last stderr line, `slamkit: error: ...`), or for
  status 0 of a warning or of the standard output;
- kept: the run outputs (`OUTPUTS`) left in {out}: "name" exists, "name:N" has N lines; any
  output not listed must be absent (metrics.json of a failed run must say completed=false, unless
  `completed` says whose it is: an earlier run's, kept as it was); None: the run folder itself is
  not created (the run was refused before any work).

Issue 36's cases add (see `Case`): `before` prepares the case (an earlier run in {out}, a damaged
cache, a run that holds the folder), `after` checks what else was kept (files unchanged, a map
without NaN); `process` runs the command in a process of its own, its output through a shell
redirection (`| head -1`, `2>&-`): for the faults that kill, hang or reach the process's file
descriptors; `signal` sends a signal once the run says it has paused at a point
(SLAMKIT_PAUSE_AT); `env` sets environment variables ({tmp} is the case's temporary folder).
For status 3 (tracking failed) and 128 + N (stopped by signal N) the line is the run's summary
on the standard output, or the last line on stderr.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import queue
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest

from support.data import REPLICA, require_data
from support.fault_inputs import (
    FRAMES,
    INTRINSICS,
    data_root_with_an_incomplete_scene,
    drop_frame,
    duplicate_timestamp,
    fifo_bag,
    flip_bytes,
    float_depth_in_metres,
    folder_with,
    install,
    make_read_only,
    non_utf8_name,
    tiny_tum,
    truncate_depth,
    truncate_half,
    truncated_download,
    tum_with,
    uint16_cast_metres,
)

#: The run outputs whose presence each case states.
OUTPUTS = ("trajectory.txt", "metrics.json", "frames.csv")


# --- the table ------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Fault:
    id: str
    argv: tuple[str, ...]
    status: int
    message: str
    kept: tuple[str, ...] | None = None
    make: Callable[[Path], object] | None = None
    program: str = "slamkit"
    before: Callable[["Case"], object] | None = None
    after: Callable[["Case", "Outcome"], object] | None = None
    process: str | None = None
    signal: tuple[str, signal.Signals] | None = None
    env: tuple[tuple[str, str], ...] = ()
    completed: bool | None = None  # metrics.json's `completed` (None: status == 0)


HUGE = "1000000"
FAST = ("tracker=kiss_icp", "mapper=none", "output.progress=false")
TUM_DATA = ("dataset=tum", "dataset.path={data}", *FAST)
FOLDER = ("dataset=folder", "dataset.path={data}", *FAST)
RAN = ("trajectory.txt", "metrics.json", "frames.csv")

FAULTS = [
    # config values: refused in one line naming the key, before the run folder exists
    Fault("stride-0", ("dataset.stride=0",), 2, "dataset.stride: expected an integer >= 1, got 0"),
    Fault("max-frames-text", ("dataset.max_frames=abc",), 2, "dataset.max_frames"),
    Fault("misspelt-key", ("tracker.no_such_key=1",), 2, "no_such_key"),
    Fault("bad-enum", ("mode=fast",), 2, "mode"),
    Fault("unknown-plugin", ("tracker=nope",), 2, "unknown tracker 'nope'; available:"),
    Fault("part-bad-value", ("mapper=gaussian_splatting", "mapper/sampler=covisible", "mapper.sampler.top_k=-1"), 2,
          "mapper.sampler.top_k"),
    Fault("cx-nan", ("dataset.cx=nan",), 2, "dataset.cx: expected null or >= 0 pixels, got nan"),
    Fault("fx-inf", ("dataset.fx=inf",), 2, "dataset.fx: expected a finite number"),
    Fault("cy-negative", ("dataset.cy=-5",), 2, "dataset.cy: expected null or >= 0 pixels, got -5.0"),
    Fault("depth-trunc-nan", ("dataset.depth_trunc=nan",), 2, "dataset.depth_trunc"),
    Fault("scale-c-nan", ("growth.scale_c=nan",), 2, "growth.scale_c"),
    Fault("fps-limit-inf", ("mode=realtime", "realtime.fps_limit=inf"), 2,
          "realtime.fps_limit: expected a finite number"),
    Fault("seed-negative", ("seed=-1",), 2, "seed: expected an integer from 0 to 2^32 - 1"),
    Fault("seed-huge", ("seed=1099511627776",), 2, "seed: expected an integer from 0 to 2^32 - 1"),
    Fault("mapper-seed-negative", ("mapper=gaussian_splatting", "mapper.seed=-1"), 2, "mapper.seed: expected"),
    Fault("kiss-min-points-0", ("tracker=kiss_icp", "tracker.min_points=0"), 2, "tracker.min_points: expected"),
    Fault("mapping-threads-huge", (f"mapping_threads={HUGE}",), 2, "mapping_threads: expected at most"),
    Fault("tracker-threads-huge", (f"tracker.num_threads={HUGE}",), 2, "tracker.num_threads: expected at most"),
    Fault("rasterizer-threads-huge",
          ("mapper=gaussian_splatting", "mapper/rasterizer=cpu", f"mapper.rasterizer.num_threads={HUGE}"), 2,
          "mapper.rasterizer.num_threads: expected at most"),
    Fault("loss-threads-huge", ("mapper=gaussian_splatting", f"mapper.loss.num_threads={HUGE}"), 2,
          "mapper.loss.num_threads: expected at most"),
    # intrinsics against the image size: refused when the dataset is opened, before any frame
    Fault("cx-huge", ("dataset.cx=1e30", *FAST), 2, "dataset.cx: expected 0 to", kept=()),
    Fault("fx-tiny-tum", (*TUM_DATA, "dataset.fx=0.001"), 2, "dataset.fx: expected", kept=(), make=tiny_tum),
    Fault("intrinsics-file-cx-huge", FOLDER, 2,
          "intrinsics.yaml: cx = 1e+30 (expected 0 to 640 pixels, inside an image 640 pixels wide)", kept=(),
          make=folder_with(INTRINSICS.replace("cx: 318.6", "cx: 1.0e+30"))),
    Fault("intrinsics-file-cx-nan", FOLDER, 2, "intrinsics.yaml: cx = nan", kept=(),
          make=folder_with(INTRINSICS.replace("cx: 318.6", "cx: .nan"))),
    Fault("intrinsics-file-fx-negative", FOLDER, 2, "intrinsics.yaml: fx = -1", kept=(),
          make=folder_with(INTRINSICS.replace("fx: 517.3", "fx: -1"))),
    Fault("intrinsics-file-missing-key", FOLDER, 2, "missing key fy", kept=(),
          make=folder_with(INTRINSICS.replace("fy: 516.5\n", ""))),
    Fault("intrinsics-file-size", FOLDER, 2, "is 640x480 but", kept=(),
          make=folder_with(INTRINSICS.replace("width: 640", "width: 320"))),
    Fault("intrinsics-file-absent", FOLDER, 2, "intrinsics.yaml not found", kept=(),
          make=folder_with(damage=lambda root: (root / "intrinsics.yaml").unlink())),
    # dataset files
    Fault("non-utf8-file-name", FOLDER, 2, "have no depth image (caf\\udce9)", kept=(), make=folder_with(
        damage=non_utf8_name)),
    Fault("dataset-path-missing", ("dataset=tum", "dataset.path={data}/nope", *FAST), 2, "nope", kept=(),
          make=lambda root: root.mkdir(parents=True)),
    Fault("replica-empty", ("dataset=replica", "dataset.path={data}", *FAST), 2, "frame%06d.jpg", kept=(),
          make=lambda root: root.mkdir(parents=True)),
    Fault("tum-duplicate-timestamp", TUM_DATA, 2, "rgb.txt", kept=(), make=tum_with(duplicate_timestamp)),
    Fault("tum-gt-path-missing", (*TUM_DATA, "dataset.gt_path=missing_gt.txt"), 2, "missing_gt.txt", kept=(),
          make=tiny_tum),
    Fault("truncated-depth-mid-run", TUM_DATA, 2, "image file is truncated (expected a 16-bit PNG)", kept=(
        "trajectory.txt:5", "metrics.json", "frames.csv"), make=tum_with(truncate_depth)),
    Fault("truncated-depth-skipped", (*TUM_DATA, "dataset.on_error=skip"), 0, "", kept=(
        f"trajectory.txt:{FRAMES}", "metrics.json", "frames.csv"), make=tum_with(truncate_depth)),
    # plugins
    Fault("plugin-raises-mid-run", (*TUM_DATA[:2], "tracker=still", "tracker.fail_at=3", "mapper=none"), 2,
          "tracker plugin 'still' failed in track(): ValueError: simulated failure",
          kept=("trajectory.txt:3", "metrics.json", "frames.csv"),
          make=lambda root: (tiny_tum(root), install("still")(root))),
    Fault("plugin-config-not-hydra", TUM_DATA, 0, "array_weights", kept=RAN,
          make=lambda root: (tiny_tum(root), install("array", "still")(root))),
    Fault("plugin-import-fails", TUM_DATA, 0, "needs libfoo", kept=RAN,
          make=lambda root: (tiny_tum(root), install("broken")(root))),
    Fault("plugin-config-not-hydra-listed", ("tracker=array_weights",), 2, "not loaded: array (slamkit-fault-plugins)",
          make=install("array")),
    Fault("plugin-defaults-invalid", TUM_DATA, 0, "cannot be built from its defaults: tracker.radius: expected > 0",
          kept=RAN, make=lambda root: (tiny_tum(root), install("bad_defaults")(root))),
    Fault("plugin-unusual-config-listed", (), 0, "level: low | high = low", program="slamkit-plugins",
          make=install("unusual")),
    Fault("plugin-unusual-config-runs", (*TUM_DATA, "tracker=still"), 0, "", kept=RAN,
          make=lambda root: (tiny_tum(root), install("unusual", "still")(root))),
    # absurd values that used to exhaust memory
    Fault("passes-huge", (*TUM_DATA, "dataset.passes=1000000000", "dataset.max_frames=4"), 0, "",
          kept=("trajectory.txt:4", "metrics.json", "frames.csv"), make=tiny_tum),
]


# --- issue 36: nothing silently wrong -------------------------------------------------------------

@dataclass
class Case:
    """A case's places and helpers for `before` and `after`: `slamkit(...)` runs an earlier
    command in this process, `spawn(...)` starts a slamkit process that stays paused (it holds its
    run folder), `memo` carries what `before` saw to `after`."""

    tmp: Path
    data: Path
    out: Path
    env: dict[str, str]
    runner: Callable[..., "Outcome"]
    memo: dict[str, Any] = field(default_factory=dict)
    holders: list[subprocess.Popen] = field(default_factory=list)

    def expand(self, text: str) -> str:
        return text.replace("{data}", str(self.data)).replace("{out}", str(self.out)).replace("{tmp}", str(self.tmp))

    def slamkit(self, *argv: str, program: str = "slamkit", status: int = 0) -> "Outcome":
        result = self.runner(program, [self.expand(a) for a in argv])
        assert result.status == status, (result.stdout + result.stderr)[-3000:]
        return result

    def spawn(self, *argv: str, pause_at: str) -> subprocess.Popen:
        exe = Path(sys.executable).with_name("slamkit")
        env = dict(os.environ, **self.env, SLAMKIT_PAUSE_AT=pause_at)
        proc = subprocess.Popen([str(exe), *(self.expand(a) for a in argv)], cwd=self.tmp, env=env, text=True,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        self.holders.append(proc)
        for line in proc.stderr:
            if "paused at" in line:
                threading.Thread(target=proc.stderr.read, daemon=True).start()  # keep its pipe drained
                return proc
        pytest.fail(f"the holding run ended before pausing: {proc.wait()}")

    def stop_holders(self, sig: signal.Signals = signal.SIGTERM) -> list[int]:
        for proc in self.holders:
            proc.send_signal(sig)
        return [proc.wait(timeout=120) for proc in self.holders]


def digests(folder: Path, ignore: tuple[str, ...] = ()) -> dict[str, str]:
    """sha256 of every file under `folder` (relative names), but the lock (which names the last
    process that tried the folder) and those under a name in `ignore`."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and p.name != ".slamkit.lock"
            and not any(str(p.relative_to(folder)).startswith(name) for name in ignore)}


TUM_RUN = (*TUM_DATA, f"dataset.max_frames={FRAMES}")
GICP = ("dataset=tum", "dataset.path={data}", "mapper=none", "output.progress=false", "dataset.max_frames=4")
TINY_MAPPING = ("dataset=synthetic", "dataset.num_frames=6", "dataset.width=64", "dataset.height=48",
                "keyframe=every_n", "keyframe.tracking_every=3", "mapper=gaussian_splatting", "final_iterations=4",
                "mapper.save_images=2", "iterations_per_frame=2", "output.progress=false")


def earlier(*argv: str, frames: int = FRAMES, base: tuple[str, ...] = TUM_DATA, then: Callable | None = None):
    """`before`: a completed run in {out} with its checkpoint (the case's TUM copy unless `base` says otherwise);
    its files' digests go to memo["digests"]; then `then(case)`."""

    def before(case: Case) -> None:
        extra = (f"dataset.max_frames={frames}",) if base is TUM_DATA else ()
        case.slamkit(*base, *extra, "checkpoint.save=true", *argv, "hydra.run.dir={out}")
        case.memo["digests"] = digests(case.out)
        if then is not None:
            then(case)

    return before


def unchanged(*ignore: str) -> Callable[[Case, Any], None]:
    """`after`: the earlier run's files are as they were (but those named in `ignore`)."""

    def after(case: Case, result) -> None:
        before = {k: v for k, v in case.memo["digests"].items() if not any(k.startswith(n) for n in ignore)}
        assert digests(case.out, ignore) == before

    return after


def holder(*argv: str, pause_at: str = "stream@1", frames: int | None = None) -> Callable[[Case], None]:
    """`before`: a slamkit process that runs in {out} and stays paused at `pause_at`
    (after an earlier run of `frames` frames in {out}, when given)."""

    def before(case: Case) -> None:
        if frames:
            earlier(frames=frames)(case)
        case.memo["holder"] = case.spawn(*argv, "hydra.run.dir={out}", pause_at=pause_at)

    return before


def holder_named_and_stopped(case: Case, result) -> None:
    """`after`: the refusal names the holding process; stopped (SIGTERM), it keeps its files."""
    assert f"pid {case.memo['holder'].pid} " in result.stderr
    assert case.stop_holders() == [128 + signal.SIGTERM]


def interrupted_by(sig: signal.Signals) -> Callable[[Case, Any], None]:
    def after(case: Case, result) -> None:
        from slamkit.formats.checkpoint import read_meta

        metrics = json.loads((case.out / "metrics.json").read_text())
        assert (metrics["status"], metrics["error"]) == ("interrupted", f"interrupted ({sig.name}) during stream")
        assert read_meta(case.out / "checkpoint.zip")["reason"] == "interrupted"

    return after


def kernel_cache(damage: Callable[[Path], None] | None) -> Callable[[Case], None]:
    """`before`: the case's own SLAMKIT_CACHE holding the G-ICP kernels, built in a process of
    their own (never loaded here: a damaged library in this process would take pytest down),
    then damaged."""

    def before(case: Case) -> None:
        cache = case.tmp / "cache"
        case.env["SLAMKIT_CACHE"] = str(cache)
        build = subprocess.run([sys.executable, "-c", "from slamkit_plugins.trackers.gicp.kernels import LIBRARY; "
                                "assert LIBRARY.get() is not None, LIBRARY.error"],
                               env=dict(os.environ, SLAMKIT_CACHE=str(cache)), capture_output=True, text=True)
        assert build.returncode == 0, build.stderr
        (library,) = (cache / "extensions").glob("slamkit_gicp_kernels_*.so")
        case.memo["library"] = (library, hashlib.sha256(library.read_bytes()).hexdigest())
        if damage is not None:
            damage(library)

    return before


def kernel_rebuilt(case: Case, result) -> None:
    library, digest = case.memo["library"]
    assert hashlib.sha256(library.read_bytes()).hexdigest() == digest  # the same source builds the same library


def no_compiler(case: Case) -> None:
    case.env["CXX"] = "false"  # a compiler that fails, saying nothing


#: A C++ compiler that reports the real one's version (so the cached library's name is the one it
#: would build) but fails to build anything: a full disk, a broken installation.
FAILING_COMPILER = """#!/bin/sh
if [ "$1" = "--version" ]; then exec c++ --version; fi
echo "c++: fatal error: cannot write the output: No space left on device" >&2
exit 1
"""


def failing_compiler(case: Case) -> None:
    path = case.tmp / "bin" / "c++"
    path.parent.mkdir()
    path.write_text(FAILING_COMPILER)
    path.chmod(0o755)
    case.env["CXX"] = str(path)


def said_damaged(case: Case, result) -> None:
    assert "is damaged (" in result.stderr and "rebuilding it" in result.stderr


def synthetic_cache_damaged(case: Case) -> None:
    case.slamkit(*SYNTHETIC, "hydra.run.dir={tmp}/first")
    (cache,) = (case.tmp / "synthetic").glob("*.npz")
    flip_bytes(cache, fraction=0.5)
    case.memo["cache"] = cache


def synthetic_cache_regenerated(case: Case, result) -> None:
    import zipfile

    with zipfile.ZipFile(case.memo["cache"]) as archive:
        assert archive.testzip() is None  # every member whole again


SYNTHETIC = ("dataset.num_frames=6", "dataset.width=64", "dataset.height=48", "dataset.cache_dir={tmp}/synthetic",
             *FAST)


def reference_poses(case: Case) -> None:
    """`before`: the same frames with the folder's own 16-bit depth, run apart."""
    tiny_tum(case.tmp / "reference")
    case.slamkit("dataset=tum", f"dataset.path={case.tmp / 'reference'}", *FAST, "hydra.run.dir={tmp}/reference_run")
    case.memo["poses"] = np.loadtxt(case.tmp / "reference_run" / "trajectory.txt")


def same_poses(case: Case, result) -> None:
    assert np.allclose(np.loadtxt(case.out / "trajectory.txt"), case.memo["poses"], atol=1e-4)


def replica_map(case: Case) -> None:
    case.slamkit("dataset=replica", f"dataset.path={require_data(REPLICA)}", "dataset.max_frames=5", "mapper=none",
                 "output.progress=false", "checkpoint.save=true", "hydra.run.dir={tmp}/map")


def nothing_localised(case: Case, result) -> None:
    metrics = json.loads((case.out / "metrics.json").read_text())
    assert (metrics["status"], metrics["localized_frames"], metrics["success_rate"]) == ("failed", 0, 0.0)


def non_finite_gaussians(case: Case) -> None:
    """Two of the checkpoint's Gaussians made NaN (a diverged map), the file rewritten as slamkit writes it."""
    from slamkit.formats.checkpoint import read_checkpoint, write_checkpoint

    path = case.out / "checkpoint.zip"
    saved = read_checkpoint(path)
    means = saved["state"]["map"]["means"]
    means[:2] = float("nan")
    case.memo["gaussians"] = len(means)
    state = saved.pop("state")
    write_checkpoint(path, {k: v for k, v in saved.items() if k not in ("format", "schema_version")}, state)
    case.memo["digests"] = digests(case.out)


def finite_ply(case: Case, result) -> None:
    from slamkit.formats.ply import load_ply

    gm = load_ply(case.tmp / "map.ply")
    assert len(gm) == case.memo["gaussians"] - 2 and np.isfinite(gm.means.detach().cpu().numpy()).all()


def sweep_with_a_failed_job(case: Case) -> None:
    """A sweep of three jobs whose second fails at run time (its dataset folder is missing, which
    composing cannot know): it stops there (the third never runs)."""
    case.slamkit("-m", "dataset=tum", *FAST, "dataset.max_frames=4", "dataset.path={data},{data}/missing,{data}/later",
                 "hydra.sweep.dir={out}", status=2)


def report_rows(*expected: tuple[str, str]) -> Callable[[Case, Any], None]:
    """report.csv's rows as (the last name of dataset.path, status), and the failed job's error."""
    def after(case: Case, result) -> None:
        import csv

        rows = list(csv.DictReader(open(case.out / "report.csv")))
        assert sorted((Path(r["dataset.path"]).name, r["status"]) for r in rows) == sorted(expected)
        failed = next(r for r in rows if r["status"] == "failed")
        assert "missing not found" in failed["error"]

    return after


def read_only(case: Case) -> None:
    case.memo["undo"] = make_read_only(case.out)


def writable_again(case: Case, result) -> None:
    case.memo.pop("undo")()
    unchanged()(case, result)


def sessions(case: Case, result) -> None:
    metrics = json.loads((case.out / "metrics.json").read_text())
    first = json.loads(case.memo["metrics"])
    assert metrics["sessions"] == 2 and metrics["num_frames"] == 8
    session = metrics["session"]
    assert session["num_frames"] == 4
    for key in ("tracking_cpu_s", "loading_cpu_s", "stream_cpu_s"):  # over both sessions: more than either
        assert metrics[key] > max(first[key], session[key]) > 0, key
    assert metrics["wall_time_s"] > session["wall_time_s"] > 0


def remember_metrics(case: Case) -> None:
    case.memo["metrics"] = (case.out / "metrics.json").read_text()


def cleaned(case: Case, result) -> None:
    assert not {p.name for p in case.out.iterdir()} & {"map.ply", "render_0000.png", "render_0005.png"}
    assert "output.existing_outputs=clean" in (case.out / ".hydra" / "overrides.yaml").read_text()
    metrics = json.loads((case.out / "metrics.json").read_text())
    assert metrics["num_frames"] == FRAMES and "psnr" not in metrics


def stderr_log_clean(case: Case, result) -> None:
    assert "Traceback" not in (case.out / "slamkit.log").read_text()


def others_files(case: Case) -> None:
    case.out.mkdir(parents=True)
    (case.out / "notes.txt").write_text("someone else's")


def others_files_kept(case: Case, result) -> None:
    assert (case.out / "notes.txt").read_text() == "someone else's"


SIGNALS = [(signal.SIGHUP, 129), (signal.SIGINT, 130), (signal.SIGQUIT, 131), (signal.SIGUSR1, 138),
           (signal.SIGUSR2, 140), (signal.SIGTERM, 143)]
CUT = ("trajectory.txt:3", "metrics.json", "frames.csv")

ISSUE_36 = [
    # 1. a run folder belongs to one run
    Fault("run-folder-in-use", TUM_RUN, 2, "is in use by another run (pid ", kept=("trajectory.txt:1", "metrics.json",
          "frames.csv"), make=tiny_tum, before=holder(*TUM_RUN), after=holder_named_and_stopped),
    Fault("resume-while-resumed", ("resume={out}", "dataset.max_frames=8"), 2, "is in use by another run (pid ",
          kept=("trajectory.txt:5", "metrics.json", "frames.csv"), make=tiny_tum,
          before=holder("resume={out}", "dataset.max_frames=8", pause_at="stream@5", frames=4),
          after=holder_named_and_stopped),
    Fault("new-run-into-a-used-folder", TUM_RUN, 2, "holds the outputs of an earlier run (", kept=RAN, completed=True,
          make=tiny_tum, before=earlier(base=TINY_MAPPING), after=unchanged()),
    Fault("new-run-into-a-used-folder-clean", (*TUM_RUN, "output.existing_outputs=clean"), 0, "", kept=RAN,
          make=tiny_tum, before=earlier(base=TINY_MAPPING), after=cleaned),
    Fault("new-run-into-another-programs-folder", TUM_RUN, 2, "holds files that are not a slamkit run's (notes.txt)",
          kept=(), make=tiny_tum, before=others_files, after=others_files_kept),
    Fault("clean-another-programs-folder", (*TUM_RUN, "output.existing_outputs=clean"), 2,
          "holds files that are not a slamkit run's (notes.txt)", kept=(), make=tiny_tum, before=others_files,
          after=others_files_kept),
    Fault("localise-into-the-maps-folder", ("mode=localize", "map={out}", "dataset=tum", "dataset.path={data}",
          "output.progress=false"), 2, "localisation writes into a folder of its own", kept=RAN, completed=True,
          make=tiny_tum, before=earlier(), after=unchanged()),
    Fault("export-over-the-checkpoint", ("ply", "{out}", "--out", "{out}/checkpoint.zip"), 2,
          "is a map checkpoint", kept=RAN, completed=True, make=tiny_tum, program="slamkit-export", before=earlier(),
          after=unchanged()),
    Fault("export-out-a-folder", ("ply", "{out}", "--out", "{tmp}"), 2, "is a folder", kept=RAN, completed=True,
          make=tiny_tum, program="slamkit-export", before=earlier(), after=unchanged()),
    Fault("export-out-unwritable", ("ply", "{out}", "--out", "/proc/slamkit/map.ply"), 1,
          "cannot write /proc/slamkit/map.ply", kept=RAN, completed=True, make=tiny_tum, program="slamkit-export",
          before=earlier(), after=unchanged()),
    # 2. every catchable signal that ends a process
    *[Fault(f"{sig.name}-mid-stream", TUM_RUN, status, "(incomplete: interrupted during stream)", kept=CUT,
            make=tiny_tum, signal=("stream@3", sig), after=interrupted_by(sig)) for sig, status in SIGNALS],
    Fault("SIGHUP-during-start-up", TUM_RUN, 129, "slamkit: interrupted (SIGHUP) during start-up", make=tiny_tum,
          signal=("startup", signal.SIGHUP)),
    # 3. caches verified
    Fault("kernel-cache-truncated", GICP, 0, "is damaged", kept=("trajectory.txt:4", "metrics.json", "frames.csv"),
          make=tiny_tum, before=kernel_cache(truncate_half), after=kernel_rebuilt, process=""),
    Fault("kernel-cache-flipped-compiled", (*GICP, "tracker.kernels=compiled"), 0, "is damaged",
          kept=("trajectory.txt:4", "metrics.json", "frames.csv"), make=tiny_tum, before=kernel_cache(flip_bytes),
          after=kernel_rebuilt, process=""),
    Fault("kernel-cache-truncated-compiler-fails", GICP, 0, "using the numpy kernels",
          kept=("trajectory.txt:4", "metrics.json", "frames.csv"), make=tiny_tum,
          before=lambda case: (kernel_cache(truncate_half)(case), failing_compiler(case)), after=said_damaged,
          process=""),
    Fault("kernel-unbuildable-compiled", (*GICP, "tracker.kernels=compiled"), 2,
          "compiling gicp_kernels.cpp failed: the compiler (false) exited with status 1", kept=(), make=tiny_tum,
          before=lambda case: (kernel_cache(None)(case), shutil.rmtree(case.tmp / "cache"), no_compiler(case)),
          process=""),
    Fault("synthetic-cache-damaged", SYNTHETIC, 0, "regenerating", kept=("trajectory.txt:6", "metrics.json",
          "frames.csv"), before=synthetic_cache_damaged, after=synthetic_cache_regenerated),
    Fault("fifo-named-mcap", ("dataset=rosbag", "dataset.path={data}/bag.mcap", *FAST), 2, "is not a regular file",
          kept=(), make=fifo_bag, process=""),
    # 4. inputs checked for meaning
    Fault("tum-float-depth-in-metres", TUM_DATA, 0, "", kept=RAN, make=tum_with(float_depth_in_metres),
          before=reference_poses, after=same_poses),
    Fault("tum-uint16-depth-in-whole-metres", TUM_DATA, 2, "dataset.depth_scale",
          kept=("trajectory.txt:0", "metrics.json", "frames.csv"), make=tum_with(uint16_cast_metres)),
    Fault("localise-in-another-scene", ("mode=localize", "map={tmp}/map", "dataset=tum", "dataset.path={data}",
          "dataset.max_frames=3", "localize.attempts=1", "output.progress=false"), 3, "no frame was localised",
          kept=("trajectory.txt:0", "metrics.json", "frames.csv"), make=tiny_tum, before=replica_map,
          after=nothing_localised),
    Fault("resume-after-the-frame-list-changed", ("resume={out}", "dataset.max_frames=8"), 2,
          "frame 2 of the dataset is at", kept=("trajectory.txt:4", "metrics.json", "frames.csv"), completed=True,
          make=tiny_tum, before=earlier(frames=4, then=lambda case: drop_frame(2)(case.data)),
          after=unchanged(".hydra", "slamkit.log")),
    Fault("export-non-finite-gaussians", ("ply", "{out}", "--out", "{tmp}/map.ply"), 0,
          "dropped 2 non-finite Gaussians", kept=("trajectory.txt:4", "metrics.json", "frames.csv"), completed=True,
          make=tiny_tum, program="slamkit-export", before=earlier(frames=4, base=GICP, then=non_finite_gaussians),
          after=finite_ply),
    # 5. output streams
    Fault("stdout-reader-quits", TUM_RUN, 0, "", kept=RAN, make=tiny_tum, process="| true"),
    Fault("stdout-head-1", TUM_RUN, 0, "", kept=RAN, make=tiny_tum, process="| head -1"),
    Fault("stdout-full", TUM_RUN, 0, "", kept=RAN, make=tiny_tum, process="> /dev/full"),
    Fault("stderr-closed-with-a-progress-bar", (*TUM_RUN, "output.progress=true"), 0, "", kept=RAN, make=tiny_tum,
          process="2>&-", after=stderr_log_clean),
    Fault("stderr-full", TUM_RUN, 0, "", kept=RAN, make=tiny_tum, process="2> /dev/full"),
    Fault("report-into-head-1", ("{out}",), 0, "", kept=RAN, completed=True, make=tiny_tum, program="slamkit-report",
          before=earlier(), process="| head -1"),
    # 6. what slamkit-report and the metrics say
    Fault("sweep-with-a-bad-value", ("-m", *TUM_DATA, "dataset.max_frames=4", "dataset.stride=1,0,2",
                                     "hydra.sweep.dir={out}"), 2,
          "job 2 of 3 of the sweep (dataset.stride=0): dataset.stride: expected an integer >= 1, got 0",
          make=tiny_tum),
    Fault("report-sweep-with-a-failed-job", ("{out}",), 0, "3 runs (1 completed, 1 failed, 1 not run)", kept=(),
          make=tiny_tum, program="slamkit-report", before=sweep_with_a_failed_job,
          after=report_rows(("data", "completed"), ("missing", "failed"), ("later", "not run"))),
    Fault("report-read-only-folder", ("{out}",), 1, "cannot write the report into", kept=RAN, completed=True,
          make=tiny_tum, program="slamkit-report", before=earlier(then=read_only), after=writable_again),
    Fault("resumed-run-metrics-per-session", ("resume={out}", "dataset.max_frames=8"), 0, "", kept=RAN,
          make=tiny_tum, before=earlier(frames=4, then=remember_metrics), after=sessions),
    Fault("resume-a-completed-run", ("resume={out}",), 0, "nothing to resume", kept=RAN, make=tiny_tum,
          before=earlier(), after=unchanged(".hydra", "slamkit.log")),
    Fault("two-frames", (*TUM_DATA, "dataset.max_frames=2"), 0, "too few frames",
          kept=("trajectory.txt:2", "metrics.json", "frames.csv"), make=tiny_tum),
]


# --- running a case ---------------------------------------------------------------------------------

@dataclass
class Outcome:
    status: int
    stdout: str
    stderr: str
    warnings: list[str]  # the Python warnings raised during the run


def run_program(program: str, argv: list[str], cwd: Path, monkeypatch, capsys) -> Outcome:
    """Run the entry point of the console script `program` (as installed: pyproject's
    [project.scripts]) in this process, as `program ARGV...` in `cwd`."""
    from importlib.metadata import entry_points

    from hydra.core.global_hydra import GlobalHydra

    (script,) = entry_points(group="console_scripts", name=program)
    main = script.load()

    monkeypatch.chdir(cwd)
    monkeypatch.setattr(sys, "argv", [program, *argv])
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    status = 0
    with warnings.catch_warnings(record=True) as warned:
        warnings.simplefilter("always")
        try:
            status = main() or 0
        except SystemExit as exc:
            status = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        finally:
            GlobalHydra.instance().clear()
            for handler in set(root.handlers) - set(handlers):  # Hydra's console and log-file handlers
                root.removeHandler(handler)
                handler.close()
            for handler in handlers:
                if handler not in root.handlers:
                    root.addHandler(handler)
            root.setLevel(level)
    captured = capsys.readouterr()
    return Outcome(status, captured.out, captured.err, [str(w.message) for w in warned])


def run_process(program: str, argv: list[str], cwd: Path, env: dict[str, str], redirect: str = "",
                pause: tuple[str, signal.Signals] | None = None, timeout: float = 180) -> Outcome:
    """Run the console script `program` in a process of its own: `program ARGV... REDIRECT` in
    bash (its exit status, not the pipe's), or, with `pause` = (point, signal), wait until it says
    it has paused at the point (SLAMKIT_PAUSE_AT) and send it the signal."""
    exe = Path(sys.executable).with_name(program)
    env = dict(os.environ, **env)
    if pause is None:
        command = f"{shlex.join([str(exe), *argv])} {redirect}; exit ${{PIPESTATUS[0]}}"
        proc = subprocess.Popen(["bash", "-c", command], cwd=cwd, env=env, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True, start_new_session=True)
    else:
        env["SLAMKIT_PAUSE_AT"] = pause[0]
        proc = subprocess.Popen([str(exe), *argv], cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True, start_new_session=True)
    lines: queue.Queue[str | None] = queue.Queue()
    err: list[str] = []
    out: list[str] = []

    def read_stderr() -> None:
        for line in proc.stderr:
            err.append(line)
            lines.put(line)
        lines.put(None)

    readers = [threading.Thread(target=read_stderr, daemon=True),
               threading.Thread(target=lambda: out.append(proc.stdout.read()), daemon=True)]
    for reader in readers:
        reader.start()
    deadline = time.monotonic() + timeout
    if pause is not None:
        while (line := lines.get(timeout=max(1.0, deadline - time.monotonic()))) is not None:
            if f"paused at {pause[0]}" in line:
                proc.send_signal(pause[1])
                break
    try:
        proc.wait(timeout=max(1.0, deadline - time.monotonic()))
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        err.insert(0, f"timed out after {timeout} s\n")
    for reader in readers:
        reader.join(timeout=10)
    return Outcome(proc.returncode, "".join(out), "".join(err), [])


def check_kept(out: Path, kept: tuple[str, ...] | None, completed: bool) -> None:
    if kept is None:
        assert not out.exists(), f"the run folder {out} was created"
        return
    assert out.is_dir()
    expected = dict(k.partition(":")[::2] for k in kept)
    for name in OUTPUTS:
        path = out / name
        if name not in expected:
            assert not path.exists(), f"{name} was written"
            continue
        assert path.is_file(), f"{name} was not kept"
        if expected[name]:
            assert len(path.read_text().splitlines()) == int(expected[name]), name
    if "metrics.json" in expected:
        assert json.loads((out / "metrics.json").read_text())["completed"] is completed


def reported_by_summary(status: int) -> bool:
    """Tracking failed (3) and stopped by a signal (128 + N): the run's summary says why."""
    return status == 3 or status > 128


# --- issue 45: the newest paths --------------------------------------------------------------------

def corrupt_moved_aside(case: Case, result) -> None:
    assert (case.data / "rgbd_dataset_freiburg1_xyz.tgz.corrupt").is_file()
    assert not (case.data / "rgbd_dataset_freiburg1_xyz.tgz").exists()
    assert not (case.data / "rgbd_dataset_freiburg1_xyz").exists()


def incomplete_scene_skipped(case: Case, result) -> None:
    """The incomplete scene named with what it lacks before the first job; the complete one ran."""
    (line,) = [ln for ln in result.stderr.splitlines() if "rgbd_dataset_freiburg2_xyz skipped" in ln]
    assert "depth.txt not found" in line
    jobs = [p for p in case.out.iterdir() if p.is_dir() and p.name.isdigit()]
    assert len(jobs) == 1
    metrics = json.loads((jobs[0] / "metrics.json").read_text())
    assert metrics["completed"] and metrics["num_frames"] == 3


def said_once(case: Case, result) -> None:
    """The error is on the terminal once (the `slamkit: error:` line), and in the run's log file."""
    message = result.stderr.strip().splitlines()[-1].removeprefix("slamkit: error: ")
    assert (result.stdout + result.stderr).count(message) == 1, result.stdout + result.stderr
    logs = list(case.out.rglob("slamkit.log"))
    assert logs and any(message in log.read_text() for log in logs)


def said_once_before_any_job(case: Case, result) -> None:
    """Every job is composed before the first runs: the error is on the terminal once, no job ran."""
    message = result.stderr.strip().splitlines()[-1].removeprefix("slamkit: error: ")
    assert (result.stdout + result.stderr).count(message) == 1, result.stdout + result.stderr
    assert not case.out.exists()


def settings_change_recorded(case: Case, result) -> None:
    metrics = json.loads((case.out / "metrics.json").read_text())
    before = json.loads(case.memo["metrics"])["settings"]["iterations_per_frame"]
    assert metrics["settings"]["iterations_per_frame"] == 7 != before
    assert metrics["settings_changes"] == [{"frame": 4, "before": {"iterations_per_frame": before},
                                            "after": {"iterations_per_frame": 7}}]
    assert "the method settings change at frame 4" in result.stdout + result.stderr


LOOPS = ("loop_closure=pose_graph", "loop_closure.min_path_m=0.5")

ISSUE_45 = [
    # 1. slamkit-data: a --root that is no folder, an archive that does not extract
    Fault("data-root-not-creatable", ("download", "fr1/xyz", "--root", "/proc/slamkit-nope"), 1,
          "--root /proc/slamkit-nope: cannot create the folder", program="slamkit-data"),
    Fault("data-root-a-file", ("download", "fr1/xyz", "--root", "{data}"), 2, "is a file, expected a folder",
          program="slamkit-data", make=lambda root: root.write_text("not a folder")),
    Fault("data-truncated-archive", ("download", "fr1/xyz", "--root", "{data}", "--base-url", "http://127.0.0.1:9",
                                     "--no-progress"), 2,
          "moved aside as rgbd_dataset_freiburg1_xyz.tgz.corrupt: run the same command again", program="slamkit-data",
          make=truncated_download, after=corrupt_moved_aside),
    # 3. a scene sweep: every scene opened before the first job, the incomplete one named and skipped
    Fault("sweep-incomplete-scene", ("+experiment=paper_tum", "data_root={data}", "preset=slamkit", *FAST,
                                     "dataset.max_frames=3", "hydra.sweep.dir={out}"), 0, "depth.txt not found",
          kept=(), make=data_root_with_an_incomplete_scene, after=incomplete_scene_skipped),
    # 5. a resume that changes the method: refused (preset, plugins) or recorded (a method key)
    Fault("resume-another-preset", ("resume={out}", "preset=paper"), 2,
          "the run was made with preset=slamkit, this one asks for preset=paper",
          kept=("trajectory.txt:4", "metrics.json", "frames.csv"), completed=True, make=tiny_tum,
          before=earlier(frames=4), after=unchanged(".hydra", "slamkit.log")),
    Fault("resume-another-loop-closure", ("resume={out}", "loop_closure=none"), 2,
          "the run was made with loop_closure=pose_graph, this one asks for loop_closure=none",
          kept=("trajectory.txt:4", "metrics.json", "frames.csv"), completed=True, make=tiny_tum,
          before=earlier(*LOOPS, base=GICP), after=unchanged(".hydra", "slamkit.log")),
    Fault("resume-a-method-key-changed", ("resume={out}", "dataset.max_frames=8", "iterations_per_frame=7"), 0, "",
          kept=("trajectory.txt:8", "metrics.json", "frames.csv"), make=tiny_tum,
          before=earlier(frames=4, then=remember_metrics), after=settings_change_recorded),
    Fault("key-of-the-preset", ("preset.x=1",), 2, "preset.x=1: preset is chosen whole (preset=NAME: paper"),
    # 6. boolean keys take booleans only
    Fault("bool-a-number", ("realtime.keyframe_thread=2",), 2,
          "realtime.keyframe_thread: expected true or false, got 2"),
    Fault("bool-negative", ("realtime.mapping_yields=-1",), 2,
          "realtime.mapping_yields: expected true or false, got -1"),
    Fault("bool-of-a-plugin", ("tracker.retry_unconverged=2",), 2,
          "tracker.retry_unconverged: expected true or false, got 2"),
    Fault("bool-in-a-sweep", ("-m", "dataset.num_frames=3", *FAST, "realtime.keyframe_thread=true,2",
                              "hydra.sweep.dir={out}"),
          2, "job 2 of 2 of the sweep (realtime.keyframe_thread=2): realtime.keyframe_thread: expected true or "
             "false, got 2",
          after=said_once_before_any_job),
    # 7. a job's error said once
    Fault("job-error-said-once", ("dataset=tum", "dataset.path={data}/nope", *FAST), 2, "not found", kept=(),
          make=lambda root: root.mkdir(parents=True), after=said_once),
]

ALL_FAULTS = FAULTS + ISSUE_36 + ISSUE_45


@pytest.mark.slow  # every case starts the slamkit command (in process)
@pytest.mark.parametrize("fault", ALL_FAULTS, ids=[f.id for f in ALL_FAULTS])
def test_fault(fault: Fault, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(sys, "path", list(sys.path))  # a case's plugins leave with it
    data, out = tmp_path / "data", tmp_path / "run"
    case = Case(tmp_path, data, out, {}, lambda program, argv: run_program(program, argv, tmp_path, monkeypatch,
                                                                           capsys))
    for key, value in fault.env:
        case.env[key] = case.expand(value)
    if fault.make is not None:
        fault.make(data)
    try:
        if fault.before is not None:
            fault.before(case)
        argv = [case.expand(a) for a in fault.argv]
        if fault.program == "slamkit" and not any(a.startswith("hydra.") for a in argv):
            argv.append(f"hydra.run.dir={out}")
        if fault.process is not None or fault.signal is not None:
            result = run_process(fault.program, argv, tmp_path, case.env, fault.process or "", fault.signal)
        else:
            for key, value in case.env.items():
                monkeypatch.setenv(key, value)
            result = run_program(fault.program, argv, tmp_path, monkeypatch, capsys)
        everything = "\n".join([result.stdout, result.stderr, *result.warnings])
        assert result.status == fault.status, everything[-3000:]
        assert "Traceback" not in everything and "Logging error" not in everything, everything[-3000:]
        assert "Exception ignored" not in everything, everything[-3000:]
        last = (result.stderr.strip().splitlines() or [""])[-1]
        if reported_by_summary(fault.status):
            assert fault.message in result.stdout or fault.message in last, everything[-3000:]
        elif fault.status:
            prefix = f"{fault.program}: error: "
            assert last.startswith(prefix) and fault.message in last, last
        elif fault.message:
            assert any(fault.message in text for text in [result.stdout, result.stderr, *result.warnings]), \
                everything[-3000:]
        if fault.after is not None:
            fault.after(case, result)
        check_kept(out, fault.kept, fault.status == 0 if fault.completed is None else fault.completed)
    finally:
        for proc in case.holders:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        if "undo" in case.memo:
            case.memo.pop("undo")()


#: A sitecustomize module that stops Hydra's clock (its `${now:...}` resolver) at one second.
FROZEN_CLOCK = """
import datetime as _datetime
import hydra.core.utils as _utils

class _Frozen(_datetime.datetime):
    @classmethod
    def now(cls, tz=None):
        return cls(2030, 1, 2, 3, 4, 5)

_utils.datetime = _Frozen
"""


def _default_folders(cwd: Path) -> dict[int, Path]:
    """The run folders under the default outputs/DATE/, by their metrics' frame count."""
    folders = sorted((cwd / "outputs" / "2030-01-02").iterdir())
    assert all(f.name.startswith("03-04-05") for f in folders), folders
    return {json.loads((f / "metrics.json").read_text())["num_frames"]: f for f in folders}


@pytest.mark.slow
def test_runs_started_in_the_same_second_get_folders_of_their_own(tmp_path):
    """Two processes started at once with the default hydra.run.dir, Hydra's clock stopped at one
    second: each run has its own folder, whose recorded overrides are its own."""
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(FROZEN_CLOCK)
    data = tiny_tum(tmp_path / "data")
    exe = Path(sys.executable).with_name("slamkit")
    env = dict(os.environ, PYTHONPATH=str(site))
    procs = [subprocess.Popen([str(exe), "dataset=tum", f"dataset.path={data}", *FAST, f"dataset.max_frames={n}"],
                              cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for n in (3, 5)]
    for proc in procs:
        _, err = proc.communicate(timeout=300)
        assert proc.returncode == 0 and "Traceback" not in err, err[-3000:]
    folders = _default_folders(tmp_path)
    assert sorted(folders) == [3, 5]
    for n, folder in folders.items():
        assert f"dataset.max_frames={n}" in (folder / ".hydra" / "overrides.yaml").read_text()


@pytest.mark.slow
def test_two_runs_in_one_process_in_the_same_second_get_folders_of_their_own(tmp_path, monkeypatch, capsys):
    import hydra.core.utils

    namespace: dict = {}
    exec(FROZEN_CLOCK.replace("_utils.datetime = _Frozen", ""), namespace)
    monkeypatch.setattr(hydra.core.utils, "datetime", namespace["_Frozen"])
    data = tiny_tum(tmp_path / "data")
    for n in (3, 5):
        result = run_program("slamkit", ["dataset=tum", f"dataset.path={data}", *FAST, f"dataset.max_frames={n}"],
                             tmp_path, monkeypatch, capsys)
        assert result.status == 0, result.stderr[-3000:]
    assert sorted(_default_folders(tmp_path)) == [3, 5]


# --- every key: the rules every config value shares (slamkit.roles.check_values) ------------------

#: Numeric keys for which a negative value is meaningful: every other one has a range. A failed
#: run's score may be any number (e.g. below every real score of a maximised metric).
NEGATIVE_OK: set[str] = {"objective.failed_value", "loop_closure.min_appearance"}  # a cosine similarity: -1 takes all


def _numeric_keys():
    """(overrides selecting the key's plugin, key, "nan" | "negative" | "threads") for every float
    key of the configuration reference (nan), every int or float key (negative) and every field
    declared a thread count (`thread_count`)."""
    import dataclasses

    from slamkit.config import THREADS

    from support.config_reference import config_class, reference_keys

    cases = []
    for section, key, type_, _ in reference_keys():
        if section == "mapper/rasterizer=gsplat":
            continue  # needs CUDA to build; its config is checked in tests/plugins/test_fake_cuda.py
        base = [section] if "=" in section else []
        if section.startswith("mapper/"):
            base.insert(0, "mapper=gaussian_splatting")
        kinds = [t.strip() for t in type_.split("|")]
        if "float" in kinds:
            cases.append((base, key, "nan"))
        if {"int", "float"} & set(kinds) and key not in NEGATIVE_OK:
            cases.append((base, key, "negative"))
        field = {f.name: f for f in dataclasses.fields(config_class(section, key))}.get(key.split(".")[-1])
        if field is not None and field.metadata.get(THREADS):
            cases.append((base, key, "threads"))
    return cases


@pytest.mark.slow  # composes the config once per key
def test_every_numeric_key_has_a_range_and_every_thread_count_is_bounded_by_the_machine():
    """Through the composition the command uses, a float key refuses nan and -inf, a numeric key
    -1 (unless NEGATIVE_OK), a thread count the machine's CPUs + 1: each with one ConfigError line
    naming the key; a thread count equal to the machine's CPUs is accepted."""
    from slamkit.config import machine_threads
    from slamkit.errors import ConfigError
    from slamkit.registry.compose import compose_run

    cases = _numeric_keys()
    threads = [key for _, key, kind in cases if kind == "threads"]
    assert len(cases) > 200 and {"mapping_threads", "tracker.num_threads", "mapper.loss.num_threads"} <= set(threads)
    bad = {"nan": ["nan", "-inf"], "negative": ["-1"], "threads": [str(machine_threads() + 1)]}
    failures = []
    for base, key, kind in cases:
        for value in bad[kind]:
            try:
                compose_run([*base, f"{key}={value}"])
                failures.append(f"{key}={value} accepted")
            except ConfigError as exc:
                if key not in str(exc) or "\n" in str(exc):
                    failures.append(f"{key}={value}: {exc}")
        if kind == "threads":
            run, _ = compose_run([*base, f"{key}={machine_threads()}"])
            node = run
            for name in key.split("."):
                node = getattr(node, name)
            assert node == machine_threads()
    assert not failures, "\n".join(failures)


def _listed_keys():
    """(overrides selecting the plugin, key, type, default) of every config key of every plugin
    `slamkit-plugins` lists (the registry as the command discovers it: the example plugins
    installed beside the built-in ones included)."""
    from slamkit.cli.plugins import config_fields
    from slamkit.registry.discovery import default_registry
    from slamkit.roles import ROLES

    registry = default_registry()
    for role in ROLES:
        for name, entry in sorted(registry.plugins[role.key].items()):
            base = [f"{role.part_of}=gaussian_splatting"] if role.part_of else []
            for key, type_, default, _ in config_fields(entry.spec.config):
                yield [*base, f"{role.group}={name}"], f"{role.path}.{key}", type_, default


def _bad_values(key: str, type_: str, default: str) -> dict[str, str]:
    """The values every key of this type must refuse: of the wrong type (a mapping or a list where
    a scalar is meant, text where a number, boolean, choice or list is), empty (unless empty is
    the default), NaN (a float) and out of range (-1 for a number, unless NEGATIVE_OK)."""
    kinds = [t.strip() for t in type_.split("|")]
    values = {"wrong type": "[1]" if kinds[0] == "str" else "{}"}
    if kinds[0] != "str":
        values["text"] = "not_a_value"
    if default != "''":
        values["empty"] = ""
    if "float" in kinds:
        values["nan"] = "nan"
    if {"int", "float"} & set(kinds) and key not in NEGATIVE_OK:
        values["out of range"] = "-1"
    return values


@pytest.mark.slow  # ~1200 compositions
def test_every_listed_key_refuses_a_wrong_type_empty_nan_and_out_of_range_value_in_one_line_naming_it():
    """Generated from what `slamkit-plugins` lists: each key of each plugin, selected, given each of
    `_bad_values`, through the composition the command uses: one ConfigError line naming the key."""
    from slamkit.cli.plugins import text_listing
    from slamkit.errors import ConfigError
    from slamkit.registry.compose import compose_run
    from slamkit.registry.discovery import default_registry

    keys = list(_listed_keys())
    listing = [line for line in text_listing(default_registry()).splitlines() if line.startswith("      ")]
    assert len(keys) == len(listing) > 250  # every key the command lists, once
    failures, cases = [], 0
    for base, key, type_, default in keys:
        for what, value in _bad_values(key, type_, default).items():
            cases += 1
            try:
                compose_run([*base, f"{key}={value}"])
                failures.append(f"{key}={value} ({what}) accepted")
            except ConfigError as exc:
                if key not in str(exc) or "\n" in str(exc):
                    failures.append(f"{key}={value} ({what}): {exc}")
    assert cases > 1000
    assert not failures, "\n".join(failures)


# --- a stop signal ends the run within a bound, in every phase (issue 45) -------------------------

#: Seconds from a stop signal to the command's exit, at most, in any phase (docs/architecture.md).
SIGNAL_EXIT_BOUND_S = 5.0
#: Real time with everything beside tracking busy: the mapper, the keyframe handover and a loop
#: closure of 0.2 s per keyframe, a keyframe every frame at 30 frames/s (90 frames, the 8 played
#: back and forth): its backlog grows by ~5 keyframe-seconds a second, and a call that took every
#: keyframe queued would last seconds by the 60th frame.
BUSY_REALTIME = ("dataset=tum", "dataset.path={data}", "dataset.passes=12", "dataset.max_frames=90",
                 "output.progress=false", "mode=realtime", "realtime.fps_limit=30", "keyframe=every_n",
                 "keyframe.tracking_every=1", "realtime.keyframe_thread=true", "mapper=gaussian_splatting",
                 "mapper/rasterizer=cpu", "loop_closure=slow",
                 "loop_closure.seconds=0.2")
SIGNAL_PHASES = {
    "startup": (TUM_RUN, "startup"),
    "stream-sequential": (TINY_MAPPING, "stream@3"),
    "stream-realtime-busy": (BUSY_REALTIME, "stream@60"),
    "loops-after-the-stream": (BUSY_REALTIME, "loops"),
    "refine": ((*TINY_MAPPING, "final_iterations=100000"), "refine"),
    "map": (TINY_MAPPING, "map"),
    "evaluate": (TINY_MAPPING, "evaluate"),
    "localize-stream": (("mode=localize", "map={tmp}/map", "dataset=tum", "dataset.path={data}",
                         "output.progress=false"),
                        "stream@3"),
}


@pytest.mark.slow
@pytest.mark.parametrize("phase", list(SIGNAL_PHASES))
def test_a_stop_signal_ends_the_run_within_the_bound_in_every_phase(phase, tmp_path, monkeypatch):
    """SIGTERM at each phase's pause point (in real time with the mapper, the keyframe handover
    and a loop closure whose backlog grows: mid-stream, and while the keyframes left after the
    stream are decided): the command exits 143 within SIGNAL_EXIT_BOUND_S seconds, having
    written what it had (metrics.json: interrupted; the checkpoint keeps the keyframes the loop
    closure had not taken)."""
    from slamkit.cli.bench import signal_to_exit
    from slamkit.formats.checkpoint import read_checkpoint

    argv, pause_at = SIGNAL_PHASES[phase]
    data, out = tmp_path / "data", tmp_path / "run"
    tiny_tum(data)
    monkeypatch.setattr(sys, "path", list(sys.path))
    site = tmp_path / "site"
    install("slow")(site.parent)  # the plugin's distribution in tmp_path/site, for the command's process too
    env = {"PYTHONPATH": os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")])}
    if phase.startswith("localize"):  # the map it localises in: a run of the same frames
        made = subprocess.run([str(Path(sys.executable).with_name("slamkit")), "dataset=tum", f"dataset.path={data}",
                               "mapper=none", "output.progress=false", "checkpoint.save=true",
                               f"hydra.run.dir={tmp_path / 'map'}"], cwd=tmp_path, capture_output=True, text=True,
                              timeout=300)
        assert made.returncode == 0, made.stderr[-3000:]
    args = [a.replace("{data}", str(data)).replace("{tmp}", str(tmp_path)) for a in argv] + [f"hydra.run.dir={out}"]
    run = signal_to_exit(args, tmp_path, pause_at, env=env)
    status, seconds, err = run["returncode"], run["seconds"], run["stderr"]
    assert run["reached"], f"never paused at {pause_at} (exit {status}): {err[-3000:]}"
    assert status == 128 + signal.SIGTERM, err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    assert seconds < SIGNAL_EXIT_BOUND_S, f"{phase}: {seconds:.1f} s from SIGTERM to exit"
    if phase == "startup":
        return
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "interrupted" and metrics["num_frames"] > 0
    if phase in ("stream-realtime-busy", "loops-after-the-stream"):
        state = read_checkpoint(out / "checkpoint.zip")["state"]["loop_closure"]
        assert len(state["queued"]) > 0  # the backlog kept, not decided on after the signal
