"""How the `slamkit` command hands its arguments to Hydra, without rewriting `sys.argv`.

- `SingleRun`: a single run (no `-m`, no swept value), its configuration composed once. Hydra's
  own entry point composes a run's configuration twice (once to read `hydra.mode`, once for the
  run) and the command's checks had composed it before; here the one composition is checked
  (`slamkit.registry.compose.validated`: one line for a bad value) and then run as Hydra runs a
  job (`hydra.core.utils.run_job`: the run folder, `.hydra/`, logging, the callbacks of
  `slamkit.cli.hydra_hooks`), as `Hydra.run` does. A configuration whose `hydra.mode` is
  MULTIRUN (an experiment that sweeps) is left to `Sweep`.
- `Sweep`: a sweep (`-m`, or an experiment's `hydra.mode: MULTIRUN`), each job's configuration
  composed once. Hydra composes a sweep's config for its mode, then for the sweep, then each job
  twice (the sweeper's check that the batch composes, and the launcher's); the command's check had
  composed each job before. Here the sweep's config is composed once and every job of Hydra's
  basic sweeper once, checked before the first job starts (one line naming the job), and the
  sweeper and its launcher are given those compositions (`_ComposedJobs`) instead of composing
  them again, as `Hydra.multirun` runs a sweep otherwise.
- `composition`: the command's one composition step for a run or a sweep: a resume's arguments
  from its checkpoint, old spellings, the output folder and the plugin choices, then `SingleRun`
  or `Sweep` (a scene sweep narrowed there to the scenes under data_root whose jobs open their
  dataset: `slamkit.cli.scenes`, each scene's job composed once).
- `run_hydra`: everything else (`--cfg job`, `--info`, `--help`, ...) as any Hydra app, its
  arguments given to Hydra's own parser.

Hydra 1.3's entry point (`hydra._internal.utils._run_hydra`) and `Hydra` are not public API:
slamkit pins hydra-core (pyproject.toml), and tests/e2e/test_cli.py runs both paths.
"""

from __future__ import annotations

import copy
import os
import sys
import tempfile
import warnings
from pathlib import Path
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
from omegaconf import OmegaConf, open_dict

from slamkit.cli.scenes import SCENE_KEY, SceneSweep, job_scene, scene_sweep, unreadable
from slamkit.errors import ConfigError
from slamkit.registry.compose import (
    CONFIG_MODULE,
    CONFIG_NAME,
    check_spellings,
    composed,
    parse_overrides,
    sweep_jobs,
    validated,
)
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


class _ComposedJobs:
    """Hydra's config loader, but a job of the sweep composed and checked beforehand is given
    from `jobs` (by its overrides, a copy each time: the sweeper's check and the launcher each
    take one) instead of being composed again. Pickled with the sweep into a launcher's workers."""

    def __init__(self, loader, master, jobs: dict[tuple[str, ...], Any]):
        self.loader, self.master, self.jobs = loader, master, jobs

    def load_sweep_config(self, master_config, sweep_overrides: list[str]):
        job = self.jobs.get(tuple(sweep_overrides)) if master_config is self.master else None
        if job is None:
            return self.loader.load_sweep_config(master_config, sweep_overrides)
        return copy.deepcopy(job)

    def __getattr__(self, name: str):  # the rest of ConfigLoader's interface
        if name.startswith("__") or name in ("loader", "master", "jobs"):
            raise AttributeError(name)
        return getattr(self.loader, name)


