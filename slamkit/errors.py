"""User-facing errors: the CLI prints them as one line, without a traceback."""


class SlamkitError(Exception):
    """An error caused by the user's input (a file, a config value): its message is one line
    naming the file or value and what was expected. The command exits with `exit_status`."""

    exit_status = 2


class DataError(SlamkitError):
    """A dataset file is missing, unreadable, or not what the loader expected."""


class ConfigError(SlamkitError):
    """A configuration value is of the wrong type or out of range."""


class PluginError(SlamkitError):
    """A plugin is unknown, failed to import, or does not implement its role."""


class OutputError(SlamkitError):
    """The run's outputs could not all be written (a full disk, a folder that went away): an
    environment failure, exit status 1. The message names the file and what was kept."""

    exit_status = 1
