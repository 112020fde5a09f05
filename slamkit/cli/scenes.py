"""Scene sweeps over `data_root` (`slamkit +experiment=paper_replica data_root=DIR`): before the
sweep starts, each scene it would run (its `scene` sweep, from `scene=a,b` on the command line or
else from the experiment's `hydra.sweeper.params.scene`) is looked up as a folder under data_root,
and each scene's job, composed once as the sweep composes it, opens its dataset (its lists read,
its frames counted); the sweep runs the complete scenes, and each missing or incomplete one is
named in one line (`slamkit: scene NAME skipped: WHY`) before the first job. None complete, or no
data_root, is a one-line error. `slamkit.cli.hydra_app.Sweep` asks these questions of the
configuration it composed; nothing here composes."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from slamkit.errors import ConfigError

#: The run config key a scene sweep varies, and the one naming the folder the scenes are under.
SCENE_KEY, ROOT_KEY = "scene", "data_root"


@dataclass(frozen=True)
class SceneSweep:
    """The scenes a sweep runs (`scenes`, folders under `root`) and where their list comes from:
    the command line's `scene=` (`given`: that override's text) or the experiment's sweeper
    params (`given` None)."""

    scenes: tuple[str, ...]
    root: str
    given: str | None

    def missing(self, scene: str) -> str | None:
        """Why `scene` has no folder under the root ("no folder PATH"), None when it has one."""
        folder = Path(self.root) / scene
        return None if folder.is_dir() else f"no folder {folder}"

    def none_complete(self) -> ConfigError:
        return ConfigError(f"{ROOT_KEY}={self.root}: none of the scenes is there complete ({', '.join(self.scenes)}); "
                           f"get them with slamkit-data download paper --root {self.root}")


def scene_sweep(cfg: Any, overrides: Sequence[str]) -> SceneSweep | None:
    """The scene sweep of a sweep's composed configuration `cfg` (its `hydra` node included) and
    the command line's `overrides`; None when it sweeps no scene. ConfigError (one line) without
    a data_root."""
    from omegaconf import OmegaConf

    from slamkit.registry.compose import parse_overrides

    given = [o for o in parse_overrides(overrides) if o.key_or_group == SCENE_KEY]
    if given:
        last = given[-1]
        scenes = [str(s) for s in (last.sweep_string_iterator() if last.is_sweep_override() else [last.value()])]
    else:
        listed = OmegaConf.select(cfg, f"hydra.sweeper.params.{SCENE_KEY}", default=None)
        if listed is None:
            return None
        scenes = [s.strip() for s in str(listed).split(",") if s.strip()]
    root = OmegaConf.select(cfg, ROOT_KEY, default=None, throw_on_resolution_failure=False)
    if not root:
        raise ConfigError(f"{ROOT_KEY}: expected the folder holding the scenes {', '.join(scenes)} "
                          f"(slamkit-data download paper --root DIR, then {ROOT_KEY}=DIR), got {root!r}")
    return SceneSweep(tuple(scenes), str(root), given[-1].input_line if given else None)


def job_scene(job: Sequence[str]) -> str | None:
    """The scene a sweep job's overrides run (`scene=NAME`), None for a job without one."""
    values = [o.split("=", 1)[1] for o in job if o.split("=", 1)[0] == SCENE_KEY]
    return values[-1] if values else None


def unreadable(run_cfg: Any, names: dict[str, str]) -> str | None:
    """Why a job's run config `run_cfg` (plugins `names` by role) could not open its dataset (a
    file missing or unreadable, no frame selected: the DataError's line), None when it can."""
    from slamkit.errors import DataError
    from slamkit.registry.discovery import default_registry
    from slamkit.run.boundary import PluginBoundary

    try:
        with PluginBoundary(names)("dataset", "__init__"):
            dataset = default_registry().create("dataset", names["dataset"], run_cfg.dataset)
        if len(dataset) == 0:
            return f"no frames selected in {run_cfg.dataset.path}"
    except DataError as exc:
        return str(exc)
    except OSError as exc:  # a folder this user cannot read
        return f"{exc.strerror or exc}: {exc.filename or run_cfg.dataset.path}"
    return None
