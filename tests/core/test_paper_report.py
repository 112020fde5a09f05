"""`slamkit-report --paper TABLE`: a sweep's runs as the paper's table, the paper's figure beside
each of ours (the row told by the swept setting, the column by the scene), seeds averaged,
unfinished runs left out, written to paper_TABLE.md."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from slamkit.cli.report import main as report_main

from support.data import REPLICA, require_data


def fake_run(root: Path, name: str, overrides: list[str], status: str = "completed", **metrics) -> None:
    """A run folder as a sweep job leaves it: .hydra/overrides.yaml and metrics.json."""
    run = root / name
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    base = {"status": status, "completed": status == "completed", "error": None, "num_frames": 20}
    (run / "metrics.json").write_text(json.dumps({**base, **metrics}))


def table_rows(text: str) -> list[list[str]]:
    rows = [[c.strip() for c in line.strip().strip("|").split("|")] for line in text.splitlines()
            if line.startswith("|")]
    return rows[0:1] + rows[2:]  # the header, then the rows (no separator)


def test_table6_rows_by_variant_with_the_papers_figures_beside_ours(tmp_path, capsys):
    sweep = tmp_path / "sweep"
    path = "dataset.path=/data/replica_room0_first20"
    for i, (variant, psnr) in enumerate([("knn", 20.0), ("z_pow", 30.0), ("none", 25.0)]):
        fake_run(sweep, str(i), [f"+scale_variant={variant}", path, "seed=0"], ate_mean_m=0.001 * (i + 1),
                 ate_rmse_m=0.002, psnr=psnr, ssim=0.9, lpips=None)
    fake_run(sweep, "3", ["+scale_variant=z_pow", path, "seed=1"], ate_mean_m=0.003, ate_rmse_m=0.004, psnr=32.0,
             ssim=0.8, lpips=None)
    fake_run(sweep, "4", ["+scale_variant=z", path, "seed=0"], status="interrupted", psnr=1.0)
    assert report_main([str(sweep), "--paper", "table6"]) == 0
    printed = capsys.readouterr().out
    written = (sweep / "paper_table6.md").read_text()
    assert written in printed
    header, *rows = table_rows(written)
    cell = {name: i for i, name in enumerate(header)}
    by_variant = {r[0]: r for r in rows}
    assert list(by_variant) == ["knn", "none", "z_pow"]  # the paper's order; the interrupted z run left out
    z_pow = by_variant["z_pow"]
    assert z_pow[cell["runs"]] == "2" and z_pow[cell["PSNR [dB]"]] == "31.00"  # two seeds averaged
    assert z_pow[cell["PSNR [dB], paper"]] == "38.83" and z_pow[cell["ATE [cm], paper"]] == "0.157"
    assert z_pow[cell["ATE [cm]"]] == "0.250" and z_pow[cell["ATE RMSE [cm]"]] == "0.300"
    assert z_pow[cell["the paper's row"]] == "z^1.5" and z_pow[cell["LPIPS"]] == "-"
    assert by_variant["knn"][cell["ATE [cm], paper"]] == "8.893"


def test_table1_takes_the_papers_column_of_the_scene_or_its_mean(tmp_path, capsys):
    sweep = tmp_path / "sweep"
    fake_run(sweep, "0", ["scene=Replica/room0", "preset=paper"], ate_mean_m=0.002, ate_rmse_m=0.003)
    fake_run(sweep, "1", ["scene=Replica/office4", "preset=paper"], ate_mean_m=0.004, ate_rmse_m=0.005)
    fake_run(sweep, "2", ["dataset.path=/elsewhere/my_room/", "preset=paper"], ate_mean_m=0.01, ate_rmse_m=0.02)
    fake_run(sweep, "3", ["scene=Replica/room0", "preset=slamkit"], ate_mean_m=0.001, ate_rmse_m=0.001)
    assert report_main([str(sweep), "--paper", "table1"]) == 0
    out = capsys.readouterr().out
    header, *rows = table_rows(out.split("**Table 1")[1])
    cell = {name: i for i, name in enumerate(header)}
    got = {(r[0], r[cell["scene"]]): (r[cell["the paper's column"]], r[cell["ATE [cm], paper"]]) for r in rows}
    assert got == {("paper", "room0"): ("room0", "0.150"), ("paper", "office4"): ("office4", "0.210"),
                   ("paper", "my_room"): ("mean", "0.160"), ("slamkit", "room0"): ("-", "-"),
                   ("paper", "mean of 3 scenes"): ("mean", "0.160")}  # the paper's "Avg." beside ours
    mean_row = next(r for r in rows if r[cell["scene"]] == "mean of 3 scenes")
    assert mean_row[cell["ATE [cm]"]] == "0.533" and mean_row[cell["runs"]] == "3"
    assert "my_room is not among the paper's scenes" in out  # the caveat under the table


def test_an_ablation_over_every_scene_under_data_root_in_real_time(tmp_path, capsys):
    """+protocol=realtime and +scenes=replica: the ablation's sweep in the paper's protocol over
    the scenes found under data_root (the sweep keeps those there, naming the others)."""
    from slamkit.registry.compose import compose_run

    from support.sweeps import job_values, swept_jobs

    (tmp_path / "Replica").mkdir()
    for scene in ("room0", "office4"):  # complete scenes (an incomplete one is skipped, naming what it lacks)
        (tmp_path / "Replica" / scene).symlink_to(require_data(REPLICA), target_is_directory=True)
    jobs = swept_jobs("+experiment=ablation_scale_alignment", "+protocol=realtime", "+scenes=replica",
                      f"data_root={tmp_path}")
    assert set(job_values(jobs, "scene")) == {"Replica/room0", "Replica/office4"}
    assert capsys.readouterr().err.count("skipped") == 6
    cfg, _ = compose_run(["+experiment=ablation_scale_alignment", "+protocol=realtime", "+scenes=replica",
                          f"data_root={tmp_path}", "scene=Replica/office4", "+scale_variant=z"])
    assert (cfg.mode.value, cfg.realtime.fps_limit, cfg.dataset.path) == ("realtime", 30.0,
                                                                        f"{tmp_path}/Replica/office4")
    assert cfg.preset == "paper" and cfg.growth.scale_alignment.value == "z"


def test_a_run_resumed_with_other_method_settings_is_no_rows_and_is_named(tmp_path, capsys):
    sweep = tmp_path / "sweep"
    fake_run(sweep, "0", ["scene=Replica/room0", "preset=paper"], ate_mean_m=0.002, ate_rmse_m=0.003)
    fake_run(sweep, "1", ["scene=Replica/office4", "preset=paper"], ate_mean_m=0.004, ate_rmse_m=0.005,
             settings_changes=[{"frame": 10, "before": {"realtime.fps_limit": 30.0},
                                "after": {"realtime.fps_limit": None}}])
    assert report_main([str(sweep), "--paper", "table1"]) == 0
    text = capsys.readouterr().out.split("**Table 1")[1]
    header, *rows = table_rows(text)
    assert [r[header.index("scene")] for r in rows] == ["room0"]
    assert "resumed with other method settings" in text and str(sweep / "1") in text


def test_an_unknown_table_is_refused(tmp_path, capsys):
    fake_run(tmp_path, "0", ["seed=0"], psnr=1.0)
    with pytest.raises(SystemExit) as exit_:
        report_main([str(tmp_path), "--paper", "table9"])
    assert exit_.value.code == 2 and "table9" in capsys.readouterr().err


def test_a_sweep_block_names_each_job_by_what_its_sweep_varied(tmp_path):
    """`<!-- slamkit-report --sweep DIR -->`: one row per job, named by the settings that differ
    among the runs (data folders left out), a job that failed a row saying so."""
    from slamkit.cli import paper_tables

    sweep = tmp_path / "benchmarks" / "sweep"
    for i, (tracker, psnr) in enumerate([("kiss_icp", 17.5), ("gicp", 18.25)]):
        fake_run(sweep, str(i), [f"tracker={tracker}", "dataset=tum", "dataset.path=/data/tum"], psnr=psnr,
                 ate_rmse_m=0.05, num_gaussians=1234, num_keyframes=20, tracking_time_s=4.0, wall_time_s=60.0)
    fake_run(sweep, "2", ["tracker=small_gicp", "dataset=tum", "dataset.path=/data/tum"], status="failed")
    text = paper_tables.regenerate_document("<!-- slamkit-report --sweep benchmarks/sweep -->\nold\n"
                                            "<!-- end slamkit-report -->\n", tmp_path)
    header, *rows = table_rows(text)
    assert header[:3] == ["tracker", "keyframes", "ATE RMSE [cm]"]
    assert rows[0][:4] == ["gicp", "20", "5.000", "18.25"] and rows[0][header.index("Gaussians")] == "1,234"
    assert rows[1][0] == "kiss_icp" and rows[2][:2] == ["small_gicp", "failed"]
    with pytest.raises(ValueError, match="--sweep DIR"):
        paper_tables.block_text(["--sweeps", "x"], tmp_path)


def test_the_mean_row_is_over_the_scenes_of_one_dataset(tmp_path, capsys):
    """A table holding a TUM and a Replica half has a mean row per dataset with two scenes or more,
    never one that averages a TUM scene with a Replica one."""
    sweep = tmp_path / "sweep"
    scenes = [("replica", "room0", 30.0), ("replica", "office4", 20.0), ("tum", "fr1_desk", 15.0)]
    for i, (dataset, scene, psnr) in enumerate(scenes):
        fake_run(sweep, str(i), ["+keyframe_variant=mapping_every10", f"dataset={dataset}",
                                 f"dataset.path=/data/{scene}"], ate_mean_m=0.01, ate_rmse_m=0.01, psnr=psnr)
    assert report_main([str(sweep), "--paper", "table7"]) == 0
    header, *rows = table_rows(capsys.readouterr().out.split("**Table 7")[1])
    scene = header.index("scene")
    means = {r[scene]: r[header.index("PSNR [dB]")] for r in rows if r[scene].startswith("mean")}
    assert means == {"mean of 2 replica scenes": "25.00"}
