"""A run's phases, and stopping it on a signal at a point where its state is whole.

A run goes through `Phase`s in order (start-up, stream, refine, map, evaluate); each phase's
outputs are written as it ends (`slamkit.run.pipeline`), so a run cut in any phase keeps those of
the phases before. `StopSignals` handles alike every catchable signal whose default is to end the
process (`SIGNALS`); the command exits with 128 + its number (`exit_status`). In the phases that
change the map or the trajectory the first signal is only noted and the run stops at the next safe
point (`check()`: between frames, between mapping steps); a second stops it at once. Start-up and
the evaluation stop at once (`hold()` defers a signal while Hydra composes the config); writing
the outputs is never interrupted. docs/architecture.md, "Phases, and nothing lost on any exit".

Test hook: `SLAMKIT_PAUSE_AT=PHASE` (or `stream@N`: after N frames) makes the run print
``slamkit: paused at PHASE`` on stderr and wait there (up to 60 s) for a signal.
"""

from __future__ import annotations

import enum
import logging
import os
import signal
import sys
import time
from contextlib import contextmanager
from typing import Iterator

log = logging.getLogger(__name__)

#: The environment variable of the test hook (see the module docstring).
PAUSE_ENV = "SLAMKIT_PAUSE_AT"
PAUSE_TIMEOUT_S = 60.0
#: The signals a run handles: every catchable one whose default action ends the process and
#: that a user, a terminal or a batch system sends to stop it (those this platform has).
SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT", "SIGUSR1", "SIGUSR2")
                if hasattr(signal, name))


def exit_status(signal_name: str | None) -> int:
    """The exit status of a command stopped by the signal named `signal_name` ("SIGTERM"):
    128 + its number, as a shell reports a process the signal ended (SIGINT's 130 when unknown)."""
    try:
        return 128 + int(signal.Signals[signal_name or "SIGINT"])
    except KeyError:
        return 128 + int(signal.SIGINT)


class Phase(str, enum.Enum):
    """Where a run is; `done` once it completed. metrics.json's `phase` is one of these."""

    startup = "startup"
    stream = "stream"
    refine = "refine"
    map = "map"
    evaluate = "evaluate"
    done = "done"


#: Phases whose work changes what is kept (the map, the trajectory): a signal waits for a safe point.
DEFERRED = {Phase.stream, Phase.refine, Phase.map}


class StopSignals:
    """The `SIGNALS` for one run (see the module docstring). `signal` is the name of the
    first signal received (None while there was none)."""

    def __init__(self) -> None:
        self.signal: str | None = None
        self.phase = Phase.startup
        self._deferring = False
        self._writing = False
        #: True once a signal stopped the run at once in a phase that changes the map (a second
        #: signal): its state may be half-updated, and no checkpoint is written from it.
        self.cut_short = False

    @contextmanager
    def installed(self) -> Iterator["StopSignals"]:
        """Handle the signals while the block runs (only possible in the main thread; elsewhere
        the signals keep their handlers)."""
        try:
            previous = {s: signal.signal(s, self._handle) for s in SIGNALS}
        except ValueError:  # not the main thread
            yield self
            return
        try:
            yield self
        finally:
            for s, handler in previous.items():
                signal.signal(s, handler)

    def enter(self, phase: Phase) -> None:
        """The run enters `phase`; pauses there if the test hook names it."""
        self.phase = phase
        self._deferring = phase in DEFERRED
        log.info("phase: %s", phase.value)
        pause_point(phase.value, self)

    def hold(self) -> None:
        """Note signals (a second one still stops at once) until `release()`: start-up while Hydra
        composes the config, which a KeyboardInterrupt would leave half-done and report as
        another error."""
        self._deferring = True

    def release(self) -> None:
        """End `hold()`: a signal noted meanwhile raises KeyboardInterrupt now."""
        self._deferring = self.phase in DEFERRED
        self.check()

    def check(self) -> None:
        """A safe point: raise KeyboardInterrupt if a signal has asked the run to stop."""
        if self.signal is not None:
            raise KeyboardInterrupt(self.signal)

    @contextmanager
    def writing(self) -> Iterator[None]:
        """Signals received while the block writes outputs are noted, never raised."""
        before, self._writing = self._writing, True
        try:
            yield
        finally:
            self._writing = before

    def _handle(self, signum: int, frame) -> None:
        name = signal.Signals(signum).name
        first = self.signal is None
        self.signal = self.signal or name
        if self._writing:
            log.warning("%s: the run is writing its outputs; it stops when they are written", name)
            return
        if self._deferring and first:
            log.warning("%s: stopping after the current step (%s); send it again to stop at once",
                        name, self.phase.value)
            return
        self.cut_short = self.cut_short or self._deferring
        raise KeyboardInterrupt(name)


def pause_point(point: str, stop: StopSignals | None = None) -> None:
    """The test hook: if $SLAMKIT_PAUSE_AT names `point`, say so on stderr and wait for a signal
    (up to PAUSE_TIMEOUT_S seconds). A signal that stops at once raises KeyboardInterrupt here;
    one that is deferred ends the wait (the run stops at its next safe point)."""
    if os.environ.get(PAUSE_ENV) != point:
        return
    print(f"slamkit: paused at {point} ({PAUSE_ENV})", file=sys.stderr, flush=True)
    deadline = time.monotonic() + PAUSE_TIMEOUT_S
    while time.monotonic() < deadline and (stop is None or stop.signal is None):
        time.sleep(0.01)
