"""The timings of the GPU check (benchmarks/gpu_check.sh, docs/gpu.md), one stage per call, each
merged into `OUT/gpu_check.json` and the table `OUT/gpu_check.md` as soon as it is measured (a
run cut off by its time limit keeps what it had):

    python benchmarks/gpu_bench.py tracking --out DIR   # tracking fps, map on the CPU / on the GPU
    python benchmarks/gpu_bench.py phases --out DIR     # one mapping step by phase, per backend
    python benchmarks/gpu_bench.py realtime --out DIR   # mode=realtime realtime.fps_limit=30 runs
    python benchmarks/gpu_bench.py note STEP STATUS SECONDS [DETAIL] --out DIR   # the script's own steps
    python benchmarks/gpu_bench.py plan                 # what each stage would run; runs nothing

Sequences: TUM fr1/rpy and Replica room0 from `--data` (default $SLAMKIT_DATA, else
../shared/data), every frame their folders hold. Backend variants are named BACKEND@DEVICE:
the rasteriser and where the map lives (`mapping_device`); `cpu@cpu` is the CPU path,
`cpu@cuda` what `mapper/rasterizer=auto` gives on a GPU machine without gsplat. `--no-gsplat` leaves
gsplat out (the script passes it when gsplat's extension did not build).

- tracking: G-ICP with the mapper off (`mapper=none`), frames read into memory first, every CPU
  thread, after a 3-frame warm-up per device (compiled kernels, CUDA context); frames/s over the
  tracker's time, and the hand-over of Gaussians between the CPU-side tracker and the map:
  `grow_map` (a keyframe's new Gaussians into the map, on its device) and `tracking_target` (the
  map's trackable Gaussians copied back for the tracker), milliseconds per keyframe, with the map
  on the CPU and on the GPU.
- phases: the map grown over the first PHASE_FRAMES frames (no training), then PHASE_WARMUP
  untimed and PHASE_STEPS timed steps of the mapper's own `optimize` (its PhaseTimer, with
  torch.cuda.synchronize around each phase: benchmarks/step_phases.py): view, render, loss,
  backward, lock, optimizer, strategy, wall milliseconds per step (and thread CPU ms in the JSON).
- realtime: `slamkit-bench`'s gsicp_realtime30 system (mode=realtime realtime.fps_limit=30; mapping stops
  with the stream, real-time mode's default) per backend variant, each run in its own process
  under REALTIME_TIMEOUT_S seconds: ATE, tracking / stream / system frames/s, mapping steps,
  PSNR, Gaussians.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SEQUENCES = {"tum": ("tum", "tum_fr1_rpy_first150"), "replica": ("replica", "replica_room0_first20")}
PHASE_VARIANTS = ("cpu@cpu", "cpu@cuda", "torch@cuda", "gsplat@cuda")
REALTIME_VARIANTS = ("gsplat@cuda", "torch@cuda", "cpu@cpu")
TRACKING_DEVICES = ("cpu", "cuda")
PHASE_FRAMES, PHASE_WARMUP, PHASE_STEPS = 10, 2, 10
REALTIME_TIMEOUT_S = 90
JSON_NAME, TABLE_NAME = "gpu_check.json", "gpu_check.md"


def say(message: str) -> None:
    print(f"[gpu_bench {time.strftime('%H:%M:%S')}] {message}", flush=True)


def data_root(arg: str | None) -> Path:
    return Path(arg or os.environ.get("SLAMKIT_DATA") or REPO.parent / "shared" / "data")


def sequence_overrides(name: str, data: Path) -> list[str]:
    plugin, folder = SEQUENCES[name]
    return [f"dataset={plugin}", f"dataset.path={data / folder}"]


def variant_overrides(variant: str) -> list[str]:
    backend, device = variant.split("@")
    return [f"mapper/rasterizer={backend}", f"mapping_device={device}"]


def selected(variants, no_gsplat: bool) -> list[str]:
    return [v for v in variants if not (no_gsplat and v.startswith("gsplat"))]


# -- results ----------------------------------------------------------------------------------


def merge(out: Path, key: str, value) -> None:
    """Put `value` under `key` in OUT/gpu_check.json (a list key gets it appended) and rewrite
    the markdown table."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / JSON_NAME
    data = json.loads(path.read_text()) if path.exists() else {}
    if key in ("tracking", "phases", "realtime"):
        data.setdefault(key, []).append(value)
    elif key == "steps":
        data.setdefault("steps", {})[value["step"]] = value
    else:
        data[key] = value
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=2, default=str) + "\n")
    tmp.replace(path)
    (out / TABLE_NAME).write_text(markdown(data))


