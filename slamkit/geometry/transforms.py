"""Rigid-body and Gaussian geometry, vectorised. Each formula lives here once.

Quaternions are (w, x, y, z), Hamilton convention, rotating vectors from the local frame to
the parent frame. Functions accept numpy arrays or torch tensors (same module out as in) unless
they say otherwise, so the tracker (numpy) and the rasteriser (torch) share one formula.
"""

from __future__ import annotations

import numpy as np

try:  # torch is a hard dependency of the package, but keep geometry importable without it
    import torch
except ImportError:  # pragma: no cover
    torch = None


def _xp(a):
    return torch if torch is not None and isinstance(a, torch.Tensor) else np


def quat_to_rotmat(q):
    """(..., 4) quaternions (w, x, y, z), normalised here, to (..., 3, 3) rotation matrices."""
    xp = _xp(q)
    q = q / xp.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]
    return xp.stack(rows, axis=-1).reshape(q.shape[:-1] + (3, 3))


def quat_left_matrix(q):
    """(..., 4, 4) matrices L(q) of (..., 4) quaternions (w, x, y, z): the Hamilton product
    q * p is L(q) @ p (L(q) is orthogonal for a unit q: rotating a quaternion by q is linear)."""
    xp = _xp(q)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [w, -x, -y, -z,
            x, w, -z, y,
            y, z, w, -x,
            z, -y, x, w]
    return xp.stack(rows, axis=-1).reshape(q.shape[:-1] + (4, 4))


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices to (..., 4) unit quaternions (w, x, y, z) with w >= 0.

    numpy only. Uses the numerically stable branch per matrix (largest diagonal term)."""
    R = np.asarray(R, dtype=np.float64)
    batch = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    m00, m11, m22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    trace = m00 + m11 + m22
    # Four candidate solutions; pick the best conditioned one per matrix.
    cand = np.stack([
        np.stack([1 + trace, R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], -1),
        np.stack([R[:, 2, 1] - R[:, 1, 2], 1 + m00 - m11 - m22, R[:, 0, 1] + R[:, 1, 0], R[:, 0, 2] + R[:, 2, 0]], -1),
        np.stack([R[:, 0, 2] - R[:, 2, 0], R[:, 0, 1] + R[:, 1, 0], 1 - m00 + m11 - m22, R[:, 1, 2] + R[:, 2, 1]], -1),
        np.stack([R[:, 1, 0] - R[:, 0, 1], R[:, 0, 2] + R[:, 2, 0], R[:, 1, 2] + R[:, 2, 1], 1 - m00 - m11 + m22], -1),
    ], axis=1)
    best = np.argmax(np.stack([trace, m00, m11, m22], -1), axis=-1)
    q = cand[np.arange(len(R)), best]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q.reshape(batch + (4,))


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 float64 pose from a 3x3 rotation and a translation in metres."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation matrices closest (Frobenius) to (..., 3, 3) matrices, via SVD."""
    U, _, Vt = np.linalg.svd(M)
    U = U.copy()
    U[..., :, 2] *= np.linalg.det(U @ Vt)[..., None]
    return U @ Vt


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to Nx3 points."""
    return points @ T[:3, :3].T + T[:3, 3]


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid (..., 4, 4) transforms."""
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    inv = np.zeros_like(T)
    inv[..., :3, :3] = Rt
    inv[..., :3, 3] = -(Rt @ T[..., :3, 3, None])[..., 0]
    inv[..., 3, 3] = 1.0
    return inv


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues: (..., 3) axis-angle vectors (radians) to (..., 3, 3) rotation matrices."""
    if np.ndim(w) > 1:  # one at a time: the single vector's arithmetic, bit for bit
        w = np.asarray(w, dtype=np.float64)
        return np.stack([so3_exp(v) for v in w.reshape(-1, 3)]).reshape(w.shape[:-1] + (3, 3))
    theta = float(np.linalg.norm(w))
    K = skew(w)
    if theta < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(theta) / theta * K + (1 - np.cos(theta)) / theta**2 * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices to (..., 3) rotation vectors (axis times angle, radians),
    the inverse of `so3_exp` for angles below pi (numpy only)."""
    R = np.asarray(R, dtype=np.float64)
    angle = np.radians(rotation_angle_deg(R))
    axis = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    s = np.sin(angle)
    # angle / (2 sin angle) -> 1/2 as the angle -> 0
    scale = np.where(s > 1e-9, angle / np.where(s > 1e-9, 2 * s, 1.0), 0.5 + angle**2 / 12)
    return axis * scale[..., None]


