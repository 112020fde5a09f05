"""What a dataset knows of its depth sensor and scenes, as the defaults of the settings that
other parts leave null (`slamkit.config.PluginConfig.resolve`)."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class DatasetTuning:
    """A dataset's depth sensor and scene scale, and the algorithm settings tuned for them.
    The defaults are a hand-held structured-light camera in a room (TUM RGB-D, as the
    reference code tunes it); a dataset plugin gives its own as `Dataset.default_tuning`."""

    #: raw depth-image units per metre (TUM 5000, Replica 6553.5; 0 = depth not stored as integers)
    depth_scale: float = 0.0
    #: metres; depth beyond is not used for tracking (inf = no limit)
    depth_trunc: float = math.inf
    #: metres; the largest plausible Gaussian standard deviation in these scenes (larger ones are pruned)
    max_gaussian_scale: float = 1.0
    #: a tracker samples every n-th pixel in x and y at the native resolution (reference: 5 TUM, 10 Replica)
    tracking_pixel_stride: int = 5
    #: metres; G-ICP's largest correspondence distance for this depth noise (0.03 TUM, 0.02 Replica)
    correspondence_distance: float = 0.03
    #: m^2; a keyframe Gaussian this close to a trackable map Gaussian is not made trackable
    new_gaussian_overlap: float = 1e-3
    #: m^2; a frame point overlaps the map when its squared distance to the nearest map Gaussian is below this
    keyframe_overlap: float = 1e-3
    #: a tracking keyframe when the overlapping fraction drops below this (0.81 TUM, 0.7 Replica)
    keyframe_threshold: float = 0.81
    #: the reference code's tracking target holds map Gaussians more opaque than this (0.09 TUM, 0.05 Replica)
    target_min_opacity: float = 0.09
    #: a depth pixel's colour is its own surface point's (false: colour and depth cameras not registered to each other)
    colour_registered: bool = True
