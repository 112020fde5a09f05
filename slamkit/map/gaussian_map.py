"""The Gaussian map shared by tracking and mapping, and the rows that enter it."""

from __future__ import annotations

import math
import threading
from contextlib import contextmanager
from dataclasses import dataclass, fields
from typing import Iterator

import numpy as np
import torch

from slamkit.geometry.pose_graph import owning_keyframes
from slamkit.geometry.transforms import covariance_from_scales, quat_left_matrix, rotmat_to_quat, scales_from_covariance
from slamkit.types import Deferred

#: The optimisable parameters, in this order everywhere (GaussianMap, GaussianRows, optimisers).
PARAMETERS = ("means", "quats", "log_scales", "opacity_logits", "colors")
#: The geometry a Gaussian entered the map with, which no optimiser changes: entry field -> parameter.
ENTRY_GEOMETRY = {"entry_means": "means", "entry_quats": "quats", "entry_log_scales": "log_scales"}
#: The map's row schema: every per-row field (GaussianRows' fields) and its width (0: one value
#: per row). Checkpoints and exports read the map through it.
ROW_WIDTHS = {"means": 3, "quats": 4, "log_scales": 3, "opacity_logits": 0, "colors": 3, "trackable": 0,
              "keyframe_id": 0, "entry_means": 3, "entry_quats": 4, "entry_log_scales": 3}


def _logit(p: np.ndarray) -> np.ndarray:
    return np.log(p / (1 - p))


def _log_scales(scales, device) -> torch.Tensor:
    """float32 log of standard deviations (metres, clamped at 1e-8)."""
    log = np.log(np.maximum(np.asarray(scales, dtype=np.float64), 1e-8))
    return torch.as_tensor(log.astype(np.float32), device=device)


class _Decomposition:
    """Quaternions and log-scales of rows made from covariances, computed on first use and only
    for the rows selected by then: a keyframe's coverage test leaves most of its candidate rows
    out (71 % on TUM fr1/rpy), and the eigen-decomposition is most of what a row costs to make.
    covariances: a zero-argument function giving the (N,3,3) m^2 world covariances; index: the
    rows of it these are (None = all); scale_factors: (N,) divisors of the scales or None."""

    def __init__(self, covariances, scale_factors, device, index=None):
        self.covariances, self.scale_factors = covariances, scale_factors
        self.device, self.index = device, index
        self._tensors: dict[str, torch.Tensor] | None = None

    def select(self, index: np.ndarray) -> _Decomposition:
        index = np.flatnonzero(index) if index.dtype == bool else index
        rows = index if self.index is None else self.index[index]
        return _Decomposition(self.covariances, self.scale_factors, self.device, rows)

    def tensor(self, name: str, copy: bool = False) -> torch.Tensor:
        """The rows' "quats" or "log_scales"; copy: a second tensor of the same values, made
        with the first (the entry geometry, which later in-place updates of the first must not
        reach whichever is read first)."""
        if self._tensors is None:
            cov = np.asarray(self.covariances(), dtype=np.float64)
            factors = self.scale_factors
            if self.index is not None:
                cov = cov[self.index]
                factors = None if factors is None else factors[self.index]
            quats, scales = scales_from_covariance(cov)
            if factors is not None:
                scales = scales / np.asarray(factors, dtype=np.float64)[:, None]
            made = {"quats": torch.as_tensor(quats.astype(np.float32), device=self.device),
                    "log_scales": _log_scales(scales, self.device)}
            self._tensors = {(k, copy): t.clone() if copy else t for k, t in made.items() for copy in (False, True)}
        return self._tensors[name, copy]


class _PendingShape:
    """A GaussianRows field not computed yet: one tensor of a _Decomposition (a copy of it for
    the entry geometry, which the optimiser's updates must not reach)."""

    def __init__(self, decomposition: _Decomposition, name: str, copy: bool = False):
        self.decomposition, self.name, self.copy = decomposition, name, copy

    def __call__(self) -> torch.Tensor:
        return self.decomposition.tensor(self.name, self.copy)

    def entry(self) -> _PendingShape:
        """The entry-geometry field of the same rows (a copy made with this one)."""
        return _PendingShape(self.decomposition, self.name, copy=True)

    def select(self, index: np.ndarray, selected: dict) -> _PendingShape:
        """The same field of the rows at `index`; `selected` shares one selected decomposition
        between the fields of one `GaussianRows.select`."""
        key = id(self.decomposition)
        if key not in selected:
            selected[key] = self.decomposition.select(index)
        return _PendingShape(selected[key], self.name, self.copy)


