"""The map checkpoint file: one zip archive, written atomically, that numpy alone can read.

Layout (schema version `SCHEMA_VERSION`):

    meta.json            {"format": "slamkit-checkpoint", "schema_version": 1, ..., "state": {...}}
    arrays/NAME.npy      every array of the state, in numpy's .npy format (no pickles)

The state is a nested structure of dicts, lists, JSON scalars and arrays (numpy arrays or torch
tensors); in meta.json an array is written as {"__array__": NAME} ({"__tensor__": NAME} for a
torch tensor, read back as a CPU tensor). Every member carries the zip CRC-32, so a truncated
file, a flipped byte or a missing array fails to load with a one-line `CheckpointError` naming
the file, as does another schema version; `slamkit.run.checkpoint` checks the contents (what a
run needs to resume). A kill at any moment while writing leaves the previous file: it is written
to a temporary file beside it and renamed (`slamkit.formats.atomic`).
"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from slamkit.errors import DataError
from slamkit.formats.atomic import atomic_open

FORMAT = "slamkit-checkpoint"
#: Bumped whenever the state's layout changes; a file of another version is refused.
SCHEMA_VERSION = 1
#: The file's name inside a run folder.
CHECKPOINT_NAME = "checkpoint.zip"


class CheckpointError(DataError):
    """A checkpoint file that is missing, damaged, of another schema version or incomplete."""


def checkpoint_path(source: str | Path) -> Path:
    """The checkpoint file of `source`: the file itself, or RUN_DIR/checkpoint.zip for a run folder."""
    source = Path(source)
    return source / CHECKPOINT_NAME if source.is_dir() else source


def write_checkpoint(path: str | Path, meta: dict[str, Any], state: dict[str, Any]) -> int:
    """Write `meta` (JSON values) and `state` (see the module docstring) to `path` atomically;
    returns the file's size in bytes."""
    arrays: dict[str, np.ndarray] = {}
    encoded = _encode(state, arrays, "")
    document = {"format": FORMAT, "schema_version": SCHEMA_VERSION, **meta, "state": encoded}
    path = Path(path)
    with atomic_open(path, "wb") as f:
        with zipfile.ZipFile(f, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as archive:
            archive.writestr("meta.json", json.dumps(document, indent=1))
            for name, array in arrays.items():
                with archive.open(f"arrays/{name}.npy", "w", force_zip64=True) as member:
                    np.lib.format.write_array(member, np.ascontiguousarray(array), allow_pickle=False)
    return path.stat().st_size


def read_meta(path: str | Path) -> dict[str, Any]:
    """The checkpoint's meta.json (its `state` with arrays still as references), checked for the
    format and schema version; cheap (no array is read)."""
    path = Path(path)
    with _open(path) as archive:
        return _meta(path, archive)


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """The checkpoint's meta.json with its `state` decoded (numpy arrays and CPU torch tensors)."""
    path = Path(path)
    with _open(path) as archive:
        meta = _meta(path, archive)
        names = {n for n in archive.namelist() if n.startswith("arrays/")}
        meta["state"] = _decode(meta.get("state"), lambda name: _array(path, archive, names, name))
    return meta


def _open(path: Path) -> zipfile.ZipFile:
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} not found (a run writes {CHECKPOINT_NAME} into its folder "
                              f"with checkpoint.save=true, or when interrupted)")
    try:
        return zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError, EOFError) as exc:
        raise CheckpointError(f"checkpoint {path} is damaged or truncated "
                              f"(not a complete zip archive: {exc})") from None


def _meta(path: Path, archive: zipfile.ZipFile) -> dict[str, Any]:
    try:
        meta = json.loads(archive.read("meta.json"))
    except KeyError:
        raise CheckpointError(f"checkpoint {path} has no meta.json (not a slamkit checkpoint)") from None
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
        raise CheckpointError(f"checkpoint {path}: meta.json is damaged ({type(exc).__name__}: {exc})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise CheckpointError(f"checkpoint {path}: meta.json is not a {FORMAT} document")
    version = meta.get("schema_version")
    if version != SCHEMA_VERSION:
        raise CheckpointError(f"checkpoint {path} has schema version {version!r}; this slamkit reads version "
                              f"{SCHEMA_VERSION} only (re-run slamkit to write a new checkpoint)")
    return meta


def _array(path: Path, archive: zipfile.ZipFile, names: set[str], name: str) -> np.ndarray:
    member = f"arrays/{name}.npy"
    if member not in names:
        raise CheckpointError(f"checkpoint {path}: array {name!r} is missing")
    try:
        return np.load(io.BytesIO(archive.read(member)), allow_pickle=False)
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
        raise CheckpointError(f"checkpoint {path}: array {name!r} is damaged ({type(exc).__name__}: {exc})") from None


def _encode(value: Any, arrays: dict[str, np.ndarray], key: str) -> Any:
    if isinstance(value, torch.Tensor):
        arrays[key] = value.detach().cpu().numpy()
        return {"__tensor__": key}
    if isinstance(value, np.ndarray):
        arrays[key] = value
        return {"__array__": key}
    if isinstance(value, dict):
        return {str(k): _encode(v, arrays, f"{key}.{k}" if key else str(k)) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_encode(v, arrays, f"{key}.{i}") for i, v in enumerate(value)]
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    raise TypeError(f"checkpoint state {key!r}: cannot store a {type(value).__name__}")


def _decode(value: Any, load) -> Any:
    if isinstance(value, dict):
        if set(value) == {"__array__"}:
            return load(value["__array__"])
        if set(value) == {"__tensor__"}:
            return torch.from_numpy(load(value["__tensor__"]))
        return {k: _decode(v, load) for k, v in value.items()}
    if isinstance(value, list):
        return [_decode(v, load) for v in value]
    return value
