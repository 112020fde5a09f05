"""`mapper/optimizer=visible_adam`: Adam updating only the rows a training step saw.

A row the step did not render (zero gradient for every parameter) keeps its parameters and
moments: the "sparse" or "visible" Adam of the 3DGS literature (gsplat's SelectiveAdam); its cost
follows the rows seen, not the map. The moments are bias-corrected with the optimiser's step
count (`bias_correction=global`, as torch.optim.Adam) or with each row's own count of the steps it
was seen in (`row`: a late row starts like a fresh Adam). `only_visible=false` updates every row.
With every row seen at every step and the same age, every setting equals torch.optim.Adam; the
learning rates are `mapper/optimizer=adam`'s (docs/results.md, "The mapper's parts: optimisers
and strategies").

On CPU the update is one pass of compiled code over the rows (csrc/visible_adam.cpp, built on
first use by `slamkit.native`); `kernels=torch` is the reference it is tested against, and the
path for GPU tensors or without a compiler.
"""

from __future__ import annotations

import ctypes
import enum
import logging
from dataclasses import dataclass
from pathlib import Path

import torch

from slamkit.errors import ConfigError
from slamkit.native import NativeLibrary
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import MapOptimizer, RunContext
from slamkit.roles.optimizer import rotated_moments
from slamkit_plugins.mappers.gaussian_splatting.optimizer.adam import AdamConfig

log = logging.getLogger(__name__)
SOURCE = Path(__file__).resolve().parent / "csrc" / "visible_adam.cpp"
ABI_VERSION = 3  # what the library's slk_abi_version() must return


def _declare(lib) -> None:
    P = ctypes.c_void_p
    lib.slk_visible_adam.restype = ctypes.c_int64
    lib.slk_visible_adam.argtypes = [ctypes.c_int64, ctypes.c_int, P, P, P, P, P, P, P, P, ctypes.c_int64,
                                     ctypes.c_float, ctypes.c_float, ctypes.c_float, ctypes.c_int, ctypes.c_int]


def new_library() -> NativeLibrary:
    """A handle on the kernel's library, not built yet (it builds on its first `get()`)."""
    return NativeLibrary(SOURCE, "visible-Adam kernel", ABI_VERSION, _declare)


LIBRARY = new_library()


#: Which step count bias-corrects a row's moments. row: its own (a late or rarely seen row steps
#: like a fresh Adam). global: the optimiser's, for every row (as torch.optim.Adam and gsplat's
#: SelectiveAdam). (Functional form: `global` is a keyword, and Hydra matches members by name.)
BiasCorrection = enum.Enum("BiasCorrection", {"row": "row", "global": "global"}, module=__name__)


class Kernels(enum.Enum):
    """auto: compiled on CPU when a compiler builds it, else torch. compiled: compiled or an
    error. torch: the torch reference."""

    auto = "auto"
    compiled = "compiled"
    torch = "torch"

#: The per-row step count's key among the state tensors `edit_rows` sees.
STEPS = "steps"


@dataclass
class VisibleAdamConfig(AdamConfig):
    """Adam on the rows a step saw."""

    #: update only the rows with a non-zero gradient (the rows the step rendered); false: every row
    only_visible: bool = True
    #: row | global: which step count corrects a row's moments (see BiasCorrection)
    bias_correction: BiasCorrection = BiasCorrection["global"]
    #: auto | compiled | torch: the same updates to float precision (see the module docstring)
    kernels: Kernels = Kernels.auto


