"""A run folder belongs to one run (docs/architecture.md, "A run folder belongs to one run").

- `RunFolderLock`: a run holds `RUN_DIR/.slamkit.lock` (an exclusive `flock`, naming its holder)
  from before it writes into its folder until the command ends; a second run or a resume into it
  stops in one line naming the holder (`RunFolderInUse`). The lock dies with its process, however
  it ends, so a killed run leaves no stale lock.
- `check_new_run_folder`: a new run into a folder holding another run's outputs, or another
  program's files, stops in one line (`output.existing_outputs=clean` empties a slamkit run folder
  first); a folder holding only what a refused run left (`.hydra/`, `slamkit.log`) counts as new.
- `check_localization_folder`: localisation never writes into its map's folder.
- `unique_suffix`: default folders (`${slamkit.run:}` in conf/config.yaml) are unique per
  run, even for runs started in the same second.
Hydra's callbacks (`slamkit.cli.hydra_hooks`) apply these before Hydra writes `.hydra/`.
"""

from __future__ import annotations

import errno
import itertools
import json
import logging
import os
import shutil
import socket
from datetime import datetime, timezone
from pathlib import Path

from slamkit.errors import ConfigError
from slamkit.registry.schema import ExistingOutputs

log = logging.getLogger(__name__)

#: The lock file inside a run folder.
LOCK_NAME = ".slamkit.lock"
#: What a run leaves before its first frame (Hydra's record of the run, its log, the lock): a
#: folder holding nothing else is as good as new.
RUN_RECORDS = frozenset({".hydra", "slamkit.log", LOCK_NAME})
#: Entries that mark a slamkit run folder (a sweep folder: multirun.yaml).
RUN_MARKS = (".hydra", "metrics.json", "checkpoint.zip", "multirun.yaml")


class RunFolderError(ConfigError):
    """The run cannot have this folder (in use, used, the map's): one line, exit status 2."""


class RunFolderInUse(RunFolderError):
    """Another process holds the folder's lock."""


_suffixes = itertools.count()


def unique_suffix() -> str:
    """A name part no other run gets: this process's id, then a count of the folders it named
    before (`4711`, `4711.1`, ...)."""
    n = next(_suffixes)
    return f"{os.getpid()}" if n == 0 else f"{os.getpid()}.{n}"


