"""The shared Gaussian map: its tensors (`gaussian_map`), how keyframes grow it (`growth`), the
row operations strategies edit it with (`editing`), rendering it (`rendering`, the rasteriser
role), and where it already explains a view (`coverage`)."""

from slamkit.map.editing import MapEdit
from slamkit.map.gaussian_map import PARAMETERS, GaussianMap, GaussianRows, TrackingTarget
from slamkit.map.coverage import DepthTolerance, covered_by_render, occupied_by_centres
from slamkit.map.rendering import Rasterizer, RenderOutput, render_map

__all__ = ["PARAMETERS", "GaussianMap", "GaussianRows", "TrackingTarget", "MapEdit", "Rasterizer", "RenderOutput",
           "DepthTolerance", "covered_by_render", "occupied_by_centres", "render_map"]
