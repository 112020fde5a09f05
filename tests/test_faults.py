"""The fault suite (issue 19, no traceback anywhere): bad inputs and faults, each run through a
console script's real entry point (`slamkit` = `slamkit.cli.main:main`, as installed) in this
process, asserting the exit status, the one-line message and what the run folder kept; then the
rules every config key shares, key by key, and the checks themselves.

One row of `FAULTS` per case; to add one, append a `Fault`:
- argv: the command's arguments; `{out}` is the run folder (`hydra.run.dir={out}` is added to
  every `slamkit` row), `{data}` the case's input made by `make` (in its own temporary folder);
- program: the console script whose entry point runs (`slamkit` unless said);
- status: the expected exit status (2: bad input or config; 1: an environment failure; 0: the
  run goes on, e.g. a broken plugin that is not selected is only reported);
- message: a fragment of the one-line error (the last stderr line, `slamkit: error: ...`), or for
  status 0 of a warning or of the standard output;
- kept: the run outputs (`OUTPUTS`) left in {out}: "name" exists, "name:N" has N lines; any
  output not listed must be absent (metrics.json of a failed run must say completed=false);
  None: the run folder itself is not created (the run was refused before any work).
"""

from __future__ import annotations

import json
import logging
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import pytest

from fault_inputs import (FRAMES, INTRINSICS, duplicate_timestamp, folder_with, install, non_utf8_name, tiny_tum,
                          truncate_depth, tum_with)

#: The run outputs whose presence each case states.
OUTPUTS = ("trajectory.txt", "metrics.json", "frames.csv")


# --- the table ------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Fault:
    id: str
    argv: tuple[str, ...]
    status: int
    message: str
    kept: tuple[str, ...] | None = None
    make: Callable[[Path], object] | None = None
    program: str = "slamkit"


HUGE = "1000000"
FAST = ("tracker=kiss_icp", "mapper=none", "progress=false")
TUM_DATA = ("dataset=tum", "dataset.path={data}", *FAST)
FOLDER = ("dataset=folder", "dataset.path={data}", *FAST)
RAN = ("trajectory.txt", "metrics.json", "frames.csv")