def machine() -> dict:
    import torch

    info = {"platform": platform.platform(), "python": platform.python_version(), "cpus": os.cpu_count(),
            "torch": torch.__version__, "torch_cuda": torch.version.cuda, "cuda_available": torch.cuda.is_available()}
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(0)
    try:
        from importlib.metadata import version

        info["gsplat"] = version("gsplat")
    except Exception:
        info["gsplat"] = None
    return info


def _f(value, digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def markdown(data: dict) -> str:
    """The whole JSON as markdown tables (for docs/results.md)."""
    lines = ["# GPU check", ""]
    if "machine" in data:
        lines += ["Machine: " + ", ".join(f"{k} {v}" for k, v in data["machine"].items()), ""]
    if data.get("steps"):
        lines += ["| step | status | seconds | detail |", "|---|---|---|---|"]
        lines += [f"| {s['step']} | {s['status']} | {_f(s['seconds'])} | {s.get('detail', '')} |"
                  for s in data["steps"].values()]
        lines.append("")
    if data.get("tracking"):
        lines += ["## Tracking (G-ICP, mapper off, frames in memory)", "",
                  "| sequence | map on | frames | keyframes | tracking fps | ATE cm | grow_map ms/kf | "
                  "tracking_target ms/kf | Gaussians/kf | copy in / out ms (MB) |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        lines += [f"| {r['sequence']} | {r['device']} | {r['frames']} | {r['keyframes']} | {_f(r['fps'])} | "
                  f"{_f(100 * r['ate_rmse_m'], 2)} | {_f(r['grow_map_ms'], 2)} | {_f(r['target_ms'], 2)} | "
                  f"{_f(r['rows_per_keyframe'], 0)} | {_f(r.get('copy_in_ms'), 2)} / {_f(r.get('copy_out_ms'), 2)} "
                  f"({_f(r.get('copy_mb'), 2)}) |" if "error" not in r else
                  f"| {r['sequence']} | {r['device']} | failed: {r['error']} |" for r in data["tracking"]]
        lines.append("")
    if data.get("phases"):
        lines += ["## One mapping step by phase (ms per step)", "",
                  "| sequence | backend@map | Gaussians | resolution | view | render | loss | backward | lock | "
                  "optimizer | strategy | step |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in data["phases"]:
            if "error" in r:
                lines.append(f"| {r['sequence']} | {r['variant']} | failed: {r['error']} |")
                continue
            ms = r["ms"]
            lines.append(f"| {r['sequence']} | {r['variant']} | {r['gaussians']} | {r['resolution']} | "
                         + " | ".join(_f(ms.get(k), 2) for k in ("view", "render", "loss", "backward", "lock",
                                                                 "optimizer", "strategy", "step")) + " |")
        lines.append("")
    if data.get("realtime"):
        lines += ["## Real time (mode=realtime realtime.fps_limit=30, mapping stops with the stream)", "",
                  "| sequence | backend@map | frames | ATE cm | track fps | stream fps | system fps | mapping steps | "
                  "PSNR dB | Gaussians |", "|---|---|---|---|---|---|---|---|---|---|"]
        for r in data["realtime"]:
            if "error" in r:
                lines.append(f"| {r['sequence']} | {r['variant']} | failed: {r['error']} |")
                continue
            lines.append(f"| {r['sequence']} | {r['variant']} | {r.get('num_frames')} | "
                         f"{_f(100 * r['ate_rmse_m'], 2) if r.get('ate_rmse_m') is not None else '-'} | "
                         f"{_f(r.get('tracking_fps'))} | {_f(r.get('stream_fps'))} | {_f(r.get('fps'))} | "
                         f"{r.get('mapping_steps', r.get('mapping_iterations'))} | {_f(r.get('psnr'), 2)} | "
                         f"{r.get('num_gaussians')} |")
        lines.append("")
    return "\n".join(lines)


# -- stages -----------------------------------------------------------------------------------


def _sync_for(device: str):
    import torch

    return torch.cuda.synchronize if device == "cuda" else (lambda: None)


def _timed(fn, sync, into: list):
    def call(*args, **kwargs):
        sync()
        start = time.perf_counter()
        result = fn(*args, **kwargs)
        sync()
        into.append(time.perf_counter() - start)
        return result

    return call


def load_frames(name: str, data: Path) -> list:
    from slamkit.registry.discovery import default_registry

    plugin, folder = SEQUENCES[name]
    registry = default_registry()
    dataset = registry.create("dataset", plugin, registry.get("dataset", plugin).config(path=str(data / folder)))
    return [dataset[i] for i in range(len(dataset))]


def tracking(name: str, device: str, data: Path, frames: list) -> dict:
    """G-ICP over `frames` (in memory) with the map on `device`; frames/s and the hand-over."""
    import numpy as np

    from slamkit.metrics import trajectory as evaluation
    from slamkit.run.build import build_run

    _, slam, _ = build_run([*sequence_overrides(name, data), "tracker=gicp", "keyframe=overlap", "mapper=none",
                            f"mapping_device={device}", "output.progress=false"])
    sync, grow, target = _sync_for(device), [], []
    slam.grow_map = _timed(slam.grow_map, sync, grow)
    gm = slam.gaussian_map
    gm.tracking_target = _timed(gm.tracking_target, sync, target)
    slam.initialize(frames[0].gt_pose)
    poses, tracking_s = [], 0.0
    for frame in frames:
        step = slam.process(frame)
        tracking_s += step.tracking_time_s
        poses.append(step.tracking.pose)
    ate = evaluation.ate(np.array(poses), [f.gt_pose for f in frames])
    kfs = max(slam.num_keyframes, 1)
    return {"sequence": name, "device": device, "frames": len(frames), "keyframes": slam.num_keyframes,
            "fps": len(frames) / tracking_s, "ms_per_frame": 1e3 * tracking_s / len(frames),
            "ate_rmse_m": ate.rmse_m, "grow_map_ms": 1e3 * sum(grow) / kfs,
            "grow_map_max_ms": 1e3 * max(grow, default=0.0), "target_ms": 1e3 * sum(target) / max(len(target), 1),
            "target_max_ms": 1e3 * max(target, default=0.0), "rows_per_keyframe": len(gm) / kfs,
            "gaussians": len(gm), **copy_times(gm, len(gm) // kfs, device)}


def copy_times(gm, rows: int, device: str, repeats: int = 5) -> dict:
    """The bare hand-over: a keyframe's worth of rows (the map's last `rows`, every column)
    copied from the CPU to `device` and back, milliseconds (best of `repeats`), and its size."""
    import dataclasses

    sync = _sync_for(device)
    last = gm.rows(slice(len(gm) - rows, len(gm)))
    host = {f.name: getattr(last, f.name).cpu() for f in dataclasses.fields(last)}
    ins, outs = [], []
    for _ in range(repeats):
        on_device = _timed(lambda: {k: v.to(device) for k, v in host.items()}, sync, ins)()
        _timed(lambda: {k: v.cpu() for k, v in on_device.items()}, sync, outs)()
    return {"copy_rows": rows, "copy_mb": sum(v.numel() * v.element_size() for v in host.values()) / 1e6,
            "copy_in_ms": 1e3 * min(ins), "copy_out_ms": 1e3 * min(outs)}


def phases(name: str, variant: str, data: Path) -> dict:
    """The map grown over the first PHASE_FRAMES frames, then timed training steps."""
    import torch

    from slamkit.run.build import build_run

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from step_phases import time_steps

    device = variant.split("@")[1]
    dataset, slam, _ = build_run([*sequence_overrides(name, data), f"dataset.max_frames={PHASE_FRAMES}",
                                  "mapper=gaussian_splatting", *variant_overrides(variant), "iterations_per_frame=0",
                                  "output.progress=false"])
    slam.initialize(dataset[0].gt_pose)
    for i in range(len(dataset)):
        slam.process(dataset[i])
    mapper = slam.mapper
    sync = torch.cuda.synchronize if device == "cuda" else None
    time_steps(mapper, PHASE_WARMUP, sync)
    first_loss = mapper.last_loss
    timer = time_steps(mapper, PHASE_STEPS, sync)
    cam = mapper.keyframes[mapper.keyframes.ids[0]].camera
    return {"sequence": name, "variant": variant, "frames": len(dataset), "keyframes": len(mapper.keyframes),
            "gaussians": len(slam.gaussian_map), "resolution": f"{cam.width}x{cam.height}", "steps": timer.steps,
            "ms": timer.per_step_ms(), "cpu_ms": {k: 1e3 * v / max(timer.steps, 1) for k, v in timer.cpu.items()},
            "first_loss": first_loss, "last_loss": mapper.last_loss}


def realtime(name: str, variant: str, data: Path, runs_dir: Path) -> dict:
    from slamkit.cli.bench import SYSTEMS, run_system

    record = run_system(f"{name}_{variant.replace('@', '_at_')}",
                        SYSTEMS["gsicp_realtime30"] + variant_overrides(variant),
                        sequence_overrides(name, data), runs_dir, REALTIME_TIMEOUT_S)
    keep = ("command", "returncode", "process_s", "error", "num_frames", "ate_rmse_m", "tracking_fps", "stream_fps",
            "fps", "mapping_iterations", "mapping_steps", "psnr", "num_gaussians", "peak_memory_mb", "wall_time_s",
            "completed")
    return {"sequence": name, "variant": variant, **{k: record[k] for k in keep if k in record}}


# -- the command ------------------------------------------------------------------------------


def plan(args) -> list[str]:
    """One line per measurement the stages would take."""
    data = data_root(args.data)
    lines = []
    for name in args.sequences:
        lines += [f"tracking {name} map on {d}: G-ICP over {data / SEQUENCES[name][1]} (mapper=none), fps and hand-over"
                  for d in TRACKING_DEVICES]
    for name in args.sequences:
        lines += [f"phases {name} {v}: grow the map over {PHASE_FRAMES} frames, {PHASE_WARMUP}+{PHASE_STEPS} steps "
                  f"by phase ({' '.join(variant_overrides(v))})" for v in selected(PHASE_VARIANTS, args.no_gsplat)]
    sys.path.insert(0, str(REPO))  # the plan runs before slamkit is installed (gpu_check.sh --dry-run)
    from slamkit.cli.bench import SYSTEMS  # no torch: the plan stays quick

    for name in args.sequences:
        lines += [f"realtime {name} {v}: slamkit {' '.join(sequence_overrides(name, data))} "
                  f"{' '.join(SYSTEMS['gsicp_realtime30'] + variant_overrides(v))} (timeout {REALTIME_TIMEOUT_S} s)"
                  for v in selected(REALTIME_VARIANTS, args.no_gsplat)]
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("stage", choices=["plan", "tracking", "phases", "realtime", "note"])
    parser.add_argument("rest", nargs="*", help="note: STEP STATUS SECONDS [DETAIL]; plan: the stages to show")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "gpu_check")
    parser.add_argument("--data", default=None, help="folder holding the sequences (default $SLAMKIT_DATA)")
    parser.add_argument("--sequences", type=lambda s: s.split(","), default=["tum", "replica"])
    parser.add_argument("--no-gsplat", action="store_true", help="leave the gsplat variants out")
    args = parser.parse_args(argv)
    if args.stage == "plan":
        for line in plan(args):
            if not args.rest or line.split()[0] in args.rest:
                print(f"  would time: {line}")
        return 0
    if args.stage == "note":
        step, status, seconds, *detail = args.rest
        merge(args.out, "steps",
              {"step": step, "status": status, "seconds": float(seconds), "detail": " ".join(detail)})
        return 0
    data = data_root(args.data)
    merge(args.out, "machine", machine())
    failures = 0
    for name in args.sequences:
        if args.stage == "tracking":
            frames = load_frames(name, data)
            jobs = [(d, lambda d=d: tracking(name, d, data, frames)) for d in TRACKING_DEVICES]
            say(f"tracking {name}: warm-up (compiled kernels, CUDA context) on 3 frames per device")
            for device in TRACKING_DEVICES:
                try:
                    tracking(name, device, data, frames[:3])
                except Exception:  # reported by the measured run
                    pass
        elif args.stage == "phases":
            jobs = [(v, lambda v=v: phases(name, v, data)) for v in selected(PHASE_VARIANTS, args.no_gsplat)]
        else:
            runs_dir = Path(tempfile.mkdtemp(prefix="gpu_bench_"))
            jobs = [(v, lambda v=v: realtime(name, v, data, runs_dir))
                    for v in selected(REALTIME_VARIANTS, args.no_gsplat)]
        for label, job in jobs:
            say(f"{args.stage} {name} {label} ...")
            start = time.perf_counter()
            try:
                row = job()
            except Exception as exc:  # one failed measurement must not stop the others
                key = "device" if args.stage == "tracking" else "variant"
                row = {"sequence": name, key: label, "error": f"{type(exc).__name__}: {exc}".splitlines()[0]}
            failures += "error" in row
            merge(args.out, args.stage, row)
            say(f"{args.stage} {name} {label}: {summary(args.stage, row)} ({time.perf_counter() - start:.1f} s)")
    return 1 if failures else 0


def summary(stage: str, row: dict) -> str:
    if "error" in row:
        return f"FAILED {row['error']}"
    if stage == "tracking":
        return (f"{row['frames']} frames, {row['fps']:.1f} fps, {row['keyframes']} keyframes; per keyframe grow_map "
                f"{row['grow_map_ms']:.2f} ms, tracking_target {row['target_ms']:.2f} ms; {row['copy_mb']:.2f} MB "
                f"copied in {row['copy_in_ms']:.2f} ms, back in {row['copy_out_ms']:.2f} ms")
    if stage == "phases":
        return f"{row['gaussians']} Gaussians at {row['resolution']}: " + ", ".join(
            f"{k} {v:.1f} ms" for k, v in row["ms"].items())
    return (f"fps {_f(row.get('fps'))}, track {_f(row.get('tracking_fps'))}, PSNR {_f(row.get('psnr'), 2)} dB, "
            f"{row.get('mapping_iterations')} mapping steps")


if __name__ == "__main__":
    sys.exit(main())
