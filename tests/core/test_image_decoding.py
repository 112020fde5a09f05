"""The frame reader's decoding (imagecodecs for PNG and JPEG, Pillow otherwise) gives Pillow's
pixels exactly on the shared sequences' images, and refuses what Pillow refuses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from slamkit.errors import DataError
from slamkit.formats import images
from slamkit.formats.images import read_depth, read_rgb

from support.data import DATA, require_data

# (folder, colour glob, depth glob, depth scale, invalid raw values): the three layouts' images
# (7-Scenes colour is JPEG in the developers' shared copy, PNG as `slamkit-data download` cuts it)
SEQUENCES = {
    "tum": ("tum_fr1_rpy_first150", "rgb/*.png", "depth/*.png", 5000.0, ()),
    "7scenes": ("7scenes_redkitchen_300to999", "*.color.*", "*.depth.png", 1000.0, (65535,)),
    "replica": ("replica_room0_first20", "results/frame*.jpg", "results/depth*.png", 6553.5, ()),
}


def _some(folder: Path, pattern: str, count: int = 4) -> list[Path]:
    found = sorted(folder.glob(pattern))
    return found[:: max(1, len(found) // count)][:count]


def pillow_depth(path: Path, scale: float, invalid_values=()) -> np.ndarray:
    """The depth as the reader computed it with Pillow before imagecodecs (metres, 0 invalid)."""
    raw = np.asarray(Image.open(path))
    invalid = raw <= 0
    for v in invalid_values:
        invalid |= raw == v
    depth = raw.astype(np.float32) / np.float32(scale)
    depth[invalid] = 0.0
    return depth


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.mark.parametrize("sequence", list(SEQUENCES))
@pytest.mark.parametrize("decoder", ["imagecodecs", "pillow"])
def test_the_reader_gives_pillows_pixels_bit_for_bit(sequence, decoder, monkeypatch):
    folder, colour, depth, scale, invalid = SEQUENCES[sequence]
    root = require_data(DATA / folder)
    if decoder == "pillow":
        monkeypatch.setattr(images, "imagecodecs", None)  # as where imagecodecs is not installed
    elif images.imagecodecs is None:
        pytest.skip("imagecodecs is not installed")
    for path in _some(root, colour):
        assert same_bits(read_rgb(path), np.asarray(Image.open(path).convert("RGB"))), path
    for path in _some(root, depth):
        assert same_bits(read_depth(path, scale, invalid), pillow_depth(path, scale, invalid)), path


@pytest.mark.parametrize("name, keep", [("frame.jpg", 0.5), ("frame.jpg", -2), ("depth.png", 0.5)])
def test_a_truncated_image_is_refused_naming_the_file(tmp_path, name, keep):
    """libjpeg-turbo pads a truncated JPEG with grey; the reader refuses it as Pillow does."""
    source = (require_data(DATA / "replica_room0_first20") / "results" / "frame000000.jpg" if name.endswith("jpg")
              else require_data(DATA / "7scenes_redkitchen_300to999") / "frame-000300.depth.png")
    data = source.read_bytes()
    cut = tmp_path / name
    cut.write_bytes(data[: int(len(data) * keep) if keep > 0 else keep])
    with pytest.raises(DataError, match=str(cut)):
        read_rgb(cut) if name.endswith("jpg") else read_depth(cut, 1000.0)


def test_a_depth_image_given_as_colour_is_refused_by_its_pixel_mode():
    path = _some(require_data(DATA / "tum_fr1_rpy_first150"), "depth/*.png", 1)[0]
    with pytest.raises(DataError, match="pixel mode I;16"):
        read_rgb(path)
