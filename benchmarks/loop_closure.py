"""Loop closure measured offline on real data: tracking only (tracker gicp, keyframe overlap,
mapper none, as `slamkit dataset=NAME mapper=none` runs it, through
`slamkit.registry.compose.build_run`), then each keyframe, with its estimated pose, points and
image, given to the loop closure in order (`detect_and_optimise` after each keyframe), as the run
does in sequential mode. Prints per sequence and setting:

- candidates: keyframe pairs verified; accepted: loops in the final pose graph;
- right: accepted loops whose relative pose is within 5 cm and 3 degrees of the ground truth's
  (ground-truth rotations re-orthonormalised first: 7-Scenes' pose files are off by ~1e-4,
  which alone reads as ~1 degree); precision = right / accepted;
- true revisits: candidate pairs whose ground-truth overlap is at least 30 % (the fraction of
  the keyframe's downsampled points with a point of the other within 2 voxels under the
  ground-truth relative pose); pair recall = right accepted true revisits / true-revisit
  candidates; keyframe recall = keyframes with a right loop / keyframes with a true revisit
  among the eligible earlier keyframes (not the last `exclude_recent`, `min_path_m` back);
- ATE RMSE of every frame (`slamkit.metrics.trajectory.ate`, SE(3)-aligned) without loop
  closure, with it (frames follow their keyframe: `follow_keyframes`), and two references on the
  same odometry edges: every eligible true revisit as a loop with the ground-truth relative pose
  (the floor of a perfect loop closure), and (--oracle) with the relative pose G-ICP finds
  from odometry's (within one voxel, or coarse to fine: --oracle-scales 4,2,1); --oracle also
  gives the median distances between odometry's, G-ICP's and the ground truth's relative poses
  of those pairs and of consecutive keyframes, how many are within 2 cm and 1 degree, and the
  ATE with only those right ones as loops, and with exact loops at those pairs and at the
  other revisits (`relative_pose_agreement` in the JSON); --oracle-colour also by coloured ICP;
- the loop closure's CPU seconds per keyframe (this process), and the CPU milliseconds of one
  optimisation of the final graph alone (indicative only: shared machine);
- the odometry edges colour_odometry moved, and how many of them ended nearer the truth's
  relative pose or further (`odometry_edges`); in the JSON also the ATE with the moved edges,
  the worst edges and every edge set to the truth (`edges_at_truth`).

With --wrong-loop, the first loop that verification accepts has its relative pose moved by
25 cm and 10 degrees before it enters the graph: a wrong loop that passed verification, which
the optimiser must drop (the column `wrong loop dropped`) or absorb.

    python benchmarks/loop_closure.py                                    # 7scenes, tum, replica
    python benchmarks/loop_closure.py --sequences 7scenes --backends gtsam,open3d --wrong-loop
    python benchmarks/loop_closure.py --sequences 7scenes --sweep loop_closure.min_fitness=0.5,0.55,0.6,0.65
    python benchmarks/loop_closure.py --keyframes .cache/loop          # keep / reuse the tracking runs
    python benchmarks/loop_closure.py --square --out benchmarks/results/loop_closure_square.json

Writes JSON (--out, default benchmarks/results/loop_closure.json).
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import inspect
import json
import platform
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from slamkit.cli.bench import markdown_table
from slamkit.config import RunContext
from slamkit.geometry import invert_pose, nearest_rotation, project_points, se3_exp, transform_points
from slamkit.geometry.registration import refine
from slamkit.metrics.trajectory import ate
from slamkit.registry.compose import compose_run
from slamkit.registry.discovery import default_registry
from slamkit.roles.loop_closure import (
    LoopKeyframe,
    PoseGraph,
    PoseGraphEdge,
    follow_keyframes,
    pose_difference,
    relative_pose,
)
from slamkit.run.build import build_run
from slamkit.run.loop_closing import loop_keyframe
from slamkit.tuning import DatasetTuning
from slamkit_plugins.loop_closures.pose_graph import closure as pose_graph_closure
from slamkit_plugins.loop_closures.pose_graph import optimisation, verification

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SEQUENCES = {  # name -> the dataset's overrides
    "7scenes": ["dataset=sevenscenes", f"dataset.path={DATA / '7scenes_redkitchen_300to999'}"],
    "tum": ["dataset=tum", f"dataset.path={DATA / 'tum_fr1_rpy_first150'}"],
    "replica": ["dataset=replica", f"dataset.path={DATA / 'replica_room0_first20'}"],
}
#: The synthetic paths that come back, frames each, with the structured-light sensor: exact
#: ground truth, odometry that drifts as a Kinect's does (as benchmarks/loop_closure_runs.py).
#: What `tracking_digest` reads of the package's source: Python, configuration, the compiled kernels.
SOURCE_SUFFIXES = (".py", ".yaml", ".cpp", ".c", ".h", ".cu")
SYNTHETIC = {"room_loop": 600, "figure_eight": 720, "return": 900, "revisit_rotated": 900}
SEQUENCES.update({f"synthetic_{path}": ["dataset=synthetic", f"dataset.camera_path={path}", f"dataset.num_frames={n}",
                                        "dataset.depth_model=structured_light"] for path, n in SYNTHETIC.items()})
#: The same paths from rest (speeding up over their first second, slowing over their last).
SEQUENCES.update({f"synthetic_{path}_from_rest": [*SEQUENCES[f"synthetic_{path}"], "dataset.ramp_s=1"]
                  for path in SYNTHETIC})
#: A loop is right when its relative pose is this close to the ground truth's (metres, degrees).
RIGHT_M, RIGHT_DEG = 0.05, 3.0
#: A candidate pair is a true revisit when this fraction of the keyframe's downsampled points has a
#: point of the other keyframe within TRUE_REVISIT_VOXELS voxels under the ground-truth relative pose.
TRUE_REVISIT_OVERLAP, TRUE_REVISIT_VOXELS = 0.3, 2.0
#: --coverage: the neighbours of an accepted loop q -> m are m +- this many keyframes (and q-2..q).
NEIGHBOURS = 8
#: A loop within these of the ground truth's relative pose is right (the issue's bound: 2 cm, 1 degree).
RIGHT_LOOP_M, RIGHT_LOOP_DEG = 0.02, 1.0
#: --oracle lists this many of odometry's keyframe edges, the furthest from the truth first.
ORACLE_EDGES = 8
#: edges_at_truth sets this many of the odometry edges furthest from the truth to the truth, each in turn.
TRUTH_EDGES = (5, 10, 20)
#: a moved odometry edge is counted better (worse) when it ends this much nearer (further from) the truth.
MOVED_EDGE_CHANGE_M = 0.002
#: --oracle: an odometry edge this far (metres) from the truth's relative pose is one where tracking slipped.
SLIPPED_EDGE_M = 0.015
#: The wrong loop of --wrong-loop: its relative pose moved by this (rotation vector rad, translation m).
WRONG_LOOP = np.array([0.0, np.radians(10.0), 0.0, 0.25, 0.0, 0.0])


@dataclass
class TrackedSequence:
    """One tracking-only run. poses, gt_poses: (F,4,4) camera-to-world, metres (gt NaN where the
    dataset has none). keyframe_frames: (K,) indices into the F frames. points[k]: (N_k,3) float32,
    keyframe k's trackable Gaussian centres in its camera frame (metres); covariances[k]:
    (N_k,3,3) float32, their G-ICP covariances in the same frame (m^2, regularised as the tracker
    uses them); images[k]: (h,w,3) uint8; colours[k]: (N_k,3) float32, the centres' RGB in [0, 1].
    overrides: the run's Hydra overrides."""

    poses: np.ndarray
    gt_poses: np.ndarray
    keyframe_frames: np.ndarray
    points: list[np.ndarray]
    covariances: list[np.ndarray]
    images: list[np.ndarray]
    colours: list[np.ndarray]
    overrides: list[str]

    def save(self, path: Path) -> None:
        arrays = {"poses": self.poses, "gt_poses": self.gt_poses, "keyframe_frames": self.keyframe_frames,
                  "overrides": np.array(self.overrides)}
        for k, (p, c, im, rgb) in enumerate(zip(self.points, self.covariances, self.images, self.colours)):
            arrays |= {f"points_{k}": p, f"covariances_{k}": c, f"image_{k}": im, f"colours_{k}": rgb}
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, **arrays)

    @classmethod
    def load(cls, path: Path) -> TrackedSequence:
        with np.load(path) as f:
            k = len(f["keyframe_frames"])
            return cls(f["poses"], f["gt_poses"], f["keyframe_frames"], [f[f"points_{i}"] for i in range(k)],
                       [f[f"covariances_{i}"] for i in range(k)], [f[f"image_{i}"] for i in range(k)],
                       [f[f"colours_{i}"] for i in range(k)], [str(o) for o in f["overrides"]])


