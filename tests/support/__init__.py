"""Helpers shared by the test modules of every layer (tests/core, tests/plugins, tests/e2e):
where the real data is, the console scripts run as processes, small data folders and scenes
built for a test, throwaway third-party plugins. On the path through pytest's `pythonpath`
option (pyproject.toml): `from support.data import TUM`. A test module never imports another
test module; what two modules share lives here."""
