"""The top-level run configuration (Hydra structured config) and its validation.

The schema is RunConfig's keys plus one group per run role of `slamkit.roles.RUN_ROLES`, each
holding the selected plugin's config dataclass (registered by
`slamkit.registry.discovery.register_configs`; a mapper's parts are groups nested in its own),
and a defaults list that selects each role's default plugin. Validation turns every group into
its dataclass (running its `validate`) before any work starts.
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass, field, is_dataclass, make_dataclass
from typing import Any, Sequence

from omegaconf import MISSING, DictConfig, OmegaConf

from slamkit.config import PluginConfig, RenderScoring, check_values, method_setting, require, thread_count
from slamkit.errors import ConfigError
from slamkit.map.growth import MapGrowthConfig
from slamkit.roles import RUN_ROLES
from slamkit.scheduling import ThreadPriority

#: Seconds: Python's thread switch interval while real-time mapping runs. Python's default,
#: 5 ms, makes each of a mapping step's torch calls (each releases the GIL and takes it back)
#: wait up to 5 ms for the tracking thread's Python code, and the tracker's kernel calls wait
#: for the mapper's (docs/results.md, "Speed").
SWITCH_INTERVAL_S = 5e-4


class ExistingOutputs(str, enum.Enum):
    """What a new run does with a folder that holds an earlier run's outputs
    (`slamkit.run.ownership`): refuse (one line, nothing touched) or clean (delete them first)."""

    refuse = "refuse"
    clean = "clean"


class Mode(enum.Enum):
    """sequential and realtime build a map (SLAM); localize tracks in a saved map (`map`)."""

    sequential = "sequential"
    realtime = "realtime"
    localize = "localize"


class LoopCorrections(enum.Enum):
    """When the loop closure's corrections move the map, the tracker and the trajectory."""

    during = "during"
    at_end = "at_end"


class Device(enum.Enum):
    """Where the map's tensors (and the keyframes the mapper trains on) live."""

    auto = "auto"
    cpu = "cpu"
    cuda = "cuda"


@dataclass
class RealtimeConfig(PluginConfig):
    """`mode=realtime`: how the input is paced and how mapping shares the machine with tracking
    (docs/architecture.md, "Real time")."""

    #: input frames per second (null: as fast as possible)
    fps_limit: float | None = method_setting(None)
    #: skip a frame when the next one has already arrived (a live camera), not process every one late
    drop_frames: bool = method_setting(False)
    #: seconds: Python's thread switch interval while mapping runs (Python's 0.005 stalls both threads)
    switch_interval: float = SWITCH_INTERVAL_S
    #: mapping's priority (its threads' too): idle (only CPU left over), low (5 nice levels), same
    mapping_priority: ThreadPriority = ThreadPriority.idle
    #: with fps_limit: no mapping step starts while tracking is late on a frame (InputClock.late_after)
    mapping_yields: bool = True
    #: the mapper takes a keyframe (training view, memory cap) in a thread beside tracking (false: inline)
    keyframe_thread: bool = True

    def validate(self) -> None:
        require(self.fps_limit is None or self.fps_limit > 0, "realtime.fps_limit", "null or > 0", self.fps_limit)
        require(0 < self.switch_interval <= 1, "realtime.switch_interval", "in (0, 1] seconds", self.switch_interval)


