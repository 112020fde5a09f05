"""`slamkit dataset=folder` on a user's own RGB-D folder (built from the first frames of the
shared TUM sequence): a run, and a missing intrinsics file as one line. The dataset itself:
tests/plugins/test_folder_dataset.py."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from slamkit.errors import DataError
from slamkit.formats.tum import read_tum_trajectory
from slamkit_plugins.datasets.folder import FolderConfig, FolderDataset
from slamkit_plugins.datasets.tum import TUMConfig, TUMDataset

from support.commands import run_slamkit
from support.data import TUM, require_data
from support.errors import one_line
from support.folders import FOLDER_FRAMES as FRAMES
from support.folders import make_folder


@pytest.fixture
def scene(tmp_path) -> Path:
    return make_folder(tmp_path / "scene", TUMDataset(TUMConfig(path=str(require_data(TUM)), max_frames=FRAMES)))



@pytest.mark.slow
def test_slamkit_runs_on_a_folder(scene, tmp_path):
    out = tmp_path / "run"
    proc = run_slamkit("dataset=folder", f"dataset.path={scene}", "dataset.trajectory=gt.txt", "mapper=none",
                       "output.progress=false", f"hydra.run.dir={out}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    timestamps, poses = read_tum_trajectory(out / "trajectory.txt")
    assert len(timestamps) == FRAMES and np.isfinite(poses).all()
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["ate_rmse_m"] is not None and metrics["ate_rmse_m"] < 0.1


@pytest.mark.slow
def test_missing_intrinsics_is_one_line_naming_the_file(scene, tmp_path):
    (scene / "intrinsics.yaml").unlink()
    with pytest.raises(DataError) as e:
        FolderDataset(FolderConfig(path=str(scene)))
    one_line(e, str(scene / "intrinsics.yaml"), "not found")
    proc = run_slamkit("dataset=folder", f"dataset.path={scene}", f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "intrinsics.yaml not found" in proc.stderr.strip().splitlines()[-1]
