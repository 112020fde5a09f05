"""Dataset plugins (tum, replica, sevenscenes) on the shared real data and on tiny synthetic
folders built in tmp_path."""

from __future__ import annotations

import logging
import zlib
from importlib.metadata import entry_points
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from slamkit.errors import ConfigError, DataError
from slamkit.formats.images import read_depth, read_rgb
from slamkit.formats.tum import interpolate_poses, read_tum_list, read_tum_trajectory
from slamkit.geometry.transforms import make_pose, quat_to_rotmat
from slamkit.types import Frame
from slamkit_plugins.datasets import replica, sevenscenes, tum
from slamkit_plugins.datasets.replica import ReplicaConfig, ReplicaDataset
from slamkit_plugins.datasets.sevenscenes import SevenScenesConfig, SevenScenesDataset
from slamkit_plugins.datasets.tum import TUMConfig, TUMDataset

from support.data import DATA
from support.data import REPLICA as REPLICA_DIR
from support.data import TUM as TUM_DIR
from support.errors import one_line
from support.folders import make_sevenscenes, save_depth


@pytest.fixture(scope="module")
def data() -> Path:
    if not DATA.is_dir():
        pytest.skip(f"shared data not found at {DATA}")
    return DATA



def assert_rigid(T: np.ndarray) -> None:
    assert T.shape == (4, 4) and np.isfinite(T).all()
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(T[3], [0, 0, 0, 1])


# --- registration -------------------------------------------------------------------------

@pytest.mark.parametrize("module, name, cls", [(tum, "tum", TUMDataset), (replica, "replica", ReplicaDataset),
                                               (sevenscenes, "sevenscenes", SevenScenesDataset)])
def test_hook_and_entry_point(module, name, cls):
    (spec,) = module.slamkit_plugins()
    assert spec.name == name and spec.cls is cls
    assert spec.config().path == ""  # every field has a default
    assert any(e.name == name and e.value == module.__name__ for e in entry_points(group="slamkit"))


def test_config_validation():
    with pytest.raises(ConfigError, match="dataset.camera"):
        TUMConfig(camera="fr4")
    with pytest.raises(ConfigError, match="dataset.association_tolerance"):
        TUMConfig(association_tolerance=0)
    with pytest.raises(ConfigError, match="dataset.depth_scale"):
        ReplicaConfig(depth_scale=-1)


# --- real data: TUM -------------------------------------------------------------------------

def test_tum_real(data):
    ds = TUMDataset(TUMConfig(path=str(TUM_DIR)))
    assert len(ds) == 150
    assert ds.camera == tum.CAMERAS["fr1"]
    assert ds.depth_trunc == 3.0 and ds.tuning.tracking_pixel_stride == 5 and ds.tuning.depth_scale == 5000
    f = ds[0]
    assert f.index == 0 and f.rgb.shape == (480, 640, 3) and f.rgb.dtype == np.uint8
    assert f.depth.shape == (480, 640) and f.depth.dtype == np.float32
    assert 0.5 < np.median(f.depth[f.depth > 0]) < 2.0
    assert f.depth_trunc == 3.0
    rgb_ts, _ = read_tum_list(TUM_DIR / "rgb.txt")
    assert f.timestamp == rgb_ts[0]
    # ground truth: interpolated from groundtruth.txt's two bracketing lines
    gt_ts, gt = read_tum_trajectory(TUM_DIR / "groundtruth.txt")
    k = np.searchsorted(gt_ts, f.timestamp)
    a = (f.timestamp - gt_ts[k - 1]) / (gt_ts[k] - gt_ts[k - 1])
    np.testing.assert_allclose(f.gt_pose[:3, 3], (1 - a) * gt[k - 1, :3, 3] + a * gt[k, :3, 3], atol=1e-9)
    np.testing.assert_allclose(f.gt_pose[:3, :3], gt[k, :3, :3], atol=0.02)  # 10 ms apart
    for i in (0, 75, 149):
        assert_rigid(ds[i].gt_pose)


def test_tum_real_selection_and_overrides(data):
    cfg = TUMConfig(path=str(TUM_DIR), start=10, stride=3, max_frames=5, fx=500.0, cy=240.0, depth_trunc=2.0)
    ds = TUMDataset(cfg)
    assert len(ds) == 5
    rgb_ts, _ = read_tum_list(TUM_DIR / "rgb.txt")
    f = ds[1]
    assert f.index == 1 and f.timestamp == rgb_ts[13]
    assert (f.camera.fx, f.camera.fy, f.camera.cx, f.camera.cy) == (500.0, 516.5, 318.6, 240.0)
    assert f.depth_trunc == 2.0
    with pytest.raises(IndexError):
        ds[5]


