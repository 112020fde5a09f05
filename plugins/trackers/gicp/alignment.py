"""Levenberg-Marquardt G-ICP on SE(3) against a `Target` (paper Sec. 3.1; Segal et al. 2009).

The pose T (camera-to-world, metres) minimises

    sum_i d_i^T (C_t,i + R C_s,i R^T)^-1 d_i,   d_i = mu_t,i - (R p_i + t)

over source points p_i (camera frame) with covariances C_s,i, from a start pose, with the right
perturbation T <- T exp(xi), re-finding each source point's nearest target mean within the
correspondence distance at every iteration. The loops over points run in the tracker's kernels
(`.kernels`).
"""

from __future__ import annotations

import time

import numpy as np

from slamkit.geometry.transforms import invert_pose, se3_exp
from slamkit_plugins.trackers.gicp.config import GICPConfig
from slamkit_plugins.trackers.gicp.extrapolation import SlideExtrapolation
from slamkit_plugins.trackers.gicp.target import Target

#: The longest cycle of poses (iterations) an alignment is seen to stall in (stop_stalled).
STALL_PERIOD = 6


def new_stats() -> dict:
    """An attempt's effort, zeroed: seconds spent on covariances, neighbour search and solving,
    and Levenberg-Marquardt iterations."""
    return {"covariance_s": 0.0, "nn_search_s": 0.0, "solve_s": 0.0, "iterations": 0}


def matched_fraction(sq: np.ndarray) -> float:
    """The fraction of an alignment's points matched at its last search: `sq`, their squared
    distances to the nearest target mean (m^2), inf where none was within reach (0 for no point)."""
    return float(np.isfinite(sq).mean()) if len(sq) else 0.0


