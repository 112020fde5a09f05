"""Plugin discovery: entry points in the group ``slamkit``, hooks from `slamkit.hookspecs`.

Built-in plugins are found exactly like third-party ones. A plugin that fails to import, or
whose hook raises or returns something malformed, is reported by name (a warning) and left
out; the others keep working.
"""

from __future__ import annotations

import dataclasses
import importlib.metadata
import logging
import warnings
from dataclasses import dataclass, field

import pluggy

from slamkit import hookspecs
from slamkit.errors import PluginError
from slamkit.plugin import PROJECT, PluginSpec
from slamkit.roles import ROLES

log = logging.getLogger(__name__)

# role (config group) -> the hook that lists its implementations
ROLE_HOOKS = {
    "dataset": "slamkit_datasets",
    "tracker": "slamkit_trackers",
    "mapper": "slamkit_mappers",
    "keyframe": "slamkit_keyframe_policies",
    "sampler": "slamkit_keyframe_samplers",
    "rasterizer": "slamkit_rasterizers",
    "viewer": "slamkit_viewers",
}


@dataclass
class Registered:
    spec: PluginSpec
    source: str  # the entry point / distribution it came from


@dataclass
class Registry:
    """All plugins by role and name, plus the ones that failed (name -> reason)."""

    plugins: dict[str, dict[str, Registered]] = field(default_factory=lambda: {r: {} for r in ROLE_HOOKS})
    failed: dict[str, str] = field(default_factory=dict)

    def get(self, role: str, name: str) -> PluginSpec:
        """The spec of plugin `name` for `role`; PluginError lists the available names."""
        found = self.plugins[role].get(name)
        if found is None:
            available = ", ".join(sorted(self.plugins[role])) or "none"
            failed = "".join(f"; not loaded: {src} ({why})" for src, why in self.failed.items())
            raise PluginError(f"unknown {role} {name!r}; available: {available}{failed}")
        return found.spec

    def create(self, role: str, name: str, config):
        """Build plugin `name` of `role` with its (validated) config object."""
        return self.get(role, name).cls(config)

    def add_module(self, module, source: str, manager: pluggy.PluginManager | None = None) -> None:
        """Register the hooks of one plugin module; failures become warnings."""
        manager = manager or _manager()
        try:
            manager.register(module, name=source)
        except Exception as exc:  # a malformed hookimpl: report, keep the others
            self._fail(source, exc)
            return
        for role, hook in ROLE_HOOKS.items():
            for impl in getattr(manager.hook, hook).get_hookimpls():
                if impl.plugin is not module:
                    continue
                try:
                    specs = impl.function() or []
                    for spec in specs:
                        self._add(role, spec, source)
                except Exception as exc:
                    self._fail(source, exc)

    def _add(self, role: str, spec: PluginSpec, source: str) -> None:
        base = ROLES[role]
        if not isinstance(spec, PluginSpec):
            raise PluginError(f"hook returned {spec!r}, expected slamkit.plugin.PluginSpec")
        if not (isinstance(spec.cls, type) and issubclass(spec.cls, base)):
            raise PluginError(f"{role} {spec.name!r}: {spec.cls!r} is not a subclass of {base.__name__}")
        if not dataclasses.is_dataclass(spec.config):
            raise PluginError(f"{role} {spec.name!r}: config {spec.config!r} is not a dataclass")
        if spec.name in self.plugins[role]:
            previous = self.plugins[role][spec.name].source
            warnings.warn(f"slamkit: {role} {spec.name!r} from {source} replaces the one from {previous}", stacklevel=2)
        self.plugins[role][spec.name] = Registered(spec, source)

    def _fail(self, source: str, exc: BaseException) -> None:
        reason = f"{type(exc).__name__}: {exc}".splitlines()[0]
        self.failed[source] = reason
        warnings.warn(f"slamkit: plugin {source!r} was not loaded: {reason}", stacklevel=2)


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
    """Put each plugin's config dataclass into Hydra's ConfigStore under its role's group."""
    from hydra.core.config_store import ConfigStore

    store = ConfigStore.instance()
    for role, plugins in registry.plugins.items():
        for name, entry in plugins.items():
            store.store(group=role, name=name, node=entry.spec.config, provider=entry.source)


_discovered: Registry | None = None


def default_registry() -> Registry:
    """The registry of the installed plugins, discovered once per process."""
    global _discovered
    if _discovered is None:
        _discovered = discover()
    return _discovered


def create_rasterizer(name: str = "auto", registry: Registry | None = None):
    """A rasteriser backend by name; `auto` = gsplat with CUDA, else cpu, else torch
    (the first of those that is registered)."""
    registry = registry or default_registry()
    if name == "auto":
        import torch

        order = (["gsplat"] if torch.cuda.is_available() else []) + ["cpu", "torch"]
        available = [n for n in order if n in registry.plugins["rasterizer"]]
        if not available:
            registry.get("rasterizer", "torch")  # raises, listing what is there
        name = available[0]
    spec = registry.get("rasterizer", name)
    return spec.cls(spec.config())
