"""What a plugin module imports: the hook marker and the spec it returns.

A plugin module is any importable module named by an entry point in the group ``slamkit``::

    [project.entry-points.slamkit]
    my_tracker = "my_package.my_tracker"

and implementing the hook of `slamkit.registry.hookspecs`::

    from slamkit.plugin import PluginSpec, hookimpl

    @hookimpl
    def slamkit_plugins():
        return [PluginSpec("my_tracker", MyTracker, MyTrackerConfig)]

The class's base (`slamkit.roles.Tracker` here) says which role the plugin fills.
"""

from __future__ import annotations

from dataclasses import dataclass

import pluggy

PROJECT = "slamkit"
hookimpl = pluggy.HookimplMarker(PROJECT)
hookspec = pluggy.HookspecMarker(PROJECT)


@dataclass(frozen=True)
class PluginSpec:
    """One implementation of a role.

    name: what users select it by (``tracker=NAME``). cls: a subclass of exactly one role's
    base class (`slamkit.roles.ROLES`), constructed as ``cls(config, context)`` with the run's
    `slamkit.config.RunContext` (a mapper also gets the parts it names in `Mapper.parts` as
    keyword arguments). config: a dataclass (ideally a
    `slamkit.roles.PluginConfig` subclass) whose fields all have defaults; it becomes the
    role's structured config group entry, so its fields are type-checked overrides.
    """

    name: str
    cls: type
    config: type
