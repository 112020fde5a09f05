"""The roles a plugin can fill: one abstract base class each, small on purpose, and the table
of roles (`ROLES`). A plugin provides a subclass of one base and a config dataclass deriving
from `PluginConfig`; the registry fills the config's null fields from the run
(`PluginConfig.resolve`) and builds the subclass as `cls(config, context)` (a mapper also gets
the parts it names in `Mapper.parts`). The mapper's parts (rasteriser, sampler, strategy,
optimiser, loss) have theirs here too, one module each, with what they are handed: a training
step's target (`training_view`) and the row operations a strategy edits the map through
(`map_edit`)."""

from slamkit.config import PluginConfig, RunContext, check_values, method_setting, require, thread_count, unlimited
from slamkit.roles.dataset import Dataset, DatasetConfig, OnError, SourceEnded
from slamkit.roles.loop_closure import (
                                        LoopCheck,
                                        LoopClosure,
                                        LoopDecision,
                                        LoopKeyframe,
                                        PoseGraph,
                                        PoseGraphEdge,
                                        follow_keyframes,
)
from slamkit.roles.loss import MappingLoss
from slamkit.roles.map_edit import MapEdit
from slamkit.roles.mapping import Mapper
from slamkit.roles.optimizer import MapOptimizer
from slamkit.roles.rendering import Rasterizer, RenderOutput
from slamkit.roles.sampler import KeyframeSampler
from slamkit.roles.strategy import StepInfo, Strategy, StrategyConfig
from slamkit.roles.table import PARTS, ROLE_KEYS, ROLES, RUN_ROLES, Role, role, role_of
from slamkit.roles.tracking import KeyframeDecision, KeyframeHistory, KeyframePolicy, Tracker
from slamkit.roles.training_view import TrainingView
from slamkit.roles.viewer import MapGaussians, MapPoints, Viewer, ViewerConfig, ViewerFrame
from slamkit.tuning import DatasetTuning

#: Names of 0.2 kept for plugins written against it (docs/CHANGELOG.md): removed in 0.4.
SensorProfile = DatasetTuning
DensifyStrategy = Strategy

__all__ = [
    "ROLES", "ROLE_KEYS", "RUN_ROLES", "PARTS", "Role", "role", "role_of",
    "PluginConfig", "RunContext", "require", "thread_count", "unlimited", "method_setting", "check_values",
    "DatasetTuning",
    "Dataset", "DatasetConfig", "OnError", "SourceEnded",
    "Tracker", "KeyframePolicy", "KeyframeDecision", "KeyframeHistory",
    "Mapper", "Rasterizer", "RenderOutput", "KeyframeSampler", "Strategy", "StrategyConfig", "MapOptimizer",
    "MappingLoss", "TrainingView", "StepInfo", "MapEdit",
    "LoopClosure", "LoopKeyframe", "LoopDecision", "LoopCheck", "PoseGraph", "PoseGraphEdge", "follow_keyframes",
    "Viewer", "ViewerConfig", "ViewerFrame", "MapPoints", "MapGaussians",
    "SensorProfile", "DensifyStrategy",
]
