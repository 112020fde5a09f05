"""Trajectory plots written as PNG files (matplotlib, imported lazily, no display needed),
atomically (`save_figure`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slamkit.formats.atomic import atomic_open

AXES = "xyz"


def plot_trajectory(path_png, est_aligned_positions, gt_positions=None, title: str = "",
                    ate_rmse_m: float | None = None, loops: list[tuple[int, int]] = ()) -> Path:
    """Write a PNG: top view of the trajectory plus x, y, z position (metres) per frame index.

    est_aligned_positions: (N, 3) estimated camera positions in metres, already aligned to the
    ground truth (ATEResult.est_aligned). gt_positions: (N, 3) ground-truth positions (NaN rows
    for missing frames, drawn as gaps) or None to plot the estimate alone. The top view shows
    the two world axes with the largest extent, with equal scale. ate_rmse_m, when given, is
    added to the title in centimetres. loops: pairs of rows (frame, the frame it closed a loop
    with), drawn as red segments in the top view. Returns the path written.
    """
    from matplotlib.figure import Figure  # no pyplot: no global state, no GUI backend

    est = np.asarray(est_aligned_positions, dtype=np.float64).reshape(-1, 3)
    gt = None if gt_positions is None else np.asarray(gt_positions, dtype=np.float64).reshape(-1, 3)
    ref = gt if gt is not None and np.isfinite(gt).any() else est
    finite = ref[np.isfinite(ref).all(axis=1)]
    extent = np.ptp(finite, axis=0) if len(finite) else np.zeros(3)
    a, b = sorted(np.argsort(-extent, kind="stable")[:2])
    if ate_rmse_m is not None:
        title = ", ".join(filter(None, [title, f"ATE RMSE {100 * ate_rmse_m:.2f} cm"]))

    fig = Figure(figsize=(12, 6), layout="constrained")
    grid = fig.add_gridspec(3, 2, width_ratios=(1.2, 1))
    top = fig.add_subplot(grid[:, 0])
    curves = [(est, "estimate", "tab:blue", "-")]
    if gt is not None:
        curves.insert(0, (gt, "ground truth", "k", "--"))
    for p, label, color, style in curves:
        top.plot(p[:, a], p[:, b], style, color=color, lw=1.2, label=label)
    top.plot(*est[0, [a, b]], "o", color="tab:green", label="start")
    for k, (i, j) in enumerate(loops):
        top.plot(est[[i, j], a], est[[i, j], b], "-", color="tab:red", lw=1.5,
                 label=f"loops closed ({len(loops)})" if k == 0 else None)
    top.set(xlabel=f"{AXES[a]} [m]", ylabel=f"{AXES[b]} [m]", aspect="equal", title="top view")
    top.legend(loc="best")
    for k in range(3):
        ax = fig.add_subplot(grid[k, 1])
        for p, label, color, style in curves:
            ax.plot(p[:, k], style, color=color, lw=1.0, label=label)
        ax.set_ylabel(f"{AXES[k]} [m]")
        if k == 2:
            ax.set_xlabel("frame index")
    fig.suptitle(title)
    path_png = Path(path_png)
    save_figure(fig, path_png)
    return path_png


def save_figure(fig, path_png: str | Path) -> None:
    """Write a matplotlib figure as a PNG file (100 dpi), atomically."""
    with atomic_open(path_png, "wb") as f:
        fig.savefig(f, format="png", dpi=100)
