"""The map optimisers' step time: torch.optim.Adam (`mapper/optimizer=adam`) against the per-row
visible Adam (`mapper/optimizer=visible_adam`, torch and compiled paths), on map-sized parameter sets
with a given fraction of the rows seen by the step (non-zero gradient).

    OMP_NUM_THREADS=1 python benchmarks/optimizer.py --rows 50000,200000 --seen 0.3,1.0

Prints a table (median milliseconds per step over `--repeats` steps, thread CPU) and writes
JSON (`--out`).
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import torch

from slamkit_plugins.mappers.gaussian_splatting.optimizer.adam import AdamConfig, TorchAdam
from slamkit_plugins.mappers.gaussian_splatting.optimizer.visible_adam import Kernels, VisibleAdam, VisibleAdamConfig

SHAPES = {"means": (3,), "quats": (4,), "log_scales": (3,), "opacity_logits": (), "colors": (3,)}
OPTIMIZERS = {
    "adam (torch.optim.Adam)": lambda: TorchAdam(AdamConfig()),
    "visible_adam torch": lambda: VisibleAdam(VisibleAdamConfig(kernels=Kernels.torch)),
    "visible_adam compiled": lambda: VisibleAdam(VisibleAdamConfig(kernels=Kernels.compiled)),
}


def time_optimizer(make, rows: int, seen: float, repeats: int) -> float:
    g = torch.Generator().manual_seed(0)
    params = {k: torch.randn((rows,) + s, generator=g).requires_grad_(True) for k, s in SHAPES.items()}
    hidden = torch.rand(rows, generator=g) >= seen
    grads = {k: torch.randn((rows,) + s, generator=g) for k, s in SHAPES.items()}
    for v in grads.values():
        v[hidden] = 0
    optimizer = make()
    optimizer.step(params, grads)  # state allocation
    times = []
    for _ in range(repeats):
        start = time.thread_time()
        optimizer.step(params, grads)
        times.append(time.thread_time() - start)
    return 1e3 * statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rows", default="50000,200000")
    parser.add_argument("--seen", default="0.3,1.0")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/optimizer.json"))
    args = parser.parse_args()
    rows = []
    for n in (int(v) for v in args.rows.split(",")):
        for seen in (float(v) for v in args.seen.split(",")):
            results = {name: time_optimizer(make, n, seen, args.repeats) for name, make in OPTIMIZERS.items()}
            base = results["adam (torch.optim.Adam)"]
            rows += [{"rows": n, "seen": seen, "optimizer": name, "ms": ms, "vs_torch_adam": base / ms}
                     for name, ms in results.items()]
    print("| rows | seen | optimizer | ms / step (thread CPU) | speed vs torch.optim.Adam |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['rows']:,} | {r['seen']:.0%} | {r['optimizer']} | {r['ms']:.2f} | {r['vs_torch_adam']:.1f}x |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": platform.platform(), "when": time.strftime("%Y-%m-%d %H:%M"),
                                    "torch_threads": torch.get_num_threads(), "rows": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