@dataclass
class GaussianRows:
    """Gaussians that are not (or not yet) rows of a map, in the map's parameterisation: torch
    tensors with one row each. means (N,3) world metres; quats (N,4) (w, x, y, z); log_scales
    (N,3) log of standard deviations in metres; opacity_logits (N,); colors (N,3) RGB in [0, 1];
    trackable (N,) bool; keyframe_id (N,) int64 (the keyframe that added it, -1 = none);
    entry_means, entry_quats, entry_log_scales: the geometry it entered the map with (what a
    tracker aligns to, see GaussianMap). Rows made `from_covariances` compute their quats and
    log_scales (and entry copies) when first read (Deferred), for the rows selected by then."""

    means: torch.Tensor
    quats: torch.Tensor = Deferred()
    log_scales: torch.Tensor = Deferred()
    opacity_logits: torch.Tensor
    colors: torch.Tensor
    trackable: torch.Tensor
    keyframe_id: torch.Tensor
    entry_means: torch.Tensor
    entry_quats: torch.Tensor = Deferred()
    entry_log_scales: torch.Tensor = Deferred()

    @classmethod
    def from_parameters(cls, params: dict[str, torch.Tensor], trackable: torch.Tensor,
                        keyframe_id: torch.Tensor) -> GaussianRows:
        """Rows entering now: their entry geometry is their current one."""
        entry = {field: params[name].detach().clone() for field, name in ENTRY_GEOMETRY.items()}
        return cls(**{k: params[k] for k in PARAMETERS}, trackable=trackable, keyframe_id=keyframe_id, **entry)

    def entering_now(self) -> GaussianRows:
        """These rows with their current geometry as their entry geometry (new Gaussians made
        from others, e.g. a split's children)."""
        return GaussianRows.from_parameters(self.parameters(), self.trackable, self.keyframe_id)

    @classmethod
    def from_shapes(cls, means, quats, scales, colors, opacity, trackable, keyframe_id, device=None) -> GaussianRows:
        """From numpy arrays in natural units: scales (N,3) metres (clamped at 1e-8), opacity
        (N,) or a scalar in (0, 1), keyframe_id an int or (N,) ints."""
        n = len(means)
        quats = torch.as_tensor(np.asarray(quats, dtype=np.float32), device=device).reshape(n, 4)
        return cls._made(means, quats, _log_scales(scales, device).reshape(n, 3), colors, opacity, trackable,
                         keyframe_id, device)

    @classmethod
    def from_covariances(cls, means, covariances, colors, opacity, trackable, keyframe_id, scale_factors=None,
                         device=None) -> GaussianRows:
        """From world covariances (N,3,3) m^2, or a zero-argument function giving them; each
        standard deviation optionally divided by `scale_factors` (N,) (the scale alignment of
        Gaussians entering the map). The decomposition into quats and scales is done when they
        are first read, for the rows `select`ed by then."""
        source = covariances if callable(covariances) else (lambda: covariances)
        factors = None if scale_factors is None else np.asarray(scale_factors, dtype=np.float64)
        shapes = _Decomposition(source, factors, device)
        return cls._made(means, _PendingShape(shapes, "quats"), _PendingShape(shapes, "log_scales"), colors, opacity,
                         trackable, keyframe_id, device)

    @classmethod
    def _made(cls, means, quats, log_scales, colors, opacity, trackable, keyframe_id, device) -> GaussianRows:
        """Rows entering now from numpy values (quats, log_scales: tensors or _PendingShapes)."""
        n = len(means)
        opacity = np.broadcast_to(np.asarray(opacity, dtype=np.float64), (n,))

        def f32(a, width):
            return torch.as_tensor(np.asarray(a, dtype=np.float32), device=device).reshape((n, width) if width else n)

        def entry(value):
            return value.entry() if isinstance(value, _PendingShape) else value.clone()

        means_t = f32(means, 3)
        return cls(means=means_t, quats=quats, log_scales=log_scales, opacity_logits=f32(_logit(opacity), 0),
                   colors=f32(colors, 3), trackable=torch.as_tensor(np.asarray(trackable, dtype=bool),
                                                                    device=device).reshape(n),
                   keyframe_id=torch.as_tensor(np.broadcast_to(np.asarray(keyframe_id, dtype=np.int64), (n,)).copy(),
                                               device=device),
                   entry_means=means_t.clone(), entry_quats=entry(quats), entry_log_scales=entry(log_scales))

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def select(self, index) -> GaussianRows:
        """The rows at `index` (a bool mask or integer indices, numpy or torch)."""
        index = torch.as_tensor(np.asarray(index) if not isinstance(index, torch.Tensor) else index,
                                device=self.means.device)
        if index.dtype == torch.uint8:  # torch's old mask type: a mask here too
            index = index.bool()
        values, selected, host_index = {}, {}, None
        for f in fields(self):
            pending = Deferred.pending(self, f.name)
            if isinstance(pending, _PendingShape):
                host_index = index.cpu().numpy() if host_index is None else host_index
                values[f.name] = pending.select(host_index, selected)
            else:
                values[f.name] = getattr(self, f.name)[index]
        return GaussianRows(**values)

    def computed(self) -> GaussianRows:
        """These rows with every field computed (the decomposition done now, e.g. before taking
        the map's lock)."""
        for f in fields(self):
            getattr(self, f.name)
        return self

    def __getstate__(self) -> dict:  # pickled with every field computed (pending ones are closures)
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def __setstate__(self, state: dict) -> None:
        for name, value in state.items():
            setattr(self, name, value)

    def parameters(self) -> dict[str, torch.Tensor]:
        return {name: getattr(self, name) for name in PARAMETERS}


