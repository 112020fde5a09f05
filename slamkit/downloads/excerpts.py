"""The test data: three short excerpts of public RGB-D sequences that the data-driven tests and
the benchmarks read (`slamkit-data download test-data`), each cut from its publisher's archive
into the folder name and layout the tests expect:

- `tum_fr1_rpy_first150/`: TUM RGB-D fr1/rpy (`rgbd_dataset_freiburg1_rpy.tgz`), the first 150
  colour frames of `rgb.txt`, the depth frames whose timestamps fall in their time window (half
  a colour frame interval either side), `rgb.txt` / `depth.txt` as the archive's header plus the
  selected lines, and the full `groundtruth.txt` and `accelerometer.txt`: all bytes as in the
  archive. TUM layout; poses camera-to-world, metres, depth = value / 5000 m.
- `replica_room0_first20/`: Replica room0 frames 0-19 from NICE-SLAM's `Replica.zip`:
  `results/frame%06d.jpg` and `depth%06d.png`, the first 20 lines of `traj.txt` (row-major 4x4
  camera-to-world, metres) and `cam_params.json` (one level up in the archive), bytes unchanged.
- `7scenes_redkitchen_300to999/`: Microsoft 7-Scenes redkitchen `seq-01` frames 300-999 from
  `redkitchen.zip` (which holds `redkitchen/seq-01.zip`): `frame-%06d.color.png` (640x480),
  `.depth.png` (16-bit millimetres; 0 and 65535 invalid) and `.pose.txt` (4x4 camera-to-world,
  metres) with the original frame numbers and bytes, and `camera-intrinsics.txt`, the 7-Scenes
  Kinect K (fx = fy = 585, cx 320, cy 240 pixels) as a 3x3 matrix.

Each cut goes into a staging folder beside its destination and is renamed into place when
whole, with a README.txt (source, archive SHA-256, what was cut) and a MANIFEST.sha256 of its
files: a folder under its own name is a complete excerpt. An archive that is not the expected
one (a member missing, too few frames) is a one-line DataError naming the archive and what was
expected; one that does not read back whole is a DamagedArchive.
"""

from __future__ import annotations

import hashlib
import io
import os
import re
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slamkit.cache import cache_dir
from slamkit.downloads import catalogue
from slamkit.downloads.archives import open_zip, tar_files, zip_member
from slamkit.errors import DataError

#: The name `slamkit-data download` takes for all three excerpts (NAME/KEY for one).
NAME = "test-data"
#: TUM: how many colour frames from the start of rgb.txt.
TUM_FRAMES = 150
TUM_SEQUENCE = "rgbd_dataset_freiburg1_rpy"
#: Replica: how many frames from frame 0 of room0.
REPLICA_FRAMES = 20
REPLICA_SCENE = "room0"
#: 7-Scenes: which scene, sequence and frames (inclusive).
SEVENSCENES_SCENE, SEVENSCENES_SEQUENCE = "redkitchen", "seq-01"
SEVENSCENES_FIRST, SEVENSCENES_LAST = 300, 999
#: 7-Scenes' Kinect intrinsics (pixels), as the project page gives them.
SEVENSCENES_K = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])


def default_root() -> Path:
    """Where `slamkit-data download test-data` puts the excerpts without --root, and where the
    tests look after $SLAMKIT_DATA and a shared folder beside the repository: $SLAMKIT_DATA when
    set, else `test-data` in the project cache (`$SLAMKIT_CACHE`, which the Makefile sets to
    `.cache/slamkit` in the project, else `~/.cache/slamkit`). An absolute path; not created."""
    env = os.environ.get("SLAMKIT_DATA")
    return Path(env).expanduser().absolute() if env else cache_dir("test-data")


def find_test_data(project: Path | None = None) -> Path:
    """Where the tests read the test data: $SLAMKIT_DATA when set; else the first folder that
    exists of `shared/data` beside the `project` checkout (the developers' copy), default_root(),
    and `project`/.cache/slamkit/test-data (where `make test-data` puts it, for a test run outside
    make); else default_root() (where the download would put it)."""
    env = os.environ.get("SLAMKIT_DATA")
    if env:
        return Path(env).expanduser()
    candidates = [default_root()]
    if project is not None:
        candidates = [project.parent / "shared" / "data", *candidates, project / ".cache" / "slamkit" / "test-data"]
    return next((c for c in candidates if c.is_dir()), default_root())


@dataclass(frozen=True)
class Excerpt:
    """One excerpt: `key` (its short name: test-data/KEY), the `folder` it makes under the root,
    the `archive` it is cut from, one line saying `what` it is, and `cut(archive, into)`, which
    writes its files into the empty folder `into` from the archive (a path, or with `by_range` a
    seekable file that reads the archive where it is: a zip whose few members can be read
    without downloading it whole)."""

    key: str
    folder: str
    archive: catalogue.Archive
    what: str
    cut: Callable[[Path, Path], None]
    by_range: bool = False


