"""The one error boundary between the run and its plugins: an exception escaping a plugin's
method becomes a one-line PluginError naming the plugin (its traceback goes to the log file),
so the run stops cleanly and writes what it has."""

from __future__ import annotations

import logging
from contextlib import contextmanager
from typing import Iterator

from slamkit.errors import PluginError, SlamkitError

log = logging.getLogger(__name__)


class PluginBoundary:
    """`with boundary("tracker", "track"): ...` around a call into the plugin chosen for a
    role; `names` maps each role key to the chosen plugin's name."""

    def __init__(self, names: dict[str, str]):
        self.names = dict(names)

    @contextmanager
    def __call__(self, role: str, method: str) -> Iterator[None]:
        try:
            yield
        except (SlamkitError, OSError):  # the user's input, the environment (a full disk): theirs to say
            raise
        except Exception as exc:
            name = self.names.get(role, "?")
            # the traceback goes to the log file (INFO), not to the terminal (WARNING and above)
            log.info("%s %r failed in %s()", role, name, method, exc_info=True)
            message = f"{role} plugin {name!r} failed in {method}(): {type(exc).__name__}: {exc}"
            raise PluginError(message.splitlines()[0]) from exc
