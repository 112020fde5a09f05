"""Where can G-ICP land after a long gap? Each frame after a forced gap, aligned from each start.

Sequential, tracking only (`tracker=gicp keyframe=overlap mapper=none`), the frames of a forced-gap
schedule (`eval.forced_gap_every`, `eval.forced_gap_length`) fed to the system one by one; at each
frame after a gap, before the system tracks it, a copy of its tracker aligns the frame (plain
G-ICP, no fallbacks) from each start:

- prediction: the tracker's prediction (constant velocity, capped at max_prediction_intervals);
- previous: the last tracked pose;
- truth's motion: the last tracked pose times the ground truth's motion since that frame, the
  pose the issue's error measures against (its alignment: how far the map lets even the right
  start stay right);
- global registration: FPFH + RANSAC to the map's trackable Gaussians (tracker.relocalize_voxel),
  from RANSAC seed 0 as the tracker draws (`--seeds N`: seeds 0 to N-1).

For each: the fraction of the frame's points matched, the map's surface agreement with the frame
seen from its pose (`slamkit.geometry.surface`: of the image cells seeing the map, the fraction
whose nearest map centre lies on the frame's depth), whether it converged, and its error against
the ground truth's motion since the frame before the gap (cm, degrees). Then the system tracks
the frame as the CLI would (the `tracked` row). Prints a table, writes JSON (`--out`).

    python benchmarks/after_gap_starts.py --sequence 7scenes --frames 120,170,470,670
    python benchmarks/after_gap_starts.py --sequence tum --schedule 60/20 --set tracker.min_matched_ratio=0.8
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from slamkit.cli.bench import markdown_table
from slamkit.geometry.registration import FeatureCloud, register
from slamkit.geometry.surface import surface_cells
from slamkit.geometry.transforms import backproject, invert_pose, rotation_angle_deg
from slamkit.registry.schema import EvalConfig
from slamkit.run.build import build_run
from slamkit_plugins.trackers.gicp.alignment import matched_fraction, new_stats
from slamkit_plugins.trackers.gicp.tracker import GICPTracker

sys.path.insert(0, str(Path(__file__).resolve().parent))
from frame_delay import DATA, SEQUENCES  # noqa: E402  (the sequences of the gaps part)


def pose_error(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    """(cm, degrees) of B relative to A."""
    E = invert_pose(A) @ B
    return 100 * float(np.linalg.norm(E[:3, 3])), float(rotation_angle_deg(E[:3, :3]))


def source(tracker: GICPTracker, frame) -> tuple[np.ndarray, np.ndarray]:
    """The frame's trackable points (camera frame, metres) and regularised covariances, as the tracker makes them."""
    points, pix = backproject(np.asarray(frame.depth), frame.camera, tracker.pixel_stride)
    trackable = points[:, 2] <= frame.depth_trunc
    raw = tracker.kernels.frame_covariances(points, pix, frame.camera, tracker.pixel_stride, tracker.cfg.knn)
    cov = tracker.kernels.regularize(raw, tracker.regularization, tracker.cfg.plane_eps)
    return points[trackable].astype(np.float64), cov[trackable]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--sequence", choices=sorted(SEQUENCES), default="7scenes")
    parser.add_argument("--schedule", default="50/20", help="EVERY/LENGTH: LENGTH frames dropped after every EVERY")
    parser.add_argument("--frames", default="", help="dataset indices to study (default: every frame after a gap)")
    parser.add_argument("--seeds", type=int, default=1, help="global registrations, each from its own RANSAC seed")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="an override of the run")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    every, length = (int(n) for n in args.schedule.split("/"))
    gaps = EvalConfig(forced_gap_every=every, forced_gap_length=length)
    chosen = {int(i) for i in args.frames.split(",") if i}
    overrides = [o for o in SEQUENCES[args.sequence](args.data) if "eval_every" not in o]
    dataset, slam, _ = build_run(overrides + ["tracker=gicp", "keyframe=overlap", "mapper=none"] + args.set)
    last_study = max(chosen) if chosen else len(dataset) - 1
    slam.initialize(dataset[0].gt_pose)
    rows, table = [], [["frame", "after", "start", "matched", "surface agreement", "converged", "error cm",
                        "error deg"]]
    last, dropped = None, False
    for i in range(last_study + 1):
        if gaps.in_forced_gap(i):
            dropped = True
            continue
        frame = dataset[i]
        if dropped and last is not None and (not chosen or i in chosen):
            tracker = slam.tracker
            copy = GICPTracker(tracker.cfg)
            copy.load_state_dict(tracker.state_dict())
            previous = tracker.poses[-1]
            truth = invert_pose(dataset[last].gt_pose) @ frame.gt_pose
            ideal = previous @ truth
            src, src_cov = source(copy, frame)
            starts = {"prediction": copy.predict(i), "previous": previous, "truth's motion": ideal}
            voxel = copy.cfg.relocalize_voxel
            cloud = FeatureCloud(src, voxel) if voxel > 0 else None
            for seed in range(args.seeds if voxel > 0 else 0):
                name = "global registration" + (f" (seed {seed})" if seed else "")
                starts[name] = register(cloud, copy.target.features(voxel), seed=seed).pose
            attempts = {}

            def surface(pose: np.ndarray) -> float | None:
                return surface_cells(copy.target.means, frame.depth, frame.camera, pose).agreement

            for name, start in starts.items():
                stats = new_stats()
                pose, ok, sq = copy.aligner.align(copy.target, src, src_cov, start, stats)
                attempts[name] = {"matched": matched_fraction(sq), "surface": surface(pose),
                                  "converged": bool(stats.get("converged")), "ok": bool(ok),
                                  "error": pose_error(ideal, pose)}
            result = slam.process(frame).tracking
            attempts["tracked"] = {"matched": result.stats.get("matched_fraction"), "surface": surface(result.pose),
                                   "converged": None, "ok": not result.lost,
                                   "fallback": result.stats.get("fallback", ""),
                                   "error": pose_error(ideal, result.pose)}
            rows.append({"index": i, "before": last, "attempts": attempts})
            for name, a in attempts.items():
                label = name if name != "tracked" else f"tracked ({a['fallback'] or 'first'}{', lost' * (not a['ok'])})"
                table.append([str(i), str(last), label, "-" if a["matched"] is None else f"{a['matched']:.3f}",
                              "-" if a["surface"] is None else f"{a['surface']:.3f}",
                              "-" if a["converged"] is None else str(a["converged"]),
                              f"{a['error'][0]:.1f}", f"{a['error'][1]:.2f}"])
        else:
            slam.process(frame)
        last, dropped = i, False
    print(f"{args.sequence}, {length} frames dropped after every {every}: each frame after a gap aligned from each "
          "start (error against the ground truth's motion since the frame before the gap)\n" + markdown_table(table))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"sequence": args.sequence, "schedule": args.schedule, "set": args.set,
                                        "frames": rows}, indent=2) + "\n")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
