"""The 3DGS mapper's keyframes: each input keyframe kept at the training resolution, in memory
or on disk, and handed to training as a `slamkit.roles.training_view.TrainingView`.

Images are kept as uint8 colour and uint16 depth in 1 mm steps (at most 0.5 mm of rounding, up
to 65.5 m; deeper pixels become invalid): a long run holds hundreds of keyframes (96 kB each at
160x120, 1 MB at Replica's 600x340). With storage `disk` they are .npy files read back when the
keyframe is trained on.
"""

from __future__ import annotations

import enum
import shutil
import tempfile
import threading
import weakref
from collections import OrderedDict
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from slamkit.geometry.transforms import invert_pose
from slamkit.roles.training_view import TrainingView
from slamkit.types import Camera, Frame, KeyframeKind

#: Keyframe depth is stored as uint16 in steps of this many metres.
KEYFRAME_DEPTH_STEP = 1e-3


class KeyframeStorage(enum.Enum):
    """Where keyframe training images live: memory, or disk (.npy files)."""

    memory = "memory"
    disk = "disk"


def resize_rgbd(rgb: np.ndarray, depth: np.ndarray, camera: Camera, scale: float, device=None):
    """(image (h,w,3) float32 in [0,1], depth (h,w) float32 metres, camera) at `scale` of the
    frame's resolution: colour by area averaging, depth by averaging the valid pixels of each
    output pixel's area (0 where fewer than half of them are valid). Non-finite or negative
    depths count as invalid."""
    image = torch.as_tensor(rgb if isinstance(rgb, torch.Tensor) else np.asarray(rgb), device=device)
    image = image.float() / 255.0 if image.dtype == torch.uint8 else image.float()
    d = torch.as_tensor(depth if isinstance(depth, torch.Tensor) else np.asarray(depth, dtype=np.float32),
                        device=device).float()
    d = torch.where(torch.isfinite(d) & (d > 0), d, torch.zeros_like(d))  # NaN / inf / negative: invalid
    if scale == 1.0:
        return image, d, camera
    cam = camera.scaled(scale)
    size = (cam.height, cam.width)
    image = F.interpolate(image.permute(2, 0, 1)[None], size=size, mode="area")[0].permute(1, 2, 0).contiguous()
    valid = (d > 0).float()[None, None]
    num = F.interpolate(d[None, None] * valid, size=size, mode="area")[0, 0]
    den = F.interpolate(valid, size=size, mode="area")[0, 0]
    d = torch.where(den >= 0.5, num / den.clamp_min(1e-12), torch.zeros_like(num))
    return image, d, cam


