"""`dataset=synthetic`: the built-in synthetic RGB-D sequence, a furnished room rendered along a
hand-held path.

Nothing is downloaded: the scene is analytic (a 6 x 5 x 3 m room seen from inside, with
furniture, a door, a window and pictures), rendered by vectorised numpy ray casting against
boxes, spheres and cylinders, each surface with its own procedural texture shaded by a fixed
directional light. Depth is exact (the camera-frame z of the hit, no holes) and ground truth is
the rendering pose. `seed` draws the camera path (`camera_path`: a hand-held wander, or one of the
paths that come back, for loop closure); the scene itself never changes. `depth_model`
gives the sensor's errors: Gaussian, or a structured-light (Kinect v1) model (`sensor`). World frame:
metres, z up, the floor at z = 0, x in [-3, 3], y in [-2.5, 2.5]; poses camera-to-world, OpenCV
camera axes. Modules: `textures`, `primitives` (shapes, ray tests), `materials` (each surface's
colours), `scene` (the room), `raycast` (`render`), `path` (`handheld_path`, `loop_path`), `sensor`
(the structured-light model), `dataset` (the plugin).
"""

from slamkit.plugin import PluginSpec, hookimpl
from slamkit_plugins.datasets.synthetic.dataset import (
    DEPTH_SCALE,
    GENERATOR_VERSION,
    SyntheticConfig,
    SyntheticDataset,
    default_cache_dir,
)
from slamkit_plugins.datasets.synthetic.path import FPS, LOOP_PATHS, PATH_BOUNDS, from_rest, handheld_path, loop_path
from slamkit_plugins.datasets.synthetic.raycast import render
from slamkit_plugins.datasets.synthetic.scene import ROOM_HI, ROOM_LO, scene, scene_clearance

__all__ = ["DEPTH_SCALE", "FPS", "GENERATOR_VERSION", "LOOP_PATHS", "PATH_BOUNDS", "ROOM_HI", "ROOM_LO",
           "SyntheticConfig", "SyntheticDataset", "default_cache_dir", "from_rest", "handheld_path", "loop_path",
           "render", "scene", "scene_clearance"]


@hookimpl
def slamkit_plugins():
    return [PluginSpec("synthetic", SyntheticDataset, SyntheticConfig)]
