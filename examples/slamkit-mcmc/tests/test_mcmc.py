"""Tests of the mcmc strategy: the relocation rule, relocation and growth on a small scene
through slamkit's 3DGS mapper, the config, the plugin's registration, and a run of the `slamkit`
command on Replica room0."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from importlib.metadata import entry_points
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from slamkit.config import RunContext
from slamkit.downloads.excerpts import find_test_data
from slamkit.errors import ConfigError
from slamkit.map.gaussian_map import GaussianMap, GaussianRows
from slamkit.registry.discovery import default_registry, discover
from slamkit.tuning import DatasetTuning
from slamkit.types import Camera, Frame, KeyframeKind
from slamkit_mcmc import MCMCConfig, MCMCStrategy, scale_factor, shared_opacity

# The real test data: $SLAMKIT_DATA, else the shared folder beside the slamkit checkout, else where
# `slamkit-data download test-data` puts it.
DATA = find_test_data(Path(__file__).resolve().parents[3])
REPLICA = DATA / "replica_room0_first20"

CAM = Camera(40, 30, 30.0, 30.0, 19.5, 14.5)
N = 300  # Gaussians in the scene
DEAD = 40  # of them made nearly transparent


# -- the relocation rule ------------------------------------------------------------------------
def binomial_sum(o_new: float, copies: int) -> float:
    """3DGS-MCMC's D as written in the paper: the alternating binomial double sum."""
    return sum(math.comb(i - 1, j) * (-1) ** j * o_new ** (j + 1) / math.sqrt(j + 1)
               for i in range(1, copies + 2) for j in range(i))


@pytest.mark.parametrize("opacity", [0.02, 0.3, 0.9, 0.999])
def test_the_stack_keeps_the_sources_opacity_and_integral(opacity):
    copies = torch.arange(0, 12, dtype=torch.float64)
    o = torch.full_like(copies, opacity)
    o_new = shared_opacity(o, copies)
    torch.testing.assert_close(1 - (1 - o_new) ** (copies + 1), o)  # as opaque at the centre
    factor = scale_factor(o, o_new, copies)
    expected = [opacity / binomial_sum(float(v), int(k)) for v, k in zip(o_new, copies)]
    torch.testing.assert_close(factor, torch.tensor(expected, dtype=torch.float64), rtol=1e-9, atol=0)
    assert float(factor[0]) == pytest.approx(1.0)  # no copy: unchanged
    assert bool((factor[1:] <= 1).all())  # copies shrink their source


# -- a small scene through the mapper ----------------------------------------------------------
def plane(opacity: np.ndarray, seed: int = 0, colors: np.ndarray | None = None) -> GaussianRows:
    """N Gaussians on the plane z = 2 m in front of the identity camera (0.08 m wide)."""
    rng = np.random.default_rng(seed)
    means = np.c_[rng.uniform([-1.5, -1.1], [1.5, 1.1], size=(N, 2)), np.full(N, 2.0)]
    colors = rng.uniform(size=(N, 3)) if colors is None else colors
    return GaussianRows.from_shapes(means, np.tile([1.0, 0, 0, 0], (N, 1)), np.tile([0.08, 0.08, 0.01], (N, 1)),
                                    colors, opacity, np.ones(N, bool), 0)


def keyframe() -> Frame:
    """The view of an opaque coloured plane from the identity pose (rgb, expected depth)."""
    truth = GaussianMap()
    truth.append(plane(np.full(N, 0.9)))
    rasterizer = default_registry().create("rasterizer", "torch")
    with torch.no_grad():
        out = rasterizer.render(truth.means, truth.quats, truth.scales, truth.opacities, truth.colors,
                                torch.eye(4), CAM)
    alpha = out.alpha.numpy()
    depth = np.where(alpha > 0.5, out.depth.numpy() / np.maximum(alpha, 1e-6), 0).astype(np.float32)
    rgb = (out.color.clamp(0, 1).numpy() * 255).round().astype(np.uint8)
    return Frame(0, 0.0, rgb, depth, CAM, np.eye(4))


def map_with_dead_gaussians() -> GaussianMap:
    """The scene's Gaussians in grey at opacity 0.5, the first DEAD of them at 0.001."""
    opacity = np.full(N, 0.5)
    opacity[:DEAD] = 0.001
    gm = GaussianMap()
    gm.append(plane(opacity, colors=np.full((N, 3), 0.5)))
    return gm


