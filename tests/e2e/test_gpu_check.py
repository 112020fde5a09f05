"""The GPU check (benchmarks/gpu_check.sh, docs/gpu.md) on a machine without a GPU: its dry run
prints every step and timing and touches nothing; the results it writes as it goes make tables;
the frames it carries load as the shared sequences do."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from support.data import REPLICA, REPO, TUM, require_data


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, REPO / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def snapshot(root: Path) -> dict[str, tuple[int, int]]:
    """(size, mtime) of every file under `root`, but the virtual environment, git's own folder
    and Python's byte-code caches."""
    files = {}
    for folder, dirs, names in os.walk(root):
        dirs[:] = [d for d in dirs if d not in (".venv", ".git", "__pycache__", ".pytest_cache")]
        for name in names:
            st = os.stat(os.path.join(folder, name))
            files[os.path.join(folder, name)] = (st.st_size, st.st_mtime_ns)
    return files


def bare_python() -> str:
    """This Python without the virtual environment's packages (no slamkit, no torch), as on the GPU
    machine before the check installs anything."""
    return getattr(sys, "_base_executable", None) or sys.executable


def dry_run(tmp_path: Path, **env: str) -> tuple[subprocess.CompletedProcess, list[str]]:
    env = {**os.environ, "PYTHON": bare_python(), "GPU_CHECK_OUT": str(tmp_path / "out"),
           "GPU_CHECK_WHEELS": str(tmp_path / "whl"), "SLAMKIT_DATA": str(tmp_path / "data"), **env}
    proc = subprocess.run(["bash", str(REPO / "benchmarks" / "gpu_check.sh"), "--dry-run"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=120)
    return proc, proc.stdout.splitlines()


def test_dry_run_prints_every_step_and_touches_nothing(tmp_path):
    before = snapshot(REPO)
    proc, lines = dry_run(tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stderr == "", proc.stderr
    assert snapshot(REPO) == before
    assert list(tmp_path.iterdir()) == []  # no output folder, nothing installed
    steps = [ln.split()[1] for ln in lines if ln.startswith("STEP ")]
    assert steps == ["machine", "install-wheels", "install-slamkit", "import-slamkit", "build-gsplat", "cuda-tests",
                     "time-tracking", "time-phases", "time-realtime"]
    text = "\n".join(lines)
    assert f"output folder: {tmp_path / 'out'}" in text

    def step(name):
        (line,) = [ln for ln in lines if ln.startswith(f"STEP {name} ")]
        return line

    assert "pip install" in step("install-wheels") and "--no-index --no-deps" in step("install-wheels")
    assert f"{tmp_path / 'whl'}/*.whl" in step("install-wheels")
    assert "--no-index --no-deps --no-build-isolation -e" in step("install-slamkit")
    assert "benchmarks/build_gsplat.py" in step("build-gsplat")
    assert "TORCH_EXTENSIONS_DIR=" + str(REPO / ".cache" / "torch_extensions") in text
    assert "-m pytest -m cuda" in step("cuda-tests") and "tests/e2e/test_cuda.py" in step("cuda-tests")
    for stage in ("tracking", "phases", "realtime"):
        command = step(f"time-{stage}")
        assert f"gpu_bench.py --out {tmp_path / 'out'}" in command and command.endswith(stage)
    timings = [ln.strip() for ln in lines if ln.strip().startswith("would time:")]
    for sequence in ("tum", "replica"):
        for device in ("cpu", "cuda"):
            assert any(t.startswith(f"would time: tracking {sequence} map on {device}") for t in timings)
        for variant in ("cpu@cpu", "cpu@cuda", "torch@cuda", "gsplat@cuda"):
            assert any(t.startswith(f"would time: phases {sequence} {variant}") for t in timings)
        for variant in ("gsplat@cuda", "torch@cuda", "cpu@cpu"):
            assert any(t.startswith(f"would time: realtime {sequence} {variant}")
                       and "mode=realtime realtime.fps_limit=30" in t
                       and f"mapper/rasterizer={variant.split('@')[0]}" in t for t in timings)
    assert "nothing is run" in lines[0]


def test_dry_run_of_a_rerun_lists_only_the_steps_asked_for(tmp_path):
    proc, lines = dry_run(tmp_path, GPU_CHECK_ONLY="build-gsplat,time-realtime")
    assert proc.returncode == 0, proc.stderr
    run = [ln.split()[1] for ln in lines if ln.startswith("STEP ") and "left out" not in ln]
    assert run == ["build-gsplat", "time-realtime"]
    assert all(ln.strip().startswith("would time: realtime") for ln in lines if "would time" in ln)


def test_dry_run_rejects_other_arguments(tmp_path):
    proc = subprocess.run(["bash", str(REPO / "benchmarks" / "gpu_check.sh"), "--fast"], capture_output=True,
                          text=True, cwd=tmp_path)
    assert proc.returncode == 2 and "usage" in proc.stderr


def test_results_are_merged_and_tabled_as_they_come(tmp_path):
    bench = _load("gpu_bench")
    out = tmp_path / "out"
    bench.main(["note", "build-gsplat", "ok", "183", "python", "benchmarks/build_gsplat.py", "--out", str(out)])
    bench.merge(out, "tracking", {"sequence": "tum", "device": "cuda", "frames": 60, "keyframes": 11, "fps": 40.5,
                                  "ate_rmse_m": 0.05, "grow_map_ms": 3.0, "target_ms": 2.0, "rows_per_keyframe": 2500.0,
                                  "copy_in_ms": 0.2, "copy_out_ms": 0.3, "copy_mb": 0.2})
    bench.merge(out, "phases", {"sequence": "tum", "variant": "gsplat@cuda", "gaussians": 26840,
                                "resolution": "320x240", "ms": {"view": 0.2, "render": 1.0, "loss": 2.0,
                                                                "backward": 3.0,
                                                                "lock": 0.0, "optimizer": 0.5, "strategy": 0.1,
                                                                "step": 6.8}})
    bench.merge(out, "phases", {"sequence": "tum", "variant": "torch@cuda", "error": "RuntimeError: out of memory"})
    bench.merge(out, "realtime", {"sequence": "replica", "variant": "cpu@cpu", "num_frames": 20, "ate_rmse_m": 3e-5,
                                  "tracking_fps": 30.2, "stream_fps": 29.0, "fps": 28.1, "mapping_steps": 4,
                                  "psnr": 12.3, "num_gaussians": 40800})
    data = json.loads((out / "gpu_check.json").read_text())
    assert data["steps"]["build-gsplat"]["seconds"] == 183 and len(data["phases"]) == 2
    table = (out / "gpu_check.md").read_text()
    assert "| build-gsplat | ok | 183.0 | python benchmarks/build_gsplat.py |" in table
    assert "| tum | cuda | 60 | 11 | 40.5 | 5.00 | 3.00 | 2.00 | 2500 | 0.20 / 0.30 (0.20) |" in table
    assert "| tum | gsplat@cuda | 26840 | 320x240 | 0.20 | 1.00 | 2.00 | 3.00 | 0.00 | 0.50 | 0.10 | 6.80 |" in table
    assert "| tum | torch@cuda | failed: RuntimeError: out of memory |" in table
    assert "| replica | cpu@cpu | 20 | 0.00 | 30.2 | 29.0 | 28.1 | 4 | 12.30 | 40800 |" in table


def test_plan_leaves_gsplat_out_when_asked(capsys):
    bench = _load("gpu_bench")
    assert bench.main(["plan", "phases", "realtime", "--no-gsplat"]) == 0
    out = capsys.readouterr().out
    assert "would time: phases tum torch@cuda" in out and "gsplat" not in out and "tracking" not in out


def test_carried_frames_load_as_the_shared_sequences(tmp_path):
    from slamkit.registry.discovery import default_registry

    require_data(TUM)
    require_data(REPLICA)
    gpu_data = _load("gpu_data")
    gpu_data.copy_tum(TUM, tmp_path / TUM.name, 5)
    gpu_data.copy_replica(REPLICA, tmp_path / REPLICA.name, 3)
    registry = default_registry()
    for plugin, folder, n in (("tum", TUM.name, 5), ("replica", REPLICA.name, 3)):
        config = registry.get("dataset", plugin).config(path=str(tmp_path / folder))
        dataset = registry.create("dataset", plugin, config)
        assert len(dataset) == n
        frame = dataset[n - 1]
        assert frame.depth.max() > 0 and frame.gt_pose is not None
    full = registry.create("dataset", "tum", registry.get("dataset", "tum").config(path=str(TUM)))
    small = registry.create("dataset", "tum", registry.get("dataset", "tum").config(path=str(tmp_path / TUM.name)))
    assert (small[4].rgb == full[4].rgb).all() and (small[4].depth == full[4].depth).all()
    assert small[4].timestamp == full[4].timestamp


@pytest.mark.skipif(not (REPO / ".whl").is_dir(), reason="no .whl/ here (make gpu-wheels fills it)")
def test_carried_wheels_are_one_version_each_for_python_3_12():
    names = sorted(p.name for p in (REPO / ".whl").glob("*.whl"))
    projects = [n.split("-")[0].lower() for n in names]
    assert len(projects) == len(set(projects)), names
    assert any(p == "gsplat" for p in projects)
    assert all(n.endswith("py3-none-any.whl") or "-cp312-" in n for n in names), names
