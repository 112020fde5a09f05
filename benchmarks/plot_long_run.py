"""Plot Gaussians and resident memory against frames from `benchmarks/long_run.py` JSON files:
one line per run (label), pass boundaries of a looped sequence as dotted lines.

    python benchmarks/plot_long_run.py looped_realtime.json looped_sequential.json --out docs/map_bound.png

Each JSON file gets a row of two panels (Gaussians, resident MB), titled with `--titles` or the
file name.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def pass_ends(num_frames: int, passes: int) -> list[int]:
    """The run frame counts at which each pass ends: a sequence of n frames played back and
    forth `passes` times has n + (passes - 1)(n - 1) frames (the turning frame is not repeated)."""
    if passes <= 1:
        return []
    n = (num_frames + passes - 1) // passes
    return [n + p * (n - 1) for p in range(passes)]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("results", type=Path, nargs="+")
    parser.add_argument("--titles", nargs="*", default=None, help="one title per JSON file")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(args.results), 2, figsize=(11, 3.4 * len(args.results)), squeeze=False)
    for row, path in enumerate(args.results):
        data = json.loads(path.read_text())
        title = args.titles[row] if args.titles and row < len(args.titles) else path.stem
        runs = [r for r in data["runs"] if r.get("samples")]
        gauss_ax, mem_ax = axes[row]
        for r in runs:
            frames = [int(s["index"]) + 1 for s in r["samples"]]
            gauss_ax.plot(frames, [int(s["num_gaussians"]) / 1e3 for s in r["samples"]], label=r["label"])
            mem_ax.plot(frames, [float(s["rss_mb"]) for s in r["samples"]], label=r["label"])
        complete = [r for r in runs if not r.get("stopped_by_time_limit") and r["metrics"].get("num_frames")]
        if complete and data.get("passes", 1) > 1:
            for end in pass_ends(complete[0]["metrics"]["num_frames"], data["passes"])[:-1]:
                for ax in (gauss_ax, mem_ax):
                    ax.axvline(end, color="grey", linestyle=":", linewidth=0.8)
        gauss_ax.set(title=f"{title}: map size", xlabel="frame", ylabel="Gaussians (thousands)")
        mem_ax.set(title=f"{title}: resident memory", xlabel="frame", ylabel="RSS (MB)")
        for ax in (gauss_ax, mem_ax):
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