def make_mapper(gm: GaussianMap, **strategy_fields):
    """slamkit's `gaussian_splatting` mapper with strategy=mcmc, built from its parts through the
    registry as a run builds it, bound to `gm`, with `frame` as its one keyframe."""
    registry = default_registry()
    context = RunContext(tuning=DatasetTuning(max_gaussian_scale=0.25), gaussian_map=gm, build=registry.create)
    parts = {role: registry.create(role, name, None, context) for role, name in
             [("rasterizer", "torch"), ("sampler", "random"), ("optimizer", "adam"), ("loss", "l1_ssim_depth")]}
    parts["strategy"] = registry.create("strategy", "mcmc", MCMCConfig(**strategy_fields), context)
    config = registry.get("mapper", "gaussian_splatting").config(resolution_scale=1.0)
    mapper = registry.create("mapper", "gaussian_splatting", config, context, **parts)
    mapper.add_keyframe(keyframe(), np.eye(4), KeyframeKind.TRACKING, slice(N, N))
    return mapper


def assert_state_follows_map(mapper) -> None:
    """The optimiser's per-row state covers exactly the map's rows."""
    n = len(mapper.gaussian_map)
    for name, tensors in mapper.optimizer.row_state().items():
        assert all(t.shape[0] == n for t in tensors), name


def test_dead_gaussians_are_relocated_onto_live_ones():
    gm = map_with_dead_gaussians()
    before = gm.rows()
    mapper = make_mapper(gm, refine_every=3, grow_fraction=0.0, jitter=False)
    mapper.optimize(2)
    assert mapper.strategy.metrics()["mcmc_relocated"] == 0  # not yet
    mapper.optimize(1)
    stats = mapper.strategy.metrics()
    assert stats["mcmc_relocated"] == DEAD and len(gm) == N
    assert float(gm.opacities.detach().min()) >= mapper.strategy.cfg.min_opacity
    # Without jitter each relocated row sits exactly on a live Gaussian of the map before.
    moved = gm.means.detach()[:DEAD]
    distance = torch.cdist(moved, before.means[DEAD:]).min(dim=1).values
    assert float(distance.max()) < 1e-3  # means moved by 3 steps at lr 4e-6 at most
    assert not bool(gm.trackable[:DEAD].any())  # copies are not tracking targets
    assert bool(gm.trackable[DEAD:].all())  # sources keep their flag
    assert_state_follows_map(mapper)
    # The moved rows and their sources (the live rows under them) start with zero optimiser
    # moments; the other rows keep theirs.
    means = gm.means.detach()
    touched = torch.cdist(means, means[:DEAD]).min(dim=1).values < 1e-6
    assert DEAD < int(touched.sum()) <= 2 * DEAD
    for m in mapper.optimizer.row_state()["colors"]:
        assert float(m[touched].abs().max()) == 0 and float(m[~touched].abs().max()) > 0


def test_sources_share_their_opacity_with_their_copies():
    gm = map_with_dead_gaussians()
    mapper = make_mapper(gm, refine_every=1, grow_fraction=0.0, jitter=False)
    mapper.optimize(1)
    o = gm.opacities.detach()
    # Every source with k copies now has opacity 1 - (1 - o_before)^(1/(k+1)), o_before = 0.5
    # moved by one Adam step (0.05 in logit).
    sources = (o[DEAD:] < 0.45).sum()
    assert 0 < int(sources) <= DEAD
    for i in range(DEAD):
        twins = torch.nonzero((gm.means.detach() - gm.means.detach()[i]).norm(dim=1) < 1e-6).squeeze(1)
        k = len(twins) - 1
        assert float(o[i]) == pytest.approx(1 - (1 - 0.5) ** (1 / (k + 1)), abs=0.015)


def test_growth_stays_within_the_budget():
    gm = map_with_dead_gaussians()
    mapper = make_mapper(gm, refine_every=2, grow_fraction=0.1, cap_max=N + 45)
    mapper.optimize(2)
    assert len(gm) == N + 30  # 10% of the map
    mapper.optimize(2)
    assert len(gm) == N + 45  # the cap
    mapper.optimize(4)
    assert len(gm) == N + 45
    stats = mapper.strategy.metrics()
    assert stats["mcmc_added"] == 45 and stats["mcmc_refinements"] == 4
    assert not bool(gm.trackable[N:].any())
    assert_state_follows_map(mapper)
    assert all(torch.isfinite(p).all() for p in gm.parameters().values())


