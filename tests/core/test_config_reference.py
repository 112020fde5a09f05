"""Every key of the generated configuration reference (docs/configuration.md) is reachable: set
to a valid non-default value through the Hydra composition the `slamkit` command uses, it
arrives in the object the run builds. A misspelt key or a bad value of any part exits with
status 2 and one line naming the key."""

from __future__ import annotations

import enum
import importlib.util
import math
import re
from pathlib import Path

import pytest

from slamkit.errors import ConfigError, SlamkitError
from slamkit.registry import default_registry
from slamkit.registry.compose import compose_run
from slamkit.roles import PARTS as PART_ROLES
from slamkit.run.build import build, build_run

from support.config_reference import BAD, TOP_SECTIONS, config_class, reference_keys

PARTS = {r.key for r in PART_ROLES}

#: Values for the keys whose type alone does not give a valid one (files, folders, addresses).
EXPLICIT = {
    "dataset.intrinsics": "intrinsics.json", "dataset.trajectory": "groundtruth.txt", "dataset.color_dir": "rgb",
    "dataset.depth_dir": "depth", "dataset.gt_path": "{data}/traj.txt", "mapper.keyframe_dir": "{tmp}/keyframes",
    "viewer.save": "{tmp}/x.rrd", "viewer.connect": "rerun+http://127.0.0.1:9876/proxy",
    "viewer.application_id": "slamkit-test", "dataset.cache_dir": "{tmp}/cache", "mapper.rasterizer.prefer": ["torch"],
    "dataset.camera": "fr1", "dataset.max_frames": 5, "dataset.start": 2, "dataset.stride": 2,
    "dataset.path": "{data}", "dataset=tum:dataset.gt_path": "{data}/groundtruth.txt",
    "dataset.camera_path": "room_loop", "dataset.depth_model": "structured_light",
    "dataset.fx": 500.0, "dataset.fy": 500.0,  # plausible for every dataset's image size (Camera.implausible)
    "resume": "{tmp}/run", "map": "{tmp}/run",
    "dataset.color_topic": "/camera/rgb/image_color", "dataset.depth_topic": "/camera/depth/image",
    "dataset.camera_info_topic": "/camera/rgb/camera_info", "dataset.groundtruth": "{data}/groundtruth.txt",
    "objective.metric": "psnr", "viewer.host": "0.0.0.0", "viewer.map_as": "ellipsoids",
    "preset": "paper", "data_root": "{tmp}", "scene": "room0",  # preset: a config group option that sets the key
    "eval.lpips_backbone": "{tmp}/alexnet-owt-7be5be79.pth",
    "dataset=realsense:dataset.groundtruth": "{data_dir}/groundtruth.txt", "dataset.serial": "215122251234",
    "dataset.record": "{tmp}/realsense-record",
}


def candidates(key: str, type_: str, default: str, tmp: Path, data: Path | None = None, section: str = "") -> list:
    """Values to try, in order, for a key: its explicit value, else by its type ({tmp}: a
    temporary folder, {data}: the dataset's folder or file, {data_dir}: the folder it lies in)."""
    section_key = f"{section}:{key}"
    if section_key in EXPLICIT or key in EXPLICIT:
        value = EXPLICIT.get(section_key, EXPLICIT.get(key))
        if isinstance(value, str):
            folder = data if data is None or data.is_dir() else data.parent  # {data_dir}: where a data file lies
            value = value.replace("{tmp}", str(tmp)).replace("{data}", str(data or tmp))
            value = value.replace("{data_dir}", str(folder or tmp))
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
    group, name = section.split("=")
    base = [f"{group}={name}"]
    if group == "dataset" and name != "synthetic":
        base.append(f"dataset.path={data[name]}")
    if group.startswith("mapper/"):
        base.insert(0, "mapper=gaussian_splatting")
    return base


