"""The rules every config value shares (`slamkit.roles.check_values`: a key's range, a NaN, a
thread count the machine cannot give) and the camera's plausibility bounds, checked directly.
Through the composition the command uses, key by key: tests/e2e/test_faults.py."""

from __future__ import annotations

import pytest


def test_camera_plausibility_bounds_follow_the_image_size():
    from slamkit.types import Camera

    tum = Camera(640, 480, 517.3, 516.5, 318.6, 255.3)
    assert tum.implausible() == []
    assert [n for n, _ in Camera(640, 480, 517.3, 516.5, 1e30, float("nan")).implausible()] == ["cx", "cy"]
    # fx for a 1 and a 170 degree field of view across 640 pixels: 36667 and 28.0; fy across 480: 21.0 at 170
    assert Camera(640, 480, 36000.0, 516.5, 320, 240).implausible() == []
    assert [n for n, _ in Camera(640, 480, 37000.0, 20.0, 320, 240).implausible()] == ["fx", "fy"]
    assert [n for n, _ in Camera(0, 480, 517.3, 516.5, 318.6, 255.3).implausible()] == ["width"]


def test_check_values_names_the_key_of_a_nan_and_of_too_many_threads():
    from dataclasses import dataclass, field

    from slamkit.config import machine_threads
    from slamkit.errors import ConfigError
    from slamkit.roles import PluginConfig, check_values, thread_count, unlimited

    @dataclass
    class Inner(PluginConfig):
        weights: list = field(default_factory=lambda: [1.0, 2.0])
        num_threads: int = thread_count(0)
        far: float = unlimited(float("inf"))

    @dataclass
    class Outer(PluginConfig):
        inner: Inner = field(default_factory=Inner)
        step: float = 0.5

    check_values(Outer())
    for bad, key in [(Outer(step=float("nan")), "step"), (Outer(Inner(weights=[1.0, float("inf")])), "inner.weights"),
                     (Outer(Inner(num_threads=machine_threads() + 1)), "inner.num_threads"),
                     (Outer(Inner(far=float("-inf"))), "inner.far")]:
        with pytest.raises(ConfigError, match=f"^{key}: expected"):
            check_values(bad)
