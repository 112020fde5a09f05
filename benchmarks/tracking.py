"""Tracking benchmark: G-ICP (ellipse / plane / none) against KISS-ICP and small_gicp on the same
frames, in one run. Frames are loaded into memory first, so disk I/O is not timed; the map grows
with keyframe Gaussians as in a tracking-only run (mapper none). Prints a table (ATE, frames/s,
G-ICP's time split into covariances / neighbour search / solve / keyframes) and writes JSON.

    python benchmarks/tracking.py                       # both shared sequences
    python benchmarks/tracking.py --datasets tum --repeats 3 --out benchmarks/results/tracking.json
    python benchmarks/tracking.py --datasets tum --starts 0,10,20,30,40,50,60   # robustness
    OMP_NUM_THREADS=1 python benchmarks/tracking.py --datasets tum --systems gicp_ellipse --repeats 5

cpu_ms_per_frame is the calling thread's CPU time per frame (steadier than wall time on a shared
machine; all of the tracker's work with OMP_NUM_THREADS=1, its kernels then using one thread);
with --repeats, the minimum over the runs, as for the wall-clock columns.

With several --starts, every system also runs from each start frame to the end, and the table adds
the mean and worst ATE RMSE over the starts (one run's ATE on a 150-frame hand-held sequence moves
by ~1 cm with any change that alters rounding, so one number is a weak comparison).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

from slamkit.cli.bench import markdown_table
from slamkit.metrics import trajectory as evaluation
from slamkit.registry.discovery import default_registry
from slamkit.run.build import build_run

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SEQUENCES = {"tum": DATA / "tum_fr1_rpy_first150", "replica": DATA / "replica_room0_first20"}
SYSTEMS = {  # name -> (tracker, tracker overrides, keyframe policy)
    "gicp_ellipse": ("gicp", {"regularization": "ellipse"}, "overlap"),
    "gicp_plane": ("gicp", {"regularization": "plane"}, "overlap"),
    "gicp_none": ("gicp", {"regularization": "none"}, "overlap"),
    "kiss_icp": ("kiss_icp", {}, "every_n"),
    "small_gicp": ("small_gicp", {}, "every_n"),
}
SPLIT = ("covariance_s", "nn_search_s", "solve_s")


def load_frames(sequence: str) -> list:
    registry = default_registry()
    config = registry.get("dataset", sequence).config(path=str(SEQUENCES[sequence]))
    dataset = registry.create("dataset", sequence, config)
    return [dataset[i] for i in range(len(dataset))]


def run_system(system: str, sequence: str, frames) -> dict:
    tracker_name, overrides, policy_name = SYSTEMS[system]
    _, slam, _ = build_run([f"dataset={sequence}", f"dataset.path={SEQUENCES[sequence]}", f"tracker={tracker_name}",
                            *(f"tracker.{k}={v}" for k, v in overrides.items()), f"keyframe={policy_name}",
                            "mapper=none"])
    slam.initialize(frames[0].gt_pose)
    poses, per_frame, split, lost = [], [], {k: 0.0 for k in SPLIT}, 0
    cpu_start = time.thread_time()
    for frame in frames:
        step = slam.process(frame)
        lost += step.tracking.lost
        poses.append(step.tracking.pose)
        per_frame.append(step.tracking_time_s)
        for key in SPLIT:
            split[key] += step.tracking.stats.get(key, 0.0)
    cpu = time.thread_time() - cpu_start
    total = float(np.sum(per_frame))
    ate = evaluation.ate(np.array(poses), [f.gt_pose for f in frames])
    n = len(frames)
    result = {"system": system, "frames": n, "ate_rmse_m": ate.rmse_m, "ate_mean_m": ate.mean_m,
              "fps": n / total, "ms_per_frame": 1e3 * total / n, "cpu_ms_per_frame": 1e3 * cpu / n,
              "keyframes": slam.num_keyframes,
              "lost": lost}
    if tracker_name == "gicp":
        result.update({f"ms_{k[:-2]}": 1e3 * v / n for k, v in split.items()})
        result["ms_keyframes_other"] = result["ms_per_frame"] - sum(result[f"ms_{k[:-2]}"] for k in SPLIT)
    return result


def best_of(system, sequence, frames, repeats: int) -> dict:
    """ATE from the first run (all runs are deterministic); times from the fastest run."""
    runs = [run_system(system, sequence, frames) for _ in range(repeats)]
    best = min(runs, key=lambda r: r["ms_per_frame"])
    return {**best, "ate_rmse_m": runs[0]["ate_rmse_m"], "ate_mean_m": runs[0]["ate_mean_m"], "repeats": repeats,
            "cpu_ms_per_frame": min(r["cpu_ms_per_frame"] for r in runs)}


def over_starts(system, sequence, frames, starts: list[int]) -> dict:
    """Mean and worst ATE RMSE of runs from each start frame to the end."""
    ates = [run_system(system, sequence, frames[s:])["ate_rmse_m"] for s in starts]
    return {"starts": starts, "ate_rmse_by_start_m": ates, "ate_rmse_starts_mean_m": float(np.mean(ates)),
            "ate_rmse_starts_max_m": float(np.max(ates))}


def print_table(rows: list[dict]) -> None:
    cols = ["dataset", "system", "ate_rmse_m", "ate_mean_m", "ate_rmse_starts_mean_m", "ate_rmse_starts_max_m", "fps",
            "ms_per_frame", "cpu_ms_per_frame", "ms_covariance", "ms_nn_search",
            "ms_solve", "ms_keyframes_other", "fps_vs_kiss", "fps_vs_small_gicp", "ate_vs_small_gicp"]

    def fmt(c, v):
        if v is None:
            return "-"
        if c.startswith("ate_r") or c == "ate_mean_m":
            return f"{100 * v:.3f} cm"
        return f"{v:.2f}" if isinstance(v, float) else str(v)
    print(markdown_table([cols] + [[fmt(c, r.get(c)) for c in cols] for r in rows]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--datasets", default="tum,replica")
    parser.add_argument("--systems", default=",".join(SYSTEMS))
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--starts", default="0", help="comma-separated start frames for the robustness columns")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/tracking.json"))
    args = parser.parse_args()
    rows = []
    for name in args.datasets.split(","):
        frames = load_frames(name)
        starts = [int(v) for v in args.starts.split(",")]
        results = [best_of(s, name, frames, args.repeats) for s in args.systems.split(",")]
        if len(starts) > 1:
            for r in results:
                r.update(over_starts(r["system"], name, frames, [s for s in starts if s < len(frames) - 10]))
        anchors = {r["system"]: r for r in results}
        for r in results:
            r["dataset"] = name
            if "kiss_icp" in anchors:
                r["fps_vs_kiss"] = r["fps"] / anchors["kiss_icp"]["fps"]
            if "small_gicp" in anchors:
                r["fps_vs_small_gicp"] = r["fps"] / anchors["small_gicp"]["fps"]
                r["ate_vs_small_gicp"] = r["ate_rmse_m"] / anchors["small_gicp"]["ate_rmse_m"]
        rows += results
    print_table(rows)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": platform.platform(), "when": time.strftime("%Y-%m-%d %H:%M"),
                                    "rows": rows}, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