@dataclass
class Keyframe:
    """A training view: its ids, kind, pose (camera-to-world, float64), camera at the training
    resolution, and its image (h,w,3) uint8 and depth (h,w) uint16 in KEYFRAME_DEPTH_STEP
    metres (0 = invalid), held in `rgbd` or, when `path` is set, in `path`_rgb.npy /
    `path`_depth.npy (read on each use)."""

    id: int
    frame_index: int
    kind: KeyframeKind
    pose: np.ndarray
    camera: Camera
    rgbd: tuple[np.ndarray, np.ndarray] | None = None
    path: Path | None = None

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(rgb (h,w,3) uint8, depth (h,w) uint16 in KEYFRAME_DEPTH_STEP units)."""
        if self.rgbd is not None:
            return self.rgbd
        return np.load(f"{self.path}_rgb.npy"), np.load(f"{self.path}_depth.npy")

    def view(self, device=None, scale: float = 1.0) -> TrainingView:
        """The keyframe as a training target (float images on `device`), at `scale` of the
        training resolution (area averaging, as when it was stored)."""
        rgb, d = self.arrays()
        image = torch.from_numpy(rgb).to(device=device, dtype=torch.float32) / 255.0
        depth = torch.from_numpy(d).to(device=device, dtype=torch.float32) * KEYFRAME_DEPTH_STEP
        image, depth, camera = resize_rgbd(image, depth, self.camera, scale, device)
        return TrainingView(
            keyframe_id=self.id,
            frame_index=self.frame_index,
            pose=self.pose,
            world_to_camera=torch.as_tensor(invert_pose(self.pose), dtype=torch.float32, device=device),
            camera=camera,
            image=image,
            depth=depth,
        )

    @property
    def nbytes(self) -> int:
        """Bytes of image data held in memory (0 when on disk)."""
        return sum(a.nbytes for a in self.rgbd) if self.rgbd is not None else 0


def quantize(image: torch.Tensor, depth: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """`image` (h,w,3) float in [0,1] and `depth` (h,w) metres as uint8 colour and uint16 depth
    in KEYFRAME_DEPTH_STEP units (out-of-range depth becomes 0, invalid)."""
    rgb = (image * 255.0).round_().clamp_(0, 255).to(torch.uint8).cpu().numpy()
    steps = torch.round(depth / KEYFRAME_DEPTH_STEP)
    steps = torch.where((steps > 0) & (steps <= 65535), steps, torch.zeros_like(steps))
    return rgb, steps.to(torch.int32).cpu().numpy().astype(np.uint16)


class ViewCache:
    """Training views kept between steps, least recently used dropped first beyond `max_bytes`
    of image data: a step on a kept view skips converting its keyframe's uint8 / uint16 images
    (docs/results.md, "One mapping step"). Views are read-only to training. Safe to
    use from several threads (a lock; uncontended in practice: the mapping thread uses it)."""

    def __init__(self, max_bytes: int):
        self.max_bytes = max_bytes
        self.held_bytes = 0
        self._views: OrderedDict[Hashable, TrainingView] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: Hashable, make: Callable[[], TrainingView]) -> TrainingView:
        """The view kept under `key`, else `make()`'s, kept if it fits the budget."""
        with self._lock:
            view = self._views.get(key)
            if view is not None:
                self._views.move_to_end(key)
                return view
        view = make()
        size = view.image.nbytes + view.depth.nbytes
        with self._lock:
            if size <= self.max_bytes and key not in self._views:
                self._views[key] = view
                self.held_bytes += size
                while self.held_bytes > self.max_bytes:
                    _, dropped = self._views.popitem(last=False)
                    self.held_bytes -= dropped.image.nbytes + dropped.depth.nbytes
        return view


    def clear(self) -> None:
        """Forget every view (their poses changed)."""
        with self._lock:
            self._views.clear()
            self.held_bytes = 0