def built_config(key: str, run, slam, viewer, dataset):
    """The config object that the built run holds `key` in (its last segment is the field)."""
    path = key.split(".")[:-1]
    if not path:
        return run
    if path[0] in ("realtime", "eval", "output", "objective", "checkpoint", "localize"):
        return getattr(run, path[0])
    if path[0] == "growth":
        return slam.growth
    objects = {"dataset": dataset, "tracker": slam.tracker, "keyframe": slam.keyframe_policy,
               "mapper": slam.mapper, "viewer": viewer, "loop_closure": slam.loop_closer.closure}
    if path[0] == "mapper" and len(path) > 1 and path[1] in PARTS:
        return getattr(slam.mapper, path[1]).cfg
    cfg = objects[path[0]].cfg
    for name in path[1:]:  # a config nested in the plugin's (mapper.admission)
        cfg = getattr(cfg, name)
    return cfg


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

    from slamkit_plugins.datasets.tum import TUMConfig, TUMDataset

    from support.data import REPLICA, TUM, require_data
    from support.folders import make_folder, make_sevenscenes
    from support.rosbag_writer import write_tum_bag

    root = tmp_path_factory.mktemp("datasets")
    folder = make_folder(root / "folder", TUMDataset(TUMConfig(path=str(require_data(TUM)), max_frames=10)))
    shutil.copytree(folder / "color", folder / "rgb")
    shutil.copy(folder / "gt.txt", folder / "groundtruth.txt")
    (folder / "intrinsics.json").write_text(json.dumps(yaml.safe_load((folder / "intrinsics.yaml").read_text())))
    make_sevenscenes(root / "chess" / "seq-01", n=8)
    bag = write_tum_bag(require_data(TUM), root / "fr1_mcap", 6, "mcap")  # a ROS2 bag folder
    shutil.copy(TUM / "groundtruth.txt", bag / "groundtruth.txt")
    data = {"tum": require_data(TUM), "replica": require_data(REPLICA), "folder": folder,
            "sevenscenes": root / "chess" / "seq-01", "rosbag": bag}
    if importlib.util.find_spec("pyrealsense2") is not None:  # else its section is skipped (the `realsense` extra)
        from support.realsense_writer import write_tum_recording

        (root / "realsense").mkdir()
        data["realsense"] = write_tum_recording(TUM, root / "realsense" / "fr1.db3", 6)
        shutil.copy(TUM / "groundtruth.txt", root / "realsense" / "groundtruth.txt")
    return data


def valid_value(section: str, key: str, type_: str, default: str, tmp: Path, data: dict[str, Path]):
    """The first candidate that the key's config dataclass accepts (its validate() and the rules
    every key shares, `check_values`)."""
    from slamkit.roles import check_values

    field, reasons = key.split(".")[-1], []
    for value in candidates(key, type_, default, tmp, data.get(section.partition("=")[2]), section):
        try:
            check_values(config_class(section, key)(**{field: value}))
            return value
        except (SlamkitError, TypeError, ValueError) as exc:
            reasons.append(f"{value!r}: {exc}")
    raise AssertionError(f"{key}: no valid value found ({'; '.join(reasons)})")


def check_arrivals(section: str, values: dict[str, object], base: list[str]) -> list[str]:
    """Compose the run with `values` set, build it, and list the keys whose value did not arrive."""
    run, names = compose_run([*base, *(override(k, v) for k, v in values.items())])
    built = build(run, default_registry(), names)
    return [f"{key}={value!r} did not arrive" for key, value in values.items()
            if not same(getattr(built_config(key, built.config, built.slam, built.viewer, built.dataset),
                            key.split(".")[-1]), value)]


@pytest.mark.slow
def test_every_key_in_the_reference_reaches_the_object_the_run_builds(data, tmp_path):
    """Each section's keys are set together to non-default values its config accepts; where the
    built run rejects the combination, key by key, naming the key it rejects."""
    rows = reference_keys()
    assert len(rows) > 150 and {"mapper.sampler.top_k", "mapper.rasterizer.num_threads",
                                "mapper.memory_cap.max_gaussians"} <= {k for _, k, _, _ in rows}
    sections: dict[str, dict[str, object]] = {}
    for section, key, type_, default in rows:
        if section == "dataset=realsense" and "realsense" not in data:
            continue  # pyrealsense2 (the `realsense` extra) has no wheel here: tests/plugins/test_realsense.py skips
        if section != "mapper/rasterizer=gsplat":  # needs CUDA: built against a stand-in gsplat in its own tests
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


@pytest.mark.parametrize("select, bad, named", BAD, ids=[b for _, b, _ in BAD])
def test_a_bad_value_or_a_misspelt_key_of_a_part_is_one_line_naming_it(select, bad, named):
    with pytest.raises(ConfigError, match=re.escape(named)) as err:
        build_run(["mapper=gaussian_splatting", select, bad])
    assert "\n" not in str(err.value)
