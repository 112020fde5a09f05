"""The Gaussian map as a PLY file in the standard 3DGS layout (what common splat viewers open).

One ``vertex`` element, binary little endian, float32 properties in this order:

    x y z  nx ny nz  f_dc_0 f_dc_1 f_dc_2  opacity  scale_0 scale_1 scale_2  rot_0 rot_1 rot_2 rot_3

x y z: world mean, metres; nx ny nz: zeros; f_dc = (rgb - 0.5) / C0, SH degree 0 (C0 =
0.28209479177387814); opacity: its logit; scale: log standard deviations in metres; rot:
quaternion (w, x, y, z), not necessarily normalised. `load_ply` also reads ascii and big-endian
files, any numeric property type, extra properties (f_rest_* are ignored: slamkit's colours are
SH degree 0) and other elements before the vertices; anything else is a DataError naming the file.
`save_ply` leaves out a Gaussian with a non-finite parameter (`finite_rows`): viewers cannot draw
it and some refuse the whole file.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from slamkit.errors import DataError
from slamkit.formats.atomic import atomic_open
from slamkit.map.gaussian_map import GaussianMap, GaussianRows

log = logging.getLogger(__name__)

#: The degree-0 real spherical harmonic, 1 / (2 sqrt(pi)).
C0 = 0.28209479177387814

PROPERTIES = (
    "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
    "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
)
#: Properties load_ply needs (the normals are optional).
REQUIRED = tuple(p for p in PROPERTIES if p not in ("nx", "ny", "nz"))

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": None}


def finite_rows(gaussian_map: GaussianMap) -> np.ndarray:
    """(N,) bool: the Gaussians whose every parameter (mean, rotation, scales, opacity, colour) is
    finite."""
    with gaussian_map.lock:
        columns = [gaussian_map.means, gaussian_map.quats, gaussian_map.log_scales,
                   gaussian_map.opacity_logits.reshape(-1, 1), gaussian_map.colors]
        return torch.cat([c.detach() for c in columns], dim=1).isfinite().all(dim=1).cpu().numpy()


def save_ply(path: str | Path, gaussian_map: GaussianMap) -> int:
    """Write `gaussian_map` to `path` (binary little endian 3DGS layout; written to a temporary
    file first, then renamed, so a reader never sees half a file), but its Gaussians with a
    non-finite parameter; returns how many were left out (logged as a warning)."""
    path = Path(path)
    with gaussian_map.lock:  # re-entrant: finite_rows takes it too
        keep = finite_rows(gaussian_map)
        means = gaussian_map.means.detach().cpu().numpy()[keep]
        colors = gaussian_map.colors.detach().cpu().numpy()[keep]
        opacity = gaussian_map.opacity_logits.detach().cpu().numpy()[keep]
        log_scales = gaussian_map.log_scales.detach().cpu().numpy()[keep]
        quats = gaussian_map.quats.detach().cpu().numpy()[keep]
    n = len(means)
    dropped = len(keep) - n
    if dropped:
        log.warning("%s: %d of %d Gaussians have a non-finite parameter and are left out", path, dropped, len(keep))
    data = np.zeros(n, dtype=[(p, "<f4") for p in PROPERTIES])
    for i, axis in enumerate("xyz"):
        data[axis] = means[:, i]
    for i in range(3):
        data[f"f_dc_{i}"] = (colors[:, i] - 0.5) / C0
        data[f"scale_{i}"] = log_scales[:, i]
    data["opacity"] = opacity
    for i in range(4):
        data[f"rot_{i}"] = quats[:, i]
    header = "ply\nformat binary_little_endian 1.0\ncomment slamkit Gaussian map (3DGS layout, SH degree 0)\n"
    header += f"element vertex {n}\n" + "".join(f"property float {p}\n" for p in PROPERTIES) + "end_header\n"
    with atomic_open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(data.tobytes())
    return dropped


def _parse_header(path: Path, raw: bytes):
    """(format, [(element name, count, [(property, numpy type)])], header length in bytes)."""
    expected = "a 3D Gaussian Splatting PLY file"
    if not raw.startswith(b"ply\n") and not raw.startswith(b"ply\r\n"):
        raise DataError(f"{path}: not a PLY file (no 'ply' magic line; expected {expected})")
    end = raw.find(b"end_header")
    if end < 0:
        raise DataError(f"{path}: PLY header has no end_header line (expected {expected})")
    newline = raw.find(b"\n", end)
    if newline < 0:
        raise DataError(f"{path}: PLY header is truncated after end_header")
    try:
        lines = raw[:end].decode("ascii").splitlines()[1:]
    except UnicodeDecodeError:
        raise DataError(f"{path}: PLY header is not ASCII text") from None
    fmt, elements = None, []
    for number, line in enumerate(lines, start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        bad = f"{path}: PLY header line {number} {line.strip()!r} is malformed"
        if words[0] == "format":
            if len(words) != 3 or words[1] not in _FORMATS:
                raise DataError(f"{bad} (expected 'format binary_little_endian|binary_big_endian|ascii 1.0')")
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise DataError(f"{bad} (expected 'element NAME COUNT')")
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise DataError(f"{bad} (a property before any element)")
            if len(words) == 5 and words[1] == "list":
                elements[-1][2].append((words[4], None))
            elif len(words) == 3 and words[1] in _TYPES:
                elements[-1][2].append((words[2], _TYPES[words[1]]))
            else:
                raise DataError(f"{bad} (expected 'property TYPE NAME' with a numeric TYPE)")
        else:
            raise DataError(f"{bad} (unknown keyword {words[0]!r})")
    if fmt is None:
        raise DataError(f"{path}: PLY header has no format line")
    return fmt, elements, newline + 1


def _read_vertices(path: Path) -> np.ndarray:
    try:
        raw = path.read_bytes()
    except OSError as exc:
        reason = exc.strerror or exc
        raise DataError(f"cannot read {path}: {reason} (expected a 3D Gaussian Splatting PLY file)") from None
    fmt, elements, offset = _parse_header(path, raw)
    order = _FORMATS[fmt]
    if fmt == "ascii":
        rows = raw[offset:].decode("ascii", errors="replace").split("\n")
        row = 0
    for name, count, props in elements:
        if any(t is None for _, t in props):
            raise DataError(f"{path}: element {name!r} has list properties before the vertices (not a Gaussian map)")
        if len(set(p for p, _ in props)) != len(props):
            raise DataError(f"{path}: element {name!r} repeats a property name")
        if fmt == "ascii":
            chunk = [r for r in rows[row : row + count]]
            row += count
            if len(chunk) < count:
                raise DataError(f"{path}: element {name!r} has {len(chunk)} of its {count} rows (file truncated)")
            data = np.zeros(count, dtype=[(p, t) for p, t in props])
            try:
                table = np.array([r.split() for r in chunk], dtype=np.float64).reshape(count, len(props))
            except ValueError:
                raise DataError(f"{path}: element {name!r}: a row does not hold {len(props)} numbers") from None
            for i, (p, _) in enumerate(props):
                data[p] = table[:, i]
        else:
            dtype = np.dtype([(p, order + t) for p, t in props])
            size = dtype.itemsize * count
            if offset + size > len(raw):
                raise DataError(
                    f"{path}: element {name!r} needs {size} bytes but only {len(raw) - offset} remain (file truncated)"
                )
            data = np.frombuffer(raw, dtype=dtype, count=count, offset=offset)
            offset += size
        if name == "vertex":
            return data
    raise DataError(f"{path}: no 'vertex' element (expected a 3D Gaussian Splatting PLY file)")


def load_ply(path: str | Path, device: str | torch.device = "cpu") -> GaussianMap:
    """Read a 3DGS PLY file into a new GaussianMap (every Gaussian trackable, keyframe_id -1).
    Raises DataError for a malformed file or one missing a required property."""
    path = Path(path)
    data = _read_vertices(path)
    names = data.dtype.names or ()
    missing = [p for p in REQUIRED if p not in names]
    if missing:
        raise DataError(
            f"{path}: vertex element lacks {', '.join(missing)} (expected the 3DGS properties {' '.join(REQUIRED)})"
        )

    def cols(*props: str) -> np.ndarray:
        return np.stack([np.asarray(data[p], dtype=np.float32) for p in props], axis=1)

    n = len(data)
    gm = GaussianMap(device)
    values = {
        "means": cols("x", "y", "z"),
        "quats": cols("rot_0", "rot_1", "rot_2", "rot_3"),
        "log_scales": cols("scale_0", "scale_1", "scale_2"),
        "opacity_logits": np.asarray(data["opacity"], dtype=np.float32).reshape(n),
        "colors": cols("f_dc_0", "f_dc_1", "f_dc_2") * np.float32(C0) + np.float32(0.5),
    }
    rows = {name: torch.tensor(np.ascontiguousarray(value), device=gm.device) for name, value in values.items()}
    gm.append(GaussianRows.from_parameters(rows, trackable=torch.ones(n, dtype=torch.bool, device=gm.device),
                           keyframe_id=torch.full((n,), -1, dtype=torch.int64, device=gm.device)))
    return gm
