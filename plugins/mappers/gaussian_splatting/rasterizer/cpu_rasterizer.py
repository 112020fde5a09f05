"""`mapper/rasterizer=cpu`: a tile-based, multi-threaded, compiled CPU rasteriser (forward + backward).

The conventions of `slamkit.roles.rendering.Rasterizer`, reproduced to float precision with
the `torch` reference backend's exact per-row pixel coverage; gradients reach means, quats,
scales, opacities, colors and the background. The work is done by `csrc/cpu_rasterizer.cpp`
(C++17 behind a C ABI, loaded with ctypes), compiled when the backend is first built and cached
by `slamkit.native` (the coverage arithmetic relies on its -ffp-contract=off). Without a
compiler, or if the build fails, building the backend is a one-line ConfigError
(`mapper/rasterizer=auto` then takes `torch`). docs/cpu_rasterizer.md has the design.
"""

from __future__ import annotations

import ctypes
import threading
from dataclasses import dataclass
from pathlib import Path

import torch

from slamkit.errors import ConfigError
from slamkit.native import NativeLibrary, available_threads
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import PluginConfig, Rasterizer, RenderOutput, RunContext, require, thread_count
from slamkit.types import Camera

SOURCE = Path(__file__).resolve().parent / "csrc" / "cpu_rasterizer.cpp"
ABI_VERSION = 5


@dataclass
class CPURasterizerConfig(PluginConfig):
    """The compiled CPU rasteriser."""

    #: threads that render (0: every CPU this process may use, $OMP_NUM_THREADS when set)
    num_threads: int = thread_count(0)
    #: compile for this machine's CPU (-march=native; the cached library is keyed by the CPU model)
    native: bool = True
    #: MiB of a render's alphas kept for its backward pass, which recomputes the rest (0: recompute all)
    stored_alphas_mb: float = 32.0

    def validate(self) -> None:
        require(self.num_threads >= 0, "mapper.rasterizer.num_threads", "an integer >= 0", self.num_threads)
        require(0 <= self.stored_alphas_mb < 2**40, "mapper.rasterizer.stored_alphas_mb", "a finite number >= 0",
                self.stored_alphas_mb)


def _declare(lib) -> None:
    P, I = ctypes.c_void_p, ctypes.c_int
    lib.slk_forward.restype = P
    lib.slk_forward.argtypes = [I, P, P, P, P, P, P, P, I, I, P, I, ctypes.c_int64, P, P, P, P, ctypes.c_char_p, I]
    lib.slk_backward.restype = I
    lib.slk_backward.argtypes = [P, P, P, P, P, P, P, P, P, I, P, P, P, P, P, P, ctypes.c_char_p, I]
    lib.slk_times.restype = None
    lib.slk_times.argtypes = [P, P]
    lib.slk_free.restype = None
    lib.slk_free.argtypes = [P]


_LIBRARIES: dict[bool, NativeLibrary] = {}
_LIBRARIES_LOCK = threading.Lock()


def new_library(native: bool = True) -> NativeLibrary:
    """A handle on the rasteriser's library (native: built with -march=native), not built yet
    (it builds on its first `get()`)."""
    return NativeLibrary(SOURCE, "CPU rasteriser", ABI_VERSION, _declare, native=native)


def get_library(native: bool = True) -> NativeLibrary:
    """The process's handle on the library for `native` (one per flag, built on first use)."""
    with _LIBRARIES_LOCK:
        if native not in _LIBRARIES:
            _LIBRARIES[native] = new_library(native)
        return _LIBRARIES[native]


class _Handle:
    """Owns the C++ forward state (tile lists, final transmittances, ...) while the autograd
    graph that may need it is alive."""

    def __init__(self, lib, ptr):
        self.lib, self.ptr = lib, ptr

    def free(self) -> None:
        if self.ptr:
            self.lib.slk_free(self.ptr)
            self.ptr = None

    def __del__(self):
        self.free()


