"""`viewer=rerun`: log the run to Rerun (https://rerun.io): record a .rrd file, or stream to a viewer.

Needs the optional extra `viewer` (`pip install -e '.[viewer]'`, rerun-sdk). Entities (timeline
`frame`, the frame index):

    world/camera                  Transform3D: the estimated pose (camera-to-world, metres)
    world/camera/image            Pinhole: the intrinsics, OpenCV axes (x right, y down, z forward)
    world/camera/image/rgb        Image: the input colour image (JPEG unless jpeg_quality=0)
    world/camera/image/depth      DepthImage: the input depth (uint16 millimetres)
    world/trajectory/estimate     LineStrips3D: camera centres so far (metres)
    world/trajectory/ground_truth LineStrips3D: the ground-truth centres so far, when the data has them
    world/keyframes               Points3D: the keyframes' camera centres (moved with the loop
                                  closure's corrections, as the estimate is)
    world/loops                   LineStrips3D: each loop the loop closure accepted, a line between
                                  its two keyframes' camera centres
    world/map                     GaussianSplats3D: the map's Gaussians (centres, scales as standard
                                  deviations in metres, rotations, colour with opacity as alpha;
                                  subsampled); map_as=ellipsoids: Ellipsoids3D of one standard
                                  deviation (also where a rerun-sdk lacks splats); map_as=points:
                                  Points3D of the centres
    render/rgb, render/depth      Image, DepthImage: the mapper's render from the estimated pose

Rendering and the map are logged every `render_every` / `map_every` frames (and the map once more
after the last frame), so their cost stays bounded. Writing a file needs no display: `viewer.save`
names it (null: RUN_DIR/recording.rrd, unless `spawn` or `connect` streams to a viewer instead).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slamkit.errors import ConfigError
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import MapGaussians, MapPoints, RunContext, Viewer, ViewerConfig, ViewerFrame, require
from slamkit.types import Camera

log = logging.getLogger(__name__)

#: The recording written into the run folder when neither save, spawn nor connect is given.
DEFAULT_RECORDING = "recording.rrd"
#: uint16 depth images hold millimetres (0 = invalid; at most 65.535 m).
DEPTH_UNITS_PER_METRE = 1000.0
#: viewer.map_as: how the map's Gaussians are logged
MAP_STYLES = ("splats", "ellipsoids", "points")


@dataclass
class RerunViewerConfig(ViewerConfig):
    """Rerun logging (see the module docstring for the entities)."""

    #: a .rrd file to record into, no display needed (null: RUN_DIR/recording.rrd unless spawn or connect)
    save: str | None = None
    #: start the Rerun viewer app and stream to it (needs a display)
    spawn: bool = False
    #: URL of a running Rerun viewer to stream to (e.g. rerun+http://127.0.0.1:9876/proxy; null: none)
    connect: str | None = None
    #: frames between logs of the input colour and depth images (0: never)
    image_every: int = 1
    #: log the input depth image
    log_depth: bool = True
    #: JPEG quality of the logged colour images, 1-100 (0: uncompressed)
    jpeg_quality: int = 90
    #: the recording's name in the viewer
    application_id: str = "slamkit"
    #: how the map is logged: splats (GaussianSplats3D), ellipsoids (one standard deviation) or points (centres)
    map_as: str = "splats"

    def validate(self) -> None:
        super().validate()
        require(self.image_every >= 0, "viewer.image_every", "an integer >= 0 (0 = never)", self.image_every)
        require(0 <= self.jpeg_quality <= 100, "viewer.jpeg_quality", "in [0, 100] (0 = uncompressed)",
                self.jpeg_quality)
        require(self.save is None or self.save.strip() != "", "viewer.save", "null or a file path", self.save)
        require(self.map_as in MAP_STYLES, "viewer.map_as", " or ".join(MAP_STYLES), self.map_as)


def _import_rerun():
    try:
        import rerun
    except ImportError as exc:
        raise ConfigError(f"viewer=rerun needs rerun-sdk ({exc}); install it with pip install -e '.[viewer]'") from None
    return rerun


class RerunViewer(Viewer):
    """Logs the camera, trajectory, images, renders and map to a Rerun recording stream."""

    def __init__(self, cfg: RerunViewerConfig, context: RunContext = RunContext()):
        self.cfg = cfg
        self.rr = _import_rerun()
        self.stream = None
        self.recording_path: Path | None = None
        self._last_map_frame: int | None = None
        self._loops_logged: np.ndarray | None = None

    # -- the Viewer role -------------------------------------------------------------------
    def start(self, camera: Camera, out_dir: Path) -> None:
        rr, cfg = self.rr, self.cfg
        self.stream = rr.RecordingStream(cfg.application_id)
        sinks = []
        live = cfg.spawn or cfg.connect
        save = cfg.save if cfg.save is not None else (None if live else str(out_dir / DEFAULT_RECORDING))
        if save is not None:
            self.recording_path = Path(save)
            self.recording_path.parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(self.recording_path)))
        if cfg.spawn:
            self.stream.spawn(connect=False)
            sinks.append(rr.GrpcSink())
        if cfg.connect:
            sinks.append(rr.GrpcSink(cfg.connect))
        self.stream.set_sinks(*sinks)
        self.stream.log("world/camera/image", rr.Pinhole(image_from_camera=camera.K, width=camera.width,
                                                        height=camera.height, camera_xyz=rr.ViewCoordinates.RDF),
                        static=True)
        where = ", ".join(filter(None, [str(self.recording_path or ""), "spawned viewer" if cfg.spawn else "",
                                        cfg.connect or ""]))
        log.info("rerun viewer: logging to %s", where)

    def show(self, view: ViewerFrame) -> None:
        rr, cfg, stream = self.rr, self.cfg, self.stream
        i = view.frame.index
        stream.set_time("frame", sequence=i)
        stream.log("world/camera", rr.Transform3D(translation=view.pose[:3, 3], mat3x3=view.pose[:3, :3]))
        self._log_trajectories(view)
        if cfg.image_every and i % cfg.image_every == 0:
            self._log_inputs(view)
        if cfg.render_every and i % cfg.render_every == 0:
            self._log_render(view)
        if cfg.map_every and i % cfg.map_every == 0:
            self._log_map(view)

    def close(self, view: ViewerFrame | None) -> None:
        if self.stream is None:
            return
        try:
            if view is not None and self._last_map_frame != view.frame.index:
                self.stream.set_time("frame", sequence=view.frame.index)
                self._log_map(view)  # the final map, whatever map_every is
        finally:
            self.stream.flush()
            self.stream.disconnect()
            self.stream = None
        if self.recording_path is not None:
            log.info("rerun recording: %s (%.1f MB)", self.recording_path, self.recording_path.stat().st_size / 1e6)

    # -- what is logged --------------------------------------------------------------------
    def _log_trajectories(self, view: ViewerFrame) -> None:
        rr = self.rr
        if len(view.trajectory) >= 2:
            self.stream.log("world/trajectory/estimate", rr.LineStrips3D([view.trajectory], colors=[[230, 90, 30]]))
        if len(view.gt_trajectory) >= 2:
            self.stream.log("world/trajectory/ground_truth",
                            rr.LineStrips3D([view.gt_trajectory], colors=[[40, 160, 60]]))
        loops_changed = self._loops_logged is None or not np.array_equal(self._loops_logged, view.loops)
        if view.keyframe or loops_changed:  # a correction moves the keyframes too
            self.stream.log("world/keyframes", rr.Points3D(view.keyframes, radii=0.01, colors=[[250, 200, 0]]))
        if loops_changed:
            self._loops_logged = view.loops.copy()
            self.stream.log("world/loops", rr.LineStrips3D(list(view.loops), colors=[[60, 120, 250]], radii=0.004))

    def _log_inputs(self, view: ViewerFrame) -> None:
        self.stream.log("world/camera/image/rgb", self._color_image(view.frame.rgb))
        if self.cfg.log_depth:
            self.stream.log("world/camera/image/depth", self._depth_image(view.frame.depth))

    def _log_render(self, view: ViewerFrame) -> None:
        out = view.render(self.cfg.render_scale)
        if out is None:
            return
        color = (out.color.clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)
        self.stream.log("render/rgb", self._color_image(color))
        self.stream.log("render/depth", self._depth_image(out.expected_depth().cpu().numpy()))

    def _log_map(self, view: ViewerFrame) -> None:
        rr, style = self.rr, self.cfg.map_as
        self._last_map_frame = view.frame.index
        if style == "points":
            points: MapPoints = view.map_points(self.cfg.map_max_points)
            self.stream.log("world/map", rr.Points3D(points.positions, colors=points.colors,
                                                     radii=np.clip(points.radii, 0.001, 0.05)))
            return
        g: MapGaussians = view.map_gaussians(self.cfg.map_max_points)
        xyzw = g.quats[:, [1, 2, 3, 0]]  # rerun's quaternion order
        rgba = (np.column_stack([g.colors, g.opacities]) * 255 + 0.5).astype(np.uint8)
        if style == "splats" and hasattr(rr, "GaussianSplats3D"):
            self.stream.log("world/map", rr.GaussianSplats3D(g.means, scales=g.scales, quaternions=xyzw, colors=rgba))
        else:  # ellipsoids, asked for or where this rerun-sdk has no splats
            self.stream.log("world/map", rr.Ellipsoids3D(centers=g.means, half_sizes=g.scales, quaternions=xyzw,
                                                         colors=rgba, fill_mode="solid"))

    def _color_image(self, rgb: np.ndarray):
        """rgb (H,W,3) uint8 (or float in [0,1]) as a Rerun image, JPEG-compressed if asked."""
        rgb = np.asarray(rgb)
        if rgb.dtype != np.uint8:
            rgb = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
        image = self.rr.Image(rgb)
        return image.compress(jpeg_quality=self.cfg.jpeg_quality) if self.cfg.jpeg_quality else image

    def _depth_image(self, depth: np.ndarray):
        """depth (H,W) metres (0 / non-finite = invalid) as uint16 millimetres."""
        d = np.nan_to_num(np.asarray(depth, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        mm = np.clip(d * DEPTH_UNITS_PER_METRE + 0.5, 0, np.iinfo(np.uint16).max).astype(np.uint16)
        return self.rr.DepthImage(mm, meter=DEPTH_UNITS_PER_METRE)


@hookimpl
def slamkit_plugins():
    return [PluginSpec("rerun", RerunViewer, RerunViewerConfig)]
