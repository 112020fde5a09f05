"""`slamkit-plugins`: the listing of every built-in plugin with its config fields."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path


def test_listing_shows_every_builtin_with_its_fields():
    exe = Path(sys.executable).with_name("slamkit-plugins")
    out = subprocess.run([str(exe)], capture_output=True, text=True, check=True).stdout
    for role, name in [("dataset", "tum"), ("tracker", "gicp"), ("tracker", "kiss_icp"), ("keyframe", "overlap"),
                       ("mapper", "none")]:
        assert f"{role}:" in out and f"  {name}  [" in out
    assert "voxel_size: float = 0.05  # metres" in out  # kiss_icp: type, default and doc
