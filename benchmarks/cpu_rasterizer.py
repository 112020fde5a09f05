"""Profile of the compiled CPU rasteriser (`mapper/rasterizer=cpu`) on the fixed scenes of
benchmarks/rasterizer.py: CPU time per phase, cycles per (pixel, Gaussian) pair, vector-lane use,
and thread scaling. The comparison with the torch backend is benchmarks/rasterizer.py's job
(`--backends torch,cpu`); this one explains where the cpu backend's time goes.

    python benchmarks/cpu_rasterizer.py [--scenes small,large] [--threads 1,2] [--repeats 5]
                                        [--map RUN_DIR/checkpoint.zip [--map-scales 0.5,0.25]]
                                        [--out benchmarks/results/cpu_rasterizer.json]

`--map` adds a run's own map (e.g. of a real-time run: `slamkit ... mode=realtime` writes
checkpoint.zip into its folder), rendered from each of its keyframes' poses at each scale of the
frame size; its rows are per view, averaged over the views.

Phase times are process CPU time (all threads; the minimum over the repeats), so they depend
little on how busy the machine is; "CPU f+b" is their sum (the rasteriser alone) and "wall f+b"
the median wall-clock time of render + loss + backward (as timed by benchmarks/rasterizer.py).
cycles/pair = CPU f+b x clock (GHz, from /proc/cpuinfo or lscpu) / pairs: the core cycles spent
per composited pair, whatever the thread count. torch's own ops (the loss) run on
`--torch-threads` threads (default 1: torch's OpenMP threads spin and, on a shared machine,
stall; that is the harness's cost, not the rasteriser's).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from rasterizer import SCENES, make_scene  # noqa: E402  (the same scenes)

from slamkit.errors import ConfigError  # noqa: E402
from slamkit.formats.checkpoint import read_checkpoint  # noqa: E402
from slamkit.types import Camera  # noqa: E402
from slamkit_plugins.mappers.gaussian_splatting.rasterizer.cpu_rasterizer import (  # noqa: E402
    TIME_KEYS,
    CPURasterizer,
    CPURasterizerConfig,
)

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "cpu_rasterizer.json"


def cpu_ghz() -> float | None:
    """The nominal clock: 'cpu MHz' of /proc/cpuinfo, else lscpu's max MHz."""
    try:
        mhz = [float(m) for m in re.findall(r"^cpu MHz\s*:\s*([0-9.]+)", Path("/proc/cpuinfo").read_text(), re.M)]
        if mhz:
            return max(mhz) / 1000.0
    except OSError:
        pass
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, timeout=10).stdout
        m = re.search(r"CPU max MHz:\s*([0-9.]+)", out)
        return float(m.group(1)) / 1000.0 if m else None
    except (OSError, subprocess.SubprocessError):
        return None


def map_views(checkpoint: Path, scale: float) -> list:
    """The scenes of a run's map checkpoint (`checkpoint.zip` of a run folder): its Gaussians
    seen from each keyframe's pose, the camera (the run folder's camera.json) scaled by
    `scale` as the mapper's training views are."""
    state = read_checkpoint(checkpoint)["state"]
    g = state["map"]
    camera = json.loads((checkpoint.parent / "camera.json").read_text())
    cam = Camera(*(camera[k] for k in ("width", "height", "fx", "fy", "cx", "cy"))).scaled(scale)
    params = (g["means"], g["quats"], g["log_scales"].exp(), torch.sigmoid(g["opacity_logits"]), g["colors"])
    return [(*params, torch.from_numpy(np.linalg.inv(pose)), cam) for pose in state["mapper"]["keyframes"]["pose"]]


