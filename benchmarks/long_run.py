"""Long-run memory: resident memory and map size against frame count on a long synthetic
sequence (default 2000 frames), through the CLI. Prints a table and writes JSON.

    python benchmarks/long_run.py --frames 2000 --out benchmarks/results/long_run.json
    python benchmarks/long_run.py --frames 600 --set mapper=gaussian_splatting --set iterations_per_frame=2
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import tempfile
from pathlib import Path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=2000)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="extra slamkit override")
    parser.add_argument("--points", type=int, default=8, help="rows of the table")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/long_run.json"))
    args = parser.parse_args()
    run_dir = Path(tempfile.mkdtemp(prefix="slamkit-long-"))
    cmd = [str(Path(sys.executable).with_name("slamkit")), f"dataset.num_frames={args.frames}", "progress=false",
           "eval.plot=false", *args.set, f"hydra.run.dir={run_dir}"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        print(proc.stderr[-2000:], file=sys.stderr)
        return 1
    rows = [r for r in csv.DictReader(open(run_dir / "frames.csv")) if r["rss_mb"]]
    picks = [rows[min(len(rows) - 1, round(i * (len(rows) - 1) / (args.points - 1)))] for i in range(args.points)]
    print("| frame | Gaussians | RSS MB |\n|---|---|---|")
    for r in picks:
        print(f"| {r['index']} | {r['num_gaussians']} | {r['rss_mb']} |")
    metrics = json.loads((run_dir / "metrics.json").read_text())
    half = [float(r["rss_mb"]) for r in rows[len(rows) // 2:]]
    growth = (half[-1] - half[0]) / max(1, len(half)) * 1000
    print(f"{metrics['num_frames']} frames, ATE {100 * metrics['ate_rmse_m']:.2f} cm, peak {metrics['peak_memory_mb']:.0f} MB, "
          f"second-half growth {growth:.1f} MB per 1000 frames")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"command": " ".join(cmd[1:]), "metrics": metrics,
                                    "samples": [{k: r[k] for k in ("index", "num_gaussians", "rss_mb")} for r in rows[::10]],
                                    "second_half_growth_mb_per_1000_frames": growth}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
