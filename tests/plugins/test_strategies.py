"""Densification strategies (`strategy=gsicp|3dgs`) through the mapper's hooks, and the growth
control every strategy has (`strategy.skip_covered`: tests/plugins/test_map_bound.py)."""

from __future__ import annotations

import math

import pytest
import torch

from slamkit.errors import ConfigError
from slamkit.registry.discovery import create_rasterizer
from slamkit.tuning import DatasetTuning
from slamkit_plugins.mappers.gaussian_splatting.admission import AdmissionConfig
from slamkit_plugins.mappers.gaussian_splatting.strategy.densify_3dgs import Densify3DGSConfig

from support.mapping_scenes import (
    N,
    add,
    make_map,
    make_mapper,
    plane_scene,
    pose_x,
    render_frame,
    start_map,
    state_follows_map,
)


@pytest.fixture(scope="module")
def frame():
    return render_frame(create_rasterizer("torch"), make_map(*plane_scene()), pose_x(0.0))


def test_gsicp_prunes_on_schedule_with_the_datasets_scale_limit(frame):
    gm = start_map()
    with torch.no_grad():
        gm.log_scales[:7, 0] = math.log(0.3)  # above Replica's 0.25 m, below TUM's 1 m
        gm.opacity_logits[7:10] = math.log(0.001 / 0.999)  # nearly transparent
    replica = DatasetTuning(max_gaussian_scale=0.25)
    mapper = make_mapper(gm, tuning=replica, strategy=("gsicp", {"prune_every": 3}))
    add(mapper, frame)
    mapper.optimize(2)
    assert len(gm) == N  # not yet
    mapper.optimize(1)
    assert len(gm) == N - 10
    state_follows_map(mapper)
    tum = start_map()
    with torch.no_grad():
        tum.log_scales[:7, 0] = math.log(0.3)
    mapper = make_mapper(tum, strategy=("gsicp", {"prune_every": 3}))  # the generic profile: 1 m
    add(mapper, frame)
    mapper.optimize(3)
    assert len(tum) == N


def test_gsicp_without_a_schedule_never_prunes(frame):
    gm = start_map()
    with torch.no_grad():
        gm.opacity_logits[:5] = math.log(0.001 / 0.999)
    mapper = make_mapper(gm, strategy=("gsicp", {"prune_every": 0}))
    add(mapper, frame)
    mapper.optimize(6)
    mapper.finish()
    assert len(gm) == N
    mapper = make_mapper(gm, strategy=("gsicp", {"prune_every": 100}))
    mapper.finish()  # the last prune after the final steps
    assert len(gm) == N - 5


def test_3dgs_clones_small_splits_large_and_resets_opacity(frame):
    gm = start_map()
    with torch.no_grad():
        gm.log_scales[:150] = math.log(0.1)  # half of them above the split scale
    mapper = make_mapper(gm, strategy=("3dgs", {"densify_every": 3, "grad_threshold": 1e-9,
                                                "split_above_scale": 0.09, "reset_opacity_every": 4,
                                                "prune_every": 0}))
    add(mapper, frame)
    mapper.optimize(3)
    seen = int((gm.keyframe_id == 0).sum())
    assert len(gm) > N  # the ones it saw: cloned (small) or split in two (large)
    assert float(gm.scales.detach().max()) < 0.1  # every large one it saw was split
    state_follows_map(mapper)
    mapper.optimize(1)
    assert float(gm.opacities.detach().max()) <= 0.01 + 1e-6
    mapper.optimize(2)
    state_follows_map(mapper)
    assert all(torch.isfinite(p).all() for p in gm.parameters().values()) and seen > 0


def test_3dgs_densification_stays_within_its_budget(frame):
    gm = start_map()
    mapper = make_mapper(gm, strategy=("3dgs", {"densify_every": 3, "grad_threshold": 1e-9,
                                                "densify_max_gaussians": N + 20, "prune_every": 0}))
    add(mapper, frame)
    mapper.optimize(3)
    assert N < len(gm) <= N + 20


def test_3dgs_prune_every_zero_never_prunes_even_when_it_densifies(frame):
    """Table 8b's "densify, no pruning" row: prune_every = 0 keeps the nearly transparent and
    the oversized Gaussians through densifications and the end of training; with a schedule,
    the first densification prunes them."""
    def run(prune_every):
        gm = start_map()
        with torch.no_grad():
            gm.opacity_logits[:5] = math.log(0.001 / 0.999)  # below prune_min_opacity (0.005)
            gm.log_scales[5:8, 0] = math.log(2.0)  # above the generic profile's 1 m
        mapper = make_mapper(gm, strategy=("3dgs", {"densify_every": 3, "grad_threshold": 1e-9,
                                                    "reset_opacity_every": 0, "prune_every": prune_every}))
        add(mapper, frame)
        mapper.optimize(3)
        return gm, mapper

    gm, mapper = run(prune_every=0)
    assert len(gm) > N  # it densified
    mapper.optimize(3)  # a second densification
    mapper.finish()
    assert int((gm.opacities.detach().reshape(-1) < 0.005).sum()) >= 5
    assert int((gm.scales.detach().max(dim=1).values > 1.0).sum()) >= 1  # a split child keeps 2 / 1.6 = 1.25 m
    state_follows_map(mapper)
    gm, _ = run(prune_every=100)
    assert int((gm.opacities.detach().reshape(-1) < 0.005).sum()) == 0
    assert int((gm.scales.detach().max(dim=1).values > 1.0).sum()) == 0


def test_strategy_settings_are_validated():
    with pytest.raises(ConfigError, match="mapper.strategy.densify_every"):
        Densify3DGSConfig(densify_every=0)
    with pytest.raises(ConfigError, match="mapper.admission.covered_alpha"):
        AdmissionConfig(covered_alpha=1.0)
