"""Stopping a run on SIGINT (Ctrl-C) or SIGTERM without cutting a frame in half.

Within `with StopSignals() as stop:` both signals raise KeyboardInterrupt in the main thread, so
the run stops and writes what it has; inside a `with stop.deferred():` block the signal is held
and raised when the block ends. The pipeline defers around each frame's step and each chunk of
refinement steps: these change the map, the tracker and the run's record together, and the
checkpoint written on interruption (`slamkit.run.checkpoint`) must see them all or none.
"""

from __future__ import annotations

import signal
from contextlib import contextmanager
from typing import Iterator

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopSignals:
    """SIGINT and SIGTERM as KeyboardInterrupt, held inside `deferred()` blocks (see the module
    docstring). Outside the main thread, where handlers cannot be set, it does nothing."""

    def __init__(self) -> None:
        self.depth = 0
        self.pending: int | None = None
        self.previous: dict[int, object] = {}

    def __enter__(self) -> StopSignals:
        for sig in STOP_SIGNALS:
            try:
                self.previous[sig] = signal.signal(sig, self._handler)
            except ValueError:  # not the main thread
                break
        return self

    def __exit__(self, *exc) -> None:
        for sig, handler in self.previous.items():
            signal.signal(sig, handler)
        self.previous = {}

    def _handler(self, signum, frame) -> None:
        if self.depth:
            self.pending = signum
            return
        raise KeyboardInterrupt(signal.Signals(signum).name)

    @contextmanager
    def deferred(self) -> Iterator[None]:
        """Hold a stop signal until the block ends (then raise it as KeyboardInterrupt)."""
        self.depth += 1
        try:
            yield
        finally:
            self.depth -= 1
        if not self.depth and self.pending is not None:
            signum, self.pending = self.pending, None
            raise KeyboardInterrupt(signal.Signals(signum).name)
