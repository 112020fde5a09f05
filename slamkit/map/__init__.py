"""The shared Gaussian map: its tensors (`gaussian_map`) and how keyframes grow it (`growth`).
Training it is `slamkit.splatting`'s."""

from slamkit.map.gaussian_map import PARAMETERS, ROW_WIDTHS, GaussianMap, GaussianRows, TrackingTarget

__all__ = ["PARAMETERS", "ROW_WIDTHS", "GaussianMap", "GaussianRows", "TrackingTarget"]
