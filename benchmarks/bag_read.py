"""ROS bag read speed: the TUM frames written as ROS1 / ROS2 SQLite3 / ROS2 MCAP bags (raw and
compressed images), read back through `dataset=rosbag`, against the TUM folder reader on the same
frames in the same run (the anchor: PNG decoding). Prints frames/s of opening (the index pass)
and of reading every frame, and writes JSON.

    python benchmarks/bag_read.py --frames 150 --out /tmp/bag_read.json
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))  # the bag writer the tests use

from rosbag_writer import write_tum_bag  # noqa: E402

from slamkit_plugins.datasets.rosbag import RosbagConfig, RosbagDataset  # noqa: E402
from slamkit_plugins.datasets.tum import TUMConfig, TUMDataset  # noqa: E402

TUM = REPO.parent / "shared" / "data" / "tum_fr1_rpy_first150"
BAGS = {  # name -> (storage, colour, depth)
    "ros1_raw": ("ros1", "rgb8", "16UC1"),
    "ros2_sqlite3_raw": ("sqlite3", "rgb8", "16UC1"),
    "ros2_mcap_raw": ("mcap", "rgb8", "16UC1"),
    "ros2_mcap_compressed": ("mcap", "jpeg", "compressedDepth"),
}


def read_all(make) -> dict:
    start = time.perf_counter()
    dataset = make()
    opened = time.perf_counter() - start
    start = time.perf_counter()
    for i in range(len(dataset)):
        dataset[i]
    read = time.perf_counter() - start
    return {"frames": len(dataset), "open_s": opened, "read_s": read, "read_fps": len(dataset) / read}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    results = {"folder_tum": read_all(lambda: TUMDataset(TUMConfig(path=str(TUM), max_frames=args.frames)))}
    work = Path(tempfile.mkdtemp(prefix="bag_read_"))
    try:
        for name, (storage, color, depth) in BAGS.items():
            start = time.perf_counter()
            bag = write_tum_bag(TUM, work / (name + (".bag" if storage == "ros1" else "")), args.frames, storage,
                                color, depth)
            written = time.perf_counter() - start
            size = sum(p.stat().st_size for p in ([bag] if bag.is_file() else bag.rglob("*")) if p.is_file())
            results[name] = read_all(lambda: RosbagDataset(RosbagConfig(path=str(bag), depth_scale=5000.0)))
            results[name].update(write_s=written, size_mb=size / 2**20)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    anchor = results["folder_tum"]["read_fps"]
    print(f"{'reader':24s} {'frames':>6s} {'open s':>7s} {'read fps':>9s} {'vs folder':>9s} {'MB':>6s}")
    for name, r in results.items():
        print(f"{name:24s} {r['frames']:6d} {r['open_s']:7.2f} {r['read_fps']:9.1f} {r['read_fps'] / anchor:9.2f} "
              f"{r.get('size_mb', float('nan')):6.0f}")
    if args.out:
        args.out.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