def _write(into: Path, rel: str, data: bytes) -> None:
    path = into / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)


# ------------------------------------------------------------------------------------ TUM
_TUM_TEXTS = ("rgb.txt", "depth.txt", "groundtruth.txt", "accelerometer.txt")


def _inside(name: str) -> str:
    """A member's path below the archive's top folder (`rgbd_dataset_.../rgb.txt` -> `rgb.txt`)."""
    return name.split("/", 1)[1] if "/" in name else name


def _tum_list(archive: Path, name: str, data: bytes) -> tuple[list[str], list[tuple[float, str, str]]]:
    """(header lines, [(timestamp s, file, line)]) of a TUM rgb.txt / depth.txt, lines as in the file."""
    header, entries = [], []
    for number, line in enumerate(data.decode("utf-8", "replace").splitlines(keepends=True), 1):
        text = line.strip()
        if not text or text.startswith("#"):
            if not entries:
                header.append(line)
            continue
        fields = text.split()
        try:
            entries.append((float(fields[0]), fields[1], line))
        except (ValueError, IndexError):
            raise DataError(f"{archive}: {name} line {number} is {text[:60]!r}, expected 'timestamp file'") from None
    return header, entries


def cut_tum(archive: Path, into: Path, frames: int = TUM_FRAMES) -> None:
    """The TUM excerpt (module docstring) from a TUM sequence .tgz: two streaming passes, the
    lists first, then the selected images."""
    texts = {_inside(n): data for n, data in tar_files(archive, lambda n: _inside(n) in _TUM_TEXTS)}
    for name in _TUM_TEXTS[:3]:
        if name not in texts:
            raise DataError(f"{archive}: no {name} in the archive (expected a TUM RGB-D sequence, "
                            f"{TUM_SEQUENCE}.tgz)")
    rgb_header, rgb = _tum_list(archive, "rgb.txt", texts["rgb.txt"])
    depth_header, depth = _tum_list(archive, "depth.txt", texts["depth.txt"])
    if len(rgb) < frames:
        raise DataError(f"{archive}: rgb.txt lists {len(rgb)} colour frames, expected at least {frames} "
                        f"({TUM_SEQUENCE}.tgz lists 723)")
    rgb = rgb[:frames]
    half = float(np.median(np.diff([t for t, _, _ in rgb]))) / 2 if frames > 1 else 0.02
    start, end = rgb[0][0] - half, rgb[-1][0] + half
    depth = [d for d in depth if start <= d[0] <= end]
    if not depth:
        raise DataError(f"{archive}: depth.txt has no depth frame between {start:.6f} and {end:.6f} s "
                        f"(the time window of the first {frames} colour frames)")
    _write(into, "rgb.txt", "".join(rgb_header + [line for _, _, line in rgb]).encode())
    _write(into, "depth.txt", "".join(depth_header + [line for _, _, line in depth]).encode())
    for name in _TUM_TEXTS[2:]:
        if name in texts:
            _write(into, name, texts[name])
    images = {f for _, f, _ in rgb + depth}
    for name, data in tar_files(archive, lambda n: _inside(n) in images):
        _write(into, _inside(name), data)
        images.discard(_inside(name))
    if images:
        raise DataError(f"{archive}: {sorted(images)[0]} is listed but not in the archive "
                        f"({len(images)} listed image(s) missing)")


# -------------------------------------------------------------------------------- Replica
def _members(z, archive: Path, names: list[str], expected: str) -> None:
    listed = set(z.namelist())
    for name in names:
        if name not in listed:
            raise DataError(f"{archive}: no member {name!r} (expected {expected})")


def cut_replica(archive: Path, into: Path, frames: int = REPLICA_FRAMES) -> None:
    """The Replica excerpt (module docstring) from NICE-SLAM's Replica.zip, read member by member."""
    scene = f"Replica/{REPLICA_SCENE}"
    images = [f"results/{kind}{i:06d}.{ext}" for i in range(frames)
              for kind, ext in (("frame", "jpg"), ("depth", "png"))]
    with open_zip(archive) as z:
        _members(z, archive, ["Replica/cam_params.json", f"{scene}/traj.txt"] + [f"{scene}/{rel}" for rel in images],
                 f"NICE-SLAM's Replica.zip with {scene}/results/ frames 0-{frames - 1}")
        lines = zip_member(z, f"{scene}/traj.txt", archive).splitlines(keepends=True)
        if len(lines) < frames:
            raise DataError(f"{archive}: {scene}/traj.txt has {len(lines)} lines, expected one 4x4 pose per frame "
                            f"(at least {frames})")
        _write(into, "traj.txt", b"".join(lines[:frames]))
        _write(into, "cam_params.json", zip_member(z, "Replica/cam_params.json", archive))
        for rel in images:
            _write(into, rel, zip_member(z, f"{scene}/{rel}", archive))