def test_tum_explicit_camera(data):
    assert TUMDataset(TUMConfig(path=str(TUM_DIR), camera="fr3")).camera == tum.CAMERAS["fr3"]


# --- real data: Replica ---------------------------------------------------------------------

def test_replica_real(data):
    ds = ReplicaDataset(ReplicaConfig(path=str(REPLICA_DIR)))
    assert len(ds) == 20
    assert ds.camera == replica.DEFAULT_CAMERA and ds.depth_trunc == 12.0
    f = ds[3]
    assert f.rgb.shape == (680, 1200, 3) and f.depth.shape == (680, 1200) and f.timestamp == 3.0
    assert 1.5 < np.median(f.depth[f.depth > 0]) < 4.0
    traj = np.loadtxt(REPLICA_DIR / "traj.txt").reshape(-1, 4, 4)
    np.testing.assert_allclose(f.gt_pose, traj[3])
    assert_rigid(f.gt_pose)
    ds = ReplicaDataset(ReplicaConfig(path=str(REPLICA_DIR), start=2, stride=5, max_frames=3, cx=600.0))
    assert len(ds) == 3 and ds[2].timestamp == 12.0 and ds[2].camera.cx == 600.0


# --- synthetic TUM folders ------------------------------------------------------------------

H, W = 480, 640


def save_rgb(path: Path, shape=(H, W)) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.full(shape + (3,), 128, np.uint8)).save(path)


def make_tum(root: Path, rgb_ts, depth_ts, gt_lines: str | None = None, rgb_order=None) -> Path:
    """A TUM-layout folder; depth image k holds 5000 * (k + 1) (i.e. k + 1 metres)."""
    root.mkdir(parents=True, exist_ok=True)
    order = rgb_order if rgb_order is not None else range(len(rgb_ts))
    (root / "rgb.txt").write_text("# color images\n" + "".join(f"{rgb_ts[i]:.6f} rgb/{i}.png\n" for i in order))
    (root / "depth.txt").write_text("".join(f"{t:.6f} depth/{k}.png\n" for k, t in enumerate(depth_ts)))
    for i in range(len(rgb_ts)):
        save_rgb(root / f"rgb/{i}.png")
    for k in range(len(depth_ts)):
        save_depth(root / f"depth/{k}.png", np.full((H, W), 5000 * (k + 1)))
    if gt_lines is not None:
        (root / "groundtruth.txt").write_text(gt_lines)
    return root


def test_tum_association_edge_cases(tmp_path):
    # rgb.txt longer than depth.txt; rgb 2 has no depth within 20 ms (the third depth is 0.5 s off)
    root = make_tum(tmp_path / "fr1_x", [0.0, 0.1, 0.2, 0.3], [0.005, 0.11, 0.7], rgb_order=[2, 0, 3, 1])
    ds = TUMDataset(TUMConfig(path=str(root)))
    assert len(ds) == 2
    f0, f1 = ds[0], ds[1]
    assert (f0.timestamp, f1.timestamp) == (0.0, 0.1)  # out-of-order lines were sorted
    assert f0.depth[0, 0] == pytest.approx(1.0) and f1.depth[0, 0] == pytest.approx(2.0)
    assert f0.gt_pose is None  # no groundtruth.txt


def test_tum_duplicate_timestamp(tmp_path):
    root = make_tum(tmp_path / "seq", [0.0, 0.1], [0.0, 0.1])
    (root / "rgb.txt").write_text("0.0 rgb/0.png\n0.1 rgb/1.png\n0.1 rgb/0.png\n")
    with pytest.raises(DataError) as e:
        TUMDataset(TUMConfig(path=str(root)))
    assert "0.100000" in one_line(e, "rgb.txt")


