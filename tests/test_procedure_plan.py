"""`plan` sets QUEST+ beside the staircase and rates every setting against the Cramér-Rao bound."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from masking_lab.commands.cli import main
from masking_lab.formats.protocol import load_protocol
from masking_lab.formats.resources import shipped
from masking_lab.planning.plan import efficiency_fields
from masking_lab.planning.procedure_plan import _outcome, compare_procedures
from masking_lab.planning.procedure_report import procedures_figure
from masking_lab.planning.settings import PlanSettings, Schedule, StopRule
from masking_lab.procedures.fisher import cramer_rao_sd, max_information
from masking_lab.procedures.quest_plus import QuestPlusSettings
from masking_lab.procedures.quest_plus_batch import simulate_quest_plus
from masking_lab.procedures.staircase_batch import COMPLETED, Observer

QUEST_PROTOCOL = shipped("protocols", "experiment1_questplus.yaml")


def read_csv(path):
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


@pytest.fixture(scope="module")
def planned(tmp_path_factory):
    out = tmp_path_factory.mktemp("plan")
    # The default QUEST+ tracks for a psi-marginal protocol (40 per set, 600 in all): each
    # runs to the ladder's SD 0.4 dB or its cap, ~30 times a known-slope track's work.
    args = ["plan", str(QUEST_PROTOCOL), "--replicates", "300", "--ml-replicates", "0"]
    args += ["--stop-rules", "11/8", "--schedules", "4,4,4,2"]
    args += ["--max-reversals", "15", "--out", str(out)]
    assert main(args) == 0
    return out


def test_plan_on_the_quest_plus_protocol_reaches_the_papers_precision_in_45_trials(planned):
    # The shipped protocol marginalises slope and lapse (psi-marginal, posterior SD ≤ 1.6 dB):
    # its estimates' SD is the paper's 1.08 dB or better in a median of at most 45 trials.
    rows = read_csv(planned / "plan_procedures.csv")
    own = [r for r in rows if r["own"] == "True"]
    assert len(own) == 1 and own[0]["procedure"] == "psi-marginal"
    assert float(own[0]["sd_db"]) <= 1.08 and float(own[0]["trials_median"]) <= 45
    assert float(own[0]["completed"]) > 0.99
    paper = next(
        r
        for r in rows
        if r["procedure"] == "staircase 4,4,4,2"
        and r["setting"] == "11/8"
        and r["capped"] == "True"
    )
    assert 0.25 <= float(paper["efficiency"]) <= 0.37  # the paper's rule: ~30 % efficient
    assert float(own[0]["efficiency"]) > 1.5 * float(paper["efficiency"])
    for r in rows:  # every setting with an SD is rated against the bound
        if r["sd_db"] and math.isfinite(float(r["sd_db"])):
            cr = float(r["cr_trials"])
            assert float(r["efficiency"]) == pytest.approx(cr / float(r["trials_mean"]), rel=1e-4)
            sd = float(cramer_rao_sd(cr, scale_db=1.5, lapse=0.02))
            assert sd == pytest.approx(float(r["sd_db"]), rel=1e-4)


def test_plan_prints_efficiencies_and_the_fewest_trials_across_procedures(planned):
    text = (planned / "plan.txt").read_text(encoding="utf-8")
    assert "Procedures against the Cramér-Rao bound" in text
    # the section heading, then the table's own title line: the table follows the last one
    table = text.rsplit("Procedures against the Cramér-Rao bound", 1)[1].split("Fewest")[0]
    rated = [
        ln for ln in table.splitlines() if ln.startswith(("staircase", "QUEST+", "psi-marginal"))
    ]
    assert rated and all(ln.rstrip().endswith("%") or ln.rstrip().endswith("—") for ln in rated)
    fewest = text.rsplit("Fewest trials for ±1 dB", 1)[1]
    assert "psi-marginal (posterior mean)" in fewest and "staircase 4,4,4,2" in fewest
    assert (planned / "plan_procedures.png").read_bytes()[:4] == b"\x89PNG"


def test_every_sd_target_is_what_a_run_with_that_stop_rule_does():
    """Targets read off one strict run equal separate runs (common random numbers)."""
    own = QuestPlusSettings(-20.0, 45.0, target_sd_db=1.5, min_trials=5, max_trials=40)
    thr = np.linspace(-2.0, 20.0, 30)
    strict = simulate_quest_plus(
        QuestPlusSettings(-20.0, 45.0, target_sd_db=0.6, max_trials=300),
        thr,
        rng=np.random.default_rng(3),
    )
    status, n, est = _outcome(strict, own, own.max_trials)
    alone = simulate_quest_plus(own, thr, rng=np.random.default_rng(3))
    assert n.tolist() == alone.n_trials.tolist()
    np.testing.assert_allclose(est, alone.estimate_db, rtol=0, atol=1e-9)  # BLAS batch sizes
    assert ((status == COMPLETED) == (alone.status == "completed")).all()


def test_the_figure_draws_the_bound_as_the_limit():
    p = load_protocol(QUEST_PROTOCOL)
    s = PlanSettings(
        (StopRule(11, 8),), (Schedule((4.0, 2.0)),), observer=Observer(1.5, 0.02), replicates=20
    )
    # A short ladder: the psi-marginal tracks stop at SD 1.25 dB, not the default 0.4 dB.
    ladder = (3.0, 2.0, 1.6, 1.25)
    c = compare_procedures(
        p, None, s, np.full((15, 20), 5.0), quest_replicates=10, sd_ladder_db=ladder
    )
    ax = procedures_figure(c).axes[0]
    bound = next(line for line in ax.get_lines() if line.get_label() == "Cramér-Rao bound")
    n, sd = bound.get_xdata(), bound.get_ydata()
    info = max_information(scale_db=1.5, lapse=0.02)[0]
    np.testing.assert_allclose(sd, 1 / np.sqrt(n * info))
    quest = next(line for line in ax.get_lines() if line.get_label() == "psi-marginal")
    x, y = quest.get_xdata(), quest.get_ydata()
    assert len(x) >= 3
    assert np.all(y >= np.interp(x, n, sd) * 0.9)  # nothing meaningfully beats the bound


def test_efficiency_of_the_papers_rule_from_the_bound():
    f = efficiency_fields(1.08, 52.0, Observer(1.5, 0.02))
    assert f["cr_trials"] == pytest.approx(16.1, abs=0.05)
    assert f["efficiency"] == pytest.approx(16.1 / 52, abs=0.002)
    assert math.isnan(efficiency_fields(math.nan, 52.0, Observer())["efficiency"])
