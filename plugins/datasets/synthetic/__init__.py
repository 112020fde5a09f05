"""`dataset=synthetic`: the built-in generated RGB-D sequence (see `.dataset`)."""

from slamkit.plugin import PluginSpec, hookimpl
from slamkit_plugins.datasets.synthetic.dataset import (
    DEPTH_SCALE,
    FPS,
    GENERATOR_VERSION,
    PATH_BOUNDS,
    ROOM_HI,
    ROOM_LO,
    SyntheticConfig,
    SyntheticDataset,
    camera_path,
    default_cache_dir,
    render,
    scene,
    scene_clearance,
)

__all__ = ["DEPTH_SCALE", "FPS", "GENERATOR_VERSION", "PATH_BOUNDS", "ROOM_HI", "ROOM_LO", "SyntheticConfig",
           "SyntheticDataset", "camera_path", "default_cache_dir", "render", "scene", "scene_clearance"]


@hookimpl
def slamkit_plugins():
    return [PluginSpec("synthetic", SyntheticDataset, SyntheticConfig)]
