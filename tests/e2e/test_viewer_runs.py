"""The viewer role through the command: `viewer=rerun` recording a real run to .rrd, the default
`viewer=none`, and a broken viewer never stopping a run. The viewers themselves:
tests/plugins/test_viewer.py."""

from __future__ import annotations

import json

import pytest
import yaml

from support.commands import run_slamkit
from support.plugins import make_plugin_dist
from support.rerun_rows import rrd_rows


@pytest.mark.slow
def test_rerun_records_a_tum_run_to_rrd(tmp_path, tum_path):
    """viewer=rerun viewer.save=x.rrd on 8 real frames with 3DGS mapping, no display."""
    pytest.importorskip("rerun", reason="rerun-sdk is the optional extra `viewer`")
    rrd = tmp_path / "rec" / "x.rrd"
    out = tmp_path / "run"
    proc = run_slamkit(
        "dataset=tum", f"dataset.path={tum_path}", "dataset.max_frames=8", "mapper=gaussian_splatting",
        "iterations_per_frame=1", "final_iterations=0", "mapper.eval_every=100", "mapper.save_images=0",
        "viewer=rerun", f"viewer.save={rrd}", "viewer.render_every=4", "viewer.map_every=4", "output.progress=false",
        f"hydra.run.dir={out}", cwd=tmp_path, env_extra={"OMP_NUM_THREADS": "1"}, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert rrd.is_file() and rrd.stat().st_size > 10_000
    assert not (out / "recording.rrd").exists()
    rows, map_sizes = rrd_rows(rrd)
    assert rows["/world/camera/image (static)"] == 1  # the pinhole
    for entity in ("/world/camera", "/world/camera/image/rgb", "/world/camera/image/depth"):
        assert rows[entity] == 8, entity
    assert rows["/world/trajectory/estimate"] == rows["/world/trajectory/ground_truth"] == 7  # from frame 1 on
    assert rows["/render/rgb"] == rows["/render/depth"] == 2  # frames 0 and 4
    metrics = json.loads((out / "metrics.json").read_text())
    assert rows["/world/keyframes"] == metrics["num_keyframes"] >= 1
    assert sorted(map_sizes) == [0, 4, 7]  # every 4th frame, and the final map after the last
    assert map_sizes[7] == metrics["num_gaussians"] > map_sizes[0] > 0


@pytest.mark.slow
def test_default_viewer_is_none_and_rerun_defaults_to_the_run_folder(tmp_path):
    pytest.importorskip("rerun", reason="rerun-sdk is the optional extra `viewer`")
    common = ["dataset=synthetic", "dataset.num_frames=4", "dataset.width=64", "dataset.height=48", "mapper=none",
              "output.progress=false", "output.plot=false"]
    proc = run_slamkit(*common, f"hydra.run.dir={tmp_path}/plain", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    hydra_cfg = yaml.safe_load((tmp_path / "plain/.hydra/hydra.yaml").read_text())
    assert hydra_cfg["hydra"]["runtime"]["choices"]["viewer"] == "none"
    assert not list((tmp_path / "plain").rglob("*.rrd"))
    proc = run_slamkit(*common, "viewer=rerun", f"hydra.run.dir={tmp_path}/rec", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows, _ = rrd_rows(tmp_path / "rec" / "recording.rrd")
    assert rows["/world/camera"] == 4 and "/render/rgb" not in rows  # mapper=none cannot render


BROKEN_VIEWER = """
from dataclasses import dataclass
from pathlib import Path
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import PluginConfig, Viewer

@dataclass
class BrokenConfig(PluginConfig):
    fail_at: int = 2

class BrokenViewer(Viewer):
    def __init__(self, cfg, context=None):
        self.cfg, self.shown = cfg, []

    def start(self, camera, out_dir):
        self.out_dir = out_dir

    def show(self, view):
        if view.frame.index == self.cfg.fail_at:
            raise RuntimeError("boom")
        self.shown.append(view.frame.index)

    def close(self, view):
        (self.out_dir / "shown.txt").write_text(",".join(map(str, self.shown)))

@hookimpl
def slamkit_plugins():
    return [PluginSpec("broken", BrokenViewer, BrokenConfig)]
"""


@pytest.mark.slow
def test_a_failing_viewer_warns_and_the_run_goes_on(tmp_path):
    site = make_plugin_dist(tmp_path / "site", "slamkit-broken-viewer", {"broken_viewer": BROKEN_VIEWER},
                            {"broken": "broken_viewer"})
    out = tmp_path / "run"
    proc = run_slamkit("dataset=synthetic", "dataset.num_frames=5", "dataset.width=64", "dataset.height=48",
                       "mapper=none", "viewer=broken", "output.progress=false", "output.plot=false",
                       f"hydra.run.dir={out}", cwd=tmp_path, env_extra={"PYTHONPATH": str(site)})
    assert proc.returncode == 0, proc.stderr[-2000:]
    said = proc.stdout + proc.stderr
    assert "viewer 'broken' failed in show(): RuntimeError: boom; it is switched off, the run goes on" in said
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["completed"] and metrics["num_frames"] == 5
    assert (out / "shown.txt").read_text() == "0,1"  # no frame after the failure; close still called
