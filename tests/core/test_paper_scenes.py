"""The paper's scene sweeps (`+experiment=paper_replica|paper_tum`) before they start: the scenes
found under data_root are kept, a given list narrowed to them, and no data_root or no scene found
is one line."""

from __future__ import annotations

import io
from pathlib import Path

import pytest

from slamkit.cli.scenes import present_scenes
from slamkit.errors import ConfigError

from support.data import paper_data_root


@pytest.fixture
def data_root(tmp_path) -> Path:
    return paper_data_root(tmp_path / "data")


def test_a_scene_sweep_without_data_root_or_any_scene_is_one_line(tmp_path):
    with pytest.raises(ConfigError, match="data_root") as err:
        present_scenes(["+experiment=paper_tum"])
    assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="none of the scenes") as err:
        present_scenes(["+experiment=paper_replica", f"data_root={tmp_path}"])
    assert "\n" not in str(err.value)


def test_the_scene_sweep_keeps_the_scenes_found_and_a_given_list(data_root):
    told = io.StringIO()
    argv = present_scenes(["-m", "+experiment=paper_tum", f"data_root={data_root}", "seed=1"], out=told)
    assert argv == ["-m", "+experiment=paper_tum", f"data_root={data_root}", "seed=1",
                    "scene=rgbd_dataset_freiburg1_desk"]
    assert len(told.getvalue().splitlines()) == 2
    argv = present_scenes(["+experiment=paper_replica", f"data_root={data_root}", "scene=Replica/room0,Replica/room9"],
                          out=io.StringIO())
    assert argv[-1] == "scene=Replica/room0" and sum(a.startswith("scene=") for a in argv) == 1
    assert present_scenes(["tracker=gicp", "seed=2"]) == ["tracker=gicp", "seed=2"]  # no scene sweep: as given


def test_an_incomplete_scene_is_named_with_what_is_missing_and_the_complete_ones_run(data_root):
    incomplete = data_root / "rgbd_dataset_freiburg2_xyz"
    incomplete.mkdir()
    (incomplete / "rgb.txt").write_text((data_root / "rgbd_dataset_freiburg1_desk" / "rgb.txt").read_text())
    told = io.StringIO()
    argv = present_scenes(["+experiment=paper_tum", f"data_root={data_root}"], out=told)
    assert argv[-1] == "scene=rgbd_dataset_freiburg1_desk"
    lines = told.getvalue().splitlines()
    (why,) = [line for line in lines if "freiburg2_xyz" in line]
    assert why.startswith("slamkit: scene rgbd_dataset_freiburg2_xyz skipped: ") and "depth.txt" in why
    # none complete: one line naming data_root
    with pytest.raises(ConfigError, match="none of the scenes is there complete") as err:
        present_scenes(["+experiment=paper_tum", f"data_root={data_root}", "scene=rgbd_dataset_freiburg2_xyz"],
                       out=io.StringIO())
    assert "\n" not in str(err.value)
