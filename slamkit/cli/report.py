"""`slamkit-report DIR [DIR ...]`: one table from many runs (a Hydra multirun directory, or run
directories), written into the first DIR as report.csv, report.md and PNG plots.

A row is one configuration: the overrides that differ between runs (the swept values) and the
metrics. Runs that differ only in `seed` are one row: mean and standard deviation. The `status`
column says what became of the runs (metrics.json's `status`: completed, interrupted, failed;
running for a run still going or killed): only completed runs are aggregated and plotted, each
unfinished run is a row of its own with its error (`--include-unfinished` aggregates them too),
and a run whose metrics.json cannot be read is a row (status unreadable) with the reason.

Every job of a sweep is a row: a job folder (Hydra's `.hydra/`) without metrics.json is running
while a process holds it (`slamkit.run.ownership`), else failed, with the last error of its log
(a bad value in one job stops a sweep there); a job of the sweep's own record (multirun.yaml,
Hydra's basic sweeper) that has no folder is `not run`, with its overrides.
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from slamkit.cli import paper_tables, streams
from slamkit.cli.run_folders import NOT_RUN, STATUSES, find_runs, load_run, not_run
from slamkit.errors import DataError, SlamkitError
from slamkit.formats.atomic import atomic_open, write_atomic
from slamkit.formats.plots import save_figure
from slamkit.formats.tum import read_tum_trajectory
from slamkit.metrics import trajectory as evaluation

METRICS = ["ate_rmse_m", "ate_mean_m", "rpe_trans_rmse_m", "fps", "tracking_fps", "psnr", "ssim",
           "psnr_train", "psnr_test", "depth_l1_cm", "num_keyframes", "num_gaussians", "lost_frames", "peak_memory_mb",
           "mapping_train_time_s", "mapping_train_cpu_s", "wall_time_s", "num_frames"]
#: Columns of the tables that are no plot: counts of the input, not results.
UNPLOTTED = ("num_frames", "lost_frames")


def swept_keys(runs: list[dict]) -> list[str]:
    keys = sorted({k for r in runs for k in r["settings"]})
    return [k for k in keys if len({r["settings"].get(k) for r in runs}) > 1]


def aggregate(runs: list[dict], include_unfinished: bool = False) -> tuple[list[str], list[dict]]:
    """Rows keyed by the swept values other than seed, with mean/std/n per metric: the completed
    runs (all readable runs with `include_unfinished`) of each configuration in one row, then
    each other run in a row of its own (its metrics as they stand, its error)."""
    keys = [k for k in swept_keys([r for r in runs if r["status"] != "unreadable"]) if k != "seed"]
    pooled = [r for r in runs if r["status"] == "completed"
              or (include_unfinished and r["status"] not in ("unreadable", NOT_RUN))]
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in pooled:
        groups[tuple(r["settings"].get(k, "") for k in keys)].append(r)
    rows = [_row(keys, values, members, pooled=True) for values, members in groups.items()]
    rows += [_row(keys, tuple(r["settings"].get(k, "") for k in keys), [r], pooled=False)
             for r in runs if r not in pooled]
    return keys, rows


def _row(keys: list[str], values: tuple, members: list[dict], pooled: bool) -> dict:
    statuses = sorted({m["status"] for m in members}, key=lambda s: (s != "completed", s))
    row = {"config": dict(zip(keys, values)), "runs": [str(m["run"]) for m in members], "n": len(members),
           "status": statuses[0] if len(statuses) == 1 else ", ".join(
               f"{sum(m['status'] == s for m in members)} {s}" for s in statuses),
           "error": "; ".join(f"{m['run'].name}: {m['error']}" if len(members) > 1 else m["error"]
                              for m in members if m["error"]),
           "aggregate": pooled}
    for name in METRICS:
        vals = [m["metrics"].get(name) for m in members]
        vals = [float(v) for v in vals if isinstance(v, (int, float)) and not isinstance(v, bool)]
        row[name] = (float(np.mean(vals)), float(np.std(vals))) if vals else None
    return row


def _fmt(cell, n: int) -> str:
    if cell is None:
        return "-"
    mean, std = cell
    text = f"{mean:.4g}"
    return f"{text} ± {std:.2g}" if n > 1 else text


def write_tables(out: Path, keys: list[str], rows: list[dict]) -> None:
    metrics = [m for m in METRICS if any(r[m] is not None for r in rows)]
    with atomic_open(out / "report.csv", "w") as f:
        writer = csv.writer(f)
        writer.writerow(keys + ["status", "n"] + [c for m in metrics for c in (m, m + "_std")] + ["error"])
        for r in rows:
            cells = [c for m in metrics for c in (r[m] or (None, None))]
            writer.writerow([r["config"][k] for k in keys] + [r["status"], r["n"]]
                            + ["" if c is None else c for c in cells] + [r["error"]])
    header = keys + ["status", "n"] + metrics + ["error"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in rows:
        cells = [r["config"][k] for k in keys] + [r["status"], str(r["n"])] + [_fmt(r[m], r["n"]) for m in metrics]
        lines.append("| " + " | ".join(cells + [r["error"].replace("|", "/") or "-"]) + " |")
    write_atomic(out / "report.md", "\n".join(lines) + "\n")


def _label(row: dict) -> str:
    return ", ".join(f"{k.split('.')[-1]}={v}" for k, v in row["config"].items()) or "run"


def write_plots(out: Path, rows: list[dict]) -> list[Path]:
    """A bar chart per metric and the trajectories, of the aggregated rows only."""
    from matplotlib.figure import Figure

    rows = [r for r in rows if r["aggregate"]]
    written = []
    for name in METRICS:
        if name in UNPLOTTED or not any(r[name] is not None for r in rows):
            continue
        fig = Figure(figsize=(max(4, 1.2 * len(rows)), 3.5), layout="constrained")
        ax = fig.add_subplot()
        means = [r[name][0] if r[name] else np.nan for r in rows]
        stds = [r[name][1] if r[name] else 0 for r in rows]
        spread = any(r["n"] > 1 for r in rows)  # a standard deviation over one run is no error bar
        ax.bar(range(len(rows)), means, yerr=stds if spread else None, capsize=4, color="tab:blue")
        ax.set_xticks(range(len(rows)), [_label(r) for r in rows], rotation=20, ha="right", fontsize=8)
        ax.set_ylabel(name)
        ax.set_title(f"{name} by configuration" + (" (mean ± std over runs)" if spread else ""), fontsize=9)
        path = out / f"bar_{name}.png"
        save_figure(fig, path)
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
        try:
            t_est, est = read_tum_trajectory(run / "trajectory.txt")
        except DataError:  # no trajectory (a run without frames), or not one: not drawn
            continue
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
    save_figure(fig, path)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="slamkit-report", description=__doc__.split("\n\n")[0])
    parser.add_argument("dirs", nargs="*", type=Path, help="multirun or run directories")
    parser.add_argument("--out", type=Path, default=None, help="where to write (default: the first DIR)")
    parser.add_argument("--include-unfinished", action="store_true",
                        help="aggregate interrupted, failed and running runs with the completed ones")
    parser.add_argument("--paper", choices=(*paper_tables.NAMES, *paper_tables.ALIASES, "all"), default=None,
                        metavar="TABLE",
                        help="also print the runs as the paper's TABLE with its figures beside ours, into "
                             f"paper_TABLE.md ({', '.join(paper_tables.NAMES)}; all: every table that has runs)")
    parser.add_argument("--html", type=Path, default=None, metavar="OUT",
                        help="with --paper all: write one self-contained HTML page of every table, figure, run "
                             "setting and provenance to OUT")
    parser.add_argument("--docs", type=Path, metavar="FILE",
                        help="rewrite the generated tables of the Markdown FILE (its '<!-- slamkit-report ... -->' "
                             "blocks) from the runs they name, folders relative to the current directory")
    parser.add_argument("--check", action="store_true",
                        help="with --docs: write nothing, exit 1 when FILE differs from its runs")
    streams.guard()  # a closed, broken or full stdout / stderr never stops the command
    args = parser.parse_args(argv)
    if args.docs is not None:
        return _docs(args.docs, args.check)
    if not args.dirs:
        parser.error("give run folders (or --docs FILE)")
    if args.html is not None and args.paper != "all":
        parser.error("--html needs --paper all")
    out = args.out or args.dirs[0]
    try:
        folders = find_runs(args.dirs)
        runs = [load_run(r) for r in folders] + not_run(args.dirs, folders)
        keys, rows = aggregate(runs, args.include_unfinished)
        out.mkdir(parents=True, exist_ok=True)
        write_tables(out, keys, rows)
        write_plots(out, rows)
    except SlamkitError as exc:
        print(f"slamkit-report: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a read-only or full place
        print(f"slamkit-report: error: cannot write the report into {out}: {exc.strerror or exc} (--out names another "
              "folder)", file=sys.stderr)
        return 1
    print((out / "report.md").read_text(), end="")
    if args.paper == "all":
        from slamkit.cli import paper_html

        for name in paper_tables.NAMES:
            if paper_html.table_runs(name, runs):
                paper_tables.report(name, paper_html.table_runs(name, runs), out)
        if args.html is not None:
            try:
                paper_html.paper_html(runs, args.html)
            except OSError as exc:
                print(f"slamkit-report: error: cannot write {args.html}: {exc.strerror or exc}", file=sys.stderr)
                return 1
            print(f"slamkit-report: wrote {args.html}", file=sys.stderr)
    elif args.paper:
        paper_tables.report(args.paper, runs, out)
    counts = ", ".join(f"{sum(r['status'] == s for r in runs)} {s}" for s in (*STATUSES, "unreadable", NOT_RUN)
                       if any(r["status"] == s for r in runs))
    print(f"slamkit-report: {len(runs)} runs ({counts}), {len(rows)} rows; wrote report.csv, report.md and plots "
          f"into {out}", file=sys.stderr)
    return 0


def _docs(path: Path, check: bool) -> int:
    """--docs: the document's generated blocks rewritten (or, --check, compared)."""
    try:
        text = path.read_text()
    except OSError as exc:
        print(f"slamkit-report: error: {path}: cannot read it ({exc.strerror or exc}; expected a Markdown file)",
              file=sys.stderr)
        return 2
    try:
        new = paper_tables.regenerate_document(text, Path.cwd())
    except (SlamkitError, ValueError) as exc:
        print(f"slamkit-report: error: {path}: {exc}", file=sys.stderr)
        return 2
    if new == text:
        print(f"slamkit-report: {path} agrees with its runs", file=sys.stderr)
        return 0
    if check:
        print(f"slamkit-report: {path} differs from its runs (slamkit-report --docs {path} rewrites it)",
              file=sys.stderr)
        return 1
    write_atomic(path, new)
    print(f"slamkit-report: rewrote the generated tables of {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
