"""Plugin discovery: entry points in the group ``slamkit``, the hook of `slamkit.registry.hookspecs`.

Built-in plugins are found exactly like third-party ones. Each spec's role is the role whose
base class its class subclasses (`slamkit.roles.ROLES`). A plugin that fails to import, whose
hook raises or returns something malformed, or whose config Hydra cannot hold, is reported by
name (a warning) and left out; the others keep working.
"""

from __future__ import annotations

import dataclasses
import importlib.metadata
import logging
import warnings
from dataclasses import dataclass, field
from typing import Any

import pluggy
from omegaconf import MISSING

from slamkit.config import RunContext, resolve_tree
from slamkit.errors import PluginError
from slamkit.plugin import PROJECT, PluginSpec
from slamkit.registry import hookspecs
from slamkit.roles import ROLE_KEYS, role, role_of

log = logging.getLogger(__name__)


@dataclass
class Registered:
    spec: PluginSpec
    source: str  # the entry point / distribution it came from


@dataclass
class Registry:
    """All plugins by role key and name, plus the ones that failed (source -> reason)."""

    plugins: dict[str, dict[str, Registered]] = field(default_factory=lambda: {k: {} for k in ROLE_KEYS})
    failed: dict[str, str] = field(default_factory=dict)

    def get(self, role: str, name: str) -> PluginSpec:
        """The spec of plugin `name` for `role`; PluginError lists the available names."""
        found = self.plugins[role].get(name)
        if found is None:
            available = ", ".join(sorted(self.plugins[role])) or "none"
            failed = "".join(f"; not loaded: {src} ({why})" for src, why in self.failed.items())
            raise PluginError(f"unknown {role} {name!r}; available: {available}{failed}")
        return found.spec

    def create(self, role: str, name: str, config=None, context: RunContext | None = None, **parts):
        """Build plugin `name` of `role` as `cls(config, context, **parts)`: `config` (None: its
        defaults) with its null fields filled from `context` (`slamkit.config.resolve_tree`;
        None: a context of defaults, whose `build` builds from this registry); `parts` are a
        mapper's parts."""
        spec = self.get(role, name)
        context = context or RunContext(build=self.create)
        config = resolve_tree(spec.config() if config is None else config, context)
        return spec.cls(config, context, **parts)

    def add_module(self, module, source: str, manager: pluggy.PluginManager | None = None) -> None:
        """Register the hook of one plugin module; failures become warnings."""
        manager = manager or _manager()
        try:
            manager.register(module, name=source)
            impls = [i for i in manager.hook.slamkit_plugins.get_hookimpls() if i.plugin is module]
            specs = [spec for impl in impls for spec in (impl.function() or [])]
            checked = [(self._check(spec), spec) for spec in specs]
        except Exception as exc:  # a malformed hookimpl or spec: report, keep the others
            self._fail(source, exc)
            return
        for key, spec in checked:
            if spec.name in self.plugins[key]:
                previous = self.plugins[key][spec.name].source
                warnings.warn(f"slamkit: {key} {spec.name!r} from {source} replaces the one from {previous}",
                              stacklevel=2)
            self.plugins[key][spec.name] = Registered(spec, source)

    @staticmethod
    def _check(spec: PluginSpec) -> str:
        """The role key of a well-formed spec; PluginError otherwise."""
        if not isinstance(spec, PluginSpec):
            raise PluginError(f"hook returned {spec!r}, expected slamkit.plugin.PluginSpec")
        role = role_of(spec.cls).key
        if not dataclasses.is_dataclass(spec.config):
            raise PluginError(f"{role} {spec.name!r}: config {spec.config!r} is not a dataclass")
        _check_hydra_can_hold(spec.config, f"{role} {spec.name!r}")
        return role

    def _fail(self, source: str, exc: BaseException) -> None:
        reason = f"{type(exc).__name__}: {exc}".splitlines()[0]
        self.failed[source] = reason
        warnings.warn(f"slamkit: plugin {source!r} was not loaded: {reason}", stacklevel=2)


def _check_hydra_can_hold(config: type, label: str) -> None:
    """PluginError unless OmegaConf can make a structured config of `config` (every field of a
    type Hydra supports, with defaults it can hold) and build the config object from it (its
    defaults pass its `validate`), as a run that selects the plugin will."""
    from omegaconf import OmegaConf

    try:
        node = OmegaConf.structured(config)
    except Exception as exc:
        raise PluginError(f"{label}: config {config.__name__} cannot be a Hydra config: {_first_line(exc)}") from None
    try:
        OmegaConf.to_object(node)
    except Exception as exc:
        raise PluginError(f"{label}: config {config.__name__} cannot be built from its defaults: "
                          f"{_first_line(exc)}") from None


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


def _manager() -> pluggy.PluginManager:
    manager = pluggy.PluginManager(PROJECT)
    manager.add_hookspecs(hookspecs)
    return manager


def discover() -> Registry:
    """Load every entry point of the group ``slamkit`` into a new Registry."""
    registry, manager = Registry(), _manager()
    for ep in importlib.metadata.entry_points(group=PROJECT):
        dist = ep.dist.name if ep.dist is not None else "?"
        source = f"{ep.name} ({dist})"
        try:
            module = ep.load()
        except Exception as exc:
            registry._fail(source, exc)
            continue
        registry.add_module(module, source, manager)
    return registry


def register_configs(registry: Registry) -> None:
    """Put each plugin's config dataclass into Hydra's ConfigStore under its role's group (a
    part's nested under its owner's: `mapper/rasterizer`); one that cannot be stored is reported
    by name (a warning) and left out of the registry."""
    from hydra.core.config_store import ConfigStore

    store = ConfigStore.instance()
    for key, plugins in registry.plugins.items():
        for name, entry in list(plugins.items()):
            try:
                node = with_parts(entry.spec.config, getattr(entry.spec.cls, "parts", ()))
                store.store(group=role(key).group, name=name, node=node, provider=entry.source)
            except Exception as exc:
                del plugins[name]
                registry._fail(entry.source, exc)


def with_parts(config: type, parts: tuple[str, ...]) -> type:
    """A plugin's config as its group entry: for a plugin composed of `parts` (a mapper's), a
    subclass with one field per part, holding the part's config, and a Hydra defaults list that
    selects each part's default (`mapper/rasterizer: auto`), so that the parts are composed only
    with their owner."""
    if not parts:
        return config
    defaults = [{key: role(key).default} for key in parts] + ["_self_"]
    fields = [(key, Any, dataclasses.field(default=MISSING)) for key in parts]
    node = dataclasses.make_dataclass(config.__name__, [("defaults", list[Any], dataclasses.field(
        default_factory=lambda: list(defaults)))] + fields, bases=(config,))
    node.__module__, node.__doc__ = config.__module__, config.__doc__
    return node


_discovered: Registry | None = None


def default_registry() -> Registry:
    """The registry of the installed plugins, discovered once per process."""
    global _discovered
    if _discovered is None:
        _discovered = discover()
    return _discovered


def create_rasterizer(name: str = "auto", registry: Registry | None = None):
    """A rasteriser backend by name with its default config (``auto``: the first backend
    available here)."""
    return (registry or default_registry()).create("rasterizer", name)
