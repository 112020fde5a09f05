"""How much does a loop depend on RANSAC's draws? For chosen keyframe pairs of a
`benchmarks/loop_closure.py` run (its kept keyframes, --keyframes), the two keyframes' clouds are
registered as the loop closure does (`slamkit.geometry.registration.register`, the default
`PoseGraphConfig`) from --seeds different seeds; for each: the fitness, RANSAC's inliers and the
pose's error from the ground truth's relative pose. Prints a table and writes JSON (--out): how
often a pair registers right (within --right-cm), and whether the right poses are the ones of
highest fitness (what `loop_closure.ransac_restarts` keeps; docs/loop_closure.md).

    python benchmarks/loop_closure.py --sequences synthetic_revisit_rotated --keyframes .cache/kf
    python benchmarks/loop_closure_seeds.py --sequence synthetic_revisit_rotated --keyframes .cache/kf \
        --pairs 876:35,886:28,896:14
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

from slamkit.geometry.registration import FeatureCloud, register
from slamkit.roles.loop_closure import pose_difference, relative_pose
from slamkit_plugins.loop_closures.pose_graph.config import PoseGraphConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
from loop_closure import load_kept  # noqa: E402  (the offline benchmark's)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sequence", required=True, help="a sequence of benchmarks/loop_closure.py")
    parser.add_argument("--keyframes", type=Path, required=True, help="the folder loop_closure.py kept them in")
    parser.add_argument("--pairs", required=True, help="FRAME:MATCH_FRAME,... (both keyframes)")
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--right-cm", type=float, default=2.0)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    cfg = PoseGraphConfig()
    seq = load_kept(args.keyframes, args.sequence)
    frames = [int(f) for f in seq.keyframe_frames]
    rows = []
    for pair in args.pairs.split(","):
        query, match = (int(f) for f in pair.split(":"))
        if query not in frames or match not in frames:
            sys.exit(f"--pairs {pair}: frame {query if query not in frames else match} is not a keyframe of "
                     f"{args.sequence}")
        i, j = frames.index(query), frames.index(match)
        source = FeatureCloud(seq.points[i], cfg.voxel, seq.covariances[i])
        target = FeatureCloud(seq.points[j], cfg.voxel, seq.covariances[j])
        truth = relative_pose(seq.gt_poses[match], seq.gt_poses[query])
        draws = []
        for seed in range(args.seeds):
            found = register(source, target, cfg.ransac_iterations, cfg.ransac_confidence, cfg.seed + seed)
            error_m, error_deg = pose_difference(truth, found.pose)
            draws.append({"seed": cfg.seed + seed, "fitness": found.fitness, "ransac_inliers": found.ransac_inliers,
                          "error_m": error_m, "error_deg": error_deg})
        right = [d for d in draws if d["error_m"] < args.right_cm / 100]
        wrong = [d for d in draws if d["error_m"] >= args.right_cm / 100]
        rows.append({"frame": query, "match_frame": match, "right": len(right), "draws": draws,
                     "lowest_right_fitness": min((d["fitness"] for d in right), default=None),
                     "highest_wrong_fitness": max((d["fitness"] for d in wrong), default=None)})
    print(f"{args.sequence}: {args.seeds} seeds a pair, right = within {args.right_cm} cm of the ground truth")
    print("| pair | right | fitness of the right (lowest) | of the wrong (highest) | wrong errors cm |")
    print("|---|---|---|---|---|")
    for r in rows:
        errors = sorted(round(100 * d["error_m"], 1) for d in r["draws"] if d["error_m"] >= args.right_cm / 100)
        low, high = r["lowest_right_fitness"], r["highest_wrong_fitness"]
        print(f"| {r['frame']} -> {r['match_frame']} | {r['right']} of {args.seeds} | "
              f"{'-' if low is None else f'{low:.3f}'} | {'-' if high is None else f'{high:.3f}'} | {errors} |")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"machine": platform.platform(), "when": time.strftime("%Y-%m-%d %H:%M"),
                                        "command": " ".join(sys.argv), "sequence": args.sequence,
                                        "right_cm": args.right_cm, "pairs": rows}, indent=1) + "\n")
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
