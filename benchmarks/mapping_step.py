"""Where a 3DGS mapping step's time goes, for several mapper configurations on the same maps.

For each sequence the map is built by the sequential GS-ICP run over its first frames (tracking,
keyframes, 10 mapping steps a frame: a trained map, not a fresh one), then `--steps` more steps
are timed by phase (the mapper's own PhaseTimer: keyframe view, render, loss, backward, lock,
optimiser, strategy), in wall and thread-CPU milliseconds, with the map size and the rasteriser's
(pixel, Gaussian) pairs. Every variant builds its own map with its own parts, so a variant that
trains differently also times its own map.

    OMP_NUM_THREADS=1 python benchmarks/mapping_step.py                       # cpu path vs torch path
    OMP_NUM_THREADS=1 python benchmarks/mapping_step.py --sequences tum --variant fast="mapper.loss.backend=compiled"

Prints a markdown table and writes JSON (`--out`). The machine is shared: compare variants of
the same run; thread CPU time is the steadier figure under load.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import torch

from slamkit.metrics.images import psnr
from slamkit.run.build import build_run

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SEQUENCES = {  # name -> (overrides, frames that build the map)
    "tum": (["dataset=tum", f"dataset.path={DATA / 'tum_fr1_rpy_first150'}"], 30),
    "replica": (["dataset=replica", f"dataset.path={DATA / 'replica_room0_first20'}"], 20),
}
VARIANTS = {
    "torch": ["mapper/rasterizer=torch", "mapper/loss=l1_ssim_depth", "mapper/optimizer=adam"],
    "cpu": ["mapper/rasterizer=cpu"],
}


def build_map(sequence: str, overrides: list[str]):
    """The SLAM system after the sequential run over the sequence's first frames."""
    base, frames = SEQUENCES[sequence]
    dataset, slam, _ = build_run([*base, f"dataset.max_frames={frames}", "mapper=gaussian_splatting", *overrides])
    slam.initialize(dataset[0].gt_pose)
    for i in range(len(dataset)):
        slam.process(dataset[i])
    return dataset, slam


def train_psnr(slam, dataset) -> float:
    """Mean PSNR over the keyframes at the training resolution (a quick quality check)."""
    mapper = slam.mapper
    values = []
    for kf in mapper.keyframes.values():
        view = kf.view(slam.gaussian_map.device)
        with torch.no_grad():
            out = mapper.render(view.world_to_camera, view.camera)
        values.append(psnr(out.color.clamp(0, 1), view.image, view.depth > 0))
    return float(np.mean(values))


def time_steps(sequence: str, name: str, overrides: list[str], steps: int) -> dict:
    dataset, slam = build_map(sequence, overrides)
    mapper = slam.mapper
    mapper.timer.reset()
    cpu0, wall0 = time.thread_time(), time.perf_counter()
    mapper.optimize(steps)
    wall, cpu = time.perf_counter() - wall0, time.thread_time() - cpu0
    n = max(mapper.timer.steps, 1)
    phases = {p: 1e3 * mapper.timer.wall[p] / n for p in mapper.timer.wall}
    phases_cpu = {p: 1e3 * mapper.timer.cpu[p] / n for p in mapper.timer.cpu}
    camera = mapper.keyframes.values()[0].camera
    return {
        "sequence": sequence, "variant": name, "overrides": overrides, "steps": n,
        "resolution": f"{camera.width}x{camera.height}", "gaussians": len(slam.gaussian_map),
        "pairs": getattr(mapper.rasterizer, "last_num_pairs", None),
        "ms_per_step": 1e3 * wall / n, "cpu_ms_per_step": 1e3 * cpu / n, "steps_per_s": n / wall,
        "phases_ms": phases, "phases_cpu_ms": phases_cpu, "train_psnr": train_psnr(slam, dataset),
    }


def print_table(rows: list[dict]) -> None:
    phases = ["view", "render", "loss", "backward", "optimizer", "strategy", "lock"]
    head = ["sequence", "variant", "resolution", "Gaussians", "Mpairs", "ms/step", "CPU ms/step", "steps/s",
            *phases, "train PSNR", "vs first"]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    first = {}
    for r in rows:
        base = first.setdefault(r["sequence"], r["ms_per_step"])
        cells = [r["sequence"], r["variant"], r["resolution"], f"{r['gaussians']:,}",
                 "" if r["pairs"] is None else f"{r['pairs'] / 1e6:.2f}", f"{r['ms_per_step']:.1f}",
                 f"{r['cpu_ms_per_step']:.1f}", f"{r['steps_per_s']:.1f}",
                 *(f"{r['phases_ms'].get(p, 0):.1f}" for p in phases), f"{r['train_psnr']:.2f}",
                 f"{base / r['ms_per_step']:.2f}x"]
        print("| " + " | ".join(cells) + " |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequences", default="tum,replica")
    parser.add_argument("--variants", default=",".join(VARIANTS), help="built-in variants to run, in order")
    parser.add_argument("--variant", action="append", default=[], metavar='NAME="OVERRIDE ..."',
                        help="an extra variant: a name and slamkit overrides separated by spaces")
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/mapping_step.json"))
    args = parser.parse_args()
    variants = {name: VARIANTS[name] for name in args.variants.split(",") if name}
    for spec in args.variant:
        name, _, overrides = spec.partition("=")
        variants[name] = overrides.split()
    rows = []
    for sequence in args.sequences.split(","):
        for name, overrides in variants.items():
            rows.append(time_steps(sequence, name, overrides, args.steps))
            print(f"{sequence} {name}: {rows[-1]['ms_per_step']:.1f} ms/step", flush=True)
    print_table(rows)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": platform.platform(), "when": time.strftime("%Y-%m-%d %H:%M"),
                                    "torch_threads": torch.get_num_threads(), "load": _load(), "rows": rows},
                                   indent=2) + "\n")
    print(f"wrote {args.out}")


def _load() -> list[float] | None:
    try:
        return [float(v) for v in Path("/proc/loadavg").read_text().split()[:3]]
    except OSError:
        return None


if __name__ == "__main__":
    main()