@dataclass
class EvalConfig(PluginConfig, RenderScoring):
    """How a run is evaluated. A run that loses more than `max_lost_fraction` of the frames it
    takes in (tracking lost or unreadable; dropped frames excluded), or tracks none, has failed:
    it reports no ATE, skips the refinement and the evaluation, and exits with status 3. Its
    scoring keys (lpips, lpips_backbone, psnr_pixels) are `slamkit.config.RenderScoring`'s, which
    the run gives its plugins as this config itself (`RunContext.scoring`)."""

    #: frames between running-ATE updates of the progress (0: off)
    running_ate_every: int = 10
    #: a run losing more than this fraction of its frames has failed (1.0: only one that tracked none)
    max_lost_fraction: float = 0.5
    #: a test of long gaps: drop forced_gap_length frames after every this many, as if tracking had been busy (0: off)
    forced_gap_every: int = 0
    #: frames each forced gap drops (forced_gap_every)
    forced_gap_length: int = 20

    def in_forced_gap(self, position: int) -> bool:
        """Whether the frame at `position` in the stream (0: its first) falls in a forced gap:
        positions N, N+1, .. N+length-1 for N = every, 2 every, ..."""
        every = self.forced_gap_every
        return bool(every) and position >= every and position % every < self.forced_gap_length

    def validate(self) -> None:
        require(0.0 <= self.max_lost_fraction <= 1.0, "eval.max_lost_fraction", "a fraction in [0, 1]",
                self.max_lost_fraction)
        require(self.running_ate_every >= 0, "eval.running_ate_every", "an integer >= 0 (0: off)",
                self.running_ate_every)
        require(self.forced_gap_every >= 0, "eval.forced_gap_every", "an integer >= 0 (0: off)",
                self.forced_gap_every)
        gap_fits = not self.forced_gap_every or self.forced_gap_length < self.forced_gap_every
        require(self.forced_gap_length >= 1 and gap_fits,
                "eval.forced_gap_length", "an integer >= 1, below eval.forced_gap_every", self.forced_gap_length)


@dataclass
class OutputConfig(PluginConfig):
    """What the run shows while it runs and writes into its folder besides its results."""

    #: refuse | clean: a run into a folder holding an earlier run's outputs stops in one line, or deletes them
    existing_outputs: ExistingOutputs = ExistingOutputs.refuse
    #: show progress: a bar on a terminal, else a line every 5 s (stream, refinement, evaluation)
    progress: bool = True
    #: write trajectory.png
    plot: bool = True


@dataclass
class CheckpointConfig(PluginConfig):
    """The run's map checkpoint (RUN_DIR/checkpoint.zip, what `resume=` and `mode=localize` read)."""

    #: write it at the end of the run (what mode=localize and a mapper=none export read; off: small run folders)
    save: bool = False
    #: write it when the run is interrupted (SIGINT, SIGTERM) or fails after the stream, for resume=
    on_interrupt: bool = True
    #: also write it every this many keyframes, and at the end (0: never)
    every_keyframes: int = 0

    def validate(self) -> None:
        require(self.every_keyframes >= 0, "checkpoint.every_keyframes", "an integer >= 0", self.every_keyframes)


@dataclass
class LocalizeConfig(PluginConfig):
    """`mode=localize`: tracking in a saved map, which stays as it is (docs/checkpoints.md). The
    first frame, and any frame where tracking is lost, is placed by global registration of its
    points against the map's trackable Gaussians (FPFH + RANSAC, then G-ICP, with open3d) and
    tracked by the run's tracker from there (the map: `map=RUN_DIR`); it is localised when it
    reaches the three min_* figures (slamkit.run.localization)."""

    #: metres: both clouds are downsampled to this for global registration
    voxel: float = 0.05
    #: a localised frame's least fraction of trackable points with a map Gaussian within correspondence distance
    min_inlier_fraction: float = 0.3
    #: a localised frame's least fraction of the cells seeing the map whose nearest Gaussian lies on its depth
    min_surface_agreement: float = 0.7
    #: a localised frame's least correlation of the map's colours with its own in those cells
    min_color_correlation: float = 0.5
    #: RANSAC's iteration limit
    ransac_iterations: int = 100000
    #: RANSAC's stopping confidence
    ransac_confidence: float = 0.999
    #: RANSAC runs (other seeds) per global registration before the frame counts as not localised
    attempts: int = 3

    def validate(self) -> None:
        require(self.voxel > 0, "localize.voxel", "> 0 metres", self.voxel)
        require(0 <= self.min_inlier_fraction <= 1, "localize.min_inlier_fraction", "in [0, 1]",
                self.min_inlier_fraction)
        require(0 <= self.min_surface_agreement <= 1, "localize.min_surface_agreement", "in [0, 1]",
                self.min_surface_agreement)
        require(0 <= self.min_color_correlation <= 1, "localize.min_color_correlation", "in [0, 1]",
                self.min_color_correlation)
        require(self.ransac_iterations >= 1, "localize.ransac_iterations", "an integer >= 1", self.ransac_iterations)
        require(0 < self.ransac_confidence < 1, "localize.ransac_confidence", "in (0, 1)", self.ransac_confidence)
        require(self.attempts >= 1, "localize.attempts", "an integer >= 1", self.attempts)


