"""Progress where stderr is not a terminal (a pipe, a batch job's log): one line every few
seconds with the count, elapsed time and ETA, a last one at the phase's end, and nothing for a
phase shorter than the interval or with progress off."""

from __future__ import annotations

import io

from slamkit.progress import Progress, duration


def test_lines_carry_count_elapsed_eta_and_postfix():
    out = io.StringIO()
    with Progress("stream", 150, "frame", enabled=True, every_s=0, stream=out) as bar:
        bar.update(60)
        bar.set_postfix("ATE 2.10 cm")
        bar.update(90)
    lines = out.getvalue().splitlines()
    assert lines[0].startswith("slamkit: stream 60/150 frames (40 %), ") and "elapsed, ETA " in lines[0]
    assert lines[1].startswith("slamkit: stream 150/150 frames (100 %), ") and lines[1].endswith(", ATE 2.10 cm")
    assert "ETA" not in lines[-1]  # done
    assert lines[-1] == lines[-2]  # the phase's end line repeats the count it ended at


def test_a_quick_phase_or_progress_off_prints_nothing():
    for enabled, every_s in ((True, 3600), (False, 0)):
        out = io.StringIO()
        with Progress("refinement", 400, "step", enabled=enabled, every_s=every_s, stream=out) as bar:
            bar.update(400)
        assert out.getvalue() == ""


def test_a_resumed_phase_counts_from_where_it_was():
    out = io.StringIO()
    with Progress("stream", 100, "frame", enabled=True, initial=40, every_s=0, stream=out) as bar:
        bar.update(10)
    assert out.getvalue().splitlines()[0].startswith("slamkit: stream 50/100 frames (50 %)")


def test_durations_read_as_a_person_writes_them():
    assert [duration(s) for s in (4.4, 65, 3725)] == ["4 s", "1 min 05 s", "1 h 02 min"]


def test_a_sweeps_size_is_the_product_of_its_swept_values_or_its_trials():
    from omegaconf import OmegaConf

    from slamkit.cli.hydra_hooks import sweep_size

    basic = "hydra._internal.core_plugins.basic_sweeper.BasicSweeper"
    config = OmegaConf.create({"hydra": {"sweeper": {"_target_": basic, "params": {"seed": "0,1,2"}},
                                         "overrides": {"task": ["tracker=gicp,kiss_icp", "dataset.num_frames=12"]}}})
    assert sweep_size(config) == 6
    search = OmegaConf.create({"hydra": {"sweeper": {"_target_": "hydra_plugins.optuna.OptunaSweeper", "n_trials": 20},
                                         "overrides": {"task": []}}})
    assert sweep_size(search) == 20
    assert sweep_size(OmegaConf.create({"hydra": {"sweeper": {"_target_": "other.Sweeper"}}})) is None