def test_tum_gt_interpolation_and_coverage(tmp_path, caplog):
    R1 = quat_to_rotmat(np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]))
    gt = "# t tx ty tz qx qy qz qw\n1.0 0 0 0 0 0 0 1\n" + f"1.02 2 0 0 0 0 {np.sin(np.pi / 4)} {np.cos(np.pi / 4)}\n"
    root = make_tum(tmp_path / "rgbd_dataset_freiburg2_desk", [1.01, 1.5], [1.01, 1.5], gt)
    ds = TUMDataset(TUMConfig(path=str(root)))
    assert ds.camera == tum.CAMERAS["fr2"]  # detected from the folder name
    mid = ds[0].gt_pose
    expected = interpolate_poses(np.array([1.0, 1.02]), np.stack([np.eye(4), make_pose(R1, [2, 0, 0])]), [1.01])[0]
    np.testing.assert_allclose(mid, expected)
    np.testing.assert_allclose(mid[:3, 3], [1.0, 0, 0])
    assert ds[1].gt_pose is None  # after the end of the ground truth
    with caplog.at_level(logging.WARNING):
        (root / "groundtruth.txt").unlink()
        ds = TUMDataset(TUMConfig(path=str(root)))
    assert ds[0].gt_pose is None and "groundtruth.txt" in caplog.text


def test_tum_undetectable_camera_warns(tmp_path, caplog):
    root = make_tum(tmp_path / "myseq", [0.0], [0.0])
    with caplog.at_level(logging.WARNING):
        assert TUMDataset(TUMConfig(path=str(root))).camera == tum.CAMERAS["fr1"]
    assert "dataset.camera" in caplog.text


def test_tum_explicit_gt_path(tmp_path):
    root = make_tum(tmp_path / "fr1_a", [0.0], [0.0])
    (tmp_path / "other.txt").write_text("0.0 1 2 3 0 0 0 1\n")
    ds = TUMDataset(TUMConfig(path=str(root), gt_path=str(tmp_path / "other.txt")))
    np.testing.assert_allclose(ds[0].gt_pose[:3, 3], [1, 2, 3])
    with pytest.raises(DataError) as e:
        TUMDataset(TUMConfig(path=str(root), gt_path="missing_gt.txt"))
    one_line(e, "missing_gt.txt")


# --- bad input --------------------------------------------------------------------------------

def test_missing_and_empty_folders(tmp_path):
    (tmp_path / "empty").mkdir()
    cases = [
        (TUMDataset, TUMConfig, tmp_path / "nope", "nope"),
        (TUMDataset, TUMConfig, tmp_path / "empty", "rgb.txt"),
        (ReplicaDataset, ReplicaConfig, tmp_path / "nope", "nope"),
        (ReplicaDataset, ReplicaConfig, tmp_path / "empty", "frame%06d.jpg"),
        (SevenScenesDataset, SevenScenesConfig, tmp_path / "nope", "nope"),
        (SevenScenesDataset, SevenScenesConfig, tmp_path / "empty", "empty"),
    ]
    for cls, cfg, path, name in cases:
        with pytest.raises(DataError) as e:
            cls(cfg(path=str(path)))
        one_line(e, name)
    with pytest.raises(DataError) as e:
        TUMDataset(TUMConfig(path=""))
    one_line(e, "dataset.path")


@pytest.mark.parametrize(
    "damage, name, needle",
    [
        (lambda r: (r / "depth/0.png").write_bytes(b"garbage bytes, not a PNG"), "0.png", "expected a 16-bit PNG"),
        (lambda r: (r / "rgb/0.png").write_bytes((r / "rgb/0.png").read_bytes()[:200]), "0.png", "colour"),
        (lambda r: (r / "depth/0.png").unlink(), "0.png", "not found"),
        (lambda r: save_depth(r / "depth/0.png", np.ones((240, 320))), "0.png", "320x240"),
        (lambda r: Image.fromarray(np.ones((H, W), np.uint8)).save(r / "depth/0.png"), "0.png", "mode L"),
        (lambda r: save_rgb(r / "rgb/0.png", (100, 100)), "0.png", "640x480"),
        (lambda r: flip_byte(r / "rgb/0.png"), "0.png", "colour"),
    ],
    ids=["garbage-depth", "truncated-rgb", "missing-depth", "depth-size", "8bit-depth", "rgb-size", "corrupt-rgb"],
)
def test_bad_images(tmp_path, damage, name, needle):
    root = make_tum(tmp_path / "fr1_bad", [0.0], [0.0])
    damage(root)
    ds = TUMDataset(TUMConfig(path=str(root)))
    with pytest.raises(DataError) as e:
        ds[0]
    assert needle in one_line(e, name)


def flip_byte(path: Path) -> None:
    """One byte in the middle of the file (a PNG's pixel data) inverted, the length kept."""
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))


