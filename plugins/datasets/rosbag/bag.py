"""A ROS bag opened through rosbags (https://gitlab.com/ternaris/rosbags), indexed by topic for
random access: ROS1 `.bag`, ROS2 bag folders (metadata.yaml) and single ROS2 storage files
(`.db3` SQLite3, `.mcap`). No ROS installation is needed.

`BagIndex.scan(topics)` reads each message of those topics once and keeps, per topic, its
record time (the bag's own clock, nanoseconds) and its header stamp (the sensor's clock,
seconds); `message(topic, k)` later reads the k-th message again by its record time, so
memory does not grow with the bag. A reader is opened per thread (the SQLite3 storage may only
be used from the thread that opened it): the run reads frames in a prefetch thread.

Every failure to open or read (a missing or truncated file, an unknown storage, a message that
does not deserialise) is a `slamkit.errors.DataError` naming the bag. The bag, or each file of a
bag folder, must be a regular file: a FIFO or a device (`mkfifo bag.mcap`) would block the
reader forever, waiting for a writer.
"""

from __future__ import annotations

import logging
import stat
import threading
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slamkit.errors import ConfigError, DataError

log = logging.getLogger(__name__)

BAG_EXPECTED = "a ROS1 .bag file, a ROS2 bag folder with metadata.yaml, or a ROS2 .db3 / .mcap file"


def _import_rosbags():
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError as exc:
        raise ConfigError(f"dataset=rosbag needs rosbags ({exc}); install it with pip install -e '.[rosbag]'") from None
    return AnyReader, Stores, get_typestore


def _reason(exc: BaseException) -> str:
    def flat(args):
        return " ".join(flat(a) if isinstance(a, tuple) else str(a) for a in args)

    text = flat(exc.args) if exc.args else str(exc)
    first = (text.strip().splitlines() or [type(exc).__name__])[0]
    return f"{type(exc).__name__}: {first}" if type(exc).__name__ not in first else first


@dataclass
class TopicIndex:
    """One topic's messages in bag order: msgtype ('sensor_msgs/msg/Image'), record times
    (int64 nanoseconds, the bag's clock) and header stamps (float64 seconds)."""

    topic: str
    msgtype: str
    record_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    stamps: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float64))

    def __len__(self) -> int:
        return len(self.record_ns)


def _check_regular_files(path: Path) -> None:
    """DataError naming the first of `path` (a file) or of its files (a bag folder) that is not
    a regular file: reading a FIFO, a socket or a device would block or never end."""
    for item in sorted(path.iterdir()) if path.is_dir() else [path]:
        try:
            mode = item.stat().st_mode
        except OSError as exc:  # a link to nowhere, a loop of links
            raise DataError(f"ROS bag {item}: {exc.strerror or exc} (expected {BAG_EXPECTED})") from None
        if not stat.S_ISREG(mode) and not stat.S_ISDIR(mode):
            kind = "a FIFO" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode) else "a device"
            raise DataError(f"ROS bag {item} is not a regular file ({kind}; expected {BAG_EXPECTED})")


class BagIndex:
    """A bag's topics (`topics`: name -> msgtype) and, after `scan`, per-topic message indices."""

    def __init__(self, path: str | Path):
        self.path = Path(path).expanduser()
        if not str(path):
            raise DataError(f"dataset.path is empty (expected {BAG_EXPECTED})")
        if not self.path.exists():
            raise DataError(f"ROS bag {self.path} not found (expected {BAG_EXPECTED})")
        _check_regular_files(self.path)
        self._local = threading.local()
        self._readers: list = []
        self._lock = threading.Lock()
        reader = self._reader()
        self.topics: dict[str, str] = {c.topic: c.msgtype for c in reader.connections}
        self.index: dict[str, TopicIndex] = {}

    # -- opening ----------------------------------------------------------------------------
    def _reader(self):
        """This thread's open AnyReader."""
        reader = getattr(self._local, "reader", None)
        if reader is None:
            AnyReader, Stores, get_typestore = _import_rosbags()
            try:
                # ROS2 SQLite3 bags before Iron carry no message definitions: use the standard ones
                reader = AnyReader([self.path], default_typestore=get_typestore(Stores.LATEST))
                reader.open()
            except Exception as exc:  # AnyReaderError, ReaderError, struct / yaml / sqlite errors
                raise DataError(f"cannot read ROS bag {self.path}: {_reason(exc)} (expected {BAG_EXPECTED})") from None
            self._local.reader = reader
            with self._lock:
                self._readers.append(reader)
        return reader

    def close(self) -> None:
        """Close every thread's reader."""
        with self._lock:
            readers, self._readers = self._readers, []
        for reader in readers:
            try:
                reader.close()
            except Exception:  # already closed, or the file went away
                pass
        self._local = threading.local()

    @contextmanager
    def _reading(self, what: str):
        """Turn any failure while reading messages into one DataError line."""
        try:
            yield
        except DataError:
            raise
        except Exception as exc:
            raise DataError(f"cannot read {what} from ROS bag {self.path}: {_reason(exc)} "
                            "(the bag may be truncated or corrupt)") from None

    def _connections(self, topic: str):
        return [c for c in self._reader().connections if c.topic == topic]

    # -- reading ----------------------------------------------------------------------------
    def first_message(self, topic: str):
        """The first message of `topic`, deserialised (None if it has none)."""
        reader = self._reader()
        with self._reading(f"topic {topic}"):
            for conn, _, raw in reader.messages(connections=self._connections(topic)):
                return reader.deserialize(raw, conn.msgtype)
        return None

    def scan(self, topics: list[str]) -> None:
        """Index every message of `topics` (one pass over the bag)."""
        reader = self._reader()
        records: dict[str, list[tuple[int, float]]] = {t: [] for t in topics}
        conns = [c for t in topics for c in self._connections(t)]
        with self._reading(", ".join(topics)):
            for conn, record_ns, raw in reader.messages(connections=conns):
                stamp = reader.deserialize(raw, conn.msgtype).header.stamp
                records[conn.topic].append((record_ns, stamp.sec + stamp.nanosec * 1e-9))
        for topic, rows in records.items():
            table = np.array(rows, dtype=np.float64).reshape(-1, 2)
            self.index[topic] = TopicIndex(topic, self.topics[topic], np.array([r[0] for r in rows], np.int64),
                                           table[:, 1])

    def message(self, topic: str, k: int):
        """The k-th message of a scanned topic, deserialised."""
        t = self.index[topic].record_ns[k]
        rank = int(k - np.searchsorted(self.index[topic].record_ns, t))  # messages recorded at the same time
        reader = self._reader()
        with self._reading(f"message {k} of {topic}"):
            for i, (conn, _, raw) in enumerate(reader.messages(connections=self._connections(topic), start=int(t),
                                                               stop=int(t) + 1)):
                if i == rank:
                    return reader.deserialize(raw, conn.msgtype)
        raise DataError(f"ROS bag {self.path}: message {k} of {topic} (recorded at {t} ns) is missing "
                        "(the bag may have changed since it was opened)")
