"""`viewer=viser`: the live map in a web browser (https://viser.studio), served from the run.

Needs the optional extra `web` (`pip install -e '.[web]'`, viser). Open the printed address
(`http://127.0.0.1:8080` by default; `viewer.port`, `viewer.host`) while the run goes on:

    /map                  the Gaussians as splats (centres, covariances, colours, opacities;
                          at most map_max_points, an even subsample), refreshed every
                          `splat_keyframes` keyframes or `splat_seconds` seconds, whichever
                          comes first, and once more after the last frame
    /camera               the current camera frustum (camera-to-world pose, metres)
    /trajectory/estimate  the camera centres so far (orange), /trajectory/ground_truth (green)
    /loops                the loop closure's accepted loops (blue): a line between each loop's
                          two keyframe camera centres
    GUI panel             the current input frame and the mapper's render from its pose, side by
                          side (every `image_every` / `render_every` frames, at render_scale)

Tracking is never waited on: `show` (called in the tracking thread) only hands the latest
frame to a worker thread and returns; the worker sends what is due, with bounded work per
update (one map copy of at most map_max_points Gaussians, one render at render_scale, two
small images). Frames that arrive while the worker is busy are skipped by it, not queued.
After the last frame the final map is sent and the run exits, unless `keep_serving=true`
keeps the page up until Ctrl-C or SIGTERM. `RUN_DIR/viser.json` records the address and the cost of
each kind of update (count, mean and max milliseconds in the worker thread).
"""

from __future__ import annotations

import json
import logging
import math
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slamkit.errors import ConfigError
from slamkit.formats.atomic import write_atomic
from slamkit.geometry.transforms import rotmat_to_quat
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import RunContext, Viewer, ViewerConfig, ViewerFrame, require
from slamkit.types import Camera

log = logging.getLogger(__name__)

#: The cost record written into the run folder.
STATS_FILE = "viser.json"
ESTIMATE_COLOUR, GROUND_TRUTH_COLOUR, LOOP_COLOUR = (230, 90, 30), (40, 160, 60), (60, 120, 250)


@dataclass
class ViserViewerConfig(ViewerConfig):
    """The browser viewer (see the module docstring)."""

    #: address to serve on (127.0.0.1: this machine only; 0.0.0.0: every interface)
    host: str = "127.0.0.1"
    #: TCP port (0: any free port; a port in use is replaced by the next free one)
    port: int = 8080
    #: refresh the splats after this many new keyframes (0: not by keyframes)
    splat_keyframes: int = 5
    #: refresh the splats when this many seconds have passed and the map changed (0: not by time)
    splat_seconds: float = 2.0
    #: frames between updates of the input image in the panel (0: never)
    image_every: int = 5
    #: pixels; the width the panel's images are resized to
    image_width: int = 320
    #: metres; the depth of the drawn camera frustum
    frustum_scale: float = 0.15
    #: after the last frame, keep serving the page until Ctrl-C or SIGTERM
    keep_serving: bool = False
    #: frames between renders of the map from the current pose (0: never)
    render_every: int = 10
    #: frames between splat refreshes besides the ones above (0: none)
    map_every: int = 0
    #: at most this many Gaussians sent as splats (an even subsample of the map)
    map_max_points: int = 100_000

    def validate(self) -> None:
        super().validate()
        require(0 <= self.port <= 65535, "viewer.port", "a TCP port in [0, 65535] (0 = any free port)", self.port)
        require(self.splat_keyframes >= 0, "viewer.splat_keyframes", "an integer >= 0", self.splat_keyframes)
        require(self.splat_seconds >= 0, "viewer.splat_seconds", ">= 0 seconds", self.splat_seconds)
        require(self.image_every >= 0, "viewer.image_every", "an integer >= 0 (0 = never)", self.image_every)
        require(self.image_width >= 16, "viewer.image_width", "an integer >= 16 pixels", self.image_width)
        require(self.frustum_scale > 0, "viewer.frustum_scale", "> 0 metres", self.frustum_scale)
        require(self.host.strip() != "", "viewer.host", "an address to serve on, e.g. 127.0.0.1", self.host)


def _import_viser():
    try:
        import viser
    except ImportError as exc:
        raise ConfigError(f"viewer=viser needs viser ({exc}); install it with pip install -e '.[web]'") from None
    return viser