@dataclass
class ObjectiveConfig:
    """What a run returns to a Hydra sweeper that optimises (hydra/sweeper=optuna; docs/search.md)."""

    #: the metrics.json key scoring the run (ate_rmse_m, psnr, fps, ...; the sweeper's direction says which way)
    metric: str = "ate_rmse_m"
    #: score of a failed run or one lacking the metric (null: a failed run stops the sweep, exit 2)
    failed_value: float | None = None


@dataclass
class RunConfig(PluginConfig):
    """Top-level keys (`run_schema` adds one group per role)."""

    #: how keyframes grow the map (MapGrowthConfig)
    growth: MapGrowthConfig = field(default_factory=MapGrowthConfig)
    #: with mode=localize, the run folder or checkpoint file of the saved map to localise in
    map: str | None = None
    #: how the run is evaluated (EvalConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    #: real time's pacing and scheduling (RealtimeConfig)
    realtime: RealtimeConfig = field(default_factory=RealtimeConfig)
    #: what the run shows and does with its folder (OutputConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    #: what the run returns to an optimising sweeper (ObjectiveConfig)
    objective: ObjectiveConfig = field(default_factory=ObjectiveConfig)
    #: sequential (fixed mapping steps a frame, deterministic) | realtime | localize (in a saved map)
    mode: Mode = method_setting(Mode.sequential)
    #: mapper steps per frame in sequential mode
    iterations_per_frame: int = method_setting(10)
    #: during: a loop's correction moves the map and the tracker when made | at_end: once, after the stream
    loop_corrections: LoopCorrections = method_setting(LoopCorrections.during)
    #: seed of every random choice
    seed: int = 0
    #: torch threads for mapping (0: every CPU sequential, every CPU but tracking's in real time)
    mapping_threads: int = thread_count(0)
    #: mapping steps after the last frame, the refinement (null: 400 sequential, none in real time as the paper)
    final_iterations: int | None = None
    #: auto | cpu | cuda: where the map and the mapper's keyframes live (auto: the GPU when there is one)
    mapping_device: Device = Device.auto
    #: the map checkpoint (CheckpointConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    #: a run folder (or checkpoint file) whose run this one continues
    resume: str | None = None
    #: mode=localize's settings (LocalizeConfig)
    localize: LocalizeConfig = field(default_factory=LocalizeConfig)
    #: the preset the run's defaults came from, set by `preset=slamkit|paper|paper_unlimited` (docs/paper.md)
    preset: str = method_setting("slamkit")
    #: folder of the paper's sequences as `slamkit-data download paper --root DIR` lays them out
    data_root: str | None = None
    #: a sequence's folder under data_root (what +experiment=paper_replica / paper_tum sweep)
    scene: str | None = None

    def device(self) -> str:
        """The torch device the map lives on ("cpu" or "cuda"); ConfigError when cuda is asked
        for and there is none."""
        import torch

        if self.mapping_device is Device.auto:
            return "cuda" if torch.cuda.is_available() else "cpu"
        require(self.mapping_device is Device.cpu or torch.cuda.is_available(), "mapping_device",
                "cpu or auto on a machine without CUDA", self.mapping_device.value)
        return self.mapping_device.value

    def refinement_iterations(self) -> int:
        """Mapping steps after the stream (`final_iterations`, or the mode's choice)."""
        if self.final_iterations is not None:
            return self.final_iterations
        return 0 if self.mode is Mode.realtime else 400

    def validate(self) -> None:
        require(self.final_iterations is None or self.final_iterations >= 0, "final_iterations",
                "null or an integer >= 0", self.final_iterations)
        require(self.iterations_per_frame >= 0, "iterations_per_frame", ">= 0", self.iterations_per_frame)
        require(self.mapping_threads >= 0, "mapping_threads", "an integer >= 0 (0: automatic)", self.mapping_threads)
        require(0 <= self.seed < 2**32, "seed", "an integer from 0 to 2^32 - 1 (numpy's seed range)", self.seed)
        require(self.mode is not Mode.localize or bool(self.map), "map",
                "a run folder or checkpoint file with mode=localize (map=RUN_DIR)", self.map)
        require(self.mode is not Mode.localize or not self.resume, "resume", "null with mode=localize", self.resume)


