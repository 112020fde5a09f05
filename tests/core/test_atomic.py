"""Atomic writes: a failure inside the block leaves the previous file and no temporary file."""

import pytest

from slamkit.formats.atomic import atomic_open, write_atomic


def test_write_replaces_the_file_whole(tmp_path):
    path = tmp_path / "sub" / "out.txt"
    write_atomic(path, "first\n")
    write_atomic(path, b"second\n")
    assert path.read_bytes() == b"second\n"
    assert [p.name for p in path.parent.iterdir()] == ["out.txt"]


def test_a_failure_midway_keeps_the_previous_version(tmp_path):
    path = tmp_path / "out.txt"
    write_atomic(path, "complete\n")
    with pytest.raises(RuntimeError):
        with atomic_open(path) as f:
            f.write("partial")
            raise RuntimeError("killed")
    assert path.read_text() == "complete\n"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]
