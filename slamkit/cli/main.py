"""The `slamkit` command: a Hydra app over the plugin registry.

`slamkit` alone runs the default pipeline on the built-in synthetic sequence; any config value
is an override (`slamkit dataset=tum dataset.path=... tracker=kiss_icp`), `-m` runs sweeps.
`slamkit resume=RUN_DIR [overrides]` continues a run from its checkpoint (in RUN_DIR);
`slamkit mode=localize map=RUN_DIR dataset=...` tracks a sequence in a saved map.
Exit status (docs/architecture.md, "Run outputs"): 0 completed; 2 a user error (a bad file, a
bad value, an output folder that cannot be made), one line, SLAMKIT_DEBUG=1 for the traceback;
1 an environment failure (a full disk: what the run kept is named); 3 tracking failed (no frame
tracked, or more than `eval.max_lost_fraction` lost: no ATE is reported); 128 + N stopped by
signal N (130 SIGINT, 143 SIGTERM, 129 SIGHUP, ...: `slamkit.run.lifecycle.SIGNALS`, at any point
from start-up: one line, the outputs so far are kept).
Heavy modules (torch, Hydra, the plugins) are imported only once those signals are handled.
"""

from __future__ import annotations

import logging
import math
import os
import re
import sys
import tempfile
import warnings
from pathlib import Path

from slamkit.cli import streams
from slamkit.errors import ConfigError, SlamkitError
from slamkit.run.lifecycle import StopSignals, exit_status, pause_point
from slamkit.run.ownership import release_all

log = logging.getLogger("slamkit")
_registry = None  # the plugin Registry, discovered once by main()
_stop: StopSignals | None = None  # the current run's, for the message of an interruption
_startup: StopSignals | None = None  # the command's, from its start to the run's
_failed_runs: list[str] = []  # a sweep's runs whose tracking failed (the sweep goes on)

#: Exit status of a run whose tracking failed (an interrupted run's: `exit_status`, 128 + the signal).
TRACKING_FAILED = 3


def _fail(message: str, status: int = 2) -> None:
    print(f"slamkit: error: {message}", file=sys.stderr)
    sys.exit(status)


def _check_plugin_overrides(registry, args: list[str]) -> None:
    """Reject `role=name` overrides naming unknown plugins, listing the available ones."""
    from slamkit.roles import ROLE_KEYS

    for arg in args:
        match = re.fullmatch(r"\+?(\w+)=(.*)", arg)
        if not match or match.group(1) not in ROLE_KEYS:
            continue
        role, value = match.groups()
        for name in re.sub(r"^\w+\((.*)\)$", r"\1", value).split(","):  # sweeps: a,b or choice(a,b)
            if name.strip():
                registry.get(role, name.strip())


def _precheck(registry, args: list[str]) -> None:
    """Compose and validate the config of a single run before Hydra starts it, so that a wrong
    type or value fails in one line before any work. Sweeps are left to Hydra."""
    from slamkit.registry.compose import compose_run

    if any(a in ("-m", "--multirun") or a.startswith("-") for a in args):
        return
    overrides = [a for a in args if not re.match(r"\+*hydra[./]", a) or a.startswith("hydra.searchpath")]
    if any(_is_sweep(a) for a in overrides):
        return
    compose_run(overrides, registry)


def _is_sweep(override: str) -> bool:
    """A Hydra sweep value: a,b / range(...) / choice(...) / glob(...) outside brackets."""
    value = override.partition("=")[2]
    if re.match(r"^(range|choice|glob|interval|tag)\(", value):
        return True
    depth = 0
    for ch in value:
        if ch in "[{(":
            depth += 1
        elif ch in "]})":
            depth -= 1
        elif ch == "," and depth == 0:
            return True
    return False


def _score(run_cfg, metrics: dict) -> float | None:
    """The run's score for an optimising sweeper (`objective.*`): metrics[objective.metric] when
    it is a finite number, else objective.failed_value (e.g. no ground truth for the ATE)."""
    value = metrics.get(run_cfg.objective.metric)
    if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
        return float(value)
    return run_cfg.objective.failed_value


def _check_output_dir(args: list[str]) -> None:
    """The folder the run (or the sweep) writes into must be a folder, or creatable: ConfigError
    naming it otherwise (a file, under a file, a read-only file system), before Hydra creates
    it. Checked up to its first interpolation (`${now:...}`), without creating it."""
    if any(a.startswith("-") and a not in ("-m", "--multirun") for a in args):  # --help, --cfg: no run
        return
    key = "hydra.sweep.dir" if any(a in ("-m", "--multirun") for a in args) else "hydra.run.dir"
    given = [m.group(1) for a in args if (m := re.fullmatch(r"\+*" + re.escape(key) + r"=(.*)", a))]
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
    import yaml

    from slamkit.registry.compose import CONF_DIR

    node = yaml.safe_load((CONF_DIR / "config.yaml").read_text())
    for part in key.split("."):
        node = node.get(part, {}) if isinstance(node, dict) else {}
    return node if isinstance(node, str) else "."