def profile(views: list, threads: int, repeats: int) -> dict:
    """Render + backward of each view, `repeats` times after a warm-up: per phase the minimum
    over the repeats, averaged over the views (pairs, too, per view)."""
    r = CPURasterizer(CPURasterizerConfig(num_threads=threads))
    gen = torch.Generator().manual_seed(1)
    per_view = []
    for means, quats, scales, opac, colors, w2c, cam in views:
        weights = [torch.randn(cam.height, cam.width, 3, generator=gen),
                   torch.randn(cam.height, cam.width, generator=gen), torch.randn(cam.height, cam.width, generator=gen)]
        phases: dict[str, list[float]] = {k: [] for k in TIME_KEYS}
        wall = []
        for i in range(repeats + 1):
            leaves = [p.detach().requires_grad_(True) for p in (means, quats, scales, opac, colors)]
            t0 = time.perf_counter()
            out = r.render(*leaves, w2c, cam)
            loss = (out.color * weights[0]).sum() + (out.depth * weights[1]).sum() + (out.alpha * weights[2]).sum()
            loss.backward()
            if i == 0:
                continue  # warm-up (and the build, on first use)
            wall.append(time.perf_counter() - t0)
            for k in TIME_KEYS:
                phases[k].append(r.last_times[f"{k}_cpu"])
        per_view.append({"pairs": r.last_num_pairs, "visible": r.last_num_visible, "entries": r.last_num_entries,
                         "rows": r.last_num_rows, "wall": statistics.median(wall),
                         "phases": {k: min(v) for k, v in phases.items()}})

    def mean(f):
        return statistics.fmean(f(v) for v in per_view)

    phase = {k: mean(lambda v: v["phases"][k]) for k in TIME_KEYS}
    return {
        "threads": threads, "views": len(views), "pairs": mean(lambda v: v["pairs"]),
        "visible": mean(lambda v: v["visible"]), "entries": mean(lambda v: v["entries"]),
        "row_spans": mean(lambda v: v["rows"]),
        "lane_use": sum(v["pairs"] for v in per_view) / max(16 * sum(v["rows"] for v in per_view), 1),
        "wall_s": mean(lambda v: v["wall"]), "cpu_s": sum(phase.values()),
        "forward_cpu_s": sum(phase[k] for k in TIME_KEYS[:5]), "phase_cpu_s": phase,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="small,large")
    ap.add_argument("--map", type=Path, default=None, metavar="CHECKPOINT",
                    help="also profile a run's map (RUN_DIR/checkpoint.zip) from its keyframe views")
    ap.add_argument("--map-scales", default="0.5,0.25", help="training resolutions of the map's views")
    ap.add_argument("--threads", default="1,2", help="comma-separated thread counts")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--torch-threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.torch_threads)
    try:
        CPURasterizer()
    except ConfigError as exc:
        print(exc)
        return 1
    ghz = cpu_ghz()
    results = {"machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(), "ghz": ghz,
                           "load_avg": os.getloadavg() if hasattr(os, "getloadavg") else None}, "runs": []}
    load = results["machine"]["load_avg"]
    averages = " ".join(f"{x:.1f}" for x in load) if load else "?"
    print(f"clock {ghz} GHz, {os.cpu_count()} CPUs, load average {averages}; phase columns: CPU time")
    head = (f"{'scene':9} {'thr':>3} {'pairs':>9} {'lanes':>6} {'wall f+b':>9} {'CPU fwd':>8} {'CPU f+b':>8} "
            f"{'cyc/pair f':>10} {'cyc/pair f+b':>12}  "
            + " ".join(f"{k[:9]:>9}" for k in TIME_KEYS))
    print(head)
    names = [s.strip() for s in args.scenes.split(",") if s.strip()]
    scenes = {name: [make_scene(*SCENES[name], args.seed)] for name in names}
    if args.map is not None:
        scenes.update({f"map@{scale}": map_views(args.map, float(scale)) for scale in args.map_scales.split(",")})
    for scene_name, views in scenes.items():
        for threads in [int(t) for t in args.threads.split(",")]:
            res = profile(views, threads, args.repeats)
            res["scene"] = scene_name
            res["cycles_per_pair"] = res["cpu_s"] * ghz * 1e9 / res["pairs"] if ghz else None
            res["cycles_per_pair_forward"] = res["forward_cpu_s"] * ghz * 1e9 / res["pairs"] if ghz else None
            results["runs"].append(res)
            cyc = (f"{res['cycles_per_pair_forward']:>10.1f} {res['cycles_per_pair']:>12.1f}" if ghz
                   else f"{'?':>10} {'?':>12}")
            print(f"{scene_name:9} {threads:>3} {res['pairs']:>9.0f} {res['lane_use']:>6.2f} "
                  f"{res['wall_s'] * 1e3:>7.1f}ms {res['forward_cpu_s'] * 1e3:>6.1f}ms "
                  f"{res['cpu_s'] * 1e3:>6.1f}ms {cyc}  "
                  + " ".join(f"{res['phase_cpu_s'][k] * 1e3:>7.2f}ms" for k in TIME_KEYS), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2))
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
