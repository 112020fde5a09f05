"""A run's lifecycle without running one: StopSignals defers a signal in the phases that change
the map and stops at once elsewhere (issue 20), slamkit-report keeps unfinished and unreadable
runs apart (issue 20), and an output folder that cannot be made is one line before any work
(issue 19). Through whole runs: tests/e2e/test_run_lifecycle.py."""

from __future__ import annotations

import csv
import json
import os
import signal
import time
from pathlib import Path

import pytest
import yaml

from slamkit.cli.report import main as report_main
from slamkit.run.lifecycle import Phase, StopSignals

from support.commands import slamkit_in_process

# -- the signal handling itself (StopSignals), in this process ----------------------------------

def _raise_signal_and_settle(sig: int) -> None:
    os.kill(os.getpid(), sig)
    time.sleep(0.05)  # the handler runs in the main thread at the next bytecode


def test_stop_signals_defer_in_phases_that_change_the_map_and_stop_at_once_elsewhere():
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    stop = StopSignals()
    with stop.installed():
        stop.enter(Phase.stream)
        _raise_signal_and_settle(signal.SIGTERM)  # noted: the frame in hand finishes
        assert stop.signal == "SIGTERM"
        with pytest.raises(KeyboardInterrupt, match="SIGTERM"):
            stop.check()  # the next safe point
        assert not stop.cut_short  # a whole state: the checkpoint is written from it
        with pytest.raises(KeyboardInterrupt, match="SIGINT"):
            _raise_signal_and_settle(signal.SIGINT)  # a second signal: at once
        assert stop.cut_short  # maybe in the middle of a step: no checkpoint from it
        with stop.writing():
            _raise_signal_and_settle(signal.SIGINT)  # never while the outputs are written
    fresh = StopSignals()
    with fresh.installed():
        fresh.enter(Phase.evaluate)
        with pytest.raises(KeyboardInterrupt, match="SIGINT"):
            _raise_signal_and_settle(signal.SIGINT)
        assert not fresh.cut_short  # the evaluation changes nothing kept
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before  # handlers given back



# -- issue 20 point 3: slamkit-report on unfinished and unreadable runs ------------------------

def _fake_run(root: Path, name: str, tracker: str, metrics: dict | str) -> Path:
    run = root / name
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump([f"tracker={tracker}"]))
    (run / "metrics.json").write_text(metrics if isinstance(metrics, str) else json.dumps(metrics))
    return run


def _done(ate: float, **more) -> dict:
    return {"num_frames": 20, "completed": True, "status": "completed", "error": None, "ate_rmse_m": ate, **more}


def test_report_shows_status_keeps_unfinished_runs_apart_and_unreadable_runs_as_rows(tmp_path, capsys):
    _fake_run(tmp_path, "0", "gicp", _done(0.02))
    _fake_run(tmp_path, "1", "kiss_icp", _done(0.04))
    _fake_run(tmp_path, "2", "gicp", {"num_frames": 5, "completed": False, "status": "interrupted", "phase": "stream",
                                      "error": "interrupted (SIGINT) during stream", "ate_rmse_m": 0.001})
    # a metrics.json from before `status`
    _fake_run(tmp_path, "3", "gicp", {"num_frames": 20, "completed": False, "error": "RuntimeError: boom"})
    _fake_run(tmp_path, "4", "gicp", "[1, 2, 3]")
    _fake_run(tmp_path, "5", "gicp", '{"num_frames": 3, "ate_')
    assert report_main([str(tmp_path)]) == 0
    rows = list(csv.DictReader(open(tmp_path / "report.csv")))
    by_status = {r["status"]: r for r in rows}
    assert [r["status"] for r in rows] == ["completed", "completed", "interrupted", "failed", "unreadable",
                                           "unreadable"]
    gicp = next(r for r in rows if r["tracker"] == "gicp" and r["status"] == "completed")
    assert gicp["n"] == "1" and float(gicp["ate_rmse_m"]) == 0.02  # the 5-frame run is not averaged in
    assert by_status["interrupted"]["error"] == "interrupted (SIGINT) during stream"
    assert float(by_status["interrupted"]["num_frames"]) == 5
    assert by_status["failed"]["error"] == "RuntimeError: boom"
    errors = sorted(r["error"] for r in rows if r["status"] == "unreadable")
    assert errors[0] == f"{tmp_path / '4' / 'metrics.json'}: a JSON list, expected an object of metrics"
    assert errors[1].startswith(f"{tmp_path / '5' / 'metrics.json'}: not valid JSON")
    err = capsys.readouterr().err
    assert "6 runs (2 completed, 1 interrupted, 1 failed, 2 unreadable), 6 rows" in err
    assert "| gicp | interrupted | 1 |" in (tmp_path / "report.md").read_text()

    assert report_main([str(tmp_path), "--include-unfinished"]) == 0
    rows = list(csv.DictReader(open(tmp_path / "report.csv")))
    gicp = next(r for r in rows if r["tracker"] == "gicp" and r["n"] == "3")
    assert gicp["status"] == "1 completed, 1 failed, 1 interrupted"
    assert float(gicp["ate_rmse_m"]) == pytest.approx((0.02 + 0.001) / 2)
    assert [r["status"] for r in rows].count("unreadable") == 2


# -- issue 19: the output folder -------------------------------------------------------------

@pytest.mark.parametrize("where", ["a file", "under a file", "a multirun's file"])
def test_an_output_folder_that_is_a_file_is_one_line(where, tmp_path, monkeypatch, capsys):
    afile = tmp_path / "afile"
    afile.write_text("x")
    key, path, args = "hydra.run.dir", afile, ()
    if where == "under a file":
        path = afile / "run"
    elif where == "a multirun's file":
        key, args = "hydra.sweep.dir", ("-m", "seed=0,1")
    code, out, err = slamkit_in_process(monkeypatch, capsys, *args, f"{key}={path}")
    assert code == 2
    assert err.strip().splitlines() == [f"slamkit: error: {key}={path}: {afile} is a file, expected a folder (or a "
                                        f"path that can be created) for the run's outputs"]
    assert afile.read_text() == "x"


def test_an_output_folder_that_cannot_be_created_is_one_line(monkeypatch, capsys):
    """/proc takes no folders, root or not (no read-only mount can be made here)."""
    code, out, err = slamkit_in_process(monkeypatch, capsys, "hydra.run.dir=/proc/slamkit/run")
    assert code == 2
    line, = err.strip().splitlines()
    assert line.startswith("slamkit: error: hydra.run.dir=/proc/slamkit/run: cannot create a folder in /proc (")
    assert line.endswith("); expected a writable place for the run's outputs")