@dataclass
class RowMotion:
    """A rigid motion per map row, as the row's parameters see it: row i's mean x becomes
    `rotations[i] @ x + translations[i]` and its quaternion q becomes `quat_maps[i] @ q` (the
    Hamilton product with the rotation's quaternion). rotations (N,3,3), translations (N,3),
    quat_maps (N,4,4), float64 tensors on the map's device; `moved` (N,) bool: rows whose motion
    is not the identity."""

    rotations: torch.Tensor
    translations: torch.Tensor
    quat_maps: torch.Tensor
    moved: torch.Tensor

    @classmethod
    def of(cls, motions: np.ndarray, which: torch.Tensor) -> RowMotion:
        """Row i moves by `motions[which[i]]`: motions (M,4,4) world-frame rigid motions
        (float64), which (N,) integer indices into them."""
        motions = np.asarray(motions, dtype=np.float64).reshape(-1, 4, 4)
        device = which.device
        quats = rotmat_to_quat(motions[:, :3, :3])
        per_motion = [torch.as_tensor(a, dtype=torch.float64, device=device)
                      for a in (motions[:, :3, :3], motions[:, :3, 3], quat_left_matrix(quats))]
        identity = torch.as_tensor(np.all(np.abs(motions - np.eye(4)) <= 1e-15, axis=(1, 2)), device=device)
        which = which.long()
        rotations, translations, quat_maps = (a[which] for a in per_motion)
        return cls(rotations, translations, quat_maps, ~identity[which])


def _leaf(t: torch.Tensor) -> torch.Tensor:
    """`t` as a new leaf tensor that autograd differentiates (the map's parameters)."""
    return t.detach().requires_grad_(True)


