"""A run's config from Hydra overrides, composed exactly as the `slamkit` command composes it,
for the command's checks, scripts, benchmarks and tests:

    cfg, names = compose_run(["dataset=tum", "dataset.path=PATH", "mapper=gaussian_splatting"])
    dataset, slam, viewer = build_run(["dataset=tum", "dataset.path=PATH"])
"""

from __future__ import annotations

import re
from pathlib import Path

from slamkit.registry.schema import RunConfig, register_run_config, validate_config
from slamkit.errors import ConfigError
from slamkit.registry.discovery import Registry, default_registry, register_configs
from slamkit.roles import ROLE_KEYS

#: The config tree (conf/config.yaml) and the experiment configs (`+experiment=NAME`), found
#: beside the source tree (slamkit is installed editable).
CONF_DIR = Path(__file__).resolve().parents[2] / "conf"
EXPERIMENTS_DIR = Path(__file__).resolve().parents[2] / "experiments"


def register(registry: Registry) -> None:
    """Put the run schema and every plugin's config into Hydra's ConfigStore, and the resolvers
    that conf/hydra/launcher/ray.yaml uses: `${slamkit.cache:NAME}` (the project cache's folder
    NAME, `slamkit.cache.cache_dir`) and `${slamkit.local_only:ADDRESS,VALUE}` (VALUE when
    ADDRESS is null or empty, i.e. for a cluster the command starts itself, else null)."""
    from omegaconf import OmegaConf

    from slamkit.cache import cache_dir

    register_configs(registry)
    register_run_config()
    if not OmegaConf.has_resolver("slamkit.cache"):
        OmegaConf.register_new_resolver("slamkit.cache", lambda name="": str(cache_dir(str(name))))
    if not OmegaConf.has_resolver("slamkit.local_only"):  # a setting for a cluster this command starts
        OmegaConf.register_new_resolver("slamkit.local_only", lambda address, value: None if address else value)


#: DESIGN.md's command-line contract spells the rasteriser `mapper.rasterizer=auto|torch|cpu|gsplat`;
#: it is its own role (config group `rasterizer`, a part of the mapper), so that spelling is
#: rewritten to it on the command line, options and sweeps included (`mapper.rasterizer.num_threads=2`,
#: `-m mapper.rasterizer=cpu,torch`); config files (an experiment's sweeper params) use `rasterizer`.
_CONTRACT_KEY = re.compile(r"^([+~]*)mapper\.rasterizer(?=[.=]|$)")


def contract_overrides(overrides: list[str] | tuple[str, ...]) -> list[str]:
    """`overrides` with DESIGN.md's spellings of a role rewritten to the role's own key
    (`mapper.rasterizer=cpu` -> `rasterizer=cpu`); the rest unchanged."""
    return [_CONTRACT_KEY.sub(r"\1rasterizer", o) for o in overrides]


def compose_run(overrides: list[str] | tuple[str, ...] = (), registry: Registry | None = None
                ) -> tuple[RunConfig, dict[str, str]]:
    """The validated run config for `overrides` and the plugin chosen for each role (key ->
    name). ConfigError (one line naming the value) for a bad override or value."""
    from hydra import compose, initialize_config_dir
    from omegaconf import open_dict

    register(registry or default_registry())
    overrides = contract_overrides(overrides)
    if EXPERIMENTS_DIR.is_dir() and not any(o.startswith("hydra.searchpath") for o in overrides):
        overrides.append(f"hydra.searchpath=[file://{EXPERIMENTS_DIR}]")
    try:
        with initialize_config_dir(str(CONF_DIR), version_base=None):
            cfg = compose("config", overrides=overrides, return_hydra_config=True)
    except Exception as exc:  # Hydra's override and type errors: name the value, one line
        causes = [str(e).strip().splitlines()[0] for e in (exc, exc.__cause__) if e is not None and str(e).strip()]
        raise ConfigError(": ".join(dict.fromkeys(causes))) from exc
    names = {key: cfg.hydra.runtime.choices[key] for key in ROLE_KEYS}
    with open_dict(cfg):
        del cfg["hydra"]
    return validate_config(cfg), names


def build_run(overrides: list[str] | tuple[str, ...] = (), registry: Registry | None = None):
    """(dataset, SLAM system, viewer) for `overrides`, built as a `slamkit` run builds them."""
    from slamkit.run.pipeline import build

    registry = registry or default_registry()
    cfg, names = compose_run(overrides, registry)
    return build(cfg, registry, names)
