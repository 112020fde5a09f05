"""3D Gaussian Splatting training of the shared map, in one place (as gsplat keeps strategy/
beside its ops): the rendering contract (`rendering`), the row operations that keep per-row
state aligned (`ops`), where the map already explains a view (`coverage`) and which new
Gaussians enter it (`admission`), the memory cap (`memory_cap`), the parts' contracts
(`sampler`, `loss`, `optimizer`, `strategy`), the keyframes as training views (`keyframes`,
`views`), the training loop (`trainer`) and the rendering metrics (`evaluation`)."""

from slamkit.splatting.admission import Admission, AdmissionConfig, CoverageTest, KeyframeView
from slamkit.splatting.loss import MappingLoss
from slamkit.splatting.memory_cap import MemoryCap, MemoryCapConfig
from slamkit.splatting.ops import MapEdit
from slamkit.splatting.optimizer import MapOptimizer
from slamkit.splatting.rendering import Rasterizer, RenderOutput, render_map
from slamkit.splatting.sampler import KeyframeSampler
from slamkit.splatting.strategy import StepInfo, Strategy, StrategyConfig
from slamkit.splatting.trainer import Trainer, TrainerConfig
from slamkit.splatting.views import TrainingView

__all__ = ["Admission", "AdmissionConfig", "CoverageTest", "KeyframeView", "MappingLoss", "MemoryCap",
           "MemoryCapConfig", "MapEdit", "MapOptimizer", "Rasterizer", "RenderOutput", "render_map",
           "KeyframeSampler", "StepInfo", "Strategy", "StrategyConfig", "Trainer", "TrainerConfig", "TrainingView"]
