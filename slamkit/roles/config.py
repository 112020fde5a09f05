"""The base of every plugin's config dataclass, the one-line check its `validate` uses, and the
checks every config value gets whatever its part (`check_values`).

Validation has two layers, both run on the composed config before any work starts:
- each config dataclass's `validate` holds the ranges of its own fields (`require(...)`);
- `check_values` walks the whole run config and applies the rules every field shares: a number
  is finite (NaN never; +inf only in a field declared `unlimited`), and a thread count (a field
  declared with `thread_count`) is at most this machine's CPUs.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeVar

from slamkit.errors import ConfigError

if TYPE_CHECKING:
    from slamkit.roles.dataset import SensorProfile

C = TypeVar("C", bound="PluginConfig")


@dataclass
class PluginConfig:
    """Base of every plugin's config dataclass. Subclasses add fields with defaults and may
    override `validate` to reject out-of-range values (raise ConfigError naming the field), and
    `with_sensor` to fill fields left null from the dataset's `SensorProfile`."""

    def validate(self) -> None:
        """Raise ConfigError for an out-of-range value. The default checks nothing."""

    def __post_init__(self) -> None:
        self.validate()

    def with_sensor(self: C, sensor: SensorProfile) -> C:
        """This config with its null fields that depend on the sensor filled from `sensor`
        (e.g. `self.fill_nulls(max_scale=sensor.max_gaussian_scale)`). The default has none."""
        return self

    def fill_nulls(self: C, **values: Any) -> C:
        """A copy in which each named field that is None takes the given value (validated)."""
        missing = {k: v for k, v in values.items() if getattr(self, k) is None}
        return dataclasses.replace(self, **missing) if missing else self


def require(condition: bool, field: str, expected: str, value: Any) -> None:
    """Raise a one-line ConfigError unless `condition` holds."""
    if not condition:
        raise ConfigError(f"{field}: expected {expected}, got {value!r}")


#: Field metadata keys read by `check_values`.
THREADS = "slamkit.thread_count"
UNLIMITED = "slamkit.unlimited"


def thread_count(default: int | None = 0) -> Any:
    """A config field that counts threads (declare it `num_threads: int = thread_count(0)`):
    `check_values` bounds it by this machine's CPUs; its own `validate` says what 0 / null mean."""
    return dataclasses.field(default=default, metadata={THREADS: True})


def unlimited(default: float | None = None) -> Any:
    """A float config field for which +inf is meaningful ("no limit"), e.g. a depth range."""
    return dataclasses.field(default=default, metadata={UNLIMITED: True})


def machine_threads() -> int:
    """The CPUs of this machine (logical), the most threads a thread count may ask for."""
    return os.cpu_count() or 1


def check_values(config: Any, prefix: str = "") -> None:
    """ConfigError (one line naming the key, e.g. `dataset.cx`) for the first value of the
    dataclass `config` (recursively; keys are `prefix` + field name) that breaks a rule every
    config shares: numbers are finite (NaN never; +inf only where the field is `unlimited`),
    thread counts (`thread_count`) are at most `machine_threads()`."""
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
        if f.metadata.get(THREADS) and isinstance(value, int) and not isinstance(value, bool):
            cpus = machine_threads()
            require(value <= cpus, key, f"at most {cpus} threads (this machine's CPUs)", value)
