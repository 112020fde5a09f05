"""Rasteriser backends: forward and forward+backward time on two fixed SLAM-like scenes.

    python benchmarks/rasterizer.py --backends torch,cpu [--out benchmarks/results/rasterizer.json]

Scenes are built deterministically from a seed: Gaussians on the surfaces of a room (floor,
ceiling, walls, two spheres) 1.3-4 m in front of the camera, flat along the surface (in-plane
scales 1-3 cm, 1-3 mm along the normal), opacities 0.1-0.9, random colours:
`small` = 20k Gaussians at 320x240, `large` = 100k at 640x480 (fx = fy = 525 * width / 640).

Times are the median of `--repeats` runs after one warm-up: wall-clock, and the process's CPU
time beside it (all threads). On a machine shared with other work the wall-clock time of
torch's multi-threaded CPU ops suffers badly: compare runs with `--threads 1` there. "pairs"
are the (pixel, Gaussian) pairs composited by the torch backend (after the alpha >= 1/255 and
transmittance cut-offs); the same count is used for every backend's pairs per second. A backend
that cannot be built here (not installed, needs CUDA) is skipped with a message. gsplat runs on CUDA tensors, the others
on CPU tensors.
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

import numpy as np
import torch

from slamkit.errors import SlamkitError
from slamkit.geometry.transforms import rotmat_to_quat
from slamkit.registry.discovery import create_rasterizer
from slamkit.types import Camera

SCENES = {"small": (20_000, 320, 240), "large": (100_000, 640, 480)}
DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "rasterizer.json"


def make_scene(num: int, width: int, height: int, seed: int = 0):
    """(means, quats, scales, opacities, colors, world_to_camera, camera) as float32 tensors."""
    rng = np.random.default_rng(seed)
    f = 525.0 * width / 640.0
    cam = Camera(width, height, f, f, (width - 1) / 2, (height - 1) / 2)
    # rays through random image points (a little beyond the border too)
    px = rng.uniform(-0.05 * width, 1.05 * width, num)
    py = rng.uniform(-0.05 * height, 1.05 * height, num)
    d = np.stack([(px - cam.cx) / f, (py - cam.cy) / f, np.ones(num)], -1)
    # planes n.x = c (camera frame, y down): floor, ceiling, side walls, a slanted back wall
    planes = [((0, 1, 0), 1.2), ((0, -1, 0), 1.4), ((-1, 0, 0), 1.9), ((1, 0, 0), 2.0), ((0.2, 0, 1), 3.6)]
    best = np.full(num, np.inf)
    normal = np.zeros((num, 3))
    for n, c in planes:
        norm = np.linalg.norm(n)
        n, c = np.asarray(n, float) / norm, c / norm
        dn = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(dn > 1e-9, c / dn, np.inf)
        hit = s < best
        best[hit], normal[hit] = s[hit], -n
    for centre, r in (((0.5, 0.3, 2.0), 0.4), ((-0.7, 0.5, 1.6), 0.3)):
        centre = np.asarray(centre)
        dd = (d * d).sum(1)
        bq = d @ centre
        disc = bq * bq - dd * (centre @ centre - r * r)
        with np.errstate(invalid="ignore"):
            s = np.where(disc > 0, (bq - np.sqrt(np.maximum(disc, 0))) / dd, np.inf)
        hit = s < best
        best[hit] = s[hit]
        p = d[hit] * s[hit, None]
        normal[hit] = (p - centre) / r
    means = d * best[:, None]
    # orientation: third axis along the normal, a random in-plane rotation
    ref = np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    e1 = np.cross(normal, ref)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(normal, e1)
    phi = rng.uniform(0, 2 * np.pi, num)[:, None]
    a1 = np.cos(phi) * e1 + np.sin(phi) * e2
    a2 = np.cross(normal, a1)
    quats = rotmat_to_quat(np.stack([a1, a2, normal], -1))
    scales = np.concatenate([rng.uniform(0.01, 0.03, (num, 2)), rng.uniform(0.001, 0.003, (num, 1))], 1)
    opacities = rng.uniform(0.1, 0.9, num)
    colors = rng.uniform(0.0, 1.0, (num, 3))
    tensors = [torch.as_tensor(x, dtype=torch.float32) for x in (means, quats, scales, opacities, colors)]
    return (*tensors, torch.eye(4), cam)


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def time_backend(rasterizer, scene, device: str, repeats: int) -> dict:
    means, quats, scales, opac, colors, w2c, cam = scene
    params = [x.to(device) for x in (means, quats, scales, opac, colors)]
    w2c = w2c.to(device)
    gen = torch.Generator().manual_seed(1)
    weights = [torch.randn(cam.height, cam.width, 3, generator=gen).to(device),
               torch.randn(cam.height, cam.width, generator=gen).to(device),
               torch.randn(cam.height, cam.width, generator=gen).to(device)]

    def forward():
        with torch.no_grad():
            out = rasterizer.render(*params, w2c, cam)
        _sync(device)
        return out

    def forward_backward():
        leaves = [p.detach().requires_grad_(True) for p in params]
        out = rasterizer.render(*leaves, w2c, cam)
        loss = (out.color * weights[0]).sum() + (out.depth * weights[1]).sum() + (out.alpha * weights[2]).sum()
        loss.backward()
        _sync(device)

    result = {}
    for name, fn in (("forward", forward), ("forward_backward", forward_backward)):
        fn()  # warm-up
        wall, cpu = [], []
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        result[f"{name}_s"] = statistics.median(wall)
        result[f"{name}_cpu_s"] = statistics.median(cpu)
        result[f"{name}_all_s"] = wall
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backends", default="torch", help="comma-separated rasteriser names (default: torch)")
    ap.add_argument("--scenes", default="small,large", help="comma-separated: small, large")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: torch's own)")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)

    backends = {}
    for name in [n.strip() for n in args.backends.split(",") if n.strip()]:
        try:
            backends[name] = create_rasterizer(name)
        except SlamkitError as exc:
            print(f"skipping backend {name}: {exc}")
    if not backends:
        print("no backend to run")
        return 1

    results = {"machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(),
                           "torch_threads": torch.get_num_threads(), "torch": torch.__version__,
                           "load_avg": os.getloadavg() if hasattr(os, "getloadavg") else None},
               "scenes": {}}
    rows = []
    for scene_name in [s.strip() for s in args.scenes.split(",") if s.strip()]:
        num, width, height = SCENES[scene_name]
        scene = make_scene(num, width, height, args.seed)
        pairs = _count_pairs(scene)
        entry = {"gaussians": num, "width": width, "height": height, "pairs": pairs, "backends": {}}
        print(f"scene {scene_name}: {num} Gaussians at {width}x{height}, {pairs} pairs", flush=True)
        for name, rasterizer in backends.items():
            device = "cuda" if name == "gsplat" else "cpu"
            r = time_backend(rasterizer, scene, device, args.repeats)
            r["device"] = device
            r["pairs_per_s_forward"] = pairs / r["forward_s"]
            r["pairs_per_s_forward_backward"] = pairs / r["forward_backward_s"]
            entry["backends"][name] = r
            rows.append((scene_name, name, r))
            print(f"  {name}: forward {r['forward_s']:.3f} s, forward+backward {r['forward_backward_s']:.3f} s "
                  f"(CPU {r['forward_cpu_s']:.3f} s, {r['forward_backward_cpu_s']:.3f} s)", flush=True)
        results["scenes"][scene_name] = entry

    print()
    results["machine"]["load_avg_end"] = os.getloadavg() if hasattr(os, "getloadavg") else None
    print(f"torch threads: {torch.get_num_threads()}, load average at start {_load(results['machine']['load_avg'])}, "
          f"at end {_load(results['machine']['load_avg_end'])}")
    header = (f"{'scene':6} {'backend':8} {'pairs':>10} {'fwd s':>8} {'fwd+bwd s':>10} {'Mpairs/s fwd':>13} "
              f"{'Mpairs/s f+b':>13} {'fwd CPU s':>10} {'f+b CPU s':>10}")
    multi = len(backends) > 1 and "torch" in backends
    if multi:
        header += f" {'speed-up f':>11} {'speed-up f+b':>13}"
    print(header)
    for scene_name, name, r in rows:
        pairs = results["scenes"][scene_name]["pairs"]
        line = (f"{scene_name:6} {name:8} {pairs:>10} {r['forward_s']:>8.3f} {r['forward_backward_s']:>10.3f} "
                f"{r['pairs_per_s_forward'] / 1e6:>13.2f} {r['pairs_per_s_forward_backward'] / 1e6:>13.2f} "
                f"{r['forward_cpu_s']:>10.3f} {r['forward_backward_cpu_s']:>10.3f}")
        if multi:
            ref = results["scenes"][scene_name]["backends"]["torch"]
            sf, sb = ref["forward_s"] / r["forward_s"], ref["forward_backward_s"] / r["forward_backward_s"]
            r["speedup_vs_torch_forward"], r["speedup_vs_torch_forward_backward"] = sf, sb
            line += f" {sf:>10.2f}x {sb:>12.2f}x"
        print(line)

    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2))
    print(f"\nwrote {args.out}")
    return 0


def _load(avg) -> str:
    return "n/a" if avg is None else " ".join(f"{x:.1f}" for x in avg)


def _count_pairs(scene) -> int:
    from slamkit_plugins.mappers.gaussian_splatting.rasterizer.torch_rasterizer import TorchRasterizer

    r = TorchRasterizer()
    with torch.no_grad():
        r.render(*scene)
    return r.last_num_pairs


if __name__ == "__main__":
    sys.exit(main())
