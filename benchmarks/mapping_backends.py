"""End-to-end training time of the 3DGS mapper along each compute path: the same `slamkit` run
(sequential GS-ICP SLAM) with the compiled CPU path (`mapper/rasterizer=cpu`, the fused loss: the
defaults on a CPU) and the torch path (`mapper/rasterizer=torch mapper.loss.backend=torch`: the
torch rasteriser, pytorch-msssim and autograd), on each shared sequence. Prints a table (whole-run wall
time, training time = mapping steps during the stream and the refinement after it, PSNR, ATE,
and the speed-up of the cpu path measured in the same invocation) and writes JSON.

    OMP_NUM_THREADS=1 python benchmarks/mapping_backends.py --sequences replica --extra dataset.max_frames=6
    python benchmarks/mapping_backends.py --sequences tum --extra dataset.max_frames=30 final_iterations=100
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SEQUENCES = {
    "replica": ["dataset=replica", f"dataset.path={DATA / 'replica_room0_first20'}"],
    "tum": ["dataset=tum", f"dataset.path={DATA / 'tum_fr1_rpy_first150'}"],
}
PATHS = {"cpu": ["mapper/rasterizer=cpu"], "torch": ["mapper/rasterizer=torch", "mapper.loss.backend=torch"]}
KEYS = ("wall_time_s", "mapping_time_s", "refine_time_s", "mapping_steps", "psnr", "ssim", "ate_rmse_m",
        "num_gaussians", "peak_memory_mb")


def run(sequence: str, backend: str, extra: list[str], out: Path) -> dict:
    exe = Path(sys.executable).with_name("slamkit")
    run_dir = out / f"{sequence}_{backend}"
    cmd = [str(exe), *SEQUENCES[sequence], "mapper=gaussian_splatting", *PATHS[backend], *extra,
           "output.progress=false", "output.plot=false", f"hydra.run.dir={run_dir}"]
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    row = {"sequence": sequence, "backend": backend, "process_s": time.perf_counter() - start,
           "command": " ".join(["slamkit", *cmd[1:-1]])}
    if proc.returncode != 0:
        row["error"] = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        return row
    metrics = json.loads((run_dir / "metrics.json").read_text())
    row.update({k: metrics.get(k) for k in KEYS})
    row["training_time_s"] = metrics["mapping_time_s"] + metrics["refine_time_s"]
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequences", default="replica,tum")
    parser.add_argument("--backends", default="cpu,torch")
    parser.add_argument("--extra", nargs="*", default=[], help="more slamkit overrides for every run")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/mapping_backends.json"))
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for sequence in args.sequences.split(","):
            runs = {b: run(sequence, b, args.extra, Path(tmp)) for b in args.backends.split(",")}
            for row in runs.values():
                if "cpu" in runs and "torch" in runs and "error" not in runs["cpu"] and "error" not in runs["torch"]:
                    row["wall_vs_cpu"] = row["wall_time_s"] / runs["cpu"]["wall_time_s"]
                    row["training_vs_cpu"] = row["training_time_s"] / runs["cpu"]["training_time_s"]
                rows.append(row)
                print(_line(row), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": platform.platform(), "when": time.strftime("%Y-%m-%d %H:%M"),
                                    "extra": args.extra, "rows": rows}, indent=2) + "\n")
    print(f"wrote {args.out}")


def _line(r: dict) -> str:
    if "error" in r:
        return f"| {r['sequence']} | {r['backend']} | failed: {r['error']} |"
    return (f"| {r['sequence']} | {r['backend']} | wall {r['wall_time_s']:.1f} s "
            f"| training {r['training_time_s']:.1f} s "
            f"({r['mapping_steps']} steps) | PSNR {r['psnr']:.2f} dB | ATE {100 * r['ate_rmse_m']:.2f} cm | "
            f"{r['num_gaussians']} G | {r['peak_memory_mb']:.0f} MB "
            f"| wall/cpu {r.get('wall_vs_cpu', float('nan')):.2f} "
            f"| training/cpu {r.get('training_vs_cpu', float('nan')):.2f} |")


if __name__ == "__main__":
    main()
