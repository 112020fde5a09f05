"""A run folder belongs to one run (slamkit.run.ownership) and the standard streams never stop a
command (slamkit.cli.streams), through their public functions; the commands themselves are
exercised by the fault suite (tests/e2e/test_faults.py)."""

from __future__ import annotations

import io
import os
import socket

import pytest

from slamkit.cli.streams import GuardedStream
from slamkit.run.ownership import (
    ExistingOutputs,
    RunFolderError,
    RunFolderInUse,
    RunFolderLock,
    check_localization_folder,
    check_new_run_folder,
    claim,
    in_use_by,
    release,
    unique_suffix,
)


def test_a_held_folder_is_refused_naming_its_holder_and_free_once_released(tmp_path):
    first = RunFolderLock(tmp_path / "run").acquire()
    assert in_use_by(tmp_path / "run").startswith(f"pid {os.getpid()} on host {socket.gethostname()} since ")
    with pytest.raises(RunFolderInUse, match=f"is in use by another run \\(pid {os.getpid()} on host "):
        RunFolderLock(tmp_path / "run").acquire()  # flock: another open file description, even in one process
    first.release()
    assert in_use_by(tmp_path / "run") is None
    RunFolderLock(tmp_path / "run").acquire().release()


def test_a_used_folder_is_refused_or_cleaned_and_anothers_files_never_touched(tmp_path):
    run = tmp_path / "run"
    (run / ".hydra").mkdir(parents=True)
    (run / "slamkit.log").write_text("a run refused before its first frame\n")
    check_new_run_folder(run)  # only what a refused run leaves: as good as new
    (run / "map.ply").write_text("old map")
    (run / "metrics.json").write_text("{}")
    with pytest.raises(RunFolderError, match=r"holds the outputs of an earlier run \(map.ply, metrics.json\)"):
        check_new_run_folder(run)
    assert (run / "map.ply").exists()
    check_new_run_folder(run, ExistingOutputs.clean)
    assert sorted(p.name for p in run.iterdir()) == []
    other = tmp_path / "notes"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    with pytest.raises(RunFolderError, match=r"holds files that are not a slamkit run's \(notes.txt\)"):
        check_new_run_folder(other, ExistingOutputs.clean)
    assert (other / "notes.txt").read_text() == "mine"


def test_claim_lets_a_resume_continue_its_own_folder_and_keeps_localisation_out_of_its_maps(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "metrics.json").write_text("{}")
    (run / "checkpoint.zip").write_text("")
    claim(run, resume=run / "checkpoint.zip")
    with pytest.raises(RunFolderInUse):
        claim(run, resume=run)
    release(run)
    with pytest.raises(RunFolderError, match="localisation writes into a folder of its own"):
        check_localization_folder(run, run / "checkpoint.zip")
    check_localization_folder(tmp_path / "elsewhere", run)


def test_default_folder_suffixes_differ_between_runs_of_one_process():
    names = {unique_suffix() for _ in range(3)}
    assert len(names) == 3 and all(n.split(".")[0] == str(os.getpid()) for n in names)


class _Broken(io.StringIO):
    def __init__(self, error: OSError):
        super().__init__()
        self.error, self.writes = error, 0

    def write(self, text):
        self.writes += 1
        raise self.error


@pytest.mark.parametrize("error", [BrokenPipeError(32, "Broken pipe"), OSError(28, "No space left on device"),
                                   OSError(5, "Input/output error")])
def test_a_stream_that_cannot_be_written_is_dropped_without_raising(error):
    stream = GuardedStream(_Broken(error), "stdout")
    assert stream.write("line\n") == 5 and stream.broken.startswith(type(error).__name__)
    stream.write("more\n")
    stream.flush()
    assert stream.stream.writes == 1  # dropped from the first failure on
