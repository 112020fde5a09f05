"""The clock of a live source (a camera, `Dataset.live`): frames arrive when the source gives
them, not at times the run sets (`slamkit.run.runner.InputClock`, for recordings)."""

from __future__ import annotations

import time

#: Seconds between two frames assumed before two have arrived.
DEFAULT_PERIOD_S = 1 / 30.0


class LiveClock:
    """`InputClock`'s questions answered by the source's own arrivals (`Dataset.arrival(i)`:
    time.perf_counter() seconds, None while frame i has not arrived)."""

    def __init__(self, dataset):
        self.dataset = dataset

    def wait(self, i: int) -> bool:
        """Frame i is there (the loop has it); True if frame i+1 has arrived too (we are late)."""
        return self.dataset.arrival(i + 1) is not None

    def arrival(self, i: int) -> float | None:
        """When frame i arrived (time.perf_counter() seconds)."""
        return self.dataset.arrival(i)

    def late_after(self, i: int) -> float | None:
        """When tracking frame i, started now, is late: once frame i+1 is due (frame i's arrival
        plus the last interval between two frames), or one interval from now when it is
        already there; None before frame i has arrived."""
        arrived = self.dataset.arrival(i)
        if arrived is None:
            return None
        before = self.dataset.arrival(i - 1) if i > 0 else None
        period = arrived - before if before is not None and arrived > before else DEFAULT_PERIOD_S
        if self.dataset.arrival(i + 1) is not None:
            return time.perf_counter() + period
        return max(arrived + period, time.perf_counter())
