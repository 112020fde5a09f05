"""The project's rule for errors, as tests check it: one line, naming what was wrong."""

from __future__ import annotations


def one_line(excinfo, *needles: str) -> str:
    """The message of a caught exception (pytest's ExceptionInfo), asserted to be one line that
    contains every one of `needles`."""
    msg = str(excinfo.value)
    assert "\n" not in msg, msg
    for needle in needles:
        assert needle in msg, msg
    return msg
