"""How the `slamkit` command hands its arguments to Hydra, without rewriting `sys.argv`.

- `SingleRun`: a single run (no `-m`, no swept value), its configuration composed once. Hydra's
  own entry point composes a run's configuration twice (once to read `hydra.mode`, once for the
  run) and the command's checks had composed it before; here the one composition is checked
  (`slamkit.registry.compose.validated`: one line for a bad value) and then run as Hydra runs a
  job (`hydra.core.utils.run_job`: the run folder, `.hydra/`, logging, the callbacks of
  `slamkit.cli.hydra_hooks`), as `Hydra.run` does. A configuration whose `hydra.mode` is
  MULTIRUN (an experiment that sweeps) is left to `run_hydra`.
- `run_hydra`: everything else (`-m`, `--cfg job`, `--info`, `--help`, ...) as any Hydra app,
  its arguments given to Hydra's own parser.

Hydra 1.3's entry point (`hydra._internal.utils._run_hydra`) and `Hydra` are not public API:
slamkit pins hydra-core (pyproject.toml), and tests/e2e/test_cli.py runs both paths.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

from hydra import version
from hydra._internal.hydra import Hydra
from hydra._internal.utils import (
    _run_hydra,
    create_automatic_config_search_path,
    detect_calling_file_or_module_from_task_function,
    detect_task_name,
    get_args_parser,
    run_and_report,
)
from hydra.core.global_hydra import GlobalHydra
from hydra.core.utils import run_job
from hydra.types import HydraContext, RunMode
from omegaconf import open_dict

from slamkit.registry.compose import CONFIG_MODULE, CONFIG_NAME, composed, validated
from slamkit.registry.discovery import Registry

CONFIG_PATH = f"pkg://{CONFIG_MODULE}"


def _hydra(task: Callable[[Any], Any]) -> Hydra:
    """Hydra for `task`, as its entry point makes it (the task's name and search path, the
    version base of `hydra.main(version_base=None)`: the current defaults, e.g. no chdir)."""
    version.setbase(None)
    calling_file, calling_module = detect_calling_file_or_module_from_task_function(task)
    search_path = create_automatic_config_search_path(calling_file, calling_module, CONFIG_PATH)
    return Hydra.create_main_hydra2(task_name=detect_task_name(calling_file, calling_module),
                                    config_search_path=search_path)


class SingleRun:
    """A single run whose configuration is composed once, here: checked in the constructor
    (ConfigError, one line: `slamkit.registry.compose.validated`), then `run()` runs `task` on it
    as Hydra runs one job. `sweep`: the configuration is a sweep's (an experiment's
    `hydra.mode: MULTIRUN`), for `run_hydra` to run; `run()` must not be called then."""

    def __init__(self, task: Callable[[Any], Any], overrides: Sequence[str], registry: Registry):
        self.task = task
        self.hydra = _hydra(task)  # Hydra's global state is this run's until `run()` ends
        try:
            self.cfg = composed(lambda: self.hydra.compose_config(CONFIG_NAME, list(overrides), run_mode=RunMode.RUN,
                                                                  with_log_configuration=True), overrides, registry)
            validated(self.cfg, overrides)
        except BaseException:
            GlobalHydra.instance().clear()
            raise
        self.sweep = self.cfg.hydra.mode == RunMode.MULTIRUN
        if self.sweep:
            GlobalHydra.instance().clear()
        elif self.cfg.hydra.mode is None:  # what Hydra's entry point adds for a run, recorded in .hydra/hydra.yaml
            with open_dict(self.cfg):
                self.cfg.hydra.mode = RunMode.RUN
                self.cfg.hydra.overrides.hydra.append("hydra.mode=RUN")

    def run(self) -> None:
        """The job: its folder, `.hydra/`, logging and callbacks as `Hydra.run` makes them; an
        exception of the task reported as Hydra reports it (`run_and_report`)."""
        from hydra._internal.callbacks import Callbacks

        cfg = self.cfg

        def job() -> None:
            callbacks = Callbacks(cfg)
            callbacks.on_run_start(config=cfg, config_name=CONFIG_NAME)
            ret = run_job(hydra_context=HydraContext(config_loader=self.hydra.config_loader, callbacks=callbacks),
                          task_function=self.task, config=cfg, job_dir_key="hydra.run.dir", job_subdir_key=None,
                          configure_logging=True)
            callbacks.on_run_end(config=cfg, config_name=CONFIG_NAME, job_return=ret)
            _ = ret.return_value  # the task's exception, raised

        try:
            run_and_report(job)
        finally:
            GlobalHydra.instance().clear()


def run_hydra(task: Callable[[Any], Any], argv: Sequence[str]) -> None:
    """Hydra's command line (`-m`, `--cfg`, `--info`, `--help`, overrides) with `argv`."""
    version.setbase(None)  # as hydra.main(version_base=None) does
    parser = get_args_parser()
    _run_hydra(args=parser.parse_args(list(argv)), args_parser=parser, task_function=task, config_path=CONFIG_PATH,
               config_name=CONFIG_NAME)


__all__ = ["SingleRun", "run_hydra"]
