"""`slamkit-data download test-data` against a local HTTP server serving the three public archives
rebuilt from the real excerpts (TUM's rgbd_dataset_freiburg1_rpy.tgz, Microsoft's redkitchen.zip
with seq-01.zip inside, NICE-SLAM's Replica.zip), each with frames beyond the excerpt so that
the cut is exercised: the excerpts come out byte-equal to the real ones (7-Scenes: depth and
poses value-equal, colour as the archive's PNGs), sizes are said before any download, a done
excerpt is skipped, a kept archive is cut again without a download, and a cut, wrong or
too-large archive is one line."""

from __future__ import annotations

import dataclasses
import functools
import io
import re
import tarfile
import zipfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from slamkit.cli import data as cli
from slamkit.downloads import excerpts, transfer
from slamkit.progress import Progress
from slamkit.run.build import build_run

from support.data import REPLICA, SEVENSCENES, TUM, require_data
from support.downloads import Server, download, one_line

TUM_PATH = "/freiburg1/rgbd_dataset_freiburg1_rpy.tgz"
REPLICA_PATH, SEVENSCENES_PATH = "/Replica.zip", "/redkitchen.zip"
#: 7-Scenes frames whose colour is the real image (as a PNG); the others carry a small stand-in.
REAL_COLOUR = (300, 301, 650, 998, 999)
#: Bytes of the rebuilt Replica.zip that stand for the scenes the excerpt does not read.
OTHER_SCENES = 40 << 20
#: Files of the real excerpts that record their own staging, not data.
RECORDS = {"README.txt", "MANIFEST.sha256"}


