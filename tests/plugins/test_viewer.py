"""The viewer role: `viewer=none` (default), `viewer=rerun` recording a real run to .rrd, a broken
viewer never stopping a run, and the mapper's render for viewers."""

from __future__ import annotations

import json
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from slamkit.config import RunContext
from slamkit.errors import ConfigError
from slamkit.map.gaussian_map import GaussianMap, GaussianRows
from slamkit.registry.discovery import discover
from slamkit.roles import Mapper, PluginConfig, Viewer, ViewerConfig, ViewerFrame
from slamkit.types import Camera, Frame, KeyframeKind

from conftest import make_plugin_dist, run_slamkit

CAMERA = Camera(width=32, height=24, fx=30.0, fy=30.0, cx=15.5, cy=11.5)


def test_builtin_viewers_registered_through_entry_points():
    registry = discover()
    for name in ("none", "rerun"):
        spec = registry.get("viewer", name)
        assert issubclass(spec.cls, Viewer) and issubclass(spec.config, PluginConfig)
        assert registry.plugins["viewer"][name].source.endswith("(slamkit)")
    assert issubclass(registry.get("viewer", "rerun").config, ViewerConfig)


def test_viewer_config_ranges_fail_in_one_line():
    from slamkit_plugins.viewers.rerun_viewer import RerunViewerConfig

    with pytest.raises(ConfigError, match=r"viewer.render_every: expected an integer >= 0"):
        RerunViewerConfig(render_every=-1)
    with pytest.raises(ConfigError, match=r"viewer.jpeg_quality: expected in \[0, 100\]"):
        RerunViewerConfig(jpeg_quality=101)
    with pytest.raises(ConfigError, match=r"viewer.render_scale"):
        RerunViewerConfig(render_scale=0.0)
    with pytest.raises(ConfigError, match=r"viewer.map_as: expected splats or ellipsoids or points, got 'cubes'"):
        RerunViewerConfig(map_as="cubes")


def test_rerun_missing_is_a_one_line_config_error(monkeypatch):
    from slamkit_plugins.viewers.rerun_viewer import RerunViewer, RerunViewerConfig

    monkeypatch.setitem(sys.modules, "rerun", None)  # makes `import rerun` raise ImportError
    with pytest.raises(ConfigError, match=r"viewer=rerun needs rerun-sdk .*pip install -e '\.\[viewer\]'"):
        RerunViewer(RerunViewerConfig())


def _small_map(n: int) -> GaussianMap:
    gm = GaussianMap()
    rng = np.random.default_rng(0)
    means = np.column_stack([rng.uniform(-0.3, 0.3, (n, 2)), rng.uniform(1.5, 2.5, n)])
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    gm.append(GaussianRows.from_shapes(means, quats, np.full((n, 3), 0.05), rng.uniform(0, 1, (n, 3)), 0.8, np.ones(n, bool), 0))
    return gm


def _no_mapper(gm: GaussianMap) -> Mapper:
    from slamkit_plugins.mappers.none import NoMapper, NoMapperConfig

    return NoMapper(NoMapperConfig(), RunContext(gaussian_map=gm))


def _view(gm: GaussianMap, mapper: Mapper) -> ViewerFrame:
    frame = Frame(index=0, timestamp=0.0, rgb=np.zeros((24, 32, 3), np.uint8), depth=np.zeros((24, 32), np.float32),
                  camera=CAMERA)
    return ViewerFrame(frame, np.eye(4), KeyframeKind.TRACKING, False, np.zeros((1, 3)), np.zeros((0, 3)), gm, mapper)


def test_map_points_is_an_even_subsample_within_the_limit():
    gm = _small_map(10)
    points = _view(gm, _no_mapper(gm)).map_points(max_points=3)
    assert points.total == 10 and len(points.positions) == 3
    np.testing.assert_allclose(points.positions, gm.means.detach().numpy()[::4])
    assert points.colors.dtype == np.uint8
    np.testing.assert_allclose(points.colors, np.round(gm.colors.detach().numpy()[::4] * 255), atol=1)
    np.testing.assert_allclose(points.radii, 0.05, rtol=1e-5)


def test_render_view_is_none_by_default_and_the_3dgs_map_render_otherwise():
    from mapping_scenes import make_mapper

    gm = _small_map(50)
    assert _view(gm, _no_mapper(gm)).render() is None

    mapper = make_mapper(gm, rasterizer="torch")
    pose = np.eye(4)
    pose[:3, 3] = [0.05, -0.02, 0.1]
    view = _view(gm, mapper)
    view.pose = pose
    out = view.render(scale=0.5)
    w2c = torch.as_tensor(np.linalg.inv(pose), dtype=torch.float32)
    reference = mapper.trainer.render(w2c, CAMERA.scaled(0.5))
    assert out.color.shape == (12, 16, 3) and not out.color.requires_grad
    torch.testing.assert_close(out.color, reference.color.detach())
    torch.testing.assert_close(out.depth, reference.depth.detach())
    assert float(out.alpha.max()) > 0.5  # the Gaussians are in view


def _rrd_map(path: Path) -> dict[str, list]:
    """The columns of the last /world/map row of a recording, by their name."""
    from rerun.chunk import RrdReader

    columns = {}
    for chunk in RrdReader(str(path)).stream().to_chunks():
        if chunk.entity_path == "/world/map":
            batch = chunk.to_record_batch()
            columns = {name: batch.column(i).to_pylist()[-1] for i, name in enumerate(batch.schema.names)}
    return columns


