"""`mapper/rasterizer=gsplat`: gsplat's fused CUDA rasteriser (gsplat 1.5.3), in slamkit's conventions.

Needs CUDA and gsplat (``pip install 'slamkit[cuda]'``), imported only when the backend is built;
building it renders one Gaussian (`probe`), so that a missing or unbuildable CUDA extension is a
one-line ConfigError here (docs/gpu.md), not an exception deep in a run.

slamkit's conventions on `gsplat.rasterization`: gsplat's pixel centres are at (j + 0.5, i + 0.5),
slamkit's at (j, i), so the principal point is passed shifted by +0.5 px (the two then agree
exactly, Jacobian clamp included); ``render_mode="RGB+D"`` gives slamkit's depth sum_i w_i z_i;
``near_plane=0.01``, ``eps2d=0.3``, ``rasterize_mode="classic"``, ``packed=False``, each
Gaussian bounded by its alpha >= 1/255 ellipse. gsplat computes in float32 on CUDA; outputs come
back in the inputs' dtype and device. gsplat clamps alpha at 0.999, not 0.99, so renders agree
with the torch reference wherever the Gaussians' opacities are <= 0.99.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from slamkit.errors import ConfigError
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import PluginConfig, Rasterizer, RenderOutput, RunContext, require
from slamkit.types import Camera

NEAR_PLANE = 0.01
EPS_2D = 0.3
MAX_TILE_SIZE = 32  # tile_size^2 threads per CUDA block, at most 1024
#: The device gsplat computes on. Tests that stand in a fake gsplat on a machine without CUDA
#: set it to "cpu"; nothing else should.
DEVICE = "cuda"
#: The probe's one-line failure in this process, if it failed: gsplat retries its whole build
#: at every call after a failed one (minutes), so a later construction fails at once instead.
_probe_failure: str | None = None
NEEDS = "mapper/rasterizer=gsplat needs CUDA and the gsplat package (pip install 'slamkit[cuda]')"


@dataclass
class GsplatRasterizerConfig(PluginConfig):
    """gsplat on CUDA."""

    #: pixels; gsplat's tile edge (speed only; tile_size^2 CUDA threads a block: at most 32)
    tile_size: int = 16

    def validate(self) -> None:
        require(1 <= self.tile_size <= MAX_TILE_SIZE, "mapper.rasterizer.tile_size",
                f"an integer in [1, {MAX_TILE_SIZE}] (tile_size^2 CUDA threads per block)", self.tile_size)


class GsplatRasterizer(Rasterizer):
    """`gsplat.rasterization` wrapped to `slamkit.roles.rendering.Rasterizer` (see module docstring)."""

    def __init__(self, cfg: GsplatRasterizerConfig | None = None, context: RunContext = RunContext()):
        self.cfg = cfg or GsplatRasterizerConfig()
        if not torch.cuda.is_available():
            raise ConfigError(NEEDS)
        try:
            from gsplat import rasterization
        except Exception as exc:  # not installed, or a broken install
            reason = f"{type(exc).__name__}: {exc}".splitlines()[0]
            raise ConfigError(f"{NEEDS}; {reason}") from None
        self._rasterization = rasterization
        self.probe()

    def probe(self) -> None:
        """Render one Gaussian on an 8x8 image, so gsplat builds or loads its CUDA extension now;
        ConfigError (one line) when it cannot (or when the GPU cannot even hold the inputs). A
        failure is remembered for the rest of the process (`_probe_failure`)."""
        global _probe_failure
        if _probe_failure is None:
            try:
                device = torch.device(DEVICE)
                one = torch.ones(1, 3, device=device)
                self.render(torch.tensor([[0.0, 0.0, 1.0]], device=device),
                            torch.tensor([[1.0, 0, 0, 0]], device=device), 0.1 * one,
                            torch.full((1,), 0.5, device=device), 0.5 * one, torch.eye(4, device=device),
                            Camera(8, 8, 8.0, 8.0, 3.5, 3.5))
                if device.type == "cuda":
                    torch.cuda.synchronize(device)
                return
            except Exception as exc:
                reason = f"{type(exc).__name__}: {exc}".strip().splitlines()[0]
                _probe_failure = f"rasterizer gsplat: its CUDA extension could not be built or loaded ({reason})"
        raise ConfigError(_probe_failure)

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
        out_device, out_dtype = means.device, means.dtype
        device = out_device if out_device.type == torch.device(DEVICE).type else torch.device(DEVICE)

        def f32(x):
            return torch.as_tensor(x).to(device=device, dtype=torch.float32)

        K = torch.tensor(
            [[camera.fx, 0.0, camera.cx + 0.5], [0.0, camera.fy, camera.cy + 0.5], [0.0, 0.0, 1.0]],
            dtype=torch.float32,
            device=device,
        )
        render_colors, render_alphas, _meta = self._rasterization(
            means=f32(means),
            quats=f32(quats),
            scales=f32(scales),
            opacities=f32(opacities),
            colors=f32(colors),
            viewmats=f32(world_to_camera)[None],
            Ks=K[None],
            width=int(camera.width),
            height=int(camera.height),
            near_plane=NEAR_PLANE,
            eps2d=EPS_2D,
            packed=False,
            tile_size=self.cfg.tile_size,
            backgrounds=None if background is None else f32(background)[None],
            render_mode="RGB+D",
            rasterize_mode="classic",
        )
        rgbd = render_colors[0]
        back = {"device": out_device, "dtype": out_dtype}
        return RenderOutput(
            color=rgbd[..., :3].to(**back),
            depth=rgbd[..., 3].to(**back),
            alpha=render_alphas[0, ..., 0].to(**back),
        )


@hookimpl
def slamkit_plugins():
    return [PluginSpec("gsplat", GsplatRasterizer, GsplatRasterizerConfig)]