# ---------------------------------------------------------------------------- the archives
def png(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


def tar_gz(files: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz", compresslevel=1) as tar:
        for name, payload in files.items():
            info = tarfile.TarInfo(name)
            info.size = len(payload)
            tar.addfile(info, io.BytesIO(payload))
    return buf.getvalue()


def zipped(files: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as z:
        for name, payload in files.items():
            z.writestr(name, payload)
    return buf.getvalue()


def tum_archive() -> bytes:
    """rgbd_dataset_freiburg1_rpy.tgz as TUM serves it, holding the real excerpt plus a depth frame
    one frame interval before its first colour frame and three frames after its last."""
    top, real = "rgbd_dataset_freiburg1_rpy", require_data(TUM)
    files = {f"{top}/{p.relative_to(real).as_posix()}": p.read_bytes() for p in sorted(real.rglob("*"))
             if p.is_file() and p.name not in RECORDS}
    rgb = (real / "rgb.txt").read_text().splitlines(keepends=True)
    depth = (real / "depth.txt").read_text().splitlines(keepends=True)
    last_rgb, last_depth = float(rgb[-1].split()[0]), float(depth[-1].split()[0])
    first_depth = float(depth[3].split()[0])
    before = f"{first_depth - 0.0332:.6f}"
    depth.insert(3, f"{before} depth/{before}.png\n")
    files[f"{top}/depth/{before}.png"] = (real / depth[4].split()[1]).read_bytes()
    for k in range(1, 4):
        t_rgb, t_depth = f"{last_rgb + 0.0332 * k:.6f}", f"{last_depth + 0.0332 * k:.6f}"
        rgb.append(f"{t_rgb} rgb/{t_rgb}.png\n")
        depth.append(f"{t_depth} depth/{t_depth}.png\n")
        files[f"{top}/rgb/{t_rgb}.png"] = (real / rgb[-1 - k].split()[1]).read_bytes()
        files[f"{top}/depth/{t_depth}.png"] = (real / depth[-1 - k].split()[1]).read_bytes()
    files[f"{top}/rgb.txt"], files[f"{top}/depth.txt"] = "".join(rgb).encode(), "".join(depth).encode()
    return tar_gz(files)


def replica_archive() -> bytes:
    """NICE-SLAM's Replica.zip layout with the real room0 frames 0-19, two more, and a second scene."""
    real = require_data(REPLICA)
    files = {"Replica/cam_params.json": (real / "cam_params.json").read_bytes()}
    traj = (real / "traj.txt").read_bytes().splitlines(keepends=True)
    for i in range(22):
        for kind, ext in (("frame", "jpg"), ("depth", "png")):
            files[f"Replica/room0/results/{kind}{i:06d}.{ext}"] = (real / "results" / f"{kind}{min(i, 19):06d}.{ext}") \
                .read_bytes()
    files["Replica/room0/traj.txt"] = b"".join(traj + traj[-2:])
    files["Replica/room1/traj.txt"] = traj[0]
    files["Replica/office0/results/frame000000.jpg"] = bytes(range(256)) * (OTHER_SCENES // 256)  # the other scenes
    return zipped(files)


def sevenscenes_pose_text(path: Path) -> bytes:
    """A pose file as 7-Scenes writes them: tab-separated, 8 significant digits, 3-digit exponents."""
    rows = np.loadtxt(path)
    text = "".join("\t".join(re.sub(r"e([+-])(\d\d)$", r"e\g<1>0\2", f"{v:.7e}") for v in row) + "\t\n"
                   for row in rows)
    return text.encode()


def sevenscenes_archive() -> bytes:
    """Microsoft's redkitchen.zip layout: redkitchen/seq-01.zip (seq-01/frame-%06d.color.png,
    .depth.png, .pose.txt) holding frames 298-1000, the real depth and poses for 300-999, the
    real colour (as PNG) for REAL_COLOUR and a small stand-in for the others."""
    real = require_data(SEVENSCENES)
    stand_in = png(np.full((48, 64, 3), 128, np.uint8))
    inner = {}
    for i in range(298, 1001):
        source = real / f"frame-{min(max(i, 300), 999):06d}"
        colour = png(np.asarray(Image.open(f"{source}.color.jpg").convert("RGB"))) if i in REAL_COLOUR else stand_in
        inner[f"seq-01/frame-{i:06d}.color.png"] = colour
        inner[f"seq-01/frame-{i:06d}.depth.png"] = Path(f"{source}.depth.png").read_bytes()
        inner[f"seq-01/frame-{i:06d}.pose.txt"] = sevenscenes_pose_text(Path(f"{source}.pose.txt"))
    return zipped({"redkitchen/TrainSplit.txt": b"sequence1\n", "redkitchen/seq-01.zip": zipped(inner)})


@pytest.fixture(scope="module")
def archives() -> dict[str, bytes]:
    return {TUM_PATH: tum_archive(), REPLICA_PATH: replica_archive(), SEVENSCENES_PATH: sevenscenes_archive()}


@pytest.fixture()
def server(archives):
    s = Server()
    s.files.update(archives)
    yield s
    s.close()


def data_files(folder: Path) -> dict[str, Path]:
    return {p.relative_to(folder).as_posix(): p for p in folder.rglob("*") if p.is_file() and p.name not in RECORDS}


def assert_same_files(cut: Path, real: Path) -> None:
    got, expected = data_files(cut), data_files(real)
    assert sorted(got) == sorted(expected)
    for name, path in expected.items():
        assert got[name].read_bytes() == path.read_bytes(), name


# ----------------------------------------------------------------------------------- tests
def test_the_excerpts_are_cut_as_the_real_ones_and_a_second_run_fetches_nothing(server, tmp_path, capsys):
    root = tmp_path / "data"
    status, out, err = download(capsys, "test-data", "--root", str(root), "--base-url", server.url)
    assert status == 0, err
    for path in (TUM_PATH, SEVENSCENES_PATH):  # each size said before its download
        said = out.index(f"({cli.size_text(len(server.files[path]))})")
        assert said < out.index(f"cutting it from {path.rsplit('/', 1)[1]}")
    to_download = len(server.files[TUM_PATH]) + len(server.files[SEVENSCENES_PATH])
    assert f"{cli.size_text(to_download)} to download in all" in out
    # Replica.zip is read where it is: its central directory and the excerpt's members only
    replica = len(server.files[REPLICA_PATH])
    assert f"out of Replica.zip ({cli.size_text(replica)}) where it is, by HTTP range requests" in out
    assert server.sent[REPLICA_PATH] < replica - OTHER_SCENES // 2 and (REPLICA_PATH, None) not in server.requests
    assert out.strip().splitlines()[-1].endswith(f"run the tests with SLAMKIT_DATA={root} (export it)")

    assert_same_files(root / TUM.name, TUM)
    assert_same_files(root / REPLICA.name, REPLICA)
    cut = root / SEVENSCENES.name
    names = data_files(cut)
    assert len(names) == 3 * 700 + 1 and "frame-000300.color.png" in names and "frame-000999.pose.txt" in names
    assert (cut / "camera-intrinsics.txt").read_bytes() == (SEVENSCENES / "camera-intrinsics.txt").read_bytes()
    for i in range(300, 1000):
        stem = f"frame-{i:06d}"
        assert (cut / f"{stem}.depth.png").read_bytes() == (SEVENSCENES / f"{stem}.depth.png").read_bytes()
        np.testing.assert_array_equal(np.loadtxt(cut / f"{stem}.pose.txt"),
                                      np.loadtxt(SEVENSCENES / f"{stem}.pose.txt"))
    for i in REAL_COLOUR[:-1]:
        stem = f"frame-{i:06d}"
        np.testing.assert_array_equal(np.asarray(Image.open(cut / f"{stem}.color.png")),
                                      np.asarray(Image.open(SEVENSCENES / f"{stem}.color.jpg").convert("RGB")))
    dataset = build_run(["dataset=sevenscenes", f"dataset.path={cut}", "mapper=none"])[0]
    assert len(dataset) == 700 and dataset.camera.fx == 585.0
    np.testing.assert_array_equal(dataset[0].gt_pose, np.loadtxt(SEVENSCENES / "frame-000300.pose.txt"))
    manifest = (cut / "MANIFEST.sha256").read_text()
    assert "./frame-000999.color.png" in manifest and "./README.txt" in manifest

    assert sorted(p.name for p in root.iterdir()) == sorted([TUM.name, REPLICA.name, SEVENSCENES.name, cli.MANIFEST])
    server.requests.clear()
    status, out, err = download(capsys, "test-data", "--root", str(root), "--base-url", server.url)
    assert status == 0, err
    assert out.count("already in") == 3 and server.requests == []


def test_a_kept_archive_is_cut_again_without_a_download(server, tmp_path, capsys):
    status, out, err = download(capsys, "test-data/replica", "--root", str(tmp_path), "--base-url", server.url,
                           "--keep-archive")
    assert status == 0, err
    assert (tmp_path / "Replica.zip").read_bytes() == server.files[REPLICA_PATH]
    (tmp_path / REPLICA.name).rename(tmp_path / "moved")
    server.requests.clear()
    status, out, err = download(capsys, "test-data/replica", "--root", str(tmp_path), "--base-url", server.url)
    assert status == 0, err
    assert server.requests == [] and "downloaded earlier" in out
    assert_same_files(tmp_path / REPLICA.name, REPLICA)
    assert not (tmp_path / "Replica.zip").exists()


def test_a_part_download_resumes_and_says_what_is_there(server, tmp_path, capsys):
    served = server.files[TUM_PATH]
    (tmp_path / "rgbd_dataset_freiburg1_rpy.tgz.part").write_bytes(served[: len(served) // 2])
    status, out, err = download(capsys, "test-data/tum", "--root", str(tmp_path), "--base-url", server.url)
    assert status == 0, err
    assert f"{cli.size_text(len(served) // 2)} of it already here" in out
    assert server.requests == [(TUM_PATH, "HEAD"), (TUM_PATH, f"bytes={len(served) // 2}-")]
    assert_same_files(tmp_path / TUM.name, TUM)


def test_without_root_it_goes_where_the_tests_look(server, tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("SLAMKIT_DATA", raising=False)
    monkeypatch.setenv("SLAMKIT_CACHE", str(tmp_path / "cache"))
    status, out, err = download(capsys, "test-data/replica", "--base-url", server.url)
    assert status == 0, err
    root = tmp_path / "cache" / "test-data"
    assert excerpts.default_root() == root and (root / REPLICA.name / "traj.txt").is_file()
    assert "where the tests look for it by default" in out.strip().splitlines()[-1]


def test_a_cut_archive_is_one_line_and_set_aside(server, tmp_path, capsys):
    served = server.files[SEVENSCENES_PATH]
    server.files[SEVENSCENES_PATH] = served[: len(served) // 2]
    status, _, err = download(capsys, "test-data/7scenes", "--root", str(tmp_path), "--base-url", server.url)
    line = one_line(err)
    assert status == 2 and "redkitchen.zip: not a complete, readable zip archive" in line
    assert "moved aside as redkitchen.zip.corrupt" in line and "run the same command again" in line
    assert not (tmp_path / SEVENSCENES.name).exists() and not list(tmp_path.glob(".*cutting"))


def _seven_scenes_without_seq01() -> bytes:
    return zipped({"redkitchen/seq-02.zip": zipped({"seq-02/frame-000000.pose.txt": b"1 0 0 0\n"})})


def _tum_with_ten_frames() -> bytes:
    top = "rgbd_dataset_freiburg1_rpy"
    lines = "".join(f"{1305031229.5 + i / 30:.6f} rgb/{i}.png\n" for i in range(10)).encode()
    return tar_gz({f"{top}/rgb.txt": b"# color images\n" + lines, f"{top}/depth.txt": lines.replace(b"rgb", b"depth"),
                   f"{top}/groundtruth.txt": b"# ground truth\n"})


@pytest.mark.parametrize("key, path, payload, message", [
    ("7scenes", SEVENSCENES_PATH, _seven_scenes_without_seq01,
     "redkitchen.zip: no seq-01.zip in the archive (expected Microsoft's 7-Scenes redkitchen.zip"),
    ("tum", TUM_PATH, _tum_with_ten_frames,
     "rgbd_dataset_freiburg1_rpy.tgz: rgb.txt lists 10 colour frames, expected at least 150"),
])
def test_a_wrong_archive_is_one_line_and_set_aside(server, tmp_path, capsys, key, path, payload, message):
    server.files[path] = payload()
    status, _, err = download(capsys, f"test-data/{key}", "--root", str(tmp_path), "--base-url", server.url)
    line = one_line(err)
    file_name = path.rsplit("/", 1)[1]
    assert status == 2 and message in line and f"moved aside as {file_name}.rejected" in line
    assert (tmp_path / f"{file_name}.rejected").read_bytes() == server.files[path]
    assert [p.name for p in tmp_path.iterdir() if p.is_dir()] == []


def test_too_little_free_space_is_one_line_before_any_download(server, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(cli.shutil, "disk_usage", lambda _: type("Usage", (), {"free": 1000})())
    status, _, err = download(capsys, "test-data/tum", "--root", str(tmp_path), "--base-url", server.url)
    line = one_line(err)
    size = cli.size_text(len(server.files[TUM_PATH]))
    assert status == 1 and f"{tmp_path}: 1 kB free, but rgbd_dataset_freiburg1_rpy.tgz needs {size} more" in line
    assert server.requests == [(TUM_PATH, "HEAD")]


def test_test_data_and_a_sequence_in_one_command_is_one_line(server, tmp_path, capsys):
    status, _, err = download(capsys, "test-data", "replica", "--root", str(tmp_path), "--base-url", server.url)
    assert status == 2 and "in one command" in one_line(err) and server.requests == []
    status, _, err = download(capsys, "test-data/scannet", "--base-url", server.url)
    assert status == 2 and "test-data/tum, test-data/7scenes, test-data/replica" in one_line(err)


def test_an_interrupted_cut_leaves_no_folder_and_the_next_run_cuts_without_a_download(server, tmp_path, capsys,
                                                                                      monkeypatch):
    tum = next(e for e in excerpts.EXCERPTS if e.key == "tum")

    def interrupted(archive, into):
        tum.cut(archive, into)
        raise KeyboardInterrupt  # Ctrl-C once all is written, before the folder moves into place

    monkeypatch.setattr(excerpts, "EXCERPTS", (dataclasses.replace(tum, cut=interrupted),))
    status, _, err = download(capsys, "test-data/tum", "--root", str(tmp_path), "--base-url", server.url)
    assert status == cli.INTERRUPTED and "nothing half-done is kept" in one_line(err)
    assert not (tmp_path / TUM.name).exists() and not list(tmp_path.glob(".*cutting"))
    archive = tmp_path / "rgbd_dataset_freiburg1_rpy.tgz"
    assert archive.read_bytes() == server.files[TUM_PATH]  # complete: not fetched again

    monkeypatch.setattr(excerpts, "EXCERPTS", (tum,))
    server.requests.clear()
    status, out, err = download(capsys, "test-data/tum", "--root", str(tmp_path), "--base-url", server.url)
    assert status == 0, err
    assert server.requests == [] and "downloaded earlier" in out
    assert_same_files(tmp_path / TUM.name, TUM)
    assert not archive.exists()


def test_a_server_without_ranges_gets_replica_downloaded_whole(server, tmp_path, capsys):
    server.ranges = False
    status, out, err = download(capsys, "test-data/replica", "--root", str(tmp_path), "--base-url", server.url)
    assert status == 0, err
    assert f"to be cut from Replica.zip ({cli.size_text(len(server.files[REPLICA_PATH]))})" in out
    assert server.sent[REPLICA_PATH] >= len(server.files[REPLICA_PATH])
    assert_same_files(tmp_path / REPLICA.name, REPLICA)
    assert not (tmp_path / "Replica.zip").exists()


def test_a_damaged_member_read_by_range_is_one_line_and_keeps_nothing(server, tmp_path, capsys):
    payload = bytearray(server.files[REPLICA_PATH])
    payload[payload.find(b"JFIF") + 100] ^= 0xFF  # inside the first JPEG (stored: its bytes as they are)
    server.files[REPLICA_PATH] = bytes(payload)
    status, _, err = download(capsys, "test-data/replica", "--root", str(tmp_path), "--base-url", server.url)
    line = one_line(err)
    assert status == 2 and f"{server.url}/Replica.zip: member 'Replica/room0/results/frame" in line
    assert "does not read back whole" in line and "nothing was kept: run the same command again" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_a_download_not_on_a_terminal_prints_progress_lines(tmp_path, monkeypatch):
    """A batch job's log shows where a long download is: a line every few seconds (here every
    update), in megabytes, with the ETA."""
    out = io.StringIO()
    monkeypatch.setattr(transfer, "Progress", functools.partial(Progress, every_s=0, stream=out))
    s = Server()
    s.files["/big.bin"] = bytes(3_500_000)
    try:
        transfer.download(f"{s.url}/big.bin", tmp_path / "big.bin")
    finally:
        s.close()
    lines = out.getvalue().splitlines()
    assert lines[0].startswith("slamkit: download big.bin 1/3 MB (33 %), 0 s elapsed, ETA ")
    assert lines[-1].startswith("slamkit: download big.bin 3/3 MB (100 %)")


def test_a_cut_range_request_is_tried_again(server, tmp_path, capsys):
    server.cuts[REPLICA_PATH] = (2, 10)  # the range probe (1 byte: whole) and the first read, cut after 10 bytes
    status, _, err = download(capsys, "test-data/replica", "--root", str(tmp_path), "--base-url", server.url)
    assert status == 0, err
    assert server.cuts[REPLICA_PATH] == (0, 10)
    first_read = server.requests[1]
    assert first_read[1] != "bytes=0-0" and server.requests[2] == first_read  # the cut read, asked again
    assert_same_files(tmp_path / REPLICA.name, REPLICA)
