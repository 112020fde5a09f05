"""`slamkit-report --paper all DIR --html OUT`: one self-contained page of the paper's tables and
figures from committed runs, opened in a real headless Chromium: it renders, every image loads
(all embedded), no console error; the committed example of the shared data does the same."""

from __future__ import annotations

import re

import pytest

from slamkit.cli.report import main as report_main

from support.browser import chromium, open_page
from support.data import REPO

pytest.importorskip("websockets.sync.client")
pytestmark = pytest.mark.skipif(chromium() is None, reason="no chromium (make setup-test installs Debian's)")

RESULTS = REPO / "benchmarks" / "results" / "paper"
EXAMPLE = RESULTS / "report.html"


def check_page(path, min_images: int) -> None:
    text = path.read_text()
    assert not re.search(r"""(src|href)=['"](?!data:|#)""", text), "the page fetches something"
    page = open_page(path)
    assert page.errors == []
    assert page.title and page.text_length > 1000
    assert len(page.images) >= min_images
    broken = [i for i in page.images if not (i["complete"] and i["width"] > 0 and i["height"] > 0)]
    assert broken == []


def test_the_report_of_the_committed_runs_renders_with_every_image_in_a_browser(tmp_path, capsys):
    out = tmp_path / "report.html"
    assert report_main([str(RESULTS), "--out", str(tmp_path), "--paper", "all", "--html", str(out)]) == 0
    text = out.read_text()
    for heading in ("Table 1: tracking on Replica", "Table 4: map quality", "Fig. 1: PSNR against FPS",
                    "Fig. 5: renders beside the ground truth", "Real-time runs", "provenance"):
        assert heading in text
    assert "LPIPS, ours - paper" in text and "commit" in text and "slamkit preset=paper" in text
    renders = len(list(RESULTS.rglob("render_*.png")))
    check_page(out, min_images=4 + 1 + renders)  # Tables 1-4's plots, Fig. 1, the renders


def test_the_committed_example_report_opens_in_a_browser():
    assert EXAMPLE.stat().st_size < 4 * 2**20
    check_page(EXAMPLE, min_images=5)


def test_a_broken_page_is_caught(tmp_path):
    page = tmp_path / "broken.html"
    page.write_text("<!DOCTYPE html><html><head><title>x</title></head><body><p>" + "y" * 1200 + "</p>"
                    "<img src='data:image/png;base64,AAAA'><script>console.error('bad')</script></body></html>")
    report = open_page(page)
    assert any("bad" in e for e in report.errors)
    assert report.images and report.images[0]["width"] == 0
