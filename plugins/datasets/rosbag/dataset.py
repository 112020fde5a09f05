"""The `rosbag` dataset: RGB-D frames from a ROS bag's colour, depth and camera-info topics."""

from __future__ import annotations

import dataclasses
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slamkit.errors import DataError
from slamkit.formats.tum import associate, interpolate_poses, read_tum_trajectory
from slamkit.roles import Dataset, DatasetConfig, DatasetTuning, RunContext, require
from slamkit.types import Camera, Frame
from slamkit_plugins.datasets.rosbag.bag import BagIndex
from slamkit_plugins.datasets.rosbag.images import (
    CAMERA_INFO,
    IMAGE_TYPES,
    camera_from_info,
    decode_color,
    decode_depth,
    distortion,
    image_size,
    is_depth,
)

log = logging.getLogger(__name__)


@dataclass
class RosbagConfig(DatasetConfig):
    """Options of a ROS1 / ROS2 bag (`path`: a .bag, a ROS2 bag folder, or a .db3 / .mcap file)."""

    #: the colour image topic (null: the bag's one colour topic, told apart from depth by encoding)
    color_topic: str | None = None
    #: the depth image topic (null: the bag's one depth topic: 16UC1, mono16, 32FC1 or compressedDepth)
    depth_topic: str | None = None
    #: the colour intrinsics topic, a CameraInfo (null: the bag's one, or the one in the colour topic's namespace)
    camera_info_topic: str | None = None
    #: seconds allowed between a colour and its depth header stamp (unpaired colour frames are dropped)
    sync_tolerance: float = 0.02
    #: raw units per metre of 16-bit depth (1000: millimetres, the ROS convention; 32FC1 is metres)
    depth_scale: float = 1000.0
    #: TUM-format ground truth (camera-to-world, metres), interpolated at the colour stamps (null: none)
    groundtruth: str | None = None
    #: seconds between a colour stamp and the nearest ground-truth pose
    gt_tolerance: float = 0.02

    def validate(self) -> None:
        super().validate()
        require(self.sync_tolerance > 0, "dataset.sync_tolerance", "> 0 seconds", self.sync_tolerance)
        require(self.depth_scale > 0, "dataset.depth_scale", "> 0 raw units per metre", self.depth_scale)
        require(self.gt_tolerance > 0, "dataset.gt_tolerance", "> 0 seconds", self.gt_tolerance)


