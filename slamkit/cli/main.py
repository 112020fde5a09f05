"""The `slamkit` command: a Hydra app over the plugin registry.

`slamkit` alone runs the default pipeline on the built-in synthetic sequence; any config value
is an override (`slamkit dataset=tum dataset.path=... tracker=kiss_icp`), `-m` runs sweeps.
`slamkit resume=RUN_DIR [overrides]` continues a run from its checkpoint (in RUN_DIR);
`slamkit mode=localize map=RUN_DIR dataset=...` tracks a sequence in a saved map.
User errors (a bad file, a bad value) print one line and exit with status 2; set
SLAMKIT_DEBUG=1 for the traceback.
"""

from __future__ import annotations

import logging
import math
import os
import re
import sys
import warnings
from pathlib import Path

from slamkit.registry.compose import CONF_DIR, EXPERIMENTS_DIR, compose_run, register
from slamkit.errors import SlamkitError
from slamkit.registry.discovery import Registry, default_registry, discover
from slamkit.roles import ROLE_KEYS

log = logging.getLogger("slamkit")
_registry: Registry | None = None


def _fail(message: str) -> None:
    print(f"slamkit: error: {message}", file=sys.stderr)
    sys.exit(2)


def _check_plugin_overrides(registry: Registry, args: list[str]) -> None:
    """Reject `role=name` overrides naming unknown plugins, listing the available ones."""
    for arg in args:
        match = re.fullmatch(r"\+?(\w+)=(.*)", arg)
        if not match or match.group(1) not in ROLE_KEYS:
            continue
        role, value = match.groups()
        for name in re.sub(r"^\w+\((.*)\)$", r"\1", value).split(","):  # sweeps: a,b or choice(a,b)
            if name.strip():
                registry.get(role, name.strip())


def _precheck(registry: Registry, args: list[str]) -> None:
    """Compose and validate the config of a single run before Hydra starts it, so that a wrong
    type or value fails in one line before any work. Sweeps are left to Hydra."""
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


def _task(cfg) -> float | None:
    """One run; returns its score (`_score`) for sweepers that optimise it."""
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import OmegaConf

    from slamkit.run import localization, pipeline
    from slamkit.registry.schema import Mode, validate_config

    registry = _registry or default_registry()  # launchers run jobs in fresh processes
    hydra_cfg = HydraConfig.get()
    names = {role: hydra_cfg.runtime.choices[role] for role in ROLE_KEYS}
    out_dir = Path(hydra_cfg.runtime.output_dir)
    failed_value = OmegaConf.select(cfg, "objective.failed_value", default=None)  # also for a config that fails
    try:
        run_cfg = validate_config(cfg)
        program = localization if run_cfg.mode is Mode.localize else pipeline
        metrics = program.run(run_cfg, registry, names, out_dir)
    except SlamkitError as exc:
        log.error("%s", exc)
        if os.environ.get("SLAMKIT_DEBUG"):
            raise
        if failed_value is None:
            _fail(str(exc))
        print(f"slamkit: error: {exc}", file=sys.stderr)  # a search goes on with the next trial
        print(f"slamkit: the run failed; its score is objective.failed_value = {failed_value}")
        return float(failed_value)
    print(f"slamkit: {program.summary(metrics)}")
    print(f"slamkit: outputs in {out_dir}")
    if not metrics["completed"]:  # interrupted (Ctrl-C, SIGTERM): stop, also a search
        sys.exit(130)
    return _score(run_cfg, metrics)


def _escape_unencodable_output() -> None:
    """Text the terminal's encoding cannot hold (a file name that is not UTF-8, kept by Python as
    surrogate escapes) is printed and logged backslash-escaped instead of raising a logging error
    (the log file's handler does the same: conf/config.yaml)."""
    for stream in (sys.stdout, sys.stderr):
        if hasattr(stream, "reconfigure"):
            stream.reconfigure(errors="backslashreplace")


def main() -> None:
    import hydra

    from slamkit.run.checkpoint import resume_arguments
    from slamkit.run.localization import localize_arguments

    global _registry
    _escape_unencodable_output()
    try:
        sys.argv[1:] = resume_arguments(localize_arguments(sys.argv[1:]))
    except SlamkitError as exc:
        if os.environ.get("SLAMKIT_DEBUG"):
            raise
        _fail(str(exc))
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
    try:
        _check_plugin_overrides(_registry, sys.argv[1:])
        _precheck(_registry, sys.argv[1:])
    except SlamkitError as exc:
        if os.environ.get("SLAMKIT_DEBUG"):
            raise
        _fail(str(exc))
    app = hydra.main(version_base=None, config_path=str(CONF_DIR), config_name="config")(_task)
    app()


if __name__ == "__main__":
    main()
