"""The base of every plugin's config dataclass, and the one-line check its `validate` uses."""

from __future__ import annotations

import dataclasses
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
