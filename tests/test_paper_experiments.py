"""Each table and figure of the paper's evaluation is one `+experiment=` (docs/paper.md): run through
the `slamkit` command on a few shared frames (tiny: 3 frames, one mapping step a frame, a tenth of
the resolution), every job of the sweep must have varied the setting its table varies, run the
paper's system with the mapper, and written the metrics its table reports; the scene sweeps run
the scenes found under data_root and name each missing one in one line."""

from __future__ import annotations

import io
import json
from pathlib import Path

import pytest
import yaml

from conftest import REPLICA, TUM, require_data, run_slamkit
from slamkit.cli.scenes import present_scenes
from slamkit.downloads.catalogue import PAPER_TUM, REPLICA_SCENES
from slamkit.errors import ConfigError

#: Few frames, one mapping step each, a tenth of the resolution, one evaluation frame at a quarter.
TINY = ["dataset.max_frames=3", "iterations_per_frame=1", "mapper.resolution_scale=0.1", "mapper.eval_every=3",
        "mapper.eval_resolution_scale=0.25", "mapper.save_images=0", "eval.lpips=off", "eval.plot=false",
        "checkpoint.save=false", "progress=false"]


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


@pytest.mark.slow
def test_ablation_regularization_is_table5(tmp_path):
    jobs = sweep("ablation_regularization", tmp_path, *on_tum())
    assert [j["settings"]["tracker.regularization"] for j in jobs] == ["none", "plane", "ellipse"]
    papers_system_mapped(jobs, "ate_rmse_m", "ate_mean_m")


@pytest.mark.slow
def test_ablation_scale_alignment_is_table6_five_rows(tmp_path):
    jobs = sweep("ablation_scale_alignment", tmp_path, *on_replica())
    rows = [(j["settings"]["growth.initial_shape"], j["settings"]["growth.scale_alignment"], j["settings"]["growth.scale_c"])
            for j in jobs]
    assert [r[0] for r in rows] == ["knn", "gicp", "gicp", "gicp", "gicp"]
    assert [r[1:] for r in rows[1:]] == [("none", 2.0), ("constant", 2.0), ("z", 2.0), ("z_pow", 2.0)]
    papers_system_mapped(jobs, "ate_rmse_m", "psnr", "ssim")


@pytest.mark.slow
def test_ablation_keyframes_is_table7_with_the_mapper(tmp_path):
    jobs = sweep("ablation_keyframes", tmp_path, *on_replica())
    assert [(j["settings"]["keyframe.max_interval"], j["settings"]["keyframe.mapping_every"]) for j in jobs] == [
        (30, 0), (10, 0), (0, 10)]
    papers_system_mapped(jobs, "ate_rmse_m", "psnr", "ssim")


@pytest.mark.slow
def test_ablation_keyframe_selection_is_fig4a(tmp_path):
    jobs = sweep("ablation_keyframe_selection", tmp_path, *on_replica())
    assert [j["choices"]["keyframe"] for j in jobs] == ["overlap", "every_n", "every_n", "every_n"]
    assert [j["settings"].get("keyframe.tracking_every") for j in jobs] == [None, 5, 10, 30]
    assert all(j["settings"]["keyframe.mapping_every"] == 10 for j in jobs)
    papers_system_mapped(jobs, "ate_rmse_m", "psnr")


@pytest.mark.slow
def test_ablation_training_keyframes_is_table8a(tmp_path):
    jobs = sweep("ablation_training_keyframes", tmp_path, *on_replica())
    assert [j["choices"]["mapper/sampler"] for j in jobs] == ["recent", "covisible", "random"]
    papers_system_mapped(jobs, "psnr", "ssim")


@pytest.mark.slow
def test_ablation_densify_prune_is_table8b_two_by_two(tmp_path):
    jobs = sweep("ablation_densify_prune", tmp_path, *on_replica())
    assert [(j["choices"]["mapper/strategy"], j["settings"]["mapper.strategy.prune_every"]) for j in jobs] == [
        ("3dgs", 200), ("3dgs", 0), ("gsicp", 200), ("gsicp", 0)]
    papers_system_mapped(jobs, "ate_rmse_m", "psnr", "ssim", "gaussians_densified")


@pytest.fixture
def data_root(tmp_path) -> Path:
    """A data_root as `slamkit-data download` lays it out, holding one Replica scene (room0: the
    shared excerpt) and one TUM sequence (fr1/desk: the shared fr1/rpy excerpt, a fr1 camera)."""
    root = tmp_path / "data"
    (root / "Replica").mkdir(parents=True)
    (root / "Replica" / "room0").symlink_to(require_data(REPLICA), target_is_directory=True)
    (root / "rgbd_dataset_freiburg1_desk").symlink_to(require_data(TUM), target_is_directory=True)
    return root


@pytest.mark.slow
@pytest.mark.parametrize("experiment, found, scenes", [
    ("paper_replica", "Replica/room0", [f"Replica/{s}" for s in REPLICA_SCENES]),
    ("paper_tum", "rgbd_dataset_freiburg1_desk", list(PAPER_TUM.values())),
], ids=["paper_replica", "paper_tum"])
def test_paper_tables_run_each_scene_found_in_both_presets_and_name_the_missing(experiment, found, scenes,
                                                                               data_root, tmp_path):
    jobs = sweep(experiment, tmp_path, f"data_root={data_root}")
    assert [(j["settings"]["preset"], j["settings"]["fps_limit"]) for j in jobs] == [
        ("paper", 30.0), ("paper_unlimited", None)]
    assert all(f"scene={found}" in j["overrides"] for j in jobs)
    assert all(j["metrics"]["settings"]["mode"] == "realtime" for j in jobs)
    for job in jobs:
        m = job["metrics"]
        assert m["status"] == "completed" and all(isinstance(m[k], float) for k in ("ate_rmse_m", "psnr", "ssim", "fps"))
    lines = [l for l in jobs[0]["stderr"].splitlines() if "skipped: no folder" in l]
    assert sorted(l.split()[2] for l in lines) == sorted(s for s in scenes if s != found)


def test_a_scene_sweep_without_data_root_or_any_scene_is_one_line(tmp_path):
    with pytest.raises(ConfigError, match="data_root") as err:
        present_scenes(["+experiment=paper_tum"])
    assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="none of the scenes") as err:
        present_scenes(["+experiment=paper_replica", f"data_root={tmp_path}"])
    assert "\n" not in str(err.value)


def test_the_scene_sweep_keeps_the_scenes_found_and_a_given_list(data_root):
    told = io.StringIO()
    argv = present_scenes(["-m", "+experiment=paper_tum", f"data_root={data_root}", "seed=1"], out=told)
    assert argv == ["-m", "+experiment=paper_tum", f"data_root={data_root}", "seed=1",
                    "scene=rgbd_dataset_freiburg1_desk"]
    assert len(told.getvalue().splitlines()) == 2
    argv = present_scenes(["+experiment=paper_replica", f"data_root={data_root}", "scene=Replica/room0,Replica/room9"],
                          out=io.StringIO())
    assert argv[-1] == "scene=Replica/room0" and sum(a.startswith("scene=") for a in argv) == 1
    assert present_scenes(["tracker=gicp", "seed=2"]) == ["tracker=gicp", "seed=2"]  # no scene sweep: as given
