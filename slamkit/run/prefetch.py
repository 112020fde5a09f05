"""Read frames ahead in a background thread so that disk I/O overlaps with tracking."""

from __future__ import annotations

import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Iterator

from slamkit.errors import DataError
from slamkit.roles import Dataset, SourceEnded
from slamkit.types import Frame


@dataclass
class UnreadableFrame:
    """A frame that failed to load (with dataset.on_error=skip)."""

    index: int
    timestamp: float
    error: DataError


@dataclass
class LoadCost:
    """CPU seconds the frame loading thread spent in `dataset[i]` (decoding, checks)."""

    cpu_s: float = 0.0


def prefetched(dataset: Dataset, ahead: int = 8, skip_errors: bool = False,
               first: int = 0, cost: LoadCost | None = None) -> Iterator[Frame | UnreadableFrame]:
    """Yield dataset[first], dataset[first + 1], ... while up to `ahead` later frames load in the
    background (image decoding releases the GIL). A DataError is raised at that frame's turn,
    after the frames before it, or yielded as an UnreadableFrame when `skip_errors`; a live source's
    SourceEnded ends the frames there. The loading
    thread's CPU time is added to `cost`."""
    cost = cost if cost is not None else LoadCost()

    def load(i: int) -> Frame:
        start = time.thread_time()
        try:
            return dataset[i]
        finally:
            cost.cpu_s += time.thread_time() - start  # one loading thread: no race

    n = len(dataset)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="slamkit-prefetch") as pool:
        pending = deque(pool.submit(load, i) for i in range(first, min(first + max(ahead, 1), n)))
        next_index = first + len(pending)
        index = first
        try:
            while pending:
                future = pending.popleft()
                if next_index < n:
                    pending.append(pool.submit(load, next_index))
                    next_index += 1
                try:
                    frame = future.result()
                except SourceEnded:  # a live source has no more frames: the stream ends here
                    return
                except DataError as exc:
                    if not skip_errors:
                        raise
                    frame = UnreadableFrame(index, dataset.timestamp(index), exc)
                yield frame
                index += 1
        finally:
            for future in pending:
                future.cancel()
