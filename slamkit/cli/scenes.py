"""Scene sweeps over `data_root` (`slamkit +experiment=paper_replica data_root=DIR`): before the
sweep starts, each scene it would run (its `scene` sweep, from the experiment's
`hydra.sweeper.params.scene` or from `scene=a,b` on the command line) is looked up as a folder
under data_root and opened as its job's dataset would be (its lists read, its frames counted);
the sweep runs the complete scenes, and each missing or incomplete one is named in one line
(`slamkit: scene NAME skipped: WHY`) before the first job. None complete, or no data_root, is a
one-line error."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Sequence

from slamkit.errors import ConfigError

#: The run config key a scene sweep varies, and the one naming the folder the scenes are under.
SCENE_KEY, ROOT_KEY = "scene", "data_root"


def present_scenes(argv: Sequence[str], out=None) -> list[str]:
    """`argv` (the command's arguments) with the scene sweep restricted to the scenes found
    under data_root (`scene=FOUND1,FOUND2` in place of any `scene=` given); each missing scene
    is one line on `out` (stderr). Arguments without a scene sweep come back unchanged, and
    are not composed unless they select an experiment (+experiment=NAME) or set `scene`."""
    from slamkit.registry.compose import parse_overrides

    out = out or sys.stderr
    overrides = [a for a in argv if not a.startswith("-")]
    parsed = parse_overrides(overrides)
    given = [o for o in parsed if o.key_or_group == SCENE_KEY]
    if not given and not any(o.key_or_group == "experiment" for o in parsed):
        return list(argv)
    cfg = _composed([o.input_line for o in parsed if not o.is_sweep_override() and o.key_or_group != SCENE_KEY])
    if given:
        last = given[-1]
        scenes = [str(s) for s in (last.sweep_string_iterator() if last.is_sweep_override() else [last.value()])]
    else:
        listed = _select(cfg, f"hydra.sweeper.params.{SCENE_KEY}")
        if listed is None:
            return list(argv)
        scenes = [s.strip() for s in str(listed).split(",") if s.strip()]
    root = _select(cfg, ROOT_KEY)
    if not root:
        raise ConfigError(f"{ROOT_KEY}: expected the folder holding the scenes {', '.join(scenes)} "
                          f"(slamkit-data download paper --root DIR, then {ROOT_KEY}=DIR), got {root!r}")
    fixed = [o.input_line for o in parsed if not o.is_sweep_override() and o.key_or_group != SCENE_KEY
             and not _hydra_setting(o.key_or_group)]
    found = []
    for scene in scenes:
        folder = Path(str(root)) / scene
        why = f"no folder {folder}" if not folder.is_dir() else _incomplete(fixed, scene)
        if why is None:
            found.append(scene)
        else:
            print(f"slamkit: scene {scene} skipped: {why}", file=out)
    if not found:
        raise ConfigError(f"{ROOT_KEY}={root}: none of the scenes is there complete ({', '.join(scenes)}); get "
                          f"them with slamkit-data download paper --root {root}")
    kept = [a for a in argv if a.startswith("-") or a not in {o.input_line for o in given}]
    return kept + [f"{SCENE_KEY}={','.join(found)}"]


def _hydra_setting(key: str) -> bool:
    return key == "hydra" or key.startswith(("hydra.", "hydra/"))


def _incomplete(overrides: list[str], scene: str) -> str | None:
    """Why the job of `scene` could not open its dataset (a file missing or unreadable, no frame
    selected: the DataError's line), None when it can. The job's config as the sweep composes
    it; a bad value in it is the command's error, raised."""
    from slamkit.errors import DataError
    from slamkit.registry.compose import compose_run
    from slamkit.registry.discovery import default_registry
    from slamkit.run.boundary import PluginBoundary

    cfg, names = compose_run([*overrides, f"{SCENE_KEY}={scene}"])
    try:
        with PluginBoundary(names)("dataset", "__init__"):
            dataset = default_registry().create("dataset", names["dataset"], cfg.dataset)
        if len(dataset) == 0:
            return f"no frames selected in {cfg.dataset.path}"
    except DataError as exc:
        return str(exc)
    except OSError as exc:  # a folder this user cannot read
        return f"{exc.strerror or exc}: {exc.filename or cfg.dataset.path}"
    return None


def _composed(overrides: list[str]):
    """The command's config for `overrides` with Hydra's own node (a ConfigError, one line, when
    they do not compose)."""
    from hydra import compose, initialize_config_module

    from slamkit.registry.compose import CONFIG_MODULE, CONFIG_NAME, register
    from slamkit.registry.discovery import default_registry

    register(default_registry())
    try:
        with initialize_config_module(CONFIG_MODULE, version_base=None):
            return compose(CONFIG_NAME, overrides=overrides, return_hydra_config=True)
    except Exception as exc:  # Hydra's errors: the first line names the override
        raise ConfigError(str(exc).strip().splitlines()[0]) from None


def _select(cfg, key: str):
    from omegaconf import OmegaConf

    return OmegaConf.select(cfg, key, default=None, throw_on_resolution_failure=False)
