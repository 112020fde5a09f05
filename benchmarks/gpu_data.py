"""Copy the first frames of the shared sequences into a folder inside the repository
(`.gpudata/`, git-ignored) for the GPU check: a lent GPU machine gets the repository's working
tree and the paths named in `carry`, never ../shared, and all of it within 64 MiB.

    python benchmarks/gpu_data.py                    # TUM 60 frames, Replica 20 -> .gpudata/
    python benchmarks/gpu_data.py --tum-frames 40 --replica-frames 10

The sub-folders keep the shared folder's names, so that SLAMKIT_DATA=.gpudata stands in for
../shared/data (tests/support/data.py, benchmarks/gpu_bench.py); each holds fewer frames (a NOTE.txt
says how many). TUM: rgb.txt and depth.txt keep their header and the selected lines,
groundtruth.txt is copied whole. Replica: frames, depths and traj.txt lines 0..N-1. Files are
copied byte for byte. Prints each folder's size and what would travel in all (the tracked tree,
untracked files that are not ignored, and the carried .whl/ and .gpudata/).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
TUM, REPLICA = "tum_fr1_rpy_first150", "replica_room0_first20"
LIMIT_MB = 64 * 2**20 / 1e6  # the transfer limit, 64 MiB, in MB


def _copy_list(src: Path, dst: Path, n: int, max_time: float | None = None) -> list[str]:
    """Copy a TUM list file: its comment lines and its first `n` entries (or those up to
    `max_time`); returns the file names of the entries kept."""
    lines = src.read_text().splitlines()
    header = [ln for ln in lines if ln.startswith("#")]
    entries = [ln for ln in lines if ln.strip() and not ln.startswith("#")]
    kept = entries[:n] if max_time is None else [ln for ln in entries if float(ln.split()[0]) <= max_time]
    dst.write_text("\n".join(header + kept) + "\n")
    return [ln.split()[1] for ln in kept]


def copy_tum(src: Path, dst: Path, n: int) -> None:
    dst.mkdir(parents=True)
    rgb = _copy_list(src / "rgb.txt", dst / "rgb.txt", n)
    last = float((dst / "rgb.txt").read_text().splitlines()[-1].split()[0])
    depth = _copy_list(src / "depth.txt", dst / "depth.txt", 0, max_time=last + 0.02)  # each rgb's partner
    for name in rgb + depth:
        (dst / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(src / name, dst / name)
    for name in ("groundtruth.txt", "README.txt"):
        shutil.copy2(src / name, dst / name)
    (dst / "NOTE.txt").write_text(f"The first {len(rgb)} of {src.name}'s colour frames and their depth frames "
                                  f"(benchmarks/gpu_data.py), for the GPU check.\n")


def copy_replica(src: Path, dst: Path, n: int) -> None:
    (dst / "results").mkdir(parents=True, exist_ok=True)
    for k in range(n):
        for name in (f"frame{k:06d}.jpg", f"depth{k:06d}.png"):
            shutil.copy2(src / "results" / name, dst / "results" / name)
    (dst / "traj.txt").write_text("\n".join((src / "traj.txt").read_text().splitlines()[:n]) + "\n")
    for name in ("cam_params.json", "README.txt"):
        shutil.copy2(src / name, dst / name)
    (dst / "NOTE.txt").write_text(f"Frames 0-{n - 1} of {src.name} (benchmarks/gpu_data.py), for the GPU check.\n")


def size_mb(path: Path) -> float:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) / 1e6 if path.exists() else 0.0


def travelling_mb() -> float:
    """The working tree that travels to the GPU machine: tracked and untracked-not-ignored
    files, plus .whl/ and .gpudata/ (carried)."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=REPO,
                            capture_output=True, check=True).stdout.split(b"\0")
    tree = sum((REPO / p.decode()).stat().st_size for p in listed if p and (REPO / p.decode()).is_file()) / 1e6
    return tree + size_mb(REPO / ".whl") + size_mb(REPO / ".gpudata")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tum-frames", type=int, default=60)
    parser.add_argument("--replica-frames", type=int, default=20)
    parser.add_argument("--shared", type=Path, default=SHARED)
    parser.add_argument("--out", type=Path, default=REPO / ".gpudata")
    args = parser.parse_args()
    if args.out.exists():
        shutil.rmtree(args.out)
    copy_tum(args.shared / TUM, args.out / TUM, args.tum_frames)
    copy_replica(args.shared / REPLICA, args.out / REPLICA, args.replica_frames)
    for name in (TUM, REPLICA):
        print(f"{args.out / name}: {size_mb(args.out / name):.1f} MB")
    total = travelling_mb()
    print(f"would travel with carry [.whl, .gpudata]: {total:.1f} MB of the {LIMIT_MB:.1f} MB (64 MiB) limit")
    if total > LIMIT_MB:
        raise SystemExit("gpu_data: over the transfer limit; use fewer frames (--tum-frames, --replica-frames)")


if __name__ == "__main__":
    main()