class Sweep:
    """A sweep whose configuration is composed once and each of its jobs once, here: the jobs of
    Hydra's basic sweeper composed and checked in the constructor (ConfigError, one line naming
    the job), then `run()` runs the sweep with those compositions as `Hydra.multirun` runs it.
    `sweep` False: the overrides sweep but neither `-m` (`multirun`) nor the configuration's
    `hydra.mode` asks for a sweep: `run()` gives them to `run_hydra`, to be refused as Hydra does."""

    def __init__(self, task: Callable[[Any], Any], overrides: Sequence[str], registry: Registry, multirun: bool):
        self.task, self.overrides = task, list(overrides)
        self.hydra = _hydra(task)  # Hydra's global state is this sweep's until `run()` ends
        try:
            mode = RunMode.MULTIRUN
            self.cfg = composed(lambda: self.hydra.compose_config(CONFIG_NAME, list(overrides), run_mode=mode,
                                                                  with_log_configuration=True), overrides, registry)
            self.sweep = multirun or self.cfg.hydra.mode == RunMode.MULTIRUN
            if self.sweep and self.cfg.hydra.mode != RunMode.MULTIRUN:  # what Hydra's entry point adds for -m
                if self.cfg.hydra.mode == RunMode.RUN:
                    warnings.warn(category=UserWarning, message="\n\tRunning Hydra app with --multirun, "
                                  "overriding with `hydra.mode=MULTIRUN`.")
                with open_dict(self.cfg):
                    self.cfg.hydra.mode = RunMode.MULTIRUN
                    self.cfg.hydra.overrides.hydra.append("hydra.mode=MULTIRUN")
            scenes = scene_sweep(self.cfg, overrides) if self.sweep else None
            if scenes is not None:  # the scenes with a folder under data_root, before any job is composed
                self._run_scenes(scenes, [s for s in scenes.scenes if not _skipped(s, scenes.missing(s))])
            jobs = self._checked_jobs(overrides, registry)
            if scenes is not None:  # and whose job opens its dataset
                jobs = self._complete_scenes(scenes, jobs)
            composed_jobs = {job: cfg for job, (cfg, _) in jobs.items()}
            self.loader = _ComposedJobs(self.hydra.config_loader, self.cfg, composed_jobs)
        except BaseException:
            GlobalHydra.instance().clear()
            raise
        if not self.sweep:
            GlobalHydra.instance().clear()

    def _run_scenes(self, scenes: SceneSweep, kept: list[str]) -> None:
        """The sweep runs the scenes `kept` of `scenes` only: its `scene=` list (the command
        line's, else the experiment's sweeper params) narrowed to them; ConfigError (one line)
        when none is kept."""
        if not kept:
            raise scenes.none_complete()
        narrowed = f"{SCENE_KEY}={','.join(kept)}"
        with open_dict(self.cfg):
            if scenes.given is None:
                self.cfg.hydra.sweeper.params[SCENE_KEY] = ",".join(kept)
            else:
                task = self.cfg.hydra.overrides.task
                self.cfg.hydra.overrides.task = [narrowed if o == scenes.given else o for o in task]
                self.overrides = [narrowed if o == scenes.given else o for o in self.overrides]

    def _complete_scenes(self, scenes: SceneSweep, jobs: dict[tuple[str, ...], Any]) -> dict[tuple[str, ...], Any]:
        """`jobs` without those whose scene's dataset does not open (each scene named in one line,
        opened by its first job), the sweep narrowed to the others (`_run_scenes`)."""
        first = {}  # scene -> its first job's (run config, plugins)
        for job, (_, run) in jobs.items():
            first.setdefault(job_scene(job), run)
        first.pop(None, None)
        incomplete = {scene for scene, (run_cfg, names) in first.items() if _skipped(scene, unreadable(run_cfg, names))}
        if incomplete:
            self._run_scenes(scenes, [scene for scene in first if scene not in incomplete])
        return {job: checked for job, checked in jobs.items() if job_scene(job) not in incomplete}

    def _checked_jobs(self, overrides: Sequence[str], registry: Registry) -> dict[tuple[str, ...], Any]:
        """Each job of the basic sweeper composed as its launcher composes it, and checked, with
        its run config and plugins (`validated`); a job that does not compose or check is refused
        in one line naming it (ConfigError)."""
        jobs = sweep_jobs(self.cfg) or []
        swept = {o.key_or_group for o in parse_overrides(overrides) if o.is_sweep_override()}
        checked = {}
        for number, job in enumerate(jobs, start=1):
            told = [o for o in job if not _is_hydra_setting(o) or o.startswith("hydra.searchpath")]
            try:
                check_spellings(told)
                cfg = composed(lambda: self.hydra.config_loader.load_sweep_config(self.cfg, list(job)), told, registry)
                run = validated(cfg, told)
            except ConfigError as exc:
                if len(jobs) == 1:
                    raise
                varied = [o for o in job if o.split("=", 1)[0] in swept]
                raise ConfigError(f"job {number} of {len(jobs)} of the sweep ({' '.join(varied) or 'as given'}): "
                                  f"{exc}") from None
            checked[tuple(job)] = (cfg, run)
        return checked

    def run(self) -> None:
        """The sweep: callbacks, sweeper and launcher as `Hydra.multirun` makes them, the jobs'
        compositions given by `_ComposedJobs`; an exception reported as Hydra reports it."""
        from hydra._internal.callbacks import Callbacks
        from hydra.core.plugins import Plugins

        if not self.sweep:
            return run_hydra(self.task, self.overrides)
        cfg = self.cfg

        def sweep() -> None:
            callbacks = Callbacks(cfg)
            callbacks.on_multirun_start(config=cfg, config_name=CONFIG_NAME)
            sweeper = Plugins.instance().instantiate_sweeper(
                config=cfg, hydra_context=HydraContext(config_loader=self.loader, callbacks=callbacks),
                task_function=self.task)
            sweeper.sweep(arguments=OmegaConf.to_container(cfg.hydra.overrides.task, resolve=False))
            callbacks.on_multirun_end(config=cfg, config_name=CONFIG_NAME)

        try:
            run_and_report(sweep)
        finally:
            GlobalHydra.instance().clear()


