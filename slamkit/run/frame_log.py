"""frames.csv, the run's per-frame log (`FrameLog`)."""

from __future__ import annotations

import csv
import io
from pathlib import Path

from slamkit.formats.atomic import write_atomic
from slamkit.run.metrics import rss_mb
from slamkit.run.slam import StepResult
from slamkit.types import Frame


def _index_below(cell: str, index: int) -> bool:
    return cell.isdigit() and int(cell) < index


class FrameLog:
    """frames.csv: one row per input frame (keyframe kind, lost flag and reason, tracking and
    mapping time in ms, ...), appended as the stream goes and flushed every `flush` call and at
    the end. A log, not written atomically: after a kill its last row may be cut short; a reader
    drops a last line that has no line end. An OSError names the file.

    `iterations` is the mapper's steps in that frame (sequential mode); `tracking_iterations` the
    tracker's, over all its attempts at the frame, and `fallback` the attempt it kept when not
    the first (both empty for a tracker that does not report them): where a slow frame's time
    went."""

    COLUMNS = ["index", "timestamp", "keyframe", "lost", "tracking_ms", "mapping_ms", "iterations",
               "correspondence_ratio", "num_gaussians", "rss_mb", "note",
               "delay_ms", "tracking_iterations", "fallback"]

    def __init__(self, path: Path, resume_from: int = 0):
        """`resume_from` > 0: extend the log of the run this one resumes, from that frame index
        on; the rows it had logged from there (after its checkpoint, before it was killed) and
        a last row cut short are dropped first, so that every frame has one row."""
        self.path = path
        append = resume_from > 0 and path.exists()
        if append:
            self._guard(self._keep_rows_before, resume_from)
        self._file = self._guard(open, path, "a" if append else "w", newline="")
        self._writer = csv.writer(self._file)
        if not append:
            self._row(self.COLUMNS)

    def _keep_rows_before(self, index: int) -> None:
        with open(self.path, newline="") as f:
            text = f.read()
        text = text[: text.rfind("\n") + 1]  # (a row cut short has no line end)
        rows = list(csv.reader(io.StringIO(text)))[1:]
        out = io.StringIO()
        csv.writer(out).writerows([self.COLUMNS] + [row for row in rows if row and _index_below(row[0], index)])
        write_atomic(self.path, out.getvalue())

    def frame(self, frame: Frame, step: StepResult, num_gaussians: int, delay_s: float | None = None) -> None:
        """A tracked frame's row; `delay_s`: from its arrival to its pose (delay_ms)."""
        result = step.tracking
        self._row([frame.index, f"{frame.timestamp:.6f}", step.keyframe.value, int(result.lost),
                   f"{1e3 * step.tracking_time_s:.2f}", f"{1e3 * step.mapping_time_s:.2f}", step.mapping_iterations,
                   _fmt(step.decision.correspondence_ratio), num_gaussians, f"{rss_mb():.1f}",
                   result.stats.get("lost_reason", ""), "" if delay_s is None else f"{1e3 * delay_s:.2f}",
                   result.stats.get("iterations", ""), result.stats.get("fallback", "")])

    def unreadable(self, index: int, timestamp: float, error: Exception) -> None:
        self._row([index, f"{timestamp:.6f}", "none", 1, "", "", 0, "", "", "", f"unreadable: {error}", "", "", ""])

    def dropped(self, frame: Frame) -> None:
        self._row([frame.index, f"{frame.timestamp:.6f}", "none", 0, "", "", 0, "", "", "", "dropped", "", "", ""])

    def flush(self) -> None:
        self._guard(self._file.flush)

    def close(self) -> None:
        self._guard(self._file.close)

    def __enter__(self) -> "FrameLog":
        return self

    def __exit__(self, *exc) -> None:
        try:
            self.close()
        except OSError:
            if exc[0] is None:  # an error already on its way says what went wrong first
                raise

    def _row(self, cells: list) -> None:
        self._guard(self._writer.writerow, cells)

    def _guard(self, call, *args, **kwargs):
        try:
            return call(*args, **kwargs)
        except OSError as exc:
            raise OSError(exc.errno, exc.strerror or str(exc), str(self.path)) from exc


def _fmt(value: float | None) -> str:
    return "" if value is None else f"{value:.4f}"
