"""`dataset=folder`: a user's own RGB-D folder, built here from the first frames of the shared
TUM sequence (colour and depth copied under the colour image's name, an intrinsics file, the
ground truth in both trajectory formats)."""

from __future__ import annotations

import json
import shutil
from importlib.metadata import entry_points
from pathlib import Path

import numpy as np
import pytest

from slamkit.errors import ConfigError, DataError
from slamkit.formats.tum import write_tum_trajectory
from slamkit_plugins.datasets import folder
from slamkit_plugins.datasets.folder import FolderConfig, FolderDataset
from slamkit_plugins.datasets.tum import CAMERAS, TUMConfig, TUMDataset

from support.data import TUM, require_data
from support.errors import one_line
from support.folders import FOLDER_FRAMES as FRAMES
from support.folders import FOLDER_INTRINSICS as INTRINSICS
from support.folders import make_folder


@pytest.fixture(scope="module")
def tum_frames() -> TUMDataset:
    return TUMDataset(TUMConfig(path=str(require_data(TUM)), max_frames=FRAMES))


@pytest.fixture
def scene(tmp_path, tum_frames) -> Path:
    return make_folder(tmp_path / "scene", tum_frames)



def test_hook_and_entry_point():
    (spec,) = folder.slamkit_plugins()
    assert spec.name == "folder" and spec.cls is FolderDataset and spec.config is FolderConfig
    assert spec.config().intrinsics == "intrinsics.yaml"
    assert any(e.name == "folder" and e.value == folder.__name__ for e in entry_points(group="slamkit"))


def test_loads_frames_intrinsics_depth_and_tum_trajectory(scene, tum_frames):
    ds = FolderDataset(FolderConfig(path=str(scene), trajectory="gt.txt"))
    assert len(ds) == FRAMES
    assert ds.camera == CAMERAS["fr1"] and ds.depth_trunc == 3.0
    assert ds.timestamp(3) == pytest.approx(tum_frames.timestamp(3), abs=1e-6)  # without reading images
    for i in (0, FRAMES - 1):
        frame, ref = ds[i], tum_frames[i]
        assert frame.timestamp == pytest.approx(ref.timestamp, abs=1e-6)  # the numeric stems
        np.testing.assert_array_equal(frame.rgb, ref.rgb)
        np.testing.assert_allclose(frame.depth, ref.depth)  # metres: raw / 5000
        assert frame.depth.dtype == np.float32 and 0.3 < np.median(frame.depth[frame.depth > 0]) < 3.0
        np.testing.assert_allclose(frame.gt_pose, ref.gt_pose, atol=1e-9)


def test_4x4_trajectory_frame_index_timestamps_and_json_intrinsics(tmp_path, tum_frames):
    scene = make_folder(tmp_path / "s", tum_frames, stems=[f"frame{i}" for i in range(FRAMES)])
    (scene / "rgb").mkdir()
    for p in (scene / "color").iterdir():  # rgb/ is accepted for color/
        p.rename(scene / "rgb" / p.name)
    (scene / "color").rmdir()
    (scene / "intrinsics.yaml").unlink()
    (scene / "intrinsics.json").write_text(json.dumps(dict(fx=517.3, fy=516.5, cx=318.6, cy=255.3, width=640,
                                                           height=480, depth_scale=5000)))
    gt = np.array([tum_frames[i].gt_pose for i in range(FRAMES)])
    np.savetxt(scene / "trajectory.txt", gt.reshape(FRAMES, 16))  # found without dataset.trajectory
    ds = FolderDataset(FolderConfig(path=str(scene), intrinsics="intrinsics.json"))
    assert [ds[i].timestamp for i in range(FRAMES)] == list(range(FRAMES))
    np.testing.assert_allclose(ds[3].gt_pose, gt[3])
    assert ds.depth_trunc == float("inf")  # no depth_trunc in the file
    # natural order: frame2 before frame10
    assert [p.stem for p in ds.rgb_files][:3] == ["frame0", "frame1", "frame2"]


