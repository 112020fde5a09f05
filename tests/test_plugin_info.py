"""`slamkit-plugins` and the generated configuration reference."""

from __future__ import annotations

import pytest

import subprocess
import sys
from pathlib import Path

from slamkit.cli.plugins import markdown_reference
from slamkit.registry.discovery import discover

from conftest import REPO


@pytest.mark.slow
def test_listing_shows_every_builtin_with_its_fields():
    exe = Path(sys.executable).with_name("slamkit-plugins")
    out = subprocess.run([str(exe)], capture_output=True, text=True, check=True).stdout
    for role, name in [("dataset", "tum"), ("tracker", "gicp"), ("tracker", "kiss_icp"), ("keyframe", "overlap"),
                       ("mapper", "none")]:
        assert f"{role}:" in out and f"  {name}  [" in out
    assert "voxel_size: float = 0.05  # metres" in out  # kiss_icp: type, default and doc


def test_configuration_reference_is_current():
    """docs/configuration.md is generated; regenerate with
    `slamkit-plugins --markdown docs/configuration.md` after changing a config dataclass."""
    expected = markdown_reference(discover())
    assert (REPO / "docs" / "configuration.md").read_text() == expected
