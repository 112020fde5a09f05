"""What a finished run's pose graph can give, whatever its loops: a `loop_closure=pose_graph` run
folder (pose_graph.g2o, keyframes.txt, loops.csv, groundtruth.txt) re-optimised with its loops'
measurements replaced by the ground truth's relative poses, and with the candidates it refused
added as exact loops too; and its odometry edges' errors against the ground truth.

Prints a table and writes JSON (`--out`). Keyframe ATE (SE(3)-aligned RMSE over the keyframes),
the run's own backend and robust width (`loop_closure=pose_graph` defaults unless `--set`).

    python benchmarks/pose_graph_floor.py RUN_DIR --out benchmarks/results/pose_graph_floor.json
"""

from __future__ import annotations

import argparse
import csv
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

from slamkit.cli.bench import markdown_table
from slamkit.formats.g2o import read_g2o
from slamkit.formats.tum import associate, read_tum_trajectory
from slamkit.geometry.pose_graph import PoseGraph, PoseGraphEdge, pose_difference, relative_pose
from slamkit.metrics.trajectory import ate
from slamkit.registry.compose import compose_run
from slamkit_plugins.loop_closures.pose_graph import optimisation

#: Odometry edges listed, largest error first.
LARGEST = 6


def poses_at(path: Path, stamps: np.ndarray) -> np.ndarray:
    """(K,4,4) camera-to-world poses of a TUM file at `stamps` (seconds, matched within 1 us)."""
    t, poses = read_tum_trajectory(path)
    found, at = associate(stamps, t, 1e-6)
    if len(found) != len(stamps):
        first = stamps[np.setdiff1d(np.arange(len(stamps)), found)[0]]
        sys.exit(f"{path}: no pose at {len(stamps) - len(found)} keyframe time(s), the first {first:.6f} s")
    return poses[at]


def edge_sigma_along(edge: PoseGraphEdge, direction: np.ndarray) -> float:
    """Standard deviation (metres) the edge's information gives along a translation direction
    (unit, the source's camera frame)."""
    return float(1.0 / np.sqrt(direction @ edge.information[3:, 3:] @ direction))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a loop_closure override (backend, robust_width)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/pose_graph_floor.json"))
    args = parser.parse_args()
    run = args.run_dir
    cfg, _ = compose_run(["loop_closure=pose_graph", *args.set])
    lc = cfg.loop_closure
    graph = read_g2o(run / "pose_graph.g2o")
    stamps = np.loadtxt(run / "keyframes.txt", ndmin=2)[:, 0]
    if len(stamps) != len(graph.keyframe_ids):
        sys.exit(f"{run}: {len(stamps)} keyframes in keyframes.txt, {len(graph.keyframe_ids)} in pose_graph.g2o")
    gt = poses_at(run / "groundtruth.txt", stamps)
    position = {int(k): i for i, k in enumerate(graph.keyframe_ids)}

    def truth(source: int, target: int) -> np.ndarray:
        return relative_pose(gt[position[source]], gt[position[target]])

    odometry = [e for e in graph.edges if e.kind == "odometry"]
    loops = [e for e in graph.edges if e.kind == "loop"]
    # the start: odometry alone, chained from the first keyframe
    chained = [graph.poses[0]]
    for e in odometry:
        chained.append(chained[-1] @ e.relative_pose)
    start = np.stack(chained)

    def solved(edges: list[PoseGraphEdge]) -> tuple[float, np.ndarray]:
        poses = optimisation.optimise(PoseGraph(graph.keyframe_ids, start, tuple(edges)), lc.backend, lc.robust_width)
        return ate(poses, gt).rmse_m, poses

    exact = [PoseGraphEdge("loop", e.source, e.target, truth(e.source, e.target), e.information) for e in loops]
    median_information = np.median(np.stack([e.information for e in loops]), axis=0) if loops else np.eye(6)
    with open(run / "loops.csv", newline="") as f:
        refused = {(int(r["match_keyframe"]), int(r["keyframe"])) for r in csv.DictReader(f) if r["accepted"] != "True"}
    refused -= {(e.source, e.target) for e in loops}
    refused_exact = [PoseGraphEdge("loop", m, q, truth(m, q), median_information) for m, q in sorted(refused)
                     if m in position and q in position]
    cases = {"as written": ate(graph.poses, gt).rmse_m,
             "odometry only": ate(start, gt).rmse_m,
             "re-optimised": solved([*odometry, *loops])[0],
             "every loop exact": solved([*odometry, *exact])[0]}
    cases["and the refused candidates as exact loops"], floor = solved([*odometry, *exact, *refused_exact])
    edges = []
    for e in odometry:
        diff = np.linalg.inv(truth(e.source, e.target)) @ e.relative_pose
        metres, degrees = pose_difference(e.relative_pose, truth(e.source, e.target))
        along = diff[:3, 3] / metres if metres > 0 else np.array([1.0, 0.0, 0.0])
        edges.append({"source": e.source, "target": e.target, "error_m": metres, "error_deg": degrees,
                      "sigma_along_error_m": edge_sigma_along(e, along)})
    edges.sort(key=lambda r: -r["error_m"])
    print(markdown_table([["graph", "keyframe ATE cm"], *[[k, f"{v * 100:.2f}"] for k, v in cases.items()]]))
    print(f"\n{len(odometry)} odometry edges, {len(loops)} loops, {len(refused_exact)} refused candidates; "
          f"odometry error summed {sum(r['error_m'] for r in edges) * 100:.1f} cm, the largest:")
    print(markdown_table([["edge", "error cm", "deg", "sigma along it cm"],
                          *[[f"{r['source']} -> {r['target']}", f"{r['error_m'] * 100:.1f}", f"{r['error_deg']:.2f}",
                             f"{r['sigma_along_error_m'] * 100:.2f}"] for r in edges[:LARGEST]]]))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({
        "machine": platform.platform(), "when": time.strftime("%Y-%m-%d %H:%M"),
        "command": "python benchmarks/pose_graph_floor.py " + " ".join(sys.argv[1:]),
        "keyframe_ate_m": cases, "odometry_edges": edges, "loops": len(loops), "refused_candidates": len(refused_exact),
        "floor_keyframe_errors_m": ate(floor, gt).errors_m.tolist(),
        "floor_keyframe_positions_minus_truth_m": (floor[:, :3, 3] - gt[:, :3, 3]).tolist()},
        indent=1, default=float) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
