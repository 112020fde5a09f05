"""LPIPS v0.1 with the AlexNet trunk (Zhang et al. 2018), GS-ICP SLAM's third map-quality metric.

The network is written here (docs/dependencies.md, "Written here, and why") and reads two weight
files: AlexNet's ImageNet weights as torchvision publishes them (`ALEXNET_FILE`, in torch's hub
cache or `eval.lpips_backbone=PATH`; the five convolutions of `features`), and the v0.1 linear
layers (`lin0..lin4`) from the installed `lpips` wheel (`LINEAR_MEMBER`). For RGB images x0, x1
in [0, 1], as lpips computes it (`normalize=True`): x <- (2 x - 1 - shift) / scale (lpips'
ScalingLayer); f_l the l-th ReLU output of the features; n_l = f_l / (||f_l||_channels + 1e-10);
LPIPS = sum_l mean_pixels(sum_c w_lc (n0_lc - n1_lc)^2). A mask sets the pixels outside it to 0
in both images first, as GS-ICP SLAM's reference code does.

`lpips_for_evaluation(mode, backbone)`: off gives None; auto gives None without the backbone file
(logging where to put it); on raises a one-line DataError then. A file that is not what is
expected is a one-line DataError naming the file and the key.
"""

from __future__ import annotations

import enum
import hashlib
import importlib.metadata
import logging
from collections.abc import Mapping
from pathlib import Path

import torch
import torch.nn.functional as F

from slamkit.errors import DataError
from slamkit.metrics.images import zero_outside

log = logging.getLogger(__name__)

#: torchvision's ImageNet AlexNet checkpoint: its file name (ending in the first 8 hex digits of
#: its SHA-256) and where torchvision downloads it from.
ALEXNET_FILE = "alexnet-owt-7be5be79.pth"
ALEXNET_SHA256_PREFIX = "7be5be79"
ALEXNET_URL = f"https://download.pytorch.org/models/{ALEXNET_FILE}"
#: The distribution carrying the v0.1 linear weights, the version pinned in pyproject.toml, and
#: the weights' path inside it.
LINEAR_DISTRIBUTION = "lpips"
LINEAR_VERSION = "0.1.4"
LINEAR_MEMBER = "lpips/weights/v0.1/alex.pth"

#: AlexNet's five convolutions as torchvision's `features` holds them: (index in `features`,
#: in channels, out channels, kernel, stride, padding, max-pool 3x3 / 2 before it). Each is
#: followed by a ReLU, whose output is an LPIPS layer.
ALEXNET_CONVS = (
    (0, 3, 64, 11, 4, 2, False),
    (3, 64, 192, 5, 1, 2, True),
    (6, 192, 384, 3, 1, 1, True),
    (8, 384, 256, 3, 1, 1, False),
    (10, 256, 256, 3, 1, 1, False),
)
#: lpips v0.1's ScalingLayer, applied to the image in [-1, 1].
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
#: Added to the channel norm before dividing by it (lpips' normalize_tensor).
NORM_EPS = 1e-10


def backbone_shapes() -> dict[str, tuple[int, ...]]:
    """The state-dict keys and shapes the AlexNet checkpoint must hold (torchvision's names)."""
    shapes = {}
    for index, c_in, c_out, k, _, _, _ in ALEXNET_CONVS:
        shapes[f"features.{index}.weight"] = (c_out, c_in, k, k)
        shapes[f"features.{index}.bias"] = (c_out,)
    return shapes


def linear_shapes() -> dict[str, tuple[int, ...]]:
    """The state-dict keys and shapes of lpips' linear layers (`lin{l}.model.1.weight`; index 1
    because lpips puts a dropout layer at 0)."""
    return {f"lin{layer}.model.1.weight": (1, conv[2], 1, 1) for layer, conv in enumerate(ALEXNET_CONVS)}


def min_image_side() -> int:
    """The smallest image side (pixels) for which every AlexNet layer has at least one pixel."""
    side = 1
    for _, _, _, k, stride, pad, pool in reversed(ALEXNET_CONVS):
        side = (side - 1) * stride + k - 2 * pad
        if pool:
            side = (side - 1) * 2 + 3
    return max(side, 1)


