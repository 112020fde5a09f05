"""Cost of one map update in each viewer, on a run's map.ply: rerun (viewer.map_as = points,
ellipsoids, splats; logging into a .rrd file) and viser (the splat update its worker thread sends:
the copy under the map's lock, the covariances and add_gaussian_splats). Milliseconds per update,
median of --repeats.

    python benchmarks/viewer_map_log.py RUN_DIR/map.ply --repeats 5
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from slamkit.config import RunContext
from slamkit.formats.ply import load_ply
from slamkit.roles import ViewerFrame
from slamkit.types import Camera, Frame, KeyframeKind


def _view(gm) -> ViewerFrame:
    from slamkit_plugins.mappers.none import NoMapper, NoMapperConfig

    mapper = NoMapper(NoMapperConfig(), RunContext(gaussian_map=gm))
    cam = Camera(64, 48, 50.0, 50.0, 31.5, 23.5)
    frame = Frame(0, 0.0, np.zeros((48, 64, 3), np.uint8), np.zeros((48, 64), np.float32), cam)
    return ViewerFrame(frame, np.eye(4), KeyframeKind.NONE, False, np.zeros((1, 3)), np.zeros((0, 3)), gm, mapper)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("ply", type=Path)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    gm = load_ply(args.ply)
    view = _view(gm)
    print(f"{len(gm)} Gaussians from {args.ply}")
    from slamkit_plugins.viewers.rerun_viewer import RerunViewer, RerunViewerConfig

    with tempfile.TemporaryDirectory() as tmp:
        for style in ("points", "ellipsoids", "splats"):
            viewer = RerunViewer(RerunViewerConfig(save=f"{tmp}/{style}.rrd", map_as=style, map_max_points=10**7))
            viewer.start(view.frame.camera, Path(tmp))
            times = []
            for _ in range(args.repeats):
                start = time.perf_counter()
                viewer._log_map(view)
                times.append(time.perf_counter() - start)
            viewer.close(None)
            size = Path(f"{tmp}/{style}.rrd").stat().st_size / args.repeats / 2**20
            print(f"rerun {style:10s} {1e3 * statistics.median(times):7.1f} ms per update, {size:5.1f} MB per update")
        from slamkit_plugins.viewers.viser_viewer import ViserViewer, ViserViewerConfig

        viewer = ViserViewer(ViserViewerConfig(port=0, map_max_points=10**7))
        viewer.start(view.frame.camera, Path(tmp))
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            viewer._send_splats(view)
            times.append(time.perf_counter() - start)
        viewer.close(None)
        print(f"viser splats     {1e3 * statistics.median(times):7.1f} ms per update")


if __name__ == "__main__":
    main()
