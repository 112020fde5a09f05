"""Which of a keyframe's Gaussians enter the map: none where the map already explains the
keyframe's view (`AdmissionConfig.skip_covered`), so that the map is bounded by the scene, not
by how long the camera looks at it. The tests are in `.coverage`.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any, Callable

import torch

from slamkit.config import PluginConfig, RunContext, method_setting, require
from slamkit.map.gaussian_map import GaussianRows
from slamkit.roles.rendering import RenderOutput
from slamkit.types import Camera
from slamkit_plugins.mappers.gaussian_splatting.coverage import DepthTolerance, covered_by_render, occupied_by_centres


class CoverageTest(enum.Enum):
    """Where the map explains a keyframe's view (`.coverage`): centres (a map
    centre projects near the point at its depth; needs no render, no training), render (the
    map's render is opaque there at its depth), either."""

    centres = "centres"
    render = "render"
    either = "either"


@dataclass
class AdmissionConfig(PluginConfig):
    """Which of a keyframe's Gaussians enter the map."""

    #: no new Gaussian where the map explains the view, except trackable ones (off: the map grows on every revisit)
    skip_covered: bool = method_setting(True)
    #: the test: centres (bounds the map in real time too), render, or either
    coverage: CoverageTest = CoverageTest.centres
    #: input pixels; the centres test's disc has radius cell / sqrt(2) (null: the dataset's tracking pixel stride)
    covered_cell: float | None = None
    #: map centres the centres test needs in a point's disc to count it explained
    covered_centres: int = 1
    #: the render test's alpha threshold
    covered_alpha: float = 0.9
    #: metres; the smallest depth difference still one surface, in both tests
    covered_depth_tolerance: float = 0.05
    #: 1/metres; the depth tolerance is at least this x z^2 at camera depth z (0: constant)
    covered_depth_quadratic: float = 0.01

    def validate(self) -> None:
        require(self.covered_cell is None or self.covered_cell > 0, "mapper.admission.covered_cell",
                "null or > 0 pixels", self.covered_cell)
        require(self.covered_centres >= 1, "mapper.admission.covered_centres", "an integer >= 1",
                self.covered_centres)
        require(0 < self.covered_alpha < 1, "mapper.admission.covered_alpha", "in (0, 1)", self.covered_alpha)
        require(self.covered_depth_tolerance > 0, "mapper.admission.covered_depth_tolerance", "> 0 metres",
                self.covered_depth_tolerance)
        require(self.covered_depth_quadratic >= 0, "mapper.admission.covered_depth_quadratic", ">= 0 per metre",
                self.covered_depth_quadratic)

    def resolve(self, context: RunContext) -> AdmissionConfig:
        # a keyframe holds about one Gaussian per sampling cell and surface
        return self.fill_nulls(covered_cell=float(context.tuning.tracking_pixel_stride))


@dataclass
class KeyframeView:
    """The keyframe whose Gaussians are being admitted: its camera at the training resolution,
    world_to_camera (4,4) float32 tensor, `render()`, the current map rendered from it (computed
    on first call), its camera at the input resolution (None: `camera`), and the map's Gaussian
    centres (M,3) world metres (None: an empty map)."""

    camera: Camera
    world_to_camera: torch.Tensor
    render: Callable[[], RenderOutput]
    input_camera: Camera | None = None
    centres: torch.Tensor | None = None


class Admission:
    """Decides which of a keyframe's Gaussians enter the map (see the module docstring).
    `skipped` counts the Gaussians left out as covered."""

    def __init__(self, cfg: AdmissionConfig):
        require(cfg.covered_cell is not None, "mapper.admission.covered_cell",
                "a value (AdmissionConfig.resolve fills it)", None)
        self.cfg = cfg
        self.tolerance = DepthTolerance(cfg.covered_depth_tolerance, cfg.covered_depth_quadratic)
        self.skipped = 0

    def admit(self, new: GaussianRows, view: KeyframeView) -> torch.Tensor | None:
        """(N,) bool: the new Gaussians that enter (the trackable ones and those where the map
        does not explain the view), or None for all (skip_covered off, nothing new)."""
        if not self.cfg.skip_covered or len(new) == 0:
            return None
        enter = ~self.covered(new.means, view) | new.trackable.to(new.means.device)
        self.skipped += int((~enter).sum())
        return enter

    def covered(self, points: torch.Tensor, view: KeyframeView) -> torch.Tensor:
        """(N,) bool: the world points (N,3, metres) where the map already explains the
        keyframe's view, by the configured test."""
        cfg, test = self.cfg, CoverageTest(self.cfg.coverage)
        covered = torch.zeros(len(points), dtype=torch.bool, device=points.device)
        if test is not CoverageTest.render and view.centres is not None:
            covered |= occupied_by_centres(points, view.centres, view.world_to_camera, view.input_camera or view.camera,
                                           cfg.covered_cell, self.tolerance, cfg.covered_centres)
        if test is not CoverageTest.centres:
            covered |= covered_by_render(points, view.render(), view.world_to_camera, view.camera,
                                         cfg.covered_alpha, self.tolerance)
        return covered

    def metrics(self) -> dict[str, Any]:
        return {"skipped_as_covered": self.skipped}