class UpdateCost:
    """Count, total and largest duration (seconds) of one kind of update."""

    def __init__(self):
        self.count, self.total, self.largest = 0, 0.0, 0.0

    def add(self, seconds: float) -> None:
        self.count += 1
        self.total += seconds
        self.largest = max(self.largest, seconds)

    def summary(self) -> dict:
        mean = self.total / self.count if self.count else None
        return {"count": self.count, "mean_ms": None if mean is None else 1e3 * mean, "max_ms": 1e3 * self.largest}


class ViserViewer(Viewer):
    """Serves the run to a browser; the work happens in a worker thread (module docstring)."""

    def __init__(self, cfg: ViserViewerConfig, context: RunContext = RunContext()):
        self.cfg = cfg
        self.viser = _import_viser()
        self.server = None
        self.url: str | None = None
        self.out_dir: Path | None = None
        self.splats_sent = 0  # Gaussians in the last splat update
        self.costs = {k: UpdateCost() for k in ("splats", "pose", "image", "render")}
        self._latest: ViewerFrame | None = None
        self._new_keyframes = 0
        self._final = False
        self._wake = threading.Condition()
        self._worker: threading.Thread | None = None
        self._sent_frame = -1
        self._splat_frame = -1
        self._splat_time = 0.0
        self._splat_version = -1
        self._pending_keyframes = 0

    # -- the Viewer role -------------------------------------------------------------------
    def start(self, camera: Camera, out_dir: Path) -> None:
        cfg = self.cfg
        self.out_dir = out_dir
        self.server = self.viser.ViserServer(host=cfg.host, port=cfg.port, label="slamkit", verbose=False)
        self.url = f"http://{cfg.host}:{self.server.get_port()}"
        gui = self.server.gui
        blank = np.zeros((max(1, round(cfg.image_width * camera.height / camera.width)), cfg.image_width, 3), np.uint8)
        self._status = gui.add_markdown("starting")
        self._input_image = gui.add_image(blank, label="input frame", format="jpeg")
        self._render_image = gui.add_image(blank, label="render from the estimated pose", format="jpeg")
        self._camera = camera
        self._worker = threading.Thread(target=self._work, name="slamkit-viser", daemon=True)
        self._worker.start()
        log.info("viser viewer: serving %s", self.url)
        print(f"slamkit: the live map is at {self.url} (viewer=viser)", flush=True)

    def show(self, view: ViewerFrame) -> None:
        with self._wake:
            self._latest = view
            self._new_keyframes += bool(view.keyframe)
            self._wake.notify()

    def close(self, view: ViewerFrame | None) -> None:
        if self._worker is None:
            return
        with self._wake:
            if view is not None:
                self._latest = view
            self._final = True
            self._wake.notify()
        self._worker.join()
        self._worker = None
        self._write_stats()
        if self.cfg.keep_serving:
            log.info("viser viewer: the run is done; still serving %s", self.url)
            print(f"slamkit: the map is served at {self.url}; Ctrl-C (or SIGTERM) to stop", flush=True)
            _wait_for_interrupt()
        self.server.stop()

    # -- the worker thread -----------------------------------------------------------------
    def _work(self) -> None:
        while True:
            with self._wake:
                while not self._final and (self._latest is None or self._latest.frame.index == self._sent_frame):
                    self._wake.wait(timeout=self.cfg.splat_seconds or None)
                    if self._due_by_time():
                        break
                view, final = self._latest, self._final
                keyframes, self._new_keyframes = self._new_keyframes, 0
            if view is None:
                return
            try:
                self._update(view, keyframes, final)
            except Exception as exc:  # a viewer never stops a run: say it once and stop updating
                log.warning("viewer 'viser' failed in its update thread: %s: %s; the page stops updating",
                            type(exc).__name__, str(exc).splitlines()[0] if str(exc) else "")
                return
            if final:
                return

    def _due_by_time(self) -> bool:
        view = self._latest
        return bool(view is not None and self.cfg.splat_seconds and
                    time.perf_counter() - self._splat_time >= self.cfg.splat_seconds and
                    view.gaussian_map.version != self._splat_version)

    def _update(self, view: ViewerFrame, new_keyframes: int, final: bool) -> None:
        cfg, i = self.cfg, view.frame.index
        self._timed("pose", self._send_pose, view)
        if cfg.image_every and (i % cfg.image_every == 0 or final):
            self._timed("image", self._send_image, view)
        if cfg.render_every and (i % cfg.render_every == 0 or final):
            self._timed("render", self._send_render, view)
        self._pending_keyframes += new_keyframes
        if final or self._splats_due(view):
            self._timed("splats", self._send_splats, view)
        self._sent_frame = i
        self._status.content = (f"frame **{i}**, {len(view.trajectory)} poses, "
                                f"{self.splats_sent} of {len(view.gaussian_map)} Gaussians shown"
                                + (" (final)" if final else ""))

    def _splats_due(self, view: ViewerFrame) -> bool:
        cfg, i = self.cfg, view.frame.index
        if view.gaussian_map.version == self._splat_version:
            return False
        by_keyframes = cfg.splat_keyframes and self._pending_keyframes >= cfg.splat_keyframes
        by_frames = cfg.map_every and i - self._splat_frame >= cfg.map_every
        by_time = cfg.splat_seconds and time.perf_counter() - self._splat_time >= cfg.splat_seconds
        return bool(by_keyframes or by_frames or by_time)

    def _timed(self, kind: str, send, view: ViewerFrame) -> None:
        start = time.perf_counter()
        send(view)
        self.costs[kind].add(time.perf_counter() - start)

    # -- what is sent ------------------------------------------------------------------------
    def _send_pose(self, view: ViewerFrame) -> None:
        scene, cam = self.server.scene, self._camera
        if self._sent_frame < 0:  # the first frame: look at it from behind, its up as the scene's up
            up = -view.pose[:3, 1]
            scene.set_up_direction(tuple(float(v) for v in up))
            forward, centre = view.pose[:3, 2], view.pose[:3, 3]
            self.server.initial_camera.position = centre - 1.0 * forward + 0.5 * up
            self.server.initial_camera.look_at = centre + forward
            self.server.initial_camera.up = up
        scene.add_camera_frustum("/camera", fov=2 * math.atan(cam.height / (2 * cam.fy)), aspect=cam.width / cam.height,
                                 scale=self.cfg.frustum_scale, color=ESTIMATE_COLOUR,
                                 wxyz=rotmat_to_quat(view.pose[:3, :3]), position=view.pose[:3, 3])
        for name, centres, colour in (("estimate", view.trajectory, ESTIMATE_COLOUR),
                                      ("ground_truth", view.gt_trajectory, GROUND_TRUTH_COLOUR)):
            if len(centres) >= 2:
                segments = np.stack([centres[:-1], centres[1:]], axis=1).astype(np.float32)
                scene.add_line_segments(f"/trajectory/{name}", segments, colour, thickness=2.0,
                                        thickness_units="screen")
        if len(view.loops):
            scene.add_line_segments("/loops", view.loops.astype(np.float32), LOOP_COLOUR, thickness=3.0,
                                    thickness_units="screen")

    def _panel_image(self, rgb: np.ndarray) -> np.ndarray:
        """rgb (H,W,3) uint8 or float in [0,1], resized to image_width (nearest, numpy only)."""
        rgb = np.asarray(rgb)
        if rgb.dtype != np.uint8:
            rgb = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
        h, w = rgb.shape[:2]
        width = min(self.cfg.image_width, w)
        height = max(1, round(h * width / w))
        rows = (np.arange(height) * h / height).astype(int)
        cols = (np.arange(width) * w / width).astype(int)
        return rgb[rows][:, cols]

    def _send_image(self, view: ViewerFrame) -> None:
        self._input_image.image = self._panel_image(view.frame.rgb)

    def _send_render(self, view: ViewerFrame) -> None:
        out = view.render(self.cfg.render_scale)
        if out is not None:
            self._render_image.image = self._panel_image(out.color.clamp(0, 1).cpu().numpy())

    def _send_splats(self, view: ViewerFrame) -> None:
        g = view.map_gaussians(self.cfg.map_max_points)
        self._splat_version = view.gaussian_map.version
        self._splat_frame, self._splat_time, self._pending_keyframes = view.frame.index, time.perf_counter(), 0
        if len(g) == 0:
            return
        self.server.scene.add_gaussian_splats("/map", centers=g.means, covariances=g.covariances(), rgbs=g.colors,
                                              opacities=g.opacities[:, None])
        self.splats_sent = len(g)

    def _write_stats(self) -> None:
        if self.out_dir is None:
            return
        stats = {"url": self.url, "splats_sent": self.splats_sent,
                 "updates": {k: c.summary() for k, c in self.costs.items()}}
        write_atomic(self.out_dir / STATS_FILE, json.dumps(stats, indent=1) + "\n")


def _wait_for_interrupt() -> None:
    """Block until Ctrl-C or SIGTERM (the latter caught only from the main thread)."""
    stop = threading.Event()
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, lambda signum, frame: stop.set())
    try:
        while not stop.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


@hookimpl
def slamkit_plugins():
    return [PluginSpec("viser", ViserViewer, ViserViewerConfig)]