def point_moments(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points' mean (3,) and mean outer product (3, 3), enough for `rms_travel`."""
    return points.mean(axis=0), points.T @ points / len(points)


def rms_travel(moments: tuple[np.ndarray, np.ndarray], start: np.ndarray, end: np.ndarray) -> float:
    """RMS displacement (metres) of points between two poses, from their `point_moments` (camera
    frame): with D = start^-1 end = [R t], the mean of |(R - I) p + t|^2 is
    tr(A S) + 2 t.(R - I) mean + |t|^2, A = (R - I)^T (R - I), S the mean outer product; so an
    alignment can check it at every iteration without a pass over the points."""
    mean, second = moments
    D = invert_pose(start) @ end
    M, t = D[:3, :3] - np.eye(3), D[:3, 3]
    return float(np.sqrt(max(np.sum((M.T @ M) * second) + 2.0 * t @ (M @ mean) + t @ t, 0.0)))


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """The pose with its rotation block projected onto SO(3) (nearest rotation, by SVD), so
    rounding cannot accumulate through pose products."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1.0, 1.0, -1.0]) @ Vt
    out = T.copy()
    out[:3, :3] = R
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


class Aligner:
    """G-ICP of source points to a target with the tracker's settings (`GICPConfig`: iterations,
    tolerances, damping, minimum correspondences) and kernels; max_corr: the correspondence
    distance in metres."""

    def __init__(self, cfg: GICPConfig, kernels, max_corr: float):
        self.cfg = cfg
        self.kernels = kernels
        self.max_corr = max_corr

    def align(self, target: Target, src: np.ndarray, src_cov: np.ndarray, T0: np.ndarray, stats: dict,
              max_corr: float | None = None, deadline: float | None = None, max_travel: float | None = None,
              moments: tuple[np.ndarray, np.ndarray] | None = None):
        """Levenberg-Marquardt G-ICP from T0. Returns (pose, ok, squared NN distances (m^2, inf
        where none) of the last correspondence search, made at the pose or at the one the pose
        is an update from: never at an extrapolated start the pose did not come from).

        It stops early, not converged, when it stalls (with `stop_stalled`: a step lands within
        the tolerances of the pose 2 to STALL_PERIOD iterations back, so the iterations left would
        only go back and forth; stats["stalled"]), when a step takes the source points more than
        `max_travel` metres (RMS, `rms_travel` from the source's `point_moments`, computed here
        unless given) from where T0 put them (stats["slid"]) or past `deadline`
        (time.perf_counter() seconds; stats["out_of_time"]). With `cfg.extrapolation`
        (`tracker.extrapolation`) the next iteration may start from the update's pose moved on
        along the slide (`.extrapolation`); what is checked and returned is always an update's
        pose, and a start that matches too few points is dropped for the update's pose.

        Residuals are taken in the body frame: r_i = R^T (mu_i - R p_i - t) with weight
        W_i = (R^T C_t,i R + C_s,i)^-1 = G_i^T G_i (G_i: inverse Cholesky factor; the
        pseudo-inverse where singular), and T <- T exp(xi), xi = (omega, v), for which
        dr_i/dxi = [[p_i]x, -I]."""
        cfg = self.cfg
        n_target = len(target)
        packed_src = np.concatenate([src, src_cov.reshape(-1, 9)], axis=1)
        T = T0.copy()  # the last Gauss-Newton result: what is checked and returned
        start = T  # where the next iteration linearises: T, or T extrapolated along the slide
        lam = None
        nu = 2.0
        sq = np.full(len(src), np.inf)
        from_search = True  # whether sq was searched at T or at the pose T is one update from
        idx = None  # the last matches: each search starts from them
        converged = False
        recent = [T0]  # the start and the last accepted poses, to see a stall
        if max_travel is not None and moments is None:
            moments = point_moments(src)
        extrapolation = (SlideExtrapolation(T0, cfg.extrapolation, max_corr or self.max_corr)
                         if cfg.extrapolation else None)
        for it in range(cfg.max_iterations):
            if deadline is not None and it and time.perf_counter() > deadline:
                stats["out_of_time"] = True
                break
            stats["iterations"] = it + 1
            R, t = start[:3, :3], start[:3, 3]
            query = (src @ R.T + t).astype(np.float32)
            ts = time.perf_counter()
            d2, idx = target.index.nearest(query, max_corr or self.max_corr, hint=idx)
            te = time.perf_counter()
            stats["nn_search_s"] += te - ts
            sq, from_search = d2.astype(np.float64), start is T
            m = int(np.count_nonzero(idx < n_target))
            stats["num_correspondences"] = m
            if m < cfg.min_correspondences and start is not T:
                start, extrapolation = T, None  # the jump left the surface: on from the update, without jumps
                continue
            if m < cfg.min_correspondences:
                stats["lost_reason"] = f"too few correspondences ({m} < {cfg.min_correspondences})"
                stats["solve_s"] += time.perf_counter() - te
                return T0, False, sq
            lin = self.kernels.linearize(packed_src, target.packed, idx, start)
            H, g, cost0 = lin.H, lin.g, lin.cost
            if lam is None:
                lam = cfg.lm_lambda * float(np.max(np.diag(H)))
            accepted = False
            for _ in range(cfg.lm_max_tries):
                try:
                    xi = np.linalg.solve(H + lam * np.eye(6), -g)
                except np.linalg.LinAlgError:
                    xi = np.linalg.lstsq(H + lam * np.eye(6), -g, rcond=None)[0]
                delta = se3_exp(xi)
                Tn = start @ delta
                cost = lin.cost_at(Tn)  # same correspondences and weights
                small = self._small(delta)
                rho_den = float(xi @ (lam * xi - g))
                rho = (cost0 - cost) / rho_den if rho_den > 0 else -1.0
                if cost <= cost0 or rho > 0:
                    T, from_search = Tn, True
                    lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3) if rho > 0 else 1.0
                    nu = 2.0
                    accepted = True
                    converged = small
                    break
                if small:
                    converged = True
                    T, from_search = start, True
                    break
                lam *= nu
                nu *= 2.0
            stats["solve_s"] += time.perf_counter() - te
            stats["singular_covariances"] = lin.singular
            if converged or not accepted:
                break
            if cfg.stop_stalled and self._stalled(recent, T):
                stats["stalled"] = True
                break
            if max_travel is not None and rms_travel(moments, T0, T) > max_travel:
                stats["slid"] = True
                break
            start = T if extrapolation is None else extrapolation.next_pose(start, T)
        stats["converged"] = bool(converged)
        if not np.isfinite(T).all():
            stats["lost_reason"] = "non-finite pose"
            return T0, False, sq
        if not from_search:
            # the last search was at an extrapolated start that gave no update (no decrease, or
            # too few matches on the last iteration): its distances are not T's, so search at T
            ts = time.perf_counter()
            sq = self.match(target, src, T, max_corr)
            stats["nn_search_s"] += time.perf_counter() - ts
            stats["num_correspondences"] = int(np.count_nonzero(np.isfinite(sq)))  # the fallbacks rank by it
        return orthonormalize(T), True, sq

    def match(self, target: Target, src: np.ndarray, pose: np.ndarray, max_corr: float | None = None) -> np.ndarray:
        """Squared distance (m^2) of each source point at `pose` to its nearest target mean
        within `max_corr` metres (default: max_correspondence_distance; inf where none)."""
        query = (src @ pose[:3, :3].T + pose[:3, 3]).astype(np.float32)
        return target.index.nearest(query, max_corr or self.max_corr)[0].astype(np.float64)

    def _stalled(self, recent: list[np.ndarray], T: np.ndarray) -> bool:
        """Whether T is within the tolerances of the pose 2 to STALL_PERIOD accepted steps back (an
        alignment cycling through poses: 7-Scenes frame 50 goes -4, -2, -1, +7 mm round and round
        for all its iterations, issue 47); T is remembered for the next iteration."""
        stalled = any(self._small(invert_pose(old) @ T) for old in recent[-STALL_PERIOD:-1])
        recent.append(T)
        del recent[:-STALL_PERIOD]
        return stalled

    def _small(self, delta: np.ndarray) -> bool:
        """Whether an update (4x4) is within rotation_tolerance (every |dR - I| entry) and
        translation_tolerance (every |dt| entry, metres): converged."""
        return bool(
            np.abs(delta[:3, :3] - np.eye(3)).max() < self.cfg.rotation_tolerance
            and np.abs(delta[:3, 3]).max() < self.cfg.translation_tolerance
        )
