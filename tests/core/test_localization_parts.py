"""`mode=localize`'s parts, in this process: global registration of a real frame from an
unknown pose, the map a localisation needs, and the fit of a map to a frame that tells a right
pose from a shifted one. Localising real sequences in a saved map: tests/e2e/test_localization.py."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slamkit.geometry.registration import GlobalRegistration
from slamkit.geometry.transforms import backproject, make_pose, so3_exp, transform_points
from slamkit.registry.compose import compose_run
from slamkit.registry.discovery import default_registry

pytest.importorskip("open3d")


def _frame(path: Path, index: int):
    cfg, names = compose_run(["dataset=tum", f"dataset.path={path}"])
    return default_registry().create("dataset", names["dataset"], cfg.dataset)[index]


def test_global_registration_finds_a_real_frame_moved_far_from_its_place(tum_path):
    frame = _frame(tum_path, 0)
    points, _ = backproject(frame.depth, frame.camera, 2)
    truth = make_pose(so3_exp(np.array([0.3, -1.2, 0.5])), np.array([1.5, -0.7, 2.0]))  # camera-to-"map"
    registration = GlobalRegistration(transform_points(truth, points), voxel=0.05)
    found = registration.register(points, seed=0)
    assert np.linalg.norm(found.pose[:3, 3] - truth[:3, 3]) < 0.02
    assert np.linalg.norm(found.pose[:3, :3] - truth[:3, :3]) < 0.03
    assert found.fitness > 0.9


def test_localize_needs_a_map(tmp_path):
    from slamkit.errors import ConfigError
    from slamkit.formats.checkpoint import CheckpointError
    from slamkit.run.checkpoint import load_map

    with pytest.raises(ConfigError, match="map: expected a run folder or checkpoint file with mode=localize"):
        compose_run(["mode=localize"])
    cfg, _ = compose_run(["mode=localize", "map=out/run", "growth.scale_c=3"])
    assert cfg.map == "out/run" and cfg.growth.scale_c == 3  # `map` names the saved map, `growth.` the map's growth
    with pytest.raises(CheckpointError, match=f"checkpoint {tmp_path / 'nothing'} not found"):
        load_map(tmp_path / "nothing")


def test_map_fit_tells_the_right_pose_from_a_shifted_one_by_shape_and_by_colour():
    """A textured wall 2 m ahead, as a map (a centre per pixel, with the pixel's colour) and as
    a frame: from the frame's own pose the map lies on its surface with its colours; 0.5 m
    closer it lies in front of it; 0.1 m to the side (the same wall, so the same depth) its
    colours no longer line up."""
    from slamkit.geometry.transforms import backproject, make_pose
    from slamkit.run.localization import map_fit
    from slamkit.types import Camera, Frame

    camera = Camera(64, 48, 50.0, 50.0, 31.5, 23.5)
    rng = np.random.default_rng(0)
    texture = rng.integers(0, 256, (48, 64, 3)).astype(np.uint8)
    depth = np.full((48, 64), 2.0, np.float32)
    frame = Frame(0, 0.0, texture, depth, camera, None)
    points, pixels = backproject(depth, camera)
    colors = texture.reshape(-1, 3)[pixels] / 255.0
    right = map_fit(frame, np.eye(4), points.astype(np.float64), colors)
    assert right.surface_agreement == 1.0 and right.color_correlation > 0.99
    closer = map_fit(frame, make_pose(np.eye(3), np.array([0.0, 0.0, 0.5])), points.astype(np.float64), colors)
    assert closer.surface_agreement == 0.0 and closer.color_correlation is None
    aside = map_fit(frame, make_pose(np.eye(3), np.array([0.1, 0.0, 0.0])), points.astype(np.float64), colors)
    assert aside.surface_agreement == 1.0 and abs(aside.color_correlation) < 0.3
