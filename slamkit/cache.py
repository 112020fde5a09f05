"""The project cache: generated data, compiled extensions and sweep scratch space live under
`$SLAMKIT_CACHE` (the Makefile sets it to `.cache/slamkit` in the project), else
`~/.cache/slamkit`.

A cached file is only used as recorded: whoever writes one records its size and SHA-256 beside
it (`record`, `NAME.record.json`), and a reader checks them first (`damage`). A file cut short
(`truncate -s 50%`), changed in place or written by something else is then rebuilt instead of
being loaded: a truncated shared library would kill its process with SIGBUS as its pages are
touched, a damaged archive would fail in the middle of a run.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

#: Bytes read at a time while hashing a cached file.
_CHUNK = 1 << 20


def cache_dir(name: str = "") -> Path:
    """`$SLAMKIT_CACHE/name`, else `~/.cache/slamkit/name` (an absolute path; not created)."""
    root = os.environ.get("SLAMKIT_CACHE")
    base = Path(root).expanduser() if root else Path.home() / ".cache" / "slamkit"
    return (base / name).absolute()


def record_path(path: Path) -> Path:
    """Where the record of the cached file `path` is kept."""
    return path.with_name(path.name + ".record.json")


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def record(path: Path, content: Path | None = None) -> None:
    """Record the size and SHA-256 of `content` (default: `path` itself; e.g. the temporary file
    about to be renamed to `path`) as those of the cached file `path` (written atomically)."""
    from slamkit.formats.atomic import write_atomic

    content = Path(content or path)
    write_atomic(record_path(Path(path)), json.dumps({"size": content.stat().st_size,
                                                      "sha256": _sha256(content)}) + "\n")


def damage(path: Path) -> str | None:
    """Why the cached file `path` cannot be used as it is (None when it matches its record):
    missing, without a record, or of another size or content than recorded."""
    path = Path(path)
    if not path.is_file():
        return "missing"
    try:
        recorded = json.loads(record_path(path).read_text())
        size, sha256 = int(recorded["size"]), str(recorded["sha256"])
    except FileNotFoundError:
        return "no record of its size and hash"
    except (OSError, ValueError, KeyError, TypeError) as exc:
        return f"its record {record_path(path).name} is unreadable ({type(exc).__name__})"
    actual = path.stat().st_size
    if actual != size:
        return f"{actual} bytes, recorded {size}"
    if _sha256(path) != sha256:
        return "its content is not the one recorded"
    return None
