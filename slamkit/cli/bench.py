"""`slamkit-bench`: the same frames through several SLAM systems in one invocation.

Each system is a list of `slamkit` overrides run in its own process (so peak memory is its own);
the table reports ATE, tracking and whole-system frames/s, PSNR and peak memory, with ratios to
anchors measured in the same run (machines are shared and noisy: compare ratios, not seconds).

    slamkit-bench --dataset tum --path ../shared/data/tum_fr1_rpy_first150 --out bench.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

SYSTEMS: dict[str, list[str]] = {
    "gicp": ["tracker=gicp", "keyframe=overlap", "mapper=none"],
    "gicp_plane": ["tracker=gicp", "tracker.regularization=plane", "keyframe=overlap", "mapper=none"],
    "gicp_none": ["tracker=gicp", "tracker.regularization=none", "keyframe=overlap", "mapper=none"],
    "kiss_icp": ["tracker=kiss_icp", "mapper=none"],
    "small_gicp": ["tracker=small_gicp", "mapper=none"],
    "gsicp_sequential": ["tracker=gicp", "keyframe=overlap", "mapper=gaussian_splatting"],
    # Real time as the reference code: mapping stops with the input stream (real-time mode's default).
    "gsicp_realtime30": ["tracker=gicp", "keyframe=overlap", "mapper=gaussian_splatting", "mode=realtime",
                         "realtime.fps_limit=30"],
    "gsicp_unlimited": ["tracker=gicp", "keyframe=overlap", "mapper=gaussian_splatting", "mode=realtime"],
}
DEFAULT_SYSTEMS = "gicp,gicp_plane,gicp_none,kiss_icp,small_gicp"
COLUMNS = [("ate_rmse_m", "ATE RMSE cm", 100), ("ate_mean_m", "ATE mean cm", 100),
           ("tracking_fps", "track fps", 1), ("stream_fps", "stream fps", 1), ("fps", "system fps", 1),
           ("mapping_iterations", "map iters", 1), ("psnr", "PSNR dB", 1),
           ("num_gaussians", "Gaussians", 1), ("peak_memory_mb", "peak MB", 1), ("lost_frames", "lost", 1)]


def run_system(name: str, overrides: list[str], common: list[str], out_dir: Path, timeout: float) -> dict:
    exe = Path(sys.executable).with_name("slamkit")
    run_dir = out_dir / name
    cmd = [str(exe), *common, *overrides, "output.progress=false", "output.plot=false", f"hydra.run.dir={run_dir}"]
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    record = {"system": name, "command": " ".join(["slamkit", *common, *overrides]),
              "returncode": proc.returncode, "process_s": time.perf_counter() - start}
    metrics_file = run_dir / "metrics.json"
    if proc.returncode == 0 and metrics_file.exists():
        record.update(json.loads(metrics_file.read_text()))
    else:
        record["error"] = (proc.stderr.strip().splitlines() or ["no output"])[-1]
    return record


def signal_to_exit(argv: list[str], cwd: Path, pause_at: str, sig: int = signal.SIGTERM,
                   env: dict[str, str] | None = None, timeout: float = 240) -> dict:
    """`slamkit ARGV` (in `cwd`, `env` added to this process's) sent `sig` once it says it has
    paused at `pause_at` (the run's SLAMKIT_PAUSE_AT test hook): {returncode, seconds (from the
    signal to the exit, None when it never reached the point), reached, stderr}. A run still going
    after `timeout` seconds is killed with its process group."""
    exe = Path(sys.executable).with_name("slamkit")
    proc = subprocess.Popen([str(exe), *argv], cwd=cwd, env=dict(os.environ, **(env or {}), SLAMKIT_PAUSE_AT=pause_at),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    sent: list[float] = []
    said: list[str] = []

    def read() -> None:
        for line in proc.stderr:
            said.append(line)
            if not sent and f"paused at {pause_at}" in line:
                sent.append(time.monotonic())
                proc.send_signal(sig)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    ended = time.monotonic()
    reader.join(timeout=10)
    return {"returncode": proc.returncode, "seconds": ended - sent[0] if sent else None, "reached": bool(sent),
            "stderr": "".join(said)}


def _cell(value, scale: float) -> str:
    if value is None:
        return "-"
    if isinstance(value, (int, float)):
        v = value * scale
        return f"{v:.0f}" if abs(v) >= 1000 else f"{v:.3g}" if abs(v) < 0.01 else f"{v:.2f}"
    return str(value)


def table(records: list[dict], ate_anchor: str | None, speed_anchor: str | None) -> str:
    anchors = {r["system"]: r for r in records}
    header = ["system"] + [label for _, label, _ in COLUMNS]
    if ate_anchor in anchors:
        header.append(f"ATE / {ate_anchor}")
    if speed_anchor in anchors:
        header.append(f"track fps / {speed_anchor}")
    rows = [header]
    for r in records:
        row = [r["system"]] + [_cell(r.get(key), scale) for key, _, scale in COLUMNS]
        if ate_anchor in anchors:
            row.append(_ratio(r.get("ate_rmse_m"), anchors[ate_anchor].get("ate_rmse_m")))
        if speed_anchor in anchors:
            row.append(_ratio(r.get("tracking_fps"), anchors[speed_anchor].get("tracking_fps")))
        if "error" in r and r.get("returncode"):
            row[1] = f"failed: {r['error'][:60]}"
        rows.append(row)
    return markdown_table(rows)


def markdown_table(rows: list[list]) -> str:
    """A Markdown table of `rows` (the first is the header), columns padded to their widest cell."""
    widths = [max(len(str(row[i])) if i < len(row) else 0 for row in rows) for i in range(len(rows[0]))]
    lines = ["| " + " | ".join(str(c).ljust(w) for c, w in zip(row, widths)) + " |" for row in rows]
    lines.insert(1, "|" + "|".join("-" * (w + 2) for w in widths) + "|")
    return "\n".join(lines)


def _ratio(a, b) -> str:
    return f"{a / b:.2f}" if a is not None and b else "-"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="slamkit-bench", description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", default="synthetic", help="dataset plugin (synthetic, tum, replica, ...)")
    parser.add_argument("--path", default=None, help="dataset.path")
    parser.add_argument("--max-frames", type=int, default=None)
    parser.add_argument("--systems", default=DEFAULT_SYSTEMS, help=f"comma-separated, from: {', '.join(SYSTEMS)}")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="an extra override for every system (repeatable)")
    parser.add_argument("--ate-anchor", default="small_gicp")
    parser.add_argument("--speed-anchor", default="kiss_icp")
    parser.add_argument("--out", type=Path, default=None, help="JSON file for the results")
    parser.add_argument("--runs-dir", type=Path, default=None, help="where the runs go (default: a temp dir)")
    parser.add_argument("--timeout", type=float, default=3600)
    args = parser.parse_args(argv)

    unknown = [s for s in args.systems.split(",") if s not in SYSTEMS]
    if unknown:
        parser.error(f"unknown system(s) {', '.join(unknown)}; available: {', '.join(SYSTEMS)}")
    common = [f"dataset={args.dataset}"] + ([f"dataset.path={args.path}"] if args.path else [])
    common += [f"dataset.max_frames={args.max_frames}"] if args.max_frames else []
    common += args.set
    runs_dir = args.runs_dir or Path(tempfile.mkdtemp(prefix="slamkit-bench-"))
    records = []
    for name in args.systems.split(","):
        print(f"running {name} ...", file=sys.stderr, flush=True)
        records.append(run_system(name, SYSTEMS[name], common, runs_dir, args.timeout))
    print(table(records, args.ate_anchor, args.speed_anchor))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        result = {"machine": {"platform": platform.platform(), "processor": platform.processor(),
                              "python": platform.python_version()},
                  "dataset": args.dataset, "path": args.path, "runs_dir": str(runs_dir), "records": records}
        args.out.write_text(json.dumps(result, indent=2, default=str) + "\n")
        print(f"wrote {args.out}", file=sys.stderr)
    return 0 if all(r["returncode"] == 0 for r in records) else 1


if __name__ == "__main__":
    sys.exit(main())
