"""`plan` describes the protocol it was given (issue 17): "this protocol" is the protocol's own
procedure and settings, no trial cap is fixed in code, plan.txt and report.html carry the same
sections, and a second plan never replaces the first one's folder."""

from __future__ import annotations

import csv
import html
import re
from pathlib import Path

import pytest

from masking_lab.commands.cli import main

PROTOCOLS = Path(__file__).resolve().parents[1] / "protocols"
FAST = [
    "--replicates", "12", "--ml-replicates", "0", "--quest-replicates", "12",
    "--schedules", "4,4,4,2", "--stop-rules", "9/6,11/8", "--max-reversals", "11",
]  # fmt: skip


def _plan(protocol: str, out: Path, *extra: str) -> Path:
    assert main(["plan", str(PROTOCOLS / protocol), *FAST, "--out", str(out), *extra]) == 0
    return out


def _rows(path: Path) -> list[dict]:
    with path.open() as fh:
        return list(csv.DictReader(fh))


def _own(rows: list[dict]) -> list[dict]:
    return [r for r in rows if r.get("own") in ("True", "true", "1")]


@pytest.fixture(scope="module")
def questplus_plan(tmp_path_factory):
    return _plan("experiment1_questplus.yaml", tmp_path_factory.mktemp("q") / "plan")


@pytest.fixture(scope="module")
def staircase_plan(tmp_path_factory):
    return _plan("experiment1.yaml", tmp_path_factory.mktemp("s") / "plan")


def test_a_questplus_protocol_is_described_as_questplus(questplus_plan):
    text = (questplus_plan / "plan.txt").read_text()
    # The shipped QUEST+ protocol marginalises slope and lapse (issue 18): psi-marginal.
    assert "this protocol: psi-marginal (slope unknown), stops at posterior SD ≤ 1.6 dB" in text
    assert "trial cap 120" in text and "not this protocol" in text
    assert not _own(_rows(questplus_plan / "plan_table.csv"))  # no staircase row is its own
    own = _own(_rows(questplus_plan / "plan_procedures.csv"))
    assert [(r["procedure"], r["setting"], r["max_trials"]) for r in own] == [
        ("psi-marginal", "SD ≤ 1.6 dB", "120")
    ]
    assert "Per set, the paper's staircase beside this protocol" in text
    assert not re.search(r"^\S.*\*\s*11/8", text, re.M)  # the 11/8 row is not starred
    assert "psi-marginal (this protocol)" in (questplus_plan / "report.html").read_text()


def test_a_staircase_protocol_stars_its_staircase_and_no_questplus_row(staircase_plan):
    text = (staircase_plan / "plan.txt").read_text()
    assert "this protocol: staircase 1-up 3-down, 11/8" in text and "trial cap 150" in text
    own = _own(_rows(staircase_plan / "plan_table.csv"))
    assert {(r["schedule"], r["rule"]) for r in own} == {("4,4,4,2", "11/8")}
    procedures = _rows(staircase_plan / "plan_procedures.csv")
    assert not [r for r in _own(procedures) if r["procedure"].startswith("QUEST")]
    # The QUEST+ beside a staircase protocol is capped as the protocol's staircase is.
    capped = {
        r["max_trials"] for r in procedures if r["procedure"] == "QUEST+" and r["capped"] == "True"
    }
    assert capped == {"150"}


def test_the_questplus_cap_is_an_option_not_a_constant(tmp_path):
    out = _plan("experiment1.yaml", tmp_path / "p", "--quest-max-trials", "60")
    procedures = _rows(out / "plan_procedures.csv")
    capped = {
        r["max_trials"] for r in procedures if r["procedure"] == "QUEST+" and r["capped"] == "True"
    }
    assert capped == {"60"}


