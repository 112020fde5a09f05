"""A run's config from Hydra overrides, composed exactly as the `slamkit` command composes it,
for the command's checks, scripts, benchmarks and tests:

    cfg, names = compose_run(["dataset=tum", "dataset.path=PATH", "mapper=gaussian_splatting"])

The config tree (`slamkit.conf`) and the experiment configs (`slamkit.experiments`, selected
with `+experiment=NAME`) ship inside the package, so an installed slamkit finds them from any
folder.
"""

from __future__ import annotations

import copy
import dataclasses
from typing import Any, Callable, Sequence

from slamkit.errors import ConfigError
from slamkit.registry.discovery import Registry, default_registry, register_configs
from slamkit.registry.schema import RunConfig, register_run_config, validate_config
from slamkit.roles import PARTS, ROLES

#: The Hydra config module of the command (its primary config: config.yaml).
CONFIG_MODULE = "slamkit.conf"
#: The primary config's name.
CONFIG_NAME = "config"

#: Keys that moved, by the version that moved them: an override spelled the old way fails with
#: one line naming the new key (each entry: old key or key prefix -> new). A mapper's parts are
#: nested under it (0.3); the run's real-time, evaluation and output settings are groups of
#: their own (0.4: `realtime.*`, `eval.*`, `output.*`).
RENAMED_IN: dict[str, dict[str, str]] = {
    "0.3": {
        **{part.key: part.group for part in PARTS},
        **{f"mapper.{part.key}": part.group for part in PARTS},
        **{f"{part.key}.": f"{part.path}." for part in PARTS},
        **{f"{prefix}strategy.{name}": f"mapper.admission.{name}" for prefix in ("", "mapper.")
           for name in ("skip_covered", "coverage", "covered_cell", "covered_centres", "covered_alpha",
                        "covered_depth_tolerance", "covered_depth_quadratic")},
        **{f"{prefix}strategy.{old}": f"mapper.memory_cap.{new}" for prefix in ("", "mapper.")
           for old, new in (("max_gaussians", "max_gaussians"), ("memory_guard_margin", "margin"))},
        "map.": "growth.",
        "localize.map": "map",
    },
    "0.4": {
        **{name: f"realtime.{name}" for name in ("fps_limit", "drop_frames", "switch_interval", "mapping_priority",
                                                  "mapping_yields", "keyframe_thread")},
        **{name: f"eval.{name}" for name in ("forced_gap_every", "forced_gap_length")},
        **{name: f"output.{name}" for name in ("existing_outputs", "progress")},
        "eval.plot": "output.plot",
    },
}


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


def parse_overrides(overrides: Sequence[str]) -> list:
    """Hydra's parse of command-line overrides; ConfigError (one line) for one it cannot parse."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:
        return OverridesParser.create().parse_overrides(list(overrides))
    except HydraException as exc:
        raise ConfigError(str(exc).strip().splitlines()[0]) from None


def renamed(key: str) -> tuple[str, str] | None:
    """(the current spelling, the version that renamed it) of an override's key when it is an
    old one (`RENAMED_IN`), else None."""
    for version, renames in RENAMED_IN.items():
        if key in renames:
            return renames[key], version
        for old, new in renames.items():
            if old.endswith(".") and key.startswith(old):
                return new + key[len(old):], version
    return None


def renamed_key(key: str) -> str | None:
    """The current spelling of an override's key when it is an old one (`RENAMED_IN`), else None."""
    found = renamed(key)
    return found[0] if found else None


def check_spellings(overrides: Sequence[str]) -> None:
    """ConfigError naming the new spelling for the first override that uses an old key
    (`slamkit rasterizer=cpu` -> `mapper/rasterizer=cpu`, `fps_limit=30` -> `realtime.fps_limit=30`)."""
    for override in parse_overrides(overrides):
        found = renamed(override.key_or_group)
        if found is not None:
            new, version = found
            line = override.input_line
            raise ConfigError(f"{line}: '{override.key_or_group}' is spelled '{new}' since slamkit {version} "
                              f"(write {line.replace(override.key_or_group, new, 1)})")