# -------------------------------------------------------------------------------- 7-Scenes
def _by_file_name(z) -> dict[str, str]:
    """{file name: member name} of a zip's files (the first of each name)."""
    names = {}
    for name in z.namelist():
        if not name.endswith("/"):
            names.setdefault(name.rsplit("/", 1)[-1], name)
    return names


def cut_sevenscenes(archive: Path, into: Path, first: int = SEVENSCENES_FIRST, last: int = SEVENSCENES_LAST) -> None:
    """The 7-Scenes excerpt (module docstring) from Microsoft's redkitchen.zip: its seq-01.zip is
    copied out beside `into`'s files (removed after), then the frames read from it."""
    inner_name = f"{SEVENSCENES_SEQUENCE}.zip"
    with open_zip(archive) as z:
        found = _by_file_name(z).get(inner_name)
        if found is None:
            raise DataError(f"{archive}: no {inner_name} in the archive (expected Microsoft's 7-Scenes "
                            f"{SEVENSCENES_SCENE}.zip, which holds {SEVENSCENES_SCENE}/{inner_name})")
        inner = into / f".{inner_name}"
        zip_member(z, found, archive, dest=inner)
    try:
        label = Path(f"{archive}!{found}")
        with open_zip(inner) as z:
            members = _by_file_name(z)
            for i in range(first, last + 1):
                for suffix in ("color.png", "depth.png", "pose.txt"):
                    name = f"frame-{i:06d}.{suffix}"
                    if name not in members:
                        raise DataError(f"{label}: no {name} (expected frames {first}-{last} of "
                                        f"{SEVENSCENES_SCENE}/{SEVENSCENES_SEQUENCE})")
                    _write(into, name, zip_member(z, members[name], label))
    finally:
        inner.unlink(missing_ok=True)
    buf = io.StringIO()
    np.savetxt(buf, SEVENSCENES_K)
    _write(into, "camera-intrinsics.txt", buf.getvalue().encode())


EXCERPTS = (
    Excerpt("tum", "tum_fr1_rpy_first150", catalogue.tum(TUM_SEQUENCE),
            f"TUM RGB-D fr1/rpy, the first {TUM_FRAMES} colour frames with their depth, full groundtruth.txt", cut_tum),
    Excerpt("7scenes", "7scenes_redkitchen_300to999", catalogue.sevenscenes(SEVENSCENES_SCENE),
            f"Microsoft 7-Scenes {SEVENSCENES_SCENE} {SEVENSCENES_SEQUENCE}, frames {SEVENSCENES_FIRST}-"
            f"{SEVENSCENES_LAST}", cut_sevenscenes),
    Excerpt("replica", "replica_room0_first20", catalogue.REPLICA,
            f"Replica {REPLICA_SCENE} (NICE-SLAM rendering), frames 0-{REPLICA_FRAMES - 1}", cut_replica,
            by_range=True),
)


def is_test_data(name: str) -> bool:
    return re.fullmatch(rf"{NAME}(/.*)?", name.strip().lower()) is not None


def resolve(name: str) -> list[Excerpt]:
    """`test-data`: all three excerpts (the smallest archive first); `test-data/KEY` (tum,
    replica, 7scenes): one. UnknownSequence naming them otherwise."""
    key = name.strip().lower()
    if key == NAME:
        return list(EXCERPTS)
    for excerpt in EXCERPTS:
        if key == f"{NAME}/{excerpt.key}":
            return [excerpt]
    raise catalogue.UnknownSequence(f"unknown test data {name!r}: known are {NAME} (all three) or "
                                    + ", ".join(f"{NAME}/{e.key}" for e in EXCERPTS))


def finish(excerpt: Excerpt, into: Path, url: str, how: str) -> None:
    """Write README.txt (what, from where, `how`: e.g. the archive's SHA-256) and MANIFEST.sha256
    (`sha256  ./path` per file, sorted) into the cut excerpt `into`."""
    _write(into, "README.txt", (
        f"{excerpt.what}\n"
        f"Cut by `slamkit-data download {NAME}/{excerpt.key}` from {url}\n"
        f"({how}); see slamkit's docs/datasets.md, 'The test data', for the layout,\n"
        f"the source's licence and how to cite it. For tests and benchmarks only: do not redistribute.\n").encode())
    lines = []
    for path in sorted(p for p in into.rglob("*") if p.is_file()):
        lines.append(f"{hashlib.sha256(path.read_bytes()).hexdigest()}  ./{path.relative_to(into).as_posix()}\n")
    _write(into, "MANIFEST.sha256", "".join(lines).encode())


def staging(root: Path, excerpt: Excerpt) -> Path:
    """An empty folder beside the excerpt's destination to cut it into."""
    path = root / f".{excerpt.folder}.cutting"
    shutil.rmtree(path, ignore_errors=True)
    path.mkdir(parents=True)
    return path
