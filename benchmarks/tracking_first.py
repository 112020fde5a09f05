"""Tracking first (issue 37): does real time keep the input rate while the map trains?

Measured as a user meets it: the real `slamkit` command, each run its own process, in real time
(`mode=realtime realtime.fps_limit=30`), tracking alone (`mapper=none`) and with the mapper
(`mapper=gaussian_splatting`), alternated A/B/A/B in one invocation (`--repeats` pairs), on TUM
fr1/rpy frames 0-149 and 7-Scenes redkitchen 300-999. Then the same pairs with
`realtime.drop_frames=true` (a camera that does not wait), and the sequential tracking-only CPU per frame
on TUM (`stream_cpu_s / frames`, every thread, reading included) with its ATE.

Prints, per sequence, every run and the medians: stream frames/s, the with/without ratio,
mapping steps in the stream, PSNR, CPU seconds per frame for reading, tracking and mapping (and
the process's), the time mapping waited for a CPU or yielded to a late tracker, the dropped fraction; then the issue's
acceptance targets against the medians. Writes JSON (`--out`).

    python benchmarks/tracking_first.py                       # the full run (~20 min on 2 cores)
    python benchmarks/tracking_first.py --quick               # a smoke test: 30 frames, one pair
    python benchmarks/tracking_first.py --variant low="realtime.mapping_priority=low"   # a third system
    python benchmarks/tracking_first.py --only-drop --set tracker.retry_unconverged=true   # drops only

Run it alone on a quiet machine: frames/s are wall-clock figures.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import tempfile
import time
from pathlib import Path

from slamkit.cli.bench import run_system

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SEQUENCES = {
    "tum": lambda data: ["dataset=tum", f"dataset.path={data / 'tum_fr1_rpy_first150'}"],
    "7scenes": lambda data: ["dataset=sevenscenes", f"dataset.path={data / '7scenes_redkitchen_300to999'}"],
}
#: Overrides of the runs with the mapper, by sequence: 7-Scenes' PSNR over every 10th of its 700
#: frames (the evaluation runs after the stream and is no target here).
MAPPER_SET = {"7scenes": ["mapper.eval_every=10"]}
COMMON = ["tracker=gicp", "keyframe=overlap"]
REALTIME = ["mode=realtime", "realtime.fps_limit=30"]
TRACKING = ["mapper=none"]
MAPPING = ["mapper=gaussian_splatting"]
#: Issue 37's acceptance targets.
TARGETS = {"ratio": 0.95, "tum_steps": 200, "tum_psnr": 17.7, "sequential_cpu_ms": 33.0, "drop_ratio": 1.1}


def per_frame(record: dict, key: str) -> float | None:
    value, frames = record.get(key), record.get("num_frames")
    return value / frames if value is not None and frames else None


def dropped_fraction(record: dict) -> float | None:
    tracked, dropped = record.get("num_frames"), record.get("dropped_frames")
    return dropped / (tracked + dropped) if tracked is not None and dropped is not None and tracked + dropped else None


def summarise(records: list[dict]) -> dict:
    """Medians over the runs that completed, of the figures the table shows."""
    ok = [r for r in records if r.get("returncode") == 0]

    def median(f):
        values = [v for v in map(f, ok) if v is not None]
        return statistics.median(values) if values else None

    return {
        "runs": len(records), "completed": len(ok),
        "stream_fps": median(lambda r: r.get("stream_fps")),
        "mapping_iterations": median(lambda r: r.get("mapping_iterations")),
        "psnr": median(lambda r: r.get("psnr")),
        "ate_rmse_m": median(lambda r: r.get("ate_rmse_m")),
        "loading_cpu_ms_per_frame": median(lambda r: _ms(per_frame(r, "loading_cpu_s"))),
        "tracking_cpu_ms_per_frame": median(lambda r: _ms(per_frame(r, "tracking_cpu_s"))),
        "mapping_cpu_ms_per_frame": median(lambda r: _ms(per_frame(r, "mapping_cpu_s"))),
        "stream_cpu_ms_per_frame": median(lambda r: _ms(per_frame(r, "stream_cpu_s"))),
        "tracking_cpu_wait_s": median(lambda r: r.get("tracking_cpu_wait_s")),
        "mapping_cpu_wait_s": median(lambda r: r.get("mapping_cpu_wait_s")),
        "mapping_yielded_s": median(lambda r: r.get("mapping_yielded_s")),
        "keyframe_handover_s": median(lambda r: r.get("keyframe_handover_s")),
        "dropped_fraction": median(dropped_fraction),
    }


def _ms(seconds: float | None) -> float | None:
    return None if seconds is None else 1e3 * seconds


def _f(value, digits=2, scale=1.0) -> str:
    return "-" if value is None else f"{value * scale:.{digits}f}"


def row(name: str, r: dict) -> list[str]:
    if "stream_cpu_ms_per_frame" not in r:  # a run, not a summary
        if r.get("returncode") != 0:
            return [name, f"failed: {r.get('error', '')[:70]}"]
        r = {**r, **{k: v for k, v in summarise([r]).items() if k.endswith("per_frame") or k == "dropped_fraction"}}
    return [name, _f(r.get("stream_fps"), 1), str(r.get("mapping_iterations", "-")), _f(r.get("psnr")),
            _f(r.get("ate_rmse_m"), 2, 100),
            " / ".join(_f(r.get(f"{k}_cpu_ms_per_frame"), 1) for k in ("loading", "tracking", "mapping", "stream")),
            _f(r.get("tracking_cpu_wait_s")), _f(r.get("mapping_cpu_wait_s")), _f(r.get("mapping_yielded_s")),
            _f(r.get("dropped_fraction"), 3)]


HEAD = ["run", "stream fps", "mapping steps", "PSNR dB", "ATE cm",
        "CPU ms/frame: reading / tracking / mapping / all", "tracking CPU wait s", "mapping CPU wait s",
        "mapping yielded s", "dropped fraction"]


def print_table(title: str, rows: list[list[str]]) -> None:
    print(f"\n{title}\n| " + " | ".join(HEAD) + " |\n|" + "---|" * len(HEAD))
    for cells in rows:
        print("| " + " | ".join(cells) + " |")


def alternate(systems: dict[str, list[str]], common: list[str], repeats: int, runs_dir: Path, label: str,
              timeout: float) -> dict[str, list[dict]]:
    """Every system once per round, `repeats` rounds (A/B/A/B...), each run a fresh process."""
    records: dict[str, list[dict]] = {name: [] for name in systems}
    for k in range(repeats):
        for name, overrides in systems.items():
            print(f"{label}: {name} {k + 1}/{repeats} ...", flush=True)
            records[name].append(run_system(f"{name}_{k}", overrides, common, runs_dir / label, timeout))
    return records


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequences", default="tum,7scenes")
    parser.add_argument("--repeats", type=int, default=3, help="A/B pairs per sequence (medians over them)")
    parser.add_argument("--quick", action="store_true", help="30 frames a sequence, one pair: a smoke test")
    parser.add_argument("--variant", action="append", default=[], metavar='NAME="OVERRIDES"',
                        help="a further real-time system with the mapper and these overrides, alternated too")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="for every run")
    parser.add_argument("--no-drop", action="store_true", help="skip the realtime.drop_frames=true pairs")
    parser.add_argument("--only-drop", action="store_true",
                        help="only the realtime.drop_frames=true pairs (no every-frame pairs, no sequential run)")
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--runs-dir", type=Path, default=None)
    parser.add_argument("--timeout", type=float, default=1800)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/tracking_first.json"))
    args = parser.parse_args()
    repeats = 1 if args.quick else args.repeats
    extra = (["dataset.max_frames=30"] if args.quick else []) + args.set
    runs_dir = args.runs_dir or Path(tempfile.mkdtemp(prefix="slamkit-tracking-first-"))
    realtime = {"tracking": COMMON + TRACKING + REALTIME, "mapping": COMMON + MAPPING + REALTIME}
    for spec in args.variant:
        name, _, overrides = spec.partition("=")
        realtime[name] = COMMON + MAPPING + REALTIME + overrides.split()
    result: dict = {"machine": platform.platform(), "processor": platform.processor(),
                    "when": time.strftime("%Y-%m-%d %H:%M"), "quick": args.quick, "repeats": repeats,
                    "set": args.set, "systems": realtime, "sequences": {}}
    for sequence in args.sequences.split(","):
        common = SEQUENCES[sequence](args.data) + extra
        entry = result["sequences"][sequence] = {}
        systems = {name: overrides + (MAPPER_SET.get(sequence, []) if "mapper=gaussian_splatting" in overrides else [])
                   for name, overrides in realtime.items()}
        if not args.only_drop:
            entry["realtime"] = alternate(systems, common, repeats, runs_dir, f"{sequence}-realtime", args.timeout)
        if not args.no_drop:
            dropping = {name: overrides + ["realtime.drop_frames=true"] for name, overrides in systems.items()}
            entry["drop_frames"] = alternate(dropping, common, repeats, runs_dir, f"{sequence}-drop", args.timeout)
        entry["medians"] = {part: {name: summarise(records) for name, records in entry[part].items()}
                            for part in ("realtime", "drop_frames") if part in entry}
        rows = []
        for part in ("realtime", "drop_frames"):
            for name, records in entry.get(part, {}).items():
                rows += [row(f"{part} {name} {k + 1}", r) for k, r in enumerate(records)]
                rows.append(row(f"**{part} {name} median**", entry["medians"][part][name]))
        print_table(f"{sequence} (input {common[1].split('=', 1)[1]})", rows)
    if "tum" in args.sequences.split(",") and not args.only_drop:
        common = SEQUENCES["tum"](args.data) + extra
        sequential = alternate({"sequential_tracking": COMMON + TRACKING}, common, repeats, runs_dir, "tum-sequential",
                               args.timeout)["sequential_tracking"]
        result["sequential_tracking"] = {"runs": sequential, "median": summarise(sequential)}
        print_table("tum sequential, tracking only", [row(f"sequential {k + 1}", r) for k, r in enumerate(sequential)]
                    + [row("**median**", result["sequential_tracking"]["median"])])
    result["acceptance"] = acceptance(result)
    print("\nacceptance (issue 37), from the medians:")
    for name, check in result["acceptance"].items():
        verdict = "compare by hand" if check["met"] is None else "met" if check["met"] else "NOT met"
        print(f"  {name}: {check['value']} (target {check['target']}): {verdict}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    load = Path("/proc/loadavg").read_text().split()[:3] if Path("/proc/loadavg").exists() else None
    result["load_after"], result["runs_dir"] = load, str(runs_dir)
    args.out.write_text(json.dumps(result, indent=2, default=str) + "\n")
    print(f"wrote {args.out}")


def acceptance(result: dict) -> dict:
    """Each target of issue 37 with the value measured (medians) and whether it is met."""
    checks = {}

    def check(name, value, target, met):
        checks[name] = {"value": None if value is None else round(value, 4), "target": target,
                        "met": bool(value is not None and met(value))}

    for sequence, entry in result["sequences"].items():
        med = entry["medians"].get("realtime")  # None with --only-drop
        if med is not None:
            alone, mapped = med["tracking"]["stream_fps"], med["mapping"]["stream_fps"]
            ratio = mapped / alone if alone and mapped is not None else None
            check(f"{sequence}: stream fps with the mapper / tracking alone", ratio, f">= {TARGETS['ratio']}",
                  lambda v: v >= TARGETS["ratio"])
        if med is not None and sequence == "tum":
            steps, psnr = TARGETS["tum_steps"], TARGETS["tum_psnr"]
            check("tum: mapping steps in the stream", med["mapping"]["mapping_iterations"], f">= {steps}",
                  lambda v: v >= steps)
            check("tum: PSNR dB", med["mapping"]["psnr"], f">= {psnr}", lambda v: v >= psnr)
        if "drop_frames" in entry["medians"]:
            drop = entry["medians"]["drop_frames"]
            alone_d, mapped_d = drop["tracking"]["dropped_fraction"], drop["mapping"]["dropped_fraction"]
            check(f"{sequence}: dropped fraction with the mapper (tracking alone {alone_d})", mapped_d,
                  f"<= {TARGETS['drop_ratio']} x tracking alone's",
                  lambda v: alone_d is not None and v <= TARGETS["drop_ratio"] * alone_d)
    if "sequential_tracking" in result:
        med = result["sequential_tracking"]["median"]
        check("tum: sequential tracking-only CPU ms per frame (stream_cpu_s / frames)", med["stream_cpu_ms_per_frame"],
              f"<= {TARGETS['sequential_cpu_ms']}", lambda v: v <= TARGETS["sequential_cpu_ms"])
        checks["tum: sequential tracking-only ATE cm"] = {"value": _f(med["ate_rmse_m"], 3, 100),
                                                          "target": "unchanged (4.90 cm)", "met": None}
    return checks


if __name__ == "__main__":
    main()
