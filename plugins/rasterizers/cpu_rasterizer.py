"""`rasterizer=cpu`: a tile-based, multi-threaded, compiled CPU rasteriser (forward + backward).

The same conventions as `slamkit.rendering.Rasterizer` and the `torch` reference backend (see
`slamkit_plugins.rasterizers.torch_rasterizer`), reproduced to float precision: projection with
the EWA covariance + 0.3 px^2, near-plane culling at z <= 0.01 m, the torch backend's exact
per-row pixel coverage (alpha >= 1/255 ellipse), alpha = min(0.99, o exp(-q/2)), front-to-back
compositing that stops before the transmittance drops below 1e-4, colour over the background,
depth = sum w z, alpha = sum w. Gradients reach means, quats, scales, opacities, colors and the
background.

The work is done by `csrc/cpu_rasterizer.cpp`: plain C++17 behind a C ABI, loaded with ctypes.
It is compiled on first use with the system C++ compiler (`$CXX`, else `c++`; a few seconds)
and cached by a hash of the source, the flags, the compiler and the CPU under
`$SLAMKIT_CACHE/extensions/` (else `~/.cache/slamkit/extensions/`). Without a compiler, or if
the build fails, a one-line warning is given and the `torch` backend renders instead. See
docs/cpu_rasterizer.md for the design and the measurements.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch

from slamkit.plugin import PluginSpec, hookimpl
from slamkit.rendering import Rasterizer, RenderOutput
from slamkit.roles import PluginConfig, require
from slamkit.types import Camera

SOURCE = Path(__file__).resolve().parent / "csrc" / "cpu_rasterizer.cpp"
ABI_VERSION = 2
# -ffp-contract=off and no -ffast-math: the pixel-coverage arithmetic must round exactly as the
# torch backend's float32 operations do. -fno-math-errno only lets sqrt be inlined.
BASE_FLAGS = ["-O3", "-std=c++17", "-shared", "-fPIC", "-pthread", "-ffp-contract=off", "-fno-math-errno", "-DNDEBUG"]


@dataclass
class CPURasterizerConfig(PluginConfig):
    """num_threads: worker threads (0 = torch.get_num_threads()). native: compile for this
    machine's CPU (-march=native; the cached library is keyed by the CPU model, so a copied cache
    is rebuilt rather than crashing on another CPU)."""

    num_threads: int = 0
    native: bool = True

    def validate(self) -> None:
        require(self.num_threads >= 0, "rasterizer.num_threads", "an integer >= 0", self.num_threads)


def cache_root() -> Path:
    root = os.environ.get("SLAMKIT_CACHE")
    return Path(root) / "extensions" if root else Path.home() / ".cache" / "slamkit" / "extensions"


def _cpu_id() -> str:
    """The CPU model and feature flags (what -march=native depends on)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
        keep = [ln for ln in text.splitlines() if ln.split(":")[0].strip() in ("model name", "flags", "Features", "CPU part")]
        return "\n".join(sorted(set(keep)))
    except OSError:
        return platform.processor() or platform.machine()


class _Library:
    """The compiled library, built on first use; `error` says why it is not available."""

    def __init__(self, native: bool):
        self.native = native
        self.lib = None
        self.error: str | None = None
        self._lock = threading.Lock()
        self._tried = False

    def get(self):
        with self._lock:
            if not self._tried:
                self._tried = True
                try:
                    self.lib = self._load()
                except Exception as exc:  # report in one line, the caller falls back
                    text = str(exc) if isinstance(exc, RuntimeError) else f"{type(exc).__name__}: {exc}"
                    self.error = (text.strip().splitlines() or [type(exc).__name__])[0]
        return self.lib

    def _load(self):
        compiler = os.environ.get("CXX", "c++")
        exe = shutil.which(compiler)
        if exe is None:
            raise RuntimeError(f"no C++ compiler found ({compiler!r} is not on PATH; set CXX)")
        version = subprocess.run([exe, "--version"], capture_output=True, text=True, timeout=60).stdout
        error = None
        # -march=native first (where asked); a compiler that rejects it gets the portable build
        for native in ([True, False] if self.native else [False]):
            flags = BASE_FLAGS + (["-march=native"] if native else [])
            digest = hashlib.sha256()
            for part in (SOURCE.read_bytes(), " ".join(flags).encode(), version.encode(), platform.machine().encode()):
                digest.update(part)
            if native:  # a cache copied to another CPU is rebuilt, not run with instructions it lacks
                digest.update(_cpu_id().encode())
            path = cache_root() / f"slamkit_cpu_rasterizer_{digest.hexdigest()[:16]}.so"
            if not path.exists():
                try:
                    _compile(exe, flags, path)
                except RuntimeError as exc:
                    error = error or exc
                    continue
            return _open(path)
        raise error