class KeyframeStore:
    """The keyframes in arrival order (`ids`), by id (`[id]`). Append-only: a keyframe is
    stored before its id is published, so a mapping thread may read while the tracking thread
    adds. `view` hands out training views, the recent ones from a cache of `view_cache_mb` MiB."""

    def __init__(self, resolution_scale: float, storage: KeyframeStorage, folder: str | None = None,
                 view_cache_mb: float = 0.0):
        self.resolution_scale = resolution_scale
        self.storage = KeyframeStorage(storage)
        self.folder = Path(folder) if folder else None
        self.ids: list[int] = []
        self._by_id: dict[int, Keyframe] = {}
        self._views = ViewCache(int(view_cache_mb * 2**20))
        self.moves = 0  # loop closures' corrections so far (`move`)

    def __len__(self) -> int:
        return len(self.ids)

    def __getitem__(self, kf_id: int) -> Keyframe:
        return self._by_id[kf_id]

    def values(self) -> list[Keyframe]:
        return [self._by_id[i] for i in list(self.ids)]

    def view(self, kf_id: int, device=None, scale: float = 1.0) -> TrainingView:
        """Keyframe `kf_id` as a training target (Keyframe.view), from the cache when it holds it
        (a keyframe's half-resolution view for `coarse_steps` is kept too, until newer views push
        it out)."""
        key = (kf_id, str(device), scale, self.moves)  # a view made before a move is never handed out after it
        return self._views.get(key, lambda: self._by_id[kf_id].view(device, scale))

    def training_camera(self, camera: Camera) -> Camera:
        return camera.scaled(self.resolution_scale) if self.resolution_scale != 1 else camera

    def add(self, frame: Frame, pose: np.ndarray, kind: KeyframeKind) -> Keyframe:
        """Store `frame` at the training resolution as the next keyframe, seen from `pose`."""
        image, depth, camera = resize_rgbd(frame.rgb, frame.depth, frame.camera, self.resolution_scale)
        return self.put(frame.index, kind, pose, camera, *quantize(image, depth))

    def state_dict(self) -> dict:
        """Every keyframe (ids, kinds, poses, cameras, images) for a map checkpoint; the images as
        stacked arrays (K,h,w,3) uint8 and (K,h,w) uint16 (KEYFRAME_DEPTH_STEP units)."""
        kfs = self.values()
        images = [kf.arrays() for kf in kfs]
        return {"resolution_scale": self.resolution_scale,
                "frame_index": [kf.frame_index for kf in kfs], "kind": [kf.kind.value for kf in kfs],
                "pose": np.array([kf.pose for kf in kfs]).reshape(-1, 4, 4),
                "camera": [[kf.camera.width, kf.camera.height, kf.camera.fx, kf.camera.fy, kf.camera.cx,
                            kf.camera.cy] for kf in kfs],
                "rgb": np.stack([rgb for rgb, _ in images]) if images else np.zeros((0, 1, 1, 3), np.uint8),
                "depth": np.stack([d for _, d in images]) if images else np.zeros((0, 1, 1), np.uint16)}

    def load_state_dict(self, state: dict) -> None:
        """Add the keyframes of a `state_dict()` (to an empty store), and train new ones at their
        resolution (checkpoints before it was saved keep the configured one)."""
        self.resolution_scale = float(state.get("resolution_scale", self.resolution_scale))
        for i, index in enumerate(state["frame_index"]):
            camera = Camera(int(state["camera"][i][0]), int(state["camera"][i][1]), *map(float, state["camera"][i][2:]))
            self.put(int(index), KeyframeKind(state["kind"][i]), state["pose"][i], camera,
                     np.ascontiguousarray(state["rgb"][i]), np.ascontiguousarray(state["depth"][i]))

    def put(self, frame_index: int, kind: KeyframeKind, pose: np.ndarray, camera: Camera, rgb: np.ndarray,
            d: np.ndarray) -> Keyframe:
        """Store the next keyframe from its training-resolution images (uint8 colour, uint16 depth)."""
        kf = Keyframe(len(self.ids), frame_index, kind, np.asarray(pose, dtype=np.float64).copy(), camera)
        path = self._path(kf.id)
        if path is None:
            kf.rgbd = (rgb, d)
        else:
            np.save(f"{path}_rgb.npy", rgb)
            np.save(f"{path}_depth.npy", d)
            kf.path = path
        self._by_id[kf.id] = kf
        self.ids.append(kf.id)
        return kf

    def move(self, updates: np.ndarray) -> None:
        """Keyframes 0..K-1 moved by `updates` ((K,4,4) world-frame rigid motions, a loop
        closure's correction): each pose becomes updates[k] @ pose (a new array, so a view taken
        before is seen to be out of date: `is_current`), and the views kept are dropped."""
        for kf_id in list(self.ids):
            if kf_id < len(updates):
                kf = self._by_id[kf_id]
                kf.pose = np.asarray(updates[kf_id], dtype=np.float64) @ kf.pose
        self.moves += 1
        self._views.clear()

    def is_current(self, view: TrainingView) -> bool:
        """Whether `view` was taken at its keyframe's current pose (not before a `move`)."""
        kf = self._by_id.get(view.keyframe_id)
        return kf is None or view.pose is kf.pose or np.array_equal(view.pose, kf.pose)

    def memory_bytes(self) -> int:
        """Bytes of keyframe images held in memory (0 with disk storage)."""
        return sum(kf.nbytes for kf in self.values())

    def _path(self, kf_id: int) -> Path | None:
        """Where keyframe `kf_id`'s images go: None (memory) or a file prefix in the folder (the
        configured one, else a temporary folder removed with this store)."""
        if self.storage is not KeyframeStorage.disk:
            return None
        if self.folder is None:
            self.folder = Path(tempfile.mkdtemp(prefix="slamkit-keyframes-"))
            weakref.finalize(self, shutil.rmtree, self.folder, ignore_errors=True)
        self.folder.mkdir(parents=True, exist_ok=True)
        return self.folder / f"keyframe_{kf_id:06d}"
