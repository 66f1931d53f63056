"""Pooling of frequency levels: the paired rule, explicit groups, and their messages."""

from __future__ import annotations

import pytest

from masking_lab.analysis.pooling import (
    decide_pooling,
    explicit_pooling,
    no_pooling,
    parse_pool_spec,
    pool_all,
    pool_by_paired_tests,
)
from masking_lab.analysis.t_tests import PairedTest
from masking_lab.core.errors import AnalysisError

LEVELS = ["MV120", "MV180", "MV270"]


def _test(a, b, p_bonf, mean_diff=1.0):
    return PairedTest(a, b, 10, mean_diff, 2.0, 9, p_bonf, p_bonf, 0.5)


def test_paper_experiment1_pools_120_and_180():
    tests = [
        _test("MV120", "MV180", 1.0),
        _test("MV120", "MV270", 0.001),
        _test("MV180", "MV270", 0.004),
    ]
    d = pool_by_paired_tests(LEVELS, tests, alpha=0.05)
    assert d.groups == (("MV120", "MV180"), ("MV270",))
    assert d.group_of("MV180") == ("MV120", "MV180")
    assert any("p = 1.000 → not different" in r for r in d.reasons)


def test_non_transitive_similarity_never_pools_different_levels():
    # 120 ≈ 180 and 180 ≈ 270, but 120 ≠ 270: only one of the similar pairs may pool.
    tests = [
        _test("MV120", "MV180", 0.40),
        _test("MV180", "MV270", 0.90),
        _test("MV120", "MV270", 0.01),
    ]
    d = pool_by_paired_tests(LEVELS, tests, alpha=0.05)
    assert d.groups == (("MV120",), ("MV180", "MV270"))  # the most similar pair wins
    assert any("not pooled" in r for r in d.reasons)


def test_all_alike_pools_everything_and_all_different_pools_nothing():
    alike = [
        _test(a, b, 1.0)
        for a, b in [(LEVELS[0], LEVELS[1]), (LEVELS[0], LEVELS[2]), (LEVELS[1], LEVELS[2])]
    ]
    assert pool_by_paired_tests(LEVELS, alike).groups == (tuple(LEVELS),)
    differ = [_test(t.a, t.b, 0.001) for t in alike]
    assert pool_by_paired_tests(LEVELS, differ).groups == tuple((lv,) for lv in LEVELS)


def test_alpha_is_a_setting():
    tests = [_test("MV120", "MV180", 0.03)]
    assert pool_by_paired_tests(["MV120", "MV180"], tests, alpha=0.05).groups == (
        ("MV120",),
        ("MV180",),
    )
    assert pool_by_paired_tests(["MV120", "MV180"], tests, alpha=0.01).groups == (
        ("MV120", "MV180"),
    )
    with pytest.raises(AnalysisError, match="alpha"):
        pool_by_paired_tests(["MV120", "MV180"], tests, alpha=1.5)


def test_zero_variance_differences_pool_only_when_identical():
    same = PairedTest("MV120", "MV180", 5, 0.0, None, 4, None, None, None, "zero variance")
    shifted = PairedTest("MV120", "MV180", 5, 2.0, None, 4, None, None, None, "zero variance")
    assert pool_by_paired_tests(["MV120", "MV180"], [same]).groups == (("MV120", "MV180"),)
    assert pool_by_paired_tests(["MV120", "MV180"], [shifted]).groups == (("MV120",), ("MV180",))


def test_missing_comparison_is_an_error():
    with pytest.raises(AnalysisError, match="no paired comparison between MV120 and MV270"):
        pool_by_paired_tests(LEVELS, [_test("MV120", "MV180", 1.0)])


def test_levels_sort_by_frequency_not_alphabetically():
    d = no_pooling(["MV270", "MV80", "MV120am40", "MV120"])
    assert d.groups == (("MV80",), ("MV120",), ("MV120am40",), ("MV270",))
    assert pool_all(["MV270", "MV80"]).groups == (("MV80", "MV270"),)


def test_parse_pool_spec_accepts_names_frequencies_and_experiments():
    spec = parse_pool_spec(["experiment1:MV120+MV180", "180+270", "EV270|MV:120+180"])
    assert spec == {
        "experiment1": [["MV120", "MV180"]],
        None: [["MV180", "MV270"]],
        "EV270|MV": [["MV120", "MV180"]],
    }


@pytest.mark.parametrize(
    ("spec", "match"),
    [("MV120", "two or more levels"), ("exp:MV120+banana", "neither a stimulus name")],
)
def test_parse_pool_spec_errors(spec, match):
    with pytest.raises(AnalysisError, match=match):
        parse_pool_spec([spec])


def test_explicit_groups_are_checked():
    d = explicit_pooling(LEVELS, [["MV180", "MV270"]])
    assert d.groups == (("MV120",), ("MV180", "MV270"))
    assert d.rule == "explicit"
    with pytest.raises(AnalysisError, match="MV90, which is not a frequency level"):
        explicit_pooling(LEVELS, [["MV90", "MV120"]])
    with pytest.raises(AnalysisError, match="in two pooling groups"):
        explicit_pooling(LEVELS, [["MV120", "MV180"], ["MV180", "MV270"]])


def test_decide_pooling_explicit_wins_and_paired_without_tests_falls_back():
    explicit = parse_pool_spec(["exp1:120+270"])
    d = decide_pooling("exp1", LEVELS, rule="paired", alpha=0.05, tests=None, explicit=explicit)
    assert d.rule == "explicit" and d.groups == (("MV120", "MV270"), ("MV180",))
    other = decide_pooling("exp2", LEVELS, rule="paired", alpha=0.05, tests=None, explicit=explicit)
    assert other.rule == "none" and "were not run" in other.reasons[0]
    # Unscoped groups apply only where all their levels exist.
    unscoped = parse_pool_spec(["120+90"])
    d = decide_pooling("exp", LEVELS, rule="none", alpha=0.05, tests=None, explicit=unscoped)
    assert d.groups == (("MV120",), ("MV180",), ("MV270",))
    with pytest.raises(AnalysisError, match="unknown pooling rule"):
        decide_pooling("exp", LEVELS, rule="magic", alpha=0.05, tests=[])
