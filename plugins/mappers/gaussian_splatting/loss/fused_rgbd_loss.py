"""The 3DGS mapping loss, fused: value and gradients in one compiled pass, no autograd graph.

    loss = w_l1 L1(colour) + w_ssim (1 - SSIM) + w_depth L1(depth) / depth_unit

over the pixels with observed depth (all pixels for the colour terms, and no depth term, when no
pixel has depth): the loss of `mapper/loss=l1_ssim_depth`, defined once, in torch, by
`torch_rgbd_loss` below (SSIM is pytorch_msssim's: 11-tap Gaussian window, sigma 1.5,
data range 1, valid filtering, pixels outside the mask set to 0 in both images).

`fused_rgbd_loss` computes the same value with `csrc/rgbd_loss.cpp` (C++17 behind a C ABI,
compiled on first use and cached by `slamkit.native`), which also returns dloss/dcolour and
dloss/ddepth, SSIM's backward done analytically; the autograd backward only scales them by the
incoming gradient. Without a C++ compiler (or if the build fails) it warns once and computes
`torch_rgbd_loss` instead.
"""

from __future__ import annotations

import ctypes
import math
import warnings
from pathlib import Path

import torch
from pytorch_msssim import ssim as _ms_ssim
from pytorch_msssim.ssim import _fspecial_gauss_1d

from slamkit.metrics.images import SSIM_SIGMA, SSIM_WINDOW
from slamkit.native import NativeLibrary, available_threads

SOURCE = Path(__file__).resolve().parent / "csrc" / "rgbd_loss.cpp"
ABI_VERSION = 1


def _declare(lib) -> None:
    P, I, D = ctypes.c_void_p, ctypes.c_int, ctypes.c_double
    lib.slk_rgbd_loss.restype = I
    lib.slk_rgbd_loss.argtypes = [I, I, P, P, P, P, P, D, D, D, D, I, P, P, P, ctypes.c_char_p, I]


def new_library() -> NativeLibrary:
    """A handle on the loss's library, not built yet (it builds on its first `get()`)."""
    return NativeLibrary(SOURCE, "fused RGB-D loss", ABI_VERSION, _declare)


LIBRARY = new_library()
#: The SSIM window's taps exactly as pytorch_msssim makes them (float32, normalised).
WINDOW = _fspecial_gauss_1d(SSIM_WINDOW, SSIM_SIGMA).reshape(-1).contiguous()
_warned = False


def available() -> bool:
    """Whether the compiled kernel is (or could now be) loaded; builds it on first call."""
    return LIBRARY.get() is not None


def check_inputs(color: torch.Tensor, depth: torch.Tensor, image: torch.Tensor, observed_depth: torch.Tensor) -> None:
    """ValueError (one line) unless color, image are (H,W,3) and depth, observed_depth (H,W),
    H and W at least the SSIM window (11 px)."""
    if color.dim() != 3 or color.shape[-1] != 3:
        raise ValueError(f"rgbd loss: color has shape {tuple(color.shape)}, expected (H, W, 3)")
    H, W = color.shape[:2]
    for name, t, shape in (("depth", depth, (H, W)), ("image", image, (H, W, 3)),
                           ("observed_depth", observed_depth, (H, W))):
        if tuple(t.shape) != shape:
            raise ValueError(f"rgbd loss: {name} has shape {tuple(t.shape)}, expected {shape} "
                             f"(color {tuple(color.shape)})")
    if H < SSIM_WINDOW or W < SSIM_WINDOW:
        raise ValueError(f"rgbd loss: the image is {W}x{H} px (WxH); SSIM's {SSIM_WINDOW}x{SSIM_WINDOW} window "
                         f"needs at least {SSIM_WINDOW} px on each side")


def torch_rgbd_loss(color: torch.Tensor, depth: torch.Tensor, image: torch.Tensor, observed_depth: torch.Tensor,
                    w_l1: float = 0.8, w_ssim: float = 0.2, w_depth: float = 0.1, depth_unit: float = 10.0,
                    num_threads: int = 1, all_pixels: bool = False) -> torch.Tensor:
    """The reference (and fallback): the loss in torch, differentiable by autograd, in the
    inputs' floating dtype. color, image (H,W,3) in [0, 1]; depth, observed_depth (H,W) in
    metres (observed 0 = no measurement); depth_unit in metres. num_threads is unused (torch's
    own threads apply); it is here so that both functions take the same arguments.
    all_pixels: every pixel counts in every term, a pixel without observed depth with the
    observed colour set to 0 there and its depth compared with 0 (GS-ICP SLAM's reference code;
    the compiled kernel computes only the default)."""
    check_inputs(color, depth, image, observed_depth)
    mask = observed_depth > 0
    has_depth = bool(mask.any())
    if all_pixels:
        image = image * mask[..., None].to(image.dtype)
    if all_pixels or not has_depth:
        mask = torch.ones_like(mask)
    m = mask.to(color.dtype)
    n = m.sum()
    loss = w_l1 * (((color - image).abs() * m[..., None]).sum() / (3 * n))
    if w_ssim:
        x = (color * m[..., None]).permute(2, 0, 1)[None]
        y = (image * m[..., None]).permute(2, 0, 1)[None]
        s = _ms_ssim(x, y, data_range=1.0, size_average=True, win_size=SSIM_WINDOW, win_sigma=SSIM_SIGMA)
        loss = loss + w_ssim * (1 - s)
    if w_depth and has_depth:
        loss = loss + w_depth * (((depth - observed_depth).abs() * m).sum() / n / depth_unit)
    return loss