FAULTS = [
    # config values: refused in one line naming the key, before the run folder exists
    Fault("stride-0", ("dataset.stride=0",), 2, "dataset.stride: expected an integer >= 1, got 0"),
    Fault("max-frames-text", ("dataset.max_frames=abc",), 2, "dataset.max_frames"),
    Fault("misspelt-key", ("tracker.no_such_key=1",), 2, "no_such_key"),
    Fault("bad-enum", ("mode=fast",), 2, "mode"),
    Fault("unknown-plugin", ("tracker=nope",), 2, "unknown tracker 'nope'; available:"),
    Fault("part-bad-value", ("mapper=gaussian_splatting", "mapper/sampler=covisible", "mapper.sampler.top_k=-1"), 2,
          "mapper.sampler.top_k"),
    Fault("cx-nan", ("dataset.cx=nan",), 2, "dataset.cx: expected null or >= 0 pixels, got nan"),
    Fault("fx-inf", ("dataset.fx=inf",), 2, "dataset.fx: expected a finite number"),
    Fault("cy-negative", ("dataset.cy=-5",), 2, "dataset.cy: expected null or >= 0 pixels, got -5.0"),
    Fault("depth-trunc-nan", ("dataset.depth_trunc=nan",), 2, "dataset.depth_trunc"),
    Fault("scale-c-nan", ("growth.scale_c=nan",), 2, "growth.scale_c"),
    Fault("fps-limit-inf", ("mode=realtime", "fps_limit=inf"), 2, "fps_limit: expected a finite number"),
    Fault("seed-negative", ("seed=-1",), 2, "seed: expected an integer from 0 to 2^32 - 1"),
    Fault("seed-huge", ("seed=1099511627776",), 2, "seed: expected an integer from 0 to 2^32 - 1"),
    Fault("mapper-seed-negative", ("mapper=gaussian_splatting", "mapper.seed=-1"), 2, "mapper.seed: expected"),
    Fault("kiss-min-points-0", ("tracker=kiss_icp", "tracker.min_points=0"), 2, "tracker.min_points: expected"),
    Fault("mapping-threads-huge", (f"mapping_threads={HUGE}",), 2, "mapping_threads: expected at most"),
    Fault("tracker-threads-huge", (f"tracker.num_threads={HUGE}",), 2, "tracker.num_threads: expected at most"),
    Fault("rasterizer-threads-huge", ("mapper=gaussian_splatting", "mapper/rasterizer=cpu", f"mapper.rasterizer.num_threads={HUGE}"),
          2, "mapper.rasterizer.num_threads: expected at most"),
    Fault("loss-threads-huge", ("mapper=gaussian_splatting", f"mapper.loss.num_threads={HUGE}"), 2,
          "mapper.loss.num_threads: expected at most"),
    # intrinsics against the image size: refused when the dataset is opened, before any frame
    Fault("cx-huge", ("dataset.cx=1e30", *FAST), 2, "dataset.cx: expected 0 to", kept=()),
    Fault("fx-tiny-tum", (*TUM_DATA, "dataset.fx=0.001"), 2, "dataset.fx: expected", kept=(), make=tiny_tum),
    Fault("intrinsics-file-cx-huge", FOLDER, 2,
          "intrinsics.yaml: cx = 1e+30 (expected 0 to 640 pixels, inside an image 640 pixels wide)", kept=(),
          make=folder_with(INTRINSICS.replace("cx: 318.6", "cx: 1.0e+30"))),
    Fault("intrinsics-file-cx-nan", FOLDER, 2, "intrinsics.yaml: cx = nan", kept=(),
          make=folder_with(INTRINSICS.replace("cx: 318.6", "cx: .nan"))),
    Fault("intrinsics-file-fx-negative", FOLDER, 2, "intrinsics.yaml: fx = -1", kept=(),
          make=folder_with(INTRINSICS.replace("fx: 517.3", "fx: -1"))),
    Fault("intrinsics-file-missing-key", FOLDER, 2, "missing key fy", kept=(),
          make=folder_with(INTRINSICS.replace("fy: 516.5\n", ""))),
    Fault("intrinsics-file-size", FOLDER, 2, "is 640x480 but", kept=(),
          make=folder_with(INTRINSICS.replace("width: 640", "width: 320"))),
    Fault("intrinsics-file-absent", FOLDER, 2, "intrinsics.yaml not found", kept=(),
          make=folder_with(damage=lambda root: (root / "intrinsics.yaml").unlink())),
    # dataset files
    Fault("non-utf8-file-name", FOLDER, 2, "have no depth image (caf\\udce9)", kept=(), make=folder_with(
        damage=non_utf8_name)),
    Fault("dataset-path-missing", ("dataset=tum", "dataset.path={data}/nope", *FAST), 2, "nope", kept=(),
          make=lambda root: root.mkdir(parents=True)),
    Fault("replica-empty", ("dataset=replica", "dataset.path={data}", *FAST), 2, "frame%06d.jpg", kept=(),
          make=lambda root: root.mkdir(parents=True)),
    Fault("tum-duplicate-timestamp", TUM_DATA, 2, "rgb.txt", kept=(), make=tum_with(duplicate_timestamp)),
    Fault("tum-gt-path-missing", (*TUM_DATA, "dataset.gt_path=missing_gt.txt"), 2, "missing_gt.txt", kept=(),
          make=tiny_tum),
    Fault("truncated-depth-mid-run", TUM_DATA, 2, "image file is truncated (expected a 16-bit PNG)", kept=(
        "trajectory.txt:5", "metrics.json", "frames.csv"), make=tum_with(truncate_depth)),
    Fault("truncated-depth-skipped", (*TUM_DATA, "dataset.on_error=skip"), 0, "", kept=(
        f"trajectory.txt:{FRAMES}", "metrics.json", "frames.csv"), make=tum_with(truncate_depth)),
    # plugins
    Fault("plugin-raises-mid-run", (*TUM_DATA[:2], "tracker=still", "tracker.fail_at=3", "mapper=none"), 2,
          "tracker plugin 'still' failed in track(): ValueError: simulated failure",
          kept=("trajectory.txt:3", "metrics.json", "frames.csv"),
          make=lambda root: (tiny_tum(root), install("still")(root))),
    Fault("plugin-config-not-hydra", TUM_DATA, 0, "array_weights", kept=RAN,
          make=lambda root: (tiny_tum(root), install("array", "still")(root))),
    Fault("plugin-import-fails", TUM_DATA, 0, "needs libfoo", kept=RAN,
          make=lambda root: (tiny_tum(root), install("broken")(root))),
    Fault("plugin-config-not-hydra-listed", ("tracker=array_weights",), 2, "not loaded: array (slamkit-fault-plugins)",
          make=install("array")),
    Fault("plugin-defaults-invalid", TUM_DATA, 0, "cannot be built from its defaults: tracker.radius: expected > 0",
          kept=RAN, make=lambda root: (tiny_tum(root), install("bad_defaults")(root))),
    Fault("plugin-unusual-config-listed", (), 0, "level: low | high = low", program="slamkit-plugins",
          make=install("unusual")),
    Fault("plugin-unusual-config-runs", (*TUM_DATA, "tracker=still"), 0, "", kept=RAN,
          make=lambda root: (tiny_tum(root), install("unusual", "still")(root))),
    # absurd values that used to exhaust memory
    Fault("passes-huge", (*TUM_DATA, "dataset.passes=1000000000", "dataset.max_frames=4"), 0, "",
          kept=("trajectory.txt:4", "metrics.json", "frames.csv"), make=tiny_tum),
]


