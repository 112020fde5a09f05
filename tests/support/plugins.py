"""Third-party plugins made for a test: `make_plugin_dist` writes an importable "installed"
distribution (a dist-info with entry points in the `slamkit` group) into a folder;
`third_party_plugins` writes the registry tests' distribution: a working tracker (`still`), one
that fails to import, one that is no plugin of any role, one whose config Hydra cannot hold."""

from __future__ import annotations

import textwrap
from pathlib import Path


def make_plugin_dist(root: Path, dist: str, modules: dict[str, str], entry_points: dict[str, str]) -> Path:
    """Write an importable 'installed' distribution into `root` (add `root` to sys.path)."""
    info = root / f"{dist.replace('-', '_')}-0.1.dist-info"  # the folder name is parsed at the first "-"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 0.1\n")
    lines = "\n".join(f"{name} = {target}" for name, target in entry_points.items())
    (info / "entry_points.txt").write_text(f"[slamkit]\n{lines}\n")
    for name, source in modules.items():
        (root / f"{name}.py").write_text(textwrap.dedent(source))
    return root


FAKE_TRACKER = """
    from dataclasses import dataclass
    import numpy as np
    from slamkit.plugin import PluginSpec, hookimpl
    from slamkit.roles import PluginConfig, Tracker, require
    from slamkit.types import TrackingResult

    @dataclass
    class StillConfig(PluginConfig):
        '''offset: metres added to x of every pose.'''
        offset: float = 0.0
        fail_at: int = -1
        def validate(self):
            require(self.offset >= 0, "tracker.offset", ">= 0", self.offset)

    class StillTracker(Tracker):
        '''Reports the first pose for every frame, shifted by cfg.offset along x.'''
        def __init__(self, cfg, context=None):
            self.cfg = cfg
        def initialize(self, first_pose):
            self.pose = first_pose.copy()
            self.pose[0, 3] += self.cfg.offset
        def track(self, frame):
            if frame.index == self.cfg.fail_at:
                raise ValueError("simulated failure")
            return TrackingResult(pose=self.pose)

    @hookimpl
    def slamkit_plugins():
        return [PluginSpec("still", StillTracker, StillConfig)]
"""

NOT_A_TRACKER = """
    from dataclasses import dataclass
    from slamkit.plugin import PluginSpec, hookimpl

    @dataclass
    class Cfg:
        x: int = 1

    @hookimpl
    def slamkit_plugins():
        return [PluginSpec("wrong", dict, Cfg)]
"""

ODD_CONFIG = """
    from dataclasses import dataclass, field
    import numpy as np
    from slamkit.plugin import PluginSpec, hookimpl
    from slamkit.roles import Tracker

    @dataclass
    class OddConfig:
        weights: np.ndarray = field(default_factory=lambda: np.ones(3))

    class OddTracker(Tracker):
        def __init__(self, cfg, context=None):
            self.cfg = cfg
        def track(self, frame):
            raise NotImplementedError

    @hookimpl
    def slamkit_plugins():
        return [PluginSpec("odd", OddTracker, OddConfig)]
"""


def third_party_plugins(root: Path) -> Path:
    """The distribution "slamkit-test-plugins" in `root` (add `root` to sys.path): trackers
    `still` (FAKE_TRACKER), `broken`, `wrong` (NOT_A_TRACKER) and `odd` (ODD_CONFIG)."""
    return make_plugin_dist(
        root,
        "slamkit-test-plugins",
        {"still_tracker": FAKE_TRACKER, "broken_plugin": "raise ImportError('needs libfoo')\n",
         "wrong_plugin": NOT_A_TRACKER, "odd_plugin": ODD_CONFIG},
        {"still": "still_tracker", "broken": "broken_plugin", "wrong": "wrong_plugin", "odd": "odd_plugin"},
    )