def test_timestamps_file_and_depth_scale_override(scene):
    (scene / "timestamps.txt").write_text("".join(f"{10 + 0.5 * i}\n" for i in range(FRAMES)))
    ds = FolderDataset(FolderConfig(path=str(scene), depth_scale=2500.0, max_frames=2))
    assert [ds[i].timestamp for i in range(2)] == [10.0, 10.5]
    assert ds[0].gt_pose is None  # no trajectory.txt, none given
    ref = FolderDataset(FolderConfig(path=str(scene)))
    np.testing.assert_allclose(ds[0].depth, 2 * ref[0].depth)


@pytest.mark.parametrize("text, needles", [
    (INTRINSICS.replace("fy: 516.5\n", ""), ["missing key fy"]),
    (INTRINSICS.replace("depth_scale: 5000\n", ""), ["missing key depth_scale"]),
    (INTRINSICS.replace("fx: 517.3", "fx: wide"), ["fx = 'wide' is not a number"]),
    (INTRINSICS.replace("fx: 517.3", "fx: -1"), ["fx = -1"]),
    (INTRINSICS.replace("width: 640", "width: 320"), ["is 640x480", "says 320x480"]),
    ("fx: [1, 2\n", ["cannot read intrinsics file", "at line"]),
    ("- 1\n- 2\n", ["not a mapping"]),
])
def test_bad_intrinsics(scene, text, needles):
    (scene / "intrinsics.yaml").write_text(text)
    with pytest.raises(DataError) as e:
        FolderDataset(FolderConfig(path=str(scene)))
    one_line(e, "intrinsics.yaml", *needles)


def test_depth_scale_override_fills_a_missing_key(scene):
    (scene / "intrinsics.yaml").write_text(INTRINSICS.replace("depth_scale: 5000\n", ""))
    assert FolderDataset(FolderConfig(path=str(scene), depth_scale=5000.0)).depth_scale == 5000.0


def test_unmatched_images_are_listed(scene):
    extra = sorted((scene / "depth").iterdir())[:4]
    for p in extra:
        p.unlink()
    shutil.copy(sorted((scene / "color").iterdir())[-1], scene / "depth" / "orphan.png")
    with pytest.raises(DataError) as e:
        FolderDataset(FolderConfig(path=str(scene)))
    msg = one_line(e, "4 colour images", extra[0].stem, "...", "1 depth images", "orphan")
    assert extra[3].stem not in msg  # a few are listed, not all


@pytest.mark.parametrize("setup, needles", [
    (lambda s: shutil.rmtree(s / "color"), ["colour folder", "color not found"]),
    (lambda s: [p.unlink() for p in (s / "depth").iterdir()], ["no depth images"]),
    (lambda s: (s / "trajectory.txt").write_text("1 2 3\n"), ["trajectory.txt", "3 fields"]),
    (lambda s: (s / "trajectory.txt").write_text("0 0 0 0 0 0 0 1\n"), ["trajectory.txt", "no pose within"]),
    (lambda s: (s / "trajectory.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n"), ["1 poses for 10 frames"]),
    (lambda s: (s / "timestamps.txt").write_text("1\n2\n"), ["timestamps.txt", "2 timestamps for 10 frames"]),
])
def test_bad_folder_contents(scene, setup, needles):
    setup(scene)
    with pytest.raises(DataError) as e:
        FolderDataset(FolderConfig(path=str(scene)))
    one_line(e, *needles)


def test_given_trajectory_must_exist_and_config_is_checked(scene):
    with pytest.raises(DataError) as e:
        FolderDataset(FolderConfig(path=str(scene), trajectory="poses.txt"))
    one_line(e, "dataset.trajectory", "poses.txt not found")
    with pytest.raises(ConfigError, match="dataset.depth_scale"):
        FolderConfig(depth_scale=0.0)


def test_written_tum_trajectory_at_frame_timestamps_round_trips(scene, tum_frames):
    ts = np.array([tum_frames[i].timestamp for i in range(FRAMES)])
    gt = np.array([tum_frames[i].gt_pose for i in range(FRAMES)])
    write_tum_trajectory(scene / "trajectory.txt", ts, gt)
    ds = FolderDataset(FolderConfig(path=str(scene)))
    np.testing.assert_allclose(ds[FRAMES - 1].gt_pose, gt[-1], atol=1e-6)
