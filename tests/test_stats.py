"""Repeated-measures statistics checked against an independent implementation (pingouin) on a
published data set and on generated 3 × 5 data, plus degenerate inputs."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats as sps

from masking_lab.analysis.stats import mauchly, rm_anova, rm_design
from masking_lab.analysis.t_tests import one_sample_t, paired_comparisons, paired_t
from masking_lab.core.errors import AnalysisError

pg = pytest.importorskip("pingouin")

PG_EFFECTS = {"frequency": 0, "level": 1, "frequency:level": 2}


def _published():
    # pingouin's "rm_anova2": performance of 10 employees, Time (Pre/Post) × Metric (3 levels),
    # from www.real-statistics.com.
    df = pg.read_dataset("rm_anova2")
    return df.rename(columns={"Subject": "participant", "Time": "a", "Metric": "b"})


def _generated(seed=0, n=12, a=3, b=5):
    rng = np.random.default_rng(seed)
    rows = []
    for s in range(n):
        offset = rng.normal(0, 2)
        for i in range(a):
            for j in range(b):
                # unequal variances across cells, so sphericity is violated
                y = offset + 0.5 * i + 2 * j + rng.normal(0, 1 + 0.5 * j + i)
                rows.append({"participant": f"S{s:02d}", "a": f"F{i}", "b": j * 5.0, "y": y})
    return pd.DataFrame(rows)


def _compare_with_pingouin(df, dv):
    design = rm_design(df, subject="participant", factor_a="a", factor_b="b", dv=dv)
    ours = rm_anova(design.data)
    ref = pg.rm_anova(
        df, dv=dv, within=["a", "b"], subject="participant", effsize="np2", correction=True
    )
    assert [e.name for e in ours] == ["frequency", "level", "frequency:level"]
    for e in ours:
        r = ref.iloc[PG_EFFECTS[e.name]]
        assert pytest.approx(r["F"], rel=1e-9) == e.F
        assert (e.df1, e.df2) == (r["ddof1"], r["ddof2"])
        assert e.p == pytest.approx(r["p_unc"], rel=1e-7)
        assert e.np2 == pytest.approx(r["np2"], rel=1e-9)
        assert e.eps_gg == pytest.approx(r["eps"], rel=1e-9)
        assert e.p_gg == pytest.approx(r["p_GG_corr"], rel=1e-7)
        if e.df1 > 1:
            assert e.mauchly_w == pytest.approx(r["W_spher"], rel=1e-7)
            assert e.mauchly_p == pytest.approx(r["p_spher"], rel=1e-6)
    return design, ours


def test_two_way_rm_anova_matches_pingouin_on_published_data():
    _, ours = _compare_with_pingouin(_published(), "Performance")
    # Values printed in pingouin's documentation for this data set.
    time, metric, inter = ours
    assert pytest.approx(33.852, abs=1e-3) == time.F
    assert pytest.approx(26.959, abs=1e-3) == metric.F
    assert inter.eps_gg == pytest.approx(0.727, abs=1e-3)


def test_two_way_rm_anova_and_mauchly_match_pingouin_on_a_3x5_design():
    df = _generated()
    _, ours = _compare_with_pingouin(df, "y")
    # Interaction sphericity on its own (pingouin.sphericity with two factors).
    ref = pg.sphericity(df, dv="y", within=["a", "b"], subject="participant")
    inter = ours[2]
    assert inter.mauchly_w == pytest.approx(ref.W, rel=1e-7)
    assert inter.mauchly_chi2 == pytest.approx(ref.chi2, rel=1e-7)
    assert inter.mauchly_df == ref.dof
    assert inter.mauchly_p == pytest.approx(ref.pval, rel=1e-6)


def test_one_way_mauchly_matches_pingouin_sphericity():
    df = _generated(seed=3)
    marginal = df.groupby(["participant", "b"])["y"].mean().unstack().to_numpy()
    z = marginal - marginal.mean(axis=1, keepdims=True)
    # Orthonormal contrasts of 5 levels, built independently with a QR factorisation.
    q, _ = np.linalg.qr(np.column_stack([np.ones(5), np.eye(5)[:, :4]]))
    scores = z @ q[:, 1:]
    cov = np.cov(scores, rowvar=False)
    w, chi2, dof, p, note = mauchly(cov, marginal.shape[0] - 1, k=5)
    ref = pg.sphericity(
        df.groupby(["participant", "b"], as_index=False)["y"].mean(),
        dv="y",
        within="b",
        subject="participant",
    )
    assert note is None
    assert (w, chi2, dof, p) == pytest.approx((ref.W, ref.chi2, ref.dof, ref.pval), rel=1e-7)


def test_paired_comparisons_match_pingouin_marginal_bonferroni():
    df = _generated(seed=1)
    design = rm_design(df, subject="participant", factor_a="a", factor_b="b", dv="y")
    ours = paired_comparisons(design.data.mean(axis=2), list(design.levels_a))
    ref = pg.pairwise_tests(df, dv="y", within=["a", "b"], subject="participant", padjust="bonf")
    ref = ref[ref["Contrast"] == "a"]
    assert len(ours) == len(ref) == 3
    for t, (_, r) in zip(ours, ref.iterrows(), strict=True):
        assert (t.a, t.b) == (r["A"], r["B"])
        assert t.t == pytest.approx(r["T"], rel=1e-9)
        assert t.p == pytest.approx(r["p_unc"], rel=1e-7)
        assert t.p_bonf == pytest.approx(r["p_corr"], rel=1e-7)


def test_one_sample_t_matches_scipy():
    v = np.array([0.4, -0.2, 1.3, 0.8, 0.1, 2.2])
    res = one_sample_t(v)
    ref = sps.ttest_1samp(v, 0.0)
    assert res.t == pytest.approx(ref.statistic)
    assert res.p == pytest.approx(ref.pvalue)
    assert res.df == 5 and res.n == 6


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    shift=st.floats(-50, 50),
    scale=st.floats(0.1, 10),
)
def test_f_is_invariant_to_participant_offsets_and_units(seed, shift, scale):
    rng = np.random.default_rng(seed)
    y = rng.normal(size=(6, 3, 4)) + np.arange(4)[None, None, :]
    base = rm_anova(y)
    moved = rm_anova(scale * (y + rng.normal(0, 5, size=(6, 1, 1))) + shift)
    for e0, e1 in zip(base, moved, strict=True):
        assert pytest.approx(e0.F, rel=1e-6) == e1.F
        assert e1.eps_gg == pytest.approx(e0.eps_gg, rel=1e-6)
        assert 1 / e0.df1 - 1e-12 <= e0.eps_gg <= 1.0


def test_one_factor_with_one_level_gives_a_one_way_anova():
    rng = np.random.default_rng(2)
    y = rng.normal(size=(8, 1, 4)) + np.arange(4)
    effects = rm_anova(y)
    assert [e.name for e in effects] == ["level"]
    # The textbook one-way repeated-measures sums of squares.
    m = y[:, 0, :]
    n, k = m.shape
    ss_cond = n * ((m.mean(axis=0) - m.mean()) ** 2).sum()
    ss_subj = k * ((m.mean(axis=1) - m.mean()) ** 2).sum()
    ss_err = ((m - m.mean()) ** 2).sum() - ss_cond - ss_subj
    f = (ss_cond / (k - 1)) / (ss_err / ((k - 1) * (n - 1)))
    assert pytest.approx(f) == effects[0].F


# ------------------------------------------------------------------------------ degenerate


def test_one_participant_is_refused_with_a_message():
    with pytest.raises(AnalysisError, match="at least two participants; got 1"):
        rm_anova(np.ones((1, 3, 5)))


def test_zero_error_variance_is_refused_naming_the_effect():
    # Every participant shows exactly the same pattern (data copied): F is undefined.
    pattern = np.arange(15.0).reshape(3, 5)
    y = np.stack([pattern + k for k in range(4)])
    with pytest.raises(AnalysisError, match="error variance of the frequency effect is zero"):
        rm_anova(y)


def test_a_missing_cell_is_named():
    df = _generated(n=4)
    df = df[~((df["a"] == "F2") & (df["b"] == 20.0))]
    with pytest.raises(AnalysisError, match=r"a=F2, b=20\.0: the design has a missing cell"):
        rm_design(df, subject="participant", factor_a="a", factor_b="b", dv="y")


def test_participants_with_missing_cells_are_dropped_and_listed():
    df = _generated(n=5)
    df = df[~((df["participant"] == "S03") & (df["a"] == "F1") & (df["b"] == 10.0))]
    design = rm_design(df, subject="participant", factor_a="a", factor_b="b", dv="y")
    assert "S03" not in design.subjects and len(design.subjects) == 4
    assert design.dropped == (("S03", "no value for F1@10.0"),)


def test_many_participants_with_gaps_are_each_listed_with_every_missing_cell_in_order():
    df = _generated(n=40)
    gone = {"S07": [("F1", 10.0)], "S22": [("F0", 0.0), ("F2", 20.0)], "S39": [("F2", 0.0)]}
    for subject, cells in gone.items():
        for a, b in cells:
            df = df[~((df["participant"] == subject) & (df["a"] == a) & (df["b"] == b))]
    design = rm_design(df, subject="participant", factor_a="a", factor_b="b", dv="y")
    assert design.dropped == (
        ("S07", "no value for F1@10.0"),
        ("S22", "no value for F0@0.0, F2@20.0"),
        ("S39", "no value for F2@0.0"),
    )
    assert len(design.subjects) == 37 and not set(gone) & set(design.subjects)
    full = df[df["participant"].isin(design.subjects)].sort_values(["participant", "a", "b"])
    assert design.data.ravel().tolist() == full["y"].tolist()


def test_too_few_complete_participants_is_refused():
    df = _generated(n=2)
    df = df[~((df["participant"] == "S01") & (df["a"] == "F0") & (df["b"] == 0.0))]
    with pytest.raises(AnalysisError, match="1 of 2 have them"):
        rm_design(df, subject="participant", factor_a="a", factor_b="b", dv="y")


def test_duplicate_values_for_a_cell_are_refused():
    df = _generated(n=3)
    df = pd.concat([df, df.iloc[[0]]])
    with pytest.raises(AnalysisError, match="has 2 values"):
        rm_design(df, subject="participant", factor_a="a", factor_b="b", dv="y")


def test_non_finite_values_are_refused():
    df = _generated(n=3)
    df.loc[0, "y"] = np.nan
    with pytest.raises(AnalysisError, match="NaN or infinite"):
        rm_design(df, subject="participant", factor_a="a", factor_b="b", dv="y")


def test_mauchly_needs_more_participants_than_df():
    rng = np.random.default_rng(0)
    effects = rm_anova(rng.normal(size=(5, 3, 5)))  # interaction has 8 df, only 5 participants
    inter = effects[2]
    assert inter.mauchly_w is None and inter.mauchly_p is None
    assert "needs more participants" in inter.note
    assert 0 < inter.eps_gg <= 1 and np.isfinite(inter.p_gg)


def test_one_sample_degenerate_cases_have_notes_not_nan():
    single = one_sample_t([2.0])
    assert single.t is None and single.p is None and "one value" in single.note
    flat = one_sample_t([1.5, 1.5, 1.5])
    assert flat.t is None and "zero variance" in flat.note
    with pytest.raises(AnalysisError):
        one_sample_t([1.0, np.nan])


# R's `sleep` data set; R 4.x prints for t.test(extra ~ group, data = sleep, paired = TRUE):
# t = -4.0621, df = 9, p-value = 0.002833, mean difference -1.58.
SLEEP_1 = [0.7, -1.6, -0.2, -1.2, -0.1, 3.4, 3.7, 0.8, 0.0, 2.0]
SLEEP_2 = [1.9, 0.8, 1.1, 0.1, -0.1, 4.4, 5.5, 1.6, 4.6, 3.4]


def test_paired_t_matches_r_on_the_sleep_data():
    r = paired_t(SLEEP_1, SLEEP_2)
    assert r.t == pytest.approx(-4.0621, abs=5e-5)
    assert r.p == pytest.approx(0.002833, abs=5e-7)
    assert (r.df, r.n) == (9, 10) and r.mean == pytest.approx(-1.58)
    flipped = paired_t(SLEEP_2, SLEEP_1)
    assert flipped.t == pytest.approx(-r.t) and flipped.p == pytest.approx(r.p)


def test_paired_t_degenerate_cases_have_notes_and_bad_input_raises():
    single = paired_t([0.5], [0.25])
    assert single.t is None and single.p is None and "one value" in single.note
    same = paired_t([0.5, 0.75, 1.0], [0.25, 0.5, 0.75])
    assert same.t is None and same.p is None and "zero variance" in same.note
    with pytest.raises(AnalysisError, match="3 values against 2"):
        paired_t([1.0, 2.0, 3.0], [1.0, 2.0])
    with pytest.raises(AnalysisError, match="NaN"):
        paired_t([1.0, np.nan], [1.0, 2.0])


def test_paired_comparison_of_identical_levels_has_a_note():
    m = np.column_stack([np.arange(5.0), np.arange(5.0), np.arange(5.0) + 1])
    tests = paired_comparisons(m, ["A", "B", "C"])
    ab = tests[0]
    assert ab.t is None and ab.p_bonf is None and ab.mean_diff == 0.0
    assert "zero variance" in ab.note
    with pytest.raises(AnalysisError, match="two participants"):
        paired_comparisons(m[:1], ["A", "B", "C"])