class RunFolderLock:
    """The exclusive lock of one run folder (see the module docstring); `acquire()` creates the
    folder if needed."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder).absolute()
        self.path = self.folder / LOCK_NAME
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> "RunFolderLock":
        """Take the lock, or raise RunFolderInUse naming its holder."""
        import fcntl

        if self._fd is not None:
            return self
        self.folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise
            raise RunFolderInUse(f"run folder {self.folder} is in use by another run ({self.holder()}); wait for "
                                 "it to end, or choose another hydra.run.dir") from None
        owner = {"pid": os.getpid(), "host": socket.gethostname(),
                 "started": datetime.now(timezone.utc).astimezone().isoformat(timespec="seconds")}
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(owner) + "\n").encode(), 0)
        self._fd = fd
        return self

    def holder(self) -> str:
        """Who holds the lock, as the lock file says: 'pid N on host H since T'."""
        try:
            owner = json.loads(self.path.read_text())
            return f"pid {owner['pid']} on host {owner['host']} since {owner['started']}"
        except (OSError, ValueError, KeyError, TypeError):
            return "a process that has not said who it is yet"

    def release(self) -> None:
        """Let the folder go (the lock file stays: removing it would race with a new holder)."""
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor drops the flock
            self._fd = None


def in_use_by(folder: str | Path) -> str | None:
    """Who holds `folder`'s lock ('pid N on host H since T'), or None when no run does."""
    lock = RunFolderLock(folder)
    if not lock.path.is_file():
        return None
    import fcntl

    try:
        fd = os.open(lock.path, os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        return None
    except OSError:
        return lock.holder()
    finally:
        os.close(fd)  # drops the shared lock taken to test it


def earlier_outputs(folder: Path) -> list[str]:
    """The entries of `folder` that a new run would find beside its own (sorted names; none for
    a missing folder, or one holding only `RUN_RECORDS`)."""
    if not folder.is_dir():
        return []
    return sorted(p.name for p in folder.iterdir() if p.name not in RUN_RECORDS)


def _listed(names: list[str], most: int = 5) -> str:
    return ", ".join(names[:most]) + (f", ... ({len(names)} in all)" if len(names) > most else "")


def is_run_folder(folder: Path) -> bool:
    """Whether `folder` is a slamkit run's (or sweep's): Hydra's record, metrics or a checkpoint."""
    return any((folder / mark).exists() for mark in RUN_MARKS)


def check_new_run_folder(folder: Path, existing: ExistingOutputs = ExistingOutputs.refuse,
                         key: str = "hydra.run.dir") -> None:
    """A new run (or sweep) may write into `folder`: RunFolderError when it holds another
    run's outputs (unless `existing` is clean: then they are deleted) or another program's files
    (always). `key` names the setting in the message."""
    left = earlier_outputs(folder)
    if not left:
        return
    if not is_run_folder(folder):
        raise RunFolderError(f"{key}={folder} holds files that are not a slamkit run's ({_listed(left)}); choose an "
                             "empty or new folder")
    if existing is not ExistingOutputs.clean:
        what, resume = ("sweep", "") if key == "hydra.sweep.dir" else ("run", f", resume={folder} to continue it")
        raise RunFolderError(f"{key}={folder} holds the outputs of an earlier {what} ({_listed(left)}); choose a new "
                             f"folder{resume}, or output.existing_outputs=clean to start it clean")
    for name in [*left, *(n for n in RUN_RECORDS - {LOCK_NAME})]:
        path = folder / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        elif path.exists() or path.is_symlink():
            path.unlink()
    log.warning("output.existing_outputs=clean: deleted the earlier outputs in %s (%s)", folder, _listed(left))


def check_localization_folder(folder: Path, map_source: str | Path | None) -> None:
    """RunFolderError when `folder` (where a localisation writes) is the folder of the map it
    localises in (a run folder, or the one holding the checkpoint file)."""
    if not map_source:
        return
    source = Path(map_source).absolute()
    map_folder = source if source.is_dir() else source.parent
    if map_folder.resolve() == Path(folder).absolute().resolve():
        raise RunFolderError(f"hydra.run.dir={folder} is the folder of the map (map={map_source}); "
                             "localisation writes into a folder of its own")


def resumed_folder(resume: str | Path | None) -> Path | None:
    """The run folder a `resume=` source continues (the folder, or the checkpoint file's)."""
    if not resume:
        return None
    source = Path(resume).absolute()
    return (source if source.is_dir() else source.parent).resolve()


_held: dict[Path, RunFolderLock] = {}


def claim(folder: Path, existing: ExistingOutputs = ExistingOutputs.refuse, resume: str | Path | None = None,
          localize_map: str | Path | None = None) -> RunFolderLock:
    """Take `folder` for one run: its lock, then the checks (`check_localization_folder`; a
    resumed run continues in its own folder; any other must find it new, or clean it). Held until
    `release(folder)` or `release_all()`."""
    folder = Path(folder).absolute()
    check_localization_folder(folder, localize_map)
    lock = RunFolderLock(folder).acquire()
    try:
        if resumed_folder(resume) != folder.resolve():
            check_new_run_folder(folder, existing)
    except BaseException:
        lock.release()
        raise
    _held[folder] = lock
    return lock


def release(folder: Path) -> None:
    lock = _held.pop(Path(folder).absolute(), None)
    if lock is not None:
        lock.release()


def release_all() -> None:
    """Release every folder this process claimed (the command's end)."""
    for folder in list(_held):
        release(folder)
