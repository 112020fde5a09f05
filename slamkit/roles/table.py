"""The one table of roles. The registry, the Hydra config groups, the run's defaults, the plugin
listing (`slamkit-plugins`) and the configuration reference (docs/configuration.md) all come
from it: a new role is a base class and a line here."""

from __future__ import annotations

from dataclasses import dataclass

from slamkit.errors import PluginError
from slamkit.roles.dataset import Dataset
from slamkit.roles.loop_closure import LoopClosure
from slamkit.roles.loss import MappingLoss
from slamkit.roles.mapping import Mapper
from slamkit.roles.optimizer import MapOptimizer
from slamkit.roles.rendering import Rasterizer
from slamkit.roles.sampler import KeyframeSampler
from slamkit.roles.strategy import Strategy
from slamkit.roles.tracking import KeyframePolicy, Tracker
from slamkit.roles.viewer import Viewer


@dataclass(frozen=True)
class Role:
    """A kind of plugin. key: its name (``tracker``, ``rasterizer``). base: the class its
    plugins subclass (how a plugin says which role it fills). default: the plugin used unless
    told otherwise. part_of: the role whose plugins are composed of this one (the mapper's
    parts), None for the run's own roles. summary: one line for listings and the docs."""

    key: str
    base: type
    default: str
    summary: str
    part_of: str | None = None

    @property
    def group(self) -> str:
        """Its Hydra config group, what the command line selects it with: the key for a run's
        role (``tracker=gicp``), nested under its owner for a part (``mapper/rasterizer=cpu``)."""
        return f"{self.part_of}/{self.key}" if self.part_of else self.key

    @property
    def path(self) -> str:
        """Where its config sits in the run config (``tracker``, ``mapper.rasterizer``)."""
        return self.group.replace("/", ".")


ROLES: tuple[Role, ...] = (
    Role("dataset", Dataset, "synthetic", "the RGB-D sequence"),
    Role("tracker", Tracker, "gicp", "estimates each frame's camera pose"),
    Role("keyframe", KeyframePolicy, "overlap", "decides which frames become keyframes"),
    Role("mapper", Mapper, "none", "optimises the shared Gaussian map"),
    Role("rasterizer", Rasterizer, "auto", "renders the Gaussians, differentiably", "mapper"),
    Role("sampler", KeyframeSampler, "random", "chooses the keyframe each training step uses", "mapper"),
    Role("strategy", Strategy, "gsicp", "grows, prunes and bounds the map while it trains", "mapper"),
    Role("optimizer", MapOptimizer, "adam", "updates the Gaussians' parameters from gradients", "mapper"),
    Role("loss", MappingLoss, "l1_ssim_depth", "compares a render with its keyframe", "mapper"),
    Role("loop_closure", LoopClosure, "none", "finds revisited places and corrects the keyframes' poses"),
    Role("viewer", Viewer, "none", "shows or records the run as it goes"),
)

ROLE_KEYS: tuple[str, ...] = tuple(r.key for r in ROLES)
#: The run's own roles (a group each at the top of the run config) and the parts of others.
RUN_ROLES: tuple[Role, ...] = tuple(r for r in ROLES if r.part_of is None)
PARTS: tuple[Role, ...] = tuple(r for r in ROLES if r.part_of is not None)


def role(key: str) -> Role:
    """The role with config key `key`."""
    for r in ROLES:
        if r.key == key:
            return r
    raise KeyError(key)


def role_of(cls: type) -> Role:
    """The role whose base class `cls` subclasses; PluginError if none or several."""
    matches = [r for r in ROLES if isinstance(cls, type) and issubclass(cls, r.base)]
    if len(matches) != 1:
        bases = ", ".join(r.base.__name__ for r in ROLES)
        found = "none" if not matches else " and ".join(r.base.__name__ for r in matches)
        raise PluginError(f"{cls!r} must subclass exactly one role base class ({bases}); it subclasses {found}")
    return matches[0]
