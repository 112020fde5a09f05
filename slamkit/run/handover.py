"""A keyframe's work that tracking does not wait for, run in a thread of its own beside it
(real time, `realtime.keyframe_thread`): `SLAM.add_keyframe` gives it to `KeyframeHandovers`, one
keyframe at a time, and the next keyframe, a loop correction and a checkpoint wait for it
(`settle`). What the next frame needs (the tracker's new target) runs first in that thread, and
the next frame waits for that part only (`ready`)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable


class KeyframeHandover(threading.Thread):
    """`first()` then `hand_over()` in a thread of its own, at the tracking thread's priority
    (the mapping thread's lower one would let training hold up the next keyframe). `first_done`
    is set once `first` has returned or failed. `error`: what it raised, for
    `KeyframeHandovers.settle` to raise on the tracking thread; `seconds`: how long it took."""

    def __init__(self, hand_over: Callable[[], None], first: Callable[[], None] | None = None):
        super().__init__(name="slamkit-keyframe", daemon=True)
        self.hand_over = hand_over
        self.first = first
        self.first_done = threading.Event()
        self.error: BaseException | None = None
        self.seconds = 0.0

    def run(self) -> None:
        start = time.perf_counter()
        try:
            if self.first is not None:
                self.first()
            self.first_done.set()
            self.hand_over()
        except BaseException as exc:  # raised again by KeyframeHandovers.settle on the tracking thread
            self.error = exc
        finally:
            self.first_done.set()
            self.seconds = time.perf_counter() - start


class KeyframeHandovers:
    """The keyframes handed over beside tracking, one at a time. `time_s` sums the handovers'
    seconds, `wait_s` the tracking thread's waits for one (`settle`)."""

    def __init__(self) -> None:
        self.current: KeyframeHandover | None = None  # the last keyframe going to the mapper beside tracking
        self.time_s = 0.0
        self.wait_s = 0.0

    def start(self, hand_over: Callable[[], None], first: Callable[[], None] | None = None) -> None:
        """Run `first()` then `hand_over()` beside the calling thread (after `settle`: one at a
        time); `ready` waits for `first` alone."""
        self.current = KeyframeHandover(hand_over, first)
        self.current.start()

    def ready(self) -> None:
        """Wait until the keyframe's `first` part is done, if one is going; when the keyframe
        failed, wait for its end and raise its failure here (`settle`)."""
        handover = self.current
        if handover is None or handover.first_done.is_set() and handover.error is None:
            return
        start = time.perf_counter()
        handover.first_done.wait()
        self.wait_s += time.perf_counter() - start
        if handover.error is not None:
            self.settle()

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
