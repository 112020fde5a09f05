"""slamkit: a plugin-based RGB-D SLAM framework (GS-ICP SLAM first).

What a plugin imports: `slamkit.plugin` (PluginSpec, hookimpl), `slamkit.roles` (the base
classes), `slamkit.config` (the config base, the run context), `slamkit.types`,
`slamkit.errors`, `slamkit.map` (the Gaussian map), `slamkit.geometry` and `slamkit.native`
(compiled helpers). The rest is grouped by concern: `metrics`, `formats`, `registry`, `run`,
`cli` (docs/architecture.md).
"""

import importlib as _importlib
import importlib.abc as _abc
import os as _os
import sys as _sys

# Tracking (numpy, pykdtree) and mapping (torch) each use OpenMP; with the default spin-waiting
# their thread pools fight over the cores (docs/results.md, "Tracking per frame").
# Must be set before either runtime starts, hence here. A user's own setting wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

#: Module paths that plugins used before 0.2 grouped the package by concern and 0.3 gave the 3DGS
#: trainer's contracts a package, and where those modules are now: `import slamkit.gaussian_map`
#: still gives `slamkit.map.gaussian_map` (docs/CHANGELOG.md).
MOVED_MODULES = {
    "slamkit.gaussian_map": "slamkit.map.gaussian_map",
    "slamkit.rendering": "slamkit.roles.rendering",
    "slamkit.map.rendering": "slamkit.roles.rendering",
    "slamkit.map.editing": "slamkit.roles.map_edit",
    "slamkit.roles.config": "slamkit.config",
    "slamkit.gaussian_geometry": "slamkit.geometry.gaussians",
    "slamkit.image_metrics": "slamkit.metrics.images",
    "slamkit.evaluation": "slamkit.metrics.trajectory",
    "slamkit.tum_format": "slamkit.formats.tum",
    "slamkit.image_io": "slamkit.formats.images",
    "slamkit.ply": "slamkit.formats.ply",
}


class _MovedModuleFinder(_abc.MetaPathFinder, _abc.Loader):
    """Imports an old module path as the module now at its new path (the module replaces its
    placeholder in sys.modules, which the import system honours)."""

    def find_spec(self, fullname, path, target=None):
        if fullname in MOVED_MODULES:
            from importlib.machinery import ModuleSpec

            return ModuleSpec(fullname, self)
        return None

    def create_module(self, spec):
        return None

    def exec_module(self, module):
        _sys.modules[module.__name__] = _importlib.import_module(MOVED_MODULES[module.__name__])


_sys.meta_path.append(_MovedModuleFinder())


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