def _is_hydra_setting(override: str) -> bool:
    """An override of Hydra's own config (`hydra.run.dir=...`, `hydra/launcher=ray`)."""
    key = parse_overrides([override])[0].key_or_group
    return key == "hydra" or key.startswith(("hydra.", "hydra/"))


def composition(task: Callable[[Any], Any], overrides: Sequence[str], registry: Registry,
                multirun: bool) -> SingleRun | Sweep:
    """The command's one composition step for a run or a sweep (`overrides`: its arguments but
    `-m`, `multirun` whether it was given): a resume's arguments from its checkpoint
    (`slamkit.run.checkpoint.resume_arguments`), an old spelling refused, the output folder and
    the plugin choices checked, then the configuration composed once and checked: `SingleRun`, or
    `Sweep` for `-m`, a swept value or an experiment that sweeps (a scene sweep narrowed there to
    the scenes under data_root). A SlamkitError, one line, for what is refused."""
    from slamkit.run.checkpoint import resume_arguments

    overrides = resume_arguments(list(overrides))
    check_spellings(overrides)
    _check_output_dir(overrides, multirun=multirun)
    _check_plugin_choices(registry, overrides)
    if not multirun and not _is_sweep(overrides):
        single = SingleRun(task, overrides, registry)  # the run's one composition, checked
        if not single.sweep:
            return single
    return Sweep(task, overrides, registry, multirun=multirun)


def _skipped(scene: str, why: str | None) -> bool:
    """Whether a scene sweep leaves `scene` out (`why` it cannot run, None: it can), said in one
    line before the first job."""
    if why is not None:
        print(f"slamkit: scene {scene} skipped: {why}", file=sys.stderr)
    return why is not None


def _is_sweep(overrides: Sequence[str]) -> bool:
    """Whether any override sweeps (a,b / range(...) / choice(...) / glob(...))."""
    return any(o.is_sweep_override() for o in parse_overrides(overrides))


def _check_plugin_choices(registry, overrides: Sequence[str]) -> None:
    """PluginError listing the available plugins for an override choosing an unknown one
    (`tracker=nope`, `mapper/rasterizer=cpu,nope`)."""
    from slamkit.roles import ROLES

    by_group = {r.group: r.key for r in ROLES}
    for override in parse_overrides(overrides):
        key = by_group.get(override.key_or_group)
        if key is None or override.is_delete():
            continue
        choices = override.sweep_string_iterator() if override.is_sweep_override() else [override.value()]
        for name in choices:
            if isinstance(name, str) and name.strip():
                registry.get(key, name.strip())


def _check_output_dir(overrides: Sequence[str], multirun: bool) -> None:
    """The folder the run (or the sweep) writes into must be a folder, or creatable: ConfigError
    naming it otherwise (a file, under a file, a read-only file system), before Hydra creates
    it. Checked up to its first interpolation (`${now:...}`), without creating it."""
    key = "hydra.sweep.dir" if multirun else "hydra.run.dir"
    given = [str(o.value()) for o in parse_overrides(overrides) if o.key_or_group == key]
    value = given[-1] if given else _default_dir(key)
    literal = value.split("${")[0]
    folder = Path(literal if "${" not in value or literal.endswith("/") else Path(literal).parent).absolute()
    existing = next(p for p in (folder, *folder.parents) if p.exists())
    if not existing.is_dir():
        raise ConfigError(f"{key}={value}: {existing} is a file, expected a folder (or a path that can be "
                          f"created) for the run's outputs")
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".slamkit-check-", dir=existing))
    except OSError as exc:
        raise ConfigError(f"{key}={value}: cannot create a folder in {existing} ({exc.strerror or exc}); "
                          f"expected a writable place for the run's outputs") from None


def _default_dir(key: str) -> str:
    """The folder `key` (hydra.run.dir, hydra.sweep.dir) names in the shipped config.yaml."""
    from importlib.resources import files

    import yaml

    node = yaml.safe_load(files(CONFIG_MODULE).joinpath(f"{CONFIG_NAME}.yaml").read_text())
    for part in key.split("."):
        node = node.get(part, {}) if isinstance(node, dict) else {}
    return node if isinstance(node, str) else "."


def run_hydra(task: Callable[[Any], Any], argv: Sequence[str]) -> None:
    """Hydra's command line (`-m`, `--cfg`, `--info`, `--help`, overrides) with `argv`."""
    version.setbase(None)  # as hydra.main(version_base=None) does
    parser = get_args_parser()
    _run_hydra(args=parser.parse_args(list(argv)), args_parser=parser, task_function=task, config_path=CONFIG_PATH,
               config_name=CONFIG_NAME)


__all__ = ["SingleRun", "Sweep", "composition", "run_hydra"]
