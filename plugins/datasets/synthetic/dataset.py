"""`dataset=synthetic`: the generated sequence as a dataset, and its cache.

The sequence is generated once and cached as one compressed .npz per parameter set (rgb uint8,
depth uint16 at 0.2 mm) in `cache_dir`, recorded with its size and hash (`slamkit.cache.record`);
later constructions open the cache if it matches its record (else it is generated again, with a
warning) and decode frames on demand. The sensor's errors (`depth_model`: Gaussian noise and
dropout, or the structured-light model of `sensor`) are applied at load time (deterministic per
seed and frame), so they share the noise-free cache.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import tempfile
import threading
import time
import zipfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from slamkit.cache import cache_dir, damage, record
from slamkit.errors import DataError
from slamkit.roles import Dataset, DatasetConfig, DatasetTuning, RunContext, require
from slamkit.types import Camera, Frame
from slamkit_plugins.datasets.synthetic import sensor
from slamkit_plugins.datasets.synthetic.path import FPS, LOOP_PATHS, handheld_path, loop_path
from slamkit_plugins.datasets.synthetic.raycast import render
from slamkit_plugins.datasets.synthetic.sensor import SensorModel

log = logging.getLogger(__name__)

#: Bump when the scene, its materials, the path or the renderer change (anything in this package
#: that changes a frame): old cache files are then ignored.
GENERATOR_VERSION = 1
#: Depth is cached as uint16 with this many units per metre (0.2 mm steps, up to 13.1 m; the
#: room's farthest point from the camera is < 8 m).
DEPTH_SCALE = 5000.0


@dataclass
class SyntheticConfig(DatasetConfig):
    """The generated sequence (`path` is unused; `fx`, `fy`, `cx`, `cy` change the intrinsics
    reported with each frame, not what is rendered)."""

    #: frames in the sequence, 30 per second of motion
    num_frames: int = 120
    #: pixels
    width: int = 320
    #: pixels
    height: int = 240
    #: degrees, horizontal field of view; square pixels, fx = fy = (width / 2) / tan(fov_deg / 2)
    fov_deg: float = 64.0
    #: draws the camera path (the scene is fixed)
    seed: int = 0
    #: handheld: multiplies the camera's linear and angular speeds (a path that comes back spans num_frames)
    speed: float = 1.0
    #: camera path: handheld (a seeded wander) or one that comes back: room_loop, figure_eight, return, revisit_rotated
    camera_path: str = "handheld"
    #: a path that comes back: seconds to speed up from rest at its start and slow to rest at its end (0: no ramp)
    ramp_s: float = 0.0
    #: depth errors: gaussian (depth_noise, depth_dropout) or structured_light (the sensor_* fields, and colour noise)
    depth_model: str = "gaussian"
    #: gaussian: metres of Gaussian depth noise at 1 m, growing with z^2 (0: exact; 1.5 mm is a Kinect v1's)
    depth_noise: float = 0.0015
    #: gaussian: fraction of pixels whose depth is set invalid (0) at random
    depth_dropout: float = 0.0
    #: structured_light: metres of axial noise, a in a + b (z - 0.4)^2 (Nguyen, Izadi, Lovell 2012: Kinect v1)
    sensor_axial_sigma_m: float = 0.0012
    #: structured_light: b in a + b (z - 0.4)^2, metres per square metre of depth (Nguyen et al. 2012)
    sensor_axial_sigma_per_m2: float = 0.0019
    #: structured_light: pixels, the IR camera's focal length (Khoshelham and Elberink 2012: Kinect v1, 580)
    sensor_focal_px: float = 580.0
    #: structured_light: metres from projector to IR camera (Khoshelham and Elberink 2012: 7.5 cm)
    sensor_baseline_m: float = 0.075
    #: structured_light: pixels, the disparity's quantisation step (Khoshelham and Elberink 2012: 1/8)
    sensor_disparity_step_px: float = 0.125
    #: structured_light: a depth step between neighbouring pixels larger than this fraction of the depth is an edge
    sensor_edge_jump: float = 0.05
    #: structured_light: pixels of depth lost on each side of an edge (the projector's shadow, the matching window)
    sensor_edge_band_px: int = 1
    #: structured_light: degrees of incidence beyond which a surface gives no depth (Nguyen et al. 2012: ~70-80)
    sensor_max_incidence_deg: float = 75.0
    #: structured_light: grey level (0-1) below which depth goes missing at random, surely at black (little IR back)
    sensor_dark_level: float = 0.08
    #: structured_light: standard deviation of the colour noise, 8-bit levels per channel
    sensor_colour_sigma: float = 2.0
    #: folder of the cached sequences (null: $SLAMKIT_CACHE/synthetic, else ~/.cache/slamkit/synthetic)
    cache_dir: str | None = None

    def validate(self) -> None:
        super().validate()
        require(self.num_frames >= 2, "dataset.num_frames", "an integer >= 2", self.num_frames)
        require(16 <= self.width <= 8192, "dataset.width", "an integer in [16, 8192] pixels", self.width)
        require(16 <= self.height <= 8192, "dataset.height", "an integer in [16, 8192] pixels", self.height)
        require(
            10.0 <= self.fov_deg <= 150.0,
            "dataset.fov_deg",
            "a horizontal field of view in [10, 150] degrees",
            self.fov_deg,
        )
        require(self.seed >= 0, "dataset.seed", "an integer >= 0", self.seed)
        require(0.0 < self.speed <= 10.0, "dataset.speed", "a factor in (0, 10]", self.speed)
        require(self.depth_noise >= 0.0, "dataset.depth_noise", ">= 0 metres", self.depth_noise)
        require(0.0 <= self.depth_dropout < 1.0, "dataset.depth_dropout", "a fraction in [0, 1)", self.depth_dropout)
        require(self.camera_path in ("handheld", *LOOP_PATHS), "dataset.camera_path",
                f"one of handheld, {', '.join(LOOP_PATHS)}", self.camera_path)
        require(self.ramp_s >= 0.0, "dataset.ramp_s", ">= 0 seconds", self.ramp_s)
        require(self.ramp_s == 0.0 or self.camera_path != "handheld", "dataset.ramp_s",
                "0 with camera_path=handheld (a ramp is for a path that comes back)", self.ramp_s)
        require(2 * self.ramp_s * FPS <= max(self.num_frames - 1, 1), "dataset.ramp_s",
                f"at most half of the path's {self.num_frames} frames at {FPS:g} frames/s", self.ramp_s)
        require(self.depth_model in ("gaussian", "structured_light"), "dataset.depth_model",
                "gaussian or structured_light", self.depth_model)
        for name in ("sensor_axial_sigma_m", "sensor_axial_sigma_per_m2", "sensor_disparity_step_px",
                     "sensor_edge_band_px", "sensor_dark_level", "sensor_colour_sigma"):
            require(getattr(self, name) >= 0, f"dataset.{name}", ">= 0", getattr(self, name))
        for name in ("sensor_focal_px", "sensor_baseline_m", "sensor_edge_jump"):
            require(getattr(self, name) > 0, f"dataset.{name}", "> 0", getattr(self, name))
        require(0 < self.sensor_max_incidence_deg <= 90, "dataset.sensor_max_incidence_deg", "in (0, 90] degrees",
                self.sensor_max_incidence_deg)

    def camera(self) -> Camera:
        """The pinhole camera of `width`, `height` and `fov_deg`, principal point at the centre."""
        fx = (self.width / 2.0) / math.tan(math.radians(self.fov_deg) / 2.0)
        return Camera(self.width, self.height, fx, fx, (self.width - 1) / 2.0, (self.height - 1) / 2.0)

    def sensor_model(self) -> SensorModel:
        """The structured-light model of these fields."""
        return SensorModel(*(getattr(self, f"sensor_{f.name}") for f in fields(SensorModel)))


def _write_npz(f, arrays) -> None:
    """Write (name, array) pairs as an .npz that np.load reads, like np.savez_compressed but
    streaming and with zlib level 1 (the frames compress nearly as well, twice as fast)."""
    with zipfile.ZipFile(f, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for name, value in arrays:
            with zf.open(name + ".npy", "w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)


def default_cache_dir() -> Path:
    """$SLAMKIT_CACHE/synthetic, else ~/.cache/slamkit/synthetic."""
    return cache_dir("synthetic")


class SyntheticDataset(Dataset):
    """The generated furnished-room sequence (see the module docstring). Frames: rgb HxWx3
    uint8, depth HxW float32 metres (exact unless depth_noise / depth_dropout or the
    structured-light model), gt_pose
    camera-to-world, timestamp raw_index / 30 s."""

    # small frames (320x240 by default) of a 6 x 5 x 3 m room: a dense sample stride
    default_tuning = DatasetTuning(depth_scale=DEPTH_SCALE, depth_trunc=6.0, max_gaussian_scale=0.5,
                                   tracking_pixel_stride=2)

    def __init__(self, cfg: SyntheticConfig, context: RunContext = RunContext()):
        super().__init__(cfg)
        self.cfg: SyntheticConfig = cfg
        self._camera = cfg.camera()
        self._lock = threading.Lock()
        self.sensor = cfg.sensor_model()
        self._store = None  # NpzFile or dict: rgb_%05d (uint8), depth_%05d (uint16), poses
        self.cache_path = Path(cfg.cache_dir).expanduser() if cfg.cache_dir else default_cache_dir()
        self.cache_path = self.cache_path / f"synthetic_{self.cache_key()[:20]}.npz"
        self._open_or_generate()

    # -- cache ----------------------------------------------------------------------------
    def generation_params(self) -> dict:
        c = self.cfg
        return {
            "version": GENERATOR_VERSION,
            "num_frames": int(c.num_frames),
            "width": int(c.width),
            "height": int(c.height),
            "fov_deg": float(c.fov_deg),
            "seed": int(c.seed),
            "speed": float(c.speed),
            # the default path keeps the key of before, so that its caches stay valid
            **({} if c.camera_path == "handheld" else {"camera_path": c.camera_path}),
            **({"ramp_s": float(c.ramp_s)} if c.ramp_s > 0 else {}),
        }

    def cache_key(self) -> str:
        return hashlib.sha256(json.dumps(self.generation_params(), sort_keys=True).encode()).hexdigest()

    def _open_or_generate(self) -> None:
        meta = json.dumps(self.generation_params(), sort_keys=True)
        if self._open_cache(meta):
            return
        t0 = time.perf_counter()
        tmp = None
        try:
            self.cache_path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=self.cache_path.parent, prefix=self.cache_path.stem + ".", suffix=".tmp")
            with os.fdopen(fd, "wb") as f:
                _write_npz(f, self._generate(meta))
            record(self.cache_path, content=Path(tmp))
            os.replace(tmp, self.cache_path)  # atomic: readers never see a partial file
            tmp = None
        except OSError as e:
            log.warning("cannot write the synthetic cache %s (%s); keeping the sequence in memory", self.cache_path, e)
            self._store = dict(self._generate(meta))
            self._poses = self._store["poses"]
            return
        finally:
            if tmp is not None:
                Path(tmp).unlink(missing_ok=True)
        log.info(
            "generated the synthetic sequence (%d frames, %dx%d) in %.1f s: %s",
            self.cfg.num_frames,
            self.cfg.width,
            self.cfg.height,
            time.perf_counter() - t0,
            self.cache_path,
        )
        if not self._open_cache(meta):
            raise DataError(f"{self.cache_path}: the synthetic sequence just written cannot be read back")

    def _open_cache(self, meta: str) -> bool:
        """Open the cache file if it exists, matches its record and holds this parameter set."""
        why = damage(self.cache_path)
        if why == "missing":
            return False
        if why is not None:
            log.warning("synthetic cache %s is damaged (%s); regenerating", self.cache_path, why)
            return False
        try:
            store = np.load(self.cache_path)
            if str(store["meta"]) == meta and f"depth_{self.cfg.num_frames - 1:05d}.npy" in store.zip.namelist():
                self._poses = store["poses"]
                self._store = store
                return True
            store.close()
            log.warning("synthetic cache %s does not match its parameters; regenerating", self.cache_path)
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as e:
            log.warning("synthetic cache %s is unreadable (%s); regenerating", self.cache_path, e)
        return False

    def _generate(self, meta: str):
        """Yield (name, array): meta, poses, then rgb_%05d (uint8) and depth_%05d (uint16,
        DEPTH_SCALE units per metre) per frame."""
        c = self.cfg
        poses = handheld_path(c.num_frames, c.seed, c.speed) if c.camera_path == "handheld" else \
            loop_path(c.camera_path, c.num_frames, c.seed, ramp_s=c.ramp_s)
        yield "meta", np.array(meta)
        yield "poses", poses
        # Frames are independent: render a chunk at a time on a few threads (numpy releases
        # the GIL); only one chunk is held in memory.
        workers = max(1, min(4, os.cpu_count() or 1))
        with ThreadPoolExecutor(workers) as pool:
            for start in range(0, len(poses), 16):
                chunk = pool.map(lambda pose: render(self._camera, pose), poses[start : start + 16])
                for i, (rgb, depth) in enumerate(chunk, start):
                    yield f"rgb_{i:05d}", rgb
                    yield f"depth_{i:05d}", np.clip(np.round(depth * DEPTH_SCALE), 0, 65535).astype(np.uint16)

    def close(self) -> None:
        """Close the cache file (frames cannot be loaded afterwards)."""
        if hasattr(self._store, "close"):
            self._store.close()
        self._store = None

    def __getstate__(self) -> dict:  # picklable (e.g. for a worker process): reopen there
        state = self.__dict__.copy()
        state["_store"] = state["_lock"] = None
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()
        self._open_or_generate()

    # -- Dataset --------------------------------------------------------------------------
    @property
    def native_camera(self) -> Camera:
        return self._camera

    def num_available(self) -> int:
        return int(self.cfg.num_frames)

    def load(self, raw_index: int) -> Frame:
        if not 0 <= raw_index < self.cfg.num_frames:
            raise IndexError(f"synthetic frame {raw_index} out of range [0, {self.cfg.num_frames})")
        try:
            with self._lock:
                rgb = np.array(self._store[f"rgb_{raw_index:05d}"])
                depth_raw = self._store[f"depth_{raw_index:05d}"]
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:  # changed since it was opened
            raise DataError(f"synthetic cache {self.cache_path}: frame {raw_index} is unreadable ({exc}); delete the "
                            "file to generate it again") from None
        depth = depth_raw.astype(np.float32) / np.float32(DEPTH_SCALE)
        c = self.cfg
        if c.depth_model == "structured_light":
            cam = self._camera
            depth, rgb = sensor.apply(depth, rgb, cam.fx, cam.fy, cam.cx, cam.cy, self.sensor,
                                      np.random.default_rng([c.seed, raw_index, 0x5E]))
        elif c.depth_noise > 0 or c.depth_dropout > 0:
            rng = np.random.default_rng([c.seed, raw_index, 0xDE])
            valid = depth > 0
            if c.depth_noise > 0:
                noise = rng.standard_normal(depth.shape).astype(np.float32) * np.float32(c.depth_noise) * depth * depth
                depth = np.where(valid, np.maximum(depth + noise, 1e-3), 0).astype(np.float32)
            if c.depth_dropout > 0:
                depth[rng.random(depth.shape) < c.depth_dropout] = 0.0
        return Frame(
            index=raw_index,
            timestamp=raw_index / FPS,
            rgb=rgb,
            depth=depth,
            camera=self._camera,
            gt_pose=np.array(self._poses[raw_index], dtype=np.float64),
        )