def track(dataset: list[str], max_frames: int | None = None, extra: tuple[str, ...] = ()) -> TrackedSequence:
    """Track the sequence `dataset` (its overrides; tracking only) and keep its keyframes (see
    TrackedSequence)."""
    overrides = [*dataset, "mapper=none", *extra]
    if max_frames:
        overrides.append(f"dataset.max_frames={max_frames}")
    data, slam, _ = build_run(overrides)
    poses, gts, kf_frames, points, covariances, images, colours = [], [], [], [], [], [], []
    for i in range(len(data)):
        frame = data[i]
        if i == 0:
            slam.initialize(frame.gt_pose if frame.gt_pose is not None else np.eye(4))
        step = slam.process(frame)
        pose = step.tracking.pose
        poses.append(pose)
        gts.append(frame.gt_pose if frame.gt_pose is not None else np.full((4, 4), np.nan))
        if step.keyframe and step.tracking.gaussians is not None:  # as the run gives it (slamkit.run.loop_closing)
            keyframe = loop_keyframe(len(kf_frames), frame, pose, step.tracking.gaussians, 0)
            kf_frames.append(i)
            points.append(keyframe.points)
            covariances.append(keyframe.covariances)
            images.append(keyframe.image)
            colours.append(keyframe.colours)
    return TrackedSequence(np.array(poses), np.array(gts), np.array(kf_frames), points, covariances, images, colours,
                           overrides)


def tracking_digest(name: str) -> str:
    """12 hex digits of what decides sequence `name`'s tracked keyframes: its overrides, the
    configuration files and the source of the package and its plugins but the loop closures (which
    this benchmark runs on them), so that kept keyframes are never those of other code."""
    root = Path(__file__).resolve().parents[1]
    overrides = [o.replace(str(DATA), "DATA") for o in SEQUENCES[name]]  # the same wherever the data is
    digest = hashlib.sha256((repr(overrides) + inspect.getsource(track) + inspect.getsource(TrackedSequence)).encode())
    files = [f for folder in ("slamkit", "plugins", "conf") for f in (root / folder).rglob("*")
             if f.suffix in SOURCE_SUFFIXES and "loop_closures" not in f.parts]
    for f in sorted(files):
        digest.update(str(f.relative_to(root)).encode() + f.read_bytes())
    return digest.hexdigest()[:12]


