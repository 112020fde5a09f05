"""`mapper/rasterizer=auto` (the default): the first backend of `prefer` that can be built here.

gsplat needs CUDA, the gsplat package and its compiled extension; cpu needs a C++ compiler
(the library is built on first use); torch always works. A backend that cannot be built is
skipped with a log line saying why: a warning on a machine with CUDA (gsplat not installed or
its extension not built: the GPU does not render), else an info line. Each is built with its
default config: to configure a backend, select it by name (`mapper/rasterizer=cpu
mapper.rasterizer.num_threads=2`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import torch

from slamkit.errors import ConfigError, PluginError
from slamkit.plugin import PluginSpec, hookimpl
from slamkit.roles import PluginConfig, Rasterizer, RunContext, require

log = logging.getLogger(__name__)


@dataclass
class AutoRasterizerConfig(PluginConfig):
    """The first backend that builds here."""

    #: the backends tried, in order (each with its default config)
    prefer: list[str] = field(default_factory=lambda: ["gsplat", "cpu", "torch"])

    def validate(self) -> None:
        require(len(self.prefer) > 0 and "auto" not in self.prefer, "mapper.rasterizer.prefer",
                "a non-empty list of backend names other than auto", self.prefer)


class AutoRasterizer(Rasterizer):
    """Renders with `backend`, the first of `prefer` that could be built in the run's registry
    (`context.build`; its name: `name`)."""

    def __init__(self, cfg: AutoRasterizerConfig, context: RunContext = RunContext()):
        if context.build is None:
            raise ConfigError("rasterizer auto: built outside a run (its context has no registry to build "
                              "backends from); build it with Registry.create('rasterizer', 'auto')")
        self.cfg = cfg
        reasons = []
        level = logging.WARNING if torch.cuda.is_available() else logging.INFO
        for name in cfg.prefer:
            try:
                self.backend = context.build("rasterizer", name)
                self.name = name
                break
            except (ConfigError, PluginError) as exc:
                reasons.append(f"{name}: {exc}")
                log.log(level, "rasterizer auto: not using %s (%s)", name, exc)
        else:
            raise ConfigError("rasterizer auto: no backend could be built (" + "; ".join(reasons) + ")")
        if reasons:
            log.log(level, "rasterizer auto: using %s", self.name)

    def render(self, *args, **kwargs):
        return self.backend.render(*args, **kwargs)


@hookimpl
def slamkit_plugins():
    return [PluginSpec("auto", AutoRasterizer, AutoRasterizerConfig)]