def kernel_rgbd_loss(color, depth, image, observed_depth, weights, num_threads: int, grads: bool):
    """One call of the compiled kernel on contiguous float32 CPU tensors. weights: (w_l1, w_ssim,
    w_depth, depth_unit). Returns (terms, grad_color, grad_depth): terms = [loss, L1, SSIM (NaN
    when w_ssim is 0), depth term, valid pixels] as floats; the gradients are None unless
    `grads`."""
    lib = LIBRARY.get()
    if lib is None:
        raise RuntimeError(f"the fused RGB-D loss is not available ({LIBRARY.error})")
    H, W = color.shape[:2]
    g_color = torch.empty(H, W, 3, dtype=torch.float32) if grads else None
    g_depth = torch.empty(H, W, dtype=torch.float32) if grads else None
    out = (ctypes.c_double * 5)()
    err = ctypes.create_string_buffer(512)
    rc = lib.slk_rgbd_loss(
        H, W, color.data_ptr(), depth.data_ptr(), image.data_ptr(), observed_depth.data_ptr(), WINDOW.data_ptr(),
        *(float(w) for w in weights), int(num_threads),
        g_color.data_ptr() if grads else None, g_depth.data_ptr() if grads else None, out, err, len(err),
    )
    if rc != 0:
        raise RuntimeError(f"fused RGB-D loss: {err.value.decode(errors='replace')}")
    return list(out), g_color, g_depth


class _FusedRGBDLoss(torch.autograd.Function):
    """forward: the kernel (loss and gradients in one call); backward: the kept gradients
    times the incoming one. No gradient reaches image or observed_depth.

    The gradients are handed to autograd, not copied: scaled in place (skipped for the usual
    incoming gradient 1), so that the leaves' .grad can take them over; a second backward
    through the same graph is refused as for any freed graph. (A copy or a multiply would run
    on torch's intra-op threads, which on a busy machine cost more than the kernel.)"""

    @staticmethod
    def forward(ctx, color, depth, image, observed_depth, weights, num_threads):
        grads = ctx.needs_input_grad[0] or ctx.needs_input_grad[1]
        terms, ctx.g_color, ctx.g_depth = kernel_rgbd_loss(color, depth, image, observed_depth, weights,
                                                           num_threads, grads)
        return torch.tensor(terms[0], dtype=torch.float32)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_output):
        g_color, g_depth = ctx.g_color, ctx.g_depth
        if g_color is None:
            raise RuntimeError("fused rgbd loss: backward through the same graph a second time (its gradients "
                               "were handed over the first time)")
        ctx.g_color = ctx.g_depth = None
        if float(grad_output) != 1.0:
            g_color.mul_(grad_output)
            g_depth.mul_(grad_output)
        return (g_color if ctx.needs_input_grad[0] else None, g_depth if ctx.needs_input_grad[1] else None,
                None, None, None, None)


def fused_rgbd_loss(color: torch.Tensor, depth: torch.Tensor, image: torch.Tensor, observed_depth: torch.Tensor,
                    w_l1: float = 0.8, w_ssim: float = 0.2, w_depth: float = 0.1, depth_unit: float = 10.0,
                    num_threads: int = 1) -> torch.Tensor:
    """`torch_rgbd_loss` computed by the compiled kernel: a 0-d float32 tensor whose backward
    gives dloss/dcolor and dloss/ddepth. Inputs: float32 CPU tensors, color, image (H,W,3) in
    [0, 1], depth, observed_depth (H,W) in metres, H and W >= 11. num_threads: row bands
    computed in parallel (0 = every CPU this process may use, `slamkit.native.available_threads`);
    the result does not depend on it.
    Falls back to `torch_rgbd_loss`, with one warning, where the kernel cannot be built."""
    global _warned
    check_inputs(color, depth, image, observed_depth)
    for name, t in (("color", color), ("depth", depth), ("image", image), ("observed_depth", observed_depth)):
        if t.device.type != "cpu" or t.dtype != torch.float32:
            raise ValueError(f"fused rgbd loss: {name} is {t.dtype} on {t.device}, expected float32 on cpu")
    if num_threads < 0:
        raise ValueError(f"fused rgbd loss: num_threads must be >= 0, got {num_threads}")
    weights = (w_l1, w_ssim, w_depth, depth_unit)
    if not all(math.isfinite(float(w)) for w in weights) or depth_unit <= 0:
        raise ValueError(f"fused rgbd loss: weights (w_l1, w_ssim, w_depth, depth_unit) = {weights} must be "
                         f"finite, depth_unit > 0")
    if not available():
        if not _warned:
            _warned = True
            warnings.warn(f"slamkit: the fused RGB-D loss is not available ({LIBRARY.error}); using the torch loss",
                          RuntimeWarning, stacklevel=2)
        return torch_rgbd_loss(color, depth, image, observed_depth, w_l1, w_ssim, w_depth, depth_unit)
    return _FusedRGBDLoss.apply(color.contiguous(), depth.contiguous(), image.contiguous(),
                                observed_depth.contiguous(), weights, num_threads or available_threads())