def test_figure_label_names_the_protocols_own_setting():
    import numpy as np

    from masking_lab.formats.protocol import load_protocol
    from masking_lab.planning import plan as P
    from masking_lab.planning.figures import speed_accuracy
    from masking_lab.procedures.staircase_batch import Observer

    def labels(name: str) -> list[str]:
        protocol = load_protocol(PROTOCOLS / name)
        settings = P.PlanSettings(
            stop_rules=(P.StopRule(11, 8),),
            schedules=(P.Schedule((4.0, 4.0, 4.0, 2.0)),),
            observer=Observer(1.5, 0.02, 1 / 3),
            replicates=8,
            ml_replicates=0,
            max_reversals=11,
        )
        thr = np.full((len(protocol.sets), 8), 5.0)
        fig = speed_accuracy(P.run_plan(protocol, settings, thr))
        return [t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().texts]

    assert any(t.startswith("this protocol (11/8, 4,4,4,2 dB)") for t in labels("experiment1.yaml"))
    assert not any("this protocol" in t for t in labels("experiment1_questplus.yaml"))


def _text_titles(text: str) -> list[str]:
    lines = text.splitlines()
    return [
        lines[i - 1]
        for i in range(1, len(lines))
        if lines[i] and set(lines[i]) == {"-"} and len(lines[i]) == len(lines[i - 1])
    ]


def test_every_plan_txt_section_is_a_heading_of_report_html(questplus_plan):
    text = (questplus_plan / "plan.txt").read_text()
    html = (questplus_plan / "report.html").read_text()
    titles = _text_titles(text)
    assert "Procedures against the Cramér-Rao bound" in titles
    assert any(t.startswith("Fewest trials for ±") for t in titles)
    headings = [re.sub(r"<[^>]+>", "", h) for h in re.findall(r"<h2[^>]*>(.*?)</h2>", html)]
    assert sorted(titles) == sorted(headings)
    # the fewest-trials answer and the bound table are in the page, not only in plan.txt
    assert "does not reach it" in html or " trials (90 % within " in html
    assert "Fisher information peaks at" in html


def test_a_second_plan_writes_plan_out_2_and_an_explicit_out_needs_force(
    tmp_path, monkeypatch, capsys
):
    monkeypatch.chdir(tmp_path)
    args = ["plan", str(PROTOCOLS / "baseline.yaml"), *FAST, "--quest-replicates", "0"]
    assert main(args) == 0 and main(args) == 0
    assert (tmp_path / "plan_out" / "plan.txt").is_file()
    assert (tmp_path / "plan_out-2" / "plan.txt").is_file()
    capsys.readouterr()
    assert main([*args, "--out", "plan_out"]) == 2
    assert "--force" in capsys.readouterr().err
    assert main([*args, "--out", "plan_out", "--force"]) == 0


def test_the_staircase_table_explains_a_star_only_when_it_has_one(questplus_plan, staircase_plan):
    def pooled(plan: Path) -> str:
        text = (plan / "plan.txt").read_text()
        return text.split("Speed and accuracy of each setting", 1)[1].split("\n\n", 1)[0]

    # QUEST+: its row is in the procedures table; the staircase table stars nothing.
    assert "*" not in pooled(questplus_plan)
    star = pooled(staircase_plan)
    assert "* this protocol." in star and star.count("*") == 2  # one starred row, its footnote


def test_rows_without_an_al_show_no_efficiency_in_the_html(questplus_plan):
    # SD ≤ 0.4 dB runs into the protocol's 80-trial cap: no AL, so no efficiency (was "— %").
    html = (questplus_plan / "report.html").read_text()
    assert "— %" not in html
    assert re.search(r"<td>\d+ %</td>", html)  # the rows with an AL keep theirs


def test_the_html_per_set_table_says_whose_rows_they_are(questplus_plan, staircase_plan):
    for plan, whose in (
        (questplus_plan, "the paper's staircase beside this protocol"),
        (staircase_plan, "this protocol's setting"),
    ):
        title = f"Per set, {whose} (4,4,4,2 dB, 11/8)"
        assert f"{title}:" in (plan / "plan.txt").read_text()
        assert f"<caption>{title}</caption>" in html.unescape((plan / "report.html").read_text())
