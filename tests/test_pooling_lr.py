"""Pooling by model comparison, pinned to statsmodels' nested-OLS tests, and in the report."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import statsmodels.formula.api as smf

from masking_lab.analysis.pooling_lr import compare_pooling, pooled_vs_separate


def _data(seed: int, slopes=(0.8, 0.8, 0.5)):
    rng = np.random.default_rng(seed)
    x = np.repeat([5.0, 10.0, 15.0, 20.0, 25.0], 10)
    # Intercepts keep every point on the ramp's rising part, where the ramp is a line and
    # the comparison is exactly the nested OLS one.
    return {
        f"MV{f}": (x, 20.0 + s * x + rng.normal(0, 1.5, x.size))
        for f, s in zip((120, 180, 270), slopes, strict=True)
    }


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_lr_and_f_equal_statsmodels_nested_ols(seed):
    points = _data(seed)
    frame = pd.concat(pd.DataFrame({"level": lv, "x": x, "y": y}) for lv, (x, y) in points.items())
    full = smf.ols("y ~ C(level) * x", data=frame).fit()
    pooled = smf.ols("y ~ x", data=frame).fit()
    lr, p_lr, df = full.compare_lr_test(pooled)
    f, p_f, _ = full.compare_f_test(pooled)
    c = pooled_vs_separate(points)
    assert c.df == df == 4
    assert c.lr_chi2 == pytest.approx(lr, rel=1e-9)
    assert c.p_lr == pytest.approx(p_lr, rel=1e-6)
    assert c.f_stat == pytest.approx(f, rel=1e-9) and c.p_f == pytest.approx(p_f, rel=1e-6)
    assert c.delta_aic == pytest.approx(pooled.aic - full.aic, rel=1e-9)
    assert c.delta_bic == pytest.approx(pooled.bic - full.bic, rel=1e-9)


def test_equal_ramps_pool_and_different_ones_do_not():
    by_pair = {c.levels: c for c in compare_pooling(_data(3), ["MV120", "MV180", "MV270"])}
    assert by_pair[("MV120", "MV180")].prefers() == "pooled"
    assert by_pair[("MV120", "MV270")].prefers() == "separate"
    assert by_pair[("MV120", "MV180", "MV270")].prefers() == "separate"


def test_the_analysis_report_shows_the_comparison_beside_the_papers_rule(tmp_path):
    from masking_lab.commands.cli import main
    from masking_lab.simulation.synthetic_logs import simulate_study

    simulate_study(tmp_path / "logs", n_participants=10, seed=4)
    # The comparison and the pooling rule use no bootstrap and no figure: spare those costs.
    argv = ["analyze", str(tmp_path / "logs"), "--out", str(tmp_path / "out"), "--quiet"]
    argv += ["--n-boot", "100", "--pf-boot", "0", "--figures", "none", "--no-trial-tables"]
    assert main(argv) == 0
    report = (tmp_path / "out" / "report.txt").read_text(encoding="utf-8")
    block = report.split("Model comparison (likelihood ratio, AIC, BIC; reported, not used):")
    assert len(block) == 3  # experiments I and II
    assert "Pooling (paired)" in block[0]  # the paper's rule still decides
    assert "LR χ²(2)" in block[1] and "ΔBIC" in block[1]
