"""Small dataset folders built for a test: a TUM folder holding the first frames of the shared
sequence, a `dataset=folder` scene made from TUM frames, a generated 7-Scenes sequence."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
from PIL import Image

from slamkit.geometry.transforms import make_pose, so3_exp

from support.data import TUM, require_data

#: The frames `tiny_tum` copies unless told.
TINY_TUM_FRAMES = 8


def tiny_tum(root: Path, frames: int = TINY_TUM_FRAMES) -> Path:
    """A TUM folder holding the first `frames` frames of the shared sequence (files copied)."""
    src = require_data(TUM)
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    for name in ("rgb", "depth"):
        lines = [ln for ln in (src / f"{name}.txt").read_text().splitlines() if not ln.startswith("#")][:frames]
        (root / f"{name}.txt").write_text("\n".join(lines) + "\n")
        for line in lines:
            rel = line.split()[1]
            shutil.copy(src / rel, root / rel)
    shutil.copy(src / "groundtruth.txt", root / "groundtruth.txt")
    return root


#: The frames of a `make_folder` scene, and its intrinsics file (TUM fr1's camera).
FOLDER_FRAMES = 10
FOLDER_INTRINSICS = ("fx: 517.3\nfy: 516.5\ncx: 318.6\ncy: 255.3\nwidth: 640\nheight: 480\ndepth_scale: 5000\n"
                     "depth_trunc: 3.0\n")


def make_folder(root: Path, tum, stems: list[str] | None = None) -> Path:
    """color/ + depth/ (frame i of the TUMDataset `tum` saved under stems[i], default the colour
    timestamp), intrinsics.yaml and the sequence's full groundtruth.txt (TUM format) as gt.txt."""
    stems = stems or [p.stem for p in tum.rgb_files[:FOLDER_FRAMES]]
    (root / "color").mkdir(parents=True)
    (root / "depth").mkdir()
    for stem, rgb, depth in zip(stems, tum.rgb_files, tum.depth_files):
        shutil.copy(rgb, root / "color" / f"{stem}.png")
        shutil.copy(depth, root / "depth" / f"{stem}.png")
    (root / "intrinsics.yaml").write_text(FOLDER_INTRINSICS)
    shutil.copy(tum.root / "groundtruth.txt", root / "gt.txt")
    return root


def save_depth(path: Path, raw: np.ndarray) -> None:
    """A 16-bit depth PNG of the raw values."""
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(raw.astype(np.uint16)).save(path)


def make_sevenscenes(root: Path, n: int = 3, intrinsics: bool = True, first: int = 0) -> tuple[Path, np.ndarray]:
    """A 7-Scenes sequence folder of `n` 64x48 frames at random poses (returned, camera-to-world),
    numbered from `first` (the shared data's start at frame-000300)."""
    root.mkdir(parents=True)
    rng = np.random.default_rng(0)
    poses = np.stack([make_pose(so3_exp(rng.normal(size=3)), rng.normal(size=3)) for _ in range(n)])
    for k in range(n):
        i = first + k
        ext = "png" if i % 2 else "jpg"
        Image.fromarray(np.zeros((48, 64, 3), np.uint8)).save(root / f"frame-{i:06d}.color.{ext}")
        raw = np.full((48, 64), 1500, np.uint16)
        raw[0, 0], raw[0, 1] = 0, 65535
        save_depth(root / f"frame-{i:06d}.depth.png", raw)
        np.savetxt(root / f"frame-{i:06d}.pose.txt", poses[k], delimiter="\t")
    if intrinsics:
        np.savetxt(root / "camera-intrinsics.txt", [[60.0, 0, 31.5], [0, 61.0, 23.5], [0, 0, 1]])
    return root, poses
