"""`dataset.record=DIR`: the frames a RealSense source gives, kept in the TUM layout so that a live
session can be replayed and evaluated later (`dataset=folder dataset.path=DIR`, or `dataset=tum`).

DIR holds rgb/TIMESTAMP.png (8-bit RGB), depth/TIMESTAMP.png (16-bit, the device's raw units, in
the colour camera's pixels), rgb.txt and depth.txt (`timestamp file` lines, TUM's lists) and
intrinsics.yaml (the colour camera in pixels, and depth_scale: raw units per metre), with
TIMESTAMP the colour frame's device time in seconds (six decimals). Images are written by a
thread of their own; `close` waits for the last one.
"""

from __future__ import annotations

import logging
import queue
import threading
from pathlib import Path

import numpy as np
from PIL import Image

from slamkit.errors import DataError
from slamkit.formats.images import read_rgbd
from slamkit.types import Camera

log = logging.getLogger(__name__)

#: Frames waiting to be written before the source waits for the disk.
PENDING = 64


class TumRecorder:
    """Writes frames into `root` in the TUM layout (see the module docstring). `camera`: the
    colour camera (pixels); `units_per_metre`: raw depth units per metre."""

    def __init__(self, root: Path, camera: Camera, units_per_metre: float):
        self.root, self.camera, self.units_per_metre = root, camera, units_per_metre
        try:
            root.mkdir(parents=True, exist_ok=True)
            (root / "rgb").mkdir(exist_ok=True)
            (root / "depth").mkdir(exist_ok=True)
        except OSError as exc:
            raise DataError(f"dataset.record: cannot make the folder {root}: {exc.strerror or exc}") from None
        if any((root / "rgb").iterdir()) or any((root / "depth").iterdir()):
            raise DataError(f"dataset.record: {root} already holds a recording (expected a new or empty folder)")
        self._write_intrinsics()
        self.files: dict[int, str] = {}  # frame index -> stem of its images
        self.written = 0
        self.error: OSError | None = None
        self._queue: queue.Queue = queue.Queue(PENDING)
        self._lists = [open(root / name, "a") for name in ("rgb.txt", "depth.txt")]
        for f, what in zip(self._lists, ("color", "depth")):
            f.write(f"# {what} images\n# recorded by slamkit dataset=realsense\n# timestamp filename\n")
        self._thread = threading.Thread(target=self._write_all, name="slamkit-realsense-record", daemon=True)
        self._thread.start()

    def _write_intrinsics(self) -> None:
        c = self.camera
        text = (f"# the colour camera of this recording (pixels); depth_scale: raw depth units per metre\n"
                f"width: {c.width}\nheight: {c.height}\nfx: {c.fx!r}\nfy: {c.fy!r}\ncx: {c.cx!r}\ncy: {c.cy!r}\n"
                f"depth_scale: {self.units_per_metre!r}\n")
        (self.root / "intrinsics.yaml").write_text(text)

    def add(self, index: int, timestamp: float, rgb: np.ndarray, depth_raw: np.ndarray) -> None:
        """Queue frame `index` (colour HxWx3 uint8, depth HxW uint16 raw) for writing; a frame
        already added is not written again. Waits while PENDING frames are waiting for the disk."""
        if index in self.files:
            return
        stem = f"{timestamp:.6f}"
        while stem in self.files.values():  # two frames in one microsecond: keep both
            stem += "1"
        self.files[index] = stem
        self._queue.put((stem, rgb, depth_raw))

    def read(self, index: int):
        """Frame `index` back from the disk: (colour HxWx3 uint8, depth HxW float32 metres);
        DataError where it was not recorded."""
        self._queue.join()
        stem = self.files.get(index)
        if stem is None:
            raise DataError(f"frame {index} is not in the recording {self.root}")
        rgb, depth = read_rgbd(self.root / "rgb" / f"{stem}.png", self.root / "depth" / f"{stem}.png",
                               self.units_per_metre, self.camera)
        return np.asarray(rgb() if callable(rgb) else rgb), depth

    def _write_all(self) -> None:
        while True:
            item = self._queue.get()
            try:
                if item is None:
                    return
                if self.error is None:
                    self._write(*item)
            except OSError as exc:
                self.error = exc
                log.error("dataset.record: cannot write into %s: %s; the recording stops here", self.root,
                          exc.strerror or exc)
            finally:
                self._queue.task_done()

    def _write(self, stem: str, rgb: np.ndarray, depth_raw: np.ndarray) -> None:
        Image.fromarray(rgb, "RGB").save(self.root / "rgb" / f"{stem}.png", compress_level=1)
        Image.fromarray(depth_raw).save(self.root / "depth" / f"{stem}.png", compress_level=1)
        for f, folder in zip(self._lists, ("rgb", "depth")):
            f.write(f"{stem} {folder}/{stem}.png\n")
            f.flush()
        self.written += 1

    def close(self) -> None:
        """Write the frames still queued and close the lists; again is a no-op."""
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()
        for f in self._lists:
            f.close()
