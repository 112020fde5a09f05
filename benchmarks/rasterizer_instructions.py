"""Instructions the compiled CPU rasteriser executes for one render + backward of a run's map,
counted by valgrind's callgrind: the same count whatever else the machine is doing (times on a
shared 2-core machine move by 10-20 % between runs), so a change to the kernels can be judged
from one run of each version.

    python benchmarks/rasterizer_instructions.py --map RUN_DIR/checkpoint.zip [--scale 0.5] [--view 2]

The view is the map seen from one of its keyframes (`--view`, an index into the checkpoint's
keyframes) at `--scale` of the frame size, as the mapper trains it; one thread. The script
builds the library with `-g` (beside the normal build; the same code) and, on x86-64, without
AVX-512 (valgrind cannot run it: 8-lane blocks, as on AVX2 CPUs), times the render and its
backward outside valgrind (the kernels' own CPU clocks, the best of 5), then runs itself under
`valgrind --tool=callgrind` (a few minutes: Python and torch start under it) and sums, from
`callgrind_annotate`, the instructions executed in the rasteriser's code (inlined code
included; libc calls such as malloc are not counted): the forward's and the backward's own
code, and the helpers both call that the compiler did not inline (the projection, the depth
sort, the thread pool), by source file too. Printed per composited (pixel, Gaussian) pair and
per block visit (one Gaussian composited on one 8-lane block of a tile row), with the whole
render's instructions per cycle at the clock /proc/cpuinfo reports (boost clocks make it an
upper bound). Writes JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
from collections import defaultdict
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cpu_rasterizer import cpu_ghz, map_views  # noqa: E402

import slamkit_plugins.mappers.gaussian_splatting.rasterizer.cpu_rasterizer as raster_module  # noqa: E402
from slamkit.errors import SlamkitError  # noqa: E402
from slamkit.native import BASE_FLAGS, NativeLibrary  # noqa: E402

CHILD = "SLAMKIT_INSTRUCTIONS_CHILD"  # set in the run under valgrind: where to write the render's stats
# the rasteriser's sources and the shared headers (callgrind names them absolute or relative to the build)
OUR_FILES = re.compile(r"(^|/)(plugins/mappers/gaussian_splatting/rasterizer|slamkit)/csrc/")
# callgrind_annotate's per-function lines: "  43,071,764 ( 0.75%)  FILE:FUNCTION [OBJECT]"
LINE = re.compile(r"^\s*([\d,]+)\s+\(\s*[\d.]+%\)\s+(\S+?):(.*?)(?:\s+\[(.*)\])?$")


def rasterizer() -> raster_module.CPURasterizer:
    """A one-thread rasteriser on the library built with -g (its own cache entry)."""
    flags = BASE_FLAGS + ("-g",) + (("-mno-avx512f",) if platform.machine() in ("x86_64", "AMD64") else ())
    library = NativeLibrary(raster_module.SOURCE, "CPU rasteriser (-g)", raster_module.ABI_VERSION,
                            raster_module._declare, native=True, flags=flags)
    raster_module._LIBRARIES[True] = library
    return raster_module.CPURasterizer(raster_module.CPURasterizerConfig(num_threads=1))


def render_once(r, view) -> dict:
    """Render + backward of `view`; the rasteriser's counts and per-phase CPU seconds."""
    means, quats, scales, opacities, colors, w2c, camera = view
    leaves = [p.detach().clone().requires_grad_(True) for p in (means, quats, scales, opacities, colors)]
    out = r.render(*leaves, w2c, camera)
    (out.color.sum() + out.depth.sum() + out.alpha.sum()).backward()
    return {"pairs": r.last_num_pairs, "entries": r.last_num_entries, "row_steps": r.last_num_rows,
            "visible": r.last_num_visible, "resolution": f"{camera.width}x{camera.height}",
            "cpu_s": {k[:-4]: v for k, v in r.last_times.items() if k.endswith("_cpu")}}


def count(annotated: str) -> dict:
    """Instructions in the rasteriser's code from `callgrind_annotate --inclusive=no` output: by
    the function that executed them (the forward's or the backward's code, inlined helpers
    included, or another: a helper the compiler did not inline) and by source file."""
    by_pass, by_file = defaultdict(int), defaultdict(int)
    for line in annotated.splitlines():
        m = LINE.match(line)
        if not m:
            continue
        n, file, function, obj = int(m.group(1).replace(",", "")), m.group(2), m.group(3), m.group(4) or ""
        # inlined code (intrinsics, std::min) is named by the header it comes from, so the
        # function (our code is in an anonymous namespace) and the object decide too
        ours = ("slamkit_cpu_rasterizer" in obj or function.startswith("(anonymous namespace)::")
                or OUR_FILES.search(file) is not None)
        if not ours:
            continue
        outer = re.match(r"\(anonymous namespace\)::(forward|backward)\(", function)
        by_pass[outer.group(1) if outer else "other"] += n
        by_file[Path(file).name] += n
    return {"by_pass": dict(by_pass), "by_file": dict(sorted(by_file.items(), key=lambda kv: -kv[1]))}


