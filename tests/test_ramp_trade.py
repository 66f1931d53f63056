"""The trade of docs/speed-accuracy.md on a few simulated participants: every route gives a
ramp per participant from the same calibration errors, the functional track's checkpoints are
prefixes of one track, precision is measured against the truth, and the Cramér-Rao bound falls
as 1/√n."""

from __future__ import annotations

import math

import numpy as np
import pytest

from masking_lab.planning.ramp_trade import (
    TradeSettings,
    cramer_rao_ramp,
    ramp_precision,
    run_trade,
)


def test_every_route_gives_a_ramp_per_participant_and_is_seeded():
    small = TradeSettings(replicates=3, checkpoints=(10, 20))
    one = run_trade(small, seed=3)
    assert [r.route for r in one] == ["paper", "quest_plus", "functional (10)", "functional (20)"]
    assert one == run_trade(small, seed=3)
    paper, quest = one[0], one[1]
    assert 150 < paper.trials_mean < 600  # five staircases of ~52 trials
    assert quest.trials_mean < paper.trials_mean
    for r in one:
        assert r.n >= 2
        assert all(
            math.isfinite(v) and v >= 0 for v in (r.sd_intercept_db, r.sd_slope, r.rms_al_db)
        )
        assert r.minutes == pytest.approx(r.trials_mean * small.seconds_per_trial / 60)


def test_precision_is_the_error_against_the_true_ramp():
    a_hat = np.array([-7.442, -7.442])
    b_hat = np.array([0.711, 0.711])
    assert ramp_precision(a_hat, b_hat, -7.442, 0.711, (5.0, 25.0)) == (0.0, 0.0, 0.0)
    sd_a, sd_b, rms = ramp_precision(a_hat + 1.0, b_hat, -7.442, 0.711, (5.0, 25.0))
    assert sd_a == pytest.approx(1.0) and sd_b == 0.0 and 0 < rms <= 1.0


def test_the_cramer_rao_bound_falls_as_one_over_root_n():
    sd100 = cramer_rao_ramp(100, (5.0, 25.0))
    sd400 = cramer_rao_ramp(400, (5.0, 25.0))
    for a, b in zip(sd100, sd400, strict=True):
        assert b == pytest.approx(a / 2)
    # a wider masker range pins the slope better
    assert cramer_rao_ramp(100, (0.0, 40.0))[1] < sd100[1]


def test_plan_on_a_functional_protocol_prints_the_trade(tmp_path, capsys):
    from test_functional_session import functional_protocol

    from masking_lab.commands.cli import main

    argv = ["plan", str(functional_protocol(tmp_path)), "--replicates", "2", "--seed", "1"]
    argv += ["--out", str(tmp_path / "plan"), "--scheduler", "synchronous", "--no-progress"]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "paper" in text and "functional (14)" in text and "Cramér-Rao" in text
    assert "paired bootstrap 95 % interval" in text and "  functional (14)" in text
    assert (tmp_path / "plan" / "masking_function_trade.txt").read_text(encoding="utf-8") == text


def test_the_same_seed_gives_the_same_table_in_process_and_on_a_two_process_cluster():
    """Chunks carry their own seeds: where they run does not change the numbers."""
    small = TradeSettings(replicates=4, checkpoints=(6,))
    here = run_trade(small, seed=5, scheduler="synchronous", chunk=2)
    from masking_lab.planning.parallel import run_chunks

    calls = []

    def spy(fn, args, *, scheduler, max_workers=4):
        calls.append((scheduler, len(args)))
        return run_chunks(fn, args, scheduler=scheduler, max_workers=2)

    import masking_lab.planning.parallel as parallel

    original = parallel.run_chunks
    parallel.run_chunks = spy
    try:
        cluster = run_trade(small, seed=5, scheduler=None, chunk=2)
    finally:
        parallel.run_chunks = original
    assert calls == [(None, 2)]
    assert cluster == here
    # and the chunking, not the workers, fixes the streams: another chunk size differs
    assert run_trade(small, seed=5, scheduler="synchronous", chunk=4) != here


def test_precision_ratios_pair_the_participants_across_routes():
    """Ratios of RMS errors to the paper route's, with a paired bootstrap interval."""
    from masking_lab.planning.ramp_trade import TradeEstimates, precision_ratios

    s = TradeSettings()
    rng = np.random.default_rng(0)
    a_err, b_err = rng.normal(0, 3.0, 40), rng.normal(0, 0.15, 40)
    paper_a, paper_b = s.intercept_db + a_err, s.slope + b_err
    est = TradeEstimates(
        intercepts_db={
            "paper": paper_a,
            "same": paper_a.copy(),
            "half": s.intercept_db + a_err / 2,
            "gaps": np.where(np.arange(40) % 4 == 0, np.nan, paper_a),
        },
        slopes={
            "paper": paper_b,
            "same": paper_b.copy(),
            "half": s.slope + b_err / 2,
            "gaps": paper_b.copy(),
        },
        trials={"paper": 260.0, "same": 260.0, "half": 87.0, "gaps": 87.0},
    )
    r = precision_ratios(s, est, n_boot=300, seed=1)
    assert sorted(r) == ["gaps", "half", "same"]
    # the same participants' errors: the ratio is 1 in every resample (pairing, not chance)
    np.testing.assert_allclose(r["same"], 1.0)
    # every error halved: intercept and slope exactly half in every resample
    np.testing.assert_allclose(r["half"][:2], 0.5)
    for row in r.values():
        assert np.all(np.isfinite(row)) and np.all(row[:, 1] <= row[:, 0] + 1e-12)
        assert np.all(row[:, 0] <= row[:, 2] + 1e-12)
    # a route without a ramp for some participants is measured on those it has
    kept = ~np.isnan(est.intercepts_db["gaps"])
    whole = math.sqrt(np.mean(a_err[kept] ** 2)) / math.sqrt(np.mean(a_err**2))
    assert r["gaps"][0, 0] == pytest.approx(whole)
    assert r["gaps"][0, 2] > r["gaps"][0, 1]  # resampling spreads it


def test_the_quest_plus_route_is_the_shipped_protocols():
    """The trade's QUEST+ per set runs what `experiment1_questplus.yaml` ships (psi-marginal)."""
    from masking_lab.formats.protocol import load_protocol
    from masking_lab.formats.resources import shipped
    from masking_lab.planning.ramp_trade import PAPER_QUEST

    protocol = load_protocol(shipped("protocols", "experiment1_questplus.yaml"))
    assert {s.procedure for s in protocol.sets} == {PAPER_QUEST}
    assert len(PAPER_QUEST.scales_db) > 1 and len(PAPER_QUEST.lapses) > 1
