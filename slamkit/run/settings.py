"""The method settings a run ran with, after the preset and the mode filled their defaults: what
metrics.json records under `settings`, so that a result says which system produced it (the
paper's or slamkit's, docs/paper.md) without reading the run's config files."""

from __future__ import annotations

import enum
from typing import Any

from slamkit.registry.compose import preset_not_applied
from slamkit.registry.schema import RunConfig

#: The run config's keys that make one method differ from another (the switches of docs/paper.md's
#: "Differences" table and what the paper's ablations vary); a key the run's plugins lack is left out.
METHOD_KEYS = (
    "preset", "mode", "fps_limit", "iterations_per_frame", "drop_frames",
    "tracker.regularization", "tracker.target_geometry", "tracker.min_target_opacity", "tracker.target_min_median",
    "tracker.initial_guess", "tracker.fallback_to_previous", "tracker.retry_unconverged", "tracker.coarse_factor",
    "keyframe.mapping_every", "keyframe.max_interval", "keyframe.tracking_every",
    "growth.initial_shape", "growth.scale_alignment", "growth.scale_c", "growth.scale_p",
    "growth.mapping_only_trackable",
    "mapper.resolution_scale", "mapper.admission.skip_covered", "mapper.strategy.prune_every",
    "mapper.strategy.prune_at_finish", "mapper.loss.pixels_without_depth",
    "eval.psnr_pixels", "eval.lpips",
)


def method_settings(cfg: RunConfig, names: dict[str, str]) -> dict[str, Any]:
    """{key: value} of METHOD_KEYS in `cfg` (the run's effective config: `BuiltRun.config`),
    enums by their value, plus `refinement_steps` (the mapping steps after the stream) and
    `preset_not_applied` (the roles whose preset settings were left out for the plugin chosen,
    `names` by role path: `slamkit.registry.compose.preset_not_applied`)."""
    settings: dict[str, Any] = {}
    for key in METHOD_KEYS:
        node: Any = cfg
        for part in key.split("."):
            node = getattr(node, part, _MISSING)
            if node is _MISSING:
                break
        if node is not _MISSING:
            settings[key] = node.value if isinstance(node, enum.Enum) else node
    settings["refinement_steps"] = cfg.refinement_iterations()
    settings["preset_not_applied"] = preset_not_applied(cfg.preset, names)
    return settings


_MISSING = object()