# --- running a case ---------------------------------------------------------------------------------

@dataclass
class Outcome:
    status: int
    stdout: str
    stderr: str
    warnings: list[str]  # the Python warnings raised during the run


def run_program(program: str, argv: list[str], cwd: Path, monkeypatch, capsys) -> Outcome:
    """Run the entry point of the console script `program` (as installed: pyproject's
    [project.scripts]) in this process, as `program ARGV...` in `cwd`."""
    from importlib.metadata import entry_points

    from hydra.core.global_hydra import GlobalHydra

    (script,) = entry_points(group="console_scripts", name=program)
    main = script.load()

    monkeypatch.chdir(cwd)
    monkeypatch.setattr(sys, "argv", [program, *argv])
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    status = 0
    with warnings.catch_warnings(record=True) as warned:
        warnings.simplefilter("always")
        try:
            status = main() or 0
        except SystemExit as exc:
            status = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        finally:
            GlobalHydra.instance().clear()
            for handler in set(root.handlers) - set(handlers):  # Hydra's console and log-file handlers
                root.removeHandler(handler)
                handler.close()
            for handler in handlers:
                if handler not in root.handlers:
                    root.addHandler(handler)
            root.setLevel(level)
    captured = capsys.readouterr()
    return Outcome(status, captured.out, captured.err, [str(w.message) for w in warned])


def check_kept(out: Path, kept: tuple[str, ...] | None, status: int) -> None:
    if kept is None:
        assert not out.exists(), f"the run folder {out} was created"
        return
    assert out.is_dir()
    expected = dict(k.partition(":")[::2] for k in kept)
    for name in OUTPUTS:
        path = out / name
        if name not in expected:
            assert not path.exists(), f"{name} was written"
            continue
        assert path.is_file(), f"{name} was not kept"
        if expected[name]:
            assert len(path.read_text().splitlines()) == int(expected[name]), name
    if "metrics.json" in expected:
        assert json.loads((out / "metrics.json").read_text())["completed"] is (status == 0)


