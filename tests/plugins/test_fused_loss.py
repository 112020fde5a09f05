"""The fused RGB-D mapping loss (`slamkit_plugins.mappers.gaussian_splatting.loss.fused_rgbd_loss`) against its torch
reference (pytorch_msssim + autograd): value and both gradients on random and real keyframes,
several weightings, thread-count independence, a finite-difference check, edge cases, input
validation and the fallback without a compiler."""

from __future__ import annotations

import os
import shutil
import warnings

import pytest
import torch
import torch.nn.functional as F

import slamkit_plugins.mappers.gaussian_splatting.loss.fused_rgbd_loss as loss_module
from slamkit.formats.images import read_depth, read_rgb
from slamkit.native import NativeLibrary
from slamkit_plugins.mappers.gaussian_splatting.loss.fused_rgbd_loss import (
    fused_rgbd_loss,
    kernel_rgbd_loss,
    torch_rgbd_loss,
)

from support.data import REPLICA, TUM, require_data
from support.loss_inputs import loss_and_grads, random_inputs

LOSS_TOL = 1e-6   # relative error of the loss value
GRAD_TOL = 1e-5   # ||fused - torch|| / ||torch|| for each gradient
WEIGHTS = [
    dict(),                                            # the mapper's defaults 0.8, 0.2, 0.1
    dict(w_ssim=0.0),
    dict(w_depth=0.0),
    dict(w_l1=0.0, w_ssim=1.0, w_depth=0.0),
    dict(w_l1=1.0, w_ssim=0.0, w_depth=0.0),
    dict(w_l1=0.3, w_ssim=0.5, w_depth=2.0, depth_unit=4.0),
]


def without_compiler(test):
    """Marks a test that runs (and must pass) where the kernel cannot be built."""
    test.needs_compiler = False
    return test


@pytest.fixture(autouse=True)
def compiled(request):
    if not getattr(request.function, "needs_compiler", True):
        return
    if not loss_module.available():
        if shutil.which(os.environ.get("CXX", "c++")):  # a compiler is there: a failed build is a bug
            pytest.fail(f"the fused loss failed to build: {loss_module.LIBRARY.error}")
        pytest.skip(f"no C++ compiler on this machine ({loss_module.LIBRARY.error})")


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.double(), b.double()
    return float((a - b).norm() / b.norm()) if float(b.norm()) > 0 else float(a.norm())


def assert_agrees(inputs, **kw):
    """The fused loss against the reference in float64 (the definition, computed exactly
    enough) and in float32 (what the mapper runs today). On real images torch's float32 result
    is itself up to ~3e-5 from the float64 one in the gradients (SSIM's variances F(x x) -
    F(x)^2 cancel on flat regions) and ~1e-5 in the value; the kernel computes those maps in
    double, so it is held to the tolerance against float64, and against float32 to the
    tolerance plus float32's own error."""
    fused = loss_and_grads(fused_rgbd_loss, inputs, **kw)
    ref = loss_and_grads(torch_rgbd_loss, inputs, **kw)
    exact = loss_and_grads(torch_rgbd_loss, inputs, dtype=torch.float64, **kw)
    assert fused[0].dtype == torch.float32 and fused[0].dim() == 0
    for k, tol in ((0, LOSS_TOL), (1, GRAD_TOL), (2, GRAD_TOL)):
        assert rel(fused[k], exact[k]) < tol, k
        assert rel(fused[k], ref[k]) < tol + rel(ref[k], exact[k]), k
    return fused, ref, exact


def area_down(rgb, depth, size):
    """Colour by area averaging; depth by the mean of each output pixel's valid pixels (0
    where fewer than half are valid), as the mapper prepares its keyframes."""
    image = torch.from_numpy(rgb).float() / 255
    image = F.interpolate(image.permute(2, 0, 1)[None], size=size, mode="area")[0].permute(1, 2, 0).contiguous()
    d = torch.from_numpy(depth)
    valid = (d > 0).float()[None, None]
    num = F.interpolate(d[None, None] * valid, size=size, mode="area")[0, 0]
    den = F.interpolate(valid, size=size, mode="area")[0, 0]
    return image, torch.where(den >= 0.5, num / den.clamp_min(1e-12), torch.zeros_like(num)).contiguous()


def real_inputs(name: str):
    """Keyframe = frame 0; "render" = a later frame of the same sequence (real image statistics:
    flat walls, edges, saturated and dark regions, holes in the depth)."""
    if name == "replica":
        root = require_data(REPLICA) / "results"
        files = [(root / f"frame{i:06d}.jpg", root / f"depth{i:06d}.png") for i in (0, 5)]
        scale, size = 6553.5, (340, 600)
    else:
        root = require_data(TUM)
        rgbs, depths = sorted((root / "rgb").iterdir()), sorted((root / "depth").iterdir())
        files = [(rgbs[i], depths[i]) for i in (0, 3)]
        scale, size = 5000.0, (240, 320)
    (image, observed), (color, depth) = (area_down(read_rgb(c), read_depth(d, scale), size) for c, d in files)
    return color, depth, image, observed


