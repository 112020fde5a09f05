"""Signal to exit (issue 45): how long the `slamkit` command takes to exit after SIGTERM, per phase.

Each case is the real `slamkit` command in a process of its own, on the shared real data, stopped
with SIGTERM once it says it has reached a phase's point (the test hook SLAMKIT_PAUSE_AT: the
tracking thread waits there while everything beside it keeps working); the time measured is from
the signal to the process's exit, everything it writes on the way out included (trajectory,
metrics, map, checkpoint). The phases:

- startup: before the config is composed;
- stream (sequential): TUM fr1/rpy with the 3DGS mapper, after 20 frames;
- stream (real time, the issue's case): 7-Scenes redkitchen, 40 frames played twice, in real time
  with the mapper, the keyframe handover and the pose-graph loop closure, after 60 frames;
- loops: the same run after its stream, where the keyframes the loop thread had not taken yet
  are decided (reached only when it had a backlog: else the row says so);
- refine, map, evaluate: TUM with the mapper and a long refinement, at each phase's start;
- localize: tracking TUM frames 60.. in the map of a run over its first 60 (made first, not timed).

Prints a table (median and largest of `--repeats` runs, and whether the largest is under the
bound of docs/architecture.md, 5 s) and writes JSON (`--out`).

    python benchmarks/signal_exit.py                 # every phase, 3 runs each (~10 min on 2 cores)
    python benchmarks/signal_exit.py --quick         # a smoke test: fewer frames, one run each
    python benchmarks/signal_exit.py --phases stream-realtime,loops --repeats 5

Run it alone on a quiet machine: the figures are wall-clock seconds.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from slamkit.cli.bench import signal_to_exit

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
BOUND_S = 5.0


def phases(data: Path, quick: bool) -> dict[str, tuple[list[str], str]]:
    """{phase: (overrides, pause point)}."""
    tum = ["dataset=tum", f"dataset.path={data / 'tum_fr1_rpy_first150'}", "output.progress=false"]
    kitchen = ["dataset=sevenscenes", f"dataset.path={data / '7scenes_redkitchen_300to999'}", "output.progress=false"]
    frames = 10 if quick else 40
    stream_at = 15 if quick else 60
    realtime = [*kitchen, f"dataset.max_frames={2 * frames}", "dataset.passes=2", "mode=realtime",
                "realtime.fps_limit=30", "tracker=gicp", "mapper=gaussian_splatting", "realtime.keyframe_thread=true",
                "loop_closure=pose_graph"]
    mapping = [*tum, "dataset.max_frames=10" if quick else "dataset.max_frames=30", "mapper=gaussian_splatting",
               "final_iterations=100000"]
    return {
        "startup": ([*tum, "mapper=none"], "startup"),
        "stream-sequential": ([*tum, "dataset.max_frames=40", "mapper=gaussian_splatting"],
                              "stream@5" if quick else "stream@20"),
        "stream-realtime": (realtime, f"stream@{stream_at}"),
        "loops": (realtime, "loops"),
        "refine": (mapping, "refine"),
        "map": ([*mapping[:-1], "final_iterations=20"], "map"),
        "evaluate": ([*mapping[:-1], "final_iterations=20"], "evaluate"),
        "localize": (["mode=localize", "map={map}", *tum, "dataset.start=60"], "stream@5" if quick else "stream@30"),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--phases", default=None, help="only these phases (comma-separated)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="fewer frames, one run of each phase")
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--timeout", type=float, default=900.0)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/signal_exit.json"))
    args = parser.parse_args()
    repeats = 1 if args.quick else args.repeats
    cases = phases(args.data, args.quick)
    chosen = args.phases.split(",") if args.phases else list(cases)
    unknown = [p for p in chosen if p not in cases]
    if unknown:
        parser.error(f"unknown phases {unknown}; expected some of {list(cases)}")
    results = {}
    with tempfile.TemporaryDirectory(prefix="slamkit-signal-exit-") as tmp:
        if "localize" in chosen:
            made = subprocess.run([str(Path(sys.executable).with_name("slamkit")), "dataset=tum",
                                   f"dataset.path={args.data / 'tum_fr1_rpy_first150'}", "dataset.max_frames=60",
                                   "mapper=none", "output.progress=false", "checkpoint.save=true",
                                   f"hydra.run.dir={tmp}/map"], cwd=tmp, capture_output=True, text=True)
            if made.returncode:
                print(f"the map for localize could not be made: {made.stderr.strip().splitlines()[-1:]}")
                return 1
        for phase in chosen:
            overrides, pause_at = cases[phase]
            overrides = [o.replace("{map}", f"{tmp}/map") for o in overrides]
            runs = []
            for k in range(repeats):
                out = Path(tmp) / f"{phase}-{k}"
                run = signal_to_exit([*overrides, f"hydra.run.dir={out}"], Path(tmp), pause_at, timeout=args.timeout)
                run["stderr_tail"] = "".join(run.pop("stderr").splitlines(keepends=True)[-3:])
                metrics = out / "metrics.json"
                run["status"] = json.loads(metrics.read_text()).get("status") if metrics.is_file() else None
                runs.append(run)
                shown = "not reached" if run["seconds"] is None else f"{run['seconds']:.2f} s"
                print(f"{phase} #{k}: {shown}, exit {run['returncode']}, metrics {run['status']}", flush=True)
            seconds = [r["seconds"] for r in runs if r["seconds"] is not None]
            results[phase] = {"overrides": overrides, "pause_at": pause_at, "runs": runs,
                              "median_s": statistics.median(seconds) if seconds else None,
                              "max_s": max(seconds) if seconds else None,
                              "exit_143": all(r["returncode"] == 128 + signal.SIGTERM for r in runs if r["reached"])}
    print(f"\n{'phase':<18} {'runs':>5} {'median s':>9} {'max s':>7}  {'< ' + str(BOUND_S) + ' s':<8} exit 143")
    for phase, r in results.items():
        reached = sum(run["reached"] for run in r["runs"])
        median = "-" if r["median_s"] is None else f"{r['median_s']:.2f}"
        largest = "-" if r["max_s"] is None else f"{r['max_s']:.2f}"
        within = "-" if r["max_s"] is None else ("yes" if r["max_s"] < BOUND_S else "NO")
        print(f"{phase:<18} {reached:>2}/{len(r['runs']):<2} {median:>9} {largest:>7}  {within:<8} "
              f"{'yes' if r['exit_143'] else 'NO'}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": platform.platform(), "cpus": os.cpu_count(),
                                    "when": time.strftime("%Y-%m-%d %H:%M"), "bound_s": BOUND_S, "quick": args.quick,
                                    "phases": results}, indent=2) + "\n")
    print(f"written {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
