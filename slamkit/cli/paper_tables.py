"""`slamkit-report --paper TABLE DIR`: a sweep's results as one of GS-ICP SLAM's tables (Ha, Yeon
and Yu, ECCV 2024), the paper's figure beside each of ours (docs/paper.md transcribes them).

A run's row in the table is told by the settings its table varies (its overrides, as
`slamkit-report` reads them: `+scale_variant=z` is `scale_variant`), and its scene by `scene` or
the folder of `dataset.path`; runs of one row and scene (seeds) are averaged. The paper's figure
is its value for that row and scene, or its mean over its scenes where ours is another one (the
`paper's column` cell says which). The paper's ATE is what the authors' code prints, the mean
translation error after alignment (called RMSE there): it stands beside our `ate_mean_m`, with our
RMSE (`ate_rmse_m`) in a column of its own. FPS is the paper's, frames over the SLAM run's time
(`fps`: start-up included, the evaluation after the stream not); `runs_table` sets it beside the
input's rate (`stream_fps`).

`slamkit-report --docs FILE` rewrites the generated blocks of a Markdown file (`BLOCK_START` with
`--paper TABLE DIR...` or `--runs DIR...`, up to `BLOCK_END`) from the runs they name, each table
followed by where its runs came from (`provenance.json`: commit, date, machine, load).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from slamkit.cli.run_folders import find_runs, load_run
from slamkit.downloads.catalogue import PAPER_TUM, REPLICA_SCENES
from slamkit.formats.atomic import write_atomic


@dataclass(frozen=True)
class Metric:
    """A column: its header, metrics.json's key, the factor to the table's unit, decimals."""

    header: str
    key: str
    scale: float = 1.0
    digits: int = 2


ATE = Metric("ATE [cm]", "ate_mean_m", 100.0, 3)
ATE_RMSE = Metric("ATE RMSE [cm]", "ate_rmse_m", 100.0, 3)
PSNR = Metric("PSNR [dB]", "psnr", 1.0, 2)
SSIM = Metric("SSIM", "ssim", 1.0, 3)
LPIPS = Metric("LPIPS", "lpips", 1.0, 3)
FPS = Metric("FPS", "fps", 1.0, 2)
#: The paper's mean over its scenes (the "Avg." column).
MEAN = "mean"
#: Replica's scenes as the paper's columns (room0 ... office4), TUM's folders as its names (fr1/desk ...).
REPLICA_COLUMNS = {s: s for s in REPLICA_SCENES}
TUM_COLUMNS = {folder: name for name, folder in PAPER_TUM.items()}


@dataclass(frozen=True)
class PaperTable:
    """One table: what it shows, the settings that tell its rows apart (`keys`), its metric
    columns, the paper's figures {(row values..., paper's column): {metric key: value}}, the
    paper's row labels, and the scene folders that are its columns (none: only its mean)."""

    title: str
    keys: tuple[str, ...]
    metrics: tuple[Metric, ...]
    paper: dict[tuple, dict[str, float]]
    labels: dict[tuple, str] = field(default_factory=dict)
    columns: dict[str, str] = field(default_factory=dict)
    note: str = ""


def _by_column(row: tuple, columns: list[str], **series: list[float]) -> dict[tuple, dict[str, float]]:
    """{(*row, column): {metric: value}} from one list per metric, in `columns` order."""
    return {(*row, c): {k: v[i] for k, v in series.items()} for i, c in enumerate(columns)}


_REPLICA = [*REPLICA_SCENES, MEAN]
_TUM = [*PAPER_TUM, MEAN]


def _rows(keys_values: dict[tuple, tuple], *metrics: str) -> dict[tuple, dict[str, float]]:
    return {(*row, MEAN): dict(zip(metrics, values)) for row, values in keys_values.items()}