class LPIPS:
    """LPIPS v0.1 (AlexNet) with its weights; `lpips(a, b, mask)` is the distance (see the module
    docstring). backbone, linear: state dicts with at least the keys of `backbone_shapes()` and
    `linear_shapes()` (other keys are ignored); a missing key or a wrong shape is a DataError
    naming `sources` (what the weights were read from: {"backbone": ..., "linear": ...}).
    device: where the network runs. provenance: the files and their SHA-256, for the record."""

    def __init__(self, backbone: Mapping[str, torch.Tensor], linear: Mapping[str, torch.Tensor],
                 device: torch.device | str | None = None, sources: Mapping[str, str] | None = None,
                 provenance: Mapping[str, str] | None = None):
        sources = dict(sources or {})
        self.device = torch.device(device or "cpu")
        self.convs = _checked(backbone, backbone_shapes(), sources.get("backbone", "the AlexNet weights"), self.device)
        self.lins = _checked(linear, linear_shapes(), sources.get("linear", "the LPIPS linear weights"), self.device)
        self.shift = torch.tensor(SHIFT, device=self.device).view(1, 3, 1, 1)
        self.scale = torch.tensor(SCALE, device=self.device).view(1, 3, 1, 1)
        self.provenance = dict(provenance or {})

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The five ReLU outputs of AlexNet's features for images x (N,3,H,W) already scaled."""
        out = []
        for index, _, _, _, stride, pad, pool in ALEXNET_CONVS:
            if pool:
                x = F.max_pool2d(x, kernel_size=3, stride=2)
            x = F.relu(F.conv2d(x, self.convs[f"features.{index}.weight"], self.convs[f"features.{index}.bias"],
                                stride=stride, padding=pad))
            out.append(x)
        return out

    @torch.no_grad()
    def __call__(self, a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> float:
        """LPIPS between two RGB images (H,W,3) in [0, 1] (0 for identical images; lower is more
        alike); pixels outside `mask` (H,W) set to 0 in both first. Each side must be at least
        `min_image_side()` pixels."""
        if a.shape != b.shape or a.dim() != 3 or a.shape[-1] != 3:
            raise ValueError(f"LPIPS needs two (H,W,3) images of one shape: got {tuple(a.shape)} and {tuple(b.shape)}")
        if mask is not None and tuple(mask.shape) != tuple(a.shape[:2]):
            raise ValueError(f"mask shape {tuple(mask.shape)} does not match the image's {tuple(a.shape[:2])}")
        if min(a.shape[:2]) < min_image_side():
            raise ValueError(f"LPIPS needs images at least {min_image_side()} pixels on each side: got "
                             f"{tuple(a.shape[:2])}")
        x = torch.stack([zero_outside(a, mask), zero_outside(b, mask)]).to(self.device).permute(0, 3, 1, 2)
        x = (2 * x - 1 - self.shift) / self.scale
        total = torch.zeros((), dtype=torch.float64)
        for layer, f in enumerate(self.features(x)):
            n = f / (f.norm(dim=1, keepdim=True) + NORM_EPS)
            diff = (n[0] - n[1]) ** 2  # (C,h,w)
            w = self.lins[f"lin{layer}.model.1.weight"].view(-1)
            total += float(torch.einsum("c,chw->hw", w, diff).mean())
        return float(total)


def _checked(state: Mapping[str, torch.Tensor], shapes: dict[str, tuple[int, ...]], source: str,
             device: torch.device) -> dict[str, torch.Tensor]:
    """The tensors of `state` named in `shapes`, checked and as float32 on `device`."""
    out = {}
    for key, shape in shapes.items():
        if key not in state:
            raise DataError(f"{source}: no {key!r} in it (expected a {shape} tensor)")
        value = state[key]
        if not isinstance(value, torch.Tensor) or tuple(value.shape) != shape:
            got = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
            raise DataError(f"{source}: {key!r} is {got}, expected {shape}")
        if not torch.isfinite(value).all():
            raise DataError(f"{source}: {key!r} has non-finite values")
        out[key] = value.detach().to(device=device, dtype=torch.float32)
    return out


def default_backbone_path() -> Path:
    """Where torchvision keeps its AlexNet checkpoint: torch's hub cache (`$TORCH_HOME/hub`,
    by default ~/.cache/torch/hub) / checkpoints / ALEXNET_FILE."""
    return Path(torch.hub.get_dir()) / "checkpoints" / ALEXNET_FILE


def installed_linear_path() -> Path | None:
    """The v0.1 AlexNet linear weights inside the installed `lpips` distribution, found through
    its metadata (the package itself is never imported); None when it is not installed or the
    file is not in it."""
    try:
        dist = importlib.metadata.distribution(LINEAR_DISTRIBUTION)
    except importlib.metadata.PackageNotFoundError:
        return None
    path = Path(dist.locate_file(LINEAR_MEMBER))
    return path if path.is_file() else None


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _load_state(path: Path) -> Mapping[str, torch.Tensor]:
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is one line naming it
        reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise DataError(f"{path}: not a readable torch state dict ({reason})") from None
    if not isinstance(state, Mapping):
        raise DataError(f"{path}: holds a {type(state).__name__}, expected a state dict of tensors")
    return state


def load_lpips(backbone: str | Path | None = None, linear: str | Path | None = None,
               device: torch.device | str | None = None) -> LPIPS:
    """LPIPS with its weights read from files. backbone: torchvision's AlexNet checkpoint (None:
    `default_backbone_path()`); linear: lpips' v0.1 alex.pth (None: the installed `lpips`
    wheel's). A file missing, unreadable or not of the expected keys and shapes is a one-line
    DataError naming it. A backbone whose SHA-256 does not start as torchvision's file name says
    is used, with a warning: its distances are not comparable with published LPIPS."""
    backbone_path = Path(backbone) if backbone is not None else default_backbone_path()
    if not backbone_path.is_file():
        raise DataError(missing_backbone_message(backbone_path))
    if linear is None:
        linear_path = installed_linear_path()
        if linear_path is None:
            raise DataError(missing_linear_message())
    else:
        linear_path = Path(linear)
        if not linear_path.is_file():
            raise DataError(f"{linear_path}: no such file (expected lpips' v0.1 AlexNet linear weights, "
                            f"{LINEAR_MEMBER} in the lpips=={LINEAR_VERSION} wheel)")
    backbone_sha = _sha256(backbone_path)
    if not backbone_sha.startswith(ALEXNET_SHA256_PREFIX):
        log.warning("%s: SHA-256 %s... is not torchvision's %s (%s...): LPIPS with it is not comparable with "
                    "published values", backbone_path, backbone_sha[:8], ALEXNET_FILE, ALEXNET_SHA256_PREFIX)
    return LPIPS(_load_state(backbone_path), _load_state(linear_path), device=device,
                 sources={"backbone": str(backbone_path), "linear": str(linear_path)},
                 provenance={"backbone": str(backbone_path), "backbone_sha256": backbone_sha,
                             "linear": str(linear_path), "linear_sha256": _sha256(linear_path)})


def missing_backbone_message(path: Path) -> str:
    """One line: the AlexNet checkpoint is not at `path`, and how to get it."""
    return (f"LPIPS needs torchvision's AlexNet ImageNet weights {ALEXNET_FILE}, not found at {path}: download "
            f"{ALEXNET_URL} into {default_backbone_path().parent}/ (torch's hub cache) or give "
            f"eval.lpips_backbone=PATH")


def missing_linear_message() -> str:
    """One line: the lpips wheel with the v0.1 linear weights is not installed, and how to get it."""
    return (f"LPIPS needs the v0.1 linear weights of the lpips package ({LINEAR_MEMBER}), which is not installed: "
            f"pip install --no-deps lpips=={LINEAR_VERSION} (or pip install 'slamkit[lpips]')")


class LpipsMode(enum.Enum):
    """auto: LPIPS when its weights are there, else none (said once). on: LPIPS or a one-line
    error. off: no LPIPS."""

    auto = "auto"
    on = "on"
    off = "off"


_told: set[str] = set()


def lpips_for_evaluation(mode: LpipsMode | str = LpipsMode.auto, backbone: str | Path | None = None,
                         device: torch.device | str | None = None) -> LPIPS | None:
    """The LPIPS a run evaluates with, by `mode` (eval.lpips) and `backbone` (eval.lpips_backbone,
    None = torch's hub cache): None when off, or when auto and a weight file is missing from
    where it is looked for by default (logged once per missing file, naming it and how to get
    it); the one-line DataError when on and one is missing, or when `backbone` is given and is
    not a file. A file present but wrong raises in both auto and on."""
    mode = LpipsMode(mode)
    if mode is LpipsMode.off:
        return None
    if backbone is not None and not Path(backbone).is_file():  # a path given is never skipped
        raise DataError(missing_backbone_message(Path(backbone)))
    backbone_path = Path(backbone) if backbone is not None else default_backbone_path()
    missing = note = None
    if not backbone_path.is_file():
        missing = missing_backbone_message(backbone_path)
        note = f"no AlexNet weights at {backbone_path} (download {ALEXNET_URL} or give eval.lpips_backbone=PATH)"
    elif installed_linear_path() is None:
        missing = missing_linear_message()
        note = f"its v0.1 weights not installed (pip install --no-deps lpips=={LINEAR_VERSION})"
    if missing is None:
        return load_lpips(backbone_path, device=device)
    if mode is LpipsMode.on:
        raise DataError(missing)
    if missing not in _told:  # once per process: once per sweep of the basic launcher
        _told.add(missing)
        log.warning("LPIPS null: %s; eval.lpips=off silences this", note)
    return None