class GaussianMap:
    """3D Gaussians in world coordinates, stored as the 3DGS optimiser sees them.

    Parameters (float32 leaf tensors with requires_grad, one row per Gaussian; see PARAMETERS):
      means (N,3) metres; quats (N,4) (w, x, y, z), not necessarily unit (normalised where
      used); log_scales (N,3) log of standard deviations in metres; opacity_logits (N,) logit
      of opacity; colors (N,3) RGB in [0, 1] (SH degree 0).
    Per-Gaussian flags: trackable (N,) bool, keyframe_id (N,) int64 (the keyframe that added it).
    Entry geometry: entry_means, entry_quats, entry_log_scales, the values each Gaussian entered
    the map with, which no optimiser changes. The tracker aligns to them by default
    (`tracking_target(geometry="entry")`): the mapper reshapes and turns Gaussians for rendering
    (1-3 mm trackable Gaussians, smaller than a training pixel, have their normals turned by
    7-14 degrees median on TUM fr1/rpy), which cost 28% mean ATE when the tracker aligned to the
    optimised shapes (docs/tracking_under_mapping.md).

    Concurrency: whoever changes the map holds `lock`. Every change bumps `version`; removing or
    overwriting rows also bumps `structure_version` (appending does not), so a training step
    that started before can tell that its rows no longer hold the same Gaussians. Rows are
    appended only at the end. The tracker never reads the live tensors: it
    takes a `tracking_target()` copy under the lock, at a tracking keyframe.
    """

    def __init__(self, device: str | torch.device = "cpu"):
        self.device = torch.device(device)
        self.lock = threading.RLock()
        self.version = 0
        self.structure_version = 0
        empty = GaussianRows.from_shapes(np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 3)), np.zeros((0, 3)),
                                         0.5, np.zeros(0, bool), 0, self.device)
        self._set(empty)

    def _set(self, rows: GaussianRows) -> None:
        for f in fields(GaussianRows):
            value = getattr(rows, f.name)
            setattr(self, f.name, _leaf(value) if f.name in PARAMETERS else value)

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def scales(self) -> torch.Tensor:
        """(N,3) standard deviations in metres."""
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:
        """(N,) opacities in (0, 1)."""
        return torch.sigmoid(self.opacity_logits)

    def parameters(self) -> dict[str, torch.Tensor]:
        """The optimisable leaf tensors by name (PARAMETERS order)."""
        return {name: getattr(self, name) for name in PARAMETERS}

    def _columns(self) -> dict[str, torch.Tensor]:
        """Every per-row tensor by GaussianRows field name (detached, not copied)."""
        return {f.name: getattr(self, f.name).detach() for f in fields(GaussianRows)}

    def rows(self, index=None) -> GaussianRows:
        """A detached copy of the rows at `index` (all rows when None)."""
        with self.lock:
            sel = slice(None) if index is None else index
            return GaussianRows(**{k: v[sel].clone() for k, v in self._columns().items()})

    def append(self, rows: GaussianRows) -> slice:
        """Add `rows` at the end; returns the rows they occupy."""
        with self.lock:
            start = len(self)
            merged = {k: torch.cat([v, getattr(rows, k).to(self.device)]) for k, v in self._columns().items()}
            self._set(GaussianRows(**merged))
            self.version += 1
        return slice(start, start + len(rows))

    def keep(self, mask: torch.Tensor) -> None:
        """Keep only the Gaussians where `mask` is true (the others are removed)."""
        with self.lock:
            mask = torch.as_tensor(mask, device=self.device)
            self._set(GaussianRows(**{k: v[mask] for k, v in self._columns().items()}))
            self.version += 1
            self.structure_version += 1

    def overwrite(self, index, rows: GaussianRows) -> None:
        """Give the rows at `index` (integer indices or a slice) the values and flags of `rows`:
        they hold other Gaussians now (`structure_version` changes)."""
        with self.lock, torch.no_grad():
            for f in fields(GaussianRows):
                getattr(self, f.name)[index] = getattr(rows, f.name).to(self.device)
            self.version += 1
            self.structure_version += 1

    def keyframe_motion(self, updates: np.ndarray) -> RowMotion:
        """Each row's motion when keyframe k moves by `updates[k]` ((K,4,4) world-frame rigid
        motions of keyframes 0..K-1, K >= 1): a row follows the keyframe that added it
        (`keyframe_id`; a row of a later keyframe follows the last one, of none the first)."""
        with self.lock:
            ids = self.keyframe_id.cpu().numpy()
        which = owning_keyframes(ids, np.arange(len(updates)))
        return RowMotion.of(updates, torch.as_tensor(which, device=self.device))

    def move_rows(self, motion: RowMotion) -> None:
        """Move every row rigidly by `motion` (one per row): its mean and entry mean, its
        quaternion and entry quaternion (scales, opacities and colours are the Gaussian's own).
        The rows hold their Gaussians elsewhere now: the parameters are new tensors (a training
        step in flight keeps differentiating the old ones) and `structure_version` changes (so
        such a step is dropped rather than applied to moved Gaussians)."""
        with self.lock, torch.no_grad():
            if len(motion.rotations) != len(self):
                raise ValueError(f"GaussianMap.move_rows: expected one motion per row ({len(self)}), "
                                 f"got {len(motion.rotations)}")
            columns = self._columns()
            for name in ("means", "entry_means"):
                x = columns[name].double()
                columns[name] = (torch.einsum("nij,nj->ni", motion.rotations, x)
                                 + motion.translations).to(columns[name].dtype)
            for name in ("quats", "entry_quats"):
                q = columns[name].double()
                columns[name] = torch.einsum("nij,nj->ni", motion.quat_maps, q).to(columns[name].dtype)
            self._set(GaussianRows(**columns))
            self.version += 1
            self.structure_version += 1

    def clamp_opacity(self, max_opacity: float) -> None:
        """Clamp every opacity to at most `max_opacity` (in (0, 1))."""
        with self.lock, torch.no_grad():
            self.opacity_logits.clamp_(max=math.log(max_opacity / (1 - max_opacity)))
            self.version += 1

    @contextmanager
    def updating(self) -> Iterator[dict[str, torch.Tensor]]:
        """Hold the lock while the block updates the parameters in place (an optimiser step);
        yields them by name, and counts the change when the block ends."""
        with self.lock:
            try:
                yield self.parameters()
            finally:
                self.version += 1

    def columns(self) -> dict[str, torch.Tensor]:
        """A detached copy of every per-row field (ROW_WIDTHS), by name."""
        with self.lock:
            return {k: v.clone() for k, v in self._columns().items()}

    def restore(self, columns: dict[str, torch.Tensor], version: int) -> None:
        """Append the rows of a saved `columns()` and take the saved `version` (an empty map
        restoring a checkpoint)."""
        with self.lock:
            self.append(GaussianRows(**{name: torch.as_tensor(columns[name]) for name in ROW_WIDTHS}))
            self.version = version

    @classmethod
    def from_columns(cls, columns: dict[str, torch.Tensor], version: int = 0,
                     device: str | torch.device = "cpu") -> GaussianMap:
        """A map holding the rows of a saved `columns()`, at `version`."""
        gm = cls(device)
        gm.restore(columns, version)
        return gm

    def covariances(self) -> torch.Tensor:
        """(N,3,3) world-frame covariances R diag(s^2) R^T in m^2."""
        return covariance_from_scales(self.quats.detach(), self.scales.detach())

    def trackable_entry_means(self, first_keyframe: int) -> np.ndarray:
        """(P,3) float32 world metres: where the trackable Gaussians that keyframes
        `first_keyframe` and later added entered the map (those a tracker's target built before
        them lacks)."""
        with self.lock:
            keep = self.trackable & (self.keyframe_id >= first_keyframe)
            return self.entry_means.detach()[keep].cpu().numpy().astype(np.float32, copy=True)

    def tracking_target(self, min_opacity: float = 0.0, geometry: str = "entry") -> TrackingTarget:
        """Copy the trackable Gaussians with opacity above `min_opacity` for a tracker, with their
        `geometry`: "entry" (means and shapes as they entered the map) or "optimised" (the
        mapper's current values, as the reference code)."""
        with self.lock:
            keep = self.trackable & (self.opacities.detach() > min_opacity)
            prefix = {"entry": "entry_", "optimised": ""}[geometry]
            means, quats, log_scales = (getattr(self, prefix + name).detach()[keep]
                                        for name in ("means", "quats", "log_scales"))
            cov = covariance_from_scales(quats, torch.exp(log_scales))
            return TrackingTarget(
                means=means.cpu().numpy().copy(), covariances=cov.cpu().numpy().copy(), version=self.version
            )


@dataclass
class TrackingTarget:
    """A read-only copy of the map Gaussians a tracker aligns to (world frame).

    means: Nx3 float32 metres. covariances: Nx3x3 float32 m^2 (raw, not regularised).
    version: the map version it was taken from.
    """

    means: np.ndarray
    covariances: np.ndarray
    version: int