TABLES: dict[str, PaperTable] = {
    "table1": PaperTable(
        "Table 1: tracking on Replica", ("preset",), (ATE, ATE_RMSE),
        _by_column(("paper",), _REPLICA, ate_mean_m=[0.15, 0.16, 0.11, 0.18, 0.12, 0.17, 0.16, 0.21, 0.16]),
        {("paper",): "GS-ICP SLAM (30 FPS)"}, REPLICA_COLUMNS),
    "table2": PaperTable(
        "Table 2: tracking on TUM RGB-D", ("preset",), (ATE, ATE_RMSE),
        _by_column(("paper",), _TUM, ate_mean_m=[2.7, 1.8, 2.7, 2.4]),
        {("paper",): "GS-ICP SLAM (30 FPS)"}, TUM_COLUMNS),
    "table3": PaperTable(
        "Table 3: map quality and speed on Replica", ("preset",), (PSNR, SSIM, LPIPS, FPS),
        {**_by_column(("paper",), _REPLICA,
                      psnr=[35.37, 37.80, 38.50, 43.13, 43.26, 36.93, 36.90, 38.75, 38.83],
                      ssim=[0.963, 0.971, 0.975, 0.986, 0.985, 0.974, 0.969, 0.973, 0.975],
                      lpips=[0.048, 0.045, 0.048, 0.026, 0.029, 0.043, 0.042, 0.045, 0.041],
                      fps=[29.97, 29.98, 29.98, 29.98, 29.99, 29.97, 29.97, 29.97, 29.98]),
         **_by_column(("paper_unlimited",), _REPLICA,
                      psnr=[32.20, 35.36, 34.42, 40.31, 40.75, 33.85, 34.08, 36.47, 35.93],
                      ssim=[0.940, 0.960, 0.957, 0.978, 0.977, 0.962, 0.953, 0.963, 0.962],
                      lpips=[0.081, 0.067, 0.083, 0.045, 0.051, 0.069, 0.067, 0.065, 0.066],
                      fps=[100.98, 84.92, 103.38, 99.10, 107.06, 95.60, 97.20, 96.66, 98.11])},
        {("paper",): "GS-ICP SLAM (30 FPS)", ("paper_unlimited",): "GS-ICP SLAM (no speed limit)"}, REPLICA_COLUMNS),
    "table4": PaperTable(
        "Table 4: map quality and speed on TUM RGB-D (the paper gives the mean of its three sequences)",
        ("preset",), (PSNR, SSIM, LPIPS, FPS),
        _rows({("paper",): (20.72, 0.768, 0.218, 29.99), ("paper_unlimited",): (19.62, 0.750, 0.240, 73.92)},
              "psnr", "ssim", "lpips", "fps"),
        {("paper",): "GS-ICP SLAM (30 FPS)", ("paper_unlimited",): "GS-ICP SLAM (no speed limit)"}),
    "table5": PaperTable(
        "Table 5: covariance regularisation (TUM RGB-D)", ("tracker.regularization",), (ATE, ATE_RMSE),
        {**_by_column(("none",), _TUM, ate_mean_m=[136.32, 196.61, 376.40, 236.54]),
         **_by_column(("plane",), _TUM, ate_mean_m=[65.63, 5.53, 16.21, 29.12]),
         **_by_column(("ellipse",), _TUM, ate_mean_m=[2.66, 1.77, 2.67, 2.37])},
        {("none",): "none", ("plane",): "plane", ("ellipse",): "ellipse"}, TUM_COLUMNS),
    "table6": PaperTable(
        "Table 6: scale alignment (Replica, the paper's mean of 8 scenes)", ("scale_variant",),
        (ATE, ATE_RMSE, PSNR, SSIM, LPIPS),
        _rows({("knn",): (8.893, 24.81, 0.840, 0.380), ("none",): (0.258, 33.21, 0.922, 0.177),
               ("constant",): (0.158, 37.33, 0.964, 0.074), ("z",): (0.158, 38.70, 0.974, 0.044),
               ("z_pow",): (0.157, 38.83, 0.975, 0.041)}, "ate_mean_m", "psnr", "ssim", "lpips"),
        {("knn",): "no G-ICP covariances", ("none",): "no re-init", ("constant",): "constant", ("z",): "z",
         ("z_pow",): "z^1.5"},
        note="the paper's ATE column has no unit; its last row equals Table 7's 0.157 cm"),
    "table7": PaperTable(
        "Table 7: keyframes and mapping-only keyframes (Replica, the paper's mean of 8 scenes)", ("keyframe_variant",),
        (ATE, ATE_RMSE, PSNR, SSIM, LPIPS),
        _rows({("tracking_every30",): (0.174, 37.52, 0.968, 0.055), ("tracking_every10",): (0.176, 38.83, 0.974, 0.041),
               ("mapping_every10",): (0.157, 38.83, 0.975, 0.041)}, "ate_mean_m", "psnr", "ssim", "lpips"),
        {("tracking_every30",): "tracking + every 30 frames", ("tracking_every10",): "tracking + every 10 frames",
         ("mapping_every10",): "tracking, mapping-only every 10"}),
    "table8a": PaperTable(
        "Table 8a: which keyframe a mapping step trains on (Replica, the paper's mean of 8 scenes)",
        ("mapper/sampler",), (PSNR, SSIM, LPIPS),
        _rows({("recent",): (26.85, 0.872, 0.200), ("covisible",): (31.34, 0.924, 0.120),
               ("random",): (38.83, 0.975, 0.041)}, "psnr", "ssim", "lpips"),
        {("recent",): "recent 1 keyframe", ("covisible",): "covisible keyframes", ("random",): "random keyframes"}),
    "table8b": PaperTable(
        "Table 8b: densification and pruning (Replica, the paper's mean of 8 scenes)",
        ("densify_variant", "mapper.strategy.prune_every"), (ATE, ATE_RMSE, PSNR, SSIM, LPIPS),
        _rows({("reference", "200"): (0.188, 38.65, 0.973, 0.041), ("reference", "0"): (0.170, 37.90, 0.971, 0.052),
               ("none", "200"): (0.157, 38.83, 0.975, 0.041), ("none", "0"): (0.159, 38.72, 0.974, 0.041)},
              "ate_mean_m", "psnr", "ssim", "lpips"),
        {("reference", "200"): "densify, prune", ("reference", "0"): "densify, no pruning",
         ("none", "200"): "no densification, prune", ("none", "0"): "neither",
         ("every100", "200"): "- (3DGS's schedule, densify, prune)", ("every100", "0"): "- (3DGS's schedule, densify)"},
        note="densify_variant reference is the reference code's schedule (clone / split every 300 steps, an opacity "
             "reset every 600), every100 3DGS's own (100 / 3000), none no densification"),
    "fig4": PaperTable(
        "Fig. 4: separated keyframe selection (the paper: Replica office4), cases 1-3", ("keyframe_variant",),
        (ATE, ATE_RMSE, PSNR, SSIM, LPIPS), {},
        {("tracking_every30",): "case 1: tracking keyframes, a forced one every 30 frames",
         ("tracking_every10",): "case 2: tracking keyframes, a forced one every 10 frames",
         ("mapping_every10",): "case 3: tracking keyframes, mapping-only every 10 frames (the paper's)"},
        note="the paper's values are in its figure only; its caption: few tracking keyframes track best (case 1), "
             "many mapping keyframes render best (case 2), case 3 takes both"),
    "fig3": PaperTable(
        "Fig. 3: keyframe selection (Replica)", ("keyframe_selection",), (ATE, ATE_RMSE, PSNR), {},
        {("overlap",): "overlap (the paper's)", ("every_5",): "every 5 frames", ("every_10",): "every 10 frames",
         ("every_30",): "every 30 frames"},
        note="the paper's values are in its figure only; its caption: every n frames tracks notably worse, "
             "the overlap selection best"),
}
NAMES = tuple(TABLES)
#: Earlier names of a table: fig4a was the paper's Fig. 3 (removed in 0.4).
ALIASES = {"fig4a": "fig3"}


