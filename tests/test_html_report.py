"""`report.html` of `analyze` and `usertest-report`, opened in real headless Chromium: the page
renders (a non-blank screenshot), its tables and embedded figures are in the rendered DOM, it
needs no network and logs no console errors. Chromium missing is a failure, not a skip."""

from __future__ import annotations

import base64
import json
import re
from pathlib import Path

import numpy as np
import pytest
from chromium_support import open_in_chromium, screenshot_pixels
from test_usertest_analysis import header, trial_records, write_log

from masking_lab.analysis.report import LogsInput, build_report
from masking_lab.analysis.report_html import render_html
from masking_lab.analysis.settings import AnalysisSettings
from masking_lab.commands.cli import main
from masking_lab.simulation.synthetic_logs import simulate_study

PNG = b"\x89PNG\r\n\x1a\n"


def _images(dom: str) -> list[bytes]:
    """Every <img> of the page, decoded from its data: URI (fails on any other source)."""
    srcs = re.findall(r"<img[^>]*\ssrc=\"([^\"]*)\"", dom)
    out = []
    for src in srcs:
        assert src.startswith("data:image/png;base64,"), src[:60]
        out.append(base64.b64decode(src.split(",", 1)[1]))
    return out


def _assert_page_rendered(page: Path, work: Path) -> str:
    shown = open_in_chromium(page, work)
    assert shown.console == [], shown.console
    assert shown.screenshot.stat().st_size > 10_000
    px = screenshot_pixels(shown.screenshot)[..., :3]
    non_white = np.mean(px.min(axis=-1) < 0.9)
    assert non_white > 0.03, f"screenshot is (nearly) blank: {non_white:.3%} non-white"
    assert px.std() > 0.05
    # Self-contained: nothing fetched from the network.
    assert not re.search(r"(src|href)=\"(https?:)?//", shown.dom)
    return shown.dom


def test_the_console_check_catches_script_errors(tmp_path):
    page = tmp_path / "bad.html"
    page.write_text("<html><body><script>console.error('boom'); nope();</script></body></html>")
    shown = open_in_chromium(page, tmp_path)
    assert any("Uncaught ReferenceError" in line for line in shown.console), shown.console
    assert any("boom" in line for line in shown.console)


@pytest.fixture(scope="module")
def analyzed(tmp_path_factory):
    root = tmp_path_factory.mktemp("html")
    simulate_study(root / "data", n_participants=4, seed=3, baseline_start_above_db=10.0)
    out = root / "out"
    argv = ["analyze", str(root / "data"), "--out", str(out), "--n-boot", "200", "--quiet"]
    assert main(argv) == 0
    return out


def test_analysis_report_renders_tables_figures_and_provenance(analyzed, tmp_path):
    dom = _assert_page_rendered(analyzed / "report.html", tmp_path)
    for caption in (
        "Two-way repeated-measures ANOVA on AL shift, with sphericity",
        "Paired comparisons between frequency levels (Bonferroni)",
        "Mean AL shift per cell (dB), one-sample t-test against 0",
        "Fitted masking functions",
    ):
        assert dom.count(caption) == 2, caption  # one per experiment
    assert "Mauchly W" in dom and "Pooling (paired" in dom
    # The embedded figures are the very PNGs written beside the report.
    images = _images(dom)
    assert images[:2] == [
        (analyzed / "figures" / f"masking_experiment{k}.png").read_bytes() for k in (1, 2)
    ]
    # ... and the individual shift plots (issue 17), also the files written beside it.
    assert images[2:] == [
        (analyzed / "figures" / f"shifts_experiment{k}.png").read_bytes() for k in (1, 2)
    ]
    # Fitted functions with their intervals, as exported.
    doc = json.loads((analyzed / "masking_params.json").read_text())
    f = doc["functions"][0]
    lo, hi = f["intercept_ci_db"]
    shown = [(float(a), float(b)) for a, b in re.findall(r"\[(-?[\d.]+), (-?[\d.]+)\]", dom)]
    assert any(abs(a - lo) < 1e-3 and abs(b - hi) < 1e-3 for a, b in shown), (lo, hi)
    # Provenance: every input's sha256.
    for item in doc["provenance"]["inputs"]:
        assert item["sha256"] in dom and item["path"] in dom
    assert "None" not in re.sub(r"<[^>]+>", " ", dom)


def test_text_from_the_data_is_escaped(tmp_path):
    model = build_report(
        [],
        AnalysisSettings(),
        source="analyze",
        inputs=LogsInput(
            "<img src=x onerror=console.error(1)>", 1, 0, (("a<b>.jsonl", "bad"),), ()
        ),
    )
    page = tmp_path / "report.html"
    page.write_text(render_html(model), encoding="utf-8")
    dom = _assert_page_rendered(page, tmp_path)
    assert "&lt;img src=x" in dom and "<img" not in dom and "a&lt;b&gt;.jsonl" in dom


def test_usertest_report_renders_in_chromium(tmp_path):
    data = tmp_path / "data"
    for p in ("A", "B", "C"):
        write_log(data / p / f"usertest-{p}.jsonl", [header(p), *trial_records(p)])
    out = tmp_path / "out"
    assert main(["usertest-report", str(data), "--out", str(out)]) == 0
    dom = _assert_page_rendered(out / "report.html", tmp_path)
    assert _images(dom) == [(out / "figure8a.png").read_bytes()]
    for caption in ("Correct rate, mean ± SD over participants", "Sessions"):
        assert caption in dom
    assert dom.count("(rows presented, columns answered)") == 4
    assert "chance (guessing)" in dom and "3 participants" in dom


def test_plan_report_renders_in_chromium(tmp_path):
    exp1 = Path(__file__).resolve().parents[1] / "protocols" / "experiment1.yaml"
    out = tmp_path / "plan"
    assert main(["plan", str(exp1), "--replicates", "20", "--out", str(out)]) == 0
    dom = _assert_page_rendered(out / "report.html", tmp_path)
    assert _images(dom)[0] == (out / "plan_speed_accuracy.png").read_bytes()
    assert "Speed and accuracy of each setting" in dom and "Reversals needed for" in dom
    # One row per (schedule, rule, estimator) of the plan table.
    table = (out / "plan_table.csv").read_text().splitlines()
    body = dom.split('id="table"')[1].split("</table>")[0]
    assert body.count("<tr") == len(table)  # header row + one per data row