def kept_keyframes(keyframes_dir: Path, name: str) -> Path:
    """Where `tracked` keeps sequence `name`'s keyframes in `keyframes_dir` (`tracking_digest`)."""
    return keyframes_dir / f"{name}-{tracking_digest(name)}.npz"


def load_kept(keyframes_dir: Path, name: str) -> TrackedSequence:
    """The keyframes this code's tracking of `name` kept in `keyframes_dir`, or a one-line exit
    saying how to make them."""
    path = kept_keyframes(keyframes_dir, name)
    if not path.is_file():
        raise SystemExit(f"{path}: no keyframes of {name} tracked by this code; make them with python "
                         f"benchmarks/loop_closure.py --sequences {name} --keyframes {keyframes_dir}")
    return TrackedSequence.load(path)


def tracked(name: str, keyframes_dir: Path | None) -> TrackedSequence:
    """Sequence `name` tracked, or read back from `keyframes_dir` when kept there by the same code
    (`kept_keyframes`; saved there when new)."""
    cache = kept_keyframes(keyframes_dir, name) if keyframes_dir else None
    if cache is not None and cache.is_file():
        return TrackedSequence.load(cache)
    seq = track(SEQUENCES[name])
    if cache is not None:
        seq.save(cache)
    return seq


def constrained_error(found: np.ndarray, truth: np.ndarray, reason: str) -> tuple[float, float]:
    """(metres, degrees) between a loop's relative pose and the truth's, leaving out the
    translation along the direction the loop left free (its reason names it, in the keyframe's
    frame): the graph takes nothing from the loop along it."""
    difference = relative_pose(found, truth)
    direction = verification.freed_direction(reason)
    if direction is not None:
        difference[:3, 3] = verification.without_component(difference[:3, 3], direction)
    return pose_difference(np.eye(4), difference)


def orthonormal(poses: np.ndarray) -> np.ndarray:
    """Poses with their rotations replaced by the nearest rotation matrices (NaN poses kept)."""
    out = np.array(poses, dtype=np.float64)
    finite = np.isfinite(out).all(axis=(1, 2))
    out[finite, :3, :3] = nearest_rotation(out[finite, :3, :3])
    return out


@dataclass
class Geometry:
    """Each keyframe's downsampled cloud (as the loop closure builds it) and the keyframe pairs
    eligible as loops with their ground-truth overlap."""

    clouds: list
    overlap: dict[tuple[int, int], float]  # (keyframe, earlier keyframe) -> ground-truth overlap


def geometry(seq: TrackedSequence, gt: np.ndarray, cfg) -> Geometry:
    from pykdtree.kdtree import KDTree

    from slamkit.geometry.registration import FeatureCloud

    clouds = [FeatureCloud(p, cfg.voxel, c) for p, c in zip(seq.points, seq.covariances)]
    trees = [KDTree(c.points) for c in clouds]
    kf = seq.keyframe_frames
    centres = seq.poses[kf, :3, 3]
    path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(centres, axis=0), axis=1))])
    overlap = {}
    for q in range(len(kf)):
        for m in range(max(q - cfg.exclude_recent, 0)):
            if path[q] - path[m] < cfg.min_path_m or not np.isfinite(gt[kf[[q, m]]]).all():
                continue
            p = transform_points(relative_pose(gt[kf[m]], gt[kf[q]]), clouds[q].points)
            d, _ = trees[m].query(p, k=1, distance_upper_bound=TRUE_REVISIT_VOXELS * cfg.voxel)
            overlap[(q, m)] = float(np.isfinite(d).mean())
    return Geometry(clouds, overlap)


def true_revisits(geo: Geometry) -> list[tuple[int, int]]:
    """The (keyframe, earlier keyframe) pairs that are true revisits."""
    return [pair for pair, overlap in geo.overlap.items() if overlap >= TRUE_REVISIT_OVERLAP]


def with_gt_loops(odometry: PoseGraph, geo: Geometry, seq: TrackedSequence, gt: np.ndarray, cfg,
                  measure=None, pairs: list[tuple[int, int]] | None = None) -> PoseGraph:
    """`odometry`'s graph with a loop edge at every eligible true revisit (or at each of `pairs`):
    the ground truth's relative pose, or `measure(q, m, odometry's relative pose)`'s."""
    kf = seq.keyframe_frames
    edges = [e for e in odometry.edges if e.kind == "odometry"]
    for q, m in true_revisits(geo) if pairs is None else pairs:
        T = relative_pose(gt[kf[m]], gt[kf[q]])
        if measure is not None:
            T = measure(q, m, relative_pose(seq.poses[kf[m]], seq.poses[kf[q]]))
        info, _ = verification.normalised_information(geo.clouds[q], geo.clouds[m], T, cfg.voxel)
        edges.append(PoseGraphEdge("loop", m, q, T, info / cfg.loop_sigma_m**2))
    return PoseGraph(odometry.keyframe_ids, seq.poses[kf], tuple(edges))


def solved_ate(seq: TrackedSequence, graph: PoseGraph, cfg) -> float:
    """ATE RMSE (metres) of every frame once `graph` is optimised as the loop closure `cfg` does."""
    return corrected_ate(seq, optimisation.optimise(graph, cfg.backend, cfg.robust_width))