def scene_of(settings: dict[str, str]) -> str:
    """The run's scene: `scene` (a folder under data_root) or the folder of `dataset.path`."""
    where = settings.get("scene") or settings.get("dataset.path") or ""
    return Path(where.rstrip("/")).name


def paper_table(name: str, runs: list[dict[str, Any]], difference: bool = False) -> str:
    """The sweep's completed `runs` (`slamkit.cli.run_folders.load_run` entries: settings, metrics,
    status) as the paper's table `name` (one of NAMES), in Markdown, the paper's figure beside
    each of ours ("-" where the paper has none) and, with `difference`, ours minus the paper's."""
    name = ALIASES.get(name, name)
    table = TABLES[name]
    groups: dict[tuple, list[dict]] = {}
    mixed = [run for run in runs if run["status"] == "completed" and run["metrics"].get("settings_changes")]
    for run in runs:
        if run["status"] == "completed" and run not in mixed:  # a run resumed with other settings is no one row's
            row = tuple(run["settings"].get(k) for k in table.keys)
            groups.setdefault((row, scene_of(run["settings"])), []).append(run["metrics"])
    order = [k[:-1] for k in table.labels] + [k[:-1] for k in table.paper]
    ranked = sorted(groups, key=lambda g: (order.index(g[0]) if g[0] in order else len(order), g[1]))
    header = [*table.keys, "the paper's row", "scene", "the paper's column", "runs"]
    for metric in table.metrics:
        header += [metric.header] + ([f"{metric.header}, paper"] if _in_paper(table, metric) else [])
        header += [f"{metric.header}, ours - paper"] if difference and _in_paper(table, metric) else []
    lines = [f"**{table.title}**", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    datasets = {scene_of(run["settings"]): run["settings"].get("dataset", "") for run in runs}
    for row, scene in ranked:
        column = table.columns.get(scene, MEAN)
        paper = table.paper.get((*row, column), {})
        cells = [str(v) if v is not None else "-" for v in row]
        cells += [table.labels.get(row, "-"), scene or "-", column if paper else "-", str(len(groups[row, scene]))]
        cells += _paper_cells(table, [_mean(groups[row, scene], metric) for metric in table.metrics], paper, difference)
        lines.append("| " + " | ".join(cells) + " |")
    # the paper's "Avg.": a mean row over our scenes of one dataset (a Replica and a TUM scene make none)
    for row, dataset in dict.fromkeys((r, datasets.get(s, "")) for r, s in ranked):
        scenes = [scene for r, scene in ranked if r == row and datasets.get(scene, "") == dataset]
        if len(scenes) < 2:
            continue
        paper = table.paper.get((*row, MEAN), {})
        cells = [str(v) if v is not None else "-" for v in row]
        cells += [table.labels.get(row, "-"), f"mean of {len(scenes)} {dataset + ' ' if dataset else ''}scenes",
                  MEAN if paper else "-", str(sum(len(groups[row, s]) for s in scenes))]
        per_scene = [[_mean(groups[row, s], metric) for s in scenes] for metric in table.metrics]
        means = [None if None in values else sum(values) / len(values) for values in per_scene]
        lines.append("| " + " | ".join(cells + _paper_cells(table, means, paper, difference)) + " |")
    if not ranked:
        lines.append("(no completed run)")
    notes = ["the paper's ATE is the reference code's mean error after alignment: beside our ate_mean_m"
             ] if ATE in table.metrics else []
    if any(scene not in table.columns and table.paper.get((*row, MEAN)) for row, scene in ranked):
        notes.append(f"{', '.join(sorted({s or '-' for r, s in ranked if s not in table.columns}))} "
                     f"{'is' if len({s for r, s in ranked if s not in table.columns}) == 1 else 'are'} not among the "
                     "paper's scenes: its figure there is its mean over its own scenes, not a measurement of ours")
    notes += [table.note] if table.note else []
    notes += [f"left out, resumed with other method settings (metrics.json settings_changes): "
              f"{', '.join(str(run['run']) for run in mixed)}"] if mixed else []
    lines += ["", "; ".join(notes) + "."] if notes else []
    return "\n".join(lines) + "\n"


def _paper_cells(table: PaperTable, ours: list[float | None], paper: dict[str, float],
                 difference: bool) -> list[str]:
    """A row's metric cells: each of `table.metrics` (`ours`, in order), the paper's figure
    beside it where the paper has the metric, and with `difference` ours minus the paper's."""
    cells = []
    for metric, value in zip(table.metrics, ours):
        cells.append(_fmt(value, metric.digits))
        if _in_paper(table, metric):
            theirs = paper.get(metric.key)
            cells.append(_fmt(theirs, metric.digits))
            if difference:
                cells.append("-" if value is None or theirs is None else f"{value - theirs:+.{metric.digits}f}")
    return cells


def report(name: str, runs: list[dict[str, Any]], out: Path) -> Path:
    """Print `paper_table(name, runs)` and write it as out/paper_NAME.md; returns the file."""
    name = ALIASES.get(name, name)
    text = paper_table(name, runs)
    print(text, end="")
    path = Path(out) / f"paper_{name}.md"
    write_atomic(path, text)
    return path


def _in_paper(table: PaperTable, metric: Metric) -> bool:
    return any(metric.key in values for values in table.paper.values())


def _mean(metrics: list[dict], metric: Metric) -> float | None:
    values = [m.get(metric.key) for m in metrics]
    values = [float(v) * metric.scale for v in values
              if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)]
    return sum(values) / len(values) if values else None


