"""Where a running system's pose graph differs from one built without loop closure (issue 46):
for a run with `loop_closure=pose_graph` and the same sequence's run with `loop_closure=none`
(both run folders of `benchmarks/loop_closure_runs.py --runs-dir DIR`, with ground truth):

- each odometry edge's translation error against the ground truth's relative pose (the
  pose_graph run's edges from pose_graph.g2o; the none run's from its keyframes.txt), summed
  over the whole path: whether the odometry after the corrections is worse edge by edge;
- the keyframes' ATE of the run's graph as it ended, and of the same graph with an exact loop
  (the ground truth's relative pose, the loop's own information) at each accepted pair: whether
  what is left is the loops' error or the graph's odometry.

With `--other RUN` (the same sequence's pose_graph run with another setting, such as
`loop_closure.colour_odometry=true`): each odometry edge between the same two keyframes (by
timestamp) whose relative poses in the two graphs are more than `--apart-cm` apart, with its
error against the ground truth in each: which edges the setting moved, and whether towards the
truth.

Prints a table and writes JSON (--out).

    python benchmarks/loop_closure_runs.py --cases synthetic --sequences synthetic_revisit_rotated --runs-dir DIR
    python benchmarks/loop_closure_graph_trace.py \\
        DIR/synthetic_synthetic_revisit_rotated_pose_graph_0 DIR/synthetic_synthetic_revisit_rotated_none_0
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
from slamkit.formats.g2o import read_g2o
from slamkit.formats.tum import read_tum_trajectory
from slamkit.geometry.pose_graph import PoseGraph, PoseGraphEdge, relative_pose
from slamkit.metrics.trajectory import ate
from slamkit_plugins.loop_closures.pose_graph import optimisation
from slamkit_plugins.loop_closures.pose_graph.config import PoseGraphConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
from loop_closure_runs import keyframe_truth  # noqa: E402  (the running-system benchmark's)


def edge_errors(measured: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(E,) metres: translation of each measured relative pose against the truth's ((E,4,4) each)."""
    return np.linalg.norm(relative_pose(measured, truth)[:, :3, 3], axis=1)


def trace(run: Path, none_run: Path) -> dict:
    graph = read_g2o(run / "pose_graph.g2o")
    truth = keyframe_truth(run)  # by keyframe id
    _, none_poses = read_tum_trajectory(none_run / "keyframes.txt")
    none_truth = keyframe_truth(none_run)
    odometry = [e for e in graph.edges if e.kind == "odometry"]
    loops = [e for e in graph.edges if e.kind == "loop"]

    def truth_between(e: PoseGraphEdge) -> np.ndarray:
        return relative_pose(truth[e.source], truth[e.target])

    ran = edge_errors(np.array([e.relative_pose for e in odometry]), np.array([truth_between(e) for e in odometry]))
    alone = edge_errors(relative_pose(none_poses[:-1], none_poses[1:]), relative_pose(none_truth[:-1], none_truth[1:]))
    exact = [PoseGraphEdge("loop", e.source, e.target, truth_between(e), e.information) for e in loops]
    cfg = PoseGraphConfig()
    with_exact = optimisation.optimise(PoseGraph(graph.keyframe_ids, graph.poses, tuple(odometry + exact)),
                                       cfg.backend, cfg.robust_width)
    graph_truth = truth[graph.keyframe_ids]
    return {"run": str(run), "none_run": str(none_run), "keyframes": len(truth), "none_keyframes": len(none_poses),
            "loops": len(loops), "odometry_error_sum_m": float(ran.sum()),
            "none_odometry_error_sum_m": float(alone.sum()),
            "keyframe_ate_m": ate(graph.poses, graph_truth).rmse_m,
            "keyframe_ate_exact_loops_m": ate(with_exact, graph_truth).rmse_m,
            "none_keyframe_ate_m": ate(none_poses, none_truth).rmse_m}


def odometry_by_stamps(run: Path) -> dict[tuple[float, float], tuple[np.ndarray, np.ndarray]]:
    """(source stamp, target stamp) -> (the odometry edge's relative pose in pose_graph.g2o, the
    ground truth's), for every odometry edge whose keyframes have ground truth."""
    graph = read_g2o(run / "pose_graph.g2o")
    stamps, _ = read_tum_trajectory(run / "keyframes.txt")
    truth = keyframe_truth(run)
    return {(round(float(stamps[e.source]), 6), round(float(stamps[e.target]), 6)):
            (e.relative_pose, relative_pose(truth[e.source], truth[e.target]))
            for e in graph.edges if e.kind == "odometry" and np.isfinite(truth[[e.source, e.target]]).all()}


def edges_apart(run: Path, other: Path, apart_m: float) -> list[dict]:
    """The odometry edges between the same keyframes whose relative poses in `run` and `other`
    differ by more than `apart_m` metres of translation, each with its error against the truth in both."""
    mine, theirs = odometry_by_stamps(run), odometry_by_stamps(other)
    rows = []
    for key in sorted(set(mine) & set(theirs)):
        (a, truth), (b, _) = mine[key], theirs[key]
        apart = float(edge_errors(a[None], b[None])[0])
        if apart > apart_m:
            rows.append({"from_stamp": key[0], "to_stamp": key[1], "apart_m": apart,
                         "error_m": float(edge_errors(a[None], truth[None])[0]),
                         "other_error_m": float(edge_errors(b[None], truth[None])[0])})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a loop_closure=pose_graph run folder")
    parser.add_argument("none_run", type=Path, help="the same sequence's loop_closure=none run folder")
    parser.add_argument("--other", type=Path, help="the same sequence's pose_graph run with another setting")
    parser.add_argument("--apart-cm", type=float, default=0.5, help="edges further apart than this are listed")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/loop_closure_graph_trace.json"))
    args = parser.parse_args()
    row = trace(args.run, args.none_run)
    if args.other is not None:
        row["other_run"] = str(args.other)
        row["other_trace"] = trace(args.other, args.none_run)
        row["edges_apart"] = edges_apart(args.run, args.other, args.apart_cm / 100)
        print(markdown_table([["edge (keyframe timestamps)", "apart", "error", "error in --other"]]
                             + [[f"{r['from_stamp']:.6f} -> {r['to_stamp']:.6f}", f"{100 * r['apart_m']:.2f} cm",
                                 f"{100 * r['error_m']:.2f} cm", f"{100 * r['other_error_m']:.2f} cm"]
                                for r in row["edges_apart"]]))
    print(markdown_table([["keyframes (none)", "loops", "odometry error sum (none)", "keyframe ATE (none)",
                           "keyframe ATE, exact loops at the accepted pairs"],
                          [f"{row['keyframes']} ({row['none_keyframes']})", str(row["loops"]),
                           f"{100 * row['odometry_error_sum_m']:.1f} cm ({100 * row['none_odometry_error_sum_m']:.1f})",
                           f"{100 * row['keyframe_ate_m']:.2f} cm ({100 * row['none_keyframe_ate_m']:.2f})",
                           f"{100 * row['keyframe_ate_exact_loops_m']:.2f} cm"]]))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": platform.node(), "when": time.strftime("%Y-%m-%d %H:%M:%S"),
                                    "command": "python " + " ".join(sys.argv), **row}, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
