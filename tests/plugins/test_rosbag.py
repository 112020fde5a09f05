"""`dataset=rosbag`: bags written with rosbags from the real TUM frames read back as the TUM
dataset reads the folder (ROS1 .bag, ROS2 SQLite3 and MCAP; raw, compressed, 16UC1, 32FC1), and
bad bags failing in one line. From the command line: tests/e2e/test_rosbag_runs.py."""

from __future__ import annotations

import numpy as np
import pytest

from slamkit.errors import DataError
from slamkit.registry.discovery import discover
from slamkit.roles import Dataset

from support.rosbag_writer import write_tum_bag

rosbags = pytest.importorskip("rosbags", reason="rosbags is the optional extra `rosbag` (in `test`)")

from slamkit_plugins.datasets.rosbag import RosbagConfig, RosbagDataset  # noqa: E402
from slamkit_plugins.datasets.tum import TUMConfig, TUMDataset  # noqa: E402

N = 6


def _tum(tum_path, **kw) -> TUMDataset:
    return TUMDataset(TUMConfig(path=str(tum_path), **kw))


def test_rosbag_is_a_registered_dataset():
    spec = discover().get("dataset", "rosbag")
    assert issubclass(spec.cls, Dataset) and spec.config is RosbagConfig


@pytest.mark.parametrize("storage, color, depth, name", [
    ("ros1", "rgb8", "16UC1", "fr1.bag"),
    ("sqlite3", "bgr8", "32FC1", "fr1_sqlite"),
    ("mcap", "png", "compressedDepth", "fr1_mcap"),
])
def test_bag_frames_equal_the_tum_folder_frames(tmp_path, tum_path, storage, color, depth, name):
    """Lossless encodings: the same pixels, depth in metres, stamps, intrinsics and ground truth."""
    bag = write_tum_bag(tum_path, tmp_path / name, N, storage, color, depth)
    ds = RosbagDataset(RosbagConfig(path=str(bag), depth_scale=5000.0,
                                    groundtruth=str(tum_path / "groundtruth.txt")))
    ref = _tum(tum_path, max_frames=N)
    assert (ds.color_topic, ds.depth_topic, ds.info_topic) == (
        "/camera/rgb/image_color", "/camera/depth/image", "/camera/rgb/camera_info")
    assert ds.camera == ref.camera
    assert len(ds) == len(ref)  # the bag has the first N colour and depth images; pairing drops the same ones
    for i in range(len(ds)):
        got, want = ds[i], ref[i]
        assert got.timestamp == pytest.approx(want.timestamp, abs=1e-6)
        np.testing.assert_array_equal(got.rgb, want.rgb)
        np.testing.assert_array_equal(got.depth, want.depth)
        np.testing.assert_allclose(got.gt_pose, want.gt_pose, atol=1e-9)


def test_a_mcap_file_opens_without_its_folder_and_jpeg_colour_decodes(tmp_path, tum_path):
    bag = write_tum_bag(tum_path, tmp_path / "jpeg", 3, "mcap", "jpeg", "32FC1")
    ds = RosbagDataset(RosbagConfig(path=str(bag / "jpeg.mcap")))
    ref = _tum(tum_path, max_frames=3)
    frame, want = ds[0], ref[0]
    np.testing.assert_array_equal(frame.depth, want.depth)  # 32FC1 is metres: no depth_scale involved
    assert np.abs(frame.rgb.astype(int) - want.rgb).mean() < 3  # JPEG quality 95
    assert frame.gt_pose is None  # no dataset.groundtruth


def test_millimetre_depth_and_intrinsics_overrides_without_camera_info(tmp_path, tum_path):
    bag = write_tum_bag(tum_path, tmp_path / "x.bag", 2, camera_info=False)
    with pytest.raises(DataError, match=r"has no CameraInfo topic .*dataset.fx, dataset.fy"):
        RosbagDataset(RosbagConfig(path=str(bag)))
    ds = RosbagDataset(RosbagConfig(path=str(bag), fx=500.0, fy=501.0, cx=320.0, cy=240.0))
    assert (ds.camera.width, ds.camera.height, ds.camera.fx, ds.camera.cy) == (640, 480, 500.0, 240.0)
    # the same raw values read as millimetres (the default depth_scale, 16UC1) are 5x the TUM metres
    np.testing.assert_allclose(ds[0].depth, _tum(tum_path)[0].depth * 5.0, rtol=1e-6)


def test_topics_chosen_by_name_and_pairing_tolerance(tmp_path, tum_path):
    bag = write_tum_bag(tum_path, tmp_path / "x.bag", 4)
    ds = RosbagDataset(RosbagConfig(path=str(bag), color_topic="/camera/rgb/image_color",
                                    depth_topic="/camera/depth/image", camera_info_topic="/camera/rgb/camera_info"))
    assert len(ds) == len(_tum(tum_path, max_frames=4))
    with pytest.raises(DataError,
                       match=r"dataset.depth_topic: /camera/rgb/camera_info is a sensor_msgs/msg/CameraInfo"):
        RosbagDataset(RosbagConfig(path=str(bag), depth_topic="/camera/rgb/camera_info"))
    with pytest.raises(DataError, match=r"none of \d+ colour frames .* within 1e-06 s"):
        RosbagDataset(RosbagConfig(path=str(bag), sync_tolerance=1e-6))


@pytest.mark.parametrize("how, message", [
    ("no_images", r"has no image topic \(expected sensor_msgs/Image or CompressedImage topics; it has "
                  r"/camera/rgb/camera_info \(CameraInfo\)\)"),
    ("truncated", r"cannot read ROS bag .*x\.bag: .*index"),
    ("sizes", r"depth images are 320x240 but the colour images are 640x480"),
    ("missing", r"ROS bag .*nothing\.bag not found"),
])
def test_bad_bags_are_one_line_data_errors(tmp_path, tum_path, how, message):
    path = tmp_path / "x.bag"
    if how == "no_images":
        write_tum_bag(tum_path, path, 2, image_topics=False)
    elif how == "truncated":
        data = write_tum_bag(tum_path, path, 2).read_bytes()
        path.write_bytes(data[: len(data) // 2])
    elif how == "sizes":
        write_tum_bag(tum_path, path, 2, depth_size=(320, 240))
    else:
        path = tmp_path / "nothing.bag"
    with pytest.raises(DataError, match=message) as info:
        RosbagDataset(RosbagConfig(path=str(path)))
    assert "\n" not in str(info.value)
