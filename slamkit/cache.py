"""The project cache: generated data, compiled extensions and sweep scratch space live under
`$SLAMKIT_CACHE` (the Makefile sets it to `.cache/slamkit` in the project), else
`~/.cache/slamkit`."""

from __future__ import annotations

import os
from pathlib import Path


def cache_dir(name: str = "") -> Path:
    """`$SLAMKIT_CACHE/name`, else `~/.cache/slamkit/name` (an absolute path; not created)."""
    root = os.environ.get("SLAMKIT_CACHE")
    base = Path(root).expanduser() if root else Path.home() / ".cache" / "slamkit"
    return (base / name).absolute()
