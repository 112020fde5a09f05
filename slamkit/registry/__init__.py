"""The plugin system: discovery through entry points (`discovery`), the one hook (`hookspecs`),
the Hydra run schema and its validation (`schema`) and composing a run from overrides as the
command does (`compose`)."""

from slamkit.registry.discovery import (
                                        Registered,
                                        Registry,
                                        create_rasterizer,
                                        default_registry,
                                        discover,
                                        register_configs,
)

__all__ = ["Registered", "Registry", "create_rasterizer", "default_registry", "discover", "register_configs"]