def motion_power(motion: np.ndarray, times: float) -> np.ndarray:
    """A 4x4 rigid motion taken `times` times (a real number): the rotation's angle and the
    translation scaled by it apart (R^times = exp(times log R), t * times), what a constant
    velocity does over `times` intervals for the small motions between video frames."""
    out = np.eye(4)
    out[:3, :3] = so3_exp(times * so3_log(motion[:3, :3]))
    out[:3, 3] = times * np.asarray(motion[:3, 3], dtype=np.float64)
    return out


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """4x4 exp of xi = (omega, v): rotation vector (rad) and translation part (metres)."""
    omega, v = xi[:3], xi[3:]
    theta = float(np.linalg.norm(omega))
    R = so3_exp(omega)
    K = skew(omega)
    if theta < 1e-10:
        V = np.eye(3) + 0.5 * K
    else:
        V = np.eye(3) + (1 - np.cos(theta)) / theta**2 * K + (theta - np.sin(theta)) / theta**3 * (K @ K)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = V @ v
    return T


def skew(v):
    """(..., 3) vectors to (..., 3, 3) cross-product matrices."""
    xp = _xp(v)
    z = xp.zeros_like(v[..., 0])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return xp.stack([z, -w, y, w, z, -x, -y, x, z], axis=-1).reshape(v.shape[:-1] + (3, 3))


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """Angle in degrees of (..., 3, 3) rotation matrices."""
    c = (np.trace(R, axis1=-2, axis2=-1) - 1) / 2
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def covariance_from_scales(quats, scales):
    """Gaussian covariances R diag(s^2) R^T from (N,4) quaternions (w,x,y,z) and (N,3) scales
    (standard deviations in metres)."""
    R = quat_to_rotmat(quats)
    return (R * (scales[..., None, :] ** 2)) @ R.mT


def scales_from_covariance(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Decompose (N,3,3) symmetric covariances into (quaternions (w,x,y,z), scales).

    Scales are the square roots of the eigenvalues (descending), the rotation's columns the
    eigenvectors, made right-handed. numpy only."""
    from slamkit.geometry.gaussians import sym3_eigh  # closed form, for many small matrices

    eigval, eigvec = sym3_eigh(cov)
    eigval, eigvec = eigval[:, ::-1], eigvec[:, :, ::-1].copy()
    det = np.linalg.det(eigvec)
    eigvec[:, :, 2] *= np.sign(det)[:, None]
    return rotmat_to_quat(eigvec), np.sqrt(np.clip(eigval, 0.0, None))


def pixel_grid(camera, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices (int arrays, flattened) of every `stride`-th pixel."""
    v, u = np.mgrid[0 : camera.height : stride, 0 : camera.width : stride]
    return v.ravel(), u.ravel()


def backproject(depth: np.ndarray, camera, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Back-project every `stride`-th pixel with valid depth to camera-frame points.

    Returns (Nx3 float32 points in metres, camera frame) and (N flat pixel indices into
    the HxW image) so callers can fetch colours or other per-pixel values.
    """
    v, u = pixel_grid(camera, stride)
    z = depth[v, u]
    keep = z > 0
    v, u, z = v[keep], u[keep], z[keep]
    x = (u - camera.cx) / camera.fx * z
    y = (v - camera.cy) / camera.fy * z
    return np.stack([x, y, z], axis=-1).astype(np.float32), v * camera.width + u


def project_points(points, world_to_camera, camera):
    """Pinhole projection of (N,3) world points (metres) through a (4,4) world-to-camera
    transform: (u, v, z), pixel coordinates with pixel centres at integers (column, row) and the
    camera depth z in metres (u, v are meaningless where z <= 0)."""
    pc = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    z = pc[..., 2]
    zs = np.where(z > 0, z, 1.0) if _xp(z) is np else torch.where(z > 0, z, torch.ones_like(z))
    return camera.fx * pc[..., 0] / zs + camera.cx, camera.fy * pc[..., 1] / zs + camera.cy, z
