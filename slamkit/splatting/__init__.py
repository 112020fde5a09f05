"""The 3DGS trainer of the shared map: which new Gaussians enter it (`admission`) where the
map does not already explain a view (`coverage`), the memory cap (`memory_cap`), the keyframes as
training views (`keyframes`), the training loop (`trainer`, with `timing`) and the rendering
metrics (`evaluation`). Its parts' contracts are roles (`slamkit.roles`)."""

from slamkit.splatting.admission import Admission, AdmissionConfig, CoverageTest, KeyframeView
from slamkit.splatting.memory_cap import MemoryCap, MemoryCapConfig
from slamkit.splatting.trainer import Trainer, TrainerConfig

__all__ = ["Admission", "AdmissionConfig", "CoverageTest", "KeyframeView", "MemoryCap", "MemoryCapConfig", "Trainer",
           "TrainerConfig"]