@pytest.mark.parametrize("seed,H,W", [(0, 48, 64), (1, 37, 53), (2, 11, 11), (3, 11, 40), (4, 70, 17)])
@pytest.mark.parametrize("kw", WEIGHTS)
def test_matches_torch_on_random_images(seed, H, W, kw):
    assert_agrees(random_inputs(H, W, seed), **kw)


@pytest.mark.parametrize("name", ["replica", "tum"])
@pytest.mark.parametrize("kw", WEIGHTS[:3])
def test_matches_torch_on_real_keyframes(name, kw):
    inputs = real_inputs(name)
    assert inputs[0].shape == ((340, 600, 3) if name == "replica" else (240, 320, 3))
    if name == "tum":
        assert 0.3 < float((inputs[3] > 0).float().mean()) < 1.0  # holes: the mask matters
    fused, ref, exact = assert_agrees(inputs, **kw)
    for f, r, e in zip(fused[1:], ref[1:], exact[1:]):  # closer to the exact gradients than torch's float32
        assert rel(f, e) <= rel(r, e) + 1e-7


@pytest.mark.parametrize("shape", [(240, 320), (97, 45), (23, 40), (34, 29)])
def test_identical_for_any_thread_count(shape):
    inputs = random_inputs(*shape, seed=5)
    one = loss_and_grads(fused_rgbd_loss, inputs, num_threads=1)
    for threads in (2, 3, 7):
        many = loss_and_grads(fused_rgbd_loss, inputs, num_threads=threads)
        for a, b in zip(one, many):
            assert torch.equal(a, b), threads


def test_gradient_matches_finite_differences():
    """Central differences of the float64 reference at every input of a small image (away from
    the kinks of |.|) against the kernel's float32 gradient."""
    color, depth, image, observed = (t.double() for t in random_inputs(14, 16, seed=6))
    color = image + torch.where(color >= image, 1, -1) * (0.02 + (color - image).abs())
    depth = observed + torch.where(depth >= observed, 1, -1) * (0.02 + (depth - observed).abs())
    kw = dict(w_l1=0.8, w_ssim=0.2, w_depth=0.5)
    _, gc, gd = loss_and_grads(fused_rgbd_loss, (color, depth, image, observed), **kw)
    h = 1e-6

    def numeric(which: int) -> torch.Tensor:
        x = (color, depth)[which]
        out = torch.empty(x.numel(), dtype=torch.float64)
        for k in range(x.numel()):
            f = []
            for step in (h, -h):
                args = [color, depth]
                args[which] = x.reshape(-1).clone().index_add_(0, torch.tensor([k]), torch.tensor([step],
                                                                dtype=torch.float64)).reshape(x.shape)
                f.append(float(torch_rgbd_loss(*args, image, observed, **kw)))
            out[k] = (f[0] - f[1]) / (2 * h)
        return out.reshape(x.shape)

    assert rel(gc, numeric(0)) < 1e-5
    assert rel(gd, numeric(1)) < 1e-5


def test_no_valid_depth_uses_every_pixel_and_drops_the_depth_term():
    color, depth, image, observed = random_inputs(30, 40, seed=7)
    observed.zero_()
    (loss, gc, gd), _, _ = assert_agrees((color, depth, image, observed))
    assert torch.count_nonzero(gd) == 0 and torch.count_nonzero(gc) > 0.9 * gc.numel()
    terms, _, _ = kernel_rgbd_loss(color, depth, image, observed, (0.8, 0.2, 0.1, 10.0), 1, grads=False)
    assert terms[3] == 0 and terms[4] == 30 * 40
    assert abs(terms[1] - float((color - image).abs().mean())) < 1e-6


@pytest.mark.parametrize("valid", [1, 2])
def test_a_few_valid_pixels(valid):
    color, depth, image, observed = random_inputs(25, 31, seed=8)
    keep = torch.zeros(25 * 31, dtype=torch.bool)
    keep[torch.randperm(25 * 31, generator=torch.Generator().manual_seed(valid))[:valid]] = True
    observed[~keep.reshape(25, 31)] = 0
    (_, gc, gd), _, _ = assert_agrees((color, depth, image, observed))
    assert torch.count_nonzero(gd) == valid  # only the valid pixels see a depth gradient


def test_loss_only_without_gradients_and_under_no_grad():
    inputs = random_inputs(40, 50, seed=9)
    terms, gc, gd = kernel_rgbd_loss(*inputs, (0.8, 0.2, 0.1, 10.0), 1, grads=False)
    assert gc is None and gd is None
    ref = torch_rgbd_loss(*inputs)
    assert rel(torch.tensor(terms[0]), ref) < LOSS_TOL
    with torch.no_grad():
        assert rel(fused_rgbd_loss(*inputs), ref) < LOSS_TOL
    assert terms[2] == pytest.approx(1 - (float(ref) - 0.8 * terms[1] - 0.1 * terms[3]) / 0.2, rel=1e-5)


