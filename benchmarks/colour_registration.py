"""Is a dataset's colour registered to its depth? Where colour edges line up with the depth's
occlusion edges, measured on the frames themselves.

A depth pixel p is given the colour at c + s (p - c) + t (c: the image centre; s: a scale, t: a
shift in pixels). For each (s, t) on a grid, the mean colour-gradient magnitude at the depth's
occlusion edges (a 4-neighbour more than 5 % nearer or farther, and the pixel next to it: the
synthetic sensor's `edges`), over the image's mean, is
summed over frames spread along the sequence. Registered colour peaks at s = 1, t = 0; colour
from a second camera with another focal length peaks at the ratio of the two (7-Scenes' Kinect:
its colour camera's 525 px over its depth camera's 585 px, 0.90) and at the cameras' offset.
Printed and written: the best (s, t), its score over the identity's (1: the identity is the
best), and the best score per scale. `DatasetTuning.colour_registered` is what a dataset says;
this is what its frames say.

    python benchmarks/colour_registration.py                 # tum, replica, 7scenes, synthetic
    python benchmarks/colour_registration.py --sequences 7scenes --frames 20

Writes JSON (--out, default benchmarks/results/colour_registration.json).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

from slamkit.cli.bench import markdown_table
from slamkit.registry.compose import compose_run
from slamkit.registry.discovery import default_registry
from slamkit_plugins.datasets.synthetic.sensor import edges as depth_edges

sys.path.insert(0, str(Path(__file__).resolve().parent))
from loop_closure import SEQUENCES  # noqa: E402  (the offline benchmark's)

#: the built-in scene with exact depth (the structured-light model drops depth at occlusion edges)
SEQUENCES = {**SEQUENCES, "synthetic": ["dataset=synthetic"]}

#: an occlusion edge is a jump between 4-neighbours of more than this fraction of the nearer depth
EDGE_JUMP_FRACTION = 0.05
#: the grid searched: scales, and shifts in pixels along x and y.
SCALES = np.round(np.arange(0.84, 1.1601, 0.02), 3)
SHIFTS = np.arange(-20, 21, 2)
#: a frame with fewer occlusion-edge pixels says nothing and is skipped.
MIN_EDGE_PIXELS = 200


def alignment_scores(rgb: np.ndarray, depth: np.ndarray) -> np.ndarray | None:
    """(scales, shifts y, shifts x): the mean colour-gradient magnitude at the depth's occlusion
    edges mapped by each (s, t), over the image's mean; None for a frame with too few edges."""
    grey = rgb.astype(np.float32).mean(axis=2)
    gy, gx = np.gradient(grey)
    gradient = np.hypot(gx, gy)
    gradient /= gradient.mean()
    # band 1: both pixels of each jump, so that neither side biases the shift
    rows, cols = np.nonzero(depth_edges(depth.astype(np.float32), EDGE_JUMP_FRACTION, 1))
    if len(rows) < MIN_EDGE_PIXELS:
        return None
    h, w = gradient.shape
    scores = np.zeros((len(SCALES), len(SHIFTS), len(SHIFTS)))
    for i, s in enumerate(SCALES):
        u0, v0 = w / 2 + s * (cols - w / 2), h / 2 + s * (rows - h / 2)
        for j, ty in enumerate(SHIFTS):
            v = np.rint(v0 + ty).astype(int)
            for k, tx in enumerate(SHIFTS):
                u = np.rint(u0 + tx).astype(int)
                inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
                scores[i, j, k] = gradient[v[inside], u[inside]].mean() if inside.any() else 0.0
    return scores


def measure(name: str, frames: int) -> dict:
    cfg, names = compose_run(SEQUENCES[name])
    dataset = default_registry().create("dataset", names["dataset"], cfg.dataset)
    total, used = np.zeros((len(SCALES), len(SHIFTS), len(SHIFTS))), 0
    for index in np.unique(np.linspace(0, len(dataset) - 1, min(frames, len(dataset))).astype(int)):
        frame = dataset[int(index)]
        scores = alignment_scores(np.asarray(frame.rgb), np.asarray(frame.depth))
        if scores is not None:
            total += scores
            used += 1
    if not used:
        raise SystemExit(f"{name}: no frame has {MIN_EDGE_PIXELS} occlusion-edge pixels with valid depth either side")
    best = np.unravel_index(np.argmax(total), total.shape)
    identity = total[int(np.argmin(np.abs(SCALES - 1.0))), len(SHIFTS) // 2, len(SHIFTS) // 2]
    return {"sequence": name, "frames": used, "colour_registered": bool(dataset.tuning.colour_registered),
            "best_scale": float(SCALES[best[0]]), "best_shift_x_px": int(SHIFTS[best[2]]),
            "best_shift_y_px": int(SHIFTS[best[1]]), "best_over_identity": float(total[best] / identity),
            "best_per_scale": {f"{s:.2f}": float(total[i].max() / identity) for i, s in enumerate(SCALES)}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequences", default="tum,replica,7scenes,synthetic")
    parser.add_argument("--frames", type=int, default=40, help="frames per sequence, spread along it")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/colour_registration.json"))
    args = parser.parse_args()
    records = [measure(name, args.frames) for name in args.sequences.split(",")]
    header = ["sequence", "frames", "colour_registered", "best_scale", "best_shift_x_px", "best_shift_y_px",
              "best_over_identity"]
    print(markdown_table([header, *([round(r[k], 3) if isinstance(r[k], float) else r[k] for k in header]
                                    for r in records)]))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": platform.platform(), "when": time.strftime("%Y-%m-%d %H:%M"),
                                    "command": "python benchmarks/colour_registration.py " + " ".join(sys.argv[1:]),
                                    "records": records}, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
