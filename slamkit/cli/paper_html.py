"""`slamkit-report --paper all DIR... --html OUT`: one self-contained HTML page reproducing the
paper's evaluation from the runs under DIR (every plot and image embedded as a data: URI, no
file or network fetch).

The page holds, for every table of `paper_tables.TABLES` that has runs among them, the table (the
paper's figure beside ours and the difference, with the caveat where our scene is not the
paper's) and a titled bar plot of exactly the metrics the table reports, ours beside the paper's;
the real-time runs' table (`paper_tables.runs_table`); Fig. 1 (PSNR against FPS over the Table
3/4 runs, ours beside the paper's means); Fig. 5 (each run's render | ground-truth images, the
runs' `render_*.png`); each run's settings and the provenance of its group (commit, date,
machine, load) with the commands that reproduce it.

A run belongs to a table when it sets every key the table's rows are told apart by to one of
the table's rows (`preset=paper` for Tables 1-4, `+scale_variant=...` for Table 6, ...) and, for
the tables of one dataset, ran on it (`TABLE_DATASETS`).
"""

from __future__ import annotations

import base64
import html
import io
import json
from pathlib import Path
from typing import Any

from slamkit.cli import paper_tables as pt
from slamkit.formats.atomic import write_atomic

#: The tables of one dataset: a run of another is not one of their rows.
TABLE_DATASETS = {"table1": "replica", "table3": "replica", "table2": "tum", "table4": "tum", "table5": "tum"}
#: Fig. 1's points: the tables whose runs it plots.
FIG1_TABLES = ("table3", "table4")


def table_runs(name: str, runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The completed runs that are rows of table `name` (see the module docstring)."""
    table = pt.TABLES[name]
    rows = {k[:-1] for k in table.paper} | set(table.labels)
    chosen = []
    for run in runs:
        if run["status"] != "completed":
            continue
        settings = run["settings"]
        if tuple(settings.get(k) for k in table.keys) not in rows:
            continue
        dataset = TABLE_DATASETS.get(name)
        if dataset and settings.get("dataset", (run["metrics"].get("settings") or {}).get("dataset")) != dataset:
            continue
        chosen.append(run)
    return chosen


def _png(fig) -> str:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90)
    return "data:image/png;base64," + base64.b64encode(buffer.getvalue()).decode("ascii")


def _markdown_to_html(text: str) -> str:
    """paper_tables' Markdown (a bold title, one pipe table, notes) as HTML."""
    out, rows = [], []

    def flush():
        if rows:
            head, body = rows[0], rows[2:]
            out.append("<table><thead><tr>" + "".join(f"<th>{html.escape(c)}</th>" for c in head) + "</tr></thead>"
                       "<tbody>" + "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>"
                                           for r in body) + "</tbody></table>")
            rows.clear()

    for line in text.splitlines():
        if line.startswith("|"):
            rows.append([c.strip() for c in line.strip().strip("|").split("|")])
            continue
        flush()
        if line.startswith("**") and line.endswith("**"):
            continue  # the table's title: the section's heading already
        if line.strip():
            out.append(f"<p>{html.escape(line)}</p>")
    flush()
    return "\n".join(out)


def _table_plot(name: str, runs: list[dict[str, Any]]) -> str | None:
    """One titled figure, a panel per metric the table reports: ours beside the paper's."""
    from matplotlib.figure import Figure

    table = pt.TABLES[name]
    groups: dict[tuple, list[dict]] = {}
    for run in runs:
        groups.setdefault((tuple(run["settings"].get(k) for k in table.keys), pt.scene_of(run["settings"])),
                          []).append(run["metrics"])
    if not groups:
        return None
    labels = [", ".join(map(str, row)) + f"\n{scene}" for row, scene in groups]
    fig = Figure(figsize=(3.2 * len(table.metrics) + 1, 3.6), layout="constrained")
    fig.suptitle(f"{table.title}: ours and the paper's")
    for i, metric in enumerate(table.metrics):
        ax = fig.add_subplot(1, len(table.metrics), i + 1)
        ours = [pt._mean(ms, metric) for ms in groups.values()]
        paper = [table.paper.get((*row, table.columns.get(scene, pt.MEAN)), {}).get(metric.key)
                 for row, scene in groups]
        xs = range(len(labels))
        ax.bar([x - 0.2 for x in xs], [v if v is not None else 0 for v in ours], 0.4, label="ours", color="tab:blue")
        if any(p is not None for p in paper):
            ax.bar([x + 0.2 for x in xs], [p if p is not None else 0 for p in paper], 0.4,
                   label="paper", color="tab:orange")
        ax.set_title(metric.header, fontsize=9)
        ax.set_xticks(list(xs), labels, fontsize=6, rotation=30, ha="right")
        ax.legend(fontsize=7)
    return _png(fig)


