"""The viewer role: the built-in viewers' registration and config, the map as rerun logs it, and
the mapper's render for viewers. Through the command (`viewer=rerun` recording a real run to
.rrd, a broken viewer never stopping a run): tests/e2e/test_viewer_runs.py."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from slamkit.config import RunContext
from slamkit.errors import ConfigError
from slamkit.map.gaussian_map import GaussianMap, GaussianRows
from slamkit.registry.discovery import discover
from slamkit.roles import Mapper, PluginConfig, Viewer, ViewerConfig, ViewerFrame
from slamkit.types import Camera, Frame, KeyframeKind

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
    gm.append(GaussianRows.from_shapes(means, quats, np.full((n, 3), 0.05), rng.uniform(0, 1, (n, 3)), 0.8,
                                       np.ones(n, bool), 0))
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
    from support.mapping_scenes import make_mapper

    gm = _small_map(50)
    assert _view(gm, _no_mapper(gm)).render() is None

    mapper = make_mapper(gm, rasterizer="torch")
    pose = np.eye(4)
    pose[:3, 3] = [0.05, -0.02, 0.1]
    view = _view(gm, mapper)
    view.pose = pose
    out = view.render(scale=0.5)
    w2c = torch.as_tensor(np.linalg.inv(pose), dtype=torch.float32)
    reference = mapper.render(w2c, CAMERA.scaled(0.5))
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
