"""slamkit: a plugin-based RGB-D SLAM framework (GS-ICP SLAM first).

What a plugin imports: `slamkit.plugin` (PluginSpec, hookimpl), `slamkit.roles` (the base
classes), `slamkit.config` (the config base, the run context), `slamkit.types`,
`slamkit.errors`, `slamkit.map` (the Gaussian map), `slamkit.geometry` and `slamkit.native`
(compiled helpers). The rest is grouped by concern: `metrics`, `formats`, `registry`, `run`,
`cli` (docs/architecture.md).
"""

import os as _os

# Tracking (numpy, pykdtree) and mapping (torch) each use OpenMP; with the default spin-waiting
# their thread pools fight over the cores (docs/results.md, "Tracking per frame").
# Must be set before either runtime starts, hence here. A user's own setting wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def __getattr__(name: str):
    """`slamkit.__version__`: the installed distribution's, one version number (pyproject.toml's),
    read when asked for (importlib.metadata is not worth importing with every run)."""
    if name == "__version__":
        from importlib.metadata import PackageNotFoundError, version

        try:
            return version("slamkit")
        except PackageNotFoundError:  # imported from a source tree that was never installed
            return "unknown"
    raise AttributeError(f"module 'slamkit' has no attribute {name!r}")
