"""The optimisers (`optimizer=adam|visible_adam`) against torch.optim.Adam on the same rows."""

from __future__ import annotations

import pytest
import torch

from slamkit.map.gaussian_map import PARAMETERS
from slamkit_plugins.mappers.gaussian_splatting.optimizer.adam import AdamConfig, TorchAdam
from slamkit_plugins.mappers.gaussian_splatting.optimizer.visible_adam import Kernels, VisibleAdam, VisibleAdamConfig

SHAPES = {"means": (3,), "quats": (4,), "log_scales": (3,), "opacity_logits": (), "colors": (3,)}
LRS = AdamConfig().learning_rates()


def params(n: int, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {k: torch.randn((n,) + s, generator=g).requires_grad_(True) for k, s in SHAPES.items()}


def grads(n: int, seed: int, zero_rows: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(1000 + seed)
    out = {k: torch.randn((n,) + s, generator=g) for k, s in SHAPES.items()}
    if zero_rows is not None:
        for v in out.values():
            v[zero_rows] = 0
    return out


def reference(p: dict[str, torch.Tensor]) -> torch.optim.Adam:
    """torch.optim.Adam with the plugins' per-parameter learning rates and eps."""
    return torch.optim.Adam([{"params": [p[k]], "lr": LRS[k]} for k in PARAMETERS], eps=1e-15)


def reference_step(opt: torch.optim.Adam, p: dict, g: dict) -> None:
    for k in PARAMETERS:
        p[k].grad = g[k].clone()
    opt.step()


def close(a: dict, b: dict, steps: int) -> None:
    """Equal to float precision: each step may round the update's sum differently by one unit in
    the last place of the parameters' magnitude."""
    for k in PARAMETERS:
        ulp = torch.finfo(torch.float32).eps * float(b[k].detach().abs().max())
        torch.testing.assert_close(a[k].detach(), b[k].detach(), rtol=0, atol=steps * ulp, msg=k)


def visible(kernels: str, **fields) -> VisibleAdam:
    return VisibleAdam(VisibleAdamConfig(kernels=Kernels(kernels), **fields))


KERNELS = ["torch", "compiled"]


@pytest.mark.parametrize("make", [lambda: TorchAdam(AdamConfig()), lambda: TorchAdam(AdamConfig(fused=False)),
                                  lambda: visible("torch"),
                                  lambda: visible("compiled"), lambda: visible("torch", only_visible=False),
                                  lambda: visible("compiled", only_visible=False)],
                         ids=["adam", "adam_unfused", "visible_adam", "visible_adam_compiled", "visible_adam_dense",
                              "visible_adam_dense_compiled"])
def test_every_row_seen_every_step_is_torch_adam(make):
    ours, theirs = params(50), params(50)
    optimizer, ref = make(), reference(theirs)
    for step in range(12):
        g = grads(50, step)
        with torch.no_grad():
            optimizer.step(ours, g)
        reference_step(ref, theirs, g)
    close(ours, theirs, 12)
    assert optimizer.num_rows() == 50


@pytest.mark.parametrize("kernels", KERNELS)
def test_visible_adam_leaves_unseen_rows_alone_and_counts_steps_per_row(kernels):
    ours, theirs = params(40), params(40)
    optimizer = visible(kernels)
    hidden = torch.arange(40) >= 30  # rows 30..39 never rendered
    before = {k: v.detach()[hidden].clone() for k, v in ours.items()}
    ref = reference({k: v[:30].detach().clone().requires_grad_(True) for k, v in theirs.items()})
    seen = {k: ref.param_groups[i]["params"][0] for i, k in enumerate(PARAMETERS)}
    for step in range(8):
        g = grads(40, step, zero_rows=hidden)
        optimizer.step(ours, g)
        reference_step(ref, seen, {k: v[:30] for k, v in g.items()})
    for k in PARAMETERS:
        assert torch.equal(ours[k].detach()[hidden], before[k]), k  # untouched
    close({k: v[:30] for k, v in ours.items()}, seen, 8)  # the seen rows: Adam on those rows alone
    steps = optimizer.row_state()["steps"][0]
    assert torch.equal(steps, torch.where(hidden, 0.0, 8.0)) and optimizer.last_updated_rows == 30


@pytest.mark.parametrize("kernels", KERNELS)
def test_a_late_row_starts_like_a_fresh_adam_with_row_bias_correction(kernels):
    """bias_correction=row: a row appended after 20 steps (zero state) moves on its first update
    as a fresh Adam moves a parameter (lr * g / |g|): its own step count bias-corrects it."""
    from slamkit_plugins.mappers.gaussian_splatting.optimizer.visible_adam import BiasCorrection

    p = params(10)
    optimizer = visible(kernels, bias_correction=BiasCorrection["row"])
    for step in range(20):
        optimizer.step(p, grads(10, step))
    optimizer.edit_rows(lambda name, v: torch.cat([v, torch.zeros((1,) + tuple(v.shape[1:]))]))
    p = {k: torch.cat([v.detach(), torch.zeros((1,) + SHAPES[k])]).requires_grad_(True) for k, v in p.items()}
    g = grads(11, 99)
    before = p["colors"].detach()[10].clone()
    optimizer.step(p, g)
    expected = before - LRS["colors"] * torch.sign(g["colors"][10])
    torch.testing.assert_close(p["colors"].detach()[10], expected, rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize("make", [lambda: TorchAdam(AdamConfig()), lambda: visible("torch"),
                                  lambda: visible("compiled")], ids=["adam", "visible_adam", "visible_adam_compiled"])
def test_removing_rows_through_edit_rows_keeps_the_others_on_course(make):
    """Rows 0-9 removed after 5 steps: the other 30 continue exactly as torch.optim.Adam run on
    them alone."""
    ours, theirs = params(40), params(40)
    optimizer, ref = make(), reference({k: v[10:].detach().clone().requires_grad_(True) for k, v in theirs.items()})
    kept = {k: ref.param_groups[i]["params"][0] for i, k in enumerate(PARAMETERS)}
    for step in range(10):
        g = grads(40, step)
        if step == 5:
            keep = torch.arange(40) >= 10
            optimizer.edit_rows(lambda name, v: v[keep])
            ours = {k: v.detach()[keep].requires_grad_(True) for k, v in ours.items()}  # the map's new tensors
        optimizer.step(ours, g if step < 5 else {k: v[10:] for k, v in g.items()})
        reference_step(ref, kept, {k: v[10:] for k, v in g.items()})
    close(ours, kept, 10)
    assert optimizer.num_rows() == 30


def test_learning_rates_are_validated():
    from slamkit.errors import ConfigError

    with pytest.raises(ConfigError, match="mapper.optimizer.lr_means"):
        AdamConfig(lr_means=-1.0)
    with pytest.raises(ConfigError, match="mapper.optimizer.eps"):
        VisibleAdamConfig(eps=0.0)


def test_the_compiled_kernel_equals_the_torch_reference_on_a_long_sparse_run():
    """200 steps, a random third of the rows seen at each, rows removed and appended between
    steps: the compiled and torch visible-Adam paths stay equal to float precision."""
    a, b = params(500), params(500)
    opts = {"torch": visible("torch"), "compiled": visible("compiled")}
    g = torch.Generator().manual_seed(5)
    for step in range(200):
        n = len(a["means"])
        hidden = torch.rand(n, generator=g) > 0.33
        grad = grads(n, step, zero_rows=hidden)
        opts["torch"].step(a, grad)
        opts["compiled"].step(b, grad)
        if step % 50 == 25:  # the map loses 10 rows and gains 20
            keep = torch.ones(n, dtype=torch.bool)
            keep[torch.randperm(n, generator=g)[:10]] = False
            for o in opts.values():
                o.edit_rows(lambda name, v: torch.cat([v[keep], torch.zeros((20,) + tuple(v.shape[1:]))]))
            new = params(20, seed=step)
            a = {k: torch.cat([v.detach()[keep], new[k].detach()]).requires_grad_(True) for k, v in a.items()}
            b = {k: torch.cat([v.detach()[keep], new[k].detach()]).requires_grad_(True) for k, v in b.items()}
    close(b, a, 200)
    assert torch.equal(opts["torch"].row_state()["steps"][0], opts["compiled"].row_state()["steps"][0])


@pytest.mark.parametrize("kernels", KERNELS)
def test_global_bias_correction_on_rows_seen_every_step_is_torch_adam_too(kernels):
    """bias_correction=global (gsplat's SelectiveAdam): the optimiser's step count for every row;
    a row that joins late takes that count, as in torch.optim.Adam."""
    from slamkit_plugins.mappers.gaussian_splatting.optimizer.visible_adam import BiasCorrection

    ours, theirs = params(30), params(30)
    optimizer, ref = visible(kernels, bias_correction=BiasCorrection["global"]), reference(theirs)
    for step in range(6):
        g = grads(30, step)
        optimizer.step(ours, g)
        reference_step(ref, theirs, g)
    close(ours, theirs, 6)


def test_adam_takes_gradients_in_any_layout():
    """An expanded (stride-0) or transposed gradient updates as its contiguous copy does (torch's
    fused kernel read such a gradient as laid out like its parameter: NaN moments)."""
    ours, theirs = params(30), params(30)
    optimizer, ref = TorchAdam(AdamConfig()), reference(theirs)
    for step in range(3):
        g = grads(30, step)
        odd = {k: v[:1].expand_as(v) if k in ("quats", "colors") else v for k, v in g.items()}
        with torch.no_grad():
            optimizer.step(ours, odd)
        reference_step(ref, theirs, {k: v.contiguous() for k, v in odd.items()})
    close(ours, theirs, 3)
    assert all(torch.isfinite(v).all() for v in ours.values())
