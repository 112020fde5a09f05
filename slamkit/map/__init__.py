"""The shared Gaussian map: its tensors (`gaussian_map`), how keyframes grow it (`growth`), the
row operations strategies edit it with (`editing`), and rendering it (`rendering`, the
rasteriser role)."""

from slamkit.map.editing import MapEdit
from slamkit.map.gaussian_map import PARAMETERS, GaussianMap, GaussianRows, TrackingTarget
from slamkit.map.rendering import Rasterizer, RenderOutput, covered_by_render, render_map

__all__ = ["PARAMETERS", "GaussianMap", "GaussianRows", "TrackingTarget", "MapEdit", "Rasterizer", "RenderOutput",
           "covered_by_render", "render_map"]