def corrupt_pixels_keep_checksums(path: Path) -> None:
    """The PNG's compressed pixel data (its first IDAT chunk) damaged in the middle, with the
    chunk's CRC recomputed: only decoding can tell."""
    data = bytearray(path.read_bytes())
    pos = 8  # after the signature: chunks of length, type, data, CRC
    while data[pos + 4:pos + 8] != b"IDAT":
        pos += 12 + int.from_bytes(data[pos:pos + 4], "big")
    length = int.from_bytes(data[pos:pos + 4], "big")
    for i in range(pos + 8 + length // 2, pos + 8 + length // 2 + 16):
        data[i] ^= 0x5A
    data[pos + 8 + length:pos + 12 + length] = zlib.crc32(bytes(data[pos + 4:pos + 8 + length])).to_bytes(4, "big")
    path.write_bytes(bytes(data))


def test_a_colour_png_is_checked_when_loaded_and_decoded_when_read(tmp_path):
    """A frame's colour PNG is checked when the frame loads and decoded when `frame.rgb` is
    first read, to the pixels `read_rgb` gives: damage that only decoding finds, done after the
    load, is a one-line DataError naming the file at the read."""
    root = make_tum(tmp_path / "fr1_lazy", [0.0, 1.0], [0.0, 1.0])
    ds = TUMDataset(TUMConfig(path=str(root)))
    frame, later = ds[0], ds[1]
    np.testing.assert_array_equal(frame.rgb, read_rgb(root / "rgb/0.png"))
    corrupt_pixels_keep_checksums(root / "rgb/1.png")
    with pytest.raises(DataError) as e:
        later.rgb
    assert "colour" in one_line(e, "1.png")
    with pytest.raises(DataError):
        ds[1].rgb  # the checks at load pass: the checksums are right
    calls = []
    lazy = Frame(0, 0.0, lambda: calls.append(1) or np.zeros((2, 2, 3), np.uint8), np.zeros((2, 2), np.float32),
                 frame.camera)
    assert calls == []
    assert lazy.rgb.shape == (2, 2, 3) and lazy.rgb.shape == (2, 2, 3) and calls == [1]


def test_image_io_direct(tmp_path):
    save_depth(tmp_path / "d.png", np.array([[0, 5000, 65535]]))
    np.testing.assert_allclose(read_depth(tmp_path / "d.png", 5000.0), [[0, 1.0, 13.107]])
    np.testing.assert_allclose(read_depth(tmp_path / "d.png", 5000.0, invalid_values=[65535]), [[0, 1.0, 0]])
    Image.fromarray(np.full((2, 3), 7, np.uint8)).save(tmp_path / "g.png")
    assert read_rgb(tmp_path / "g.png").shape == (2, 3, 3)
    with pytest.raises(DataError) as e:
        read_rgb(tmp_path / "d.png")
    assert "colour" in one_line(e, "d.png")


# --- synthetic Replica ------------------------------------------------------------------------

def make_replica(root: Path, n: int, traj_lines: int, cam=True) -> Path:
    (root / "results").mkdir(parents=True)
    for i in range(n):
        Image.fromarray(np.zeros((6, 8, 3), np.uint8)).save(root / f"results/frame{i:06d}.jpg")
        save_depth(root / f"results/depth{i:06d}.png", np.full((6, 8), 1000 * (i + 1)))
    poses = np.stack([make_pose(np.eye(3), [i, 0, 0]) for i in range(traj_lines)])
    np.savetxt(root / "traj.txt", poses.reshape(-1, 16))
    if cam:
        (root / "cam_params.json").write_text(
            '{"camera": {"w": 8, "h": 6, "fx": 10.0, "fy": 11.0, "cx": 3.5, "cy": 2.5, "scale": 1000.0}}'
        )
    return root


def test_replica_synthetic(tmp_path):
    ds = ReplicaDataset(ReplicaConfig(path=str(make_replica(tmp_path / "r", 3, 3))))
    assert ds.camera.fx == 10.0 and ds.camera.width == 8 and len(ds) == 3
    f = ds[2]
    assert f.depth[0, 0] == pytest.approx(3.0)  # cam_params scale 1000 overrides 6553.5
    assert f.gt_pose[0, 3] == 2.0


def test_replica_errors(tmp_path):
    with pytest.raises(DataError) as e:
        ReplicaDataset(ReplicaConfig(path=str(make_replica(tmp_path / "a", 3, 2))))
    one_line(e, "traj.txt")
    root = make_replica(tmp_path / "b", 3, 3)
    (root / "results/depth000001.png").unlink()
    with pytest.raises(DataError) as e:
        ReplicaDataset(ReplicaConfig(path=str(root)))
    one_line(e, "depth000001.png")
    root = make_replica(tmp_path / "c", 2, 2)
    (root / "cam_params.json").write_text('{"camera": {"w": 8}}')
    with pytest.raises(DataError) as e:
        ReplicaDataset(ReplicaConfig(path=str(root)))
    one_line(e, "cam_params.json")
    with pytest.raises(DataError) as e:
        ReplicaDataset(ReplicaConfig(path=str(make_replica(tmp_path / "d", 2, 2)), gt_path="nothere.txt"))
    one_line(e, "nothere.txt")


# --- synthetic 7-Scenes -----------------------------------------------------------------------

def test_sevenscenes_synthetic(tmp_path):
    root, poses = make_sevenscenes(tmp_path / "chess" / "seq-01")
    (root / "frame-000002.pose.txt").unlink()
    ds = SevenScenesDataset(SevenScenesConfig(path=str(root)))
    assert len(ds) == 3 and ds.depth_trunc == 4.0
    c = ds.camera
    assert (c.width, c.height, c.fx, c.fy, c.cx, c.cy) == (64, 48, 60.0, 61.0, 31.5, 23.5)
    f = ds[1]
    assert f.timestamp == 1.0 and f.rgb.shape == (48, 64, 3)
    assert f.depth[0, 0] == 0 and f.depth[0, 1] == 0 and f.depth[1, 1] == pytest.approx(1.5)
    np.testing.assert_allclose(f.gt_pose, poses[1])
    assert ds[2].gt_pose is None


def test_sevenscenes_timestamps_are_the_frame_numbers_read_or_not(tmp_path):
    """A selection that starts at frame-000300: the timestamp a frame is read with and the one
    the dataset gives without reading it (what resume= checks the frame list with) agree."""
    root, _ = make_sevenscenes(tmp_path / "kitchen" / "seq-01", first=300)
    ds = SevenScenesDataset(SevenScenesConfig(path=str(root)))
    assert [ds.timestamp(i) for i in range(len(ds))] == [ds[i].timestamp for i in range(len(ds))] == [300.0, 301.0,
                                                                                                       302.0]


def test_sevenscenes_defaults_and_errors(tmp_path):
    root, _ = make_sevenscenes(tmp_path / "scene" / "seq-01", n=2, intrinsics=False)
    cam = SevenScenesDataset(SevenScenesConfig(path=str(root))).camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (585.0, 585.0, 320.0, 240.0)
    np.savetxt(root.parent / "camera-intrinsics.txt", [[70.0, 0, 32], [0, 70.0, 24], [0, 0, 1]])
    assert SevenScenesDataset(SevenScenesConfig(path=str(root))).camera.fx == 70.0  # found in the parent
    # a scene folder holding seq-NN subfolders: the message points at them
    with pytest.raises(DataError) as e:
        SevenScenesDataset(SevenScenesConfig(path=str(root.parent)))
    assert "seq-01" in one_line(e, "scene")
    (root / "frame-000001.pose.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 -inf\n0 0 0 1\n")
    ds = SevenScenesDataset(SevenScenesConfig(path=str(root)))
    with pytest.raises(DataError) as e:
        ds[1]
    assert "line 3" in one_line(e, "frame-000001.pose.txt")
    (root / "frame-000001.depth.png").unlink()
    with pytest.raises(DataError) as e:
        SevenScenesDataset(SevenScenesConfig(path=str(root)))
    one_line(e, "frame-000001.depth.png")


def test_passes_play_the_frames_back_and_forth_with_running_timestamps(replica_path):
    from slamkit_plugins.datasets.replica import ReplicaConfig, ReplicaDataset

    one = ReplicaDataset(ReplicaConfig(path=str(replica_path), max_frames=None))
    three = ReplicaDataset(ReplicaConfig(path=str(replica_path), passes=3))
    assert len(three) == 20 + 19 + 19
    assert list(three.raw_indices())[18:23] == [18, 19, 18, 17, 16] and list(three.raw_indices())[-2:] == [18, 19]
    stamps = [three.timestamp(i) for i in range(len(three))]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    back = three[21]  # the second pass, raw frame 17
    np.testing.assert_array_equal(back.depth, one[17].depth)
    np.testing.assert_allclose(back.gt_pose, one[17].gt_pose)
    assert back.index == 21 and back.timestamp == pytest.approx(stamps[21])
    assert len(ReplicaDataset(ReplicaConfig(path=str(replica_path), passes=3, max_frames=25))) == 25
