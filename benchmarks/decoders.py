"""CPU per image of the frame reader's decoders on the shared sequences' files: Pillow, OpenCV
(opencv-python-headless), imageio, simplejpeg (JPEG), pyspng and imagecodecs (PNG; where
installed), each checked to give Pillow's array exactly.

The decoders are timed in one process, in turns (every round decodes every image with every
decoder, in an order that rotates), by the calling thread's CPU time (`time.thread_time`): on a
shared machine the medians of many rounds compare decoders fairly where wall times do not.

    python benchmarks/decoders.py --rounds 30 --images 12 --out benchmarks/results/decoders.json

Then the frame reader itself (`slamkit.formats.images.read_rgbd`: colour checked or decoded,
depth decoded and converted to metres), as it reads a frame of each sequence, with imagecodecs
and on Pillow alone (as where imagecodecs is not installed), in turns.

Prints tables (median CPU ms per image or frame, and the ratio to Pillow) and writes JSON (`--out`).
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path
from typing import Callable

import numpy as np
from PIL import Image

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def _files(kind: str, count: int) -> list[Path]:
    globs = {
        "tum colour png": ("tum_fr1_rpy_first150/rgb", "*.png"),
        "tum depth png16": ("tum_fr1_rpy_first150/depth", "*.png"),
        "7scenes colour jpeg": ("7scenes_redkitchen_300to999", "*.color.jpg"),
        "7scenes depth png16": ("7scenes_redkitchen_300to999", "*.depth.png"),
        "replica colour jpeg": ("replica_room0_first20/results", "frame*.jpg"),
        "replica depth png16": ("replica_room0_first20/results", "depth*.png"),
    }
    folder, pattern = globs[kind]
    found = sorted((DATA / folder).glob(pattern))
    step = max(1, len(found) // count)
    return found[::step][:count]


def pillow(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im)


def _decoders(kind: str) -> dict[str, Callable[[Path], np.ndarray]]:
    """The decoders that can read `kind`, by name (only those installed)."""
    colour, jpeg = "colour" in kind, "jpeg" in kind
    found: dict[str, Callable[[Path], np.ndarray]] = {"pillow": pillow}
    try:
        import cv2

        if colour:
            found["opencv"] = lambda p: cv2.imread(str(p), cv2.IMREAD_COLOR_RGB)
            found["opencv (bytes)"] = lambda p: cv2.imdecode(np.fromfile(p, np.uint8), cv2.IMREAD_COLOR_RGB)
        else:
            found["opencv"] = lambda p: cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            found["opencv (bytes)"] = lambda p: cv2.imdecode(np.fromfile(p, np.uint8), cv2.IMREAD_UNCHANGED)
    except ImportError:
        pass
    try:
        import imageio.v3 as iio

        found["imageio"] = lambda p: iio.imread(p)
    except ImportError:
        pass
    if jpeg:
        try:
            import simplejpeg

            found["simplejpeg"] = lambda p: simplejpeg.decode_jpeg(p.read_bytes(), colorspace="RGB")
        except ImportError:
            pass
    else:
        try:
            import pyspng

            found["pyspng"] = lambda p: pyspng.load(p.read_bytes())
        except ImportError:
            pass
    try:
        import imagecodecs

        decode = imagecodecs.jpeg8_decode if jpeg else imagecodecs.png_decode
        found["imagecodecs"] = lambda p: decode(p.read_bytes())
    except (ImportError, AttributeError):
        pass
    return found


def measure(kind: str, images: int, rounds: int) -> dict:
    files = _files(kind, images)
    decoders = _decoders(kind)
    reference = {p: pillow(p) for p in files}
    identical = {}
    for name, decode in decoders.items():
        identical[name] = all(np.array_equal(decode(p), reference[p]) and decode(p).dtype == reference[p].dtype
                              for p in files)
    names = list(decoders)
    cpu: dict[str, list[float]] = {n: [] for n in names}
    for r in range(rounds):
        order = names[r % len(names):] + names[:r % len(names)]
        for p in files:
            for name in order:
                start = time.thread_time()
                decoders[name](p)
                cpu[name].append(time.thread_time() - start)
    medians = {n: statistics.median(v) * 1e3 for n, v in cpu.items()}
    return {"files": len(files), "rounds": rounds, "example": str(files[0]),
            "median_cpu_ms": medians, "ratio_to_pillow": {n: medians[n] / medians["pillow"] for n in names},
            "identical_to_pillow": identical}


READER_SEQUENCES = {  # dataset overrides of the frame reader's measurement
    "tum": ["dataset=tum", f"dataset.path={DATA / 'tum_fr1_rpy_first150'}"],
    "7scenes": ["dataset=sevenscenes", f"dataset.path={DATA / '7scenes_redkitchen_300to999'}"],
    "replica": ["dataset=replica", f"dataset.path={DATA / 'replica_room0_first20'}"],
}


def measure_reader(sequence: str, frames: int, rounds: int) -> dict:
    """Median CPU ms per frame of `read_rgbd` with imagecodecs and with Pillow alone."""
    from slamkit.formats import images
    from slamkit.run.build import build_run

    dataset, _, _ = build_run(READER_SEQUENCES[sequence] + ["mapper=none"])
    picked = list(range(0, len(dataset), max(1, len(dataset) // frames)))[:frames]
    invalid = (65535,) if sequence == "7scenes" else ()
    scale = dataset.tuning.depth_scale
    installed = images.imagecodecs
    cpu: dict[str, list[float]] = {"imagecodecs": [], "pillow": []}
    try:
        for r in range(rounds):
            for i in picked:
                for name in (("imagecodecs", "pillow") if r % 2 == 0 else ("pillow", "imagecodecs")):
                    images.imagecodecs = installed if name == "imagecodecs" else None
                    start = time.thread_time()
                    images.read_rgbd(dataset.rgb_files[i], dataset.depth_files[i], scale, dataset.camera, invalid)
                    cpu[name].append(time.thread_time() - start)
    finally:
        images.imagecodecs = installed
    medians = {n: statistics.median(v) * 1e3 for n, v in cpu.items()}
    return {"frames": len(picked), "rounds": rounds, "median_cpu_ms": medians,
            "ratio_to_pillow": medians["imagecodecs"] / medians["pillow"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kinds", default="tum colour png,tum depth png16,7scenes colour jpeg,7scenes depth png16,"
                                           "replica colour jpeg,replica depth png16")
    parser.add_argument("--images", type=int, default=12)
    parser.add_argument("--rounds", type=int, default=30)
    parser.add_argument("--reader", default="tum,7scenes,replica", help="sequences of the frame reader's measurement")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/decoders.json"))
    args = parser.parse_args()
    results = {}
    for kind in args.kinds.split(","):
        results[kind] = r = measure(kind, args.images, args.rounds)
        print(f"\n{kind} ({r['files']} files x {r['rounds']} rounds): median CPU ms per image (ratio to Pillow)")
        for name, ms in sorted(r["median_cpu_ms"].items(), key=lambda kv: kv[1]):
            same = "" if r["identical_to_pillow"][name] else "  NOT identical to Pillow"
            print(f"  {name:16s} {ms:7.3f}  ({r['ratio_to_pillow'][name]:.2f}){same}")
    reader = {}
    for sequence in filter(None, args.reader.split(",")):
        reader[sequence] = r = measure_reader(sequence, args.images * 2, args.rounds // 3 or 1)
        ms = r["median_cpu_ms"]
        print(f"\nframe reader, {sequence} ({r['frames']} frames x {r['rounds']} rounds): median CPU ms per frame "
              f"imagecodecs {ms['imagecodecs']:.3f}, Pillow alone {ms['pillow']:.3f} ({r['ratio_to_pillow']:.2f})")
    versions = {}
    for module in ("PIL", "cv2", "imageio", "simplejpeg", "pyspng", "imagecodecs", "numpy"):
        try:
            versions[module] = __import__(module).__version__
        except (ImportError, AttributeError):
            pass
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": platform.platform(), "processor": platform.processor(),
                                    "when": time.strftime("%Y-%m-%d %H:%M"), "versions": versions,
                                    "results": results, "reader": reader}, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
