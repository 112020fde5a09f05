"""`slamkit-data download` (slamkit.cli.data) against a local HTTP server (a thread on
127.0.0.1 with Range support) serving small fabricated archives in the real layouts: a full
download that `dataset=tum` / `dataset=replica` opens, resuming a cut transfer (within a run and
across runs), checksum mismatches, a damaged archive, HTTP errors and unknown names, each a
one-line error."""

from __future__ import annotations

import hashlib
import io
import json
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from slamkit.cli import data as cli
from slamkit.run.build import build_run

from support.downloads import Server, download, one_line

TUM_SEQUENCE = "rgbd_dataset_freiburg1_desk"
TUM_URL_PATH = f"/freiburg1/{TUM_SEQUENCE}.tgz"


# ---------------------------------------------------------------------------- the archives
def png(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG")
    return buf.getvalue()


def jpeg(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="JPEG", quality=95)
    return buf.getvalue()


def colour(h: int, w: int, shade: int) -> np.ndarray:
    ramp = np.linspace(0, 200, w, dtype=np.uint8)[None, :, None]
    return np.broadcast_to(ramp, (h, w, 3)).copy() + np.uint8(shade)


def tum_archive(depth_m: float = 1.25, frames: int = 2) -> bytes:
    """A TUM .tgz as the TUM server's: one top folder with rgb.txt, depth.txt,
    groundtruth.txt, rgb/*.png and depth/*.png (16-bit, depth * 5000), 640x480."""
    files = {}
    stamps = [1305031452.791720 + i / 30 for i in range(frames)]
    rgb_lines, depth_lines, gt_lines = ["# colour images"], ["# depth images"], ["# ground truth"]
    for i, t in enumerate(stamps):
        files[f"rgb/{t:.6f}.png"] = png(colour(480, 640, 10 * i))
        files[f"depth/{t + 0.004:.6f}.png"] = png(np.full((480, 640), int(depth_m * 5000), np.uint16))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines.append(f"{t + 0.004:.6f} depth/{t + 0.004:.6f}.png")
    for t in np.arange(stamps[0] - 0.1, stamps[-1] + 0.1, 0.01):
        gt_lines.append(f"{t:.4f} 1.0 0.5 1.5 0 0 0 1")
    files["rgb.txt"] = "\n".join(rgb_lines).encode() + b"\n"
    files["depth.txt"] = "\n".join(depth_lines).encode() + b"\n"
    files["groundtruth.txt"] = "\n".join(gt_lines).encode() + b"\n"
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        for name, payload in files.items():
            info = tarfile.TarInfo(f"{TUM_SEQUENCE}/{name}")
            info.size = len(payload)
            tar.addfile(info, io.BytesIO(payload))
    return buf.getvalue()


def replica_archive(compression: int = zipfile.ZIP_DEFLATED) -> bytes:
    """NICE-SLAM's Replica.zip layout: Replica/cam_params.json and, per scene, results/
    frame%06d.jpg and depth%06d.png (16-bit, depth * 6553.5) and traj.txt; one frame each."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression) as z:
        cam = {"camera": {"w": 1200, "h": 680, "fx": 600.0, "fy": 600.0, "cx": 599.5, "cy": 339.5, "scale": 6553.5}}
        z.writestr("Replica/cam_params.json", json.dumps(cam))
        for k, scene in enumerate(("room0", "room1", "room2", "office0", "office1", "office2", "office3", "office4")):
            z.writestr(f"Replica/{scene}/results/frame000000.jpg", jpeg(colour(680, 1200, k)))
            z.writestr(f"Replica/{scene}/results/depth000000.png", png(np.full((680, 1200), 13107, np.uint16)))
            z.writestr(f"Replica/{scene}/traj.txt", " ".join(map(str, np.eye(4).ravel())) + "\n")
    return buf.getvalue()


@pytest.fixture()
def server():
    s = Server()
    s.files[TUM_URL_PATH] = tum_archive()
    s.files["/Replica.zip"] = replica_archive()
    yield s
    s.close()


def open_dataset(name: str, folder: Path):
    """The dataset a `slamkit dataset=NAME dataset.path=FOLDER` run builds, and its first frame."""
    dataset = build_run([f"dataset={name}", f"dataset.path={folder}", "mapper=none"])[0]
    return dataset, dataset[0]


# ----------------------------------------------------------------------------------- tests
def test_a_tum_sequence_downloads_into_the_layout_dataset_tum_opens(server, tmp_path, capsys):
    root = tmp_path / "data"
    status, out, err = download(capsys, "fr1/desk", "--root", str(root), "--base-url", server.url)
    assert status == 0, err
    folder = root / TUM_SEQUENCE
    assert f"dataset.path={folder}" in out
    assert not (root / f"{TUM_SEQUENCE}.tgz").exists()  # deleted once extracted
    assert not list(root.glob(".*"))  # no staging or part file left
    record = json.loads((root / cli.MANIFEST).read_text())[f"{TUM_SEQUENCE}.tgz"]
    served = server.files[TUM_URL_PATH]
    assert record["sha256"] == hashlib.sha256(served).hexdigest() and record["bytes"] == len(served)
    assert record["url"] == server.url + TUM_URL_PATH and record["extracted"] == [TUM_SEQUENCE]
    dataset, frame = open_dataset("tum", folder)
    assert len(dataset) == 2 and frame.rgb.shape == (480, 640, 3)
    np.testing.assert_allclose(frame.depth, 1.25, atol=1e-3)
    np.testing.assert_allclose(frame.gt_pose[:3, 3], [1.0, 0.5, 1.5], atol=1e-9)
    # a second run finds it complete and downloads nothing
    n = len(server.requests)
    status, out, _ = download(capsys, TUM_SEQUENCE, "--root", str(root), "--base-url", server.url)
    assert status == 0 and "already" in out and len(server.requests) == n


def test_replica_downloads_into_the_nice_slam_layout_dataset_replica_opens(server, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv(cli.BASE_URL_ENV, server.url)  # the environment's base URL
    status, _, err = download(capsys, "replica", "--root", str(tmp_path), "--keep-archive")
    assert status == 0, err
    assert (tmp_path / "Replica.zip").read_bytes() == server.files["/Replica.zip"]
    for scene in ("room0", "office4"):
        dataset, frame = open_dataset("replica", tmp_path / "Replica" / scene)
        assert dataset.camera.width == 1200 and frame.rgb.shape == (680, 1200, 3)
        np.testing.assert_allclose(frame.depth, 2.0, atol=1e-3)  # 13107 / 6553.5
        np.testing.assert_allclose(frame.gt_pose, np.eye(4))


def test_a_cut_download_resumes_within_the_run_and_on_the_next_run(server, tmp_path, capsys):
    served = server.files[TUM_URL_PATH]
    after = len(served) // 3
    server.cuts[TUM_URL_PATH] = (1, after)
    status, _, err = download(capsys, "fr1/desk", "--root", str(tmp_path / "a"), "--base-url", server.url,
                         "--retries", "1")
    assert status == 0, err
    assert server.requests[-2:] == [(TUM_URL_PATH, None), (TUM_URL_PATH, f"bytes={after}-")]
    assert (tmp_path / "a" / TUM_SEQUENCE / "rgb.txt").is_file()

    server.requests.clear()
    server.cuts[TUM_URL_PATH] = (1, after)
    root = tmp_path / "b"
    status, _, err = download(capsys, "fr1/desk", "--root", str(root), "--base-url", server.url, "--retries", "0")
    line = one_line(err)
    assert status == 1 and f"stopped at {after} of {len(served)} bytes" in line and "resume" in line
    part = root / f"{TUM_SEQUENCE}.tgz.part"
    assert part.read_bytes() == served[:after]  # kept
    assert not (root / TUM_SEQUENCE).exists()
    status, _, err = download(capsys, "fr1/desk", "--root", str(root), "--base-url", server.url, "--retries", "0")
    assert status == 0, err
    assert server.requests == [(TUM_URL_PATH, None), (TUM_URL_PATH, f"bytes={after}-")]
    record = json.loads((root / cli.MANIFEST).read_text())[f"{TUM_SEQUENCE}.tgz"]
    assert record["sha256"] == hashlib.sha256(served).hexdigest()
    assert not part.exists()


def test_a_complete_part_file_is_not_fetched_again(server, tmp_path, capsys):
    """An earlier run that stopped after the last byte: the server answers 416 to the range."""
    served = server.files[TUM_URL_PATH]
    (tmp_path / f"{TUM_SEQUENCE}.tgz.part").write_bytes(served)
    status, _, err = download(capsys, "fr1/desk", "--root", str(tmp_path), "--base-url", server.url)
    assert status == 0, err
    assert server.requests == [(TUM_URL_PATH, f"bytes={len(served)}-")]
    assert (tmp_path / TUM_SEQUENCE / "depth.txt").is_file()


def test_a_checksum_mismatch_is_one_line_and_extracts_nothing(server, tmp_path, capsys):
    served = server.files[TUM_URL_PATH]
    wrong = "0" * 64
    status, _, err = download(capsys, "fr1/desk", "--root", str(tmp_path), "--base-url", server.url, "--sha256", wrong)
    line = one_line(err)
    assert status == 2 and wrong in line and hashlib.sha256(served).hexdigest() in line
    assert (tmp_path / f"{TUM_SEQUENCE}.tgz.corrupt").read_bytes() == served and not (tmp_path / TUM_SEQUENCE).exists()

    # the SHA-256 recorded at the first download is what a later download must match
    root = tmp_path / "again"
    assert download(capsys, "fr1/desk", "--root", str(root), "--base-url", server.url)[0] == 0
    (root / TUM_SEQUENCE).rename(root / "moved_away")
    server.files[TUM_URL_PATH] = tum_archive(depth_m=2.5)  # the server's file changed
    status, _, err = download(capsys, "fr1/desk", "--root", str(root), "--base-url", server.url)
    assert status == 2 and "SHA-256" in one_line(err) and hashlib.sha256(served).hexdigest() in err


def test_a_damaged_archive_is_one_line_and_leaves_no_folder(server, tmp_path, capsys):
    good = server.files[TUM_URL_PATH]
    damaged = bytearray(good)
    damaged[len(good) // 2] ^= 0xFF  # one flipped byte inside the gzip stream
    server.files[TUM_URL_PATH] = bytes(damaged)
    status, _, err = download(capsys, "fr1/desk", "--root", str(tmp_path), "--base-url", server.url, "--keep-archive")
    line = one_line(err)
    assert status == 2 and f"{TUM_SEQUENCE}.tgz" in line and "not a complete, readable tar archive" in line
    assert not (tmp_path / TUM_SEQUENCE).exists() and not list(tmp_path.glob(".*extracting"))
    # a zip with a member whose CRC does not match (stored uncompressed, so the flip is in its bytes)
    payload = bytearray(replica_archive(zipfile.ZIP_STORED))
    payload[payload.find(b"1.0 0.0 0.0 0.0")] ^= 0x01  # the first scene's traj.txt
    server.files["/Replica.zip"] = bytes(payload)
    status, _, err = download(capsys, "replica", "--root", str(tmp_path / "r"), "--base-url", server.url)
    line = one_line(err)
    assert status == 2 and "Replica.zip" in line and "CRC" in line and not (tmp_path / "r" / "Replica").exists()


def test_an_archive_member_outside_its_folder_refuses_the_archive(server, tmp_path, capsys):
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        for name in (f"{TUM_SEQUENCE}/rgb.txt", "../outside.txt"):
            info = tarfile.TarInfo(name)
            info.size = 1
            tar.addfile(info, io.BytesIO(b"x"))
    server.files[TUM_URL_PATH] = buf.getvalue()
    root = tmp_path / "root"
    status, _, err = download(capsys, "fr1/desk", "--root", str(root), "--base-url", server.url)
    assert status == 2 and "'../outside.txt'" in one_line(err) and "outside" in err
    assert not (tmp_path / "outside.txt").exists() and not (root / TUM_SEQUENCE).exists()


def test_unknown_names_list_the_known_ones_and_download_nothing(server, tmp_path, capsys):
    status, _, err = download(capsys, "fr1/desk", "scannet", "--root", str(tmp_path), "--base-url", server.url)
    line = one_line(err)
    assert status == 2 and "'scannet'" in line
    assert all(k in line for k in ("replica", "fr1/desk", "fr2/xyz", "fr3/office", "rgbd_dataset_freiburg"))
    assert server.requests == []


def test_an_http_error_is_one_line_and_the_other_names_still_download(server, tmp_path, capsys):
    status, _, err = download(capsys, "fr2/no_such_sequence", "fr1/desk", "--root", str(tmp_path), "--base-url",
                         server.url)
    line = one_line(err)
    assert status == 2 and "HTTP 404" in line and "rgbd_dataset_freiburg2_no_such_sequence.tgz" in line
    assert (tmp_path / TUM_SEQUENCE / "rgb.txt").is_file()


def test_the_console_script(server, tmp_path):
    script = Path(sys.executable).with_name("slamkit-data")
    done = subprocess.run([str(script), "download", "fr1/desk", "--root", str(tmp_path), "--base-url", server.url],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / TUM_SEQUENCE / "groundtruth.txt").is_file()
    listed = subprocess.run([str(script), "list"], capture_output=True, text=True, timeout=60)
    assert listed.returncode == 0 and "fr3/office (rgbd_dataset_freiburg3_long_office_household)" in listed.stdout


def test_a_truncated_archive_is_moved_aside_and_the_next_run_downloads_it_again(server, tmp_path, capsys):
    good = server.files[TUM_URL_PATH]
    server.files[TUM_URL_PATH] = good[: len(good) // 2]  # the server's file cut short (its length says so too)
    status, _, err = download(capsys, "fr1/desk", "--root", str(tmp_path), "--base-url", server.url)
    line = one_line(err)
    assert status == 2 and "not a complete, readable tar archive" in line
    assert f"moved aside as {TUM_SEQUENCE}.tgz.corrupt" in line and "run the same command again" in line
    assert (tmp_path / f"{TUM_SEQUENCE}.tgz.corrupt").read_bytes() == good[: len(good) // 2]
    assert not (tmp_path / f"{TUM_SEQUENCE}.tgz").exists() and not (tmp_path / TUM_SEQUENCE).exists()
    assert f"{TUM_SEQUENCE}.tgz" not in json.loads((tmp_path / cli.MANIFEST).read_text())  # its checksum forgotten

    server.files[TUM_URL_PATH] = good  # the server serves the right file again: the same command succeeds
    status, _, err = download(capsys, "fr1/desk", "--root", str(tmp_path), "--base-url", server.url)
    assert status == 0, err
    assert open_dataset("tum", tmp_path / TUM_SEQUENCE)[1].depth is not None
    assert json.loads((tmp_path / cli.MANIFEST).read_text())[f"{TUM_SEQUENCE}.tgz"]["sha256"] == \
        hashlib.sha256(good).hexdigest()


@pytest.mark.parametrize("kind", ["a file", "under a file", "not creatable"])
def test_a_root_that_is_no_folder_is_one_line_before_any_request(server, tmp_path, capsys, kind):
    (tmp_path / "file").write_text("not a folder")
    root, expected, message = {"a file": (tmp_path / "file", 2, "is a file, expected a folder"),
                               "under a file": (tmp_path / "file" / "data", 2, "is a file, expected a folder"),
                               "not creatable": (Path("/proc/slamkit-nope"), 1, "cannot create the folder")}[kind]
    status, _, err = download(capsys, "fr1/desk", "--root", str(root), "--base-url", server.url)
    line = one_line(err)
    assert status == expected and line.startswith(f"slamkit-data: error: --root {root}: ") and message in line
    assert server.requests == [] and (tmp_path / "file").read_text() == "not a folder"