def _ptr(t: torch.Tensor) -> int:
    return t.data_ptr()


TIME_KEYS = ("project", "sort", "bin", "lists", "composite", "backward_tiles", "backward_reduce")


def _times(lib, ptr) -> dict[str, float]:
    """Seconds per phase: wall clock (`NAME`) and process CPU time (`NAME_cpu`)."""
    out = torch.zeros(16, dtype=torch.int64)
    lib.slk_times(ptr, out.data_ptr())
    us = out.tolist()
    times = {k: us[i] / 1e6 for i, k in enumerate(TIME_KEYS)}
    times.update({f"{k}_cpu": us[8 + i] / 1e6 for i, k in enumerate(TIME_KEYS)})
    return times


class _Render(torch.autograd.Function):
    """Inputs: contiguous float32 CPU tensors (validated by `CPURasterizer.render`)."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, colors, background, viewmat, intr, H, W, nthreads, alpha_bytes,
                lib, owner, keep_state):
        color = torch.empty(H, W, 3, dtype=torch.float32)
        depth = torch.empty(H, W, dtype=torch.float32)
        alpha = torch.empty(H, W, dtype=torch.float32)
        stats = torch.zeros(6, dtype=torch.int64)
        err = ctypes.create_string_buffer(512)
        ptr = lib.slk_forward(
            means.shape[0], _ptr(means), _ptr(quats), _ptr(scales), _ptr(opacities), _ptr(colors), _ptr(viewmat),
            _ptr(intr), W, H, _ptr(background), nthreads, alpha_bytes if keep_state else 0, _ptr(color),
            _ptr(depth), _ptr(alpha), _ptr(stats), err, len(err),
        )
        if not ptr:
            raise RuntimeError(f"cpu rasteriser: {err.value.decode(errors='replace')}")
        handle = _Handle(lib, ptr)
        (owner.last_num_pairs, owner.last_num_visible, owner.last_num_entries, owner.last_num_rows,
         owner.last_num_threads, owner.last_num_rows_stored) = stats.tolist()
        owner.last_times = _times(lib, ptr)
        if keep_state:
            ctx.handle, ctx.lib, ctx.nthreads, ctx.owner = handle, lib, nthreads, owner
            ctx.save_for_backward(means, quats, scales, opacities, background)
        else:
            handle.free()
        return color, depth, alpha

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_color, g_depth, g_alpha):
        means, quats, scales, opacities, background = ctx.saved_tensors
        N = means.shape[0]
        g_color = g_color.to(torch.float32).contiguous()
        g_depth = g_depth.to(torch.float32).contiguous()
        g_alpha = g_alpha.to(torch.float32).contiguous()
        gm, gq, gs = torch.empty(N, 3), torch.empty(N, 4), torch.empty(N, 3)
        go, gc, g_bg = torch.empty(N), torch.empty(N, 3), torch.empty(3)
        err = ctypes.create_string_buffer(512)
        rc = ctx.lib.slk_backward(
            ctx.handle.ptr, _ptr(means), _ptr(quats), _ptr(scales), _ptr(opacities), _ptr(g_color), _ptr(g_depth),
            _ptr(g_alpha), _ptr(background), ctx.nthreads, _ptr(gm), _ptr(gq), _ptr(gs), _ptr(go), _ptr(gc),
            _ptr(g_bg), err, len(err),
        )
        if rc != 0:
            raise RuntimeError(f"cpu rasteriser backward: {err.value.decode(errors='replace')}")
        ctx.owner.last_times = _times(ctx.lib, ctx.handle.ptr)
        return gm, gq, gs, go, gc, g_bg, None, None, None, None, None, None, None, None, None


def _check_shapes(means, quats, scales, opacities, colors, background) -> int:
    n = means.shape[0] if means.dim() == 2 else -1
    expected = {"means": (means, (n, 3)), "quats": (quats, (n, 4)), "scales": (scales, (n, 3)),
                "opacities": (opacities, (n,)), "colors": (colors, (n, 3)), "background": (background, (3,))}
    for name, (t, shape) in expected.items():
        if n < 0 or tuple(t.shape) != shape:
            raise ValueError(f"cpu rasteriser: {name} has shape {tuple(t.shape)}, expected {shape} "
                             f"(means {tuple(means.shape)})")
    return n


class CPURasterizer(Rasterizer):
    """Compiled tile-based CPU rasteriser. Computes in float32 on CPU tensors; other floating
    dtypes are cast, and the outputs are returned in the input dtype. Thread-safe: each render
    owns its state, and the compiled code runs without the GIL. Building it compiles the library
    if needed; ConfigError (one line) where that is impossible. Tensors on another device (a map
    on the GPU) are copied to the CPU and the outputs back (and the gradients with them)."""

    def __init__(self, cfg: CPURasterizerConfig | None = None, context: RunContext = RunContext()):
        self.cfg = cfg or CPURasterizerConfig()
        self.library = get_library(self.cfg.native)
        self.lib = self.library.get()
        if self.lib is None:
            raise ConfigError(f"rasterizer cpu: the compiled library is not available ({self.library.error}); "
                              "mapper/rasterizer=torch needs no compiler")
        self.last_num_pairs = 0  # (pixel, Gaussian) pairs composited by the last render
        self.last_num_visible = 0  # Gaussians that cover at least one pixel row span
        self.last_num_entries = 0  # (tile, Gaussian) entries
        self.last_num_rows = 0  # (entry, tile row) spans composited, in 16-pixel vector steps (8-lane halves count 1/2)
        self.last_num_threads = 0  # threads that composited tiles in the last forward pass
        self.last_num_rows_stored = 0  # of last_num_rows, those whose alphas were kept for the backward
        self.last_times: dict[str, float] = {}  # seconds per phase of the last forward (+ backward)

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
        lib = self.lib
        dtype, device = means.dtype, means.device
        tensors = [means, quats, scales, opacities, colors] + ([background] if background is not None else [])
        if any(t.device.type != "cpu" for t in tensors):  # a map on the GPU: render on the CPU
            means, quats, scales, opacities, colors = (t.cpu() for t in tensors[:5])
            background = background.cpu() if background is not None else None
            tensors = [means, quats, scales, opacities, colors] + ([background] if background is not None else [])
        if background is None:
            background = torch.zeros(3, dtype=torch.float32)
        opacities = opacities.reshape(-1) if opacities.dim() == 2 and opacities.shape[-1] == 1 else opacities
        _check_shapes(means, quats, scales, opacities, colors, background)
        H, W = int(camera.height), int(camera.width)
        if H <= 0 or W <= 0:
            raise ValueError(f"cpu rasteriser: image size {W}x{H}")
        keep_state = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)

        def f32(x):
            return x.to(dtype=torch.float32).contiguous()

        w2c = torch.as_tensor(world_to_camera).detach().to(device="cpu", dtype=torch.float64).contiguous()
        intr = torch.tensor([camera.fx, camera.fy, camera.cx, camera.cy], dtype=torch.float64)
        nthreads = self.cfg.num_threads or available_threads()
        color, depth, alpha = _Render.apply(
            f32(means), f32(quats), f32(scales), f32(opacities), f32(colors), f32(background),
            w2c, intr, H, W, int(nthreads), int(self.cfg.stored_alphas_mb * 2**20), lib, self, keep_state,
        )
        back = {"device": device, "dtype": dtype if dtype.is_floating_point else torch.float32}
        return RenderOutput(color=color.to(**back), depth=depth.to(**back), alpha=alpha.to(**back))


@hookimpl
def slamkit_plugins():
    return [PluginSpec("cpu", CPURasterizer, CPURasterizerConfig)]
