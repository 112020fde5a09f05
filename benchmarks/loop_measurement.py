"""How well can a loop's relative pose be measured from the depth? The floor of a geometric loop
closure on 7-Scenes redkitchen 300-999 (tracking only, as `slamkit dataset=sevenscenes
mapper=none` tracks it).

For the true revisits among the keyframes (pairs at least `min_path_m` of path apart, not the
last `exclude_recent`, whose ground-truth overlap is >= 30 %: benchmarks/loop_closure.py's
definition; a deterministic subsample of at most --pairs), each way of measuring the
keyframe's pose in the earlier keyframe's frame starts from odometry's relative pose (where it
fails, odometry's pose is kept and counted):

- `gicp`: G-ICP of the two keyframes' points (the loop closure's refinement; 2.5 cm voxels);
- `gicp_dense`: the same on 1 cm voxels;
- `point_to_plane`: point-to-plane ICP (2.5 cm voxels);
- `colored`: open3d's coloured ICP (Park et al. 2017: geometry and the points' colours);
- `submap`: G-ICP against the earlier keyframe and its `--submap` neighbours on each side,
  merged in its frame by odometry (a local map, as the map's Gaussians around the match);
- and the two references, odometry's relative pose and the ground truth's.

Per method: the median and 90th percentile of its distance from the ground truth's relative
pose (cm, degrees), the median point-to-plane residual of the aligned pair (how well the
depth agrees with itself under that pose: mm), and the ATE of every frame when each of those
pairs is a loop edge carrying that relative pose (the pose graph of `loop_closure=pose_graph`,
its odometry edges, frames following their keyframes). Writes JSON (--out).

    python benchmarks/loop_measurement.py --keyframes .cache/loop          # ~15 min on 2 cores
"""

from __future__ import annotations

import argparse
import hashlib
import inspect
import json
import platform
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from slamkit.geometry import transform_points
from slamkit.geometry.pose_graph import PoseGraph, PoseGraphEdge, pose_difference, relative_pose
from slamkit.geometry.registration import import_open3d
from slamkit.metrics.trajectory import ate
from slamkit.registry.compose import compose_run
from slamkit.run.build import build_run
from slamkit.run.loop_closing import loop_keyframe
from slamkit_plugins.loop_closures.pose_graph import optimisation, verification
from slamkit_plugins.loop_closures.pose_graph.verification import INFORMATION_FLOOR

sys.path.insert(0, str(Path(__file__).resolve().parent))
from loop_closure import (  # noqa: E402
    SEQUENCES,
    TRUE_REVISIT_OVERLAP,
    corrected_ate,
    geometry,
    orthonormal,
    tracking_digest,
)

#: ICP's correspondence distance, in voxels of the cloud it registers.
ICP_DISTANCE_VOXELS = 1.0
#: Point-to-plane residuals are taken over points with a partner within this many metres.
RESIDUAL_DISTANCE_M = 0.05


def track_with_colours(cache: Path | None):
    """(poses, gt, keyframe frame indices, per keyframe: points, covariances, colours) of
    tracking-only 7-Scenes; points and covariances as the run gives them to the loop closure."""
    if cache is not None and cache.is_file():
        with np.load(cache) as f:
            k = len(f["keyframe_frames"])
            return (f["poses"], f["gt"], f["keyframe_frames"], [f[f"points_{i}"] for i in range(k)],
                    [f[f"covariances_{i}"] for i in range(k)], [f[f"colours_{i}"] for i in range(k)])
    data, slam, _ = build_run([*SEQUENCES["7scenes"], "mapper=none"])
    poses, gts, frames, points, covariances, colours = [], [], [], [], [], []
    for i in range(len(data)):
        frame = data[i]
        if i == 0:
            slam.initialize(frame.gt_pose)
        step = slam.process(frame)
        poses.append(step.tracking.pose)
        gts.append(frame.gt_pose)
        g = step.tracking.gaussians
        if step.keyframe and g is not None:
            keyframe = loop_keyframe(len(frames), frame, step.tracking.pose, g, 0)
            frames.append(i)
            points.append(keyframe.points)
            covariances.append(keyframe.covariances)
            colours.append(np.asarray(g.colors, dtype=np.float32)[np.asarray(g.trackable, dtype=bool)])
    out = (np.array(poses), np.array(gts), np.array(frames), points, covariances, colours)
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        arrays = {"poses": out[0], "gt": out[1], "keyframe_frames": out[2]}
        for k in range(len(frames)):
            arrays |= {f"points_{k}": points[k], f"covariances_{k}": covariances[k], f"colours_{k}": colours[k]}
        np.savez_compressed(cache, **arrays)
    return out


