"""What tells a localised frame from a wrong answer: the three figures `mode=localize` judges a
pose by (inlier fraction, surface agreement, colour correlation: slamkit.run.localization), per
frame, for frames of the map's own scene and for frames of another scene.

Maps are made with the slamkit command (tracking only, `mapper=none`, the default G-ICP tracker)
from the shared data; each case localises frames in one map as `mode=localize` does, with the
default minimums and `localize.attempts=1` (a frame not localised is registered globally again),
and prints per case how many frames were localised and each figure's minimum / median / maximum
over the localised frames and over all (a frame not localised: the figures of the best pose it
was tried at); the JSON has every frame.

    python benchmarks/localization_fit.py --data ../shared/data --out /tmp/localization_fit.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

#: (name, map dataset, its path, map frames) and (case, map name, dataset, its path, start, frames, stride, same scene)
MAPS = [("tum_0_99", "tum", "tum_fr1_rpy_first150", 100), ("tum_0_39", "tum", "tum_fr1_rpy_first150", 40),
        ("replica_0_9", "replica", "replica_room0_first20", 10)]
CASES = [("TUM 100-149 in TUM 0-99", "tum_0_99", "tum", "tum_fr1_rpy_first150", 100, 50, 1, True),
         ("TUM 50-79 in TUM 0-39", "tum_0_39", "tum", "tum_fr1_rpy_first150", 50, 30, 1, True),
         ("Replica 10-19 in Replica 0-9", "replica_0_9", "replica", "replica_room0_first20", 10, 10, 1, True),
         ("TUM 0-145 (every 5th) in Replica 0-9", "replica_0_9", "tum", "tum_fr1_rpy_first150", 0, 30, 5, False),
         ("Replica 0-18 (every 2nd) in TUM 0-99", "tum_0_99", "replica", "replica_room0_first20", 0, 10, 2, False)]
FIGURES = ("inlier_fraction", "surface_agreement", "color_correlation")


def make_map(folder: Path, dataset: str, path: Path, frames: int) -> None:
    exe = Path(sys.executable).with_name("slamkit")
    subprocess.run([str(exe), f"dataset={dataset}", f"dataset.path={path}", f"dataset.max_frames={frames}",
                    "mapper=none", "output.progress=false", "checkpoint.save=true",
                    f"hydra.run.dir={folder}"], check=True, capture_output=True)


def localise(map_folder: Path, dataset: str, path: Path, start: int, frames: int, stride: int) -> list[dict]:
    from slamkit.config import RunContext
    from slamkit.registry.compose import compose_run
    from slamkit.registry.discovery import default_registry
    from slamkit.run.checkpoint import load_map
    from slamkit.run.localization import Localizer

    registry = default_registry()
    cfg, names = compose_run(["mode=localize", f"map={map_folder}", f"dataset={dataset}",
                              f"dataset.path={path}", f"dataset.start={start}", f"dataset.max_frames={frames}",
                              f"dataset.stride={stride}", "localize.attempts=1"], registry)
    data = registry.create("dataset", names["dataset"], cfg.dataset)
    context = RunContext(tuning=data.tuning, build=registry.create)
    localizer = Localizer(cfg, registry.create("tracker", names["tracker"], cfg.tracker, context),
                          load_map(map_folder)[0])
    rows = []
    for i in range(len(data)):
        done = localizer.step(data[i])
        rows.append({"index": done.index, "localized": done.localized, "inlier_fraction": done.inlier_fraction,
                     "surface_agreement": done.fit.surface_agreement, "color_correlation": done.fit.color_correlation})
    return rows


def spread(rows: list[dict], figure: str) -> list[float] | None:
    """[min, median, max] of a figure over `rows` (None where none was judged)."""
    values = [r[figure] for r in rows if r[figure] is not None]
    return [round(float(np.min(values)), 3), round(float(np.median(values)), 3),
            round(float(np.max(values)), 3)] if values else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    from slamkit.registry.schema import LocalizeConfig

    defaults = LocalizeConfig()
    minimums = {f: getattr(defaults, f"min_{f}") for f in FIGURES}
    results = {"minimums": minimums, "cases": []}
    with tempfile.TemporaryDirectory() as tmp:
        for name, dataset, folder, frames in MAPS:
            make_map(Path(tmp) / name, dataset, args.data / folder, frames)
        for case, map_name, dataset, folder, start, frames, stride, same in CASES:
            rows = localise(Path(tmp) / map_name, dataset, args.data / folder, start, frames, stride)
            localized = [r for r in rows if r["localized"]]
            summary = {"case": case, "same_scene": same, "frames": len(rows), "localized": len(localized),
                       "all": {f: spread(rows, f) for f in FIGURES},
                       "localized_frames": {f: spread(localized, f) for f in FIGURES}, "rows": rows}
            results["cases"].append(summary)
            print(f"{case}: {len(localized)}/{len(rows)} localised; min/median/max, localised frames: " +
                  "; ".join(f"{f} {summary['localized_frames'][f]}" for f in FIGURES) + "; all frames: " +
                  "; ".join(f"{f} {summary['all'][f]}" for f in FIGURES), flush=True)
    if args.out:
        args.out.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