def test_backward_scales_by_the_incoming_gradient():
    inputs = random_inputs(20, 24, seed=10)
    _, gc, gd = loss_and_grads(fused_rgbd_loss, inputs)
    color, depth = inputs[0].clone().requires_grad_(), inputs[1].clone().requires_grad_()
    (3.0 * fused_rgbd_loss(color, depth, *inputs[2:])).backward()
    assert torch.allclose(color.grad, 3 * gc) and torch.allclose(depth.grad, 3 * gd)


@without_compiler
@pytest.mark.parametrize("fn", [fused_rgbd_loss, torch_rgbd_loss])
@pytest.mark.parametrize("H,W", [(10, 40), (40, 10), (5, 5)])
def test_too_small_images_are_refused(fn, H, W):
    color, depth, image, observed = torch.rand(H, W, 3), torch.rand(H, W), torch.rand(H, W, 3), torch.rand(H, W)
    with pytest.raises(ValueError, match=f"{W}x{H} px"):
        fn(color, depth, image, observed)


@without_compiler
def test_inputs_are_validated():
    color, depth, image, observed = random_inputs(20, 30, seed=11)
    bad = [
        ((color[..., :2], depth, image, observed), "color has shape"),
        ((color, depth[:, :-1], image, observed), "depth has shape"),
        ((color, depth, image.permute(1, 0, 2), observed), "image has shape"),
        ((color, depth, image, observed[None]), "observed_depth has shape"),
        ((color.double(), depth, image, observed), "color is torch.float64"),
    ]
    for args, match in bad:
        with pytest.raises(ValueError, match=match):
            fused_rgbd_loss(*args)
    with pytest.raises(ValueError, match="depth_unit"):
        fused_rgbd_loss(color, depth, image, observed, depth_unit=0.0)


def test_non_contiguous_inputs_are_accepted():
    color, depth, image, observed = random_inputs(30, 20, seed=12)
    t = [x.transpose(0, 1).contiguous().transpose(0, 1) for x in (color, depth, image, observed)]
    assert not t[0].is_contiguous()
    a = loss_and_grads(fused_rgbd_loss, t)
    b = loss_and_grads(fused_rgbd_loss, (color, depth, image, observed))
    assert all(torch.equal(x, y) for x, y in zip(a, b))


@without_compiler
def test_without_a_compiler_it_warns_once_and_uses_torch(monkeypatch):
    monkeypatch.setenv("CXX", "no-such-compiler-slamkit")
    monkeypatch.setattr(loss_module, "LIBRARY", NativeLibrary(loss_module.SOURCE, "fused RGB-D loss",
                                                               loss_module.ABI_VERSION, loss_module._declare))
    monkeypatch.setattr(loss_module, "_warned", False)
    inputs = random_inputs(20, 30, seed=13)
    with pytest.warns(RuntimeWarning, match="no C\\+\\+ compiler found.*using the torch loss"):
        out = fused_rgbd_loss(*inputs)
    assert not loss_module.available()
    assert torch.equal(out, torch_rgbd_loss(*inputs))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fused_rgbd_loss(*inputs)  # once only


def test_a_second_backward_through_the_same_graph_is_refused():
    color, depth, image, observed = random_inputs(20, 24, seed=14)
    color.requires_grad_()
    loss = fused_rgbd_loss(color, depth, image, observed)
    loss.backward(retain_graph=True)
    with pytest.raises(RuntimeError, match="second time"):
        loss.backward()


def test_portable_build_agrees_with_the_native_one(monkeypatch, tmp_path):
    """The build without -march=native (no AVX-512: the generic vector code, no FMA) computes the
    same loss to rounding."""
    monkeypatch.setenv("SLAMKIT_CACHE", str(tmp_path))
    inputs = random_inputs(45, 70, seed=15)
    native = loss_and_grads(fused_rgbd_loss, inputs)
    portable = NativeLibrary(loss_module.SOURCE, "fused RGB-D loss", loss_module.ABI_VERSION, loss_module._declare,
                             native=False)
    monkeypatch.setattr(loss_module, "LIBRARY", portable)
    assert loss_module.available(), portable.error
    other = loss_and_grads(fused_rgbd_loss, inputs)
    assert rel(other[0], native[0]) < 1e-6
    assert rel(other[1], native[1]) < 1e-5 and rel(other[2], native[2]) < 1e-6


def test_non_finite_inputs_give_a_non_finite_loss_as_torch():
    """The mapper skips a step whose loss is not finite: NaN in the render must reach the loss
    (also under the mask, where torch's c * m is NaN too)."""
    color, depth, image, observed = random_inputs(24, 30, seed=16)
    observed[3, 4] = 0
    for where in [(3, 4), (10, 11)]:
        bad = color.clone()
        bad[where][1] = float("nan")
        assert torch.isnan(fused_rgbd_loss(bad, depth, image, observed))
        assert torch.isnan(torch_rgbd_loss(bad, depth, image, observed))
