"""`slamkit-report DIR [DIR ...]`: one table from many runs (a Hydra multirun directory, or run
directories), written into the first DIR as report.csv, report.md and PNG plots.

A row is one configuration: the overrides that differ between runs (the swept values) and the
metrics. Runs that differ only in `seed` are one row: mean and standard deviation.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import yaml

from slamkit.metrics import trajectory as evaluation
from slamkit.errors import DataError, SlamkitError
from slamkit.formats.tum import read_tum_trajectory

METRICS = ["ate_rmse_m", "ate_mean_m", "rpe_trans_rmse_m", "fps", "tracking_fps", "psnr", "ssim",
           "psnr_train", "psnr_test", "depth_l1_cm", "num_keyframes", "num_gaussians", "lost_frames", "peak_memory_mb",
           "mapping_train_time_s", "mapping_train_cpu_s", "wall_time_s"]


def find_runs(dirs: list[Path]) -> list[Path]:
    """Run directories (holding metrics.json) under the given folders, sorted."""
    runs = sorted({p.parent for d in dirs for p in Path(d).rglob("metrics.json")})
    if not runs:
        raise DataError(f"no runs (metrics.json) found under {', '.join(map(str, dirs))}")
    return runs


def load_run(run: Path) -> dict:
    overrides_file = run / ".hydra" / "overrides.yaml"
    overrides = yaml.safe_load(overrides_file.read_text()) if overrides_file.exists() else []
    settings = {}
    for item in overrides or []:
        key, _, value = item.lstrip("+~").partition("=")
        if not key.startswith("hydra"):
            settings[key] = value
    try:
        metrics = json.loads((run / "metrics.json").read_text())
    except json.JSONDecodeError as exc:
        raise DataError(f"{run / 'metrics.json'}: not valid JSON ({exc})") from exc
    return {"run": run, "settings": settings, "metrics": metrics}


def swept_keys(runs: list[dict]) -> list[str]:
    keys = sorted({k for r in runs for k in r["settings"]})
    return [k for k in keys if len({r["settings"].get(k) for r in runs}) > 1]


def aggregate(runs: list[dict]) -> tuple[list[str], list[dict]]:
    """Rows keyed by the swept values other than seed, with mean/std/n per metric."""
    keys = [k for k in swept_keys(runs) if k != "seed"]
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in runs:
        groups[tuple(r["settings"].get(k, "") for k in keys)].append(r)
    rows = []
    for values, members in groups.items():
        row = {"config": dict(zip(keys, values)), "runs": [str(m["run"]) for m in members], "n": len(members)}
        for name in METRICS:
            vals = [m["metrics"].get(name) for m in members]
            vals = [float(v) for v in vals if isinstance(v, (int, float))]
            row[name] = (float(np.mean(vals)), float(np.std(vals))) if vals else None
        rows.append(row)
    return keys, rows


def _fmt(cell, n: int) -> str:
    if cell is None:
        return "-"
    mean, std = cell
    text = f"{mean:.4g}"
    return f"{text} ± {std:.2g}" if n > 1 else text


def write_tables(out: Path, keys: list[str], rows: list[dict]) -> None:
    metrics = [m for m in METRICS if any(r[m] is not None for r in rows)]
    with open(out / "report.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(keys + ["n"] + [c for m in metrics for c in (m, m + "_std")])
        for r in rows:
            cells = [c for m in metrics for c in (r[m] or (None, None))]
            writer.writerow([r["config"][k] for k in keys] + [r["n"]] + ["" if c is None else c for c in cells])
    header = keys + ["n"] + metrics
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in rows:
        lines.append("| " + " | ".join([r["config"][k] for k in keys] + [str(r["n"])]
                                       + [_fmt(r[m], r["n"]) for m in metrics]) + " |")
    (out / "report.md").write_text("\n".join(lines) + "\n")


def _label(row: dict) -> str:
    return ", ".join(f"{k.split('.')[-1]}={v}" for k, v in row["config"].items()) or "run"


def write_plots(out: Path, rows: list[dict]) -> list[Path]:
    from matplotlib.figure import Figure

    written = []
    for name in METRICS:
        if not any(r[name] is not None for r in rows):
            continue
        fig = Figure(figsize=(max(4, 1.2 * len(rows)), 3.5), layout="constrained")
        ax = fig.add_subplot()
        means = [r[name][0] if r[name] else np.nan for r in rows]
        stds = [r[name][1] if r[name] else 0 for r in rows]
        ax.bar(range(len(rows)), means, yerr=stds, capsize=4, color="tab:blue")
        ax.set_xticks(range(len(rows)), [_label(r) for r in rows], rotation=20, ha="right", fontsize=8)
        ax.set_ylabel(name)
        path = out / f"bar_{name}.png"
        fig.savefig(path, dpi=100)
        written.append(path)
    written.append(_plot_trajectories(out, rows))
    return [p for p in written if p]


def _plot_trajectories(out: Path, rows: list[dict]) -> Path | None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 5), layout="constrained")
    ax = fig.add_subplot()
    gt_drawn = False
    for r in rows:
        run = Path(r["runs"][0])
        if not (run / "trajectory.txt").exists():
            continue
        t_est, est = read_tum_trajectory(run / "trajectory.txt")
        positions = est[:, :3, 3]
        if (run / "groundtruth.txt").exists():
            t_gt, gt = read_tum_trajectory(run / "groundtruth.txt")
            index = {round(t, 6): i for i, t in enumerate(t_est)}
            gt_full = [None] * len(est)
            for t, pose in zip(t_gt, gt):
                if round(t, 6) in index:
                    gt_full[index[round(t, 6)]] = pose
            result = evaluation.ate(est, gt_full)
            if result.rmse_m is not None:
                positions = result.est_aligned
                if not gt_drawn:
                    ax.plot(gt[:, 0, 3], gt[:, 1, 3], "k--", lw=2, label="ground truth")
                    gt_drawn = True
        ax.plot(positions[:, 0], positions[:, 1], lw=1, label=_label(r))
    if not ax.lines:
        return None
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(fontsize=7)
    path = out / "trajectories.png"
    fig.savefig(path, dpi=100)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="slamkit-report", description=__doc__.split("\n\n")[0])
    parser.add_argument("dirs", nargs="+", type=Path, help="multirun or run directories")
    parser.add_argument("--out", type=Path, default=None, help="where to write (default: the first DIR)")
    args = parser.parse_args(argv)
    try:
        runs = [load_run(r) for r in find_runs(args.dirs)]
        keys, rows = aggregate(runs)
        out = args.out or args.dirs[0]
        out.mkdir(parents=True, exist_ok=True)
        write_tables(out, keys, rows)
        write_plots(out, rows)
    except SlamkitError as exc:
        print(f"slamkit-report: error: {exc}", file=sys.stderr)
        return 2
    print((out / "report.md").read_text(), end="")
    print(f"slamkit-report: {len(runs)} runs, {len(rows)} rows; wrote report.csv, report.md and plots into {out}",
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
