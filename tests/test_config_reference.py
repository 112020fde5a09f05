"""Every key of the generated configuration reference (docs/configuration.md) is reachable: set
to a valid non-default value through the Hydra composition the `slamkit` command uses, it
arrives in the object the run builds. A misspelt key or a bad value of any part exits with
status 2 and one line naming the key."""

from __future__ import annotations

import enum
import math
import re
from pathlib import Path

import pytest

from conftest import REPO, run_slamkit
from slamkit.errors import ConfigError, SlamkitError
from slamkit.registry import default_registry
from slamkit.registry.compose import build_run, compose_run
from slamkit.run.pipeline import build
from slamkit.roles import ROLES

REFERENCE = REPO / "docs" / "configuration.md"
PARTS = {r.key for r in ROLES if r.part_of == "mapper"}

#: Values for the keys whose type alone does not give a valid one (files, folders, addresses).
EXPLICIT = {
    "dataset.intrinsics": "intrinsics.json", "dataset.trajectory": "groundtruth.txt", "dataset.color_dir": "rgb",
    "dataset.depth_dir": "depth", "dataset.gt_path": "{data}/traj.txt", "mapper.keyframe_dir": "{tmp}/keyframes",
    "viewer.save": "{tmp}/x.rrd", "viewer.connect": "rerun+http://127.0.0.1:9876/proxy",
    "viewer.application_id": "slamkit-test", "dataset.cache_dir": "{tmp}/cache", "rasterizer.prefer": ["torch"],
    "dataset.camera": "fr1", "dataset.max_frames": 5, "dataset.start": 2, "dataset.stride": 2,
    "dataset.path": "{data}", "dataset=tum:dataset.gt_path": "{data}/groundtruth.txt",
    "dataset.fx": 500.0, "dataset.fy": 500.0,  # plausible for every dataset's image size (Camera.implausible)
    "resume": "{tmp}/run", "localize.map": "{tmp}/run",
    "dataset.color_topic": "/camera/rgb/image_color", "dataset.depth_topic": "/camera/depth/image",
    "dataset.camera_info_topic": "/camera/rgb/camera_info", "dataset.groundtruth": "{data}/groundtruth.txt",
    "objective.metric": "psnr", "viewer.host": "0.0.0.0", "viewer.map_as": "ellipsoids",
}
#: Top-level sections of keys that are not a role's (section -> the RunConfig field holding them).
TOP_SECTIONS = ("map", "eval", "objective", "checkpoint", "localize")


