"""`slamkit-export mesh`: the run outputs it reads (camera.json, keyframes.txt), TSDF fusion of map
renders on a known plane and on a real Replica mapping run, and its one-line errors."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from slamkit.cli.export import main as export_main
from slamkit.formats.ply import save_ply
from slamkit.formats.tum import read_tum_trajectory, write_tum_trajectory
from slamkit.geometry.transforms import backproject, make_pose, so3_exp, transform_points
from slamkit.map.gaussian_map import GaussianMap, GaussianRows
from slamkit.run.outputs import write_camera
from slamkit.types import Camera

from support.commands import run_slamkit

EXPORT = Path(sys.executable).with_name("slamkit-export")
PLANE_Z = 2.0  # metres, world frame
PLANE_COLOR = (0.8, 0.3, 0.1)


def _plane_run(run_dir: Path) -> None:
    """A fake run folder: a map of flat opaque Gaussians tiling the plane z = PLANE_Z (world) and
    two keyframes looking at it, the second turned 10 degrees and moved."""
    run_dir.mkdir(parents=True)
    xs, ys = np.meshgrid(np.arange(-2.5, 2.5, 0.04), np.arange(-2.0, 2.0, 0.04))
    n = xs.size
    means = np.column_stack([xs.ravel(), ys.ravel(), np.full(n, PLANE_Z)])
    gm = GaussianMap()
    gm.append(GaussianRows.from_shapes(means, np.tile([1.0, 0, 0, 0], (n, 1)), np.tile([0.03, 0.03, 0.003], (n, 1)),
              np.tile(PLANE_COLOR, (n, 1)), 0.95, np.ones(n, bool), 0))
    save_ply(run_dir / "map.ply", gm)
    write_camera(run_dir / "camera.json", Camera(64, 48, 40.0, 40.0, 31.5, 23.5), float("inf"))
    turned = make_pose(so3_exp(np.array([0.0, np.radians(10), 0.0])), np.array([0.2, -0.1, 0.3]))
    write_tum_trajectory(run_dir / "keyframes.txt", [0.0, 1.0], np.stack([np.eye(4), turned]))


@pytest.mark.slow
def test_mesh_of_a_plane_lies_on_the_plane(tmp_path, capsys):
    pytest.importorskip("open3d", reason="open3d is the optional extra `mesh`")
    import open3d as o3d

    run = tmp_path / "run"
    _plane_run(run)
    assert export_main(["mesh", str(run), "--voxel", "0.02", "--out", str(tmp_path / "plane.ply")]) == 0
    assert "from 2 keyframe views" in capsys.readouterr().out
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "plane.ply"))
    vertices = np.asarray(mesh.vertices)
    assert len(vertices) > 1000 and len(mesh.triangles) > 1000
    assert np.abs(vertices[:, 2] - PLANE_Z).max() < 0.02  # within a voxel of the plane, world frame
    np.testing.assert_allclose(np.asarray(mesh.vertex_colors).mean(axis=0), PLANE_COLOR, atol=0.03)
    # both views were fused: the turned camera sees the plane farther along +x than the first
    assert vertices[:, 0].max() > 1.7


@pytest.mark.slow
def test_errors_are_one_line(tmp_path, capsys, monkeypatch):
    def fails(args: list[str], *expected: str) -> None:
        assert export_main(args) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("slamkit-export: error: "), err
        assert all(text in err for text in expected), err

    fails(["mesh", str(tmp_path / "nowhere")], "run directory")
    (tmp_path / "tracking_only").mkdir()
    fails(["mesh", str(tmp_path / "tracking_only")], "map.ply not found: the mesh is made from the Gaussian map; "
                                                     "run slamkit with mapper=gaussian_splatting")
    run = tmp_path / "run"
    _plane_run(run)
    (run / "camera.json").write_text("{}")
    fails(["mesh", str(run)], "camera.json: expected JSON with width, height, fx, fy, cx, cy")
    write_camera(run / "camera.json", Camera(64, 48, 40.0, 40.0, 31.5, 23.5), 5.0)
    (run / "keyframes.txt").write_text("")
    fails(["mesh", str(run)], "keyframes.txt: no keyframes")
    write_tum_trajectory(run / "keyframes.txt", [0.0], np.eye(4)[None])
    fails(["mesh", str(run), "--rasterizer", "nope"], "unknown rasterizer 'nope'")
    monkeypatch.setitem(sys.modules, "open3d", None)  # `import open3d` raises ImportError
    fails(["mesh", str(run)], "open3d is not installed", "install it with pip install -e '.[mesh]'")
    with pytest.raises(SystemExit) as stop:
        export_main(["mesh", str(run), "--voxel", "-1"])
    assert stop.value.code == 2 and "--voxel: expected a number > 0, got '-1'" in capsys.readouterr().err


@pytest.mark.slow
def test_run_writes_its_camera_and_keyframe_poses(tmp_path):
    out = tmp_path / "run"
    proc = run_slamkit("dataset=synthetic", "dataset.num_frames=12", "dataset.width=64", "dataset.height=48",
                       "mapper=none", "keyframe=every_n", "keyframe.tracking_every=4", "output.progress=false",
                       "output.plot=false", f"hydra.run.dir={out}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    camera = json.loads((out / "camera.json").read_text())
    assert camera["width"] == 64 and camera["height"] == 48 and camera["fx"] > 0
    assert set(camera) == {"width", "height", "fx", "fy", "cx", "cy", "depth_trunc"}
    with open(out / "frames.csv") as f:
        keyframe_rows = [i for i, row in enumerate(csv.DictReader(f)) if row["keyframe"] != "none"]
    assert keyframe_rows == [0, 4, 8]
    ts, poses = read_tum_trajectory(out / "trajectory.txt")
    kf_ts, kf_poses = read_tum_trajectory(out / "keyframes.txt")
    np.testing.assert_allclose(kf_ts, ts[keyframe_rows])
    np.testing.assert_allclose(kf_poses, poses[keyframe_rows], atol=1e-8)


@pytest.mark.slow
def test_mesh_of_a_replica_mapping_run_matches_the_true_depth(tmp_path, replica_path):
    """5 real frames mapped (3 keyframes, ~300 steps at quarter resolution), then the mesh: its
    vertices must lie on the surfaces the ground-truth depth sees, and cover most of them."""
    pytest.importorskip("open3d", reason="open3d is the optional extra `mesh`")
    import open3d as o3d
    from pykdtree.kdtree import KDTree

    from slamkit.registry.discovery import discover

    out = tmp_path / "run"
    proc = run_slamkit(
        "dataset=replica", f"dataset.path={replica_path}", "dataset.max_frames=5", "keyframe=every_n",
        "keyframe.tracking_every=2", "mapper=gaussian_splatting", "iterations_per_frame=2",
        "final_iterations=300", "mapper.resolution_scale=0.25", "mapper.eval_every=100",
        "mapper.save_images=0", "output.progress=false", "output.plot=false", f"hydra.run.dir={out}",
        cwd=tmp_path, env_extra={"OMP_NUM_THREADS": "1"}, timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    export = subprocess.run([str(EXPORT), "mesh", str(out), "--voxel", "0.02"], capture_output=True, text=True,
                            timeout=600)
    assert export.returncode == 0, export.stderr[-2000:]
    assert "from 3 keyframe views" in export.stdout and str(out / "mesh.ply") in export.stdout
    mesh = o3d.io.read_triangle_mesh(str(out / "mesh.ply"))
    vertices = np.asarray(mesh.vertices, dtype=np.float32)
    assert len(vertices) > 10_000 and len(mesh.triangles) > 10_000 and mesh.has_vertex_colors()

    spec = discover().get("dataset", "replica")
    dataset = spec.cls(spec.config(path=str(replica_path), max_frames=5))
    truth = np.concatenate([transform_points(f.gt_pose, backproject(f.depth, f.camera, 4)[0])
                            for f in (dataset[i] for i in range(len(dataset)))]).astype(np.float32)
    to_truth, _ = KDTree(truth).query(vertices, k=1)
    assert np.median(to_truth) < 0.02 and np.percentile(to_truth, 90) < 0.05  # metres
    to_mesh, _ = KDTree(vertices).query(truth, k=1)
    assert np.mean(to_mesh < 0.03) > 0.8  # the mesh covers the seen surfaces
