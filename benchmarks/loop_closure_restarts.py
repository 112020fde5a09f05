"""Is a verified loop's pose unique? For each candidate of a `benchmarks/loop_closure.py` run
(--results: its JSON) that passed every figure but perhaps the inlier-RMSE bound, the two
keyframes are registered again as the loop closure does (same clouds, same seed: the same pose
to the bit), and G-ICP (`slamkit.geometry.registration.refine`) is restarted from that pose
displaced along the alignment's weakest translation direction (the smallest eigenvector of the
point-to-plane information's translation block) by +-1, 2, 3 cm, and about its weakest rotation
axis by +-0.5, 1, 2 degrees (--rotation-steps-deg). Prints, per candidate, how far (cm, degrees)
each restart converged from the found pose, beside the loop's error from the ground truth: a
right loop's restarts come back, a sliding one's do not (docs/loop_closure.md, "Long revisits").

    python benchmarks/loop_closure.py --sequences synthetic_return --keyframes .cache/kf \
        --sweep loop_closure.max_inlier_rmse_m=0.015,0.02
    python benchmarks/loop_closure_restarts.py --sequences synthetic_return --keyframes .cache/kf

Needs the keyframes of that run (--keyframes, as benchmarks/loop_closure.py keeps them).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

from slamkit.geometry.registration import FeatureCloud, register
from slamkit_plugins.loop_closures.pose_graph import verification
from slamkit_plugins.loop_closures.pose_graph.config import PoseGraphConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
from loop_closure import TrackedSequence, load_kept  # noqa: E402  (the offline benchmark's)

TRANSLATION_STEPS_M = (0.01, 0.02, 0.03)


def candidates(row: dict) -> list[dict]:
    """The checks of one benchmark row that passed every figure but perhaps the inlier RMSE."""
    return [c for c in row["checks"] if c["accepted"] or c["reason"].startswith(("inlier RMSE", "inconsistent"))]


def probe(seq: TrackedSequence, check: dict, cfg: PoseGraphConfig, rotation_steps_deg: list[float]) -> dict:
    """One candidate re-registered and restarted (see the module docstring)."""
    q, m = check["keyframe"], check["match_keyframe"]
    query, match = (FeatureCloud(seq.points[k], cfg.voxel, seq.covariances[k]) for k in (q, m))
    found = register(query, match, cfg.ransac_iterations, cfg.ransac_confidence, cfg.seed + q)
    information, _ = verification.normalised_information(query, match, found.pose, cfg.voxel)
    fractions, translations = np.linalg.eigh(information[3:, 3:])
    _, rotations = np.linalg.eigh(information[:3, :3])
    signs = np.array([1.0, -1.0])
    steps = [np.r_[0, 0, 0, s * step * translations[:, 0]] for step in TRANSLATION_STEPS_M for s in signs]
    steps += [np.r_[s * np.radians(step) * rotations[:, 0], 0, 0, 0] for step in rotation_steps_deg for s in signs]
    start = time.perf_counter()
    away = verification.restarts(query, match, found.pose, np.array(steps))
    seconds = time.perf_counter() - start
    return {"frame": check["frame"], "match_frame": check["match_frame"], "accepted": check["accepted"],
            "reason": check["reason"], "inlier_rmse_m": check["inlier_rmse_m"], "fitness": check["fitness"],
            "error_m": check["error_m"], "error_deg": check["error_deg"], "weakest": float(fractions[0]),
            "same_pose": bool(np.allclose(found.pose[:3, 3], [check["tx"], check["ty"], check["tz"]], atol=1e-6)),
            "translation_steps_m": [s * step for step in TRANSLATION_STEPS_M for s in signs],
            "rotation_steps_deg": [s * step for step in rotation_steps_deg for s in signs],
            "converged_away": away.tolist(), "seconds_per_restart": seconds / len(steps)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--results", type=Path, default=Path("benchmarks/results/loop_closure_long_revisits.json"))
    parser.add_argument("--setting", default="loop_closure.max_inlier_rmse_m=0.02", help="the rows of this setting")
    parser.add_argument("--sequences", required=True)
    parser.add_argument("--keyframes", type=Path, required=True)
    parser.add_argument("--rotation-steps-deg", default="0.5,1,2", help="'' for none")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/loop_closure_restarts.json"))
    args = parser.parse_args()
    cfg = PoseGraphConfig()
    rotation_steps = [float(v) for v in args.rotation_steps_deg.split(",") if v]
    rows = []
    for row in json.loads(args.results.read_text())["rows"]:
        if row["sequence"] not in args.sequences.split(",") or row["setting"] != args.setting:
            continue
        seq = load_kept(args.keyframes, row["sequence"])
        for check in candidates(row):
            rows.append({"sequence": row["sequence"], **probe(seq, check, cfg, rotation_steps)})
            r = rows[-1]
            away = " ".join(f"{100 * d:.1f}cm/{a:.2f}deg" for d, a in r["converged_away"])
            print(f"{r['sequence']} {r['frame']}->{r['match_frame']} accepted={r['accepted']} error "
                  f"{100 * r['error_m']:.1f} cm, {r['error_deg']:.2f} deg; weakest {r['weakest']:.3f}; restarts "
                  f"converged {away}", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": platform.platform(), "when": time.strftime("%Y-%m-%d %H:%M"),
                                    "command": "python benchmarks/loop_closure_restarts.py " + " ".join(sys.argv[1:]),
                                    "rows": rows}, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