def corrected_ate(seq: TrackedSequence, keyframe_poses: np.ndarray) -> float:
    """ATE RMSE (metres) of every frame once the keyframes sit at `keyframe_poses`."""
    kf = seq.keyframe_frames
    after = follow_keyframes(seq.poses, np.arange(len(seq.poses)), kf, keyframe_poses @ invert_pose(seq.poses[kf]))
    return ate(after, seq.gt_poses).rmse_m


def gicp_from_odometry(geo: Geometry, cfg, scales: tuple[float, ...] = (1.0,)):
    """measure(q, m, odometry) for with_gt_loops: G-ICP of q's cloud in m's from odometry's pose
    (`slamkit.geometry.registration.refine`, whose correspondences reach one voxel; each pair
    registered once). `scales`: > 1 voxel first, coarse to fine, each from the last's pose: the
    capture range, against odometry's error of several centimetres at a revisit."""
    found: dict[tuple[int, int], np.ndarray] = {}

    def measure(q: int, m: int, start: np.ndarray) -> np.ndarray:
        if (q, m) not in found:
            pose = np.asarray(start, dtype=np.float64)
            for scale in scales:
                pose = refine(geo.clouds[q], geo.clouds[m], pose, max_distance=scale * geo.clouds[m].voxel).pose
            found[(q, m)] = pose if np.isfinite(pose).all() else start
        return found[(q, m)]

    return measure


def keyframe_colours(name: str, seq: TrackedSequence, geo: Geometry) -> list[np.ndarray]:
    """Each keyframe's downsampled points' colours (N_k, 3) in [0, 1]: the points (its camera
    frame) projected into the colour image of its frame, read again from the dataset."""
    data, _, _ = build_run([*SEQUENCES[name], "mapper=none"])
    colours = []
    for k, frame_index in enumerate(seq.keyframe_frames):
        frame = data[int(frame_index)]
        u, v, _ = project_points(geo.clouds[k].points, np.eye(4), frame.camera)
        u = np.clip(np.round(u).astype(int), 0, frame.camera.width - 1)
        v = np.clip(np.round(v).astype(int), 0, frame.camera.height - 1)
        colours.append(np.asarray(frame.rgb)[v, u].astype(np.float64) / 255.0)
    return colours


def coloured_icp_from_odometry(geo: Geometry, colours: list[np.ndarray], cfg, scales: tuple[float, ...]):
    """measure(q, m, odometry) as `gicp_from_odometry`, by open3d's coloured ICP (Park et al.
    2017: point-to-plane and the colour's gradient on the tangent plane, 0.968 to 0.032, open3d's
    default) from odometry's pose, coarse to fine at `scales` voxels; a scale with no
    correspondence keeps the pose so far."""
    from slamkit.geometry.registration import import_open3d, single_threaded

    o3d = import_open3d()
    reg = o3d.pipelines.registration
    clouds: dict[int, object] = {}
    found: dict[tuple[int, int], np.ndarray] = {}

    def cloud(k: int):
        if k not in clouds:
            pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(geo.clouds[k].points.astype(np.float64)))
            pc.colors = o3d.utility.Vector3dVector(colours[k])
            pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * cfg.voxel, max_nn=30))
            pc.orient_normals_towards_camera_location(np.zeros(3))
            clouds[k] = pc
        return clouds[k]

    def measure(q: int, m: int, start: np.ndarray) -> np.ndarray:
        if (q, m) not in found:
            pose = np.asarray(start, dtype=np.float64)
            with single_threaded():
                for scale in scales:
                    try:
                        pose = np.asarray(reg.registration_colored_icp(
                            cloud(q), cloud(m), scale * cfg.voxel, pose, reg.TransformationEstimationForColoredICP(),
                            reg.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6,
                                                       max_iteration=50)).transformation)
                    except RuntimeError:  # "No correspondences found": diverged out of the overlap
                        pass
            found[(q, m)] = pose
        return found[(q, m)]

    return measure


def agreement(seq: TrackedSequence, gt: np.ndarray, measure,
              pairs: list[tuple[int, int]]) -> tuple[dict, list[tuple[int, int]]]:
    """Median distances (metres, degrees) between the relative poses of keyframe pairs (q, m) by
    odometry, by G-ICP (`measure`) and by the ground truth, how many G-ICP has right, and each
    pair's distances ("per_pair": q, m, then the six as named); and those right pairs (within
    RIGHT_LOOP_M and RIGHT_LOOP_DEG of the ground truth)."""
    kf = seq.keyframe_frames
    rows = []
    for q, m in pairs:
        odometry = relative_pose(seq.poses[kf[m]], seq.poses[kf[q]])
        truth = relative_pose(gt[kf[m]], gt[kf[q]])
        gicp = measure(q, m, odometry)
        rows.append([*pose_difference(odometry, truth), *pose_difference(gicp, truth),
                     *pose_difference(odometry, gicp)])
    median = np.median(np.array(rows), axis=0) if rows else [None] * 6
    names = ("odometry_vs_gt_m", "odometry_vs_gt_deg", "gicp_vs_gt_m", "gicp_vs_gt_deg", "odometry_vs_gicp_m",
             "odometry_vs_gicp_deg")
    right = [pair for pair, row in zip(pairs, rows) if row[2] < RIGHT_LOOP_M and row[3] < RIGHT_LOOP_DEG]
    return {"pairs": len(rows), **{n: None if v is None else float(v) for n, v in zip(names, median)},
            "gicp_within_2cm_1deg": len(right),
            "per_pair": [[int(q), int(m), *(float(v) for v in row)] for (q, m), row in zip(pairs, rows)]}, right