def test_finish_prunes_the_dead_and_the_oversized():
    gm = map_with_dead_gaussians()
    with torch.no_grad():
        gm.log_scales[DEAD:DEAD + 5, 0] = math.log(0.3)  # above the sensor's 0.25 m
    mapper = make_mapper(gm, refine_every=1000)
    mapper.finish()
    assert len(gm) == N - DEAD - 5
    assert mapper.strategy.metrics()["mcmc_pruned"] == DEAD + 5
    assert_state_follows_map(mapper)


# -- config and registration ---------------------------------------------------------------------
def test_config_validation_names_the_field():
    for field, value in [("refine_every", 0), ("min_opacity", 1.5), ("grow_fraction", -0.1), ("cap_max", 0),
                         ("max_scale", -1.0)]:
        with pytest.raises(ConfigError, match=f"^mapper.strategy.{field}: expected"):
            MCMCConfig(**{field: value})
    assert MCMCConfig().resolve(RunContext(tuning=DatasetTuning(max_gaussian_scale=0.25))).max_scale == 0.25
    with pytest.raises(ConfigError, match="mapper.strategy.max_scale"):
        MCMCStrategy(MCMCConfig())  # not filled from the dataset's tuning


def test_registered_through_the_entry_point():
    assert any(e.name == "mcmc" and e.value == "slamkit_mcmc" for e in entry_points(group="slamkit"))
    spec = discover().get("strategy", "mcmc")
    assert spec.cls is MCMCStrategy and spec.config is MCMCConfig


@pytest.mark.slow
def test_slamkit_plugins_lists_it():
    exe = Path(sys.executable).with_name("slamkit-plugins")
    out = subprocess.run([str(exe)], capture_output=True, text=True, timeout=300).stdout
    assert "mcmc  [mcmc (slamkit-mcmc)]  slamkit_mcmc.MCMCStrategy" in out


def test_the_strategy_sweep_selects_every_strategy_it_names():
    """slamkit's experiment compare_strategies sweeps mapper/strategy=gsicp,3dgs,mcmc."""
    from importlib.resources import files

    from slamkit.registry.compose import compose_run

    sweep = files("slamkit.experiments").joinpath("experiment", "compare_strategies.yaml")
    names = yaml.safe_load(sweep.read_text())["hydra"]["sweeper"]["params"]["mapper/strategy"].split(",")
    assert "mcmc" in names
    for name in names:
        _, chosen = compose_run(["+experiment=compare_strategies", "dataset=replica", f"mapper/strategy={name}"])
        assert chosen["mapper.strategy"] == name and chosen["mapper"] == "gaussian_splatting"


# -- end to end ---------------------------------------------------------------------------------
@pytest.mark.slow
def test_slamkit_runs_mcmc_on_replica(tmp_path):
    if not REPLICA.is_dir():
        pytest.skip(f"shared data not found at {REPLICA} (`slamkit-data download test-data` fetches it, or set "
                    f"SLAMKIT_DATA)")
    out = tmp_path / "run"
    slamkit = Path(sys.executable).with_name("slamkit")
    proc = subprocess.run(
        [str(slamkit), "dataset=replica", f"dataset.path={REPLICA}", "dataset.max_frames=4",
         "mapper=gaussian_splatting", "mapper/strategy=mcmc", "mapper.strategy.refine_every=10",
         "iterations_per_frame=5",
         "final_iterations=20", "mapper.resolution_scale=0.25", "mapper.eval_every=3",
         "mapper.save_images=0", "output.progress=false", f"hydra.run.dir={out}"],
        cwd=tmp_path, capture_output=True, text=True, timeout=600, env=dict(os.environ, OMP_NUM_THREADS="1"),
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["completed"] and metrics["ate_rmse_m"] < 0.01
    assert metrics["mapping_steps"] == 40 and metrics["mcmc_refinements"] == 4  # 4 frames x 5 + 20 steps
    assert metrics["mcmc_added"] > 0 and metrics["eval_frames"] == 2