class VisibleAdam(MapOptimizer):
    """Per-row Adam (see the module docstring). State: first and second moments per parameter,
    one step count per row."""

    def __init__(self, cfg: VisibleAdamConfig, context: RunContext = RunContext()):
        self.cfg = cfg
        self.lrs = cfg.learning_rates()
        self.moments: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}
        self.steps = torch.zeros(0)
        self.lib = None if Kernels(cfg.kernels) is Kernels.torch else LIBRARY.get()
        if self.lib is None and Kernels(cfg.kernels) is Kernels.compiled:
            raise ConfigError(f"mapper.optimizer.kernels=compiled: the kernel is not available ({LIBRARY.error})")
        self.last_updated_rows = 0  # rows the last step updated
        self._row_counts = BiasCorrection(cfg.bias_correction) is BiasCorrection["row"]
        self.calls = 0  # steps taken: no row's step count exceeds it
        self._corrections = torch.zeros(0, 2)  # (t, 1 - beta^t) for t = 0..calls

    def num_rows(self) -> int:
        return int(self.steps.shape[0])

    def edit_rows(self, edit) -> None:
        self.moments = {name: (edit(name, m), edit(name, v)) for name, (m, v) in self.moments.items()}
        self.steps = edit(STEPS, self.steps)

    def move_rows(self, motion) -> None:
        """The moments follow rows a loop closure moved (`rotated_moments`); step counts stay."""
        for name, linear in (("means", motion.rotations), ("quats", motion.quat_maps)):
            if name in self.moments:
                self.moments[name] = rotated_moments(linear, *self.moments[name])

    def reset(self) -> None:
        self.moments, self.steps = {}, torch.zeros(0)

    def state_dict(self) -> dict:
        """Moments per parameter, each row's step count and the optimiser's."""
        return {"moments": {k: [m, v] for k, (m, v) in self.moments.items()}, "steps": self.steps, "calls": self.calls}

    def load_state_dict(self, state: dict) -> None:
        self.moments = {k: (torch.as_tensor(m), torch.as_tensor(v)) for k, (m, v) in state["moments"].items()}
        self.steps = torch.as_tensor(state["steps"])
        self.calls = int(state["calls"])

    @torch.no_grad()
    def step(self, params: dict[str, torch.Tensor], grads: dict[str, torch.Tensor]) -> None:
        n = next(iter(params.values())).shape[0]
        if not self.moments:
            device = next(iter(params.values())).device
            self.moments = {k: (torch.zeros_like(p), torch.zeros_like(p)) for k, p in params.items()}
            self.steps = torch.zeros(n, device=device)
        self.calls += 1
        if self._compiled(params, grads):
            return
        rows = self._rows(grads, n)
        self.last_updated_rows = len(rows)
        self.steps[rows] += 1
        b1, b2 = self.cfg.beta1, self.cfg.beta2
        t = self.steps[rows] if self._row_counts else torch.full_like(self.steps[rows], float(self.calls))
        c1, c2 = 1 - b1**t, 1 - b2**t
        for name, p in params.items():
            g = grads.get(name)
            if g is None:
                continue
            m, v = self.moments[name]
            g = g[rows]
            m_rows = m[rows].mul_(b1).add_(g, alpha=1 - b1)
            v_rows = v[rows].mul_(b2).addcmul_(g, g, value=1 - b2)
            shape = (-1,) + (1,) * (p.dim() - 1)
            update = (m_rows / c1.view(shape)) / (v_rows / c2.view(shape)).sqrt_().add_(self.cfg.eps)
            m[rows], v[rows] = m_rows, v_rows
            p[rows] -= self.lrs[name] * update

    def _compiled(self, params: dict[str, torch.Tensor], grads: dict[str, torch.Tensor]) -> bool:
        """The update in one compiled pass, where it applies (CPU float32); False otherwise."""
        names = [k for k in params if k in grads]
        tensors = [params[k] for k in names] + [grads[k] for k in names] + [self.steps]
        if self.lib is None or any(t.device.type != "cpu" or t.dtype != torch.float32 for t in tensors):
            return False
        grads = {k: grads[k].contiguous() for k in names}

        def pointers(ts):
            return (ctypes.c_void_p * len(ts))(*(t.data_ptr() for t in ts))

        width = (ctypes.c_int * len(names))(*(params[k][0].numel() if len(params[k]) else 1 for k in names))
        lr = (ctypes.c_float * len(names))(*(self.lrs[k] for k in names))
        m = [self.moments[k][0] for k in names]
        v = [self.moments[k][1] for k in names]
        self.last_updated_rows = self.lib.slk_visible_adam(
            len(self.steps), len(names), pointers([params[k] for k in names]), pointers([grads[k] for k in names]),
            pointers(m), pointers(v), width, lr, self.steps.data_ptr(), self._bias_corrections().data_ptr(),
            0 if self._row_counts else self.calls, self.cfg.beta1, self.cfg.beta2, self.cfg.eps,
            int(self.cfg.only_visible), 1)
        return True

    def _bias_corrections(self) -> torch.Tensor:
        """(calls + 1, 2) float32: 1 - beta1^t and 1 - beta2^t for every step count t a row can
        have now, computed once per count (in float64, rounded once, as the torch path's pow)."""
        if len(self._corrections) <= self.calls:
            t = torch.arange(2 * self.calls + 2, dtype=torch.float64)[:, None]
            betas = torch.tensor([self.cfg.beta1, self.cfg.beta2], dtype=torch.float64)
            self._corrections = (1 - betas**t).to(torch.float32).contiguous()
        return self._corrections

    def _rows(self, grads: dict[str, torch.Tensor], n: int) -> torch.Tensor:
        """The rows to update: those with a non-zero gradient (or every row)."""
        if not self.cfg.only_visible:
            return torch.arange(n, device=self.steps.device)
        seen = torch.zeros(n, dtype=torch.bool, device=self.steps.device)
        for g in grads.values():
            seen |= (g != 0).reshape(n, -1).any(dim=1)
        return torch.nonzero(seen).squeeze(1)


@hookimpl
def slamkit_plugins():
    return [PluginSpec("visible_adam", VisibleAdam, VisibleAdamConfig)]
