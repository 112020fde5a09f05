"""`viewer=viser`: a headless server that serves the page and sends the map as splats to a
browser client (a websocket client decoding viser's wire format stands in for the browser),
refreshed by keyframes, never waited on by tracking. Runs with it: tests/e2e/test_viser_viewer_runs.py."""

from __future__ import annotations

import asyncio
import json
import time
import urllib.request

import numpy as np
import pytest

from slamkit.config import RunContext
from slamkit.errors import ConfigError
from slamkit.map.gaussian_map import GaussianMap, GaussianRows
from slamkit.registry.discovery import discover
from slamkit.roles import Viewer, ViewerFrame
from slamkit.types import Camera, Frame, KeyframeKind

viser = pytest.importorskip("viser", reason="viser is the optional extra `web` (in `test`)")

from slamkit_plugins.mappers.none import NoMapper, NoMapperConfig  # noqa: E402
from slamkit_plugins.viewers.viser_viewer import ViserViewer, ViserViewerConfig  # noqa: E402

CAMERA = Camera(width=32, height=24, fx=30.0, fy=30.0, cx=15.5, cy=11.5)


class SlowRenderMapper(NoMapper):
    """A mapper whose render takes `seconds`: the viewer's work must not hold up tracking."""

    def __init__(self, seconds: float, gaussian_map: GaussianMap):
        super().__init__(NoMapperConfig(), RunContext(gaussian_map=gaussian_map))
        self.seconds = seconds

    def render_view(self, pose, camera):
        time.sleep(self.seconds)
        return None


def _add_gaussians(gm: GaussianMap, n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    means = np.column_stack([rng.uniform(-0.3, 0.3, (n, 2)), rng.uniform(1.5, 2.5, n)])
    quats = rng.normal(size=(n, 4))
    gm.append(GaussianRows.from_shapes(means, quats / np.linalg.norm(quats, axis=1, keepdims=True),
                                       np.full((n, 3), 0.03), rng.uniform(0, 1, (n, 3)), 0.7, np.ones(n, bool), seed))


def _view(i: int, gm: GaussianMap, mapper, keyframe: bool) -> ViewerFrame:
    pose = np.eye(4)
    pose[:3, 3] = [0.01 * i, 0.0, 0.0]
    frame = Frame(index=i, timestamp=i / 30, rgb=np.full((24, 32, 3), 40 * (i % 6), np.uint8),
                  depth=np.ones((24, 32), np.float32), camera=CAMERA)
    centres = np.array([[0.01 * k, 0.0, 0.0] for k in range(i + 1)])
    return ViewerFrame(frame, pose, KeyframeKind.TRACKING if keyframe else KeyframeKind.NONE, False, centres,
                       np.zeros((0, 3)), gm, mapper)


def _wait(condition, timeout: float = 10.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.02)
    return condition()


def _client_messages(url: str) -> list[tuple[str, dict, list[int]]]:
    """What a browser connecting now receives: (message type, message, binary buffer sizes) of
    each message of viser's replayed scene (zstd-compressed msgpack + raw buffers per frame)."""
    import msgspec
    import websockets
    import zstandard

    async def receive():
        got = []
        async with websockets.connect(url.replace("http", "ws"), subprotocols=[f"viser-v{viser.__version__}"],
                                      max_size=None) as ws:
            while not any(t == "ReplayDoneMessage" for t, _, _ in got):
                data = await asyncio.wait_for(ws.recv(), 10)
                size, packed = int.from_bytes(data[:8], "little"), int.from_bytes(data[8:16], "little")
                inner = msgspec.msgpack.decode(zstandard.ZstdDecompressor().decompress(data[16:16 + packed],
                                                                                       max_output_size=size))
                got += [(m["type"], m, list(inner["binaryBufferLengths"])) for m in inner["messages"]]
        return got

    return asyncio.run(receive())


def test_viser_is_a_registered_viewer_and_its_config_is_checked():
    spec = discover().get("viewer", "viser")
    assert issubclass(spec.cls, Viewer) and spec.config is ViserViewerConfig
    with pytest.raises(ConfigError, match=r"viewer.port: expected a TCP port in \[0, 65535\]"):
        ViserViewerConfig(port=70000)
    with pytest.raises(ConfigError, match=r"viewer.splat_seconds"):
        ViserViewerConfig(splat_seconds=-1)


def test_headless_server_serves_the_page_and_splats_after_keyframes(tmp_path):
    gm = GaussianMap()
    mapper = SlowRenderMapper(0.0, gm)
    viewer = ViserViewer(ViserViewerConfig(port=0, splat_keyframes=2, splat_seconds=0, render_every=1))
    viewer.start(CAMERA, tmp_path)
    try:
        page = urllib.request.urlopen(viewer.url, timeout=10).read().decode()
        assert page.lstrip().lower().startswith("<!doctype html>") and "<script" in page
        _add_gaussians(gm, 40, seed=1)
        viewer.show(_view(0, gm, mapper, keyframe=True))
        assert _wait(lambda: viewer.costs["pose"].count == 1)
        assert viewer.splats_sent == 0  # one keyframe: not yet due (splat_keyframes=2)
        _add_gaussians(gm, 60, seed=2)
        viewer.show(_view(1, gm, mapper, keyframe=True))
        assert _wait(lambda: viewer.splats_sent == 100)
        messages = _client_messages(viewer.url)
        splats = [(m, sizes) for t, m, sizes in messages if t == "GaussianSplatsMessage"]
        assert len(splats) == 1 and splats[0][0]["name"] == "/map"
        buffer = splats[0][1][splats[0][0]["props"]["buffer"]["__binary_index"]]
        assert buffer > 0 and buffer % 100 == 0  # one fixed-size record per Gaussian
        assert {"CameraFrustumMessage", "LineSegmentsMessage", "GuiImageMessage"} <= {t for t, _, _ in messages}
    finally:
        viewer.close(_view(1, gm, mapper, keyframe=False))
    stats = json.loads((tmp_path / "viser.json").read_text())
    assert stats["url"] == viewer.url and stats["splats_sent"] == 100
    assert stats["updates"]["splats"]["count"] >= 1 and stats["updates"]["pose"]["mean_ms"] > 0
    with pytest.raises(OSError):  # the server is gone after close (keep_serving=false)
        urllib.request.urlopen(viewer.url, timeout=2)


def test_show_never_waits_for_the_viewers_work(tmp_path):
    """Renders of 1 s each: 30 frames are handed over in less than half a render (waiting for
    even one would take a whole one; the margin is for a loaded machine), the worker skips
    frames it has no time for, and close() still sends the final map."""
    gm = GaussianMap()
    _add_gaussians(gm, 20, seed=3)
    mapper = SlowRenderMapper(1.0, gm)
    viewer = ViserViewer(ViserViewerConfig(port=0, render_every=1, splat_keyframes=1, splat_seconds=0))
    viewer.start(CAMERA, tmp_path)
    start = time.perf_counter()
    for i in range(30):
        viewer.show(_view(i, gm, mapper, keyframe=i % 3 == 0))
    handed_over = time.perf_counter() - start
    viewer.close(_view(29, gm, mapper, keyframe=False))
    assert handed_over < 0.5, handed_over
    assert 1 <= viewer.costs["render"].count < 30  # frames arriving during a render were skipped
    assert viewer.splats_sent == 20
