"""Map checkpoints (issue 17): the file format and its one-line errors, and the frame log a
resumed run continues. Runs continued from their checkpoint: tests/e2e/test_checkpoint_resume.py."""

from __future__ import annotations

import csv
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from slamkit.errors import SlamkitError
from slamkit.formats.checkpoint import SCHEMA_VERSION, CheckpointError, read_checkpoint, read_meta, write_checkpoint
from slamkit.run.frame_log import FrameLog


def _state(n: int = 5) -> dict:
    return {"map": {"means": torch.arange(3.0 * n).reshape(n, 3), "flags": np.arange(n) % 2 == 0},
            "list": [1, 2.5, None, "x", np.ones((2, 2), np.float32)], "nested": {"a": {"b": True}}, "big": 2**100}


def test_round_trip_keeps_arrays_tensors_and_values(tmp_path):
    path = tmp_path / "c.zip"
    write_checkpoint(path, {"last_frame_index": 4}, _state())
    back = read_checkpoint(path)
    assert back["schema_version"] == SCHEMA_VERSION and back["last_frame_index"] == 4
    state = back["state"]
    assert isinstance(state["map"]["means"], torch.Tensor)
    assert torch.equal(state["map"]["means"], _state()["map"]["means"])
    assert state["map"]["flags"].dtype == bool and state["map"]["flags"].tolist() == [True, False, True, False, True]
    assert state["list"][:4] == [1, 2.5, None, "x"] and np.array_equal(state["list"][4], np.ones((2, 2)))
    assert state["nested"] == {"a": {"b": True}} and state["big"] == 2**100
    assert read_meta(path)["state"]["map"]["means"] == {"__tensor__": "map.means"}  # arrays not read


def _rewrite_meta(path: Path, edit) -> None:
    with zipfile.ZipFile(path) as z:
        members = {n: z.read(n) for n in z.namelist()}
    meta = json.loads(members["meta.json"])
    edit(meta)
    members["meta.json"] = json.dumps(meta).encode()
    with zipfile.ZipFile(path, "w") as z:
        for name, data in members.items():
            z.writestr(name, data)


def test_damaged_checkpoints_fail_with_one_line_naming_the_file(tmp_path):
    path = tmp_path / "c.zip"
    write_checkpoint(path, {}, _state(1000))
    data = path.read_bytes()

    path.write_bytes(data[: len(data) // 2])  # truncated
    with pytest.raises(CheckpointError, match=r"c\.zip is damaged or truncated"):
        read_checkpoint(path)

    flipped = bytearray(data)
    offset = data.index(b"\x93NUMPY") + 200  # inside the first array's data
    flipped[offset] ^= 0xFF
    path.write_bytes(bytes(flipped))
    with pytest.raises(CheckpointError, match=r"array 'map\.means' is damaged"):
        read_checkpoint(path)

    path.write_bytes(data)
    _rewrite_meta(path, lambda m: m.update(schema_version=SCHEMA_VERSION + 1))
    with pytest.raises(CheckpointError, match=f"schema version {SCHEMA_VERSION + 1}; this slamkit reads version"):
        read_meta(path)

    path.write_bytes(data)
    _rewrite_meta(path, lambda m: m["state"]["map"].update(means={"__tensor__": "nowhere"}))
    with pytest.raises(CheckpointError, match="array 'nowhere' is missing"):
        read_checkpoint(path)

    with pytest.raises(CheckpointError, match="not found"):
        read_checkpoint(tmp_path / "absent.zip")
    for error in (CheckpointError("x"),):
        assert isinstance(error, SlamkitError)  # the CLI prints it as one line, exit status 2


HEADER = ",".join(FrameLog.COLUMNS)


@pytest.mark.parametrize("before, kept", [
    ("", []),  # killed before its header reached the disk
    (HEADER[:12], []),  # ... while writing it
    (f"{HEADER}\r\n0,0.0,none,1,,,0,,,,\"unreadable: line\nbreak\"\r\n1,0.1,none\r\n2,0.2,none\r\n3,0.3,no",
     ["0", "1"]),  # rows past the checkpoint (2, 3), the last one cut short; a note with a line break
])
def test_a_resumed_frame_log_has_one_row_per_frame(tmp_path, before, kept):
    path = tmp_path / "frames.csv"
    with open(path, "w", newline="") as f:
        f.write(before)
    with FrameLog(path, resume_from=2) as log:
        log.unreadable(2, 0.2, OSError("gone"))
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    assert rows[0] == FrameLog.COLUMNS
    assert [row[0] for row in rows[1:]] == kept + ["2"]


def test_a_checkpoint_before_0_4_gives_its_method_settings_under_their_new_keys():
    """saved_settings reads a setting 0.4 moved into a group (`fps_limit`) at its old key too."""
    from slamkit.run.checkpoint import saved_settings

    before = {"config": {"preset": "paper", "fps_limit": 30.0, "tracker": {"regularization": "plane"}}}
    keys = ["preset", "realtime.fps_limit", "realtime.drop_frames", "tracker.regularization"]
    assert saved_settings(before, keys) == {"preset": "paper", "realtime.fps_limit": 30.0,
                                            "tracker.regularization": "plane"}
    now = {"config": {"realtime": {"fps_limit": None, "drop_frames": True}}}
    assert saved_settings(now, keys) == {"realtime.fps_limit": None, "realtime.drop_frames": True}