def reference_keys() -> list[tuple[str, str, str, str]]:
    """(section, key, type, default) of every row of docs/configuration.md; section is "" for the
    top level, "map" / "eval" / "objective", or "role=name"."""
    rows, section = [], ""
    for line in REFERENCE.read_text().splitlines():
        heading = re.match(r"#+ `(\w+)(?:=(\w+)|\.\*)`", line)
        if heading:
            section = f"{heading.group(1)}={heading.group(2)}" if heading.group(2) else heading.group(1)
            if heading.group(2) is None and heading.group(1) in {r.key for r in ROLES}:
                section = ""  # the role's heading before its plugins
        cells = [c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", line)[1:-1]]
        if len(cells) == 4 and re.fullmatch(r"`[\w.]+`", cells[0]):
            rows.append((section, cells[0].strip("`"), cells[1], cells[2].strip("`")))
    return rows


def candidates(key: str, type_: str, default: str, tmp: Path, data: Path | None = None, section: str = "") -> list:
    """Values to try, in order, for a key: its explicit value, else by its type ({tmp}: a
    temporary folder, {data}: the dataset's folder)."""
    section_key = f"{section}:{key}"
    if section_key in EXPLICIT or key in EXPLICIT:
        value = EXPLICIT.get(section_key, EXPLICIT.get(key))
        if isinstance(value, str):
            value = value.replace("{tmp}", str(tmp)).replace("{data}", str(data or tmp))
        return [value]
    kinds = [t.strip() for t in type_.split("|")]
    if "bool" in kinds:
        return [default != "True"]
    if len(kinds) > 1 and not {"int", "float", "str", "null"} >= set(kinds):
        return [k for k in kinds if k not in (default, "null")]  # an enum: another member
    if "int" in kinds:
        d = int(default) if default not in ("null", "") else None
        return ([d + 1, 2 * d, d - 1] if d is not None else []) + [2, 5, 1, 100, 3]
    if "float" in kinds:
        d = float(default) if default not in ("null", "") else None
        return ([d * 1.5, d * 0.5, d + 0.1, d - 0.1] if d is not None and math.isfinite(d) else []) + \
            [0.5, 2.0, 0.05, 10.0, 0.9]
    raise AssertionError(f"{key}: no candidate value for type {type_}")


def base_overrides(section: str, tmp: Path, data: dict[str, Path]) -> list[str]:
    """What selects the plugin a key belongs to (and the data it needs)."""
    if not section or section in TOP_SECTIONS:
        return []
    role, name = section.split("=")
    base = [f"{role}={name}"]
    if role == "dataset" and name != "synthetic":
        base.append(f"dataset.path={data[name]}")
    if role in PARTS:
        base.append("mapper=gaussian_splatting")
    return base


def built_config(section: str, key: str, run, slam, viewer, dataset):
    """The config object the built run holds for `key`'s group."""
    group = key.split(".")[0] if "." in key else ""
    if not group:
        return run
    if group in ("eval", "objective", "checkpoint", "localize"):
        return getattr(run, group)
    if group == "map":
        return slam.map_growth
    if group == "loop_closure":  # not yet part of the built run (issue 35's integration): built from the run's config
        return default_registry().create("loop_closure", section.partition("=")[2], run.loop_closure).cfg
    objects = {"dataset": dataset, "tracker": slam.tracker, "keyframe": slam.keyframe_policy,
               "mapper": slam.mapper, "viewer": viewer}
    obj = objects[group] if group in objects else getattr(slam.mapper, group)
    return obj.cfg


def same(actual, expected) -> bool:
    if isinstance(actual, enum.Enum):
        actual = actual.value
    if isinstance(expected, float) or isinstance(actual, float):
        return actual is not None and math.isclose(float(actual), float(expected), rel_tol=1e-9)
    return list(actual) == list(expected) if isinstance(expected, list) else actual == expected


def override(key: str, value) -> str:
    if isinstance(value, list):
        return f"{key}=[{','.join(value)}]"
    return f"{key}={value}"


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> dict[str, Path]:
    """Every dataset's folder: the shared TUM and Replica data; a folder dataset made from TUM
    frames (with the alternative files the keys name); a generated 7-Scenes sequence."""
    import json
    import shutil

    import yaml

    from conftest import REPLICA, TUM, require_data
    from slamkit_plugins.datasets.tum import TUMConfig, TUMDataset
    from test_datasets import make_sevenscenes
    from test_folder_dataset import make_folder
    from rosbag_writer import write_tum_bag

    root = tmp_path_factory.mktemp("datasets")
    folder = make_folder(root / "folder", TUMDataset(TUMConfig(path=str(require_data(TUM)), max_frames=10)))
    shutil.copytree(folder / "color", folder / "rgb")
    shutil.copy(folder / "gt.txt", folder / "groundtruth.txt")
    (folder / "intrinsics.json").write_text(json.dumps(yaml.safe_load((folder / "intrinsics.yaml").read_text())))
    make_sevenscenes(root / "chess" / "seq-01", n=8)
    bag = write_tum_bag(require_data(TUM), root / "fr1_mcap", 6, "mcap")  # a ROS2 bag folder
    shutil.copy(TUM / "groundtruth.txt", bag / "groundtruth.txt")
    return {"tum": require_data(TUM), "replica": require_data(REPLICA), "folder": folder,
            "sevenscenes": root / "chess" / "seq-01", "rosbag": bag}


def config_class(section: str) -> type:
    """The dataclass that holds a section's keys."""
    from slamkit.map.growth import MapGrowthConfig
    from slamkit.registry.schema import CheckpointConfig, EvalConfig, LocalizeConfig, ObjectiveConfig, RunConfig

    if section in ("", *TOP_SECTIONS):
        return {"": RunConfig, "map": MapGrowthConfig, "eval": EvalConfig, "objective": ObjectiveConfig,
                "checkpoint": CheckpointConfig, "localize": LocalizeConfig}[section]
    role, name = section.split("=")
    return default_registry().get(role, name).config


def valid_value(section: str, key: str, type_: str, default: str, tmp: Path, data: dict[str, Path]):
    """The first candidate that the key's config dataclass accepts (its validate() and the rules
    every key shares, `check_values`)."""
    from slamkit.roles import check_values

    field, reasons = key.split(".")[-1], []
    for value in candidates(key, type_, default, tmp, data.get(section.partition("=")[2]), section):
        try:
            check_values(config_class(section)(**{field: value}))
            return value
        except (SlamkitError, TypeError, ValueError) as exc:
            reasons.append(f"{value!r}: {exc}")
    raise AssertionError(f"{key}: no valid value found ({'; '.join(reasons)})")


def check_arrivals(section: str, values: dict[str, object], base: list[str]) -> list[str]:
    """Compose the run with `values` set, build it, and list the keys whose value did not arrive."""
    run, names = compose_run([*base, *(override(k, v) for k, v in values.items())])
    dataset, slam, viewer = build(run, default_registry(), names)
    return [f"{key}={value!r} did not arrive" for key, value in values.items()
            if not same(getattr(built_config(section, key, run, slam, viewer, dataset), key.split(".")[-1]), value)]


@pytest.mark.slow
def test_every_key_in_the_reference_reaches_the_object_the_run_builds(data, tmp_path):
    """Each section's keys are set together to non-default values its config accepts; where the
    built run rejects the combination, key by key, naming the key it rejects."""
    rows = reference_keys()
    assert len(rows) > 150 and {"sampler.top_k", "rasterizer.num_threads", "strategy.max_gaussians"} <= {
        k for _, k, _, _ in rows}
    sections: dict[str, dict[str, object]] = {}
    for section, key, type_, default in rows:
        if section != "rasterizer=gsplat":  # needs CUDA: built against a stand-in gsplat in its own tests
            sections.setdefault(section, {})[key] = valid_value(section, key, type_, default, tmp_path, data)
    missed = []
    for section, values in sections.items():
        base = base_overrides(section, tmp_path, data)
        try:
            missed += check_arrivals(section, values, base)
        except SlamkitError:
            for key, value in values.items():
                try:
                    missed += check_arrivals(section, {key: value}, base)
                except SlamkitError as exc:
                    missed.append(f"{section}: {key}={value!r} rejected: {exc}")
    assert not missed, "\n".join(missed)


BAD = [
    ("sampler=covisible", "sampler.top_k=-1", "sampler.top_k"),
    ("rasterizer=gsplat", "rasterizer.tile_size=0", "rasterizer.tile_size"),
    ("rasterizer=torch", "rasterizer.max_pairs_per_chunk=10", "rasterizer.max_pairs_per_chunk"),
    ("rasterizer=cpu", "rasterizer.num_threads=-2", "rasterizer.num_threads"),
    ("strategy=3dgs", "strategy.grad_threshold=0", "strategy.grad_threshold"),
    ("optimizer=adam", "optimizer.lr_means=-1", "optimizer.lr_means"),
    ("loss=l1_ssim_depth", "loss.weight_ssim=-0.2", "loss.weight_ssim"),
    ("strategy=gsicp", "strategy.prune_evry=100", "prune_evry"),
    ("sampler=covisible", "sampler.topk=3", "topk"),
    ("optimizer=visible_adam", "optimizer.only_visible=maybe", "optimizer.only_visible"),
]


@pytest.mark.parametrize("select, bad, named", BAD, ids=[b for _, b, _ in BAD])
def test_a_bad_value_or_a_misspelt_key_of_a_part_is_one_line_naming_it(select, bad, named):
    with pytest.raises(ConfigError, match=re.escape(named)) as err:
        build_run(["mapper=gaussian_splatting", select, bad])
    assert "\n" not in str(err.value)


@pytest.mark.slow
def test_the_command_exits_2_with_one_line_for_each(tmp_path):
    for select, bad, named in BAD[::3]:
        proc = run_slamkit("mapper=gaussian_splatting", select, bad, f"hydra.run.dir={tmp_path / 'x'}", cwd=tmp_path)
        assert proc.returncode == 2, (bad, proc.stderr[-500:])
        last = proc.stderr.strip().splitlines()[-1]
        assert last.startswith("slamkit: error: ") and named in last and "Traceback" not in proc.stderr
