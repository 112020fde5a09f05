"""Where along the path a loop closure helps or hurts (issue 46): for run folders of the same
sequence (`benchmarks/loop_closure_runs.py --runs-dir DIR`, each with trajectory.txt and
groundtruth.txt), each frame's pose relative to the first frame against the ground truth's
relative pose (translation, cm), the median over each stretch of frames. Unlike the ATE, no
alignment mixes the stretches: a stretch the tracker had already brought back to the first
views' map shows a small error whatever the rest of the path does.

Prints a table and writes JSON (--out).

    python benchmarks/loop_closure_drift_since_start.py --stretches 150:200,200:230,230:260 \\
        none=DIR/tracking_7scenes_none_0 during=DIR2/tracking_7scenes_pose_graph_0 ...
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

from slamkit.cli.bench import markdown_table
from slamkit.formats.tum import read_tum_trajectory
from slamkit.geometry.pose_graph import relative_pose

sys.path.insert(0, str(Path(__file__).resolve().parent))
from loop_closure_runs import truth_by_stamp  # noqa: E402  (the running-system benchmark's)


def drift_since_start(run: Path) -> np.ndarray:
    """Metres, per frame of `run`: the translation between its pose in the first frame's camera
    and the ground truth's (matched by timestamp)."""
    stamps, poses = read_tum_trajectory(run / "trajectory.txt")
    by_stamp = truth_by_stamp(run)
    missing = [float(s) for s in stamps if round(float(s), 6) not in by_stamp]
    if missing:
        raise SystemExit(f"{run}: no ground truth at {len(missing)} frames, the first at {missing[0]:.6f} s "
                         "(expected groundtruth.txt at every frame)")
    truth = np.array([by_stamp[round(float(s), 6)] for s in stamps])
    return np.linalg.norm(relative_pose(relative_pose(poses[0], poses), relative_pose(truth[0], truth))[:, :3, 3],
                          axis=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="NAME=RUN_FOLDER, one per run")
    parser.add_argument("--stretches", required=True, help="FIRST:END,... frame ranges (END excluded)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/loop_closure_drift_since_start.json"))
    args = parser.parse_args()
    stretches = [tuple(int(x) for x in s.split(":")) for s in args.stretches.split(",")]
    rows = []
    for named in args.runs:
        name, _, folder = named.partition("=")
        error = drift_since_start(Path(folder))
        rows.append({"run": name, "folder": folder, "frames": len(error),
                     "median_m": {f"{a}:{b}": float(np.median(error[a:b])) for a, b in stretches}})
    print(markdown_table([["run", *(f"frames {a}-{b - 1}" for a, b in stretches)],
                          *([r["run"], *(f"{100 * v:.2f} cm" for v in r["median_m"].values())] for r in rows)]))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": platform.node(), "when": time.strftime("%Y-%m-%d %H:%M:%S"),
                                    "command": "python " + " ".join(sys.argv), "runs": rows}, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
