"""docs/paper.md's tables of our runs are written by `slamkit-report --docs` from the runs'
outputs committed under benchmarks/results/paper/ (metrics.json, overrides, provenance.json):
the page regenerated from them is the page, and a changed output changes the page."""

from __future__ import annotations

import json
import shutil

import pytest

from slamkit.cli import paper_tables
from slamkit.cli.report import main as report_main

from support.data import REPO

RESULTS = REPO / "benchmarks" / "results" / "paper"


def blocks(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith(paper_tables.BLOCK_START)]


@pytest.mark.parametrize("page", ["paper.md", "results.md"])
def test_every_generated_table_of_a_page_is_regenerated_from_the_committed_runs(page):
    """docs/paper.md's tables of ours, and docs/results.md's sweeps (the tracker ablation)."""
    text = (REPO / "docs" / page).read_text()
    assert blocks(text), f"docs/{page} has no generated tables"
    regenerated = paper_tables.regenerate_document(text, REPO)
    assert regenerated == text, f"docs/{page} differs from its runs: slamkit-report --docs docs/{page}"
    for line in blocks(text):  # each names committed runs with their provenance
        for folder in line.split()[4 if "--paper" in line else 3:-1]:
            runs = list((REPO / folder).rglob("metrics.json"))
            assert runs, f"{folder}: no committed metrics.json"
            assert all(paper_tables.provenance_of(r.parent) is not None for r in runs)


def test_a_changed_output_changes_the_page_and_check_says_so(tmp_path, monkeypatch, capsys):
    shutil.copytree(RESULTS / "realtime", tmp_path / "benchmarks" / "results" / "paper" / "realtime")
    doc = tmp_path / "paper.md"
    doc.write_text("# x\n\n<!-- slamkit-report --runs benchmarks/results/paper/realtime -->\nstale\n"
                   "<!-- end slamkit-report -->\n\nafter\n")
    monkeypatch.chdir(tmp_path)
    assert report_main(["--docs", str(doc), "--check"]) == 1
    assert report_main(["--docs", str(doc)]) == 0
    written = doc.read_text()
    assert "stale" not in written and written.endswith("<!-- end slamkit-report -->\n\nafter\n")
    assert "| tum_paper |" in written and "load average" in written
    assert report_main(["--docs", str(doc), "--check"]) == 0
    metrics_path = tmp_path / "benchmarks" / "results" / "paper" / "realtime" / "tum_paper" / "metrics.json"
    metrics = json.loads(metrics_path.read_text())
    metrics["psnr"] = 99.5
    metrics_path.write_text(json.dumps(metrics))
    assert report_main(["--docs", str(doc), "--check"]) == 1
    assert "99.50" in paper_tables.regenerate_document(doc.read_text(), tmp_path)


@pytest.mark.parametrize("head", ["--paper table99 x", "--paper", "--nothing x"])
def test_a_bad_block_is_a_one_line_error_naming_the_file(tmp_path, monkeypatch, capsys, head):
    doc = tmp_path / "paper.md"
    doc.write_text(f"<!-- slamkit-report {head} -->\n<!-- end slamkit-report -->\n")
    monkeypatch.chdir(tmp_path)
    assert report_main(["--docs", str(doc)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(doc) in err
