"""The sequences `slamkit-data download` fetches: any TUM RGB-D sequence (one .tgz each, from
the TUM computer vision group's server) and the eight Replica scenes GS-ICP SLAM evaluates on
(the NICE-SLAM rendering, one Replica.zip), with where their archives are, where they extract to
under a root folder, and what each extracted folder must hold for the dataset plugins
(`dataset=tum` / `dataset=replica`) to read it.

Under ROOT: `rgbd_dataset_freiburgN_NAME/` (rgb.txt, depth.txt, groundtruth.txt, rgb/, depth/),
and `Replica/` with `cam_params.json` and one folder per scene (`room0` ... `office4`: results/,
traj.txt), exactly as the archives hold them.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from slamkit.errors import SlamkitError

#: Where the archives are by default (a base URL given instead replaces both).
TUM_BASE_URL = "https://cvg.cit.tum.de/rgbd/dataset"
REPLICA_BASE_URL = "https://cvg-data.inf.ethz.ch/nice-slam/data"
#: Microsoft Research's 7-Scenes: one SCENE.zip per scene, holding SCENE/seq-NN.zip per sequence.
SEVENSCENES_BASE_URL = "https://download.microsoft.com/download/2/8/5/28564B23-0828-408F-8631-23B1EFF1DAC8"
#: The Replica scenes of NICE-SLAM's archive (paper Tables 1, 3, 6-8).
REPLICA_SCENES = ("room0", "room1", "room2", "office0", "office1", "office2", "office3", "office4")
#: The paper's TUM sequences under the names its tables use (Tables 2, 4, 5).
PAPER_TUM = {
    "fr1/desk": "rgbd_dataset_freiburg1_desk",
    "fr2/xyz": "rgbd_dataset_freiburg2_xyz",
    "fr3/office": "rgbd_dataset_freiburg3_long_office_household",
}
_TUM_NAME = re.compile(r"rgbd_dataset_freiburg([123])_[a-z0-9_]+")
_TUM_SHORT = re.compile(r"(?:fr|freiburg)([123])[/_]([a-z0-9_]+)")


class UnknownSequence(SlamkitError):
    """A name that is not in the catalogue (exit status 2)."""


@dataclass(frozen=True)
class Archive:
    """One downloadable archive. name: the catalogue's name for it. url_path: its path under
    the base URL. default_base_url: where it is unless a base URL is given. dataset: the
    plugin that reads what it holds. folders: the dataset folders it extracts to, relative to
    the root. required: paths each of those folders must hold. shared: paths relative to the
    root that must exist as well."""

    name: str
    url_path: str
    default_base_url: str
    dataset: str
    folders: tuple[str, ...]
    required: tuple[str, ...]
    shared: tuple[str, ...] = ()

    @property
    def file_name(self) -> str:
        return self.url_path.rsplit("/", 1)[-1]

    def url(self, base_url: str | None = None) -> str:
        return f"{(base_url or self.default_base_url).rstrip('/')}/{self.url_path}"

    def missing(self, root: Path) -> list[Path]:
        """What the extracted archive should have made under `root` and is not there."""
        wanted = [root / s for s in self.shared]
        wanted += [root / folder / r for folder in self.folders for r in self.required]
        return [p for p in wanted if not p.exists()]


def tum(sequence: str) -> Archive:
    """A TUM RGB-D sequence, `rgbd_dataset_freiburgN_NAME`."""
    n = _TUM_NAME.fullmatch(sequence).group(1)
    return Archive(sequence, f"freiburg{n}/{sequence}.tgz", TUM_BASE_URL, "tum", (sequence,),
                   ("rgb.txt", "depth.txt", "rgb", "depth"))


REPLICA = Archive("replica", "Replica.zip", REPLICA_BASE_URL, "replica",
                  tuple(f"Replica/{s}" for s in REPLICA_SCENES), ("results", "traj.txt"), ("Replica/cam_params.json",))


def sevenscenes(scene: str) -> Archive:
    """Microsoft's 7-Scenes archive of one scene (`redkitchen`, ...): SCENE/seq-NN.zip inside,
    each holding seq-NN/frame-%06d.color.png, .depth.png and .pose.txt. Its sequences are nested
    zips, so only `slamkit-data download test-data` reads it (the redkitchen excerpt)."""
    return Archive(scene, f"{scene}.zip", SEVENSCENES_BASE_URL, "sevenscenes", (scene,), ("seq-01.zip",))


def known() -> str:
    """The names `resolve` takes, in one line."""
    return ("replica (NICE-SLAM's Replica.zip: " + ", ".join(REPLICA_SCENES) + "), "
            + ", ".join(f"{short} ({full})" for short, full in PAPER_TUM.items())
            + ", any TUM RGB-D sequence as rgbd_dataset_freiburgN_NAME or frN/NAME (e.g. fr1/xyz), "
            + "or paper (all of the paper's: replica, " + ", ".join(PAPER_TUM) + ")")


def resolve(name: str) -> list[Archive]:
    """The archives for one name of the catalogue (see `known()`); UnknownSequence naming the
    known ones otherwise."""
    key = name.strip().lower()
    if key == "replica":
        return [REPLICA]
    if key == "paper":
        return [REPLICA, *(tum(full) for full in PAPER_TUM.values())]
    if key in PAPER_TUM:
        return [tum(PAPER_TUM[key])]
    if _TUM_NAME.fullmatch(key):
        return [tum(key)]
    short = _TUM_SHORT.fullmatch(key)
    if short:
        return [tum(f"rgbd_dataset_freiburg{short.group(1)}_{short.group(2)}")]
    raise UnknownSequence(f"unknown sequence {name!r}: known are {known()}")