def _compile(exe: str, flags: list[str], path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    print("slamkit: compiling the CPU rasteriser (first use, ~5 s)...", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    fd, tmp = tempfile.mkstemp(suffix=".so.tmp", dir=path.parent)
    os.close(fd)
    try:
        proc = subprocess.run([exe, *flags, str(SOURCE), "-o", tmp], capture_output=True, text=True, timeout=600)
        if proc.returncode != 0:
            first = next((ln for ln in proc.stderr.splitlines() if "error" in ln), proc.stderr.strip()[:200])
            raise RuntimeError(f"compiling {SOURCE.name} failed: {first.strip()}")
        os.replace(tmp, path)  # atomic: concurrent builders each install a complete file
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    print(f"slamkit: CPU rasteriser compiled in {time.perf_counter() - t0:.1f} s ({path})", file=sys.stderr, flush=True)


def _open(path: Path):
    lib = ctypes.CDLL(str(path))
    if lib.slk_abi_version() != ABI_VERSION:
        raise RuntimeError(f"{path} has ABI {lib.slk_abi_version()}, expected {ABI_VERSION}")
    P, I = ctypes.c_void_p, ctypes.c_int
    lib.slk_forward.restype = P
    lib.slk_forward.argtypes = [I, P, P, P, P, P, P, P, I, I, P, I, P, P, P, P, ctypes.c_char_p, I]
    lib.slk_backward.restype = I
    lib.slk_backward.argtypes = [P, P, P, P, P, P, P, P, P, I, P, P, P, P, P, P, ctypes.c_char_p, I]
    lib.slk_times.restype = None
    lib.slk_times.argtypes = [P, P]
    lib.slk_free.restype = None
    lib.slk_free.argtypes = [P]
    return lib


_LIBRARIES: dict[bool, _Library] = {}
_LIBRARIES_LOCK = threading.Lock()


def get_library(native: bool = True) -> _Library:
    with _LIBRARIES_LOCK:
        if native not in _LIBRARIES:
            _LIBRARIES[native] = _Library(native)
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
    def forward(ctx, means, quats, scales, opacities, colors, background, viewmat, intr, H, W, nthreads, lib, owner,
                keep_state):
        color = torch.empty(H, W, 3, dtype=torch.float32)
        depth = torch.empty(H, W, dtype=torch.float32)
        alpha = torch.empty(H, W, dtype=torch.float32)
        stats = torch.zeros(4, dtype=torch.int64)
        err = ctypes.create_string_buffer(512)
        ptr = lib.slk_forward(
            means.shape[0], _ptr(means), _ptr(quats), _ptr(scales), _ptr(opacities), _ptr(colors), _ptr(viewmat),
            _ptr(intr), W, H, _ptr(background), nthreads, _ptr(color), _ptr(depth), _ptr(alpha), _ptr(stats),
            err, len(err),
        )
        if not ptr:
            raise RuntimeError(f"cpu rasteriser: {err.value.decode(errors='replace')}")
        handle = _Handle(lib, ptr)
        owner.last_num_pairs, owner.last_num_visible, owner.last_num_entries, owner.last_num_rows = stats.tolist()
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
        return gm, gq, gs, go, gc, g_bg, None, None, None, None, None, None, None, None


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
    """Compiled tile-based CPU rasteriser; falls back to the `torch` backend (with a warning)
    where it cannot be compiled. Computes in float32 on CPU tensors; other floating dtypes are
    cast, and the outputs are returned in the input dtype. Thread-safe: each render owns its
    state, and the compiled code runs without the GIL."""

    def __init__(self, cfg: CPURasterizerConfig | None = None):
        self.cfg = cfg or CPURasterizerConfig()
        self.last_num_pairs = 0  # (pixel, Gaussian) pairs composited by the last render
        self.last_num_visible = 0  # Gaussians that cover at least one pixel row span
        self.last_num_entries = 0  # (tile, Gaussian) entries
        self.last_num_rows = 0  # (entry, tile row) spans composited: 16-pixel vector steps
        self.last_times: dict[str, float] = {}  # seconds per phase of the last forward (+ backward)
        self._fallback = None

    @property
    def available(self) -> bool:
        """Whether the compiled library is (or could now be) loaded; builds it if needed."""
        return get_library(self.cfg.native).get() is not None

    def _torch_fallback(self, reason: str):
        if self._fallback is None:
            from slamkit_plugins.rasterizers.torch_rasterizer import TorchRasterizer

            warnings.warn(f"slamkit: the cpu rasteriser is not available ({reason}); using the torch backend",
                          RuntimeWarning, stacklevel=3)
            self._fallback = TorchRasterizer()
        return self._fallback

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
        library = get_library(self.cfg.native)
        lib = library.get()
        if lib is None:
            fallback = self._torch_fallback(library.error or "unknown reason")
            out = fallback.render(means, quats, scales, opacities, colors, world_to_camera, camera, background)
            self.last_num_pairs = fallback.last_num_pairs
            return out
        dtype = means.dtype
        tensors = [means, quats, scales, opacities, colors] + ([background] if background is not None else [])
        for t in tensors:
            if t.device.type != "cpu":
                raise ValueError(f"the cpu rasteriser takes CPU tensors, got one on {t.device}")
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
        nthreads = self.cfg.num_threads or torch.get_num_threads()
        color, depth, alpha = _Render.apply(
            f32(means), f32(quats), f32(scales), f32(opacities), f32(colors), f32(background),
            w2c, intr, H, W, int(nthreads), lib, self, keep_state,
        )
        if dtype != torch.float32 and dtype.is_floating_point:
            color, depth, alpha = color.to(dtype), depth.to(dtype), alpha.to(dtype)
        return RenderOutput(color=color, depth=depth, alpha=alpha)


@hookimpl
def slamkit_rasterizers():
    return [PluginSpec("cpu", CPURasterizer, CPURasterizerConfig)]