def slipped_edges_freed(graph: PoseGraph, edge_errors: dict[int, float]) -> PoseGraph:
    """`graph` with each odometry edge into keyframe k whose error `edge_errors[k]` (metres, against
    the ground truth) exceeds SLIPPED_EDGE_M given 1/100 of its information: an oracle of where
    tracking slipped."""
    edges = tuple(replace(e, information=e.information / 100.0)
                  if e.kind == "odometry" and edge_errors.get(e.target, 0.0) > SLIPPED_EDGE_M else e
                  for e in graph.edges)
    return PoseGraph(graph.keyframe_ids, graph.poses, edges)


def coverage(closure, geo: Geometry, seq: TrackedSequence, gt: np.ndarray, cfg) -> dict:
    """What the accepted loops leave to coverage rather than to accuracy: ATE (metres) with the
    ground truth's relative pose at exactly the accepted pairs (as good as exact loops can do
    there), and at the true revisits next to them (keyframe q-2..q against m-NEIGHBOURS..m+NEIGHBOURS
    of each accepted loop q -> m); and those neighbours registered by G-ICP alone
    (`refine`), started from the accepted loop's pose chained with odometry on both sides (so
    started within the odometry of a few keyframes of the truth): their errors against the
    ground truth and the ATE with them as loops."""
    kf = seq.keyframe_frames
    odometry_graph = closure.pose_graph()
    odometry = seq.poses[kf]
    loops = {(c.keyframe_id, c.match_id): c.relative_pose for c in closure.loops()}
    revisits = set(true_revisits(geo))
    found = {}
    for (q, m), loop in loops.items():
        for q2 in range(max(q - 2, 0), q + 1):
            for m2 in range(max(m - NEIGHBOURS, 0), m + NEIGHBOURS + 1):
                if (q2, m2) in revisits and (q2, m2) not in loops and (q2, m2) not in found:
                    start = invert_pose(odometry[m2]) @ odometry[m] @ loop @ invert_pose(odometry[q]) @ odometry[q2]
                    pose = refine(geo.clouds[q2], geo.clouds[m2], start).pose
                    found[(q2, m2)] = pose if np.isfinite(pose).all() else start
    errors = np.array([pose_difference(T, relative_pose(gt[kf[m]], gt[kf[q]])) for (q, m), T in found.items()])
    measured = {**loops, **found}

    def solved(graph: PoseGraph) -> float:
        return solved_ate(seq, graph, cfg)

    return {"ate_gt_at_accepted_m": solved(with_gt_loops(odometry_graph, geo, seq, gt, cfg, pairs=list(loops))),
            "neighbour_pairs": len(found),
            "ate_gt_with_neighbours_m": solved(with_gt_loops(odometry_graph, geo, seq, gt, cfg,
                                                             pairs=list(measured))),
            "ate_gicp_neighbours_m": solved(with_gt_loops(odometry_graph, geo, seq, gt, cfg,
                                                          lambda q, m, _: measured[(q, m)], list(measured))),
            "neighbour_error_median_m": float(np.median(errors[:, 0])) if len(found) else None,
            "neighbour_error_max_m": float(errors[:, 0].max()) if len(found) else None,
            "neighbours_within_2cm": int((errors[:, 0] <= 0.02).sum()) if len(found) else 0}


@functools.cache
def dataset_tuning(overrides: tuple[str, ...]) -> DatasetTuning:
    """The tuning of the dataset `overrides` name (built once per sequence)."""
    cfg, names = compose_run(list(overrides))
    return default_registry().create("dataset", names["dataset"], cfg.dataset).tuning


def feed(seq: TrackedSequence, overrides: list[str], wrong_loop: bool):
    """(the loop closure after every keyframe went through it, every check it made, CPU seconds,
    the (keyframe, match) of the injected wrong loop or None)."""
    cfg, names = compose_run([*seq.overrides, "loop_closure=pose_graph", *overrides])
    registry = default_registry()
    # the sequence's dataset tuning, as in a run (colour_odometry left null follows its colour_registered)
    context = RunContext(tuning=dataset_tuning(tuple(seq.overrides)), build=registry.create)
    closure = registry.create("loop_closure", names["loop_closure"], cfg.loop_closure, context)
    injected: list[tuple[int, int]] = []
    honest = verification.verify

    def verify_with_one_wrong(*args, **kwargs):
        check, information = honest(*args, **kwargs)
        if check.accepted and not injected:
            injected.append((check.keyframe_id, check.match_id))
            check = replace(check, relative_pose=check.relative_pose @ se3_exp(WRONG_LOOP))
        return check, information

    checks, cpu = [], 0.0
    pose_graph_closure.verification.verify = verify_with_one_wrong if wrong_loop else honest
    try:
        for k, frame in enumerate(seq.keyframe_frames):
            start = time.process_time()
            closure.add_keyframe(LoopKeyframe(k, int(frame), seq.poses[frame], seq.points[k], seq.covariances[k],
                                              seq.images[k], colours=seq.colours[k]))
            checks += closure.detect_and_optimise().checks
            cpu += time.process_time() - start
    finally:
        pose_graph_closure.verification.verify = honest
    return closure, closure.cfg, checks, cpu, injected[0] if injected else None


