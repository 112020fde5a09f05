"""The runs behind docs/paper.md's tables: run them, and keep what the tables are written from.

`run GROUP OUT` runs one group of docs/paper.md's runs (the commands are GROUPS below, on the
shared data; `--data` names the folder) into OUT, one run or sweep each, recording the load
average before and after every one. `collect OUT GROUP` then copies, for every run under OUT, its
metrics.json and the overrides it ran with (.hydra/overrides.yaml, the data folder written as
$DATA) into benchmarks/results/paper/GROUP/, with provenance.json: the commit, the date, the
machine, the load and the commands. `slamkit-report --docs docs/paper.md` writes the tables from
those files and tests/core/test_paper_docs.py checks that the document agrees with them.

    python benchmarks/paper_results.py run realtime /tmp/paper_runs/realtime     # ~6 min on 2 cores
    python benchmarks/paper_results.py collect /tmp/paper_runs/realtime realtime
    python benchmarks/paper_results.py run table6 /tmp/paper_runs/table6         # sequential sweeps
    python benchmarks/paper_results.py run table7 /tmp/t7 --only tum             # one entry of a group
    python benchmarks/paper_results.py collect /tmp/t7 table7 --only tum          # beside its others
    slamkit-report --docs docs/paper.md

Frames/s depend on the machine and its load: the provenance says which; quality metrics of a
sequential run do not.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "paper"
DEFAULT_DATA = REPO.parent / "shared" / "data"
TUM = "dataset=tum dataset.path=$DATA/tum_fr1_rpy_first150"
REPLICA = "dataset=replica dataset.path=$DATA/replica_room0_first20"
#: GROUP: [(name, the slamkit arguments)]; `-m +experiment=...` ones are sweeps.
GROUPS = {
    "realtime": [("tum_paper", f"preset=paper {TUM}"), ("tum_paper_unlimited", f"preset=paper_unlimited {TUM}"),
                 ("tum_default", f"mode=realtime realtime.fps_limit=30 mapper=gaussian_splatting {TUM}"),
                 ("replica_paper", f"preset=paper {REPLICA}"),
                 ("replica_paper_unlimited", f"preset=paper_unlimited {REPLICA}"),
                 ("replica_default", f"mode=realtime realtime.fps_limit=30 mapper=gaussian_splatting {REPLICA}")],
    "table5": [("tum", f"-m +experiment=ablation_regularization {TUM} mapper.resolution_scale=0.5")],
    "table6": [("replica", f"-m +experiment=ablation_scale_alignment {REPLICA}")],
    "table7": [("replica", f"-m +experiment=ablation_keyframes {REPLICA}"),
               ("tum", f"-m +experiment=ablation_keyframes {TUM} mapper.resolution_scale=0.5")],
    "table8a": [("replica", f"-m +experiment=ablation_training_keyframes {REPLICA}"),
                ("tum", f"-m +experiment=ablation_training_keyframes {TUM} mapper.resolution_scale=0.5")],
    "table8b": [("replica", f"-m +experiment=ablation_densify_prune {REPLICA}")],
    "fig3": [("replica", f"-m +experiment=ablation_keyframe_selection {REPLICA}")],
    # not a paper table: docs/results.md's tracker ablation (any tracker under the 3DGS mapper)
    "ablation_tracker": [
        ("tum", f"-m +experiment=ablation_tracker tracker=gicp,kiss_icp,small_gicp,p2plane {TUM}"),
        ("replica", f"-m +experiment=ablation_tracker tracker=gicp,kiss_icp,small_gicp,p2plane {REPLICA}")],
}


def load_average() -> str:
    return " ".join(Path("/proc/loadavg").read_text().split()[:3]) if Path("/proc/loadavg").exists() else "?"


def machine() -> str:
    model = platform.processor() or platform.machine()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        names = [line.split(":", 1)[1].strip() for line in cpuinfo.read_text().splitlines()
                 if line.startswith("model name")]
        model = names[0] if names else model
    return f"{model}, {os.cpu_count()} cores, no GPU used"


def git_commit() -> str:
    head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "slamkit", "plugins"],
                           capture_output=True, text=True).stdout.strip()
    return head.stdout.strip() + (" (with uncommitted changes to slamkit/ or plugins/)" if dirty else "")


def run_group(group: str, out: Path, data: Path, only: str | None = None) -> None:
    """The group's runs (`only`: its entry of that name alone) into `out`, with run_record.json."""
    slamkit = Path(sys.executable).with_name("slamkit")
    record = {"group": group, "commit": git_commit(), "machine": machine(), "runs": []}
    out.mkdir(parents=True, exist_ok=True)
    for name, arguments in GROUPS[group]:
        if only is not None and name != only:
            continue
        args = arguments.replace("$DATA", str(data)).split()
        where = "hydra.sweep.dir" if "-m" in args else "hydra.run.dir"
        before, started = load_average(), datetime.datetime.now(datetime.timezone.utc)
        t0 = time.perf_counter()
        done = subprocess.run([str(slamkit), *args, f"{where}={out / name}"])
        record["runs"].append({"name": name, "command": f"slamkit {arguments} {where}=OUT/{name}",
                               "started": started.strftime("%Y-%m-%d %H:%M UTC"), "load_before": before,
                               "load_after": load_average(), "seconds": round(time.perf_counter() - t0, 1),
                               "exit_status": done.returncode})
        print(f"{name}: exit {done.returncode}, load {before} -> {record['runs'][-1]['load_after']}")
    (out / "run_record.json").write_text(json.dumps(record, indent=2) + "\n")


