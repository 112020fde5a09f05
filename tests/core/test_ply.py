"""The Gaussian map's PLY file: standard 3DGS layout, round trip, clear errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from slamkit.errors import DataError
from slamkit.formats.ply import C0, PROPERTIES, load_ply, save_ply
from slamkit.map.gaussian_map import GaussianMap, GaussianRows


def random_map(n: int = 50, seed: int = 0) -> GaussianMap:
    rng = np.random.default_rng(seed)
    gm = GaussianMap()
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    gm.append(GaussianRows.from_shapes(
        rng.normal(size=(n, 3)),
        q,
        rng.uniform(0.001, 0.2, size=(n, 3)),
        rng.uniform(size=(n, 3)),
        rng.uniform(0.01, 0.99, size=n),
        rng.uniform(size=n) > 0.5,
        3,
    ))
    return gm


def read_header(path):
    """Parse the header by hand, as any PLY reader does: (lines, byte offset of the data)."""
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    return raw[:end].decode("ascii").splitlines(), end, raw


def test_round_trip_keeps_every_parameter(tmp_path):
    gm = random_map()
    save_ply(tmp_path / "map.ply", gm)
    back = load_ply(tmp_path / "map.ply")
    assert len(back) == len(gm)
    for name, value in gm.parameters().items():
        torch.testing.assert_close(getattr(back, name), value, rtol=0, atol=1e-6, msg=name)
    assert back.trackable.all() and (back.keyframe_id == -1).all()
    # the covariances the tracker would use are the same
    torch.testing.assert_close(back.covariances(), gm.covariances(), rtol=1e-5, atol=1e-7)


def test_file_is_the_standard_3dgs_layout(tmp_path):
    gm = random_map(7)
    save_ply(tmp_path / "map.ply", gm)
    lines, offset, raw = read_header(tmp_path / "map.ply")
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0"
    assert "element vertex 7" in lines
    props = [line.split() for line in lines if line.startswith("property")]
    assert [p[2] for p in props] == list(PROPERTIES)
    assert all(p[1] == "float" for p in props)
    data = np.frombuffer(raw, dtype="<f4", offset=offset).reshape(7, len(PROPERTIES))
    col = {name: data[:, i] for i, name in enumerate(PROPERTIES)}
    np.testing.assert_allclose(np.c_[col["x"], col["y"], col["z"]], gm.means.detach().numpy(), atol=1e-7)
    np.testing.assert_allclose(col["f_dc_0"], (gm.colors.detach()[:, 0].numpy() - 0.5) / C0, rtol=1e-6)
    np.testing.assert_allclose(col["opacity"], gm.opacity_logits.detach().numpy(), atol=1e-6)  # logit
    np.testing.assert_allclose(col["scale_2"], gm.log_scales.detach()[:, 2].numpy(), atol=1e-6)  # log
    np.testing.assert_allclose(col["rot_0"], gm.quats.detach()[:, 0].numpy(), atol=1e-7)  # w first
    assert (col["nx"] == 0).all()


def test_empty_map_round_trips(tmp_path):
    save_ply(tmp_path / "empty.ply", GaussianMap())
    assert len(load_ply(tmp_path / "empty.ply")) == 0


def test_reads_ascii_doubles_and_extra_properties(tmp_path):
    """Files from other 3DGS tools: any byte order / type, f_rest_* present (ignored)."""
    props = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "f_rest_0", "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    row = [1, 2, 3, 0, 1.0, -1.0, 9, 0.5, -2, -3, -4, 1, 0, 0, 0]
    header = "ply\nformat ascii 1.0\nelement vertex 2\n" + "".join(f"property double {p}\n" for p in props)
    text = header + "end_header\n" + " ".join(map(str, row)) + "\n" + " ".join(map(str, row)) + "\n"
    (tmp_path / "a.ply").write_text(text)
    gm = load_ply(tmp_path / "a.ply")
    assert len(gm) == 2
    torch.testing.assert_close(gm.means.detach()[0], torch.tensor([1.0, 2.0, 3.0]))
    torch.testing.assert_close(gm.colors.detach()[0], torch.tensor([0.5, 0.5 + C0, 0.5 - C0]))
    # big endian binary, float
    dt = np.dtype([(p, ">f4") for p in props])
    data = np.array([tuple(row)], dtype=dt)
    header = "ply\nformat binary_big_endian 1.0\nelement vertex 1\n" + "".join(f"property float {p}\n" for p in props)
    (tmp_path / "b.ply").write_bytes((header + "end_header\n").encode() + data.tobytes())
    torch.testing.assert_close(load_ply(tmp_path / "b.ply").log_scales[0], torch.tensor([-2.0, -3.0, -4.0]))


@pytest.mark.parametrize(
    "content, message",
    [
        (b"hello\n", "not a PLY file"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n", "no end_header"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nproperty float x\nend_header\n", "lacks y, z"),
        (b"ply\nformat weird 1.0\nelement vertex 0\nend_header\n", "malformed"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quux x\nend_header\n", "malformed"),
        (b"ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n3 0 1 2\n",
         "list properties"),
        (b"ply\nformat ascii 1.0\nelement face 0\nend_header\n", "no 'vertex' element"),
    ],
)
def test_malformed_files_raise_data_error(tmp_path, content, message):
    path = tmp_path / "bad.ply"
    path.write_bytes(content)
    with pytest.raises(DataError, match=message) as info:
        load_ply(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_truncated_binary_and_missing_file(tmp_path):
    save_ply(tmp_path / "map.ply", random_map(10))
    raw = (tmp_path / "map.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(raw[:-5])
    with pytest.raises(DataError, match="truncated"):
        load_ply(tmp_path / "cut.ply")
    with pytest.raises(DataError, match="cannot read"):
        load_ply(tmp_path / "nope.ply")


def test_gaussians_with_a_non_finite_parameter_are_left_out_and_counted(tmp_path):
    gm = random_map(10)
    with torch.no_grad():
        gm.means[2, 0] = float("nan")
        gm.log_scales[5, 1] = float("inf")
        gm.opacity_logits[7] = float("-inf")
    assert save_ply(tmp_path / "map.ply", gm) == 3
    back = load_ply(tmp_path / "map.ply")
    kept = [i for i in range(10) if i not in (2, 5, 7)]
    assert len(back) == 7 and torch.isfinite(back.means).all()
    assert torch.allclose(back.means, gm.means.detach()[kept])
    assert save_ply(tmp_path / "empty.ply", GaussianMap()) == 0 and len(load_ply(tmp_path / "empty.ply")) == 0
