"""User-facing errors: the CLI prints them as one line, without a traceback."""


class SlamkitError(Exception):
    """An error caused by the user's input (a file, a config value): its message is one line
    naming the file or value and what was expected."""


class DataError(SlamkitError):
    """A dataset file is missing, unreadable, or not what the loader expected."""


class ConfigError(SlamkitError):
    """A configuration value is of the wrong type or out of range."""


class PluginError(SlamkitError):
    """A plugin is unknown, failed to import, or does not implement its role."""
