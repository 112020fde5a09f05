"""Sweep launchers' overhead: the same grid of short tracking-only runs on TUM through Hydra's basic
launcher (one job after another, in-process: the anchor), joblib and Ray, timed from the command's
start to its end. The overhead per job is (launcher wall - basic wall) / jobs when both run the
jobs one at a time; with 2 jobs at once the launchers also gain from parallelism, shown apart.

    OMP_NUM_THREADS=1 python benchmarks/sweep_overhead.py --jobs 4 --frames 20 --out /tmp/sweep.json
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TUM = REPO.parent / "shared" / "data" / "tum_fr1_rpy_first150"
SLAMKIT = Path(sys.executable).with_name("slamkit")
LAUNCHERS = {  # name -> overrides
    "basic": [],
    "joblib_1": ["hydra/launcher=joblib", "hydra.launcher.n_jobs=1"],
    "ray_1": ["hydra/launcher=ray", "hydra.launcher.ray.init.num_cpus=1"],
    "joblib_2": ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2"],
    "ray_2": ["hydra/launcher=ray", "hydra.launcher.ray.init.num_cpus=2"],
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--jobs", type=int, default=4)
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    seeds = ",".join(str(s) for s in range(args.jobs))
    grid = ["-m", "dataset=tum", f"dataset.path={TUM}", f"dataset.max_frames={args.frames}", "mapper=none",
            "tracker=gicp", f"seed={seeds}", "output.progress=false", "output.plot=false"]
    work = Path(tempfile.mkdtemp(prefix="sweep_overhead_"))
    env = dict(os.environ, SLAMKIT_CACHE=str(work / "cache"))
    results = {}
    try:
        for name, overrides in LAUNCHERS.items():
            start = time.perf_counter()
            proc = subprocess.run([str(SLAMKIT), *grid, *overrides, f"hydra.sweep.dir={work / name}"], env=env,
                                  capture_output=True, text=True)
            wall = time.perf_counter() - start
            if proc.returncode != 0:
                raise SystemExit(f"{name} failed: {proc.stderr[-2000:]}")
            run_walls = [json.loads(p.read_text())["wall_time_s"] for p in (work / name).glob("*/metrics.json")]
            results[name] = {"wall_s": wall, "jobs": len(run_walls), "run_wall_s_sum": sum(run_walls)}
    finally:
        shutil.rmtree(work, ignore_errors=True)
    basic = results["basic"]["wall_s"]
    print(f"{args.jobs} jobs of {args.frames} TUM frames (G-ICP, no mapping)")
    print(f"{'launcher':10s} {'wall s':>7s} {'vs basic':>8s} {'overhead/job s':>14s}")
    for name, r in results.items():
        r["overhead_per_job_s"] = (r["wall_s"] - basic) / args.jobs
        print(f"{name:10s} {r['wall_s']:7.1f} {r['wall_s'] / basic:8.2f} {r['overhead_per_job_s']:14.2f}")
    if args.out:
        args.out.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
