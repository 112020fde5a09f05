"""The inputs of the fault suite (tests/e2e/test_faults.py): data folders made from the first frames
of the shared TUM sequence, their damages, and throwaway third-party plugins installed as a
distribution with entry points (a tmp dist-info on sys.path)."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path
from typing import Callable

from support.folders import TINY_TUM_FRAMES, tiny_tum
from support.plugins import FAKE_TRACKER, make_plugin_dist

FRAMES = TINY_TUM_FRAMES


# --- inputs a case starts from ------------------------------------------------------------------

INTRINSICS = "fx: 517.3\nfy: 516.5\ncx: 318.6\ncy: 255.3\nwidth: 640\nheight: 480\ndepth_scale: 5000\n"


def folder_scene(root: Path, intrinsics: str = INTRINSICS) -> Path:
    """A `dataset=folder` scene (color/, depth/, intrinsics.yaml) from the tiny TUM copy."""
    tum = tiny_tum(root.parent / f"{root.name}_tum")
    (root / "color").mkdir(parents=True)
    (root / "depth").mkdir()
    for rgb, depth in zip(sorted((tum / "rgb").iterdir()), sorted((tum / "depth").iterdir())):
        shutil.copy(rgb, root / "color" / rgb.name)
        shutil.copy(depth, root / "depth" / rgb.name)
    (root / "intrinsics.yaml").write_text(intrinsics)
    return root


def tum_with(damage: Callable[[Path], None]) -> Callable[[Path], Path]:
    def make(root: Path) -> Path:
        damage(tiny_tum(root))
        return root

    return make


def folder_with(intrinsics: str = INTRINSICS, damage: Callable[[Path], None] = lambda root: None):
    def make(root: Path) -> Path:
        damage(folder_scene(root, intrinsics))
        return root

    return make


def truncate_depth(root: Path, index: int = 5) -> None:
    victim = sorted((root / "depth").iterdir())[index]
    victim.write_bytes(victim.read_bytes()[:200])


def duplicate_timestamp(root: Path) -> None:
    lines = (root / "rgb.txt").read_text().splitlines()
    (root / "rgb.txt").write_text("\n".join([*lines, lines[-1]]) + "\n")


def non_utf8_name(root: Path) -> None:
    """A colour image whose file name is not UTF-8 (a Latin-1 byte), without its depth image."""
    first = sorted((root / "color").iterdir())[0]
    shutil.copy(first, root / "color" / "caf\udce9.png")  # the file system gets the byte 0xe9


# --- plugins a case installs (a tmp dist-info with entry points, on sys.path); `still` is
# support.plugins' FAKE_TRACKER (the first pose for every frame, raising at `fail_at`) ---------

#: A config field type Hydra cannot hold (a numpy array), declared as a type, not only a value.
ARRAY_CONFIG = """
    from dataclasses import dataclass, field
    import numpy as np
    from slamkit.plugin import PluginSpec, hookimpl
    from slamkit.roles import PluginConfig, Tracker

    @dataclass
    class ArrayConfig(PluginConfig):
        weights: np.ndarray = field(default_factory=lambda: np.ones(3))

    class ArrayTracker(Tracker):
        def __init__(self, cfg, context=None):
            self.cfg = cfg
        def track(self, frame):
            raise NotImplementedError

    @hookimpl
    def slamkit_plugins():
        return [PluginSpec("array_weights", ArrayTracker, ArrayConfig)]
"""

#: Hydra can hold these fields, though they are unusual: an enum whose values are not strings, a
#: union of scalars, bytes, an untyped tuple.
UNUSUAL_CONFIG = """
    import enum
    from dataclasses import dataclass
    from typing import Any, Union
    from slamkit.plugin import PluginSpec, hookimpl
    from slamkit.roles import PluginConfig, Tracker

    class Level(enum.Enum):
        low = 1.5
        high = 2

    @dataclass
    class UnusualConfig(PluginConfig):
        '''level: how hard it tries.'''
        level: Level = Level.low
        either: Union[int, str] = 1
        raw: bytes = b"x"
        pair: tuple = (1.0, 2.0)

    class UnusualTracker(Tracker):
        def __init__(self, cfg, context=None):
            self.cfg = cfg
        def track(self, frame):
            raise NotImplementedError

    @hookimpl
    def slamkit_plugins():
        return [PluginSpec("unusual", UnusualTracker, UnusualConfig)]
"""

#: Its defaults fail its own validate: reported when loaded, not when a run selects it.
BAD_DEFAULTS = """
    from dataclasses import dataclass
    from slamkit.plugin import PluginSpec, hookimpl
    from slamkit.roles import PluginConfig, Tracker, require

    @dataclass
    class BadDefaultsConfig(PluginConfig):
        radius: float = -1.0
        def validate(self):
            require(self.radius > 0, "tracker.radius", "> 0 metres", self.radius)

    class BadDefaultsTracker(Tracker):
        def __init__(self, cfg, context=None):
            self.cfg = cfg
        def track(self, frame):
            raise NotImplementedError

    @hookimpl
    def slamkit_plugins():
        return [PluginSpec("bad_defaults", BadDefaultsTracker, BadDefaultsConfig)]
"""

#: A loop closure that takes `seconds` per keyframe and finds nothing: in real time its backlog
#: grows with every keyframe (what a stop signal must not wait for).
SLOW_LOOP_CLOSURE = """
    import time
    from dataclasses import dataclass
    from slamkit.plugin import PluginSpec, hookimpl
    from slamkit.roles import PluginConfig
    from slamkit.roles.loop_closure import LoopClosure, LoopDecision

    @dataclass
    class SlowConfig(PluginConfig):
        seconds: float = 1.0

    class SlowLoopClosure(LoopClosure):
        def __init__(self, cfg, context=None):
            self.cfg, self.pending = cfg, 0
        def add_keyframe(self, keyframe):
            self.pending += 1
        def detect_and_optimise(self):
            time.sleep(self.cfg.seconds * self.pending)
            self.pending = 0
            return LoopDecision()
        def state_dict(self):
            return {}
        def load_state_dict(self, state):
            pass

    @hookimpl
    def slamkit_plugins():
        return [PluginSpec("slow", SlowLoopClosure, SlowConfig)]
