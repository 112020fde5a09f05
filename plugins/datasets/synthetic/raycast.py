"""Ray casting of the synthetic scene, vectorised numpy in float32.

One ray per pixel of a pinhole camera (OpenCV axes); the nearest hit per pixel among the scene's
primitives, each tested only inside the pixel rectangle its bounding box projects to; then each
primitive's pixels coloured by its material and shaded by a fixed directional light (Lambertian
with an ambient term, so colours do not depend on the viewpoint). Depth is exact: the
camera-frame z of the hit in metres, no holes.
"""

from __future__ import annotations

import numpy as np

from slamkit.types import Camera
from slamkit_plugins.datasets.synthetic.primitives import Hit, Primitive
from slamkit_plugins.datasets.synthetic.scene import scene

#: Light: a fixed direction (towards the light), Lambertian with ambient term.
_LIGHT = np.array([0.35, -0.25, 0.90]) / np.linalg.norm([0.35, -0.25, 0.90])
_AMBIENT, _DIFFUSE = 0.60, 0.45
#: Shading overrides for self-lit surfaces (names).
_UNLIT = {"ceiling lamp", "window"}

_BOX_EDGES = [(i, j) for i in range(8) for j in range(i + 1, 8) if bin(i ^ j).count("1") == 1]


def _screen_rect(corners_cam: np.ndarray, camera: Camera, near: float = 0.02) -> tuple[int, int, int, int] | None:
    """Pixel rectangle (v0, v1, u0, u1) bounding the projection of a box given by its 8
    camera-frame corners (clipped at z = near), or None when it is out of view."""
    z = corners_cam[:, 2]
    front = z > near
    if not front.any():
        return None
    pts = [corners_cam[front]]
    if not front.all():  # add where the box's edges cross the near plane
        for i, j in _BOX_EDGES:
            if front[i] != front[j]:
                a, b = corners_cam[i], corners_cam[j]
                pts.append((a + (near - a[2]) / (b[2] - a[2]) * (b - a))[None])
    pts = np.concatenate(pts)
    uu = camera.fx * pts[:, 0] / pts[:, 2] + camera.cx
    vv = camera.fy * pts[:, 1] / pts[:, 2] + camera.cy
    v0 = max(0, int(np.floor(vv.min())) - 1)
    v1 = min(camera.height, int(np.ceil(vv.max())) + 2)
    u0 = max(0, int(np.floor(uu.min())) - 1)
    u1 = min(camera.width, int(np.ceil(uu.max())) + 2)
    return (v0, v1, u0, u1) if v0 < v1 and u0 < u1 else None


def render(camera: Camera, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Render the scene from `pose` (camera-to-world, OpenCV axes): (HxWx3 uint8 rgb,
    HxW float32 depth in metres, the camera-frame z of the nearest hit)."""
    prims = scene()
    R = pose[:3, :3].astype(np.float64)
    o = pose[:3, 3].astype(np.float64)
    dw = _ray_directions(camera, R)
    tbest, ids = _nearest_hits(prims, camera, R, o, dw)
    return _shade(prims, camera, o, dw, tbest, ids), tbest


def _ray_directions(camera: Camera, R: np.ndarray) -> list[np.ndarray]:
    """The x, y, z world components (3 float32 HxW arrays) of each pixel's ray direction for a
    camera with rotation R (camera-to-world)."""
    H, W = camera.height, camera.width
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    xc = (u - np.float32(camera.cx)) / np.float32(camera.fx)
    yc = (v - np.float32(camera.cy)) / np.float32(camera.fy)
    # World directions with camera-frame z = 1: the hit distance t is the depth itself.
    Rf = R.astype(np.float32)
    return [Rf[k, 0] * xc + Rf[k, 1] * yc + Rf[k, 2] for k in range(3)]


def _nearest_hits(prims: list[Primitive], camera: Camera, R: np.ndarray, o: np.ndarray,
                  dw: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Depth of the nearest hit (HxW float32 metres, inf where none) and the index of the
    primitive hit there (HxW int16), for rays from the camera centre o along dw; R: the camera's
    rotation (camera-to-world)."""
    H, W = camera.height, camera.width
    with np.errstate(divide="ignore"):
        invw = [np.float32(1.0) / dk for dk in dw]

    tbest = np.full((H, W), np.inf, np.float32)
    ids = np.zeros((H, W), np.int16)
    for k, prim in enumerate(prims):
        corners = prim.corners()
        if corners is None:
            rect = (0, H, 0, W)
        else:
            rect = _screen_rect((corners - o) @ R, camera)
            if rect is None:
                continue
        v0, v1, u0, u1 = rect
        ol = (o - prim.center) @ prim.R
        if prim.axis_aligned:
            d = [dk[v0:v1, u0:u1] for dk in dw]
            inv = [ik[v0:v1, u0:u1] for ik in invw]
        else:
            Rp = prim.R.astype(np.float32)
            sub = [dk[v0:v1, u0:u1] for dk in dw]
            d = [Rp[0, j] * sub[0] + Rp[1, j] * sub[1] + Rp[2, j] * sub[2] for j in range(3)]
            inv = None
        t = prim.intersect(ol, d, inv)
        tb = tbest[v0:v1, u0:u1]
        better = t < tb
        if better.any():
            tb[better] = t[better]
            ids[v0:v1, u0:u1][better] = k
    return tbest, ids


def _shade(prims: list[Primitive], camera: Camera, o: np.ndarray, dw: list[np.ndarray], tbest: np.ndarray,
           ids: np.ndarray) -> np.ndarray:
    """HxWx3 uint8 colours of the nearest hits: each primitive's pixels coloured by its material
    and shaded by the light (self-lit surfaces are not)."""
    H, W = camera.height, camera.width
    # Shade, one primitive at a time. Points are kept as (3, n) planes and handed to materials
    # as their (n, 3) transposes, so that p[:, k] is contiguous.
    tflat = tbest.ravel()
    idflat = ids.ravel()
    dflat = [dk.ravel() for dk in dw]
    order = np.argsort(idflat, kind="stable")
    counts = np.bincount(idflat, minlength=len(prims))
    starts = np.concatenate([[0], np.cumsum(counts)])
    rgb = np.empty((3, H * W), np.float32)
    inv_f = np.float32(1.5 / max(camera.fx, camera.fy))  # pixel footprint (m) per metre of depth
    light = _LIGHT.astype(np.float32)
    for k in np.nonzero(counts)[0]:
        prim = prims[k]
        pix = order[starts[k] : starts[k + 1]]
        t = np.take(tflat, pix)
        P = np.empty((3, len(pix)), np.float32)
        for j in range(3):
            P[j] = np.float32(o[j]) + t * np.take(dflat[j], pix)
        Pl = P - prim.center.astype(np.float32)[:, None]
        if not prim.axis_aligned:
            Pl = prim.R.T.astype(np.float32) @ Pl
        nl, face = prim.surface(Pl.T)
        col = prim.material(Hit(P.T, Pl.T, nl, face, t * inv_f))
        if prim.name in _UNLIT:
            shade = np.float32(1.0)
        else:
            nw_dot_l = nl @ (prim.R.T.astype(np.float32) @ light)
            shade = np.float32(_AMBIENT) + np.float32(_DIFFUSE) * np.maximum(nw_dot_l, 0.0)
        col = (col * (shade[:, None] if np.ndim(shade) else shade)).T
        for j in range(3):
            np.put(rgb[j], pix, col[j])
    rgb = rgb.T
    rgb8 = np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8).reshape(H, W, 3)
    return rgb8
