"""Long-run memory: resident memory and map size against frame count on a long synthetic
sequence (default 2000 frames), or a real one looped (`--dataset`, `--path`, `--passes`: the
frames played back and forth), through the CLI. Prints a table every `--every` frames and
writes JSON (`benchmarks/plot_long_run.py` plots it).

    python benchmarks/long_run.py --frames 2000 --out benchmarks/results/long_run.json
    OMP_NUM_THREADS=1 python benchmarks/long_run.py --frames 2000 --mapper --max-gaussians none,200000 \\
        --time-limit 1500 --out benchmarks/results/long_run_mapper.json
    OMP_NUM_THREADS=1 python benchmarks/long_run.py --dataset tum --path ../shared/data/tum_fr1_rpy_first150 \\
        --passes 4 --mapper --variant before=mapper.admission.skip_covered=false --variant after= --out looped.json

`--mapper` runs the 3DGS mapper with settings cheap enough for a CPU (`--iterations` steps per
frame, no final iterations, evaluation of every `--eval-every`-th frame); `--max-gaussians` runs
one variant per `mapper.memory_cap.max_gaussians` (`none` = no cap). `--time-limit` stops a run
that is still going after that many seconds (SIGTERM: slamkit writes what it has; the run is
reported as incomplete, up to the frame it reached). `--set KEY=VALUE` passes any other slamkit override;
`--variant LABEL="OVERRIDES"` (repeatable, space-separated overrides) runs one variant per label
instead of one per memory cap.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=None,
                        help="synthetic: frames to generate (default 2000); a real dataset: frames played, all passes "
                             "counted (default all)")
    parser.add_argument("--dataset", default="synthetic", help="dataset plugin (synthetic, tum, replica, ...)")
    parser.add_argument("--path", default=None, help="the dataset's folder (a real dataset)")
    parser.add_argument("--passes", type=int, default=1, help="play the frames back and forth this many times")
    parser.add_argument("--variant", action="append", default=[], metavar='LABEL="OVERRIDES"',
                        help="one run with these extra overrides (repeatable)")
    parser.add_argument("--sample-every", type=int, default=10, help="frames between the JSON's samples")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="extra slamkit override")
    parser.add_argument("--every", type=int, default=250, help="frames between table rows")
    parser.add_argument("--mapper", action="store_true", help="map with mapper=gaussian_splatting")
    parser.add_argument("--iterations", type=int, default=4, help="mapping steps per frame (with --mapper)")
    parser.add_argument("--eval-every", type=int, default=50, help="evaluate every n-th frame (with --mapper)")
    parser.add_argument("--max-gaussians", default=None,
                        help="comma-separated memory caps, one run each; none = no guard (with --mapper)")
    parser.add_argument("--time-limit", type=float, default=None, help="seconds before a run is stopped")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/long_run.json"))
    args = parser.parse_args()
    if args.max_gaussians and not args.mapper:
        parser.error("--max-gaussians needs --mapper")
    if args.max_gaussians and args.variant:
        parser.error("--max-gaussians and --variant: choose one")
    if args.dataset != "synthetic" and not args.path:
        parser.error(f"--dataset {args.dataset} needs --path")
    runs = [run_variant(args, label, overrides) for label, overrides in variants(args)]
    if len(runs) > 1:
        print_comparison(runs)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"frames": args.frames, "dataset": args.dataset, "passes": args.passes,
                                    "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
                                    "runs": runs}, indent=2) + "\n")
    return 0 if all(r["returncode"] in (0, 130) for r in runs) else 1


def variants(args) -> list[tuple[str, list[str]]]:
    """(label, slamkit overrides) for each run."""
    if args.dataset == "synthetic":
        base = {"dataset.num_frames": str(args.frames or 2000)}
    else:
        base = {"dataset": args.dataset, "dataset.path": str(Path(args.path).resolve())}
        if args.frames:
            base["dataset.max_frames"] = str(args.frames)
    if args.passes > 1:
        base["dataset.passes"] = str(args.passes)
    base.update({"output.progress": "false", "output.plot": "false"})
    if args.mapper:
        base.update({"mapper": "gaussian_splatting", "iterations_per_frame": str(args.iterations),
                     "final_iterations": "0", "mapper.eval_every": str(args.eval_every)})
    for item in args.set:  # the user's values win
        key, _, value = item.partition("=")
        base[key] = value
    out = []
    for item in args.variant:
        label, _, extra = item.partition("=")
        overrides = dict(base)
        for override in extra.split():
            key, _, value = override.partition("=")
            overrides[key] = value
        out.append((label, [f"{k}={v}" for k, v in overrides.items()]))
    if out:
        return out
    caps = [c.strip() for c in args.max_gaussians.split(",")] if args.max_gaussians else [None]
    for cap in caps:
        overrides = dict(base)
        if cap is not None:
            overrides["mapper.memory_cap.max_gaussians"] = "null" if cap.lower() == "none" else cap
        cap_label = overrides.get("mapper.memory_cap.max_gaussians", "null")
        label = "tracking only" if not args.mapper else f"max_gaussians={cap_label}"
        out.append((label, [f"{k}={v}" for k, v in overrides.items()]))
    return out


def run_variant(args, label: str, overrides: list[str]) -> dict:
    """Run slamkit once; print its table; return the record for the JSON."""
    run_dir = Path(tempfile.mkdtemp(prefix="slamkit-long-"))
    cmd = [str(Path(sys.executable).with_name("slamkit")), *overrides, f"hydra.run.dir={run_dir}"]
    print(f"\n## {label}\n\n`slamkit {' '.join(overrides)}`\n", flush=True)
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    stopped = False
    try:
        _, stderr = proc.communicate(timeout=args.time_limit)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGTERM)  # slamkit writes its outputs and exits with 130
        _, stderr = proc.communicate()
        stopped = True
    wall = time.perf_counter() - start
    if proc.returncode not in (0, 130) or not (run_dir / "metrics.json").exists():
        print(stderr[-2000:], file=sys.stderr)
        return {"label": label, "command": "slamkit " + " ".join(overrides), "returncode": proc.returncode}
    rows = [r for r in csv.DictReader(open(run_dir / "frames.csv")) if r["rss_mb"]]
    checkpoints = table(rows, args.every)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    print(summary(metrics, stopped, wall))
    return {"label": label, "command": "slamkit " + " ".join(overrides), "returncode": proc.returncode,
            "stopped_by_time_limit": stopped, "process_wall_s": wall, "run_dir": str(run_dir), "metrics": metrics,
            "checkpoints": checkpoints,
            "samples": [{k: r[k] for k in ("index", "num_gaussians", "rss_mb")} for r in rows[::args.sample_every]]}


def table(rows: list[dict], every: int) -> list[dict]:
    """Print and return, every `every` frames and at the last one: frame, keyframes so far,
    Gaussians, resident memory (MB) at that frame and the largest so far, and the SLAM time so
    far (tracking + mapping, s) with its frames/s."""
    out, peak, slam_s, keyframes = [], 0.0, 0.0, 0
    for i, r in enumerate(rows):
        rss = float(r["rss_mb"])
        peak = max(peak, rss)
        slam_s += (float(r["tracking_ms"] or 0) + float(r["mapping_ms"] or 0)) / 1e3
        keyframes += r["keyframe"] != "none"
        frame = int(r["index"])
        if (frame + 1) % every == 0 or frame == 0 or i == len(rows) - 1:
            out.append({"frame": frame + 1, "keyframes": keyframes, "num_gaussians": int(r["num_gaussians"]),
                        "rss_mb": rss, "peak_rss_mb": peak, "slam_s": slam_s, "fps": (i + 1) / slam_s})
    print("| frames | keyframes | Gaussians | RSS MB | peak RSS MB so far | SLAM s so far | frames/s so far |")
    print("|---|---|---|---|---|---|---|")
    for c in out:
        print(f"| {c['frame']} | {c['keyframes']} | {c['num_gaussians']:,} | {c['rss_mb']:.0f} "
              f"| {c['peak_rss_mb']:.0f} "
              f"| {c['slam_s']:.0f} | {c['fps']:.2f} |")
    return out


def summary(m: dict, stopped: bool, wall: float) -> str:
    ate = "n/a" if m["ate_rmse_m"] is None else f"{100 * m['ate_rmse_m']:.2f} cm"
    text = (f"\n{m['num_frames']} frames{' (stopped by the time limit)' if stopped else ''}, "
            f"ATE RMSE {ate}, {m['fps']:.2f} frames/s, {m['num_gaussians']:,} Gaussians, "
            f"peak {m['peak_memory_mb']:.0f} MB (ru_maxrss), process {wall:.0f} s")
    if m.get("psnr") is not None:
        text += (f", PSNR {m['psnr']:.2f} dB, {m['pruned_by_memory_cap']:,} pruned by the memory cap, "
                 f"keyframe images {m['keyframe_memory_mb']:.1f} MB")
    return text


def print_comparison(runs: list[dict]) -> None:
    """Peak resident memory (MB so far) and Gaussians side by side, per frame count."""
    ok = [r for r in runs if "checkpoints" in r]
    frames = sorted({c["frame"] for r in ok for c in r["checkpoints"]})
    print("\n| frames | " + " | ".join(f"{r['label']}: peak MB, Gaussians" for r in ok) + " |")
    print("|---|" + "---|" * len(ok))
    for f in frames:
        cells = []
        for r in ok:
            c = next((c for c in r["checkpoints"] if c["frame"] == f), None)
            cells.append("-" if c is None else f"{c['peak_rss_mb']:.0f}, {c['num_gaussians']:,}")
        print(f"| {f} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    sys.exit(main())