def collect(src: Path, group: str, data: Path, load_note: str | None, only: str | None = None) -> Path:
    """Copy the runs' small files into RESULTS/group and write its provenance.json; `only`: the
    runs of the group's entry of that name (`run --only`) into RESULTS/group/only, with a
    provenance.json of their own there, the group's other runs kept."""
    dest = RESULTS / group if only is None else RESULTS / group / only
    if only is not None:
        src = src / only
    runs = sorted(p.parent for p in src.rglob("metrics.json"))
    if not runs:
        raise SystemExit(f"{src}: no metrics.json under it (expected the folder `run` wrote)")
    if dest.exists():
        shutil.rmtree(dest)
    for run in runs:
        target = dest / run.relative_to(src)
        (target / ".hydra").mkdir(parents=True)
        metrics = json.loads((run / "metrics.json").read_text())
        (target / "metrics.json").write_text(json.dumps(metrics, indent=1) + "\n")
        renders = sorted(run.glob("render_*.png"))
        if renders and group == "realtime":  # the middle one, 640 pixels across: Fig. 5 of the HTML report, per preset
            from PIL import Image

            image = Image.open(renders[len(renders) // 2])
            image.thumbnail((640, 640))
            image.save(target / renders[len(renders) // 2].name, optimize=True)
        overrides = run / ".hydra" / "overrides.yaml"
        if overrides.exists():
            text = overrides.read_text().replace(str(data.resolve()), "$DATA").replace(str(data), "$DATA")
            (target / ".hydra" / "overrides.yaml").write_text(text)
    record_path = (src.parent if only is not None else src) / "run_record.json"
    record = json.loads(record_path.read_text()) if record_path.exists() else {"group": group}
    loads = [r[k] for r in record.get("runs", []) for k in ("load_before", "load_after")]
    firsts = [float(x.split()[0]) for x in loads if x != "?"]
    record.setdefault("commit", git_commit())
    record.setdefault("machine", machine())
    record["group"] = group
    record["date"] = min((r["started"] for r in record.get("runs", [])), default=record.get("date", "?"))
    if firsts:
        record["load_average"] = f"{min(firsts):.1f}-{max(firsts):.1f}"
    if load_note:
        record["load_note"] = load_note
    record["data"] = "$DATA: the shared frames (TUM fr1/rpy 0-149, Replica room0 0-19, 7-Scenes redkitchen 300-999)"
    (dest / "provenance.json").write_text(json.dumps(record, indent=2) + "\n")
    print(f"{len(runs)} runs into {dest}")
    return dest


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run a group of docs/paper.md's runs")
    run.add_argument("group", choices=sorted(GROUPS))
    run.add_argument("out", type=Path)
    run.add_argument("--data", type=Path, default=DEFAULT_DATA)
    run.add_argument("--only", metavar="NAME", help="the group's entry of that name alone (e.g. tum)")
    col = sub.add_parser("collect", help="keep a group's metrics and overrides under benchmarks/results/paper/")
    col.add_argument("src", type=Path)
    col.add_argument("group", choices=sorted(GROUPS))
    col.add_argument("--data", type=Path, default=DEFAULT_DATA)
    col.add_argument("--load-note", help="what the load average means (default: a machine shared with other work)")
    col.add_argument("--only", metavar="NAME", help="the runs of `run --only NAME`, the group's others kept")
    args = parser.parse_args(argv)
    if args.command == "run":
        run_group(args.group, args.out, args.data, args.only)
    else:
        collect(args.src, args.group, args.data, args.load_note, args.only)
    return 0


if __name__ == "__main__":
    sys.exit(main())