def _key_of_a_choice(overrides: Sequence[str]) -> str | None:
    """The one line for a key under a config group that is a choice without keys of its own
    (`preset.x=1`: Hydra's "Cannot convert 'dict' to string"), else None."""
    from importlib.resources import files

    roles = {r.key for r in ROLES}
    for override in parse_overrides(overrides):
        group, _, rest = override.key_or_group.partition(".")
        if not rest or group in roles or group == "hydra":
            continue
        for module in (CONFIG_MODULE, "slamkit.experiments"):
            folder = files(module).joinpath(group)
            if folder.is_dir():
                names = sorted(f.name[:-5] for f in folder.iterdir() if f.name.endswith(".yaml"))
                return (f"{override.input_line}: {group} is chosen whole ({group}=NAME: {', '.join(names)}) and has "
                        f"no keys; set what it sets by its own key instead (e.g. realtime.fps_limit=30)")
    return None


def _part_without_owner(overrides: Sequence[str], error: Exception) -> str | None:
    """The one line for a part chosen while its owner composes no such part (`mapper/rasterizer=cpu`
    with `mapper=none`, Hydra's "Could not override 'mapper/rasterizer'"), else None."""
    for override in parse_overrides(overrides):
        part = next((p for p in PARTS if p.group == override.key_or_group), None)
        if part is not None and f"Could not override '{part.group}'" in str(error):
            owners = [o.value() for o in parse_overrides(overrides) if o.key_or_group == part.part_of]
            owner = owners[-1] if owners else next(r.default for r in ROLES if r.key == part.part_of)
            return (f"{override.input_line}: the {part.part_of} {owner!r} has no {part.key} (its parts are "
                    f"composed with it: choose one that has, e.g. {part.part_of}=gaussian_splatting)")
    return None


#: The roles (by path) whose plugin's settings a preset may give (conf/preset_settings/GROUP/PRESET/
#: PLUGIN.yaml, GROUP the path's last part), each with the role it is a part of, if any.
PRESET_ROLES: dict[str, str | None] = {"tracker": None, "keyframe": None, "mapper": None,
                                       "mapper.strategy": "mapper", "mapper.loss": "mapper"}


def preset_not_applied(preset: str, names: dict[str, str]) -> dict[str, dict]:
    """The roles whose settings in preset `preset` were left out because the run chose another
    plugin: {role path: {"settings_for": [plugins the preset has settings for], "chosen": name}}
    (a part only where its owner's settings applied). `names`: the chosen plugin by role path."""
    from importlib.resources import files

    skipped: dict[str, dict] = {}
    for path, owner in PRESET_ROLES.items():
        if path not in names or (owner is not None and owner in skipped):
            continue
        folder = files(CONFIG_MODULE) / "preset_settings" / path.split(".")[-1] / preset
        plugins = sorted(f.name.removesuffix(".yaml") for f in (folder.iterdir() if folder.is_dir() else ())
                         if f.name.endswith(".yaml"))
        if plugins and names[path] not in plugins:
            skipped[path] = {"settings_for": plugins, "chosen": names[path]}
    return skipped


def composition_error(exc: BaseException, overrides: Sequence[str], registry: Registry) -> str:
    """One whole line for a Hydra composition error: where the value came from (the override, or
    the preset or experiment that set it), the key, and what was expected; for a key the chosen
    plugin lacks, the role, the plugin and the settings it has."""
    chain = [e for e in (exc, exc.__cause__, getattr(exc.__cause__, "__cause__", None)) if e is not None]
    first = [str(e).strip().splitlines()[0] for e in chain if str(e).strip()]
    missing = next((e for e in chain if type(e).__name__ in ("ConfigKeyError", "ConfigAttributeError")
                    and getattr(e, "full_key", None)), None)
    if missing is None:
        return ": ".join(dict.fromkeys(first))
    full_key, config_type = str(missing.full_key), getattr(missing, "object_type", None)
    given = [o for o in overrides if f'{o.split("=", 1)[0].lstrip("+~")}.'.startswith(f"{full_key}.")]
    origin = given[-1] if given else f"{full_key} ({first[0].split(':')[0].removesuffix('.')})"
    role = max((r for r in ROLES if full_key.startswith(r.path + ".")), key=lambda r: len(r.path), default=None)
    plugin = next((name for name, entry in registry.plugins.get(role.key if role else "", {}).items()
                   if entry.spec.config.__name__ == getattr(config_type, "__name__", None)), None)
    if role is None or plugin is None or not dataclasses.is_dataclass(config_type):
        return f"{origin}: {str(missing).strip().splitlines()[0]}"
    settings = ", ".join(f.name for f in dataclasses.fields(config_type)) or "none"
    key = full_key[len(role.path) + 1:]
    return (f"{origin}: the {role.path.replace('.', ' ')} {plugin!r} has no setting {key!r} (its settings: "
            f"{settings}; choose a {role.path.replace('.', ' ')} that has it with {role.group}=NAME)")


