"""Real-time GS-ICP SLAM on a CPU beside the sequential run and tracking alone, on the shared
sequences: PSNR, ATE, frames/s and the mapping steps that fit in the stream.

Each system is one `slamkit` run in its own process (as `slamkit-bench` runs them). TUM fr1/rpy
plays its 150 frames once (5 s at 30 fps); Replica room0's 20 frames are played back and forth
(`dataset.passes`) so that its stream lasts over 10 s. `--variant NAME="OVERRIDES"` adds a
real-time system with extra overrides (an ablation of the mapper's options).

    python benchmarks/realtime.py                                   # both sequences, the default systems
    python benchmarks/realtime.py --sequences tum --variant covered="mapper.admission.skip_covered=true"

Prints a table per sequence and writes JSON (`--out`).
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

from slamkit.cli.bench import SYSTEMS, run_system

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SEQUENCES = {
    "tum": ["dataset=tum", f"dataset.path={DATA / 'tum_fr1_rpy_first150'}"],
    "replica": ["dataset=replica", f"dataset.path={DATA / 'replica_room0_first20'}", "dataset.passes=17"],
}
DEFAULT = "gsicp_realtime30,gsicp_sequential,gicp_realtime"
REALTIME = SYSTEMS["gsicp_realtime30"]
EXTRA = {"gicp_realtime": ["tracker=gicp", "keyframe=overlap", "mapper=none", "mode=realtime", "realtime.fps_limit=30"]}


def row(r: dict) -> list[str]:
    def f(key, scale=1.0, digits=2):
        v = r.get(key)
        return "-" if v is None else f"{v * scale:.{digits}f}"

    steps_per_s = r["mapping_iterations"] / r["stream_time_s"] if r.get("stream_time_s") else None
    return [r["system"], f("ate_rmse_m", 100), f("psnr"), f("stream_fps", digits=1), f("fps", digits=1),
            str(r.get("mapping_iterations", "-")), "-" if steps_per_s is None else f"{steps_per_s:.1f}",
            str(r.get("refine_iterations", "-")), f"{r.get('num_gaussians', 0):,}", f("peak_memory_mb", digits=0),
            " / ".join(f(k, digits=2) for k in ("tracking_cpu_s", "mapping_cpu_s", "loading_cpu_s", "stream_cpu_s"))]


def print_table(sequence: str, records: list[dict]) -> None:
    head = ["system", "ATE cm", "PSNR dB", "stream fps", "run fps", "steps in stream", "steps/s", "refine steps",
            "Gaussians", "peak MB", "stream CPU s: tracking / mapping / loading / all"]
    print(f"\n{sequence}\n| " + " | ".join(head) + " |\n|" + "---|" * len(head))
    for r in records:
        cells = row(r) if r.get("returncode") == 0 else [r["system"], f"failed: {r.get('error', '')[:60]}"]
        print("| " + " | ".join(cells) + " |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequences", default="tum,replica")
    parser.add_argument("--systems", default=DEFAULT)
    parser.add_argument("--variant", action="append", default=[], metavar='NAME="OVERRIDES"')
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="for every system")
    parser.add_argument("--runs-dir", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/realtime.json"))
    args = parser.parse_args()
    systems = {name: {**SYSTEMS, **EXTRA}[name] for name in args.systems.split(",") if name}
    for spec in args.variant:
        name, _, overrides = spec.partition("=")
        systems[name] = REALTIME + overrides.split()
    runs_dir = args.runs_dir or Path(tempfile.mkdtemp(prefix="slamkit-realtime-"))
    results = {}
    for sequence in args.sequences.split(","):
        records = []
        for name, overrides in systems.items():
            print(f"{sequence}: {name} ...", flush=True)
            records.append(run_system(name, overrides, SEQUENCES[sequence] + args.set, runs_dir / sequence, 3600))
        print_table(sequence, records)
        results[sequence] = records
    args.out.parent.mkdir(parents=True, exist_ok=True)
    load = Path("/proc/loadavg").read_text().split()[:3] if Path("/proc/loadavg").exists() else None
    args.out.write_text(json.dumps({"machine": platform.platform(), "when": time.strftime("%Y-%m-%d %H:%M"),
                                    "load_after": load, "results": results}, indent=2, default=str) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
