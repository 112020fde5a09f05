"""A keyframe's work that tracking does not wait for, run in a thread of its own beside it
(real time, `realtime.keyframe_thread`): `SLAM.add_keyframe` gives it to `KeyframeHandovers`, one keyframe
at a time, and the next keyframe, a loop correction and a checkpoint wait for it (`settle`)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable


class KeyframeHandover(threading.Thread):
    """`hand_over()` in a thread of its own, at the tracking thread's priority (the mapping
    thread's lower one would let training hold up the next keyframe). `error`: what it raised,
    for `KeyframeHandovers.settle` to raise on the tracking thread; `seconds`: how long it took."""

    def __init__(self, hand_over: Callable[[], None]):
        super().__init__(name="slamkit-keyframe", daemon=True)
        self.hand_over = hand_over
        self.error: BaseException | None = None
        self.seconds = 0.0

    def run(self) -> None:
        start = time.perf_counter()
        try:
            self.hand_over()
        except BaseException as exc:  # raised again by KeyframeHandovers.settle on the tracking thread
            self.error = exc
        finally:
            self.seconds = time.perf_counter() - start


class KeyframeHandovers:
    """The keyframes handed over beside tracking, one at a time. `time_s` sums the handovers'
    seconds, `wait_s` the tracking thread's waits for one (`settle`)."""

    def __init__(self) -> None:
        self.current: KeyframeHandover | None = None  # the last keyframe going to the mapper beside tracking
        self.time_s = 0.0
        self.wait_s = 0.0

    def start(self, hand_over: Callable[[], None]) -> None:
        """Run `hand_over()` beside the calling thread (after `settle`: one at a time)."""
        self.current = KeyframeHandover(hand_over)
        self.current.start()

    def settle(self) -> None:
        """Wait for the keyframe going to the mapper, if one is; raise its failure here (on the
        tracking thread), once."""
        handover = self.current
        if handover is None:
            return
        start = time.perf_counter()
        handover.join()  # an interrupt here leaves it to the next settle()
        self.current = None
        self.wait_s += time.perf_counter() - start
        self.time_s += handover.seconds
        if handover.error is not None:
            raise handover.error