#: Hydra's own sweeper, whose jobs `sweep_jobs` lists (another, e.g. Optuna's, picks them as it goes).
BASIC_SWEEPER = "hydra._internal.core_plugins.basic_sweeper.BasicSweeper"


def sweep_jobs(cfg) -> list[list[str]] | None:
    """The overrides of each job of the sweep whose composed config (its `hydra` node included)
    is `cfg`: its hydra.sweeper.params (e.g. an experiment's), then the command line's overrides,
    as Hydra's basic sweeper combines them; None for a sweeper that chooses its jobs as it goes."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from omegaconf import OmegaConf

    sweeper = cfg.hydra.sweeper
    if sweeper.get("_target_") != BASIC_SWEEPER:
        return None
    params = [f"{key}={value}" for key, value in (sweeper.get("params") or {}).items()]
    task = list(OmegaConf.to_container(cfg.hydra.overrides.task, resolve=False))
    return [job for batch in BasicSweeper.split_arguments(parse_overrides([*params, *task]), None)
            for job in batch]


def chosen_plugins(choices) -> dict[str, str]:
    """The plugin chosen for each role and part in a composed config, from Hydra's runtime
    choices (group -> option), by role path: `tracker`, `mapper.rasterizer` (parts only where
    their owner composes them)."""
    return {r.path: str(choices[r.group]) for r in ROLES if choices.get(r.group) is not None}


def compose_run(overrides: Sequence[str] = (), registry: Registry | None = None) -> tuple[RunConfig, dict[str, str]]:
    """The validated run config for `overrides` and the plugin chosen for each role and part
    (`chosen_plugins`). ConfigError (one line naming the value) for a bad override or value."""
    from hydra import compose, initialize_config_module

    registry = registry or default_registry()
    register(registry)
    check_spellings(overrides)

    def hydra_compose():
        with initialize_config_module(CONFIG_MODULE, version_base=None):
            return compose(CONFIG_NAME, overrides=list(overrides), return_hydra_config=True)

    return validated(composed(hydra_compose, overrides, registry), overrides)


def composed(compose: Callable[[], Any], overrides: Sequence[str], registry: Registry):
    """`compose()`, a Hydra composition of `overrides` (its `hydra` node included), with Hydra's
    override and type errors as one line naming the value (ConfigError)."""
    try:
        return compose()
    except Exception as exc:  # Hydra's override and type errors: name the value, one line
        orphan = _part_without_owner(overrides, exc) or _key_of_a_choice(overrides)
        if orphan:
            raise ConfigError(orphan) from None
        raise ConfigError(composition_error(exc, overrides, registry)) from exc


def validated(cfg, overrides: Sequence[str]) -> tuple[RunConfig, dict[str, str]]:
    """The run config of a composed config `cfg` (its `hydra` node included, left as it is) and
    the plugin chosen for each role and part; ConfigError (one line) for a value out of range or
    a plugin the mode does not use."""
    from omegaconf import open_dict

    names = chosen_plugins(cfg.hydra.runtime.choices)
    task = copy.deepcopy(cfg)  # the run's own keys, as Hydra gives them to a job (run_job)
    with open_dict(task):
        del task["hydra"]
    run_cfg = validate_config(task, parse_overrides(overrides))
    check_mode_uses(run_cfg, names)
    return run_cfg, names


#: The roles mode=localize does not run (it tracks in a saved map, which it never changes): a
#: plugin chosen for one is refused rather than ignored.
UNUSED_WHEN_LOCALIZING = ("mapper", "loop_closure", "viewer")


def check_mode_uses(cfg: RunConfig, names: dict[str, str]) -> None:
    """ConfigError (one line) for a plugin chosen for a role the run's mode does not use."""
    from slamkit.registry.schema import Mode

    if cfg.mode is not Mode.localize:
        return
    unused = [f"{role}={names[role]}" for role in UNUSED_WHEN_LOCALIZING if names.get(role, "none") != "none"]
    if unused:
        raise ConfigError(f"mode=localize tracks frames in a saved map and changes nothing, so {', '.join(unused)} "
                          f"would not be used: leave {' and '.join(u.split('=')[0] + '=none' for u in unused)}, "
                          f"or map further with resume=RUN (mode=sequential or realtime)")
