"""`mapper/rasterizer=torch`: our pure-PyTorch differentiable 3DGS rasteriser (CPU and CUDA).

The reference the other backends are checked against, and the fallback where neither gsplat
(CUDA) nor a compiled CPU backend is available: exactly the conventions of
`slamkit.roles.rendering.Rasterizer`. The projection is ordinary autograd; the compositing
is one `torch.autograd.Function` with 3DGS's analytic backward, reaching means, quats, scales,
opacities, colors and the background.

Vectorised and memory-bounded: each Gaussian's image rows and, per row, its exact interval of
covered columns are computed in closed form; (pixel, Gaussian) pairs are made row by row in depth
order and stably sorted by pixel, so that each pixel's Gaussians are contiguous and front to back.
The transmittance is a segmented cumulative sum of log(1 - alpha) (float64), the backward a
segmented suffix sum, over bands of rows of at most `max_pairs_per_chunk` pairs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from slamkit.geometry.transforms import covariance_from_scales
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import PluginConfig, Rasterizer, RenderOutput, RunContext, require
from slamkit.types import Camera

NEAR_PLANE = 0.01  # metres: Gaussians at camera z <= this are culled
EPS_2D = 0.3  # px^2 added to the 2D covariance's diagonal
ALPHA_MIN = 1.0 / 255.0  # pairs with a smaller alpha are skipped
ALPHA_MAX = 0.99  # alpha is clamped to this
T_MIN = 1e-4  # compositing stops before the transmittance would drop below this
LOG_T_MIN = math.log(T_MIN)
JACOBIAN_MARGIN = 0.15  # of the image size, beyond each edge, where J's x/z, y/z are clamped
_U16 = 1 << 16  # pixels per band on CPU (so the pixel sort key fits 16 bits)
USE_NUMPY_ON_CPU = True  # numpy's radix sort and flatnonzero on CPU tensors (tests switch it off)


@dataclass
class TorchRasterizerConfig(PluginConfig):
    """The pure-torch reference rasteriser."""

    #: (pixel, Gaussian) pairs processed at once: ~60 bytes a pair in flight, 16 kept for the backward
    max_pairs_per_chunk: int = 2_000_000

    def validate(self) -> None:
        n = self.max_pairs_per_chunk
        require(n >= 1024, "mapper.rasterizer.max_pairs_per_chunk", "an integer >= 1024", n)


class TorchRasterizer(Rasterizer):
    """Pure-PyTorch 3DGS rasteriser (the conventions of `Rasterizer`)."""

    def __init__(self, cfg: TorchRasterizerConfig | None = None, context: RunContext = RunContext()):
        self.cfg = cfg or TorchRasterizerConfig()
        self.last_num_pairs = 0  # pairs composited by the last render (after the T cut-off)
        self.last_num_bands = 0  # bands of image rows the last render was processed in

    def render(
        self,
        means: torch.Tensor,
        quats: torch.Tensor,
        scales: torch.Tensor,
        opacities: torch.Tensor,
        colors: torch.Tensor,
        world_to_camera: torch.Tensor,
        camera: Camera,
        background: torch.Tensor | None = None,
    ) -> RenderOutput:
        dtype, device = means.dtype, means.device
        H, W = int(camera.height), int(camera.width)
        if background is None:
            background = torch.zeros(3, dtype=dtype, device=device)
        background = background.to(device=device, dtype=dtype)
        w2c = torch.as_tensor(world_to_camera).to(device=device, dtype=dtype)
        R, t = w2c[:3, :3], w2c[:3, 3]

        with torch.no_grad():  # cull behind the near plane, and Gaussians too faint to show
            z_all = means.detach() @ R[2] + t[2]
            keep = (z_all > NEAR_PLANE) & (opacities.detach() > ALPHA_MIN)
            idx = _flatnonzero(keep)
        inputs = (means, quats, scales, opacities, colors, background, w2c)
        keep_state = torch.is_grad_enabled() and any(x.requires_grad for x in inputs)
        u, v, a, b, c, z = _project(_take(means, idx), _take(quats, idx), _take(scales, idx), R, t, camera)
        color, depth, alpha = _Composite.apply(
            u, v, a, b, c, _take(opacities, idx), _take(colors, idx), z, background, H, W,
            self.cfg.max_pairs_per_chunk, keep_state, self,
        )
        return RenderOutput(color=color, depth=depth, alpha=alpha)


def _project(means, quats, scales, R, t, cam: Camera):
    """2D means (u, v), conics (a, b, c) = inverse 2D covariance entries and camera z."""
    pc = means @ R.T + t
    x, y, z = pc.unbind(-1)
    inv_z = 1.0 / z
    u = cam.fx * x * inv_z + cam.cx
    v = cam.fy * y * inv_z + cam.cy
    # J at the mean, x/z and y/z clamped as 3DGS / gsplat do (their pixel centres are at +0.5)
    m = JACOBIAN_MARGIN
    lim_x = (m * cam.width + cam.cx + 0.5) / cam.fx, ((1 + m) * cam.width - cam.cx - 0.5) / cam.fx
    lim_y = (m * cam.height + cam.cy + 0.5) / cam.fy, ((1 + m) * cam.height - cam.cy - 0.5) / cam.fy
    tx = torch.clamp(x * inv_z, -lim_x[0], lim_x[1])
    ty = torch.clamp(y * inv_z, -lim_y[0], lim_y[1])
    zero = torch.zeros_like(z)
    J = torch.stack(
        [cam.fx * inv_z, zero, -cam.fx * tx * inv_z, zero, cam.fy * inv_z, -cam.fy * ty * inv_z], -1
    ).reshape(-1, 2, 3)
    M = J @ R  # the Jacobian of world -> pixels
    cov2d = M @ covariance_from_scales(quats, scales) @ M.mT
    sxx = cov2d[:, 0, 0] + EPS_2D
    syy = cov2d[:, 1, 1] + EPS_2D
    sxy = 0.5 * (cov2d[:, 0, 1] + cov2d[:, 1, 0])
    inv_det = 1.0 / (sxx * syy - sxy * sxy)
    return u, v, syy * inv_det, -sxy * inv_det, sxx * inv_det, z


# ----------------------------------------------------------------------------------------------
# Helpers that use numpy on CPU (much faster there) and torch elsewhere.


def _take(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """x[index] along the first dimension (index_select: much faster than advanced indexing)."""
    return x.index_select(0, index)


def _numpy_ok(x: torch.Tensor) -> bool:
    return USE_NUMPY_ON_CPU and x.device.type == "cpu"


def _flatnonzero(mask: torch.Tensor) -> torch.Tensor:
    if _numpy_ok(mask):
        return torch.from_numpy(np.flatnonzero(mask.numpy()))
    return torch.nonzero(mask).squeeze(1)


def _repeat(values: torch.Tensor, counts: torch.Tensor, total: int) -> torch.Tensor:
    """values[i] repeated counts[i] times (total = counts.sum()). On CPU numpy's repeat: faster,
    and torch's repeat_interleave there wakes its thread pool even for a few elements, which
    costs milliseconds whenever the cores are busy."""
    if _numpy_ok(values):
        return torch.from_numpy(np.repeat(values.numpy(), counts.numpy()))
    return torch.repeat_interleave(values, counts, output_size=total)


def _stable_argsort(key: torch.Tensor, bound: int) -> torch.Tensor:
    """Stable argsort of non-negative integer keys < bound."""
    if _numpy_ok(key) and bound <= _U16:
        return torch.from_numpy(np.argsort(key.numpy().astype(np.uint16), kind="stable"))
    return torch.sort(key, stable=True).indices


def _pixel_bands(row_pairs: torch.Tensor, W: int, max_pairs: int, radix16: bool) -> list[tuple[int, int]]:
    """Split image rows into bands [r0, r1) of at most max_pairs pairs (a single row may hold
    more) and, on CPU, at most 2^16 pixels."""
    max_rows = max(1, _U16 // W) if radix16 else 1 << 30
    bands, r0, acc = [], 0, 0
    for r, n in enumerate(row_pairs.tolist()):
        if r > r0 and (acc + n > max_pairs or r - r0 >= max_rows):
            bands.append((r0, r))
            r0, acc = r, 0
        acc += n
    bands.append((r0, len(row_pairs)))
    return bands


class _Chunk:
    """What the backward pass keeps of one band: its pairs, sorted by (pixel, depth), as
    counts per pixel and, per pair, its (Gaussian, row) entry, alpha, T and dx (16 bytes)."""

    __slots__ = ("first_pix", "counts", "row", "alpha", "T", "dx")


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, u, v, a, b, c, opac, colors, z, background, H, W, max_pairs, keep_state, owner):
        dtype, device = u.dtype, u.device
        radix16 = _numpy_ok(u)  # then bands hold at most 2^16 pixels, for numpy's 16-bit radix sort
        npix = H * W
        out_color = torch.zeros(npix, 3, dtype=dtype, device=device)
        out_depth = torch.zeros(npix, dtype=dtype, device=device)
        out_alpha = torch.zeros(npix, dtype=dtype, device=device)

        # Gaussian tables in front-to-back order (the index into them is the depth rank)
        order = torch.argsort(z, stable=True)
        u, v, a, b, c, opac, z = (_take(x, order) for x in (u, v, a, b, c, opac, z))
        cols = [_take(colors[:, k], order) for k in range(3)]
        level = 2.0 * torch.log(255.0 * opac)  # the ellipse q <= level is where alpha >= 1/255
        det = a * c - b * b
        ry = torch.sqrt(level.clamp(min=0) * a / det)
        rx = torch.sqrt(level.clamp(min=0) * c / det)
        y0 = torch.ceil(v - ry).clamp(min=0)
        y1 = torch.floor(v + ry).clamp(max=H - 1)
        on_screen = (level > 0) & (y1 >= y0) & (torch.floor(u + rx) >= 0) & (torch.ceil(u - rx) <= W - 1)
        nrows = ((y1 - y0 + 1) * on_screen).long()
        num_rows = int(nrows.sum())

        # One entry per (Gaussian, image row) the ellipse crosses: the covered columns in
        # closed form, and log alpha along the row as a quadratic in dx.
        rg = _repeat(torch.arange(len(nrows), device=device), nrows, num_rows)  # depth rank of each row
        first = torch.cumsum(nrows, 0) - nrows
        row = torch.arange(num_rows, device=device) + _take(y0.long() - first, rg)
        dy = row.to(dtype) - _take(v, rg)
        a_r, b_r = _take(a, rg), _take(b, rg)
        half = torch.sqrt((a_r * _take(level, rg) - _take(det, rg) * dy * dy).clamp(min=0)) / a_r
        mid = _take(u, rg) - b_r / a_r * dy
        xl = torch.ceil(mid - half).clamp(min=0)
        xr = torch.floor(mid + half).clamp(max=W - 1)
        cnt = (xr - xl + 1).clamp(min=0).long()
        rows = _Rows()
        rows.k = _take(torch.log(opac), rg) - 0.5 * _take(c, rg) * dy * dy  # log alpha = k - dx (a dx + b2) / 2
        rows.a, rows.b2 = a_r, 2.0 * b_r * dy
        rows.dx = xl - _take(u, rg)  # dx at the row's first covered pixel
        rows.pix = row * W + xl.long()
        rows.cnt, rows.g = cnt, rg.to(torch.int32)

        row_pairs = torch.zeros(H, dtype=torch.long, device=device).index_add_(0, row, cnt)
        bands = _pixel_bands(row_pairs.cpu(), W, max_pairs, radix16)
        band_of_row = torch.zeros(H, dtype=torch.long, device=device)
        for i, (r0, r1) in enumerate(bands):
            band_of_row[r0:r1] = i
        rsel = _flatnonzero(cnt > 0)
        rband = _take(band_of_row, _take(row, rsel))
        rsel = _take(rsel, _stable_argsort(rband, len(bands)))  # rows grouped by band
        rows_per_band = torch.bincount(rband, minlength=len(bands)).tolist()

        chunks, total, start = [], 0, 0
        for (r0, r1), nr in zip(bands, rows_per_band):
            sel = rsel[start : start + nr]
            start += nr
            if nr == 0:
                continue
            ch, composited = _band_forward(r0, r1, W, sel, rows, z, cols, out_color, out_depth, out_alpha, radix16)
            total += composited
            if keep_state:  # (not when rendering without gradients)
                chunks.append(ch)

        out_color += (1.0 - out_alpha)[:, None] * background
        owner.last_num_pairs = total
        owner.last_num_bands = len(bands)
        ctx.chunks, ctx.order = chunks, order
        ctx.save_for_backward(a, b, c, opac, z, _take(colors, order), background, out_alpha, rg, dy, rows.g)
        return out_color.view(H, W, 3), out_depth.view(H, W), out_alpha.view(H, W)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_color, g_depth, g_alpha):
        a, b, c, opac, z, colors, background, out_alpha, rg, dy, rows_g = ctx.saved_tensors
        dtype, device = a.dtype, a.device
        M, npix = a.numel(), out_alpha.numel()
        g_color = g_color.reshape(npix, 3).to(dtype)
        g_depth = g_depth.reshape(npix).to(dtype)
        g_alpha = g_alpha.reshape(npix).to(dtype)
        g_acc = g_alpha - g_color @ background  # d colour / d alpha_total = -background
        pix_grads = [g_color[:, 0].contiguous(), g_color[:, 1].contiguous(), g_color[:, 2].contiguous(), g_depth, g_acc]
        feats = [colors[:, 0].contiguous(), colors[:, 1].contiguous(), colors[:, 2].contiguous(), z]
        # per (Gaussian, row): sums of s, s dx, s dx^2 (s = dL/dlog alpha); per Gaussian: w gC, w gD
        acc_rows = torch.zeros(3, rg.numel(), dtype=dtype, device=device)
        acc_g = torch.zeros(4, M, dtype=dtype, device=device)
        for ch in ctx.chunks:
            _band_backward(ch, rows_g, pix_grads, feats, acc_rows, acc_g)

        r0, rx, rxx = acc_rows  # dy is constant along a row: fold it in per row
        sums = torch.zeros(6, M, dtype=dtype, device=device)
        for k, m in enumerate((r0, rx, r0 * dy, rxx, rx * dy, r0 * dy * dy)):
            sums[k].index_add_(0, rg, m)
        s0, sx, sy, sxx, sxy, syy = sums
        # log alpha = log o - (a dx^2 + 2 b dx dy + c dy^2) / 2 with dx = px - u, dy = py - v
        grad_u = a * sx + b * sy
        grad_v = b * sx + c * sy
        grad_a, grad_b, grad_c = -0.5 * sxx, -sxy, -0.5 * syy
        grad_o = s0 / opac
        grad_col = acc_g[:3].T
        grad_z = acc_g[3]
        grad_bg = ((1.0 - out_alpha)[:, None] * g_color).sum(0)

        inv = torch.empty_like(ctx.order)
        inv[ctx.order] = torch.arange(M, device=device)
        grads = [_take(x, inv) for x in (grad_u, grad_v, grad_a, grad_b, grad_c, grad_o, grad_col, grad_z)]
        return (*grads, grad_bg, None, None, None, None, None)


class _Rows:
    """Per (Gaussian, image row): g (depth rank), pix (first covered pixel), cnt (covered
    pixels), dx (at the first pixel), and log alpha = k - dx (a dx + b2) / 2 along the row."""

    __slots__ = ("g", "pix", "cnt", "dx", "k", "a", "b2")


def _band_forward(r0, r1, W, sel, rows: _Rows, z, cols, out_color, out_depth, out_alpha, radix16) -> tuple[_Chunk, int]:
    """Composite one band of image rows into the outputs; returns what the backward pass needs
    and the number of pairs composited."""
    device, dtype = z.device, z.dtype
    npix_band = (r1 - r0) * W
    cnt = _take(rows.cnt, sel)
    num = int(cnt.sum())
    # the band's pairs, row after row in depth order: their row and column offset in the row
    row_j = _repeat(sel.to(torch.int32), cnt, num)
    off = torch.arange(num, device=device) - _repeat(torch.cumsum(cnt, 0) - cnt, cnt, num)
    pix = off + _take(rows.pix - r0 * W, row_j)  # pixel index within the band
    dx = off.to(dtype) + _take(rows.dx, row_j)
    log_alpha = _take(rows.k, row_j) - 0.5 * dx * (_take(rows.a, row_j) * dx + _take(rows.b2, row_j))
    del off

    # front to back within each pixel: the pairs are in depth order; sort by pixel, stably
    perm = _stable_argsort(pix, npix_band if radix16 else 1 << 62).to(torch.int32)
    counts = torch.bincount(pix, minlength=npix_band)
    del pix
    row_j = _take(row_j, perm)
    dx = _take(dx, perm)
    alpha = _take(log_alpha, perm).exp_().clamp_(max=ALPHA_MAX)
    del perm, log_alpha
    g = _take(rows.g, row_j)

    # transmittance: segmented (per pixel) cumulative sum of log(1 - alpha), in float64
    log1m = torch.log1p(-alpha)
    csum = torch.cumsum(log1m, 0, dtype=torch.float64)
    base = _take(torch.cat([csum.new_zeros(1), csum]), torch.cumsum(counts, 0) - counts)
    log_t_after = csum.sub_(_repeat(base, counts, num))
    keep = log_t_after >= LOG_T_MIN  # a prefix of each pixel's pairs
    T = log_t_after.to(dtype).sub_(log1m).exp_()
    del csum, log_t_after, log1m
    num_keep = int(keep.sum())
    if num_keep < 0.75 * num:  # many pairs behind the cut-off: drop them
        k = _flatnonzero(keep)
        counts = torch.segment_reduce(keep.to(dtype), "sum", lengths=counts).long()
        g, row_j, dx, alpha, T = (_take(x, k) for x in (g, row_j, dx, alpha, T))
    elif num_keep < num:  # a few: zero their weight (and so their gradient)
        T.mul_(keep)
    w = alpha * T

    sl = slice(r0 * W, r1 * W)
    out_alpha[sl] = torch.segment_reduce(w, "sum", lengths=counts)
    out_depth[sl] = torch.segment_reduce(w * _take(z, g), "sum", lengths=counts)
    for k in range(3):
        out_color[sl, k] = torch.segment_reduce(w * _take(cols[k], g), "sum", lengths=counts)

    ch = _Chunk()
    ch.first_pix, ch.counts, ch.row, ch.alpha, ch.T, ch.dx = r0 * W, counts, row_j, alpha, T, dx
    return ch, num_keep


def _band_backward(ch: _Chunk, rows_g, pix_grads, feats, acc_rows, acc_g) -> None:
    alpha, T, counts = ch.alpha, ch.T, ch.counts
    num, device = alpha.numel(), alpha.device
    first = torch.arange(ch.first_pix, ch.first_pix + counts.numel(), device=device, dtype=torch.int32)
    pix = _repeat(first, counts, num)
    g = _take(rows_g, ch.row)
    gp = [_take(x, pix) for x in pix_grads]  # gC0, gC1, gC2, gD, gA' at each pair's pixel
    gf = [_take(x, g) for x in feats]  # c0, c1, c2, z of each pair's Gaussian
    # v_i = d loss / d w_i (w_i = alpha_i T_i)
    val = gf[0] * gp[0]
    val.addcmul_(gf[1], gp[1]).addcmul_(gf[2], gp[2]).addcmul_(gf[3], gp[3]).add_(gp[4])
    del gf
    w = alpha * T
    # later_i = sum over the same pixel's later pairs of w_j v_j (a segmented suffix sum)
    csum = torch.cumsum(w * val, 0, dtype=torch.float64)
    end_val = _take(torch.cat([csum.new_zeros(1), csum]), torch.cumsum(counts, 0))
    later = _repeat(end_val, counts, num).sub_(csum).to(alpha.dtype)
    del csum
    # dL/dalpha_i = T_i v_i - later_i / (1 - alpha_i); s_i = dL/dlog alpha_i (0 where clamped)
    s = val.mul_(T).sub_(later.div_(1.0 - alpha)).mul_(alpha)
    s.masked_fill_(alpha >= ALPHA_MAX, 0.0)
    sdx = s * ch.dx
    for k, m in enumerate((s, sdx, sdx * ch.dx)):
        acc_rows[k].index_add_(0, ch.row, m)
    for k in range(4):
        acc_g[k].index_add_(0, g, gp[k].mul_(w))


@hookimpl
def slamkit_plugins():
    return [PluginSpec("torch", TorchRasterizer, TorchRasterizerConfig)]
