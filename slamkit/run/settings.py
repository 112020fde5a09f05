"""The method settings a run ran with, after the preset and the mode filled their defaults: what
metrics.json records under `settings`, so that a result says which system produced it (the
paper's or slamkit's, docs/paper.md) without reading the run's config files."""

from __future__ import annotations

import dataclasses
import enum
from typing import Any

from slamkit.config import METHOD
from slamkit.registry.compose import preset_not_applied
from slamkit.registry.schema import RunConfig


def marked_settings(config: Any, prefix: str = "") -> dict[str, Any]:
    """{dotted key: value} of the fields of the dataclass `config` declared `method_setting`
    (the switches of docs/paper.md's "Differences" table and what the paper's ablations vary),
    recursively through the configs nested in it (keys `prefix` + field name), enums by their
    value. A plugin's marked field appears where that plugin is chosen, and only there."""
    settings: dict[str, Any] = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            settings.update(marked_settings(value, f"{prefix}{f.name}."))
        elif f.metadata.get(METHOD):
            settings[f"{prefix}{f.name}"] = value.value if isinstance(value, enum.Enum) else value
    return settings


def method_settings(cfg: RunConfig, names: dict[str, str]) -> dict[str, Any]:
    """The method settings of `cfg` (the run's effective config: `BuiltRun.config`, its
    `marked_settings`), plus `refinement_steps` (the mapping steps after the stream) and
    `preset_not_applied` (the roles whose preset settings were left out for the plugin chosen,
    `names` by role path: `slamkit.registry.compose.preset_not_applied`)."""
    settings = marked_settings(cfg)
    settings["refinement_steps"] = cfg.refinement_iterations()
    settings["preset_not_applied"] = preset_not_applied(cfg.preset, names)
    return settings
