"""Map checkpoints (issue 17) end to end: a kill -9 while saving, a run continued from its
checkpoint (in process, and `slamkit resume=` on TUM with the 3DGS mapper), an interrupted
run's checkpoint, and `slamkit-export` from a checkpoint. The file format and its one-line
errors: tests/core/test_checkpoint.py."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from slamkit.formats.checkpoint import (
    CHECKPOINT_NAME,
    read_checkpoint,
    read_meta,
)
from slamkit.formats.tum import read_tum_trajectory
from slamkit.registry.compose import compose_run
from slamkit.registry.discovery import default_registry
from slamkit.run import checkpoint, pipeline

from support.commands import run_slamkit

SAVER = """
import sys, numpy as np
from slamkit.formats.checkpoint import write_checkpoint
path = sys.argv[1]
for version in range(1000):
    write_checkpoint(path, {"version": version}, {"data": np.full(4_000_000, version, dtype=np.float64)})
    print(version, flush=True)
"""


@pytest.mark.slow
def test_kill_9_while_saving_leaves_the_previous_checkpoint(tmp_path):
    path = tmp_path / CHECKPOINT_NAME
    proc = subprocess.Popen([sys.executable, "-c", SAVER, str(path)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "0"  # one complete checkpoint exists
        deadline = time.monotonic() + 60
        while not list(tmp_path.glob(f".{CHECKPOINT_NAME}.*.tmp")):  # the next one is being written
            assert time.monotonic() < deadline, "the saver never started a second checkpoint"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        proc.kill()
    back = read_checkpoint(path)
    version = back["version"]
    assert np.all(back["state"]["data"] == version)  # a whole checkpoint, the last one completed


def _cfg(tmp_path: Path, *overrides: str):
    return compose_run(["mapper=gaussian_splatting", "checkpoint.save=true", "dataset.num_frames=10",
                        "mapper.resolution_scale=0.25",
                        "mapper.eval_resolution_scale=0.25", "mapper.eval_every=5", "mapper.save_images=0",
                        "iterations_per_frame=2", "final_iterations=0", "output.progress=false", "output.plot=false",
                        "mapper/rasterizer=cpu", "mapper.strategy.prune_every=0", *overrides])


@pytest.mark.slow
def test_a_resumed_run_continues_exactly_where_its_checkpoint_stopped(tmp_path):
    """Sequential mode is deterministic: 6 frames, then resumed to 10, give the 10-frame run's
    trajectory and map (tracker target and motion, keyframes, Adam moments, sampler state). No
    refinement and no pruning at the end (the first run's end would otherwise differ)."""
    registry = default_registry()
    cfg, names = _cfg(tmp_path)
    whole = pipeline.run(cfg, registry, names, tmp_path / "whole")
    part_cfg, _ = _cfg(tmp_path, "dataset.max_frames=6")
    pipeline.run(part_cfg, registry, names, tmp_path / "part")
    saved = checkpoint.load(tmp_path / "part")
    assert saved["last_frame_index"] == 5 and saved["reason"] == "end" and saved["completed"]
    # as if the first run had logged two more frames after its checkpoint and been killed while
    # writing a third: the resumed run logs those frames again, once each
    with open(tmp_path / "part" / "frames.csv", "a") as log:
        log.write("6,0.2,none,0,50.0,0.0,2,0.9,100,300.0,\n7,0.23,none,0,50.0,0.0,2,0.9,100,300.0,\n8,0.2")
    resumed_cfg, _ = _cfg(tmp_path, f"resume={tmp_path / 'part'}")
    resumed = pipeline.run(resumed_cfg, registry, names, tmp_path / "part")
    assert resumed["num_frames"] == whole["num_frames"] == 10
    assert resumed["num_keyframes"] == whole["num_keyframes"]
    assert resumed["num_gaussians"] == whole["num_gaussians"]
    assert resumed["mapping_iterations"] == whole["mapping_iterations"]
    _, poses_whole = read_tum_trajectory(tmp_path / "whole" / "trajectory.txt")
    _, poses_resumed = read_tum_trajectory(tmp_path / "part" / "trajectory.txt")
    assert np.abs(poses_whole - poses_resumed).max() < 1e-6
    assert resumed["psnr"] == pytest.approx(whole["psnr"], abs=1e-3)
    logged = list(csv.DictReader(open(tmp_path / "part" / "frames.csv")))
    assert [int(r["index"]) for r in logged] == list(range(10))  # every frame once, in order
    map_whole, _ = checkpoint.load_map(tmp_path / "whole")
    map_resumed, _ = checkpoint.load_map(tmp_path / "part")
    assert torch.allclose(map_whole.means, map_resumed.means, atol=1e-6)


@pytest.mark.slow
def test_every_n_keyframes_a_checkpoint_is_written(tmp_path, caplog):
    cfg, names = compose_run(["dataset.max_frames=30", "mapper=none", "checkpoint.every_keyframes=2",
                              "output.progress=false", "output.plot=false"])
    with caplog.at_level("INFO", logger="slamkit.run.checkpoint"):
        metrics = pipeline.run(cfg, default_registry(), names, tmp_path)
    saved = [r.getMessage() for r in caplog.records if r.getMessage().startswith("checkpoint (keyframes)")]
    assert metrics["num_keyframes"] >= 4 and len(saved) == metrics["num_keyframes"] // 2
    assert read_meta(tmp_path / CHECKPOINT_NAME)["reason"] == "end"


@pytest.mark.slow
def test_a_default_run_writes_no_checkpoint_at_its_end_and_a_resumed_one_keeps_its_own(tmp_path):
    """Run folders stay small: the end checkpoint only when asked; but a folder that holds one (a
    resumed run's) has it brought to the end, so the finished run is not resumed again."""
    base = ["mapper=none", "output.progress=false", "output.plot=false"]
    cfg, names = compose_run(["dataset.max_frames=12", *base])
    metrics = pipeline.run(cfg, default_registry(), names, tmp_path / "plain")
    assert metrics["completed"] and not (tmp_path / "plain" / CHECKPOINT_NAME).exists()
    assert metrics["run_folder_mb"] < 1  # 12 synthetic frames, tracking only: logs, trajectory, plot
    cfg, names = compose_run(["dataset.max_frames=6", "checkpoint.save=true", *base])
    pipeline.run(cfg, default_registry(), names, tmp_path / "part")
    cfg, names = compose_run(["dataset.max_frames=12", *base, f"resume={tmp_path / 'part'}"])
    pipeline.run(cfg, default_registry(), names, tmp_path / "part")
    saved = read_meta(tmp_path / "part" / CHECKPOINT_NAME)
    assert saved["reason"] == "end" and saved["num_frames"] == 12


@pytest.mark.slow
def test_resume_refuses_other_plugins_and_a_damaged_checkpoint(tmp_path, tum_path):
    out = tmp_path / "run"
    base = ("dataset=tum", f"dataset.path={tum_path}", "dataset.max_frames=5", "mapper=none", "output.progress=false",
            "checkpoint.save=true")
    proc = run_slamkit(*base, f"hydra.run.dir={out}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    proc = run_slamkit(f"resume={out}", "tracker=kiss_icp", cwd=tmp_path)
    assert proc.returncode == 2 and "made with tracker=gicp" in proc.stderr
    data = (out / CHECKPOINT_NAME).read_bytes()
    (out / CHECKPOINT_NAME).write_bytes(data[:-100])
    proc = run_slamkit(f"resume={out}", "dataset.max_frames=8", cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        f"slamkit: error: checkpoint {out / CHECKPOINT_NAME} is damaged or truncated "
        "(not a complete zip archive: File is not a zip file)"]


@pytest.mark.slow
def test_an_interrupted_run_is_resumed_to_the_end(tmp_path, tum_path):
    """SIGTERM mid-run writes the checkpoint of the last whole frame; `slamkit resume=` then
    finishes the sequence in the same folder, the trajectory extended."""
    out = tmp_path / "run"
    exe = Path(sys.executable).with_name("slamkit")
    args = ["dataset=tum", f"dataset.path={tum_path}", "dataset.max_frames=60", "mapper=none", "output.progress=false",
            "realtime.fps_limit=15", "mode=realtime", f"hydra.run.dir={out}"]
    proc = subprocess.Popen([str(exe), *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not (out / "frames.csv").exists() or len((out / "frames.csv").read_text().splitlines()) < 12:
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.1)
        os.kill(proc.pid, signal.SIGTERM)
        proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM
    saved = read_meta(out / CHECKPOINT_NAME)
    stopped = json.loads((out / "metrics.json").read_text())["num_frames"]
    assert saved["reason"] == "interrupted" and saved["num_frames"] == stopped < 60
    proc = run_slamkit(f"resume={out}", "realtime.fps_limit=null", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["num_frames"] == 60 and metrics["completed"]
    timestamps, _ = read_tum_trajectory(out / "trajectory.txt")
    assert len(timestamps) == 60 and np.all(np.diff(timestamps) > 0)
    assert metrics["ate_rmse_m"] < 0.1  # fr1/rpy tracking-only: ~5 cm


@pytest.mark.slow
def test_export_reads_a_checkpoint(tmp_path, replica_path, capsys):
    from slamkit.cli.export import main as export_main

    out = tmp_path / "run"
    # the paper's scale alignment: 1-3 mm Gaussians at opacity 0.1, too faint to mesh at alpha 0.5
    proc = run_slamkit("dataset=replica", f"dataset.path={replica_path}", "dataset.max_frames=3", "mapper=none",
                       "growth.scale_alignment=z_pow", "output.progress=false", "checkpoint.save=true",
                       f"hydra.run.dir={out}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert not (out / "map.ply").exists()  # mapper=none: the checkpoint is the map
    assert export_main(["ply", str(out / CHECKPOINT_NAME), "--out", str(tmp_path / "m.ply")]) == 0
    from slamkit.formats.ply import load_ply

    gm, _ = checkpoint.load_map(out)
    assert len(load_ply(tmp_path / "m.ply")) == len(gm) > 1000
    assert export_main(["mesh", str(out), "--voxel", "0.05", "--scale", "0.25"]) == 2  # too faint at alpha 0.5
    assert "no surface to mesh" in capsys.readouterr().err
    assert export_main(["mesh", str(out), "--voxel", "0.05", "--scale", "0.25", "--min-alpha", "0.2"]) == 0
    assert (out / "mesh.ply").is_file() and "mesh with" in capsys.readouterr().out