def run_groups() -> dict[str, type]:
    """The run's nested groups of keys (`growth.*`, `realtime.*`, ...): each RunConfig field that
    holds a config, its name -> its config class, in declaration order (a new group is a new
    such field, nothing else)."""
    return {f.name: f.default_factory for f in dataclasses.fields(RunConfig)
            if f.default_factory is not dataclasses.MISSING and is_dataclass(f.default_factory)}


def run_schema() -> type:
    """RunConfig with one field per run role (`slamkit.roles.RUN_ROLES`), each the selected
    plugin's config, and a Hydra defaults list that selects each role's default plugin."""
    defaults = [{r.key: r.default} for r in RUN_ROLES] + ["_self_"]
    role_fields = [(r.key, Any, field(default=MISSING)) for r in RUN_ROLES]
    return make_dataclass("SlamkitConfig", [("defaults", list[Any], field(default_factory=lambda: list(defaults)))]
                          + role_fields, bases=(RunConfig,))


def register_run_config() -> None:
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(name="slamkit_schema", node=run_schema())


def check_booleans(cfg: DictConfig, overrides: Sequence[Any]) -> None:
    """ConfigError naming the key for an override (Hydra's parsed `Override`s) that gives a
    boolean key anything but true, false or null: OmegaConf would take `2` or `-1` as true."""
    from omegaconf import BooleanNode

    for override in overrides:
        key = override.key_or_group
        if override.is_delete() or override.is_sweep_override() or "/" in key or key.startswith("hydra"):
            continue
        node: Any = cfg
        for part in key.split("."):
            try:
                node = node._get_node(part) if isinstance(node, DictConfig) else None
            except Exception:  # noqa: BLE001 - not a key of the run config (a group: +experiment=NAME)
                node = None
        value = override.value()
        if isinstance(node, BooleanNode) and not (value is None or isinstance(value, bool)
                                                  or (isinstance(value, str) and value.startswith("${"))):
            raise ConfigError(f"{key}: expected true or false, got {override.get_value_element_as_str()}")


def validate_config(cfg: DictConfig, overrides: Sequence[Any] = ()) -> RunConfig:
    """Turn the composed config into a RunConfig whose groups are the plugins' config
    dataclasses, running every `validate`, then the rules every value shares
    (`slamkit.roles.check_values`: finite numbers, thread counts bounded by the machine), and
    `check_booleans` over the `overrides` it was composed with (Hydra's parsed `Override`s).
    Raises ConfigError (one line naming the key) on a wrong value."""
    check_booleans(cfg, overrides)
    try:
        run = OmegaConf.to_object(cfg)
    except ConfigError:
        raise
    except Exception as exc:  # OmegaConf's own type errors: keep their first line
        raise ConfigError(str(exc).splitlines()[0]) from exc
    if not isinstance(run, RunConfig):
        raise ConfigError(f"expected the slamkit run config, got {type(run).__name__}")
    for r in RUN_ROLES:
        if not is_dataclass(getattr(run, r.key)):
            raise ConfigError(f"{r.key}: no plugin selected (use {r.key}=NAME)")
    check_values(run)
    return live_input_defaults(run, overrides)


def live_input_defaults(run: RunConfig, overrides: Sequence[Any] = ()) -> RunConfig:
    """`run` for a live source (a camera: `DatasetConfig.live`): real time dropping frames, a
    camera not waiting for the run, unless the overrides (Hydra's parsed `Override`s) set
    `mode` or `realtime.drop_frames` themselves. Other sources: `run` as it is."""
    live = getattr(run.dataset, "live", None)
    if live is None or not live():
        return run
    given = {getattr(o, "key_or_group", None) for o in overrides}
    if "mode" not in given and run.mode is Mode.sequential:
        run.mode = Mode.realtime
    if "realtime.drop_frames" not in given:
        run.realtime.drop_frames = True
    return run