@pytest.mark.parametrize("style", ["splats", "ellipsoids", "points"])
def test_rerun_logs_the_map_as_gaussian_splats(tmp_path, style):
    """viewer.map_as: splats (default) carry each Gaussian's centre, scales, rotation and colour
    with opacity; ellipsoids the same shapes; points the centres only."""
    pytest.importorskip("rerun", reason="rerun-sdk is the optional extra `viewer`")
    from slamkit.geometry.transforms import quat_to_rotmat
    from slamkit_plugins.viewers.rerun_viewer import RerunViewer, RerunViewerConfig

    rng = np.random.default_rng(1)
    n = 12
    quats = rng.normal(size=(n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    scales = rng.uniform(0.01, 0.1, (n, 3))
    colors, opacities = rng.uniform(0, 1, (n, 3)), rng.uniform(0.1, 0.9, n)
    gm = GaussianMap()
    gm.append(GaussianRows.from_shapes(rng.normal(size=(n, 3)), quats, scales, colors, opacities, np.ones(n, bool), 0))
    view = _view(gm, _no_mapper(gm))
    rrd = tmp_path / "map.rrd"
    viewer = RerunViewer(RerunViewerConfig(save=str(rrd), render_every=0, map_every=1, map_as=style))
    viewer.start(CAMERA, tmp_path)
    viewer.show(view)
    viewer.close(view)
    cols = _rrd_map(rrd)
    prefix = {"splats": "GaussianSplats3D", "ellipsoids": "Ellipsoids3D", "points": "Points3D"}[style]
    centres = np.array(cols[f"{prefix}:{'positions' if style == 'points' else 'centers'}"])
    np.testing.assert_allclose(centres, gm.means.detach().numpy(), atol=1e-6)
    if style == "points":
        return
    sizes = np.array(cols[f"{prefix}:{'scales' if style == 'splats' else 'half_sizes'}"])
    np.testing.assert_allclose(sizes, scales, rtol=1e-5)
    xyzw = np.array(cols[f"{prefix}:quaternions"])
    np.testing.assert_allclose(quat_to_rotmat(xyzw[:, [3, 0, 1, 2]]), quat_to_rotmat(quats), atol=1e-5)
    rgba = np.array(cols[f"{prefix}:colors"], dtype=np.uint32)
    channels = np.stack([(rgba >> s) & 0xFF for s in (24, 16, 8, 0)], axis=1)  # packed 0xRRGGBBAA
    np.testing.assert_allclose(channels / 255, np.column_stack([colors, opacities]), atol=1 / 255 + 1e-3)


def _rrd_rows(path: Path) -> tuple[Counter, dict[int, int]]:
    """Rows logged per entity (non-static), and the number of map points logged at each frame."""
    from rerun.chunk import RrdReader

    rows: Counter = Counter()
    map_sizes: dict[int, int] = {}
    for chunk in RrdReader(str(path)).stream().to_chunks():
        if chunk.is_static:
            rows[chunk.entity_path + " (static)"] += chunk.num_rows
            continue
        rows[chunk.entity_path] += chunk.num_rows
        if chunk.entity_path == "/world/map":
            batch = chunk.to_record_batch()
            frames = batch.column(batch.schema.names.index("frame")).to_pylist()
            positions = batch.column(batch.schema.names.index("GaussianSplats3D:centers")).to_pylist()
            map_sizes.update({f: len(p) for f, p in zip(frames, positions)})
    return rows, map_sizes


@pytest.mark.slow
def test_rerun_records_a_tum_run_to_rrd(tmp_path, tum_path):
    """viewer=rerun viewer.save=x.rrd on 8 real frames with 3DGS mapping, no display."""
    pytest.importorskip("rerun", reason="rerun-sdk is the optional extra `viewer`")
    rrd = tmp_path / "rec" / "x.rrd"
    out = tmp_path / "run"
    proc = run_slamkit(
        "dataset=tum", f"dataset.path={tum_path}", "dataset.max_frames=8", "mapper=gaussian_splatting",
        "iterations_per_frame=1", "final_iterations=0", "mapper.eval_every=100", "mapper.save_images=0",
        "viewer=rerun", f"viewer.save={rrd}", "viewer.render_every=4", "viewer.map_every=4", "progress=false",
        f"hydra.run.dir={out}", cwd=tmp_path, env_extra={"OMP_NUM_THREADS": "1"}, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert rrd.is_file() and rrd.stat().st_size > 10_000
    assert not (out / "recording.rrd").exists()
    rows, map_sizes = _rrd_rows(rrd)
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
              "progress=false", "eval.plot=false"]
    proc = run_slamkit(*common, f"hydra.run.dir={tmp_path}/plain", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    hydra_cfg = yaml.safe_load((tmp_path / "plain/.hydra/hydra.yaml").read_text())
    assert hydra_cfg["hydra"]["runtime"]["choices"]["viewer"] == "none"
    assert not list((tmp_path / "plain").rglob("*.rrd"))
    proc = run_slamkit(*common, "viewer=rerun", f"hydra.run.dir={tmp_path}/rec", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows, _ = _rrd_rows(tmp_path / "rec" / "recording.rrd")
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
                       "mapper=none", "viewer=broken", "progress=false", "eval.plot=false",
                       f"hydra.run.dir={out}", cwd=tmp_path, env_extra={"PYTHONPATH": str(site)})
    assert proc.returncode == 0, proc.stderr[-2000:]
    said = proc.stdout + proc.stderr
    assert "viewer 'broken' failed in show(): RuntimeError: boom; it is switched off, the run goes on" in said
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["completed"] and metrics["num_frames"] == 5
    assert (out / "shown.txt").read_text() == "0,1"  # no frame after the failure; close still called