"""

PLUGINS = {"still": FAKE_TRACKER, "array": ARRAY_CONFIG, "broken": "raise ImportError('needs libfoo')\n",
           "unusual": UNUSUAL_CONFIG, "bad_defaults": BAD_DEFAULTS, "slow": SLOW_LOOP_CLOSURE}


def install(*names: str) -> Callable[[Path], None]:
    """A maker that installs the named `PLUGINS` as one distribution on sys.path."""

    def make(root: Path) -> None:
        site = make_plugin_dist(root / "site", "slamkit-fault-plugins", {f"fault_{n}": PLUGINS[n] for n in names},
                                {n: f"fault_{n}" for n in names})
        sys.path.insert(0, str(site))

    return make


# --- inputs of issue 36's cases ------------------------------------------------------------------

def float_depth_in_metres(root: Path) -> None:
    """Every depth image of a TUM folder rewritten as a float32 TIFF in metres (depth.txt names
    the new files): a unit that is not the folder's 16-bit raw one, but unambiguous."""
    import numpy as np
    from PIL import Image

    _rewrite_depth(root, ".tiff", lambda raw: Image.fromarray((raw / 5000.0).astype(np.float32), mode="F"))


def uint16_cast_metres(root: Path) -> None:
    """Every depth image of a TUM folder rewritten as 16-bit PNG holding whole metres (what
    `depth_m.astype(np.uint16)` writes): at the folder's 5000 units per metre, 0.2 mm steps."""
    import numpy as np
    from PIL import Image

    _rewrite_depth(root, ".png", lambda raw: Image.fromarray(np.round(raw / 5000.0).astype(np.uint16)))


def _rewrite_depth(root: Path, suffix: str, convert) -> None:
    import numpy as np
    from PIL import Image

    lines = []
    for line in (root / "depth.txt").read_text().splitlines():
        stamp, rel = line.split()
        src = root / rel
        raw = np.asarray(Image.open(src), dtype=np.float64)
        src.unlink()
        rel = str(Path(rel).with_suffix(suffix))
        convert(raw).save(root / rel)
        lines.append(f"{stamp} {rel}")
    (root / "depth.txt").write_text("\n".join(lines) + "\n")


def drop_frame(index: int) -> Callable[[Path], None]:
    """Remove frame `index` from a TUM folder's rgb.txt (the frame list changes)."""

    def damage(root: Path) -> None:
        lines = (root / "rgb.txt").read_text().splitlines()
        del lines[index]
        (root / "rgb.txt").write_text("\n".join(lines) + "\n")

    return damage


def fifo_bag(root: Path) -> Path:
    """A FIFO (named pipe) called bag.mcap: opening it for reading blocks until a writer comes."""
    import os

    root.mkdir(parents=True)
    os.mkfifo(root / "bag.mcap")
    return root


def flip_bytes(path: Path, fraction: float = 0.5, count: int = 64) -> None:
    """Invert `count` bytes of `path` from `fraction` of its length on (a damaged file of the same size)."""
    data = bytearray(path.read_bytes())
    start = int(len(data) * fraction)
    for i in range(start, min(start + count, len(data))):
        data[i] ^= 0xFF
    path.write_bytes(bytes(data))


def truncate_half(path: Path) -> None:
    """`truncate -s 50% path`."""
    import os

    os.truncate(path, path.stat().st_size // 2)


def make_read_only(folder: Path) -> Callable[[], None]:
    """Make `folder` read-only for this process (chmod; as root, which chmod does not stop, the
    immutable attribute); returns the undo. Skips the test where neither takes effect."""
    import os
    import subprocess

    import pytest

    folder.chmod(0o555)
    if not os.access(folder, os.W_OK):
        return lambda: folder.chmod(0o755)
    if subprocess.run(["chattr", "+i", str(folder)], capture_output=True).returncode == 0:
        return lambda: (subprocess.run(["chattr", "-i", str(folder)]), folder.chmod(0o755))
    folder.chmod(0o755)
    pytest.skip("cannot make a folder read-only here (root without chattr)")


# --- inputs of issue 45's cases ------------------------------------------------------------------

def truncated_download(root: Path, name: str = "rgbd_dataset_freiburg1_xyz") -> Path:
    """ROOT/NAME.tgz: the first half of a TUM archive (the tiny TUM copy), as a server that cut
    it short leaves it, complete in size as far as the transfer knew."""
    import io
    import tarfile

    tum = tiny_tum(root.parent / f"{root.name}_tum")
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:
        tar.add(tum, arcname=name)
    root.mkdir(parents=True)
    archive = root / f"{name}.tgz"
    archive.write_bytes(buffer.getvalue()[: len(buffer.getvalue()) // 2])
    return archive


def data_root_with_an_incomplete_scene(root: Path) -> Path:
    """A `data_root` for `+experiment=paper_tum`: fr1/desk complete (the tiny TUM copy), fr2/xyz
    with its rgb.txt alone (a download cut before its depth list), fr3/office absent."""
    tiny_tum(root / "rgbd_dataset_freiburg1_desk")
    (root / "rgbd_dataset_freiburg2_xyz").mkdir()
    shutil.copy(root / "rgbd_dataset_freiburg1_desk" / "rgb.txt", root / "rgbd_dataset_freiburg2_xyz" / "rgb.txt")
    return root
