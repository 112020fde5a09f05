"""Which RealSense library `dataset=realsense` uses, by what each does here (no timing): Intel's
`pyrealsense2` (the `realsense` extra) against open3d's RealSense reader (`open3d.t.io`, which
the `mesh` extra installs). For each: its version and installed size, whether it enumerates
devices without one connected, writes a recording with no camera (the tests need one), and
opens and plays that recording with its frames intact. Then what the chosen one gives a run: the
TUM fr1/rpy frames written as a recording and played back through `slamkit dataset=realsense`,
sequentially (G-ICP tracking, mapper=none), against the same run on the TUM folder (ATE, largest
pose difference). `--format db3` (the default): the .db3 that SDK 2.59 records, written by its
software device and recorder; `--format bag`: the SDK's older ROS1 .bag, written with rosbags
in the SDK's layout (slamkit_plugins.datasets.realsense.bag).

    python benchmarks/realsense_library.py --data ../shared/data/tum_fr1_rpy_first150 \\
        --frames 150 --out benchmarks/results/realsense/library.json
    python benchmarks/realsense_library.py --data ../shared/data/tum_fr1_rpy_first150 \\
        --frames 150 --format bag --out benchmarks/results/realsense/library_bag.json
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from slamkit.formats.tum import read_tum_trajectory


def installed_mb(dist: str) -> float | None:
    """Megabytes of the files pip installed for distribution `dist` (None: not installed)."""
    try:
        files = importlib.metadata.distribution(dist).files or []
    except importlib.metadata.PackageNotFoundError:
        return None
    return round(sum(f.locate().stat().st_size for f in files if f.locate().is_file()) / 2**20, 1)


def version(dist: str) -> str | None:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


def pyrealsense2_facts(recording: Path, tum: Path, frames: int, fmt: str) -> dict:
    from slamkit_plugins.datasets.realsense import RealSenseConfig, RealSenseDataset, sdk
    from slamkit_plugins.datasets.tum import TUMConfig, TUMDataset

    ds = RealSenseDataset(RealSenseConfig(path=str(recording)))
    ref = TUMDataset(TUMConfig(path=str(tum), max_frames=frames))
    rgb_equal, depth_diff, stamp_diff = True, 0.0, 0.0
    for i in range(len(ds)):
        got, want = ds[i], ref[i]
        rgb_equal &= bool(np.array_equal(np.asarray(got.rgb), np.asarray(want.rgb)))
        depth_diff = max(depth_diff, float(np.abs(got.depth - want.depth).max()))
        stamp_diff = max(stamp_diff, abs(got.timestamp - want.timestamp))
    facts = {"devices_without_a_camera": len(sdk.list_devices()), "writes_a_recording_without_a_camera": True,
             f"opens_the_{fmt}": True, "frames_played": len(ds), "frames_written": len(ref),
             "colour_identical": rgb_equal, "depth_max_difference_m": depth_diff,
             "timestamp_max_difference_s": stamp_diff, "depth_scale_m": ds.stream.depth_scale,
             "intrinsics": [ds.camera.fx, ds.camera.fy, ds.camera.cx, ds.camera.cy]}
    ds.close()
    return facts


def open3d_facts(recording: Path, fmt: str) -> dict:
    import open3d as o3d

    reader = o3d.t.io.RSBagReader()
    opened = bool(reader.open(str(recording)))
    return {"devices_without_a_camera": int(bool(o3d.t.io.RealSenseSensor.list_devices())),
            "writes_a_recording_without_a_camera": any("software" in n.lower() for n in dir(o3d.t.io)),
            f"opens_the_{fmt}": opened, "reader": "open3d.t.io.RSBagReader", "camera": "open3d.t.io.RealSenseSensor"}


def run(out_dir: Path, *args: str) -> tuple[np.ndarray, np.ndarray, dict]:
    exe = Path(sys.executable).with_name("slamkit")
    common = ["mapper=none", "output.progress=false", "output.plot=false", f"hydra.run.dir={out_dir}"]
    proc = subprocess.run([str(exe), *args, *common], capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"slamkit {' '.join(args)} failed: {proc.stderr[-2000:]}")
    t, poses = read_tum_trajectory(out_dir / "trajectory.txt")
    return t, poses, json.loads((out_dir / "metrics.json").read_text())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="a TUM RGB-D folder")
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--format", choices=("db3", "bag"), default="db3",
                        help="the recording played: the .db3 SDK 2.59 records, or the older ROS1 .bag")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    from slamkit_plugins.datasets.realsense.bag import write_bag_recording
    from slamkit_plugins.datasets.realsense.writer import write_recording
    from slamkit_plugins.datasets.tum import TUMConfig, TUMDataset

    with tempfile.TemporaryDirectory(prefix="realsense-library-") as tmp:
        tmp = Path(tmp)
        fmt = args.format
        write = write_bag_recording if fmt == "bag" else write_recording
        recording = write(TUMDataset(TUMConfig(path=str(args.data), max_frames=args.frames)), tmp / f"tum.{fmt}",
                          5000.0)
        libraries = {
            "pyrealsense2": {"version": version("pyrealsense2"), "installed_mb": installed_mb("pyrealsense2"),
                             **pyrealsense2_facts(recording, args.data, args.frames, fmt)},
            "open3d": {"version": version("open3d-cpu") or version("open3d"),
                       "installed_mb": installed_mb("open3d-cpu") or installed_mb("open3d"),
                       **open3d_facts(recording, fmt)},
        }
        t_f, p_f, m_f = run(tmp / "folder", "dataset=tum", f"dataset.path={args.data}",
                            f"dataset.max_frames={args.frames}")
        t_r, p_r, m_r = run(tmp / fmt, "dataset=realsense", f"dataset.path={recording}",
                            f"dataset.groundtruth={args.data / 'groundtruth.txt'}")
    same = len(t_f) == len(t_r)
    result = {
        "command": " ".join(["python", "benchmarks/realsense_library.py", *sys.argv[1:]]),
        "machine": {"python": platform.python_version(), "platform": platform.platform()},
        "libraries": libraries,
        "run": {"frames": args.frames, "tracker": "gicp", "mapper": "none", "mode": "sequential",
                "recording": {"db3": "pyrealsense2's software_device and recorder",
                              "bag": "rosbags, the SDK's ROS1 layout (slamkit_plugins.datasets.realsense.bag)"}[fmt],
                "folder_ate_rmse_m": m_f["ate_rmse_m"], f"{fmt}_ate_rmse_m": m_r["ate_rmse_m"],
                "folder_frames": len(t_f), f"{fmt}_frames": len(t_r),
                "max_position_difference_m": float(np.abs(p_f[:, :3, 3] - p_r[:, :3, 3]).max()) if same else None,
                "max_timestamp_difference_s": float(np.abs(t_f - t_r).max()) if same else None},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