class RosbagDataset(Dataset):
    """RGB-D frames of a ROS bag (see RosbagConfig). Timestamps are the colour header stamps
    (seconds); depth in metres; gt_pose camera-to-world from `groundtruth` or None."""

    def __init__(self, cfg: RosbagConfig, context: RunContext = RunContext()):
        super().__init__(cfg)
        self.bag = BagIndex(cfg.path)
        self.color_topic, self.depth_topic = self._image_topics()
        self.info_topic = self._info_topic()
        self.bag.scan([self.color_topic, self.depth_topic])
        color, depth = self.bag.index[self.color_topic], self.bag.index[self.depth_topic]
        self._check_pairs_exist(color, depth)
        ic, idepth = associate(color.stamps, depth.stamps, cfg.sync_tolerance)
        if len(ic) == 0:
            raise DataError(f"ROS bag {self.bag.path}: none of {len(color)} colour frames on {self.color_topic} has a "
                            f"depth frame on {self.depth_topic} within {cfg.sync_tolerance} s (expected matching "
                            "header stamps; set dataset.sync_tolerance)")
        if len(ic) < len(color):
            log.info("%s: %d of %d colour frames have no depth frame and are skipped", self.bag.path,
                     len(color) - len(ic), len(color))
        self.color_k, self.depth_k = ic, idepth
        self.timestamps = color.stamps[ic]
        self._camera = self._intrinsics()
        self.default_tuning = dataclasses.replace(DatasetTuning(), depth_scale=cfg.depth_scale)
        self._check_sizes()
        self.gt_poses = self._ground_truth()

    # -- topics -----------------------------------------------------------------------------
    def _where(self, topic: str) -> str:
        return f"ROS bag {self.bag.path} topic {topic}"

    def _image_topics(self) -> tuple[str, str]:
        cfg, topics = self.cfg, self.bag.topics
        for key, topic in (("color_topic", cfg.color_topic), ("depth_topic", cfg.depth_topic)):
            if topic is not None and topics.get(topic) not in IMAGE_TYPES:
                found = f"a {topics[topic]} topic" if topic in topics else "not in the bag"
                raise DataError(f"dataset.{key}: {topic} is {found} (expected one of the bag's image topics: "
                                f"{self._list(IMAGE_TYPES)})")
        images = [t for t, m in topics.items() if m in IMAGE_TYPES]
        if not images:
            raise DataError(f"ROS bag {self.bag.path} has no image topic (expected sensor_msgs/Image or "
                            f"CompressedImage topics; it has {self._list()})")
        if cfg.color_topic is not None and cfg.depth_topic is not None:
            return cfg.color_topic, cfg.depth_topic
        kinds = {"depth": [], "colour": []}
        for t in images:
            msg = self.bag.first_message(t)
            if msg is not None:
                kinds["depth" if is_depth(msg, topics[t]) else "colour"].append(t)
        picked = {"colour": cfg.color_topic, "depth": cfg.depth_topic}
        for kind, key in (("colour", "color_topic"), ("depth", "depth_topic")):
            if picked[kind] is None:
                candidates = [t for t in kinds[kind] if t not in picked.values()]
                if len(candidates) != 1:
                    have = ", ".join(candidates) if candidates else "none"
                    raise DataError(f"ROS bag {self.bag.path}: {len(candidates)} {kind} image topics ({have}) "
                                    f"(expected one; set dataset.{key})")
                picked[kind] = candidates[0]
        return picked["colour"], picked["depth"]

    def _info_topic(self) -> str | None:
        cfg, topics = self.cfg, self.bag.topics
        if cfg.camera_info_topic is not None:
            if topics.get(cfg.camera_info_topic) != CAMERA_INFO:
                raise DataError(f"dataset.camera_info_topic: {cfg.camera_info_topic} is not a CameraInfo topic of "
                                f"{self.bag.path} (it has {self._list((CAMERA_INFO,))})")
            return cfg.camera_info_topic
        infos = [t for t, m in topics.items() if m == CAMERA_INFO]
        if len(infos) <= 1:
            return infos[0] if infos else None
        namespace = self.color_topic.rsplit("/", 1)[0]
        near = [t for t in infos if t.rsplit("/", 1)[0] == namespace]
        if len(near) == 1:
            return near[0]
        raise DataError(f"ROS bag {self.bag.path}: {len(infos)} CameraInfo topics ({', '.join(infos)}) and none "
                        f"alone beside {self.color_topic} (expected one; set dataset.camera_info_topic)")

    def _list(self, types: tuple[str, ...] = ()) -> str:
        chosen = [f"{t} ({m.split('/')[-1]})" for t, m in self.bag.topics.items() if not types or m in types]
        return ", ".join(chosen) or "none"

    # -- intrinsics, sizes, ground truth -------------------------------------------------------
    def _check_pairs_exist(self, color, depth) -> None:
        for index, topic in ((color, self.color_topic), (depth, self.depth_topic)):
            if len(index) == 0:
                raise DataError(f"{self._where(topic)} has no messages (expected one image per frame)")

    def _intrinsics(self) -> Camera:
        cfg = self.cfg
        overrides = (cfg.fx, cfg.fy, cfg.cx, cfg.cy)
        first = self.bag.message(self.color_topic, int(self.color_k[0]))
        width, height = image_size(first, self.bag.topics[self.color_topic], self._where(self.color_topic))
        if self.info_topic is None:
            if any(v is None for v in overrides):
                raise DataError(f"ROS bag {self.bag.path} has no CameraInfo topic (expected one, or the intrinsics "
                                "as dataset.fx, dataset.fy, dataset.cx and dataset.cy in pixels)")
            return Camera(width, height, *overrides)
        info = self.bag.first_message(self.info_topic)
        camera = camera_from_info(info, self._where(self.info_topic))
        if (camera.width, camera.height) != (width, height):
            raise DataError(f"{self._where(self.info_topic)}: the camera is {camera.width}x{camera.height} but the "
                            f"colour images on {self.color_topic} are {width}x{height} (expected the same size)")
        if np.any(distortion(info) != 0):
            log.warning("%s: distortion %s is not corrected (images are used as recorded)",
                        self._where(self.info_topic), distortion(info).round(4).tolist())
        return camera

    def _check_sizes(self) -> None:
        msg = self.bag.message(self.depth_topic, int(self.depth_k[0]))
        w, h = image_size(msg, self.bag.topics[self.depth_topic], self._where(self.depth_topic))
        c = self._camera
        if (w, h) != (c.width, c.height):
            raise DataError(f"{self._where(self.depth_topic)}: depth images are {w}x{h} but the colour images are "
                            f"{c.width}x{c.height} (expected depth registered to colour, of the same size)")

    def _ground_truth(self) -> np.ndarray | None:
        """(N,4,4) camera-to-world poses (NaN where none is within gt_tolerance), or None."""
        if self.cfg.groundtruth is None:
            return None
        path = Path(os.path.expanduser(self.cfg.groundtruth))
        if not path.is_file():
            raise DataError(f"dataset.groundtruth: {path} not found (expected a TUM-format trajectory file)")
        gt_ts, gt = read_tum_trajectory(path)
        poses = interpolate_poses(gt_ts, gt, self.timestamps, self.cfg.gt_tolerance)
        if not np.isfinite(poses).all(axis=(1, 2)).any():
            raise DataError(f"{path}: no pose within {self.cfg.gt_tolerance} s of any colour stamp "
                            f"({self.timestamps[0]:.6f} .. {self.timestamps[-1]:.6f}; expected the bag's time)")
        return poses

    # -- the Dataset role ---------------------------------------------------------------------
    @property
    def native_camera(self) -> Camera:
        return self._camera

    def num_available(self) -> int:
        return len(self.timestamps)

    def raw_timestamp(self, raw_index: int) -> float:
        return float(self.timestamps[raw_index])

    def load(self, raw_index: int) -> Frame:
        bag, topics = self.bag, self.bag.topics
        color_msg = bag.message(self.color_topic, int(self.color_k[raw_index]))
        depth_msg = bag.message(self.depth_topic, int(self.depth_k[raw_index]))
        stamp = f"at {self.timestamps[raw_index]:.6f} s"
        rgb = decode_color(color_msg, topics[self.color_topic], f"{self._where(self.color_topic)} {stamp}")
        depth = decode_depth(depth_msg, topics[self.depth_topic], self.cfg.depth_scale,
                             f"{self._where(self.depth_topic)} {stamp}")
        c = self._camera
        for what, image, topic in (("colour", rgb, self.color_topic), ("depth", depth, self.depth_topic)):
            if image.shape[:2] != (c.height, c.width):
                raise DataError(f"{self._where(topic)} {stamp}: a {image.shape[1]}x{image.shape[0]} {what} image "
                                f"(expected {c.width}x{c.height}, the camera's size)")
        gt = None
        if self.gt_poses is not None and np.isfinite(self.gt_poses[raw_index]).all():
            gt = self.gt_poses[raw_index].copy()
        return Frame(raw_index, float(self.timestamps[raw_index]), rgb, depth, c, gt)
