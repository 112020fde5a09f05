"""The paper's scene sweeps (`+experiment=paper_replica|paper_tum`) before they start: the scenes
found under data_root are kept, a given list narrowed to them, an incomplete one named with what
it lacks, and no data_root or no scene found is one line; the sweep and each scene's job are
composed once (the command's composition step, `slamkit.cli.hydra_app.composition`)."""

from __future__ import annotations

from pathlib import Path

import pytest

from slamkit.errors import ConfigError

from support.data import paper_data_root
from support.sweeps import job_values, swept_jobs


@pytest.fixture
def data_root(tmp_path) -> Path:
    return paper_data_root(tmp_path / "data")


def _swept_scenes(*overrides: str, counted: list | None = None) -> list[str]:
    """The scene of each job of the sweep of `overrides`, as the command composes it (not run)."""
    return job_values(swept_jobs(*overrides, counted=counted), "scene")


def test_a_scene_sweep_without_data_root_or_any_scene_is_one_line(tmp_path):
    with pytest.raises(ConfigError, match="data_root") as err:
        _swept_scenes("+experiment=paper_tum")
    assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="none of the scenes") as err:
        _swept_scenes("+experiment=paper_replica", f"data_root={tmp_path}")
    assert "\n" not in str(err.value)


def test_the_scene_sweep_keeps_the_scenes_found_and_a_given_list_composing_each_once(data_root, capsys):
    counted = []
    scenes = _swept_scenes("+experiment=paper_tum", f"data_root={data_root}", "seed=1", counted=counted)
    assert set(scenes) == {"rgbd_dataset_freiburg1_desk"}
    skipped = [line for line in capsys.readouterr().err.splitlines() if " skipped: no folder " in line]
    assert len(skipped) == 2 and all(line.startswith("slamkit: scene ") for line in skipped)
    # the sweep's configuration once, and the job of each scene found once (both presets)
    assert len(counted) == 1 + len(scenes), counted
    scenes = _swept_scenes("+experiment=paper_replica", f"data_root={data_root}", "scene=Replica/room0,Replica/room9")
    assert set(scenes) == {"Replica/room0"}


def test_an_incomplete_scene_is_named_with_what_is_missing_and_the_complete_ones_run(data_root, capsys):
    incomplete = data_root / "rgbd_dataset_freiburg2_xyz"
    incomplete.mkdir()
    (incomplete / "rgb.txt").write_text((data_root / "rgbd_dataset_freiburg1_desk" / "rgb.txt").read_text())
    assert set(_swept_scenes("+experiment=paper_tum", f"data_root={data_root}")) == {"rgbd_dataset_freiburg1_desk"}
    lines = capsys.readouterr().err.splitlines()
    why = {line for line in lines if "freiburg2_xyz" in line}
    assert len(why) == 1 and why.pop().startswith("slamkit: scene rgbd_dataset_freiburg2_xyz skipped: ")
    assert any("depth.txt" in line for line in lines if "freiburg2_xyz" in line)
    # none complete: one line naming data_root
    with pytest.raises(ConfigError, match="none of the scenes is there complete") as err:
        _swept_scenes("+experiment=paper_tum", f"data_root={data_root}", "scene=rgbd_dataset_freiburg2_xyz")
    assert "\n" not in str(err.value)
