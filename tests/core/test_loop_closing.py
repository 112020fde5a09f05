"""Loop closure inside the run (`slamkit.run.loop_closing`, `SLAM.correct`), in process: the map's
Gaussians move rigidly with their keyframe and the optimiser's state with them, the trajectory,
keyframes and tracker follow a correction (sequential), viewers see it, the loop closure's state
survives a checkpoint, loops.csv and pose_graph.g2o are written, and a tracker that cannot follow
is refused. Real time (the loop closure's own process) and real 7-Scenes frames:
tests/e2e/test_loop_closing_runs.py."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import torch

from slamkit.formats.checkpoint import read_checkpoint, write_checkpoint
from slamkit.formats.g2o import read_g2o
from slamkit.formats.tum import read_tum_trajectory
from slamkit.geometry import make_pose, quat_to_rotmat, so3_exp
from slamkit.map.gaussian_map import GaussianMap, GaussianRows
from slamkit.roles.loop_closure import LoopDecision
from slamkit.run import checkpoint
from slamkit.run.build import build_run
from slamkit.run.loop_closing import Correction, LoopCloser
from slamkit.run.state import RunState
from slamkit.types import Camera, Frame

from support.loop_closing import (
    SHIFT,
    RecordingViewer,
    ShiftingConfig,
    ShiftingLoopClosure,
    check_run_follows_shift,
    loop_registry,
    offsets,
    run_shifted,
)


@pytest.fixture
def registry():
    return loop_registry()

#: components with signs: Adam's element-wise second moment follows it exactly.
HALF_TURN = make_pose(so3_exp(np.array([0.0, 0.0, np.pi])), [0.05, -0.02, 0.03])


def rows_of_keyframes(keyframe_ids: list[int], seed: int = 0) -> GaussianRows:
    rng = np.random.default_rng(seed)
    n = len(keyframe_ids)
    quats = rng.normal(size=(n, 4))
    return GaussianRows.from_shapes(rng.normal(size=(n, 3)), quats / np.linalg.norm(quats, axis=1, keepdims=True),
                                    rng.uniform(0.01, 0.05, (n, 3)), rng.uniform(0, 1, (n, 3)), 0.7,
                                    np.ones(n, bool), np.asarray(keyframe_ids))


def test_each_gaussian_moves_rigidly_with_the_keyframe_that_added_it():
    """Rows of keyframes 0, 1 and 2 (2 added after the correction's last keyframe: it follows
    1's motion): means, rotations and the entry geometry the tracker aligns to move; the shape,
    colour and opacity do not; the map counts a structural change (a training step in flight
    is dropped)."""
    gm = GaussianMap()
    gm.append(rows_of_keyframes([0, 0, 1, 1, 2, 2]))
    before = gm.rows()
    version, structure = gm.version, gm.structure_version
    updates = np.array([make_pose(so3_exp(np.array([0.0, 0.1, 0.0])), [0.1, 0.0, 0.0]), HALF_TURN])
    gm.move_rows(gm.keyframe_motion(updates))
    after = gm.rows()
    owner = np.array([0, 0, 1, 1, 1, 1])
    for field in ("means", "entry_means"):
        x = getattr(before, field).double().numpy()
        expected = np.einsum("nij,nj->ni", updates[owner, :3, :3], x) + updates[owner, :3, 3]
        np.testing.assert_allclose(getattr(after, field).numpy(), expected, atol=1e-6)
    for field in ("quats", "entry_quats"):
        rotations = quat_to_rotmat(getattr(before, field).double().numpy())
        np.testing.assert_allclose(quat_to_rotmat(getattr(after, field).double().numpy()),
                                   updates[owner, :3, :3] @ rotations, atol=1e-6)
    for field in ("log_scales", "entry_log_scales", "colors", "opacity_logits", "keyframe_id", "trackable"):
        assert torch.equal(getattr(after, field), getattr(before, field)), field
    assert gm.version > version and gm.structure_version > structure


def _trained_slam(optimizer: str):
    """A 3DGS SLAM run three synthetic frames in: keyframes, Gaussians and Adam moments."""
    dataset, slam, _ = build_run(["mapper=gaussian_splatting", "mapper/rasterizer=cpu", f"mapper/optimizer={optimizer}",
                                  "dataset.num_frames=3", "mapper.resolution_scale=0.25", "iterations_per_frame=2",
                                  "mapper.strategy.prune_every=0", "mapper.view_cache_mb=0"])
    slam.initialize(dataset[0].gt_pose)
    for i in range(len(dataset)):
        slam.process(dataset[i])
    return slam


@pytest.mark.parametrize("optimizer", ["adam", "visible_adam"])
def test_moving_the_map_commutes_with_a_training_step(optimizer):
    """The optimiser's state stays consistent: moving every keyframe (its Gaussians and its
    training view) by one rigid motion, then training a step, gives the moved map of training
    the step first, moments included (the motion's rotation permutes coordinates, so even Adam's
    element-wise second moment follows it exactly)."""
    moved_first, trained_first = _trained_slam(optimizer), _trained_slam(optimizer)
    updates = np.repeat(HALF_TURN[None], moved_first.num_keyframes, axis=0)
    moved_first.mapper.move_keyframes(updates)
    assert moved_first.optimize(1) == 1
    assert trained_first.optimize(1) == 1
    trained_first.mapper.move_keyframes(updates)
    a, b = moved_first.gaussian_map, trained_first.gaussian_map
    assert len(a) == len(b) > 0
    for name in ("means", "quats", "log_scales", "colors", "opacity_logits"):
        torch.testing.assert_close(getattr(a, name).detach(), getattr(b, name).detach(), atol=2e-5, rtol=1e-4)
    state_a = moved_first.mapper.optimizer.row_state()
    state_b = trained_first.mapper.optimizer.row_state()
    for name in ("means", "quats"):
        for va, vb in zip(state_a[name], state_b[name]):
            torch.testing.assert_close(va, vb, atol=1e-9, rtol=1e-3)
    keyframes_a = moved_first.mapper.keyframes
    for k in keyframes_a.ids:
        np.testing.assert_allclose(keyframes_a[k].pose, trained_first.mapper.keyframes[k].pose, atol=1e-12)


def test_a_correction_spreads_over_the_keyframes_and_the_frames_follow_them():
    """Keyframes 0-3, the decision's graph holds 0-2 (3 was tracked while it was made): 3 and
    the frames after it follow 2; two decisions compose; the trajectory's frames keep their
    pose relative to their keyframe."""
    a, b = make_pose(np.eye(3), [0.1, 0, 0]), make_pose(so3_exp(np.array([0, 0.2, 0])), [0, 0.3, 0])
    decision = LoopDecision(updates={0: np.eye(4), 1: a, 2: b}, world=1)
    correction = Correction.of(decision, num_keyframes=4)
    np.testing.assert_allclose(correction.updates, [np.eye(4), a, b, b])
    both = correction.then(Correction(np.array([a, a, a, a, a])))
    np.testing.assert_allclose(both.updates, [a, a @ a, a @ b, a @ b, a @ b])
    state = RunState()
    rng = np.random.default_rng(1)
    poses = [make_pose(so3_exp(rng.normal(size=3) * 0.1), rng.normal(size=3)) for _ in range(7)]
    state.poses, state.keyframe_rows = list(poses), [0, 2, 4]  # keyframes 0, 1, 2 at frames 0, 2, 4
    state.follow(correction)
    owner = [0, 0, 1, 1, 2, 2, 2]
    followed = [correction.updates[k] @ p for k, p in zip(owner, poses)]
    np.testing.assert_allclose(np.array(state.poses), np.array(followed))


# -- a loop closure whose decisions are known: it shifts every keyframe by SHIFT once ----------

def test_the_run_follows_a_correction_its_map_tracker_and_trajectory(tmp_path, registry):
    check_run_follows_shift(tmp_path, registry, "sequential")


def test_corrections_held_to_the_end_leave_tracking_in_odometry_s_frame_then_move_everything(tmp_path, registry):
    """loop_corrections=at_end: the decision (made at the third keyframe) waits for the end of
    the stream: every frame is tracked and shown where odometry puts it (millimetres from the
    truth, where with corrections during the stream the frames after the decision are shown
    10 cm off), the loop shown all the same, then one correction moves the trajectory, the
    keyframes and the map by SHIFT, as during the stream."""
    shown = {}
    for when in ("during", "at_end"):
        metrics = run_shifted(registry, tmp_path / when, "viewer=recording", f"loop_corrections={when}")
        assert metrics["loop_corrections"] == 1 and metrics["loops_accepted"] == 1
        np.testing.assert_allclose(offsets(tmp_path / when), np.tile(SHIFT[:3, 3], (30, 1)), atol=0.01)
        _, gt = read_tum_trajectory(tmp_path / when / "groundtruth.txt")
        shown[when] = np.array([p[:3, 3] for p in RecordingViewer.poses]) - gt[:, :3, 3]
        assert RecordingViewer.loops[-1] == 1  # the loop is shown while the stream goes on, held or not
    assert np.abs(shown["at_end"]).max() < 0.01
    assert np.abs(shown["during"][-1] - SHIFT[:3, 3]).max() < 0.01
    maps = {when: checkpoint.load_map(tmp_path / when)[0].entry_means.mean(dim=0).numpy() for when in shown}
    np.testing.assert_allclose(maps["at_end"], maps["during"], atol=0.01)


def test_two_held_decisions_compose_as_the_two_applied_when_made(tmp_path, registry):
    """Two decisions (at the third and the fourth keyframe), each moving every keyframe by SHIFT:
    applied when made or held to the end and composed, the trajectory ends 2 SHIFT from the
    truth, frames before, between and after the decisions alike; held, every frame was shown
    where odometry put it and both loops were shown."""
    for when in ("during", "at_end"):
        metrics = run_shifted(registry, tmp_path / when, "viewer=recording", "loop_closure.again=4",
                              f"loop_corrections={when}")
        assert metrics["loops_accepted"] == 2 and metrics["loop_corrections"] == (2 if when == "during" else 1)
        np.testing.assert_allclose(offsets(tmp_path / when), np.tile(2 * SHIFT[:3, 3], (30, 1)), atol=0.01)
        assert RecordingViewer.loops[-1] == 2
    _, gt = read_tum_trajectory(tmp_path / "at_end" / "groundtruth.txt")
    assert np.abs(np.array([p[:3, 3] for p in RecordingViewer.poses]) - gt[:, :3, 3]).max() < 0.01


def test_viewers_are_shown_the_corrected_trajectory_and_the_loops(tmp_path, registry):
    """The ViewerFrame after a correction: the trajectory and the keyframes moved with it, and
    the loop as a line between its two keyframes' corrected camera centres; rerun records it."""
    run_shifted(registry, tmp_path / "run", "viewer=recording")
    view = RecordingViewer.last
    _, poses = read_tum_trajectory(tmp_path / "run" / "trajectory.txt")
    _, keyframes = read_tum_trajectory(tmp_path / "run" / "keyframes.txt")
    np.testing.assert_allclose(view.trajectory, poses[:, :3, 3], atol=1e-6)
    np.testing.assert_allclose(view.keyframes, keyframes[:, :3, 3], atol=1e-6)
    with open(tmp_path / "run" / "loops.csv") as f:
        (loop,) = list(csv.DictReader(f))
    np.testing.assert_allclose(view.loops, [[keyframes[int(loop["match_keyframe"]), :3, 3],
                                             keyframes[int(loop["keyframe"]), :3, 3]]], atol=1e-6)
    pytest.importorskip("rerun", reason="rerun-sdk is the optional extra `viewer`")
    from rerun.chunk import RrdReader

    run_shifted(registry, tmp_path / "rerun", "viewer=rerun", "viewer.map_every=0", "viewer.render_every=0",
         "viewer.image_every=0")
    strips = []
    for chunk in RrdReader(str(tmp_path / "rerun" / "recording.rrd")).stream().to_chunks():
        if chunk.entity_path == "/world/loops":
            batch = chunk.to_record_batch()
            strips += batch.column(batch.schema.names.index("LineStrips3D:strips")).to_pylist()
    assert [len(s) for s in strips] == [0, 1]  # none, then the loop: one strip of two points
    assert len(strips[-1][0]) == 2


