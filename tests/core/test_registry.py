"""The plugin registry: entry-point discovery, type checks, failures reported by name."""

from __future__ import annotations

import json

import pytest

from slamkit.errors import ConfigError, PluginError
from slamkit.registry.discovery import discover

from conftest import make_plugin_dist, run_slamkit

FAKE_TRACKER = """
    from dataclasses import dataclass
    import numpy as np
    from slamkit.plugin import PluginSpec, hookimpl
    from slamkit.roles import PluginConfig, Tracker, require
    from slamkit.types import TrackingResult

    @dataclass
    class StillConfig(PluginConfig):
        '''offset: metres added to x of every pose.'''
        offset: float = 0.0
        fail_at: int = -1
        def validate(self):
            require(self.offset >= 0, "tracker.offset", ">= 0", self.offset)

    class StillTracker(Tracker):
        '''Reports the first pose for every frame, shifted by cfg.offset along x.'''
        def __init__(self, cfg, context=None):
            self.cfg = cfg
        def initialize(self, first_pose):
            self.pose = first_pose.copy()
            self.pose[0, 3] += self.cfg.offset
        def track(self, frame):
            if frame.index == self.cfg.fail_at:
                raise ValueError("simulated failure")
            return TrackingResult(pose=self.pose)

    @hookimpl
    def slamkit_plugins():
        return [PluginSpec("still", StillTracker, StillConfig)]
"""

NOT_A_TRACKER = """
    from dataclasses import dataclass
    from slamkit.plugin import PluginSpec, hookimpl

    @dataclass
    class Cfg:
        x: int = 1

    @hookimpl
    def slamkit_plugins():
        return [PluginSpec("wrong", dict, Cfg)]
"""

ODD_CONFIG = """
    from dataclasses import dataclass, field
    import numpy as np
    from slamkit.plugin import PluginSpec, hookimpl
    from slamkit.roles import Tracker

    @dataclass
    class OddConfig:
        weights: np.ndarray = field(default_factory=lambda: np.ones(3))

    class OddTracker(Tracker):
        def __init__(self, cfg, context=None):
            self.cfg = cfg
        def track(self, frame):
            raise NotImplementedError

    @hookimpl
    def slamkit_plugins():
        return [PluginSpec("odd", OddTracker, OddConfig)]
"""


@pytest.fixture
def plugin_dir(tmp_path, monkeypatch):
    root = make_plugin_dist(
        tmp_path / "site",
        "slamkit-test-plugins",
        {"still_tracker": FAKE_TRACKER, "broken_plugin": "raise ImportError('needs libfoo')\n",
         "wrong_plugin": NOT_A_TRACKER, "odd_plugin": ODD_CONFIG},
        {"still": "still_tracker", "broken": "broken_plugin", "wrong": "wrong_plugin", "odd": "odd_plugin"},
    )
    monkeypatch.syspath_prepend(str(root))
    return root


def test_builtin_plugins_are_found_through_entry_points():
    registry = discover()
    assert {"tum", "replica", "sevenscenes", "synthetic"} <= set(registry.plugins["dataset"])
    assert "kiss_icp" in registry.plugins["tracker"]
    assert "none" in registry.plugins["mapper"]
    assert "(slamkit)" in registry.plugins["tracker"]["kiss_icp"].source


def test_third_party_plugin_found_and_broken_ones_reported(plugin_dir):
    with pytest.warns(UserWarning) as warned:
        registry = discover()
    assert registry.get("tracker", "still").cls.__name__ == "StillTracker"
    messages = " ".join(str(w.message) for w in warned)
    assert "broken" in messages and "needs libfoo" in messages
    assert "wrong" in messages and "must subclass exactly one role base class" in messages
    assert "wrong" not in registry.plugins["tracker"]
    assert "odd" in messages and "cannot be a Hydra config" in messages  # a config Hydra cannot hold
    assert "odd" not in registry.plugins["tracker"]
    assert "kiss_icp" in registry.plugins["tracker"]  # the others keep working


def test_unknown_plugin_lists_available(plugin_dir):
    with pytest.warns(UserWarning):
        registry = discover()
    with pytest.raises(PluginError) as err:
        registry.get("tracker", "gicpp")
    message = str(err.value)
    assert "unknown tracker 'gicpp'" in message and "kiss_icp" in message and "still" in message
    assert "\n" not in message


