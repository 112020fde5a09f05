"""A sweep as the `slamkit` command composes it, without running it: its jobs, and every
composition of a configuration it took (the command's one composition step,
`slamkit.cli.hydra_app.composition`)."""

from __future__ import annotations

import logging

from hydra.core.global_hydra import GlobalHydra

from slamkit.cli.hydra_app import composition
from slamkit.registry.compose import register, sweep_jobs
from slamkit.registry.discovery import default_registry


def swept_jobs(*overrides: str, counted: list | None = None) -> list[list[str]]:
    """Each job's overrides of the sweep `slamkit -m OVERRIDES` would run (not run); with
    `counted`, the overrides of each composition of a configuration appended to it (Hydra
    composes through `ConfigLoaderImpl.load_configuration`, whoever asks)."""
    from hydra._internal.config_loader_impl import ConfigLoaderImpl

    load = ConfigLoaderImpl.load_configuration

    def counting(self, *args, **kwargs):
        if counted is not None:
            counted.append(kwargs.get("overrides", args[1] if len(args) > 1 else None))
        return load(self, *args, **kwargs)

    registry = default_registry()
    register(registry)  # the run schema and the plugins' configs, as the command does first
    # composing configures Hydra's logging on this process's stderr (pytest's capture, closed
    # after the test): the handlers are put back, or a later test's log line is a logging error
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    ConfigLoaderImpl.load_configuration = counting
    try:
        sweep = composition(lambda cfg: None, list(overrides), registry, multirun=True)
        return sweep_jobs(sweep.cfg)
    finally:
        ConfigLoaderImpl.load_configuration = load
        GlobalHydra.instance().clear()
        root.handlers[:] = handlers
        root.setLevel(level)


def job_values(jobs: list[list[str]], key: str) -> list[str]:
    """The value of `key` in each job that sets it (`scene=NAME` -> NAME), in job order."""
    return [o.split("=", 1)[1] for job in jobs for o in job if o.split("=", 1)[0] == key]
