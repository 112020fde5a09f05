"""Where a long mapping run's resident memory goes: resident set vs live torch tensors vs
glibc's heap (bytes in use, bytes free but still resident, mmapped), every `--every` frames of
the synthetic sequence, in-process, with or without `slamkit.run.heap.release_free_memory` at
keyframes (`--no-trim` turns it off). Linux / glibc only.

    OMP_NUM_THREADS=1 python benchmarks/heap.py --frames 500 --max-gaussians 200000
    OMP_NUM_THREADS=1 python benchmarks/heap.py --frames 500 --max-gaussians 200000 --no-trim
    MALLOC_MMAP_THRESHOLD_=1048576 OMP_NUM_THREADS=1 python benchmarks/heap.py --frames 500 --no-trim ...
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import os
import time

import torch

import slamkit.run.slam
from slamkit.run.build import build_run


class MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                               "fsmblks", "uordblks", "fordblks", "keepcost")]


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def tensor_mb() -> float:
    """MB of the distinct storages of the torch tensors Python can reach."""
    sizes = {}
    for o in gc.get_objects():
        if torch.is_tensor(o):
            s = o.untyped_storage()
            sizes[s.data_ptr()] = s.nbytes()
    return sum(sizes.values()) / 2**20


def build(frames: int, cap: int | None, iterations: int) -> tuple:
    dataset, slam, _ = build_run(["dataset=synthetic", "dataset.num_frames=2000", f"dataset.max_frames={frames}",
                                  "tracker=gicp", "keyframe=overlap", "mapper=gaussian_splatting",
                                  "final_iterations=0", f"mapper.memory_cap.max_gaussians={cap or 'null'}",
                                  f"iterations_per_frame={iterations}"])
    return dataset, slam


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=500)
    parser.add_argument("--max-gaussians", type=int, default=200_000)
    parser.add_argument("--iterations", type=int, default=4, help="mapping steps per frame")
    parser.add_argument("--every", type=int, default=100)
    parser.add_argument("--no-trim", action="store_true", help="do not return free heap pages at keyframes")
    args = parser.parse_args()
    if args.no_trim:
        slamkit.run.slam.release_free_memory = lambda: False
    mallinfo2 = ctypes.CDLL("libc.so.6").mallinfo2
    mallinfo2.restype = MallInfo2
    dataset, slam = build(args.frames, args.max_gaussians, args.iterations)
    slam.initialize(dataset[0].gt_pose)
    print("| frames | Gaussians | keyframes | RSS MB | live tensors MB | heap in use MB | heap free MB "
          "| mmapped MB | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    start = time.perf_counter()
    for i in range(len(dataset)):
        slam.process(dataset[i])
        if (i + 1) % args.every == 0:
            elapsed = time.perf_counter() - start
            gc.collect()
            m = mallinfo2()
            print(f"| {i + 1} | {len(slam.gaussian_map):,} | {slam.num_keyframes} | {rss_mb():.0f} | {tensor_mb():.0f} "
                  f"| {m.uordblks / 2**20:.0f} | {m.fordblks / 2**20:.0f} | {m.hblkhd / 2**20:.0f} | {elapsed:.0f} |",
                  flush=True)


if __name__ == "__main__":
    main()
