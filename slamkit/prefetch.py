"""Read frames ahead in a background thread so that disk I/O overlaps with tracking."""

from __future__ import annotations

from collections import deque
from concurrent.futures import ThreadPoolExecutor
from typing import Iterator

from slamkit.roles import Dataset
from slamkit.types import Frame


def prefetched(dataset: Dataset, ahead: int = 8) -> Iterator[Frame]:
    """Yield dataset[0], dataset[1], ... while up to `ahead` later frames load in the
    background (image decoding releases the GIL). A loading error is raised at that frame's
    turn, after the frames before it have been yielded."""
    n = len(dataset)
    if ahead <= 0:
        for i in range(n):
            yield dataset[i]
        return
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="slamkit-prefetch") as pool:
        pending = deque(pool.submit(dataset.__getitem__, i) for i in range(min(ahead, n)))
        next_index = len(pending)
        try:
            while pending:
                frame = pending.popleft().result()
                if next_index < n:
                    pending.append(pool.submit(dataset.__getitem__, next_index))
                    next_index += 1
                yield frame
        finally:
            for future in pending:
                future.cancel()
