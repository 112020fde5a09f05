"""`mapper=gaussian_splatting`: GS-ICP SLAM's 3DGS mapper (see `.mapper`)."""

from slamkit.plugin import PluginSpec, hookimpl
from slamkit_plugins.mappers.gaussian_splatting.config import GaussianSplattingConfig
from slamkit_plugins.mappers.gaussian_splatting.mapper import GaussianSplattingMapper

__all__ = ["GaussianSplattingConfig", "GaussianSplattingMapper"]


@hookimpl
def slamkit_plugins():
    return [PluginSpec("gaussian_splatting", GaussianSplattingMapper, GaussianSplattingConfig)]
