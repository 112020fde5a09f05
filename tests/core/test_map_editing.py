"""The shared row operations (slamkit.roles.map_edit.MapEdit) keep the optimiser's and the strategy's
per-row state aligned with the map, whatever the optimiser."""

from __future__ import annotations

import math

import pytest
import torch

from slamkit.map.gaussian_map import PARAMETERS
from slamkit.roles.map_edit import MapEdit
from slamkit_plugins.mappers.gaussian_splatting.optimizer.adam import AdamConfig, TorchAdam
from slamkit_plugins.mappers.gaussian_splatting.optimizer.visible_adam import VisibleAdam, VisibleAdamConfig

from support.mapping_scenes import N, plane_scene, rows, start_map

OPTIMIZERS = {"adam": lambda: TorchAdam(AdamConfig()), "visible_adam": lambda: VisibleAdam(VisibleAdamConfig())}


def trained_edit(optimizer_name: str, steps: int = 3) -> MapEdit:
    """A map of N Gaussians, `steps` optimiser steps on random gradients, strategy state = row index."""
    gm = start_map()
    edit = MapEdit(gm, OPTIMIZERS[optimizer_name](), {"row": torch.arange(N, dtype=torch.float32)})
    g = torch.Generator().manual_seed(0)
    for _ in range(steps):
        grads = {k: torch.randn(p.shape, generator=g) for k, p in gm.parameters().items()}
        edit.sync()
        edit.optimizer.step(gm.parameters(), grads)
    return edit


def moments(edit: MapEdit) -> dict[str, torch.Tensor]:
    """Each parameter's first state tensor (Adam's first moment)."""
    return {k: v[0] for k, v in edit.optimizer.row_state().items() if k in PARAMETERS}


def aligned(edit: MapEdit) -> None:
    n = len(edit.map)
    for name, tensors in edit.optimizer.row_state().items():
        assert all(t.shape[0] == n for t in tensors), name
    assert all(v.shape[0] == n for v in edit.state.values())


@pytest.mark.parametrize("opt", list(OPTIMIZERS))
def test_remove_drops_the_rows_state_and_bumps_the_structure_version(opt):
    edit = trained_edit(opt)
    before, structure = moments(edit), edit.map.structure_version
    drop = torch.zeros(N, dtype=torch.bool)
    drop[::3] = True
    assert edit.remove(drop) == int(drop.sum())
    aligned(edit)
    for k, m in moments(edit).items():
        torch.testing.assert_close(m, before[k][~drop], rtol=0, atol=0)
    assert torch.equal(edit.state["row"], torch.arange(N, dtype=torch.float32)[~drop])
    assert edit.map.structure_version == structure + 1


@pytest.mark.parametrize("opt", list(OPTIMIZERS))
def test_append_and_duplicate_give_new_rows_zero_moments(opt):
    edit = trained_edit(opt)
    before = moments(edit)
    added = edit.append(rows(*plane_scene(seed=3, n=20)))
    assert added == slice(N, N + 20)
    copies = edit.duplicate(torch.tensor([5, 5, 7]))
    assert copies == slice(N + 20, N + 23)
    aligned(edit)
    for k, m in moments(edit).items():
        torch.testing.assert_close(m[:N], before[k], rtol=0, atol=0)
        assert not m[N:].any()
    assert edit.state["row"][N:N + 20].tolist() == [0.0] * 20  # new rows: zero statistics
    assert edit.state["row"][N + 20:].tolist() == [5.0, 5.0, 7.0]  # copies: their originals'
    torch.testing.assert_close(edit.map.means.detach()[N + 20:], edit.map.means.detach()[[5, 5, 7]])


@pytest.mark.parametrize("opt", list(OPTIMIZERS))
def test_split_replaces_each_parent_by_smaller_children_drawn_from_it(opt):
    edit = trained_edit(opt)
    parents = torch.zeros(N, dtype=torch.bool)
    parents[[1, 4]] = True
    mean4 = edit.map.means.detach()[4].clone()
    scale4 = edit.map.scales.detach()[4].clone()
    assert edit.split(parents, 2, 1.6, torch.Generator().manual_seed(0)) == 2
    assert len(edit.map) == N + 2
    aligned(edit)
    children = edit.map.rows(torch.arange(N - 2, N + 2))
    torch.testing.assert_close(torch.exp(children.log_scales[[1, 3]]), (scale4 / 1.6).expand(2, 3))
    assert ((children.means[[1, 3]] - mean4).abs() < 4 * scale4.max()).all()
    assert sorted(edit.state["row"][-4:].tolist()) == [1.0, 1.0, 4.0, 4.0]


@pytest.mark.parametrize("opt", list(OPTIMIZERS))
def test_reset_opacity_clamps_and_forgets_only_the_opacity_moments(opt):
    edit = trained_edit(opt)
    before = moments(edit)
    edit.reset_opacity(0.01)
    assert float(edit.map.opacities.detach().max()) <= 0.01 + 1e-6
    after = moments(edit)
    assert not after["opacity_logits"].any()
    torch.testing.assert_close(after["colors"], before["colors"], rtol=0, atol=0)


def test_update_overwrites_rows_and_restarts_their_state():
    edit = trained_edit("visible_adam")
    new = rows(*plane_scene(seed=9, n=2))
    edit.update(torch.tensor([0, 10]), new)
    torch.testing.assert_close(edit.map.means.detach()[[0, 10]], new.means)
    steps = edit.optimizer.row_state()["steps"][0]
    assert steps[0] == steps[10] == 0 and steps[1] == 3
    assert math.isclose(float(edit.map.opacities.detach()[0]), 0.9, rel_tol=1e-6)


def test_rows_appended_outside_are_picked_up_and_rows_lost_outside_reset_the_state(caplog):
    edit = trained_edit("adam")
    edit.map.append(rows(*plane_scene(seed=3, n=5)))  # a keyframe, through the core
    edit.sync()
    aligned(edit)
    keep = torch.ones(len(edit.map), dtype=torch.bool)
    keep[:4] = False
    edit.map.keep(keep)  # not through MapEdit: state can no longer be matched to rows
    edit.sync()
    assert edit.optimizer.num_rows() == 0 and "optimiser and strategy state reset" in caplog.text


def test_counts_say_what_the_operations_added_removed_and_replaced():
    edit = trained_edit("adam")
    assert edit.counts == {"appended": 0, "cloned": 0, "split": 0, "removed": 0, "updated": 0}
    edit.duplicate(torch.tensor([0, 1, 1]))
    mask = torch.zeros(len(edit.map), dtype=torch.bool)
    mask[2:6] = True
    assert edit.split(mask, children=3) == 4  # four parents, each replaced by three children
    drop = torch.zeros(len(edit.map), dtype=torch.bool)
    drop[:5] = True
    edit.remove(drop)
    edit.update(torch.tensor([0, 1]), edit.map.rows(torch.tensor([2, 3])))
    assert edit.counts == {"appended": 0, "cloned": 3, "split": 8, "removed": 5, "updated": 2}
    assert len(edit.map) == N + 3 + 8 - 5