def measure(name: str, seq: TrackedSequence, overrides: list[str], wrong_loop: bool, oracle: bool,
            references: dict, with_coverage: bool = False, oracle_scales: tuple[float, ...] = (1.0,),
            oracle_colour: bool = False) -> dict:
    closure, cfg, checks, cpu, injected = feed(seq, overrides, wrong_loop)
    gt = orthonormal(seq.gt_poses)
    kf = seq.keyframe_frames
    key = (cfg.voxel, cfg.exclude_recent, cfg.min_path_m, cfg.loop_sigma_m, cfg.backend, cfg.robust_width,
           cfg.colour_odometry, cfg.colour_max_constraint, cfg.colour_max_across_m, cfg.colour_max_turn_deg,
           cfg.colour_max_slide_m)  # (the odometry edges the exact loops join)
    if key not in references:  # the references depend on these settings only (not on the thresholds)
        geo = geometry(seq, gt, cfg)
        floor = with_gt_loops(closure.pose_graph(), geo, seq, gt, cfg)
        ate_floor = solved_ate(seq, floor, cfg)
        ate_oracle, agree = None, None
        if oracle:
            register = gicp_from_odometry(geo, cfg, oracle_scales)
            measured = with_gt_loops(closure.pose_graph(), geo, seq, gt, cfg, register)
            ate_oracle = solved_ate(seq, measured, cfg)
            revisits = true_revisits(geo)
            at_revisits, right = agreement(seq, gt, register, revisits)
            # what checks refusing every wrong one of these loops and no right one would leave
            right_only = with_gt_loops(closure.pose_graph(), geo, seq, gt, cfg, register, right)
            right_pairs = set(right)
            others = [pair for pair in revisits if pair not in right_pairs]

            def solved(graph: PoseGraph) -> float:
                return solved_ate(seq, graph, cfg)

            edge_errors = [(k, *pose_difference(relative_pose(seq.poses[kf[k - 1]], seq.poses[kf[k]]),
                                                relative_pose(gt[kf[k - 1]], gt[kf[k]]))) for k in range(1, len(kf))]
            agree = {"true_revisits": at_revisits,
                     # where odometry's drift is: its keyframe edges furthest from the truth's relative pose
                     "odometry_edges_largest_errors": [
                         {"keyframe": k, "frames": [int(kf[k - 1]), int(kf[k])], "error_m": e_m, "error_deg": e_deg}
                         for k, e_m, e_deg in sorted(edge_errors, key=lambda row: -row[1])[:ORACLE_EDGES]],
                     "odometry_edges_error_sum_m": float(sum(row[1] for row in edge_errors)),
                     # were the graph told where odometry slipped: the accepted loops, and the odometry
                     # edges further than SLIPPED_EDGE_M from the truth given 1/100 of their information
                     "ate_slipped_edges_freed_m": solved(slipped_edges_freed(
                         closure.pose_graph(), {k: e_m for k, e_m, _ in edge_errors})),
                     "consecutive_keyframes": agreement(seq, gt, register, [(k, k - 1) for k in range(1, len(kf))])[0],
                     "ate_right_loops_only_m": solved(right_only),
                     # which revisits decide: exact loops at the pairs G-ICP has right, and at the others
                     "ate_gt_at_right_pairs_m": solved(with_gt_loops(closure.pose_graph(), geo, seq, gt, cfg,
                                                                     pairs=right)),
                     "ate_gt_at_other_pairs_m": solved(with_gt_loops(closure.pose_graph(), geo, seq, gt, cfg,
                                                                     pairs=others))}
            if oracle_colour:
                coloured = coloured_icp_from_odometry(geo, keyframe_colours(name, seq, geo), cfg, oracle_scales)
                at_revisits, right_coloured = agreement(seq, gt, coloured, revisits)
                agree["coloured_icp"] = {
                    "true_revisits": at_revisits,
                    "right_where_gicp_is_not": len(set(right_coloured) - set(right)),
                    "ate_right_loops_only_m": solved(with_gt_loops(closure.pose_graph(), geo, seq, gt, cfg, coloured,
                                                                   right_coloured)),
                    # perfect checks choosing, pair by pair, whichever of the two is right
                    "ate_either_right_m": solved(with_gt_loops(
                        closure.pose_graph(), geo, seq, gt, cfg,
                        lambda q, m, start: register(q, m, start) if (q, m) in right else coloured(q, m, start),
                        sorted(set(right) | set(right_coloured))))}
        references[key] = (geo, ate_floor, ate_oracle, agree)
    geo, ate_floor, ate_oracle, agree = references[key]
    graph = closure.pose_graph()
    start, repeats = time.process_time(), 20
    for _ in range(repeats):  # the optimisation alone, on the final graph
        optimisation.optimise(graph, cfg.backend, cfg.robust_width)
    optimise_ms = 1e3 * (time.process_time() - start) / repeats
    index = {int(f): k for k, f in enumerate(kf)}
    final = {(c.keyframe_id, c.match_id) for c in closure.loops()}
    rows = []
    for c in checks:
        err_m, err_deg = pose_difference(c.relative_pose, relative_pose(gt[c.match_frame_index], gt[c.frame_index]))
        overlap = geo.overlap.get((index[c.frame_index], index[c.match_frame_index]), 0.0)
        rows.append({**c.row(), "accepted": (c.keyframe_id, c.match_id) in final, "reason": c.reason,
                     "error_m": err_m, "error_deg": err_deg, "right": bool(err_m <= RIGHT_M and err_deg <= RIGHT_DEG),
                     "constrained_error_m": constrained_error(
                         c.relative_pose, relative_pose(gt[c.match_frame_index], gt[c.frame_index]), c.reason)[0],
                     "gt_overlap": overlap, "true_revisit": overlap >= TRUE_REVISIT_OVERLAP,
                     "injected_wrong": (c.keyframe_id, c.match_id) == injected})
    accepted = [r for r in rows if r["accepted"]]
    right = [r for r in accepted if r["right"]]
    revisits = [r for r in rows if r["true_revisit"]]
    revisit_keyframes = {q for (q, m), o in geo.overlap.items() if o >= TRUE_REVISIT_OVERLAP}
    looped_keyframes = {r["keyframe"] for r in right}
    return {
        "sequence": name, "backend": cfg.backend.value, "setting": " ".join(overrides) or "defaults",
        "frames": len(seq.poses), "keyframes": len(kf), "candidates": len(rows), "accepted": len(accepted),
        "right": len(right), "precision": len(right) / len(accepted) if accepted else None,
        "true_revisit_candidates": len(revisits),
        "pair_recall": sum(r["accepted"] and r["right"] for r in revisits) / len(revisits) if revisits else None,
        "keyframes_with_true_revisit": len(revisit_keyframes),
        "keyframe_recall": (len(looped_keyframes & revisit_keyframes) / len(revisit_keyframes)
                            if revisit_keyframes else None),
        "ate_none_m": ate(seq.poses, seq.gt_poses).rmse_m, "ate_loop_m": corrected_ate(seq, closure.pose_graph().poses),
        "ate_gt_loops_m": ate_floor, "ate_gicp_loops_m": ate_oracle, "cpu_s_per_keyframe": cpu / len(kf),
        "optimise_cpu_ms": optimise_ms, "relative_pose_agreement": agree,
        # the graph's odometry edges: how many colour_odometry moved, how far all are from the truth
        **odometry_edges(graph, seq, gt), **edges_at_truth(graph, seq, gt, cfg),
        "wrong_loop": None if not wrong_loop else ("none accepted" if injected is None
                                                   else "dropped" if injected not in final else "kept"),
        "coverage": coverage(closure, geo, seq, gt, cfg) if with_coverage else None,
        "checks": rows,
    }


