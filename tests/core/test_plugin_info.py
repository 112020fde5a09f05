"""The generated configuration reference and its one-line field docs (the `slamkit-plugins`
listing itself: tests/e2e/test_plugin_info_runs.py)."""

from __future__ import annotations

import dataclasses

from slamkit.cli.plugins import markdown_reference
from slamkit.config import field_docs
from slamkit.registry.discovery import discover
from slamkit.registry.schema import RunConfig

from support.data import REPO


def test_configuration_reference_is_current():
    """docs/configuration.md is generated; regenerate with
    `slamkit-plugins --markdown docs/configuration.md` after changing a config dataclass."""
    expected = markdown_reference(discover())
    assert (REPO / "docs" / "configuration.md").read_text() == expected


def _undocumented(cls: type, prefix: str) -> list[str]:
    """The keys of `cls`'s fields, and of the configs nested in it (a dataclass default, e.g.
    `mapper.admission`), that have no one-line doc."""
    docs = field_docs(cls)
    missing = []
    for f in dataclasses.fields(cls):
        nested = f.default_factory() if f.default_factory is not dataclasses.MISSING else None
        if dataclasses.is_dataclass(nested):
            missing += _undocumented(type(nested), f"{prefix}{f.name}.")
        elif not docs.get(f.name, "").strip() or "\n" in docs[f.name]:
            missing.append(f"{prefix}{f.name} ({cls.__module__}.{cls.__qualname__})")
    return missing


def test_every_builtin_config_field_has_a_one_line_doc():
    """Each field of each built-in plugin's config (and of the configs nested in it) is
    documented by a `#:` line above it, which docs/configuration.md shows."""
    registry = discover()
    builtin = [(role, name, entry) for role, plugins in registry.plugins.items()
               for name, entry in plugins.items() if entry.source.endswith("(slamkit)")]
    assert {role for role, _, _ in builtin} >= {"dataset", "tracker", "keyframe", "mapper", "viewer"}
    missing = [f"{role}={name}: {key}" for role, name, entry in builtin
               for key in _undocumented(entry.spec.config, f"{role}.")]
    missing += _undocumented(RunConfig, "")  # the run's own keys: eval.*, growth.*, checkpoint.*, ...
    assert not missing, "fields without a `#:` line:\n" + "\n".join(missing)
