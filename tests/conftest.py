"""Shared fixtures: the real data folder beside the repository (or $SLAMKIT_DATA), temporary
plugins, and the `cuda` marker's skip where there is no GPU."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: The shared data folder; SLAMKIT_DATA names another holding the same sub-folders (on a GPU
#: machine the data travels inside the repository: docs/gpu.md).
DATA = Path(os.environ.get("SLAMKIT_DATA") or REPO.parent / "shared" / "data")
TUM = DATA / "tum_fr1_rpy_first150"
REPLICA = DATA / "replica_room0_first20"
SEVENSCENES = DATA / "7scenes_redkitchen_300to999"


def pytest_collection_modifyitems(config, items):
    """Tests marked `cuda` are skipped, with the reason, where torch sees no CUDA device."""
    cuda_tests = [item for item in items if item.get_closest_marker("cuda")]
    if not cuda_tests:
        return
    import torch

    if not torch.cuda.is_available():
        skip = pytest.mark.skip(reason="CUDA not available")
        for item in cuda_tests:
            item.add_marker(skip)


def require_data(path: Path) -> Path:
    if not path.is_dir():
        pytest.skip(f"shared data not found at {path} (it ships beside the repository in CI)")
    return path


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


def make_plugin_dist(root: Path, dist: str, modules: dict[str, str], entry_points: dict[str, str]) -> Path:
    """Write an importable 'installed' distribution into `root` (add `root` to sys.path)."""
    info = root / f"{dist.replace('-', '_')}-0.1.dist-info"  # the folder name is parsed at the first "-"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 0.1\n")
    lines = "\n".join(f"{name} = {target}" for name, target in entry_points.items())
    (info / "entry_points.txt").write_text(f"[slamkit]\n{lines}\n")
    for name, source in modules.items():
        (root / f"{name}.py").write_text(textwrap.dedent(source))
    return root


def run_slamkit(*args: str, cwd: Path, env_extra: dict[str, str] | None = None, timeout: float = 600):
    """Run the `slamkit` console script; returns the CompletedProcess (text)."""
    env = dict(os.environ, **(env_extra or {}))
    exe = Path(sys.executable).with_name("slamkit")
    return subprocess.run([str(exe), *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
