"""Tracking with and without 3DGS mapping: ATE from several start frames, PSNR and map size per
variant, each a `slamkit` CLI run (sequential mode is deterministic).

    OMP_NUM_THREADS=1 python benchmarks/tracking_under_mapping.py --starts 0,10,20,30 \
        --variants tracking_only,mapping,entry_target --out benchmarks/results/tracking_under_mapping.json

The start-0 run of a mapping variant is the full run (final training steps, every frame
evaluated: its PSNR is the table's); the other starts only track and map (no final steps, one
frame evaluated), since ATE does not depend on what happens after the last frame. A variant
already in --out is not run again (delete it to rerun). `--realtime` adds the real-time run
(`mode=realtime realtime.fps_limit=30 final_iterations=0`) from frame 0.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "tum_fr1_rpy_first150"
MAPPER = ["mapper=gaussian_splatting"]
VARIANTS = {  # name -> CLI overrides (entry_shape and mapper.freeze_trackable: commit afdf8d5 only)
    "tracking_only": ["mapper=none"],
    "mapping": MAPPER + ["tracker.target_geometry=optimised", "tracker.min_target_opacity=0.09"],
    "mapping_lr0": MAPPER + ["tracker.target_geometry=optimised", "tracker.min_target_opacity=0.09",
                             "mapper.optimizer.lr_means=0", "mapper.optimizer.lr_quats=0",
                             "mapper.optimizer.lr_scales=0", "mapper.optimizer.lr_opacity=0"],
    "opacity0": MAPPER + ["tracker.target_geometry=optimised", "tracker.min_target_opacity=0"],
    "entry_target": MAPPER + ["tracker.target_geometry=entry", "tracker.min_target_opacity=0"],
    "entry_target_op09": MAPPER + ["tracker.target_geometry=entry", "tracker.min_target_opacity=0.09"],
}
QUICK = ["final_iterations=0", "mapper.eval_every=100000", "mapper.save_images=0"]
REALTIME = ["mode=realtime", "realtime.fps_limit=30", "final_iterations=0"]


def run(name: str, overrides: list[str], start: int, out_root: Path, extra: list[str]) -> dict:
    out = out_root / f"{name}_s{start}{'_rt' if 'mode=realtime' in extra else ''}"
    exe = Path(sys.executable).with_name("slamkit")
    args = [str(exe), "dataset=tum", f"dataset.path={DATA}", f"dataset.start={start}", "tracker=gicp",
            *overrides, *extra, "output.progress=false", f"hydra.run.dir={out}"]
    t0 = time.time()
    proc = subprocess.run(args, env=dict(os.environ, OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "1")),
                          capture_output=True, text=True)
    if proc.returncode:
        raise RuntimeError(f"{' '.join(args)}\n{proc.stderr[-2000:]}")
    m = json.loads((out / "metrics.json").read_text())
    return {"start": start, "ate_rmse_cm": 100 * m["ate_rmse_m"], "psnr": m.get("psnr"),
            "gaussians": m.get("num_gaussians"), "keyframes": m["num_keyframes"],
            "mapping_steps": m.get("mapping_iterations"), "wall_s": time.time() - t0, "dir": str(out),
            "command": " ".join(args[1:])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--variants", default="tracking_only,mapping")
    ap.add_argument("--starts", default="0,10,20,30")
    ap.add_argument("--realtime", action="store_true")
    ap.add_argument("--runs", default="/tmp/tracking_under_mapping")
    ap.add_argument("--out", default="benchmarks/results/tracking_under_mapping.json")
    a = ap.parse_args()
    out = Path(a.out)
    results = json.loads(out.read_text()) if out.exists() else {}
    starts = [int(s) for s in a.starts.split(",")]
    for name in a.variants.split(","):
        rows = results.setdefault(name, {})
        for start in starts:
            key = f"s{start}"
            if key in rows:
                continue
            quick = start != 0 and name != "tracking_only"
            rows[key] = run(name, VARIANTS[name], start, Path(a.runs), QUICK if quick else [])
            print(name, key, f"{rows[key]['ate_rmse_cm']:.2f} cm", rows[key]["psnr"], flush=True)
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(json.dumps(results, indent=1))
        if a.realtime and name != "tracking_only" and "rt" not in rows:
            rows["rt"] = run(name, VARIANTS[name], 0, Path(a.runs), REALTIME)
            print(name, "rt", f"{rows['rt']['ate_rmse_cm']:.2f} cm", rows["rt"]["psnr"], flush=True)
            out.write_text(json.dumps(results, indent=1))
    print_table(results, starts)


def print_table(results: dict, starts: list[int]) -> None:
    print("| variant | " + " | ".join(f"start {s}" for s in starts) + " | mean | worst | real time (start 0) "
          "| PSNR (start 0) | Gaussians | real-time PSNR |")
    print("|---" * (len(starts) + 7) + "|")
    for name, rows in results.items():
        ates = [rows[f"s{s}"]["ate_rmse_cm"] for s in starts if f"s{s}" in rows]
        rt = rows.get("rt", {})
        s0 = rows.get("s0", {})
        cells = [f"{rows[f's{s}']['ate_rmse_cm']:.2f}" if f"s{s}" in rows else "" for s in starts]
        mean = f"{sum(ates) / len(ates):.2f}" if ates else ""
        worst = f"{max(ates):.2f}" if ates else ""
        fmt = lambda v, f: "" if v is None else format(v, f)  # noqa: E731
        print(f"| {name} | " + " | ".join(cells) + f" | {mean} | {worst} | {fmt(rt.get('ate_rmse_cm'), '.2f')} | "
              f"{fmt(s0.get('psnr'), '.2f')} | {fmt(s0.get('gaussians'), ',')} | {fmt(rt.get('psnr'), '.2f')} |")


if __name__ == "__main__":
    main()
