"""The roles a plugin can fill: one abstract base class each, small on purpose, and the table
of roles (`ROLES`). A plugin provides a subclass of one base and a config dataclass deriving
from `PluginConfig`; the registry builds the subclass with the validated config (and, for a
mapper, the parts it names in `Mapper.parts`)."""

from slamkit.map.rendering import Rasterizer, RenderOutput
from slamkit.roles.config import PluginConfig, check_values, require, thread_count, unlimited
from slamkit.roles.dataset import Dataset, DatasetConfig, OnError, SensorProfile
from slamkit.roles.loop_closure import (LoopCheck, LoopClosure, LoopDecision, LoopKeyframe, PoseGraph,
                                        PoseGraphEdge, follow_keyframes)
from slamkit.roles.mapping import KeyframeSampler, Mapper, MapOptimizer, MappingLoss, TrainingView
from slamkit.roles.strategy import CoverageTest, DensifyStrategy, KeyframeView, StepInfo, StrategyConfig
from slamkit.roles.table import ROLE_KEYS, ROLES, Role, role, role_of
from slamkit.roles.tracking import KeyframeHistory, KeyframePolicy, Tracker
from slamkit.roles.viewer import MapGaussians, MapPoints, Viewer, ViewerConfig, ViewerFrame

__all__ = [
    "ROLES", "ROLE_KEYS", "Role", "role", "role_of", "PluginConfig", "require", "thread_count", "unlimited", "check_values",
    "Dataset", "DatasetConfig", "OnError", "SensorProfile",
    "Tracker", "KeyframePolicy", "KeyframeHistory",
    "Mapper", "Rasterizer", "RenderOutput", "KeyframeSampler", "DensifyStrategy", "StrategyConfig", "CoverageTest", "MapOptimizer",
    "MappingLoss", "TrainingView", "KeyframeView", "StepInfo",
    "LoopClosure", "LoopKeyframe", "LoopDecision", "LoopCheck", "PoseGraph", "PoseGraphEdge", "follow_keyframes",
    "Viewer", "ViewerConfig", "ViewerFrame", "MapPoints", "MapGaussians",
]
