"""The slamkit command's hooks into Hydra (conf/config.yaml's `hydra.callbacks`): a run's folder
is claimed for it (`slamkit.run.ownership`) before Hydra writes anything into it, and the
`${slamkit.run:}` resolver that makes default folders unique.

- `on_run_start` (one run): the folder `hydra.run.dir` names is locked and checked (in use by
  another run, an earlier run's outputs, the map's folder of a localisation) before Hydra
  creates `.hydra/` in it; `on_run_end` lets it go.
- `on_multirun_start` (a sweep): `hydra.sweep.dir` must be new, or an earlier sweep's cleaned
  with `output.existing_outputs=clean`; `on_job_start` / `on_job_end` lock each job's folder.

`SweepProgressCallback` says, as each job of a sweep starts, which of how many it is, the time
since the sweep started and an estimate of the time left (`slamkit: sweep job 3 of 8, 2 min 10 s
elapsed, ETA 4 min 20 s`).

Hydra turns an exception in a callback into a warning, so a refusal here is the command's
one-line error and exit (`SystemExit`), as `slamkit.cli.main` reports a `SlamkitError`.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import OmegaConf

from slamkit.errors import SlamkitError
from slamkit.run import ownership

#: `${slamkit.run:}` in a folder name: unique per run (`slamkit.run.ownership.unique_suffix`),
#: cached per composed config as Hydra's `${now:...}` is, so that a run (and a sweep's jobs)
#: resolve it to one value.
RESOLVER = "slamkit.run"
OmegaConf.register_new_resolver(RESOLVER, ownership.unique_suffix, use_cache=True, replace=True)


def _refuse(exc: SlamkitError) -> None:
    if os.environ.get("SLAMKIT_DEBUG"):
        raise exc
    print(f"slamkit: error: {exc}", file=sys.stderr)
    sys.exit(exc.exit_status)


def _value(config, key: str, default=None):
    """The config's value at `key` (an enum's value as such, e.g. mode's "localize")."""
    value = OmegaConf.select(config, key, default=default)
    return getattr(value, "value", value)


def _existing(config) -> ownership.ExistingOutputs:
    return ownership.ExistingOutputs(_value(config, "output.existing_outputs", "refuse"))


def _claim(folder: Path, **how) -> None:
    """`ownership.claim`, a refusal or a folder that cannot be locked (a read-only place) one line."""
    try:
        ownership.claim(folder, **how)
    except SlamkitError as exc:
        _refuse(exc)
    except OSError as exc:
        _refuse(ownership.RunFolderError(f"cannot take the run folder {folder}: {exc.strerror or exc}"))


class RunFolderCallback(Callback):
    """Claims each run's folder (see the module docstring)."""

    def __init__(self) -> None:
        self.multirun = False

    def on_run_start(self, config, **kwargs: Any) -> None:
        from hydra.core.hydra_config import HydraConfig

        HydraConfig.instance().set_config(config)  # for ${hydra:...} in the folder's name, as Hydra does
        folder = Path(str(OmegaConf.select(config, "hydra.run.dir"))).absolute()
        localizing = _value(config, "mode") == "localize"
        _claim(folder, existing=_existing(config), resume=_value(config, "resume"),
               localize_map=_value(config, "map") if localizing else None)

    def on_run_end(self, config, **kwargs: Any) -> None:
        ownership.release(Path(str(OmegaConf.select(config, "hydra.runtime.output_dir"))))

    def on_multirun_start(self, config, **kwargs: Any) -> None:
        self.multirun = True
        folder = Path(str(OmegaConf.select(config, "hydra.sweep.dir"))).absolute()
        try:
            ownership.check_new_run_folder(folder, _existing(config), key="hydra.sweep.dir")
        except SlamkitError as exc:
            _refuse(exc)
        except OSError as exc:
            _refuse(ownership.RunFolderError(f"cannot clean hydra.sweep.dir={folder}: {exc.strerror or exc}"))

    def on_job_start(self, config, **kwargs: Any) -> None:
        if not self.multirun:  # a single run's folder was claimed in on_run_start
            return
        _claim(Path(str(config.hydra.runtime.output_dir)), resume=_value(config, "resume"))

    def on_job_end(self, config, **kwargs: Any) -> None:
        if self.multirun:
            ownership.release(Path(str(config.hydra.runtime.output_dir)))


class SweepProgressCallback(Callback):
    """One line on stderr (and in the log) as each job of a sweep starts: job n of N, elapsed,
    ETA. N is known for Hydra's basic sweeper (the product of the swept values) and for a
    search's `n_trials`; where the jobs run in other processes (joblib, SLURM) each line says
    only which job it is."""

    def __init__(self) -> None:
        self.start: float | None = None
        self.total: int | None = None

    def on_multirun_start(self, config, **kwargs: Any) -> None:
        self.start = time.monotonic()
        self.total = sweep_size(config)

    def on_job_start(self, config, **kwargs: Any) -> None:
        from slamkit.progress import duration

        num = OmegaConf.select(config, "hydra.job.num")
        multirun = str(OmegaConf.select(config, "hydra.mode")).endswith("MULTIRUN")
        if num is None or not multirun or _value(config, "output.progress") is False:  # output.progress=false: quiet
            return
        text = f"sweep job {num + 1}" + (f" of {self.total}" if self.total else "")
        if self.start is not None:
            elapsed = time.monotonic() - self.start
            text += f", {duration(elapsed)} elapsed"
            if self.total and num > 0:
                text += f", ETA {duration(elapsed / num * (self.total - num))}"
        print(f"slamkit: {text}", file=sys.stderr, flush=True)


def sweep_size(config) -> int | None:
    """How many jobs the sweep runs: the basic sweeper's product of the swept values (its
    `params` and the command line's overrides), a search's `n_trials`; None where unknown."""
    sweeper = OmegaConf.select(config, "hydra.sweeper") or {}
    target = str(sweeper.get("_target_", ""))
    if target.endswith("BasicSweeper"):
        from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
        from hydra.core.override_parser.overrides_parser import OverridesParser

        params = sweeper.get("params") or {}
        overrides = [f"{k}={v}" for k, v in params.items()]
        overrides += list(OmegaConf.select(config, "hydra.overrides.task") or [])
        try:
            batches = BasicSweeper.split_arguments(OverridesParser.create().parse_overrides(overrides), None)
        except Exception:  # noqa: BLE001 - a progress figure: the sweep itself reports bad overrides
            return None
        return sum(len(batch) for batch in batches)
    trials = sweeper.get("n_trials")
    return int(trials) if isinstance(trials, int) else None