@pytest.mark.parametrize("when", ["during", "at_end"])
def test_a_resumed_run_keeps_the_graph_and_goes_on_with_it(tmp_path, registry, when):
    """15 frames (the correction made at the second keyframe, frame 10), then resumed to 30:
    the trajectory and the pose graph of the 30-frame run, and one correction in all (at_end:
    the first session's, applied when its stream ended)."""
    setting = ("loop_closure.after=2", f"loop_corrections={when}")
    whole = run_shifted(registry, tmp_path / "whole", *setting)
    run_shifted(registry, tmp_path / "part", *setting, "dataset.max_frames=15")
    assert checkpoint.load(tmp_path / "part")["state"]["loop_closure"]["plugin"]["world_updates"]
    resumed = run_shifted(registry, tmp_path / "part", *setting, f"resume={tmp_path / 'part'}")
    assert resumed["num_frames"] == whole["num_frames"] == 30
    assert resumed["loop_corrections"] == whole["loop_corrections"] == 1
    _, poses_whole = read_tum_trajectory(tmp_path / "whole" / "trajectory.txt")
    _, poses_resumed = read_tum_trajectory(tmp_path / "part" / "trajectory.txt")
    # at_end: the resumed session tracks in the corrected world from frame 15, the whole run in odometry's (float32 map)
    assert np.abs(poses_whole - poses_resumed).max() < (1e-6 if when == "during" else 1e-5)
    graph_whole, graph_resumed = (read_g2o(tmp_path / run / "pose_graph.g2o") for run in ("whole", "part"))
    np.testing.assert_allclose(graph_whole.poses, graph_resumed.poses, atol=1e-6)


