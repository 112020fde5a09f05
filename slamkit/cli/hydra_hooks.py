"""The slamkit command's hooks into Hydra (conf/config.yaml's `hydra.callbacks`): a run's folder
is claimed for it (`slamkit.run.ownership`) before Hydra writes anything into it, and the
`${slamkit.run:}` resolver that makes default folders unique.

- `on_run_start` (one run): the folder `hydra.run.dir` names is locked and checked (in use by
  another run, an earlier run's outputs, the map's folder of a localisation) before Hydra
  creates `.hydra/` in it; `on_run_end` lets it go.
- `on_multirun_start` (a sweep): `hydra.sweep.dir` must be new, or an earlier sweep's cleaned
  with `existing_outputs=clean`; `on_job_start` / `on_job_end` lock each job's folder.

Hydra turns an exception in a callback into a warning, so a refusal here is the command's
one-line error and exit (`SystemExit`), as `slamkit.cli.main` reports a `SlamkitError`.
"""

from __future__ import annotations

import os
import sys
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
    return ownership.ExistingOutputs(_value(config, "existing_outputs", "refuse"))


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