def cloud(points: np.ndarray, voxel: float, covariances=None, colours=None):
    """open3d cloud downsampled to `voxel` with normals (and covariances / colours averaged)."""
    o3d = import_open3d()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    if covariances is not None:
        pcd.covariances = o3d.utility.Matrix3dVector(np.asarray(covariances, dtype=np.float64))
    if colours is not None:
        pcd.colors = o3d.utility.Vector3dVector(np.clip(np.asarray(colours, dtype=np.float64), 0, 1))
    pcd = pcd.voxel_down_sample(voxel)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
    return pcd


def residual_mm(source, target, pose: np.ndarray) -> float:
    """Median point-to-plane distance (mm) of `source`'s points, moved by `pose`, to their
    nearest `target` point's tangent plane (points with a partner within RESIDUAL_DISTANCE_M)."""
    from pykdtree.kdtree import KDTree

    p = transform_points(pose, np.asarray(source.points))
    q = np.asarray(target.points)
    d, i = KDTree(q).query(p, k=1, distance_upper_bound=RESIDUAL_DISTANCE_M)
    ok = np.isfinite(d) & (i < len(q))
    n = np.asarray(target.normals)[i[ok]]
    return float(1e3 * np.median(np.abs(np.einsum("ij,ij->i", p[ok] - q[i[ok]], n)))) if ok.any() else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--keyframes", type=Path, default=None, help="folder to keep / reuse the tracking run in")
    parser.add_argument("--pairs", type=int, default=300, help="true revisits measured, at most (an even subsample)")
    parser.add_argument("--submap", type=int, default=3, help="keyframes on each side of the match in `submap`")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/loop_measurement.json"))
    args = parser.parse_args()
    o3d = import_open3d()
    reg = o3d.pipelines.registration
    # named by the code that tracked them, as benchmarks/loop_closure.py's kept keyframes: never another code's
    code = hashlib.sha256((tracking_digest("7scenes") + inspect.getsource(track_with_colours)).encode()).hexdigest()
    cache = args.keyframes / f"7scenes_colours-{code[:12]}.npz" if args.keyframes else None
    poses, gt_raw, kf, points, covariances, colours = track_with_colours(cache)
    gt = orthonormal(gt_raw)
    lc = compose_run(["loop_closure=pose_graph"])[0].loop_closure

    seq = SimpleNamespace(points=points, covariances=covariances, keyframe_frames=kf, poses=poses, gt_poses=gt_raw)
    geo = geometry(seq, gt, lc)
    revisits = sorted(pair for pair, overlap in geo.overlap.items() if overlap >= TRUE_REVISIT_OVERLAP)
    step = max(1, int(np.ceil(len(revisits) / args.pairs)))
    pairs = revisits[::step]
    print(f"{len(revisits)} true revisits among {len(kf)} keyframes; measuring {len(pairs)}", flush=True)

    voxel = lc.voxel
    coarse = [cloud(p, voxel, c, col) for p, c, col in zip(points, covariances, colours)]
    dense = [cloud(p, 0.01, c) for p, c in zip(points, covariances)]
    kf_poses = poses[kf]

    def submap(m: int):
        ids = range(max(0, m - args.submap), min(len(kf), m + args.submap + 1))
        merged = [transform_points(relative_pose(kf_poses[m], kf_poses[j]), points[j]) for j in ids]
        R = [relative_pose(kf_poses[m], kf_poses[j])[:3, :3] for j in ids]
        covs = [r @ covariances[j].astype(np.float64) @ r.T for r, j in zip(R, ids)]
        return cloud(np.concatenate(merged), voxel, np.concatenate(covs))

    criteria = reg.ICPConvergenceCriteria(max_iteration=50)

    def gicp(source, target, start, distance):
        estimation = reg.TransformationEstimationForGeneralizedICP()
        return reg.registration_generalized_icp(source, target, distance, start, estimation, criteria).transformation

    methods = {
        "gicp": lambda q, m, start: gicp(coarse[q], coarse[m], start, ICP_DISTANCE_VOXELS * voxel),
        "gicp_dense": lambda q, m, start: gicp(dense[q], dense[m], start, ICP_DISTANCE_VOXELS * 0.01),
        "point_to_plane": lambda q, m, start: reg.registration_icp(
            coarse[q], coarse[m], ICP_DISTANCE_VOXELS * voxel, start, reg.TransformationEstimationPointToPlane(),
            criteria).transformation,
        "colored": lambda q, m, start: reg.registration_colored_icp(
            coarse[q], coarse[m], ICP_DISTANCE_VOXELS * voxel, start, reg.TransformationEstimationForColoredICP(),
            criteria).transformation,
        "submap": lambda q, m, start: gicp(coarse[q], submap(m), start, ICP_DISTANCE_VOXELS * voxel),
    }
    found: dict[str, dict[tuple[int, int], np.ndarray]] = {"odometry": {}, "ground_truth": {}}
    for q, m in pairs:
        found["odometry"][(q, m)] = relative_pose(kf_poses[m], kf_poses[q])
        found["ground_truth"][(q, m)] = relative_pose(gt[kf[m]], gt[kf[q]])
    cpu, failed = {}, {}
    for name, measure in methods.items():
        start_cpu = time.process_time()
        found[name], failed[name] = {}, 0
        for q, m in pairs:
            try:
                pose = np.asarray(measure(q, m, found["odometry"][(q, m)]), dtype=np.float64).copy()
            except RuntimeError:  # open3d: no correspondences from the start pose
                pose = np.full((4, 4), np.nan)
            failed[name] += not np.isfinite(pose).all()
            found[name][(q, m)] = pose if np.isfinite(pose).all() else found["odometry"][(q, m)]
        cpu[name] = (time.process_time() - start_cpu) / len(pairs)
        print(f"{name}: {1e3 * cpu[name]:.0f} ms CPU a pair, {failed[name]} failed (odometry's pose kept)", flush=True)

    graph = PoseGraph(np.arange(len(kf)), kf_poses, ())
    odometry_edges = []
    for k in range(1, len(kf)):
        rel = relative_pose(kf_poses[k - 1], kf_poses[k])
        info, _ = verification.normalised_information(geo.clouds[k], geo.clouds[k - 1], rel, voxel)
        odometry_edges.append(PoseGraphEdge("odometry", k - 1, k, rel,
                                            (info + INFORMATION_FLOOR * np.eye(6)) / lc.odometry_sigma_m**2))

    rows = []
    for name, poses_found in found.items():
        errors = np.array([pose_difference(poses_found[p], found["ground_truth"][p]) for p in pairs])
        residuals = np.array([residual_mm(coarse[q], coarse[m], poses_found[(q, m)]) for q, m in pairs])
        edges = list(odometry_edges)
        for (q, m), pose in poses_found.items():
            info, _ = verification.normalised_information(geo.clouds[q], geo.clouds[m], pose, voxel)
            edges.append(PoseGraphEdge("loop", m, q, pose, info / lc.loop_sigma_m**2))
        optimised = optimisation.optimise(PoseGraph(graph.keyframe_ids, graph.poses, tuple(edges)), lc.backend,
                                          lc.robust_width)
        rows.append({"method": name, "pairs": len(pairs),
                     "error_median_cm": 100 * float(np.median(errors[:, 0])),
                     "error_p90_cm": 100 * float(np.percentile(errors[:, 0], 90)),
                     "error_median_deg": float(np.median(errors[:, 1])),
                     "error_p90_deg": float(np.percentile(errors[:, 1], 90)),
                     "residual_median_mm": float(np.nanmedian(residuals)),
                     "ate_cm": 100 * corrected_ate(seq, optimised), "cpu_ms_per_pair": 1e3 * cpu.get(name, 0.0),
                     "failed": failed.get(name, 0)})
    print(f"\nATE without loops: {100 * ate(poses, gt_raw).rmse_m:.2f} cm")
    header = list(rows[0])
    print("| " + " | ".join(header) + " |")
    print("|" + "|".join("---" for _ in header) + "|")
    for r in rows:
        print("| " + " | ".join(f"{v:.2f}" if isinstance(v, float) else str(v) for v in r.values()) + " |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": platform.platform(), "when": time.strftime("%Y-%m-%d %H:%M"),
                                    "command": "python benchmarks/loop_measurement.py " + " ".join(sys.argv[1:]),
                                    "true_revisits": len(revisits), "ate_none_cm": 100 * ate(poses, gt_raw).rmse_m,
                                    "rows": rows}, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
