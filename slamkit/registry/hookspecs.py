"""The slamkit plugin API: the hook a plugin module implements.

There is one hook. It returns the plugin module's implementations; the role each fills is the
role whose base class its class subclasses (`slamkit.roles.ROLES`: Dataset, Tracker,
KeyframePolicy, Mapper, LoopClosure, Viewer, and the mapper's parts Rasterizer, KeyframeSampler,
Strategy, MapOptimizer, MappingLoss), and the user selects it by name with ``ROLE=NAME``
(``tracker=gicp``), a part with ``mapper/PART=NAME`` (``mapper/strategy=3dgs``).
"""

from __future__ import annotations

from slamkit.plugin import PluginSpec, hookspec


@hookspec
def slamkit_plugins() -> list[PluginSpec]:
    """This module's plugins: `PluginSpec(name, cls, config)` each, where `cls` subclasses one
    role's base class and `config` is a dataclass (ideally deriving from
    `slamkit.roles.PluginConfig`, or the role's own config base such as `DatasetConfig`) whose
    fields all have defaults. The registry checks both and reports a bad spec by module name
    without taking the other plugins down."""
