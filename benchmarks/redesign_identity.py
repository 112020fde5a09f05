"""Identity of a refactoring's outputs (issue 42's acceptance): the same runs made by two versions
of slamkit must give byte-identical `trajectory.txt` and `map.ply` (and `keyframes.txt`,
`loops.csv`) and the same `metrics.json` once its timings (and the process's peak memory) are
set aside.

`run` makes the fixed set of runs below through the public command line (the `slamkit` console
script beside this Python), each its own process, into OUT/<case>. With `--rev REV` the runs use
a snapshot of that git revision (`git archive` into OUT/src, put first on PYTHONPATH, so that the
code being changed in the working tree does not leak into the reference); without it, the
installed (editable) slamkit. A revision before 0.4 knows only the old spellings of the keys
0.4 renamed (issue 42, point 4: `progress` for `output.progress`, ...): its runs are given them,
and `compare` reads its metrics.json under the new keys. `compare` prints one table row a case
and writes JSON.

    python benchmarks/redesign_identity.py run /tmp/ref --rev main       # before
    python benchmarks/redesign_identity.py run /tmp/new                   # after (the working tree)
    python benchmarks/redesign_identity.py compare /tmp/ref /tmp/new      # table + JSON
    python benchmarks/redesign_identity.py timing /tmp/rt --rev b43124f   # real time, alternated

Cases (sequential mode: results independent of the machine's speed): TUM fr1/rpy and Replica
room0 with the 3DGS mapper, 7-Scenes redkitchen with the pose-graph loop closure, a mapped TUM
run stopped after 20 frames and resumed to 40, and a localisation of TUM frames 40-59 in that
resumed run's map. `--tum-frames`, `--sevenscenes-frames` shorten the long ones on a slow machine
(the JSON records the counts used).

`timing` is the real-time half of the acceptance: the mapped TUM run at 30 frames/s (with and
without drop_frames) and 7-Scenes 300-999 with drop_frames (`--cases` picks), the revision's
snapshot and the installed slamkit alternated `--repeats` times, each run its own process; it
prints and writes each side's stream frames/s, mapping steps, ATE and PSNR (medians and every
run). Timings: run it alone on a quiet machine.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
import re
import subprocess
import sys
import tarfile
import time
from pathlib import Path
from typing import Callable

import tomllib

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("SLAMKIT_DATA", REPO.parent / "shared" / "data"))
TUM = ["dataset=tum", f"dataset.path={DATA / 'tum_fr1_rpy_first150'}"]
REPLICA = ["dataset=replica", f"dataset.path={DATA / 'replica_room0_first20'}"]
SEVENSCENES = ["dataset=sevenscenes", f"dataset.path={DATA / '7scenes_redkitchen_300to999'}"]
QUIET = ["output.progress=false", "output.plot=false"]
#: metrics.json keys that measure time or the process's memory, not the result: left out of the
#: comparison (matched on the last part of the dotted key).
TIMING = re.compile(r"(_s|_ms|fps|_cpu_s|peak_memory_mb)$|^delay_|^mapping_step_ms$|_s_per_")
#: metrics.json keys that name a path of the run's inputs (the map a localisation reads): they
#: differ between two output folders by construction.
PATHS = {"map"}
#: Two floats this close (relative) are "equal to rounding": a figure computed from identical
#: files (the ATE of an identical trajectory) may differ in its last bit with BLAS's threading.
ROUNDING = 1e-12
OUTPUTS = ("trajectory.txt", "map.ply", "metrics.json", "keyframes.txt", "loops.csv")
#: metrics.json keys that 0.4 renamed besides the settings' (the memory cap's counters).
RENAMED_METRICS = {"pruned_by_memory_guard": "pruned_by_memory_cap", "memory_guard_prunings": "memory_cap_prunings"}


def cases(tum_frames: int, sevenscenes_frames: int) -> list[tuple[str, list[str]]]:
    """(case, overrides) in run order; `resume` continues `resumed`, `localize` uses its map."""
    mapped = ["mode=sequential", "mapper=gaussian_splatting"]
    return [
        ("tum_mapped", [*TUM, *mapped, f"dataset.max_frames={tum_frames}"]),
        ("replica_mapped", [*REPLICA, *mapped]),
        ("sevenscenes_loop", [*SEVENSCENES, "mode=sequential", "mapper=none", "loop_closure=pose_graph",
                              f"dataset.max_frames={sevenscenes_frames}"]),
        ("resumed", [*TUM, *mapped, "dataset.max_frames=20", "checkpoint.save=true"]),
        ("resume", ["dataset.max_frames=40"]),  # resume=OUT/resumed, added at run time
        ("localize", [*TUM, "mode=localize", "dataset.start=40", "dataset.max_frames=20"]),
    ]


def snapshot(rev: str, dest: Path) -> Path:
    """The revision's tree under dest, importable as `slamkit` and `slamkit_plugins`, with the
    revision's own entry points (its plugins' module paths may differ from the installed ones)."""
    dest.mkdir(parents=True, exist_ok=True)
    blob = subprocess.run(["git", "-C", str(REPO), "archive", rev], check=True, capture_output=True).stdout
    with tarfile.open(fileobj=io.BytesIO(blob)) as tar:
        tar.extractall(dest, filter="data")
    project = tomllib.loads((dest / "pyproject.toml").read_text())
    # the wheel's package-dir mapping (plugins/ -> slamkit_plugins, and conf/ -> slamkit/conf where
    # the revision has one), as links
    for package, folder in project["tool"]["setuptools"].get("package-dir", {}).items():
        link = dest / package.replace(".", "/")
        if not link.exists():
            link.symlink_to(os.path.relpath(dest / folder, link.parent))
    # first on PYTHONPATH, this distribution's entry points are the ones importlib.metadata reads
    info = dest / "slamkit-0.0.0.dist-info"
    info.mkdir(exist_ok=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: slamkit\nVersion: 0.0.0\n")
    points = project["project"]["entry-points"]
    (info / "entry_points.txt").write_text("".join(
        f"[{group}]\n" + "".join(f"{k} = {v}\n" for k, v in eps.items()) for group, eps in points.items()))
    return dest


def renamed_in_0_4() -> dict[str, str]:
    """{old key: new key} of the run keys that slamkit 0.4 renamed (`fps_limit`: `realtime.fps_limit`)."""
    from slamkit.registry.compose import RENAMED_IN

    return RENAMED_IN["0.4"]


def old_spellings(overrides: list[str]) -> list[str]:
    """`overrides` as a revision before 0.4 spells them (`output.progress=false` -> `progress=false`)."""
    old = {new: old for old, new in renamed_in_0_4().items()}
    return [old.get(key, key) + sep + value for key, sep, value in (o.partition("=") for o in overrides)]


def revision(rev: str | None, out: Path) -> tuple[dict, Callable[[list[str]], list[str]]]:
    """(environment, spelling) of runs made by `rev`'s snapshot under out/src (None: the
    installed slamkit): the environment puts it first on PYTHONPATH, and the spelling gives a
    revision before 0.4 the old spellings of the overrides."""
    env = dict(os.environ)
    if not rev:
        return env, list
    src = snapshot(rev, out / "src")
    env["PYTHONPATH"] = os.pathsep.join([str(src), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    schema = src / "slamkit" / "registry" / "schema.py"
    before_0_4 = not schema.exists() or "class RealtimeConfig" not in schema.read_text()
    return env, old_spellings if before_0_4 else list


def run(out: Path, rev: str | None, tum_frames: int, sevenscenes_frames: int) -> None:
    out.mkdir(parents=True, exist_ok=True)
    env, spelled = revision(rev, out)  # spelled: the overrides as the slamkit that runs them spells its keys
    exe = Path(sys.executable).with_name("slamkit")
    log = {"rev": rev, "tum_frames": tum_frames, "sevenscenes_frames": sevenscenes_frames, "runs": {}}
    for name, overrides in cases(tum_frames, sevenscenes_frames):
        extra = {"resume": [f"resume={out / 'resumed'}"], "localize": [f"map={out / 'resumed'}"]}.get(name, [])
        run_dir = out / ("resumed" if name == "resume" else name)
        # a resume writes into the folder it continues; hydra.run.dir must not be given then
        where = [] if name == "resume" else [f"hydra.run.dir={run_dir}"]
        cmd = [str(exe), *spelled([*extra, *overrides, *QUIET]), *where]
        start = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=out)
        log["runs"][name] = {"command": " ".join(cmd), "returncode": proc.returncode,
                             "process_s": round(time.perf_counter() - start, 1),
                             "last_line": (proc.stderr.strip().splitlines() or [""])[-1]}
        print(f"{name}: exit {proc.returncode}, {log['runs'][name]['process_s']} s", flush=True)
        if name == "resumed":  # keep the first session's outputs apart: the resume extends them
            _copy_outputs(run_dir, out / "resumed_first")
    (out / "runs.json").write_text(json.dumps(log, indent=2))


#: (case, overrides) of `timing`: the real-time runs whose stream rate and mapping steps a
#: redesign must keep.
REALTIME_CASES = [
    ("tum_realtime30", [*TUM, "mode=realtime", "realtime.fps_limit=30", "mapper=gaussian_splatting"]),
    ("tum_realtime30_drop", [*TUM, "mode=realtime", "realtime.fps_limit=30", "realtime.drop_frames=true",
                             "mapper=gaussian_splatting"]),
    ("sevenscenes_realtime30_drop", [*SEVENSCENES, "mode=realtime", "realtime.fps_limit=30",
                                     "realtime.drop_frames=true", "mapper=gaussian_splatting"]),
]
TIMING_KEYS = ("stream_fps", "mapping_steps", "ate_rmse_m", "psnr", "dropped_frames")


def timing(out: Path, rev: str, repeats: int, out_json: Path, only: tuple[str, ...] = ()) -> None:
    """Alternate the revision's runs with the installed slamkit's (before, after, before, ...)
    for each REALTIME_CASES case (those named in `only`, if any); write {case: {side: [metrics
    of each run]}} and medians."""
    import statistics

    out.mkdir(parents=True, exist_ok=True)
    sides = {"before": revision(rev, out), "after": revision(None, out)}  # (environment, spelling)
    exe = Path(sys.executable).with_name("slamkit")
    results: dict = {"rev": rev, "repeats": repeats, "cases": {}}
    for name, overrides in [c for c in REALTIME_CASES if not only or c[0] in only]:
        runs: dict[str, list] = {"before": [], "after": []}
        for i in range(repeats):
            for side in ("before", "after"):
                run_dir = out / f"{name}_{side}_{i}"
                env, spelled = sides[side]
                cmd = [str(exe), *spelled([*overrides, *QUIET, "output.existing_outputs=clean"]),
                       f"hydra.run.dir={run_dir}"]
                proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=out)
                metrics = json.loads((run_dir / "metrics.json").read_text()) if proc.returncode == 0 else {}
                flat = {key.rsplit(".", 1)[-1]: v for key, v in _flat(metrics, timings=True).items()}
                runs[side].append({k: flat.get(k) for k in TIMING_KEYS} | {"returncode": proc.returncode})
                print(f"{name} {side} {i}: " + ", ".join(f"{k} {runs[side][-1][k]}" for k in TIMING_KEYS), flush=True)
        medians = {side: {k: statistics.median(r[k] for r in rs if r[k] is not None)
                          for k in TIMING_KEYS if any(r[k] is not None for r in rs)} for side, rs in runs.items()}
        results["cases"][name] = {"runs": runs, "median": medians}
        b, a = medians["before"], medians["after"]
        print(f"{name}: stream fps {b.get('stream_fps', 0):.2f} -> {a.get('stream_fps', 0):.2f}, mapping steps "
              f"{b.get('mapping_steps', 0):.0f} -> {a.get('mapping_steps', 0):.0f} (medians of {repeats})", flush=True)
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(results, indent=2))
    print(out_json)


def _copy_outputs(src: Path, dest: Path) -> None:
    dest.mkdir(parents=True, exist_ok=True)
    for name in OUTPUTS:
        if (src / name).exists():
            (dest / name).write_bytes((src / name).read_bytes())


def _flat(d: dict, prefix: str = "", timings: bool = False) -> dict:
    """Every leaf of a nested dict under its dotted key; the timings left out unless `timings`."""
    flat = {}
    for key, value in d.items():
        if not timings and TIMING.search(key):  # a timing, or a dict of them (mapping_step_ms)
            continue
        if isinstance(value, dict):
            flat.update(_flat(value, f"{prefix}{key}.", timings))
        else:
            flat[prefix + key] = value
    return flat


def _metrics(path: Path) -> dict:
    """metrics.json flattened (`_flat`), a run before 0.4's keys under their 0.4 names (its
    `settings.fps_limit` is `settings.realtime.fps_limit`), so that a revision before the rename
    compares with one after it."""
    renamed = {**{f"settings.{old}": f"settings.{new}" for old, new in renamed_in_0_4().items()}, **RENAMED_METRICS}
    return {renamed.get(key, key): value for key, value in _flat(json.loads(path.read_text())).items()}


def _rounding(a, b) -> bool:
    """Both floats, within ROUNDING of each other (relative)."""
    return (isinstance(a, float) and isinstance(b, float)
            and abs(a - b) <= ROUNDING * max(abs(a), abs(b), 1e-300))


def compare_dirs(a: Path, b: Path) -> dict:
    """Per output: 'identical', 'equal to rounding (keys)' (metrics.json), 'differs (...)', or
    'missing ...'."""
    result = {}
    for name in OUTPUTS:
        fa, fb = a / name, b / name
        if not fa.exists() and not fb.exists():
            continue
        if not (fa.exists() and fb.exists()):
            result[name] = "missing in " + ("before" if not fa.exists() else "after")
        elif name == "metrics.json":
            ma, mb = _metrics(fa), _metrics(fb)
            diff = sorted(k for k in ma.keys() | mb.keys()
                          if k not in PATHS and ma.get(k, "<absent>") != mb.get(k, "<absent>"))
            real = [k for k in diff if not _rounding(ma.get(k), mb.get(k))]
            result[name] = ("identical" if not diff else f"differs ({', '.join(real[:6])})" if real
                            else f"equal to rounding ({', '.join(diff[:6])})")
        else:
            ha, hb = (hashlib.sha256(f.read_bytes()).hexdigest() for f in (fa, fb))
            result[name] = "identical" if ha == hb else "differs"
    return result


def compare(before: Path, after: Path, out_json: Path) -> bool:
    names = [n for n, _ in cases(0, 0) if n != "resume"] + ["resumed_first"]
    rows, same = {}, True
    print(f"{'case':<18} {'trajectory.txt':<16} {'map.ply':<16} {'keyframes.txt':<14} {'loops.csv':<12} "
          "metrics.json (timings aside)")
    for name in names:
        rows[name] = compare_dirs(before / name, after / name)
        same &= all(not v.startswith(("differs", "missing")) for v in rows[name].values()) and bool(rows[name])
        r = rows[name]
        print(f"{name:<18} {r.get('trajectory.txt', '-'):<16} {r.get('map.ply', '-'):<16} "
              f"{r.get('keyframes.txt', '-'):<14} {r.get('loops.csv', '-'):<12} {r.get('metrics.json', '-')}")
    runs = {side: json.loads((d / "runs.json").read_text()) for side, d in (("before", before), ("after", after))}
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps({"identical": same, "cases": rows, "runs": runs}, indent=2))
    print(f"{'all identical' if same else 'NOT identical'}; {out_json}")
    return same


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p_run = sub.add_parser("run", help="make the fixed set of runs into OUT")
    p_run.add_argument("out", type=Path)
    p_run.add_argument("--rev", help="a git revision to run from a snapshot (default: the installed slamkit)")
    p_run.add_argument("--tum-frames", type=int, default=150)
    p_run.add_argument("--sevenscenes-frames", type=int, default=700)
    p_cmp = sub.add_parser("compare", help="compare two OUT folders")
    p_cmp.add_argument("before", type=Path)
    p_cmp.add_argument("after", type=Path)
    p_cmp.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "redesign_identity.json")
    p_time = sub.add_parser("timing", help="real-time runs of REV and the installed slamkit, alternated")
    p_time.add_argument("out", type=Path)
    p_time.add_argument("--rev", required=True)
    p_time.add_argument("--repeats", type=int, default=3)
    p_time.add_argument("--cases", default="", help="comma-separated REALTIME_CASES names (default: all)")
    p_time.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "redesign_realtime.json")
    args = parser.parse_args(argv)
    if args.command == "timing":
        timing(args.out, args.rev, args.repeats, args.json, tuple(filter(None, args.cases.split(","))))
        return 0
    if args.command == "run":
        run(args.out, args.rev, args.tum_frames, args.sevenscenes_frames)
        return 0
    return 0 if compare(args.before, args.after, args.out) else 1


if __name__ == "__main__":
    sys.exit(main())