def child(args) -> None:
    view = map_views(args.map, args.scale)[args.view]
    stats = render_once(rasterizer(), view)
    Path(os.environ[CHILD]).write_text(json.dumps(stats))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--map", type=Path, required=True, metavar="CHECKPOINT", help="a run's RUN_DIR/checkpoint.zip")
    ap.add_argument("--scale", type=float, default=0.5, help="of the frame size (the mapper's training resolution)")
    ap.add_argument("--view", type=int, default=0, help="index of the keyframe whose pose renders the map")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/rasterizer_instructions.json"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    if os.environ.get(CHILD):
        child(args)
        return 0
    missing = [tool for tool in ("valgrind", "callgrind_annotate") if shutil.which(tool) is None]
    if missing:
        print(f"rasterizer_instructions: {' and '.join(missing)} not found (apt-get install valgrind)", file=sys.stderr)
        return 1
    try:
        views = map_views(args.map, args.scale)
    except (SlamkitError, OSError, KeyError, ValueError) as exc:
        print(f"rasterizer_instructions: --map {args.map}: not a run's checkpoint.zip ({exc})", file=sys.stderr)
        return 1
    if not 0 <= args.view < len(views):
        print(f"rasterizer_instructions: --view {args.view}: the map has {len(views)} keyframes", file=sys.stderr)
        return 1
    r = rasterizer()
    runs = [render_once(r, views[args.view]) for _ in range(6)][1:]  # (the first warms up)
    cpu_s = {k: min(run["cpu_s"][k] for run in runs) for k in runs[0]["cpu_s"]}
    with tempfile.TemporaryDirectory() as tmp:
        stats_path, out = Path(tmp) / "stats.json", Path(tmp) / "callgrind.out"
        env = {**os.environ, CHILD: str(stats_path), "OMP_NUM_THREADS": "1"}
        proc = subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", sys.executable,
                               str(Path(__file__).resolve()), *sys.argv[1:]], env=env, capture_output=True, text=True)
        if proc.returncode != 0:
            last = (proc.stderr.strip().splitlines() or ["no output"])[-1]
            print(f"rasterizer_instructions: the run under valgrind failed ({last})", file=sys.stderr)
            return 1
        stats = json.loads(stats_path.read_text())
        annotated = subprocess.run(["callgrind_annotate", "--inclusive=no", "--threshold=100", "--auto=no", str(out)],
                                   capture_output=True, text=True, check=True).stdout
    counts = count(annotated)
    visits = stats["row_steps"] * 2  # 16-lane row steps, composited as two 8-lane blocks
    ghz = cpu_ghz()
    total = sum(counts["by_pass"].values())
    cpu_total_s = sum(cpu_s.values())
    rows = [{"part": name, "instructions": n, "per_pair": n / stats["pairs"], "per_visit": n / visits}
            for name, n in (("forward's code", counts["by_pass"].get("forward", 0)),
                            ("backward's code", counts["by_pass"].get("backward", 0)),
                            ("helpers not inlined (projection, depth sort, thread pool)",
                             counts["by_pass"].get("other", 0)),
                            ("all", total))]
    ipc = total / (cpu_total_s * ghz * 1e9) if ghz else None
    print(f"{args.map} view {args.view} at {stats['resolution']}: {stats['pairs']:,} pairs, {visits:,} block visits "
          f"(8 lanes), {stats['entries']:,} (tile, Gaussian) entries, {stats['visible']:,} Gaussians\n")
    print("| part | instructions | per pair | per block visit |")
    print("|---|---|---|---|")
    for row in rows:
        print(f"| {row['part']} | {row['instructions'] / 1e6:.1f}M | {row['per_pair']:.1f} | {row['per_visit']:.1f} |")
    print(f"\nCPU time of the render + backward (best of 5): {1e3 * cpu_total_s:.2f} ms ("
          + ", ".join(f"{k} {1e3 * v:.2f}" for k, v in cpu_s.items())
          + (f"); {ipc:.2f} instructions a cycle at {ghz:.2f} GHz" if ghz else "); clock unknown"))
    print("\nby source file (inlined code counts where it is written; files under 0.5 a visit left out):")
    for name, n in counts["by_file"].items():
        if n >= 0.5 * visits:
            print(f"  {name:20} {n / 1e6:8.1f}M  {n / visits:6.1f} per visit")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": platform.platform(), "ghz": ghz, "map": str(args.map),
                                    "scale": args.scale, "view": args.view, "visits": visits, **stats,
                                    "cpu_s": cpu_s, "instructions_per_cycle": ipc, "parts": rows,
                                    "by_file": counts["by_file"]}, indent=2) + "\n")
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
