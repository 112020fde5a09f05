"""Fixtures and collection rules shared by every layer: the real data folders (skipped with the
reason where they are absent), one per-session cache for generated data, every test under
tests/e2e marked `slow`, the `cuda` marker's skip where there is no GPU, and a loud last line
when tests were skipped for absent data. Helpers that test modules import live in tests/support
(a test module never imports another, conftest included)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from support.data import MISSING, REPLICA, TUM, missing_data_line, require_data
from support.plugins import third_party_plugins

E2E = Path(__file__).resolve().parent / "e2e"


@pytest.hookimpl(tryfirst=True)  # before `-m` deselects by marker
def pytest_collection_modifyitems(config, items):
    """Tests under tests/e2e (console scripts, processes, whole sequences) are marked `slow`,
    so `pytest -m "not slow"` is the quick loop; tests marked `cuda` are skipped, with the
    reason, where torch sees no CUDA device."""
    for item in items:
        if item.path.resolve().is_relative_to(E2E):
            item.add_marker(pytest.mark.slow)
    cuda_tests = [item for item in items if item.get_closest_marker("cuda")]
    if not cuda_tests:
        return
    import torch

    if not torch.cuda.is_available():
        skip = pytest.mark.skip(reason="CUDA not available")
        for item in cuda_tests:
            item.add_marker(skip)


def pytest_unconfigure(config):
    """A run that skipped tests for absent data ends with one loud line (after pytest's own
    summary) saying how many and how to give the tests their data: a green run with the
    data-driven tests skipped is not a pass."""
    reporter = config.pluginmanager.get_plugin("terminalreporter")
    if reporter is None:
        return
    skipped = [r for r in reporter.stats.get("skipped", [])
               if isinstance(r.longrepr, tuple) and MISSING in str(r.longrepr[-1])]
    if skipped:
        reporter.write_sep("!", missing_data_line(len(skipped)), red=True, bold=True)


@pytest.fixture
def tum_path() -> Path:
    return require_data(TUM)


@pytest.fixture
def replica_path() -> Path:
    return require_data(REPLICA)


@pytest.fixture(autouse=True)
def _cache_dir(tmp_path_factory, monkeypatch):
    """Keep generated data (the synthetic sequence) in one per-session cache."""
    if "SLAMKIT_CACHE" not in os.environ:
        monkeypatch.setenv("SLAMKIT_CACHE", str(tmp_path_factory.getbasetemp() / "slamkit_cache"))


@pytest.fixture
def plugin_dir(tmp_path, monkeypatch) -> Path:
    """support.plugins.third_party_plugins installed for this test (on sys.path; give it to a
    `slamkit` process as PYTHONPATH)."""
    root = third_party_plugins(tmp_path / "site")
    monkeypatch.syspath_prepend(str(root))
    return root