def tracked_and_true(e: PoseGraphEdge, seq: TrackedSequence, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """(the tracked relative pose, the truth's, whether `e` is moved from the tracked one) of
    odometry edge `e`: 4x4 poses of its target keyframe in its source's camera frame."""
    kf = seq.keyframe_frames
    a, b = kf[e.source], kf[e.target]
    tracked = relative_pose(seq.poses[a], seq.poses[b])
    return tracked, relative_pose(gt[a], gt[b]), not np.allclose(e.relative_pose, tracked, atol=1e-9)


def odometry_edges(graph: PoseGraph, seq: TrackedSequence, gt: np.ndarray) -> dict:
    """{"odometry_edges_moved": how many odometry edges of `graph` are not at the tracked relative
    pose, "graph_odometry_edges_error_sum_m": every odometry edge's distance from the truth's
    relative pose, summed (metres; the tracked edges' sum is relative_pose_agreement's
    "odometry_edges_error_sum_m"), and of the moved edges: "moved_edges": (tracked edge's error,
    moved edge's error, distance between the two) each (metres), how many ended more than
    MOVED_EDGE_CHANGE_M nearer the truth ("moved_edges_better") or further ("moved_edges_worse")}."""
    moved, error = [], 0.0
    for e in graph.edges:
        if e.kind == "odometry":
            tracked, truth, is_moved = tracked_and_true(e, seq, gt)
            error += pose_difference(e.relative_pose, truth)[0]
            if is_moved:
                moved.append((pose_difference(tracked, truth)[0], pose_difference(e.relative_pose, truth)[0],
                              pose_difference(tracked, e.relative_pose)[0]))
    change = np.array([after - before for before, after, _ in moved])
    return {"odometry_edges_moved": len(moved), "graph_odometry_edges_error_sum_m": error, "moved_edges": moved,
            "moved_edges_better": int((change < -MOVED_EDGE_CHANGE_M).sum()),
            "moved_edges_worse": int((change > MOVED_EDGE_CHANGE_M).sum())}


def edges_at_truth(graph: PoseGraph, seq: TrackedSequence, gt: np.ndarray, cfg) -> dict:
    """The ATE (metres) of `graph` solved with some of its odometry edges set to the truth's
    relative pose: its moved edges (colour_odometry's; None when none moved), the `n` whose
    tracked relative pose is furthest from the truth's for each n of TRUTH_EDGES, and every one.
    Where odometry's errors cancel along the path, making a few of them right can raise the ATE;
    where they add up, it lowers it. A few solves of the final graph (milliseconds each), so it
    is measured on every row."""
    edges = {e.target: (e, *tracked_and_true(e, seq, gt)) for e in graph.edges if e.kind == "odometry"}

    def solved_with_truth(targets: set[int]) -> float:
        changed = tuple(replace(e, relative_pose=edges[e.target][2]) if e.kind == "odometry" and e.target in targets
                        else e for e in graph.edges)
        return solved_ate(seq, PoseGraph(graph.keyframe_ids, graph.poses, changed), cfg)

    moved = {k for k, (_, _, _, is_moved) in edges.items() if is_moved}
    worst = sorted(edges, key=lambda k: -pose_difference(edges[k][1], edges[k][2])[0])
    return {"ate_moved_edges_at_truth_m": solved_with_truth(moved) if moved else None,
            "ate_worst_edges_at_truth_m": {n: solved_with_truth(set(worst[:n])) for n in TRUTH_EDGES},
            "ate_every_edge_at_truth_m": solved_with_truth(set(edges))}


COLUMNS = [("sequence", "sequence"), ("backend", "backend"), ("setting", "setting"), ("keyframes", "keyframes"),
           ("candidates", "candidates"), ("accepted", "accepted"), ("right", "right"), ("precision", "precision"),
           ("true_revisit_candidates", "true-revisit cand."), ("pair_recall", "pair recall"),
           ("keyframe_recall", "keyframe recall"), ("ate_none_m", "ATE none cm"), ("ate_loop_m", "ATE loop cm"),
           ("ate_gt_loops_m", "ATE GT loops cm"), ("ate_gicp_loops_m", "ATE G-ICP loops cm"),
           ("cpu_s_per_keyframe", "CPU s/keyframe"), ("optimise_cpu_ms", "optimise CPU ms"),
           ("odometry_edges_moved", "odometry moved"), ("moved_edges_better", "moved: better"),
           ("moved_edges_worse", "moved: worse"), ("wrong_loop", "wrong loop")]


def print_table(rows: list[dict]) -> None:
    def cell(key: str, value) -> str:
        if value is None:
            return "-"
        if key.startswith("ate_"):
            return f"{100 * value:.2f}"
        return f"{value:.2f}" if isinstance(value, float) else str(value)

    print(markdown_table([[title for _, title in COLUMNS]] + [[cell(k, r.get(k)) for k, _ in COLUMNS] for r in rows]))


def square_drift() -> list[dict]:
    """The backends on tests/plugins/test_loop_closure.py's synthetic square (20 keyframes, 0.3 degrees
    and 4 mm of drift on every odometry edge, one exact loop): the worst position error before
    and after optimising, per backend."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the scene the tests use
    from test_loop_closure import drifted_graph, position_errors, square_path

    from slamkit_plugins.loop_closures.pose_graph.config import Backend

    truth = square_path()
    drift = {k: np.r_[0.0, np.radians(0.3), 0.0, 0.004, 0.0, 0.0] for k in range(len(truth) - 1)}
    graph = drifted_graph(truth, drift)
    rows = []
    for backend in Backend:
        poses = optimisation.optimise(graph, backend, robust_width=3.0)
        rows.append({"backend": backend.value, "worst_error_before_m": float(position_errors(graph.poses, truth).max()),
                     "worst_error_after_m": float(position_errors(poses, truth).max()),
                     "loop_residual_before": float(optimisation.whitened_residuals(graph, graph.poses)[-1]),
                     "loop_residual_after": float(optimisation.whitened_residuals(graph, poses)[-1])})
        print(f"square, {backend.value}: worst position error {100 * rows[-1]['worst_error_before_m']:.2f} cm -> "
              f"{100 * rows[-1]['worst_error_after_m']:.2f} cm; the loop's whitened residual "
              f"{rows[-1]['loop_residual_before']:.1f} -> {rows[-1]['loop_residual_after']:.1f}")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequences", default="7scenes,tum,replica")
    parser.add_argument("--backends", default="gtsam")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="an override for every run (e.g. loop_closure.max_candidates=4)")
    parser.add_argument("--sweep", default=None, metavar="KEY=V1,V2,...", help="one run per value")
    parser.add_argument("--wrong-loop", action="store_true", help="also run with one injected wrong loop")
    parser.add_argument("--oracle", action="store_true",
                        help="the G-ICP-loops reference: G-ICP at every true revisit (minutes)")
    parser.add_argument("--oracle-scales", default="1", metavar="S1,S2,...",
                        help="--oracle's G-ICP correspondence distances, voxels, coarse to fine (1: refine's)")
    parser.add_argument("--oracle-colour", action="store_true",
                        help="--oracle also by coloured ICP (open3d's), the points' colours from their frames")
    parser.add_argument("--coverage", action="store_true",
                        help="ATE with exact loops at the accepted pairs, and with their neighbours (see coverage)")
    parser.add_argument("--square", action="store_true",
                        help="only the backends on the synthetic square of the tests (one loop after drift)")
    parser.add_argument("--keyframes", type=Path, default=None, help="folder to keep / reuse the tracking runs in")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/loop_closure.json"))
    args = parser.parse_args()
    if args.square:
        rows = square_drift()
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"machine": platform.platform(), "when": time.strftime("%Y-%m-%d %H:%M"),
                                        "square": rows}, indent=1) + "\n")
        print(f"wrote {args.out}")
        return
    settings = [list(args.set)]
    if args.sweep:
        key, _, values = args.sweep.partition("=")
        settings = [[*args.set, f"{key}={v}"] for v in values.split(",")]
    rows = []
    for name in args.sequences.split(","):
        seq, references = tracked(name, args.keyframes), {}
        for backend in args.backends.split(","):
            for setting in settings:
                overrides = [*setting, f"loop_closure.backend={backend}"] if backend != "gtsam" else setting
                for wrong in (False, True) if args.wrong_loop else (False,):
                    row = measure(name, seq, overrides, wrong, args.oracle, references, args.coverage,
                                  tuple(float(v) for v in args.oracle_scales.split(",")), args.oracle_colour)
                    row["injected"] = wrong
                    rows.append(row)
                    print_table([row])
                    if row["coverage"]:
                        print(f"{name} coverage: " + ", ".join(
                            f"{k} {100 * v:.2f} cm" if k.endswith("_m") and v is not None else f"{k} {v}"
                            for k, v in row["coverage"].items()))
    print()
    print_table(rows)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": platform.platform(), "when": time.strftime("%Y-%m-%d %H:%M"),
                                    "command": "python benchmarks/loop_closure.py " + " ".join(
                                        a if " " not in a else repr(a) for a in __import__("sys").argv[1:]),
                                    "rows": rows}, indent=1, default=float) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
