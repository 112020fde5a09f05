"""Each table and figure of the paper's evaluation is one `+experiment=` (docs/paper.md): run through
the `slamkit` command on a few shared frames (tiny: 3 frames, one mapping step a frame, a tenth of
the resolution), every job of the sweep must have varied the setting its table varies, run the
paper's system with the mapper, and written the metrics its table reports; the scene sweeps run
the scenes found under data_root and name each missing one in one line; the command refuses
`eval.lpips=on` without weights in one line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from slamkit.downloads.catalogue import PAPER_TUM, REPLICA_SCENES

from support.commands import run_slamkit
from support.data import REPLICA, TUM, paper_data_root, require_data

pytestmark = pytest.mark.slow  # every test here starts the slamkit command

#: Few frames, one mapping step each, a tenth of the resolution, one evaluation frame at a quarter.
TINY = ["dataset.max_frames=3", "iterations_per_frame=1", "mapper.resolution_scale=0.1", "mapper.eval_every=3",
        "mapper.eval_resolution_scale=0.25", "mapper.save_images=0", "eval.lpips=off", "output.plot=false",
        "checkpoint.save=false", "output.progress=false"]


def sweep(experiment: str, tmp_path: Path, *extra: str) -> list[dict]:
    """Run `+experiment=NAME` with TINY and `extra`; for each job, its settings (metrics.json's
    `settings`), metrics, Hydra's plugin choices and its overrides."""
    out = tmp_path / "sweep"
    proc = run_slamkit(f"+experiment={experiment}", *TINY, *extra, f"hydra.sweep.dir={out}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    jobs = []
    for job in sorted((p for p in out.iterdir() if p.name.isdigit()), key=lambda p: int(p.name)):
        metrics = json.loads((job / "metrics.json").read_text())
        hydra = yaml.safe_load((job / ".hydra" / "hydra.yaml").read_text())["hydra"]
        jobs.append({"settings": metrics["settings"], "metrics": metrics, "choices": hydra["runtime"]["choices"],
                     "overrides": hydra["overrides"]["task"], "stderr": proc.stderr})
    return jobs


def on_replica() -> list[str]:
    return ["dataset=replica", f"dataset.path={require_data(REPLICA)}"]


def on_tum() -> list[str]:
    return ["dataset=tum", f"dataset.path={require_data(TUM)}"]


def papers_system_mapped(jobs: list[dict], *metrics: str) -> None:
    """Every job completed in the paper's system (sequential, for determinism) with the mapper
    and wrote `metrics` (a number each; LPIPS is off here, so its key is there with null)."""
    for job in jobs:
        m, s = job["metrics"], job["settings"]
        assert m["status"] == "completed", m.get("error")
        assert (s["preset"], s["tracker.target_geometry"], s["growth.mapping_only_trackable"]) == (
            "paper", "optimised", False)
        assert job["choices"]["mapper"] == "gaussian_splatting" and m["mapping_steps"] > 0
        for name in metrics:
            assert isinstance(m[name], (int, float)), (name, m[name])
        assert "lpips" in m and "gaussians_added" in m and "gaussians_pruned" in m


def test_ablation_regularization_is_table5(tmp_path):
    jobs = sweep("ablation_regularization", tmp_path, *on_tum())
    assert [j["settings"]["tracker.regularization"] for j in jobs] == ["none", "plane", "ellipse"]
    papers_system_mapped(jobs, "ate_rmse_m", "ate_mean_m")


def test_ablation_scale_alignment_is_table6_five_rows(tmp_path):
    jobs = sweep("ablation_scale_alignment", tmp_path, *on_replica())
    rows = [tuple(j["settings"][f"growth.{key}"] for key in ("initial_shape", "scale_alignment", "scale_c"))
            for j in jobs]
    assert [r[0] for r in rows] == ["knn", "gicp", "gicp", "gicp", "gicp"]
    assert [r[1:] for r in rows[1:]] == [("none", 2.0), ("constant", 2.0), ("z", 2.0), ("z_pow", 2.0)]
    papers_system_mapped(jobs, "ate_rmse_m", "psnr", "ssim")


def test_ablation_keyframes_is_table7_with_the_mapper(tmp_path):
    jobs = sweep("ablation_keyframes", tmp_path, *on_replica())
    assert [(j["settings"]["keyframe.max_interval"], j["settings"]["keyframe.mapping_every"]) for j in jobs] == [
        (30, 0), (10, 0), (0, 10)]
    papers_system_mapped(jobs, "ate_rmse_m", "psnr", "ssim")


def test_ablation_keyframe_selection_is_fig3(tmp_path):
    jobs = sweep("ablation_keyframe_selection", tmp_path, *on_replica())
    assert [j["choices"]["keyframe"] for j in jobs] == ["overlap", "every_n", "every_n", "every_n"]
    assert [j["settings"].get("keyframe.tracking_every") for j in jobs] == [None, 5, 10, 30]
    assert all(j["settings"]["keyframe.mapping_every"] == 10 for j in jobs)
    papers_system_mapped(jobs, "ate_rmse_m", "psnr")


def test_ablation_training_keyframes_is_table8a(tmp_path):
    jobs = sweep("ablation_training_keyframes", tmp_path, *on_replica())
    assert [j["choices"]["mapper/sampler"] for j in jobs] == ["recent", "covisible", "random"]
    papers_system_mapped(jobs, "psnr", "ssim")


def test_ablation_densify_prune_is_table8b_two_by_two(tmp_path):
    jobs = sweep("ablation_densify_prune", tmp_path, *on_replica())
    assert [(j["choices"]["densify_variant"], j["choices"]["mapper/strategy"],
             j["settings"]["mapper.strategy.prune_every"]) for j in jobs] == [
        ("reference", "3dgs", 200), ("reference", "3dgs", 0), ("none", "gsicp", 200), ("none", "gsicp", 0)]
    papers_system_mapped(jobs, "ate_rmse_m", "psnr", "ssim", "gaussians_densified")
    config = yaml.safe_load((tmp_path / "sweep" / "0" / ".hydra" / "config.yaml").read_text())
    assert (config["mapper"]["strategy"]["densify_every"], config["mapper"]["strategy"]["reset_opacity_every"]) == (
        300, 600)  # the reference code's schedule


@pytest.fixture
def data_root(tmp_path) -> Path:
    return paper_data_root(tmp_path / "data")


@pytest.mark.parametrize("experiment, found, scenes", [
    ("paper_replica", "Replica/room0", [f"Replica/{s}" for s in REPLICA_SCENES]),
    ("paper_tum", "rgbd_dataset_freiburg1_desk", list(PAPER_TUM.values())),
], ids=["paper_replica", "paper_tum"])
def test_paper_tables_run_each_scene_found_in_both_presets_and_name_the_missing(experiment, found, scenes,
                                                                               data_root, tmp_path):
    jobs = sweep(experiment, tmp_path, f"data_root={data_root}")
    assert [(j["settings"]["preset"], j["settings"]["realtime.fps_limit"]) for j in jobs] == [
        ("paper", 30.0), ("paper_unlimited", None)]
    assert all(f"scene={found}" in j["overrides"] for j in jobs)
    assert all(j["metrics"]["settings"]["mode"] == "realtime" for j in jobs)
    for job in jobs:
        m = job["metrics"]
        assert m["status"] == "completed"
        assert all(isinstance(m[k], float) for k in ("ate_rmse_m", "psnr", "ssim", "fps"))
    lines = [line for line in jobs[0]["stderr"].splitlines() if "skipped: no folder" in line]
    assert sorted(line.split()[2] for line in lines) == sorted(s for s in scenes if s != found)


def test_the_command_exits_2_for_lpips_on_without_weights(tmp_path):
    proc = run_slamkit("mapper=gaussian_splatting", "eval.lpips=on", f"eval.lpips_backbone={tmp_path / 'none.pth'}",
                       "dataset.num_frames=3", f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert proc.returncode == 2
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("slamkit: error: ") and "eval.lpips_backbone" in last and "Traceback" not in proc.stderr
