"""The slamkit plugin API: every hook a plugin can implement.

Each hook takes no arguments and returns a list of `slamkit.plugin.PluginSpec`, one per
implementation the plugin offers for that role. The role's base class is in `slamkit.roles`;
the registry checks that each spec's class subclasses it and that its config is a dataclass.
"""

from __future__ import annotations

from slamkit.plugin import PluginSpec, hookspec


@hookspec
def slamkit_datasets() -> list[PluginSpec]:
    """RGB-D sequences: subclasses of `slamkit.roles.Dataset`, configs deriving from
    `slamkit.roles.DatasetConfig` (path, start, stride, max_frames, depth_trunc, intrinsics).
    Selected with ``dataset=NAME``."""


@hookspec
def slamkit_trackers() -> list[PluginSpec]:
    """Pose estimators: subclasses of `slamkit.roles.Tracker`. Selected with ``tracker=NAME``."""


@hookspec
def slamkit_mappers() -> list[PluginSpec]:
    """Map optimisers: subclasses of `slamkit.roles.Mapper`. Selected with ``mapper=NAME``."""


@hookspec
def slamkit_keyframe_policies() -> list[PluginSpec]:
    """Keyframe selection: subclasses of `slamkit.roles.KeyframePolicy`. Selected with
    ``keyframe=NAME``."""


@hookspec
def slamkit_keyframe_samplers() -> list[PluginSpec]:
    """Which keyframe the mapper trains on next: subclasses of `slamkit.roles.KeyframeSampler`.
    Selected with ``sampler=NAME``."""


@hookspec
def slamkit_rasterizers() -> list[PluginSpec]:
    """Gaussian rasteriser backends: subclasses of `slamkit.rendering.Rasterizer`. Selected by
    a mapper's ``rasterizer`` option (``auto`` picks gsplat on CUDA, else ``cpu``, else
    ``torch``)."""


@hookspec
def slamkit_viewers() -> list[PluginSpec]:
    """Live display or recording of a run: subclasses of `slamkit.roles.Viewer`, configs
    ideally deriving from `slamkit.roles.ViewerConfig`. Selected with ``viewer=NAME``
    (``none`` by default)."""