def _fig1(runs: list[dict[str, Any]]) -> str | None:
    """Fig. 1: PSNR against FPS, ours (Tables 3/4's runs) and the paper's means."""
    from matplotlib.figure import Figure

    points = []
    for name in FIG1_TABLES:
        for run in table_runs(name, runs):
            m = run["metrics"]
            if isinstance(m.get("psnr"), (int, float)) and isinstance(m.get("fps"), (int, float)):
                points.append((m["fps"], m["psnr"], f"ours: {run['settings'].get('preset')}, "
                                                    f"{pt.scene_of(run['settings'])}"))
    if not points:
        return None
    fig = Figure(figsize=(6.5, 4.2), layout="constrained")
    ax = fig.add_subplot()
    ax.set_title("Fig. 1: PSNR against FPS (Tables 3 and 4; FPS = frames / total time)", fontsize=10)
    fig.text(0.01, 0.01, "ours: the machine and load of each run's provenance (below); the paper's: an RTX 4090",
             fontsize=7)
    for fps, psnr, label in points:
        ax.scatter([fps], [psnr], marker="o", label=label)
    for name, dataset in (("table3", "Replica"), ("table4", "TUM")):
        for key, values in pt.TABLES[name].paper.items():
            if key[-1] == pt.MEAN and "psnr" in values and "fps" in values:
                ax.scatter([values["fps"]], [values["psnr"]], marker="*", s=120,
                           label=f"paper: {pt.TABLES[name].labels.get(key[:-1], key[0])}, {dataset} mean")
    ax.set_xlabel("FPS [frames / s]")
    ax.set_ylabel("PSNR [dB]")
    ax.legend(fontsize=6)
    return _png(fig)


def _images(run: dict[str, Any]) -> list[tuple[str, str]]:
    out = []
    for path in sorted(Path(run["run"]).glob("render_*.png")):
        out.append((path.stem.replace("render_", "frame "),
                    "data:image/png;base64," + base64.b64encode(path.read_bytes()).decode("ascii")))
    return out


STYLE = """body{font-family:sans-serif;max-width:1200px;margin:1em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;font-size:12px;margin:.5em 0}td,th{border:1px solid #bbb;padding:2px 6px}
th{background:#eee}img{max-width:100%}figure{margin:.5em 0}figcaption{font-size:12px;color:#555}
pre{background:#f6f6f6;padding:.5em;font-size:11px;overflow-x:auto}.grid{display:flex;flex-wrap:wrap;gap:8px}
.grid figure{width:380px}"""


def paper_html(runs: list[dict[str, Any]], out: Path, title: str = "GS-ICP SLAM's evaluation, reproduced") -> Path:
    """Write the page (see the module docstring) for `runs` (`slamkit.cli.run_folders.load_run`
    entries) to `out`; returns it."""
    parts = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             f"<style>{STYLE}</style></head><body><h1>{html.escape(title)}</h1>",
             "<p>Every figure of ours comes from the runs listed at the end (their metrics.json); the paper's "
             "figures are transcribed from Ha, Yeon and Yu, ECCV 2024. Where our scene is not one of the "
             "paper's, the paper's figure beside ours is its mean over its own scenes (said under each table).</p>"]
    realtime = [r for r in runs if r["status"] == "completed" and r["metrics"].get("mode") == "realtime"]
    if realtime:
        parts += ["<h2>Real-time runs</h2>", _markdown_to_html(pt.runs_table(realtime)),
                  f"<p>{html.escape(pt.provenance_line(realtime))}</p>"]
    for name in pt.NAMES:
        chosen = table_runs(name, runs)
        if not chosen:
            continue
        parts += [f"<h2 id='{name}'>{html.escape(pt.TABLES[name].title)}</h2>",
                  _markdown_to_html(pt.paper_table(name, chosen, difference=True)),
                  f"<p>{html.escape(pt.provenance_line(chosen))}</p>"]
        plot = _table_plot(name, chosen)
        if plot:
            parts.append(f"<figure><img src='{plot}' alt='{html.escape(pt.TABLES[name].title)}'></figure>")
    fig1 = _fig1(runs)
    if fig1:
        parts += ["<h2 id='fig1'>Fig. 1: PSNR against FPS</h2>", f"<figure><img src='{fig1}' alt='Fig. 1'></figure>"]
    with_images = [r for r in runs if r["status"] == "completed" and _images(r)]
    if with_images:
        parts.append("<h2 id='fig5'>Fig. 5: renders beside the ground truth (left: the map's render, right: the "
                     "frame)</h2><div class='grid'>")
        for run in with_images:
            for frame, uri in _images(run):
                caption = f"{Path(run['run']).name}, {frame}"
                parts.append(f"<figure><img src='{uri}' alt='{html.escape(caption)}'>"
                             f"<figcaption>{html.escape(caption)}</figcaption></figure>")
        parts.append("</div>")
    parts.append("<h2>Runs: settings and provenance</h2>")
    seen = []
    for run in runs:
        record = pt.provenance_of(run["run"])
        if record is not None and record not in seen:
            seen.append(record)
            commands = "\n".join(r.get("command", "") for r in record.get("runs", []))
            parts.append(f"<h3>{html.escape(str(record.get('group', 'runs')))}</h3>"
                         f"<p>{html.escape(pt.provenance_line([run]))}</p>"
                         + (f"<pre>{html.escape(commands)}</pre>" if commands else ""))
    for run in runs:
        settings = run["metrics"].get("settings") or run["settings"]
        parts.append(f"<details><summary>{html.escape(str(run['run']))} ({html.escape(run['status'])})</summary>"
                     f"<pre>{html.escape(json.dumps(settings, indent=1))}</pre></details>")
    parts.append("</body></html>\n")
    write_atomic(out, "\n".join(parts))
    return out
