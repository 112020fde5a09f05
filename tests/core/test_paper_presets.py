"""The paper's system as one preset (`preset=paper|paper_unlimited`, docs/paper.md) and the switches
it sets: each arrives in the run the command builds, a later override wins, mapping-only
keyframes' Gaussians stay out of the tracking target, the reference code's loss at pixels
without depth, the strategy's last pruning, the run's scoring settings (LPIPS, PSNR pixels)
reaching the mapper's evaluation, and the effective settings recorded for metrics.json."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from slamkit.errors import DataError
from slamkit.registry import default_registry
from slamkit.registry.compose import compose_run
from slamkit.run.build import build, build_run
from slamkit.run.settings import method_settings
from slamkit.types import KeyframeKind

from support.lpips_weights import SHAPES_BACKBONE, fabricated

#: What preset=paper must set (docs/paper.md, "Differences"), after the dataset's tuning is filled
#: (TUM: the reference code's target opacity 0.09).
PAPER = {"preset": "paper", "mode": "realtime", "realtime.fps_limit": 30.0, "refinement_steps": 0,
         "tracker.target_geometry": "optimised", "tracker.min_target_opacity": 0.09, "tracker.target_min_median": 1e-3,
         "tracker.initial_guess": "previous", "tracker.fallback_to_previous": False, "tracker.coarse_factor": 1.0,
         "keyframe.mapping_every": 10, "growth.mapping_only_trackable": False, "growth.scale_alignment": "z_pow",
         "growth.scale_c": 2.0, "growth.scale_p": 1.5, "mapper.resolution_scale": 1.0,
         "mapper.admission.skip_covered": False, "mapper.strategy.prune_every": 200,
         "mapper.strategy.prune_at_finish": False, "mapper.loss.pixels_without_depth": "zero",
         "eval.psnr_pixels": "all"}


def effective_settings(overrides: list[str]) -> tuple[dict, dict]:
    cfg, names = compose_run(overrides)
    built = build(cfg, default_registry(), names)
    return method_settings(built.config, names), names


def test_preset_paper_sets_every_switch_of_the_papers_system(tum_path):
    settings, names = effective_settings(["preset=paper", "dataset=tum", f"dataset.path={tum_path}"])
    assert {k: settings[k] for k in PAPER} == PAPER
    assert (names["tracker"], names["keyframe"], names["mapper"], names["mapper.sampler"],
            names["mapper.strategy"]) == ("gicp", "overlap", "gaussian_splatting", "random", "gsicp")


def test_preset_paper_unlimited_is_the_same_without_the_input_limit(tum_path):
    paper, _ = effective_settings(["preset=paper", "dataset=tum", f"dataset.path={tum_path}"])
    unlimited, _ = effective_settings(["preset=paper_unlimited", "dataset=tum", f"dataset.path={tum_path}"])
    assert unlimited["realtime.fps_limit"] is None and unlimited["preset"] == "paper_unlimited"
    assert {k: v for k, v in unlimited.items() if k not in ("realtime.fps_limit", "preset")} == \
        {k: v for k, v in paper.items() if k not in ("realtime.fps_limit", "preset")}


def test_the_default_preset_is_slamkits_defaults_and_a_later_override_wins(replica_path):
    default, names = effective_settings(["dataset=replica", f"dataset.path={replica_path}"])
    assert default["preset"] == "slamkit" and names["mapper"] == "none"
    assert (default["mode"], default["tracker.target_geometry"], default["growth.mapping_only_trackable"]) == (
        "sequential", "entry", False)
    paper, _ = effective_settings(["preset=paper", "tracker.target_geometry=entry", "mode=sequential",
                                   "dataset=replica", f"dataset.path={replica_path}"])
    assert (paper["tracker.target_geometry"], paper["mode"], paper["refinement_steps"]) == ("entry", "sequential", 0)
    assert paper["tracker.min_target_opacity"] == 0.05  # Replica's, from the dataset's tuning


@pytest.mark.parametrize("choice, role, left_out_for", [
    ("mapper=none", "mapper", ["gaussian_splatting"]),
    ("tracker=kiss_icp", "tracker", ["gicp"]),
    ("keyframe=every_n", "keyframe", ["overlap"]),
])
def test_a_preset_composes_with_a_plugin_it_does_not_name_and_says_what_it_left_out(tum_path, choice, role,
                                                                                      left_out_for):
    settings, names = effective_settings(["preset=paper", choice, "dataset=tum", f"dataset.path={tum_path}"])
    assert settings["preset_not_applied"] == {role: {"settings_for": left_out_for, "chosen": choice.split("=")[1]}}
    assert (settings["mode"], settings["realtime.fps_limit"], settings["growth.scale_c"]) == ("realtime", 30.0, 2.0)
    if role != "tracker":  # the paper's tracker still has the paper's settings
        assert (settings["tracker.initial_guess"], settings["tracker.target_min_median"]) == ("previous", 1e-3)
    else:
        assert "tracker.initial_guess" not in settings and settings["mapper.admission.skip_covered"] is False


def test_a_mapper_part_the_preset_has_no_settings_for_is_left_out_with_the_rest_applied(tum_path):
    settings, names = effective_settings(["preset=paper", "mapper/strategy=mcmc", "dataset=tum",
                                          f"dataset.path={tum_path}"])
    assert names["mapper.strategy"] == "mcmc"
    assert settings["preset_not_applied"] == {"mapper.strategy": {"settings_for": ["3dgs", "gsicp"], "chosen": "mcmc"}}
    assert (settings["mapper.resolution_scale"], settings["mapper.loss.pixels_without_depth"]) == (1.0, "zero")


#: The method settings of a paper run as 0.3 listed them by name in core (`METHOD_KEYS`), at their
#: keys since 0.4: what the fields marked `method_setting` must give, no more and no less.
LISTED_BEFORE = {
    "preset", "mode", "realtime.fps_limit", "iterations_per_frame", "realtime.drop_frames",
    "tracker.regularization", "tracker.target_geometry", "tracker.min_target_opacity", "tracker.target_min_median",
    "tracker.initial_guess", "tracker.fallback_to_previous", "tracker.retry_unconverged", "tracker.coarse_factor",
    "keyframe.mapping_every", "keyframe.max_interval",
    "growth.initial_shape", "growth.scale_alignment", "growth.scale_c", "growth.scale_p",
    "growth.mapping_only_trackable",
    "mapper.resolution_scale", "mapper.admission.skip_covered", "mapper.strategy.prune_every",
    "mapper.strategy.prune_at_finish", "mapper.loss.pixels_without_depth",
    "eval.psnr_pixels", "eval.lpips",
}


def test_the_method_settings_are_the_fields_marked_on_themselves(tum_path):
    settings, _ = effective_settings(["preset=paper", "dataset=tum", f"dataset.path={tum_path}"])
    added = {"loop_corrections"}  # marked since (when a loop closure's corrections are applied)
    assert set(settings) == LISTED_BEFORE | added | {"refinement_steps", "preset_not_applied"}
    every_n, _ = effective_settings(["keyframe=every_n", "dataset=tum", f"dataset.path={tum_path}"])
    assert every_n["keyframe.tracking_every"] == 30 and "keyframe.max_interval" not in every_n


def test_marked_settings_walk_nested_configs_by_dotted_key_and_skip_unmarked_fields():
    import dataclasses
    import enum

    from slamkit.config import method_setting
    from slamkit.run.settings import marked_settings

    class Colour(enum.Enum):
        red = "red"

    @dataclasses.dataclass
    class Part:
        switch: Colour = method_setting(Colour.red)
        tuning: int = 3

    @dataclasses.dataclass
    class Whole:
        part: Part = dataclasses.field(default_factory=Part)
        steps: int = method_setting(10)
        threads: int = 0

    assert marked_settings(Whole()) == {"part.switch": "red", "steps": 10}


def test_a_key_the_chosen_plugin_lacks_is_one_whole_line_naming_key_plugin_and_its_settings():
    from slamkit.errors import ConfigError

    with pytest.raises(ConfigError) as err:
        compose_run(["preset=paper", "tracker=kiss_icp", "tracker.regularization=none"])
    message = str(err.value)
    assert "\n" not in message
    assert message.startswith("tracker.regularization=none: the tracker 'kiss_icp' has no setting 'regularization'")
    assert "voxel_size" in message and "tracker=NAME" in message


def _mapping_only_rows(trackable: bool, tum_path) -> tuple[torch.Tensor, torch.Tensor]:
    """Trackable flags of the Gaussians that mapping-only keyframes and that tracking keyframes
    added, over 24 TUM frames with a mapping-only keyframe every 3 frames."""
    dataset, slam, _ = build_run(["dataset=tum", f"dataset.path={tum_path}", "dataset.max_frames=24", "mapper=none",
                                  "mapper.keep_untrackable=true", "keyframe.mapping_every=3",
                                  f"growth.mapping_only_trackable={trackable}"])
    slam.initialize(dataset[0].gt_pose)
    kinds = [k for k in (slam.process(dataset[i]).keyframe for i in range(len(dataset))) if k]
    gm = slam.gaussian_map
    mapping_only = torch.tensor([kinds[int(k)] is KeyframeKind.MAPPING_ONLY for k in gm.keyframe_id])
    assert mapping_only.any() and (~mapping_only).any()
    return gm.trackable[mapping_only], gm.trackable[~mapping_only]


def test_mapping_only_keyframes_gaussians_never_enter_the_target_when_switched_off(tum_path):
    off_mapping, off_tracking = _mapping_only_rows(False, tum_path)
    on_mapping, _ = _mapping_only_rows(True, tum_path)
    assert not off_mapping.any() and off_tracking.any()
    assert on_mapping.any()  # today's behaviour: the tracker's trackable points away from the target


def test_loss_with_pixels_without_depth_zeroed_counts_every_pixel_as_the_reference_code():
    from slamkit_plugins.mappers.gaussian_splatting.loss.fused_rgbd_loss import torch_rgbd_loss

    g = torch.Generator().manual_seed(0)
    color, image = torch.rand(16, 20, 3, generator=g), torch.rand(16, 20, 3, generator=g)
    depth, observed = 1 + torch.rand(16, 20, generator=g), 1 + torch.rand(16, 20, generator=g)
    observed[:, :7] = 0  # no depth in the left third
    valid = (observed > 0).float()
    got = torch_rgbd_loss(color, depth, image, observed, 0.8, 0.0, 0.1, 10.0, all_pixels=True)
    expected = 0.8 * (color - image * valid[..., None]).abs().mean() + 0.1 * (depth - observed).abs().mean() / 10
    assert float(got) == pytest.approx(float(expected), rel=1e-6)
    ignore = torch_rgbd_loss(color, depth, image, observed, 0.8, 0.0, 0.1, 10.0)
    m = valid.bool()
    expected_ignore = 0.8 * (color - image).abs()[m].mean() + 0.1 * (depth - observed).abs()[m].mean() / 10
    assert float(ignore) == pytest.approx(float(expected_ignore), rel=1e-6)


def test_the_compiled_loss_refuses_the_reference_codes_pixels_in_one_line():
    from slamkit.errors import ConfigError

    with pytest.raises(ConfigError, match="pixels_without_depth") as err:
        build_run(["mapper=gaussian_splatting", "mapper.loss.backend=compiled",
                   "mapper.loss.pixels_without_depth=zero"])
    assert "\n" not in str(err.value)


def test_no_pruning_after_the_last_step_when_prune_at_finish_is_off():
    from slamkit.map.gaussian_map import GaussianMap, GaussianRows
    from slamkit.roles import MapEdit
    from slamkit_plugins.mappers.gaussian_splatting.optimizer.adam import AdamConfig, TorchAdam
    from slamkit_plugins.mappers.gaussian_splatting.strategy.gsicp import PruneConfig, PruneStrategy

    def finished(prune_at_finish: bool) -> int:
        gm = GaussianMap()
        n = 10
        gm.append(GaussianRows.from_shapes(np.zeros((n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)), np.full((n, 3), 0.01),
                                           np.full((n, 3), 0.5), np.r_[np.full(5, 0.001), np.full(5, 0.5)],
                                           np.ones(n, bool), 0))
        strategy = PruneStrategy(PruneConfig(max_scale=1.0, prune_at_finish=prune_at_finish))
        edit = MapEdit(gm, TorchAdam(AdamConfig()), strategy.state)
        strategy.finish(edit)
        return len(gm)

    assert finished(True) == 5 and finished(False) == 10  # the five nearly transparent ones


def test_lpips_on_without_its_weights_stops_before_any_work_in_one_line(tmp_path):
    missing = tmp_path / "alexnet.pth"
    with pytest.raises(DataError, match="alexnet-owt-7be5be79.pth") as err:
        build_run(["mapper=gaussian_splatting", "eval.lpips=on", f"eval.lpips_backbone={missing}"])
    assert "\n" not in str(err.value) and str(missing) in str(err.value)


def test_the_mappers_evaluation_scores_with_the_runs_lpips_and_psnr_pixels(tum_path, tmp_path):

    from slamkit.metrics.lpips_weights import installed_linear_path

    if installed_linear_path() is None:
        pytest.skip("the lpips wheel (its v0.1 linear weights) is not installed")
    backbone = tmp_path / "alexnet.pth"
    torch.save(fabricated(SHAPES_BACKBONE, 0), backbone)
    scores = {}
    for pixels in ("valid", "all"):
        dataset, slam, _ = build_run(["dataset=tum", f"dataset.path={tum_path}", "dataset.max_frames=2",
                                      "mapper=gaussian_splatting", "mapper.resolution_scale=0.25",
                                      "iterations_per_frame=2",
                                      "mapper.eval_every=5", "mapper.save_images=0", "eval.lpips=on",
                                      f"eval.lpips_backbone={backbone}", f"eval.psnr_pixels={pixels}"])
        slam.initialize(dataset[0].gt_pose)
        poses = [slam.process(dataset[i]).tracking.pose for i in range(len(dataset))]
        scores[pixels] = slam.evaluate(dataset, poses, tmp_path)
    valid_fraction = float((torch.as_tensor(np.asarray(dataset[0].depth)) > 0).float().mean())
    assert scores["valid"]["eval_frames"] == 1 and valid_fraction < 0.99
    # over every pixel, those without depth zeroed in both: the MSE shrinks by the valid fraction
    assert scores["all"]["psnr"] - scores["valid"]["psnr"] == pytest.approx(-10 * math.log10(valid_fraction), abs=1e-3)
    assert 0 < scores["all"]["lpips"] == scores["valid"]["lpips"] < 2 and scores["all"]["lpips_train"] is not None


def test_renders_too_small_for_lpips_record_it_as_null_instead_of_failing(tum_path, caplog):
    from slamkit.metrics.lpips_network import min_image_side
    from slamkit.roles.rendering import RenderOutput
    from slamkit_plugins.mappers.gaussian_splatting.evaluation import evaluate_renders

    dataset, slam, _ = build_run(["dataset=tum", f"dataset.path={tum_path}", "dataset.max_frames=1"])
    frames = [dataset[0]]

    def render(pose, camera):
        shape = (camera.height, camera.width)
        return RenderOutput(color=torch.zeros(*shape, 3), depth=torch.ones(shape), alpha=torch.ones(shape))

    def never(*args):
        raise AssertionError("LPIPS called on an image smaller than its network takes")

    scale = (min_image_side() - 1) / frames[0].camera.height  # one pixel short
    with caplog.at_level("WARNING"):
        metrics = evaluate_renders(render, slam.gaussian_map, frames, [frames[0].gt_pose], set(), scale=scale,
                                   lpips=never)
    assert metrics["lpips"] is None and isinstance(metrics["psnr"], float)
    assert "LPIPS is null" in caplog.text
