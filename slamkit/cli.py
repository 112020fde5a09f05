"""The `slamkit` command: a Hydra app over the plugin registry.

`slamkit` alone runs the default pipeline on the built-in synthetic sequence; any config value
is an override (`slamkit dataset=tum dataset.path=... tracker=kiss_icp`), `-m` runs sweeps.
User errors (a bad file, a bad value) print one line and exit with status 2; set
SLAMKIT_DEBUG=1 for the traceback.
"""

from __future__ import annotations

import logging
import os
import re
import sys
from pathlib import Path

from slamkit.errors import ConfigError, SlamkitError
from slamkit.registry import ROLE_HOOKS, Registry, default_registry, discover, register_configs

CONF_DIR = Path(__file__).resolve().parent.parent / "conf"
# Experiment configs (`+experiment=NAME`) live in experiments/experiment/NAME.yaml.
EXPERIMENTS_DIR = Path(__file__).resolve().parent.parent / "experiments"
log = logging.getLogger("slamkit")
_registry: Registry | None = None


def _fail(message: str) -> None:
    print(f"slamkit: error: {message}", file=sys.stderr)
    sys.exit(2)


def _check_plugin_overrides(registry: Registry, args: list[str]) -> None:
    """Reject `role=name` overrides naming unknown plugins, listing the available ones."""
    for arg in args:
        match = re.fullmatch(r"\+?(\w+)=(.*)", arg)
        if not match or match.group(1) not in ROLE_HOOKS:
            continue
        role, value = match.groups()
        for name in re.sub(r"^\w+\((.*)\)$", r"\1", value).split(","):  # sweeps: a,b or choice(a,b)
            if name.strip():
                registry.get(role, name.strip())


def _precheck(args: list[str]) -> None:
    """Compose and validate the config of a single run before Hydra starts it, so that a wrong
    type or value fails in one line before any work. Sweeps are left to Hydra."""
    from hydra import compose, initialize_config_dir

    from slamkit.config import validate_config

    if any(a in ("-m", "--multirun") or a.startswith("-") for a in args):
        return
    overrides = [a for a in args if not re.match(r"\+*hydra[./]", a) or a.startswith("hydra.searchpath")]
    if any(_is_sweep(a) for a in overrides):
        return
    try:
        with initialize_config_dir(str(CONF_DIR), version_base=None):
            cfg = compose("config", overrides=overrides)
    except Exception as exc:  # Hydra's override and type errors: name the value, one line
        causes = [str(e).strip().splitlines()[0] for e in (exc, exc.__cause__) if e is not None and str(e).strip()]
        raise ConfigError(": ".join(dict.fromkeys(causes))) from exc
    validate_config(cfg)


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


def _task(cfg) -> None:
    from hydra.core.hydra_config import HydraConfig

    from slamkit import pipeline
    from slamkit.config import PLUGIN_GROUPS, validate_config

    registry = _registry or default_registry()  # launchers run jobs in fresh processes
    hydra_cfg = HydraConfig.get()
    names = {role: hydra_cfg.runtime.choices[role] for role in PLUGIN_GROUPS}
    out_dir = Path(hydra_cfg.runtime.output_dir)
    try:
        run_cfg = validate_config(cfg)
        metrics = pipeline.run(run_cfg, registry, names, out_dir)
    except SlamkitError as exc:
        log.error("%s", exc)
        if os.environ.get("SLAMKIT_DEBUG"):
            raise
        _fail(str(exc))
    print(f"slamkit: {pipeline.summary(metrics)}")
    print(f"slamkit: outputs in {out_dir}")
    if not metrics["completed"]:
        sys.exit(130)


def main() -> None:
    import hydra

    from slamkit.config import register_run_config

    global _registry
    _registry = discover()
    if EXPERIMENTS_DIR.is_dir() and not any(a.startswith("hydra.searchpath") for a in sys.argv[1:]):
        sys.argv.append(f"hydra.searchpath=[file://{EXPERIMENTS_DIR}]")
    register_configs(_registry)
    register_run_config()
    try:
        _check_plugin_overrides(_registry, sys.argv[1:])
        _precheck(sys.argv[1:])
    except SlamkitError as exc:
        if os.environ.get("SLAMKIT_DEBUG"):
            raise
        _fail(str(exc))
    app = hydra.main(version_base=None, config_path=str(CONF_DIR), config_name="config")(_task)
    app()


if __name__ == "__main__":
    main()