@pytest.mark.slow
def test_third_party_plugin_runs_from_the_cli_with_its_config(plugin_dir, tmp_path):
    out = tmp_path / "run"
    env = {"PYTHONPATH": str(plugin_dir)}
    proc = run_slamkit("tracker=still", "tracker.offset=0.5", "dataset.num_frames=8", "progress=false",
                       f"hydra.run.dir={out}", cwd=tmp_path, env_extra=env)
    assert proc.returncode == 0, proc.stderr
    lines = (out / "trajectory.txt").read_text().splitlines()
    assert len(lines) == 8
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["num_frames"] == 8 and metrics["ate_rmse_m"] > 0


@pytest.mark.slow
def test_third_party_config_validation_and_unknown_name_from_the_cli(plugin_dir, tmp_path):
    env = {"PYTHONPATH": str(plugin_dir)}
    bad = run_slamkit("tracker=still", "tracker.offset=-1", f"hydra.run.dir={tmp_path / 'x'}", cwd=tmp_path, env_extra=env)
    assert bad.returncode == 2
    assert bad.stderr.strip().splitlines()[-1] == "slamkit: error: tracker.offset: expected >= 0, got -1.0"
    assert "Traceback" not in bad.stderr
    unknown = run_slamkit("tracker=nope", cwd=tmp_path, env_extra=env)
    assert unknown.returncode == 2
    assert "unknown tracker 'nope'; available:" in unknown.stderr and "still" in unknown.stderr


@pytest.mark.slow
def test_a_plugin_that_raises_stops_the_run_cleanly_naming_it(plugin_dir, tmp_path):
    out = tmp_path / "run"
    proc = run_slamkit("tracker=still", "tracker.fail_at=3", "dataset.num_frames=8", f"hydra.run.dir={out}",
                       cwd=tmp_path, env_extra={"PYTHONPATH": str(plugin_dir)})
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == (
        "slamkit: error: tracker plugin 'still' failed in track(): ValueError: simulated failure")
    assert len((out / "trajectory.txt").read_text().splitlines()) == 3
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["completed"] is False and "simulated failure" in metrics["error"]
    assert "Traceback" in (out / "slamkit.log").read_text()  # the log keeps the details


def test_the_mappers_parts_are_groups_nested_under_it():
    """`mapper/rasterizer=torch` chooses the part and `mapper.rasterizer.FIELD` configures it; a
    run without the 3DGS mapper composes no part."""
    from slamkit.registry.compose import compose_run

    cfg, names = compose_run(["mapper=gaussian_splatting", "mapper/rasterizer=torch",
                              "mapper.rasterizer.max_pairs_per_chunk=4096", "mapper.strategy.prune_every=400"])
    assert names["mapper.rasterizer"] == "torch" and cfg.mapper.rasterizer.max_pairs_per_chunk == 4096
    assert names["mapper.strategy"] == "gsicp" and cfg.mapper.strategy.prune_every == 400
    cfg, names = compose_run([])
    assert names["mapper"] == "none" and not any(key.startswith("mapper.") for key in names)
    with pytest.raises(ConfigError, match=r"^mapper/rasterizer=torch: the mapper 'none' has no rasterizer"):
        compose_run(["mapper/rasterizer=torch"])


@pytest.mark.parametrize("old, new", [
    ("rasterizer=cpu", "mapper/rasterizer=cpu"),
    ("mapper.rasterizer=cpu,torch", "mapper/rasterizer=cpu,torch"),
    ("+rasterizer.num_threads=2", "+mapper.rasterizer.num_threads=2"),
    ("strategy.prune_every=0", "mapper.strategy.prune_every=0"),
    ("strategy.skip_covered=false", "mapper.admission.skip_covered=false"),
    ("mapper.strategy.max_gaussians=1000", "mapper.memory_cap.max_gaussians=1000"),
    ("map.scale_alignment=z", "growth.scale_alignment=z"),
    ("localize.map=out", "map=out"),
])
def test_an_old_spelling_gets_one_line_naming_the_new_one(old, new):
    from slamkit.registry.compose import compose_run

    with pytest.raises(ConfigError, match="since slamkit 0.3") as err:
        compose_run(["mapper=gaussian_splatting", old])
    assert f"(write {new})" in str(err.value) and "\n" not in str(err.value)