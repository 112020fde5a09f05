"""The run folders a report reads: finding them (a run, or folders of runs and sweeps), and each
one's settings, metrics and status, including the jobs a sweep recorded but never started.

Shared by `slamkit-report`, the paper tables and the HTML report, which each present them.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import yaml

from slamkit.errors import DataError
from slamkit.registry.compose import BASIC_SWEEPER

STATUSES = ("completed", "interrupted", "failed", "running")
#: A sweep's job that never started (no folder).
NOT_RUN = "not run"
#: Hydra's job folder name: the jobs a sweep record stands for.
JOB_NUMBER_SUBDIR = "${hydra.job.num}"


def find_runs(dirs: list[Path]) -> list[Path]:
    """Run directories under the given folders, sorted: those holding metrics.json, and job
    folders (Hydra's .hydra/) that have none yet."""
    for d in dirs:
        if not Path(d).is_dir():
            raise DataError(f"{d} not found (expected a run folder, or a folder of runs or sweeps)")
    runs = sorted({p.parent for d in dirs for p in Path(d).rglob("metrics.json")}
                  | {p.parent for d in dirs for p in Path(d).rglob(".hydra") if p.is_dir()})
    if not runs:
        raise DataError(f"no runs (metrics.json) found under {', '.join(map(str, dirs))}")
    return runs


def not_run(dirs: list[Path], runs: list[Path]) -> list[dict]:
    """Entries (status `not run`) of the jobs that the sweeps under `dirs` recorded
    (multirun.yaml) and that have no folder among `runs`."""
    found = {r.resolve() for r in runs}
    entries = []
    for record in sorted({p for d in dirs for p in Path(d).rglob("multirun.yaml")}):
        for folder, overrides in sweep_jobs(record):
            if folder.resolve() not in found:
                entries.append({"run": folder, "settings": _parse_overrides(overrides), "metrics": {},
                                "status": NOT_RUN, "error": "the sweep ended before this job started"})
    return entries


def sweep_jobs(record: Path) -> list[tuple[Path, list[str]]]:
    """(folder, overrides) of every job of the sweep recorded in `record` (its multirun.yaml), in
    job order, as Hydra's basic sweeper makes them; none for another sweeper (an optimising one
    decides its jobs as it goes) or job folders not named by job number."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        hydra = (yaml.safe_load(record.read_text()) or {}).get("hydra", {})
        sweeper, subdir = hydra["sweeper"], hydra["sweep"]["subdir"]
        if sweeper.get("_target_") != BASIC_SWEEPER or subdir != JOB_NUMBER_SUBDIR:
            return []
        params = [f"{k}={v}" for k, v in (sweeper.get("params") or {}).items()]
        parsed = OverridesParser.create().parse_overrides(overrides=params + list(hydra["overrides"]["task"]))
        (jobs,) = BasicSweeper.split_arguments(parsed, None)
    except Exception as exc:  # not a record this reader understands: its jobs are the folders found
        print(f"slamkit-report: {record}: the sweep's jobs cannot be listed from it ({type(exc).__name__}: {exc}); "
              "reporting its job folders", file=sys.stderr)
        return []
    return [(record.parent / str(i), overrides) for i, overrides in enumerate(jobs)]


def load_run(run: Path) -> dict:
    """A run's settings (its overrides), metrics, `status` and `error`; a metrics.json (or
    overrides.yaml) that cannot be read gives status "unreadable", no metrics and the reason; a
    job folder without metrics.json is running (its folder is held) or failed (`_ended_early`)."""
    entry = {"run": run, "settings": {}, "metrics": {}, "status": "unreadable", "error": None}
    try:
        entry["settings"] = _settings(run / ".hydra" / "overrides.yaml")
        if not (run / "metrics.json").exists():
            entry["status"], entry["error"] = _ended_early(run)
            return entry
        entry["metrics"] = _metrics(run / "metrics.json")
    except DataError as exc:
        entry["error"] = str(exc)
        return entry
    entry["status"], entry["error"] = _status(entry["metrics"])
    return entry


def _ended_early(run: Path) -> tuple[str, str]:
    """(status, why) of a job folder without metrics.json: running while a process holds it,
    else failed with the last error its log recorded."""
    from slamkit.run.ownership import in_use_by

    holder = in_use_by(run)
    if holder is not None:
        return "running", f"no metrics.json yet: running ({holder})"
    try:
        lines = (run / "slamkit.log").read_text(errors="replace").splitlines()
    except OSError:
        lines = []
    errors = [line.partition("][ERROR] - ")[2] for line in lines if "][ERROR] - " in line]
    if errors:
        return "failed", errors[-1]
    return "failed", "no metrics.json and no error in its log: the job was killed before its stream ended"


def _settings(path: Path) -> dict[str, str]:
    try:
        overrides = yaml.safe_load(path.read_text()) if path.exists() else []
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise DataError(f"{path}: not readable as YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(overrides, (list, type(None))):
        raise DataError(f"{path}: a YAML {type(overrides).__name__}, expected a list of overrides")
    return _parse_overrides(overrides or [])


def _parse_overrides(overrides: list) -> dict[str, str]:
    settings = {}
    for item in overrides:
        key, _, value = str(item).lstrip("+~").partition("=")
        if not key.startswith("hydra"):
            settings[key] = value
    return settings


def _metrics(path: Path) -> dict:
    try:
        metrics = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: not readable ({str(exc).splitlines()[0]})") from None
    except json.JSONDecodeError as exc:
        raise DataError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(metrics, dict):
        raise DataError(f"{path}: a JSON {type(metrics).__name__}, expected an object of metrics")
    return metrics


def _status(metrics: dict) -> tuple[str, str | None]:
    """(status, error) of a run's metrics; runs written before `status` existed are completed,
    or interrupted / failed after their error."""
    error = metrics.get("error")
    error = None if error is None else str(error)
    status = metrics.get("status")
    if status in STATUSES:
        return status, error
    if metrics.get("completed") is True:
        return "completed", error
    return ("interrupted" if error is None or error.startswith("interrupted") else "failed"), error
