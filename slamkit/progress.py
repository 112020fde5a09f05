"""A phase's progress (the stream, the refinement, the evaluation; a sweep's jobs): a tqdm bar
where stderr is a terminal, and where it is not (a pipe, a batch job's log, which a bar would
leave empty or fill with carriage returns) one line every few seconds on stderr and in the log:

    slamkit: stream 60/150 frames (40 %), 12 s elapsed, ETA 18 s, ATE 2.10 cm

A phase shorter than the interval prints no line at all: quick runs stay quiet."""

from __future__ import annotations

import logging
import sys
import time
from typing import TextIO

log = logging.getLogger(__name__)

#: Seconds between two progress lines where stderr is not a terminal.
EVERY_S = 5.0
#: Whether phases show progress at all: the run's `progress` setting (`configure`).
ENABLED = True


def configure(enabled: bool) -> None:
    """Progress shown (a bar or lines) or not, for every phase of this process's run."""
    global ENABLED
    ENABLED = bool(enabled)


def duration(seconds: float) -> str:
    """`42 s`, `3 min 05 s`, `1 h 02 min`: elapsed times and ETAs in a progress line."""
    s = int(round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


class Progress:
    """Progress through `total` units of one phase (`initial` done before, e.g. a resumed run's
    frames). enabled=False shows nothing (None: as `configure` said, the run's `progress`); `stream` is where it shows
    (stderr); `every_s` the interval between two lines where that is not a terminal; `units` the
    unit's plural in a line (default `unit` + "s": `MB` for a unit `MB`)."""

    def __init__(self, phase: str, total: int | None, unit: str, enabled: bool | None = None, initial: int = 0,
                 every_s: float = EVERY_S, stream: TextIO | None = None, units: str | None = None):
        from tqdm import tqdm

        self.phase, self.total, self.unit, self.every_s = phase, total, unit, every_s
        self.units = units or f"{unit}s"
        self.stream = stream if stream is not None else sys.stderr
        enabled = ENABLED if enabled is None else enabled
        terminal = enabled and _isatty(self.stream)
        self.lines = enabled and not terminal
        self.bar = tqdm(total=total, initial=initial, unit=unit, desc=phase, dynamic_ncols=True,
                        disable=not terminal, file=self.stream)
        self.done, self.first = initial, initial
        self.start = self.last = time.monotonic()
        self.postfix = ""
        self.printed = 0

    def update(self, n: int = 1) -> None:
        self.done += n
        self.bar.update(n)
        if self.lines and time.monotonic() - self.last >= self.every_s:
            self._line()

    def set_postfix(self, text: str) -> None:
        """A figure shown after the count (the running ATE)."""
        self.postfix = text
        self.bar.set_postfix_str(text, refresh=False)

    def line(self) -> str:
        """The progress line as it stands."""
        elapsed = time.monotonic() - self.start
        count = f"{self.done}/{self.total} {self.units}" if self.total else f"{self.done} {self.units}"
        if self.total:
            count += f" ({100 * self.done / self.total:.0f} %)"
        text = f"{self.phase} {count}, {duration(elapsed)} elapsed"
        progressed = self.done - self.first
        if self.total and progressed > 0 and self.done < self.total:
            text += f", ETA {duration(elapsed * (self.total - self.done) / progressed)}"
        return text + (f", {self.postfix}" if self.postfix else "")

    def _line(self) -> None:
        self.last = time.monotonic()
        text = self.line()
        print(f"slamkit: {text}", file=self.stream, flush=True)
        log.info("%s", text)
        self.printed += 1

    def close(self) -> None:
        """The bar cleared; where lines were printed, a last one with the phase's end."""
        self.bar.close()
        if self.printed:
            self._line()

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _isatty(stream: TextIO) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):  # a closed or a replaced stream
        return False
