"""The plugin registry: entry-point discovery, type checks, failures reported by name (the same
third-party plugins run from the command line: tests/e2e/test_registry_runs.py)."""

from __future__ import annotations

import pytest

from slamkit.errors import ConfigError, PluginError
from slamkit.registry.discovery import discover


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


@pytest.mark.parametrize("old, new, version", [
    ("rasterizer=cpu", "mapper/rasterizer=cpu", "0.3"),
    ("mapper.rasterizer=cpu,torch", "mapper/rasterizer=cpu,torch", "0.3"),
    ("+rasterizer.num_threads=2", "+mapper.rasterizer.num_threads=2", "0.3"),
    ("strategy.prune_every=0", "mapper.strategy.prune_every=0", "0.3"),
    ("strategy.skip_covered=false", "mapper.admission.skip_covered=false", "0.3"),
    ("mapper.strategy.max_gaussians=1000", "mapper.memory_cap.max_gaussians=1000", "0.3"),
    ("map.scale_alignment=z", "growth.scale_alignment=z", "0.3"),
    ("localize.map=out", "map=out", "0.3"),
    ("fps_limit=30", "realtime.fps_limit=30", "0.4"),
    ("drop_frames=true", "realtime.drop_frames=true", "0.4"),
    ("switch_interval=0.005", "realtime.switch_interval=0.005", "0.4"),
    ("mapping_priority=low", "realtime.mapping_priority=low", "0.4"),
    ("mapping_yields=false", "realtime.mapping_yields=false", "0.4"),
    ("keyframe_thread=false", "realtime.keyframe_thread=false", "0.4"),
    ("forced_gap_every=50", "eval.forced_gap_every=50", "0.4"),
    ("forced_gap_length=20", "eval.forced_gap_length=20", "0.4"),
    ("existing_outputs=clean", "output.existing_outputs=clean", "0.4"),
    ("progress=false", "output.progress=false", "0.4"),
    ("eval.plot=false", "output.plot=false", "0.4"),
])
def test_an_old_spelling_gets_one_line_naming_the_new_one(old, new, version):
    from slamkit.registry.compose import compose_run

    with pytest.raises(ConfigError, match=f"is spelled .* since slamkit {version} ") as err:
        compose_run(["mapper=gaussian_splatting", old])
    assert f"(write {new})" in str(err.value) and "\n" not in str(err.value)