def _task(cfg) -> float | None:
    """One run; returns its score (`_score`) for sweepers that optimise it."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode
    from omegaconf import OmegaConf

    from slamkit.registry.discovery import default_registry
    from slamkit.registry.schema import Mode, validate_config
    from slamkit.roles import ROLE_KEYS
    from slamkit.run import localization, pipeline
    from slamkit.run.state import FAILED, INTERRUPTED as STOPPED

    global _stop
    if _startup is not None:
        _startup.release()  # Hydra has composed the config: a signal noted meanwhile stops the command here
    registry = _registry or default_registry()  # launchers run jobs in fresh processes
    hydra_cfg = HydraConfig.get()
    names = {role: hydra_cfg.runtime.choices[role] for role in ROLE_KEYS}
    out_dir = Path(hydra_cfg.runtime.output_dir)
    failed_value = OmegaConf.select(cfg, "objective.failed_value", default=None)  # also for a config that fails
    _stop = StopSignals()
    try:
        run_cfg = validate_config(cfg)
        program = localization if run_cfg.mode is Mode.localize else pipeline
        metrics = program.run(run_cfg, registry, names, out_dir, _stop)
    except SlamkitError as exc:
        log.error("%s", exc)
        if os.environ.get("SLAMKIT_DEBUG"):
            raise
        if failed_value is None:
            _fail(str(exc), exc.exit_status)
        print(f"slamkit: error: {exc}", file=sys.stderr)  # a search goes on with the next trial
        print(f"slamkit: the run failed; its score is objective.failed_value = {failed_value}")
        return float(failed_value)
    print(f"slamkit: {program.summary(metrics)}")
    print(f"slamkit: outputs in {out_dir}")
    if metrics["status"] == STOPPED:  # interrupted (Ctrl-C, SIGTERM): stop, also a search
        sys.exit(exit_status(_stop.signal))
    if metrics["status"] == FAILED:  # tracking failed: a sweep goes on, and exits with it at the end
        if hydra_cfg.mode == RunMode.MULTIRUN:
            _failed_runs.append(str(out_dir))
        else:
            sys.exit(TRACKING_FAILED)
    return _score(run_cfg, metrics)


def _escape_unencodable_output() -> None:
    """Text the terminal's encoding cannot hold (a file name that is not UTF-8, kept by Python as
    surrogate escapes) is printed and logged backslash-escaped instead of raising a logging error
    (the log file's handler does the same: conf/config.yaml)."""
    for stream in (sys.stdout, sys.stderr):
        if hasattr(stream, "reconfigure"):
            stream.reconfigure(errors="backslashreplace")


def main() -> None:
    """The `slamkit` command (see the module docstring)."""
    global _stop, _startup
    streams.guard()  # a closed, broken or full stdout / stderr never stops the command
    _stop, _startup = None, StopSignals()
    _failed_runs.clear()
    try:
        with _startup.installed():
            _main()
    except KeyboardInterrupt as exc:
        phase = _stop.phase.value if _stop else "startup"
        print(f"slamkit: interrupted ({str(exc) or 'SIGINT'}) during {phase.replace('startup', 'start-up')}",
              file=sys.stderr)
        sys.exit(exit_status(str(exc) or "SIGINT"))
    finally:
        release_all()  # the run folders this command claimed (slamkit.cli.hydra_hooks), however it ends
    if _failed_runs:
        _fail(f"tracking failed in {len(_failed_runs)} of the sweep's runs: {', '.join(_failed_runs)}",
              TRACKING_FAILED)


def _main() -> None:
    global _registry
    pause_point("startup")
    import hydra

    from slamkit.registry.compose import CONF_DIR, EXPERIMENTS_DIR, contract_overrides, register
    from slamkit.registry.discovery import discover
    from slamkit.run.checkpoint import resume_arguments
    from slamkit.run.localization import localize_arguments

    _escape_unencodable_output()
    try:
        sys.argv[1:] = resume_arguments(localize_arguments(contract_overrides(sys.argv[1:])))
    except SlamkitError as exc:
        if os.environ.get("SLAMKIT_DEBUG"):
            raise
        _fail(str(exc), exc.exit_status)
    # hydra/launcher=ray: a local Ray cluster writes no token under the home folder
    # (conf/hydra/launcher/ray.yaml); a cluster that uses tokens needs RAY_AUTH_MODE=token.
    os.environ.setdefault("RAY_AUTH_MODE", "disabled")
    # conf/hydra/launcher/ray.yaml takes the place of the Ray launcher's own config of that name on
    # purpose; Hydra 1.3 still validates it against that schema, and warns that this is deprecated.
    warnings.filterwarnings("ignore", message=r"(?s).*is validated against ConfigStore schema with the same name")
    _registry = discover()
    if EXPERIMENTS_DIR.is_dir() and not any(a.startswith("hydra.searchpath") for a in sys.argv[1:]):
        sys.argv.append(f"hydra.searchpath=[file://{EXPERIMENTS_DIR}]")
    register(_registry)
    _startup.hold()  # Hydra and OmegaConf cut by a KeyboardInterrupt report another error: hold it
    try:
        _check_output_dir(sys.argv[1:])
        _check_plugin_overrides(_registry, sys.argv[1:])
        _precheck(_registry, sys.argv[1:])
    except SlamkitError as exc:
        if os.environ.get("SLAMKIT_DEBUG"):
            raise
        _fail(str(exc))
    app = hydra.main(version_base=None, config_path=str(CONF_DIR), config_name="config")(_task)
    try:
        app()
    finally:
        _startup.release()  # --help, --cfg: no task


if __name__ == "__main__":
    main()