def test_a_checkpoint_holds_the_keyframes_and_decisions_not_applied_yet(tmp_path):
    """Between a decision and the frame that applies it (real time), and with keyframes the
    loop thread has not taken: the checkpoint keeps both, and the restored loop closer applies
    the same correction and decides on those keyframes."""
    cfg = ShiftingConfig(after=2)
    closer = LoopCloser(ShiftingLoopClosure(cfg))
    camera = Camera(8, 8, 10.0, 10.0, 4.0, 4.0)
    frame = Frame(index=0, timestamp=0.0, rgb=np.zeros((8, 8, 3), np.uint8), depth=np.ones((8, 8)), camera=camera)
    for k in range(2):
        closer.add_keyframe(k, frame, make_pose(np.eye(3), [k, 0, 0]), None)
    closer.detect()  # the decision: waiting for the tracking thread
    closer.add_keyframe(2, frame, make_pose(np.eye(3), [2, 0, 0]), None)  # not taken by the loop closure yet
    path = tmp_path / "checkpoint.zip"
    write_checkpoint(path, {}, {"loop_closure": closer.state_dict()})
    restored = LoopCloser(ShiftingLoopClosure(cfg))
    restored.load_state_dict(read_checkpoint(path)["state"]["loop_closure"])
    correction, expected = restored.take(3), closer.take(3)
    np.testing.assert_allclose(correction.updates, expected.updates)
    np.testing.assert_allclose(correction.updates, np.repeat(SHIFT[None], 3, axis=0))
    assert restored.applied_world == 1 and restored.waiting() == 1
    restored.detect()  # keyframe 2 was tracked in world 0: the loop closure places it in world 1
    np.testing.assert_allclose(restored.closure.poses[2], SHIFT @ make_pose(np.eye(3), [2, 0, 0]))
    assert [r["accepted"] for r in restored.rows()] == [True]


def test_a_tracker_that_cannot_follow_a_correction_is_refused_before_therun_shifted(registry):
    from slamkit.errors import ConfigError

    with pytest.raises(ConfigError, match="tracker=small_gicp cannot follow a loop closure's corrections"):
        build_run(["tracker=small_gicp", "loop_closure=shifting"], registry)
