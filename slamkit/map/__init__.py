"""The shared Gaussian map: its tensors (`gaussian_map`) and how keyframes grow it (`growth`).
Training it is a mapper's (`slamkit.roles.Mapper`)."""

from slamkit.map.gaussian_map import PARAMETERS, ROW_WIDTHS, GaussianMap, GaussianRows, TrackingTarget

__all__ = ["PARAMETERS", "ROW_WIDTHS", "GaussianMap", "GaussianRows", "TrackingTarget"]
