"""The mapping loss, forward + backward: the torch path (pytorch_msssim + autograd) against the
fused compiled kernel (`slamkit_plugins.mappers.gaussian_splatting.loss.fused_rgbd_loss`).

    python benchmarks/loss.py [--sizes 320x240,600x340] [--threads 1,2] [--repeats 50]
                              [--out benchmarks/results/loss.json]

Each timed step is what a mapping step pays for its loss: `loss = fn(color, depth, image,
observed_depth)` then `loss.backward()` into colour and depth that require gradients (the
mapper's weights 0.8, 0.2, 0.1). Inputs are deterministic: a random keyframe image, a
rendered colour near it, depths 0.5-4.5 m with 10 % of the pixels without a measurement. The
`kernel` row is the compiled call alone (loss and both gradients, no autograd, no Python
around it beyond ctypes): the rest of `fused` is autograd's and the Function's overhead.

Times are over `--repeats` runs after warm-up: the median and the minimum wall-clock time, and
the median process CPU time (all threads); speed-ups are torch's time over each path's, for
each of the three. `threads` is torch.set_num_threads for the torch path and num_threads (row
bands) for the fused one. On a machine shared with other work the wall-clock medians wander
(a run that loses its core waits): compare the minima and the CPU times, and the one-thread
rows; the load average at the start is printed and stored.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

from slamkit_plugins.mappers.gaussian_splatting.loss.fused_rgbd_loss import (
    available,
    fused_rgbd_loss,
    kernel_rgbd_loss,
    torch_rgbd_loss,
)

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "loss.json"
WEIGHTS = dict(w_l1=0.8, w_ssim=0.2, w_depth=0.1, depth_unit=10.0)


def make_inputs(width: int, height: int, seed: int = 0):
    """(color, depth, image, observed_depth) float32: colour in [0, 1], depths in metres."""
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(height, width, 3, generator=g)
    color = (image + 0.1 * torch.randn(height, width, 3, generator=g)).clamp(0, 1)
    observed = 0.5 + 4 * torch.rand(height, width, generator=g)
    observed[torch.rand(height, width, generator=g) < 0.1] = 0
    depth = observed + 0.05 * torch.randn(height, width, generator=g)
    return color, depth, image, observed


def time_it(step, repeats: int) -> dict:
    """Median wall and process-CPU seconds of `step()` over `repeats` runs (after 3 warm-ups)."""
    for _ in range(3):
        step()
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        step()
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return {"wall_s": statistics.median(wall), "wall_min_s": min(wall), "cpu_s": statistics.median(cpu)}


def steps(inputs, threads: int) -> dict:
    """The timed step of each path: fn(...) then backward, on fresh leaf tensors."""
    color, depth, image, observed = inputs
    c, d = color.clone().requires_grad_(), depth.clone().requires_grad_()

    def autograd_step(fn, **kw):
        def step():
            c.grad = d.grad = None
            fn(c, d, image, observed, **WEIGHTS, **kw).backward()
        return step

    weights = tuple(WEIGHTS.values())
    return {
        "torch": autograd_step(torch_rgbd_loss),
        "fused": autograd_step(fused_rgbd_loss, num_threads=threads),
        "kernel": lambda: kernel_rgbd_loss(color, depth, image, observed, weights, threads, grads=True),
    }


def run(sizes, threads_list, repeats: int) -> list[dict]:
    rows = []
    for width, height in sizes:
        inputs = make_inputs(width, height)
        for threads in threads_list:
            torch.set_num_threads(threads)
            results = {name: time_it(step, repeats) for name, step in steps(inputs, threads).items()}
            base = results["torch"]
            for name, r in results.items():
                rows.append({"size": f"{width}x{height}", "threads": threads, "path": name, **r,
                             "speedup": base["wall_s"] / r["wall_s"],
                             "speedup_min": base["wall_min_s"] / r["wall_min_s"],
                             "speedup_cpu": base["cpu_s"] / r["cpu_s"]})
    return rows


def print_table(rows) -> None:
    print(f"{'size':>8} {'thr':>3} {'path':>7} {'wall ms':>9} {'min ms':>8} {'CPU ms':>8}   speed-up: "
          f"{'wall':>6} {'min':>6} {'CPU':>6}")
    for r in rows:
        print(f"{r['size']:>8} {r['threads']:>3} {r['path']:>7} {1e3 * r['wall_s']:9.3f} {1e3 * r['wall_min_s']:8.3f} "
              f"{1e3 * r['cpu_s']:8.3f}             {r['speedup']:5.1f}x {r['speedup_min']:5.1f}x "
              f"{r['speedup_cpu']:5.1f}x")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="320x240,600x340", help="WxH,... (default: 320x240,600x340)")
    ap.add_argument("--threads", default="1,2", help="thread counts (default: 1,2)")
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"JSON results (default: {DEFAULT_OUT})")
    args = ap.parse_args(argv)
    if not available():
        print("benchmarks/loss.py: the fused loss cannot be built here (no C++ compiler?)", file=sys.stderr)
        return 2
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    threads_list = [int(t) for t in args.threads.split(",")]
    load = os.getloadavg()
    print(f"load average at start {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; {os.cpu_count()} CPUs; torch "
          f"{torch.__version__}")
    rows = run(sizes, threads_list, args.repeats)
    print_table(rows)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"load_average": load, "cpus": os.cpu_count(), "machine": platform.processor() or platform.machine(),
            "torch": torch.__version__, "repeats": args.repeats, "weights": WEIGHTS}
    args.out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
