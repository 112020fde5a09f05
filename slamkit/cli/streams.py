"""The commands' standard output and error, made so that they can never stop a run.

A command's output may go where it cannot be written: a reader that has quit (`| head -1`:
EPIPE), a full disk (ENOSPC), a terminal gone with its SSH session (EIO), a stream closed before
the start (`2>&-`). None of that is the run's business: its results are its files. `guard()`,
called first thing by each command, gives a closed standard descriptor (0, 1 or 2) /dev/null, so
that no file the run opens later takes its number, and replaces `sys.stdout` and `sys.stderr` by
`GuardedStream`s: a write or flush that fails is dropped, said once in the log
(`slamkit.streams`), and the descriptor pointed at /dev/null, so that later writes (Python's,
compiled code's, at exit) go nowhere. The command then exits with its normal status.
"""

from __future__ import annotations

import logging
import os
import sys
from typing import Any

log = logging.getLogger("slamkit.streams")


class GuardedStream:
    """A text stream (`sys.stdout`, `sys.stderr`) whose writes and flushes never raise: the
    first that fails breaks it (`broken` says why), and from then on its output is dropped."""

    def __init__(self, stream, name: str):
        self.stream, self.name = stream, name
        self.broken: str | None = None

    def write(self, text: str) -> int:
        if self.broken is None:
            try:
                return self.stream.write(text)
            except (OSError, ValueError) as exc:  # ValueError: the stream was closed
                self._break(exc)
        return len(text)

    def writelines(self, lines) -> None:
        for line in lines:
            self.write(line)

    def flush(self) -> None:
        if self.broken is None:
            try:
                self.stream.flush()
            except (OSError, ValueError) as exc:
                self._break(exc)

    def _break(self, exc: BaseException) -> None:
        self.broken = f"{type(exc).__name__}: {exc}"
        try:
            fd = self.stream.fileno()
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, fd)  # what is still buffered, and every later write, goes to /dev/null
            os.close(null)
        except (OSError, ValueError, AttributeError):  # no descriptor (an in-memory stream)
            pass
        log.info("standard %s cannot be written (%s); its output is dropped from here on", self.name, self.broken)

    def __getattr__(self, name: str) -> Any:  # encoding, isatty, fileno, reconfigure, ...
        return getattr(self.stream, name)


def _reopen_closed_descriptors() -> None:
    """Give each closed standard descriptor /dev/null (before anything else can take its number)."""
    for fd in (0, 1, 2):
        try:
            os.fstat(fd)
        except OSError:
            null = os.open(os.devnull, os.O_RDONLY if fd == 0 else os.O_WRONLY)
            if null != fd:  # a lower descriptor is closed too: it gets its own in its turn
                os.dup2(null, fd)
                os.close(null)


def guard() -> None:
    """Make the standard streams safe for the rest of the process (see the module docstring);
    calling it again changes nothing."""
    _reopen_closed_descriptors()
    for name in ("stdout", "stderr"):
        stream = getattr(sys, name)
        if isinstance(stream, GuardedStream):
            continue
        if stream is None:  # closed at the start: Python made no stream of it
            stream = open(1 if name == "stdout" else 2, "w", encoding="utf-8", errors="backslashreplace",
                          closefd=False)
        setattr(sys, name, GuardedStream(stream, name))


#: `log.error(..., extra={SAID: True})`: a record the command also prints itself (its
#: `slamkit: error:` line): kept in the log file, not shown on the terminal twice.
SAID = "slamkit_said"


class SaidOnce:
    """The console handler's logging filter (conf/config.yaml): drops the records marked `SAID`."""

    def filter(self, record) -> bool:
        return not getattr(record, SAID, False)