@pytest.mark.slow  # every case starts the slamkit command (in process)
@pytest.mark.parametrize("fault", FAULTS, ids=[f.id for f in FAULTS])
def test_fault(fault: Fault, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(sys, "path", list(sys.path))  # a case's plugins leave with it
    data, out = tmp_path / "data", tmp_path / "run"
    if fault.make is not None:
        fault.make(data)
    argv = [a.replace("{data}", str(data)).replace("{out}", str(out)) for a in fault.argv]
    if fault.program == "slamkit":
        argv.append(f"hydra.run.dir={out}")
    result = run_program(fault.program, argv, tmp_path, monkeypatch, capsys)
    everything = "\n".join([result.stdout, result.stderr, *result.warnings])
    assert result.status == fault.status, everything[-3000:]
    assert "Traceback" not in everything and "Logging error" not in everything, everything[-3000:]
    if fault.status:
        last = (result.stderr.strip().splitlines() or [""])[-1]
        assert last.startswith("slamkit: error: ") and fault.message in last, last
    elif fault.message:
        assert any(fault.message in text for text in [result.stdout, *result.warnings]), everything[-3000:]
    check_kept(out, fault.kept, fault.status)


# --- every key: the rules every config value shares (slamkit.roles.check_values) ------------------

#: Numeric keys for which a negative value is meaningful: every other one has a range. A failed
#: run's score may be any number (e.g. below every real score of a maximised metric).
NEGATIVE_OK: set[str] = {"objective.failed_value"}


def _numeric_keys():
    """(overrides selecting the key's plugin, key, "nan" | "negative" | "threads") for every float
    key of the configuration reference (nan), every int or float key (negative) and every field
    declared a thread count (`thread_count`)."""
    import dataclasses

    from test_config_reference import config_class, reference_keys

    from slamkit.config import THREADS

    cases = []
    for section, key, type_, _ in reference_keys():
        if section == "mapper/rasterizer=gsplat":
            continue  # needs CUDA to build; its config is checked in tests/test_fake_cuda.py
        base = [section] if "=" in section else []
        if section.startswith("mapper/"):
            base.insert(0, "mapper=gaussian_splatting")
        kinds = [t.strip() for t in type_.split("|")]
        if "float" in kinds:
            cases.append((base, key, "nan"))
        if {"int", "float"} & set(kinds) and key not in NEGATIVE_OK:
            cases.append((base, key, "negative"))
        field = {f.name: f for f in dataclasses.fields(config_class(section, key))}.get(key.split(".")[-1])
        if field is not None and field.metadata.get(THREADS):
            cases.append((base, key, "threads"))
    return cases


@pytest.mark.slow  # composes the config once per key
def test_every_numeric_key_has_a_range_and_every_thread_count_is_bounded_by_the_machine():
    """Through the composition the command uses, a float key refuses nan and -inf, a numeric key
    -1 (unless NEGATIVE_OK), a thread count the machine's CPUs + 1: each with one ConfigError line
    naming the key; a thread count equal to the machine's CPUs is accepted."""
    from slamkit.errors import ConfigError
    from slamkit.registry.compose import compose_run
    from slamkit.config import machine_threads

    cases = _numeric_keys()
    threads = [key for _, key, kind in cases if kind == "threads"]
    assert len(cases) > 200 and {"mapping_threads", "tracker.num_threads", "mapper.loss.num_threads"} <= set(threads)
    bad = {"nan": ["nan", "-inf"], "negative": ["-1"], "threads": [str(machine_threads() + 1)]}
    failures = []
    for base, key, kind in cases:
        for value in bad[kind]:
            try:
                compose_run([*base, f"{key}={value}"])
                failures.append(f"{key}={value} accepted")
            except ConfigError as exc:
                if key not in str(exc) or "\n" in str(exc):
                    failures.append(f"{key}={value}: {exc}")
        if kind == "threads":
            run, _ = compose_run([*base, f"{key}={machine_threads()}"])
            node = run
            for name in key.split("."):
                node = getattr(node, name)
            assert node == machine_threads()
    assert not failures, "\n".join(failures)


# --- the checks themselves, quickly --------------------------------------------------------------

def test_camera_plausibility_bounds_follow_the_image_size():
    from slamkit.types import Camera

    tum = Camera(640, 480, 517.3, 516.5, 318.6, 255.3)
    assert tum.implausible() == []
    assert [n for n, _ in Camera(640, 480, 517.3, 516.5, 1e30, float("nan")).implausible()] == ["cx", "cy"]
    # fx for a 1 and a 170 degree field of view across 640 pixels: 36667 and 28.0; fy across 480: 21.0 at 170
    assert Camera(640, 480, 36000.0, 516.5, 320, 240).implausible() == []
    assert [n for n, _ in Camera(640, 480, 37000.0, 20.0, 320, 240).implausible()] == ["fx", "fy"]
    assert [n for n, _ in Camera(0, 480, 517.3, 516.5, 318.6, 255.3).implausible()] == ["width"]


def test_check_values_names_the_key_of_a_nan_and_of_too_many_threads():
    from dataclasses import dataclass, field

    from slamkit.errors import ConfigError
    from slamkit.roles import PluginConfig, check_values, thread_count, unlimited
    from slamkit.config import machine_threads

    @dataclass
    class Inner(PluginConfig):
        weights: list = field(default_factory=lambda: [1.0, 2.0])
        num_threads: int = thread_count(0)
        far: float = unlimited(float("inf"))

    @dataclass
    class Outer(PluginConfig):
        inner: Inner = field(default_factory=Inner)
        step: float = 0.5

    check_values(Outer())
    for bad, key in [(Outer(step=float("nan")), "step"), (Outer(Inner(weights=[1.0, float("inf")])), "inner.weights"),
                     (Outer(Inner(num_threads=machine_threads() + 1)), "inner.num_threads"),
                     (Outer(Inner(far=float("-inf"))), "inner.far")]:
        with pytest.raises(ConfigError, match=f"^{key}: expected"):
            check_values(bad)