def _fmt(value: float | None, digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


# ------------------------------------------------------------------ a table of runs, one row each
#: The real-time runs' table: the input's rate and the paper's FPS (frames over the SLAM run's
#: time, start-up included, evaluation not) side by side, and what the map became.
RUN_COLUMNS = (
    Metric("stream frames/s", "stream_fps"), Metric("FPS (frames / total time, the paper's)", "fps"),
    Metric("mapping steps", "mapping_steps", digits=0), Metric("PSNR [dB]", "psnr"),
    Metric("SSIM", "ssim", digits=3), Metric("LPIPS", "lpips", digits=3),
    Metric("ATE mean [cm]", "ate_mean_m", 100.0, 3), Metric("ATE RMSE [cm]", "ate_rmse_m", 100.0, 3),
    Metric("Gaussians", "num_gaussians", digits=0),
)


def runs_table(runs: list[dict[str, Any]]) -> str:
    """The completed `runs` one row each (the run's folder name), RUN_COLUMNS, the training
    resolution and which pixels PSNR is over (the run's `settings`)."""
    header = ["run", "training resolution", "PSNR pixels", *(c.header for c in RUN_COLUMNS)]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for run in sorted((r for r in runs if r["status"] == "completed"), key=lambda r: str(r["run"])):
        m = run["metrics"]
        resolution = m.get("train_resolution")
        cells = [Path(run["run"]).name, "x".join(map(str, resolution)) if resolution else "-",
                 str((m.get("settings") or {}).get("eval.psnr_pixels", "-"))]
        lines.append("| " + " | ".join(cells + _run_cells(m, RUN_COLUMNS)) + " |")
    return "\n".join(lines) + "\n"


def _run_cells(metrics: dict, columns: tuple[Metric, ...]) -> list[str]:
    """One run's `metrics` in `columns`, thousands separated ("-" where a metric is missing)."""
    values = [_mean([metrics], column) for column in columns]
    return ["-" if v is None else f"{v:,.{c.digits}f}" for v, c in zip(values, columns)]


#: A sweep's table (sequential runs, one row per job): what the method made of the frames and
#: what it cost, without the real-time rates.
SWEEP_COLUMNS = (
    Metric("keyframes", "num_keyframes", digits=0), Metric("ATE RMSE [cm]", "ate_rmse_m", 100.0, 3),
    Metric("PSNR [dB]", "psnr"), Metric("SSIM", "ssim", digits=3), Metric("LPIPS", "lpips", digits=3),
    Metric("Gaussians", "num_gaussians", digits=0), Metric("tracking [s]", "tracking_time_s", digits=1),
    Metric("whole run [s]", "wall_time_s", digits=1),
)


def varied_settings(runs: list[dict[str, Any]]) -> list[str]:
    """The settings (override keys) whose values differ among `runs`, data folders left out."""
    keys = sorted({k for r in runs for k in r["settings"]})
    return [k for k in keys if not k.endswith("path") and len({str(r["settings"].get(k)) for r in runs}) > 1]


def sweep_table(runs: list[dict[str, Any]]) -> str:
    """The completed `runs` one row each, named by the settings that vary among them
    (`varied_settings`), with SWEEP_COLUMNS; a run that did not complete is a row saying so."""
    varied = varied_settings(runs)
    header = [*varied, *(c.header for c in SWEEP_COLUMNS)]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for run in sorted(runs, key=lambda r: [str(r["settings"].get(k)) for k in varied]):
        cells = [str(run["settings"].get(k, "-")) for k in varied]
        cells += (_run_cells(run["metrics"], SWEEP_COLUMNS) if run["status"] == "completed"
                  else [run["status"]] + [""] * (len(SWEEP_COLUMNS) - 1))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------ where the committed runs came from
PROVENANCE = "provenance.json"


def provenance_of(run: Path) -> dict[str, Any] | None:
    """The provenance record (PROVENANCE: commit, date, machine, load, commands) of the folder of
    runs that holds `run`, the nearest one above it; None without one."""
    for folder in (Path(run), *Path(run).parents):
        path = folder / PROVENANCE
        if path.is_file():
            import json

            return json.loads(path.read_text())
    return None


def provenance_line(runs: list[dict[str, Any]]) -> str:
    """One sentence per distinct provenance record of `runs`: when, where and at which commit they
    ran, and the machine's load (frames/s are that machine's under that load)."""
    seen, parts = [], []
    for run in runs:
        record = provenance_of(run["run"])
        if record is None or record in seen:
            continue
        seen.append(record)
        load = record.get("load_average")
        parts.append(f"{record.get('group', 'runs')}: commit {record.get('commit', '?')}, {record.get('date', '?')}, "
                     f"{record.get('machine', '?')}"
                     + (f", load average {load} ({record.get('load_note', 'a machine shared with other work')})"
                        if load else ""))
    return ("Measured " + "; ".join(parts) + ".") if parts else "(no provenance record)"


# ------------------------------------------------------------------ the tables of a document, regenerated
#: A generated block of a Markdown document: the opening comment names what writes it (as
#: slamkit-report's arguments: `--paper TABLE DIR...`, `--runs DIR...` or `--sweep DIR...` (one row
#: per job, named by the settings its sweep varied), folders relative to the
#: repository), the closing one ends it; everything between is rewritten.
BLOCK_START = "<!-- slamkit-report "
BLOCK_END = "<!-- end slamkit-report -->"


def block_text(args: list[str], root: Path) -> str:
    """What a block with arguments `args` holds: the table and where its runs came from."""
    if len(args) < 2 or args[0] not in ("--paper", "--runs", "--sweep") or (args[0] == "--paper" and len(args) < 3):
        raise ValueError(f"a block's arguments are '--paper TABLE DIR...', '--runs DIR...' or '--sweep DIR...', "
                         f"got {' '.join(args)!r}")
    dirs = [root / d for d in (args[2:] if args[0] == "--paper" else args[1:])]
    runs = [load_run(r) for r in find_runs(dirs)]
    if args[0] == "--paper":
        if ALIASES.get(args[1], args[1]) not in TABLES:
            raise ValueError(f"no paper table {args[1]!r} (expected one of {', '.join(NAMES)})")
        table = paper_table(args[1], runs)
    else:
        table = runs_table(runs) if args[0] == "--runs" else sweep_table(runs)
    return f"{table}\n{provenance_line(runs)}\n"


def regenerate_document(text: str, root: Path) -> str:
    """`text` with every generated block rewritten from the runs it names (under `root`)."""
    out, pos = [], 0
    while (start := text.find(BLOCK_START, pos)) >= 0:
        head_end = text.index("-->", start) + 3
        end = text.find(BLOCK_END, head_end)
        if end < 0:
            raise ValueError(f"a generated block at character {start} has no {BLOCK_END!r}")
        args = text[start + len(BLOCK_START):head_end - 3].split()
        out += [text[pos:head_end], "\n", block_text(args, root)]
        pos = end
    out.append(text[pos:])
    return "".join(out)
