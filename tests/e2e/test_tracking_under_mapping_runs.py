"""G-ICP tracking while the 3DGS mapper trains in real time, through the command (TUM fr1/rpy):
the trajectory written is the tracking-only run's. In process: tests/plugins/test_tracking_under_mapping.py."""

from __future__ import annotations

import json

import pytest

from support.commands import run_slamkit
from support.data import TUM, require_data


@pytest.mark.slow
def test_realtime_mapping_run_tracks_as_tracking_only_through_the_cli(tmp_path):
    """`mode=realtime fps_limit=30`: the mapping thread trains while frames are tracked; the
    trajectory written is the tracking-only run's, whatever the machine let mapping do."""
    # one scale alignment for both (real time defaults to none, sequential to z_pow): the tracking
    # target is scale-free, but dividing by another median rounds differently (1e-9)
    common = ["dataset=tum", f"dataset.path={require_data(TUM)}", "dataset.max_frames=30", "tracker=gicp",
              "growth.scale_alignment=z_pow", "progress=false", "eval.plot=false"]
    runs = {"none": ["mapper=none"],
            # `low` priority: at `idle` (the default) a busy test machine may leave mapping no CPU
            "realtime": ["mapper=gaussian_splatting", "mode=realtime", "mapping_priority=low", "fps_limit=30",
                         "mapper.resolution_scale=0.25",
                         "mapper.eval_every=100", "mapper.save_images=0"]}
    for name, args in runs.items():
        proc = run_slamkit(*common, *args, f"hydra.run.dir={tmp_path / name}", cwd=tmp_path, timeout=300)
        assert proc.returncode == 0, proc.stderr[-2000:]
    metrics = json.loads((tmp_path / "realtime" / "metrics.json").read_text())
    assert metrics["mapping_iterations"] > 0
    lines = [(tmp_path / name / "trajectory.txt").read_text() for name in runs]
    assert lines[0] == lines[1]
