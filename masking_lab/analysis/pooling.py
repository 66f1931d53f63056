"""Which frequency levels share one masking function (paper §2.4: "data points that did not
differ significantly from each other were fitted into a single line").

The levels are those of the ANOVA's frequency factor: the MV stimulus of each pair (masker in
Experiment I, target in Experiment II), named like ``"MV120"``. Rules:

``paired`` (default)
    Pool levels whose Bonferroni-corrected paired comparison is not significant
    (``p_bonf ≥ alpha``). Groups only ever contain levels that are *all* mutually
    non-significant: pairs are merged most-similar first (largest p first), and two groups merge
    only if no pair across them differs. So 120 ≈ 180 and 180 ≈ 270 with 120 ≠ 270 never pools
    all three.
``none``
    Every level alone.
``all``
    Every level in one group.
explicit
    Groups given by the analyst (:func:`parse_pool_spec`); levels not named stay alone.

Everything here is pure; the decision carries the reasons, which the report prints.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

from masking_lab.core.errors import AnalysisError
from masking_lab.core.stimulus import is_stimulus_name, parse_stimulus

if TYPE_CHECKING:  # the figure worker imports this module for level_sort_key alone
    from masking_lab.analysis.t_tests import PairedTest

PoolingRule = Literal["paired", "none", "all", "explicit"]
RULES: tuple[str, ...] = ("paired", "none", "all")


@dataclass(frozen=True)
class PoolingDecision:
    """How the levels of one experiment's frequency factor are grouped.

    Attributes
    ----------
    groups : tuple[tuple[str, ...], ...]
        Groups of level names; each level appears in exactly one group. Sorted.
    rule : str
        ``"paired"``, ``"none"``, ``"all"`` or ``"explicit"``.
    alpha : float or None
        Significance level of the ``paired`` rule.
    reasons : tuple[str, ...]
        One human-readable line per decision taken.
    model_comparison : tuple[str, ...]
        Pooled-against-separate ramp comparisons by likelihood ratio, AIC and BIC
        (:mod:`masking_lab.analysis.pooling_lr`), reported beside the decision, not used by it.
    """

    groups: tuple[tuple[str, ...], ...]
    rule: str
    alpha: float | None
    reasons: tuple[str, ...]
    model_comparison: tuple[str, ...] = ()

    def group_of(self, level: str) -> tuple[str, ...]:
        """The group containing ``level``."""
        for g in self.groups:
            if level in g:
                return g
        raise KeyError(level)


def level_sort_key(level: str) -> tuple:
    """Sort MV stimulus names by carrier frequency, then envelope, then name."""
    if is_stimulus_name(level):
        s = parse_stimulus(level)
        return (0, s.carrier_hz, s.envelope_hz or 0.0, level)
    return (1, 0.0, 0.0, level)


def _sorted_groups(groups: list[list[str]]) -> tuple[tuple[str, ...], ...]:
    out = [tuple(sorted(g, key=level_sort_key)) for g in groups]
    return tuple(sorted(out, key=lambda g: level_sort_key(g[0])))


def no_pooling(levels: Sequence[str]) -> PoolingDecision:
    """Every level fitted on its own."""
    return PoolingDecision(_sorted_groups([[lv] for lv in levels]), "none", None, ())


def pool_all(levels: Sequence[str]) -> PoolingDecision:
    """All levels fitted together."""
    return PoolingDecision(_sorted_groups([list(levels)]), "all", None, ())


def pool_by_paired_tests(
    levels: Sequence[str], tests: Sequence[PairedTest], alpha: float = 0.05
) -> PoolingDecision:
    """Pool levels that the Bonferroni-corrected paired comparisons do not separate.

    Parameters
    ----------
    levels : sequence of str
        The frequency-factor levels.
    tests : sequence of PairedTest
        Paired comparisons between those levels (from
        :func:`masking_lab.analysis.t_tests.paired_comparisons`).
    alpha : float
        A pair with ``p_bonf ≥ alpha`` counts as "not different". A pair whose differences have
        zero variance counts as not different only if its mean difference is 0.

    Raises
    ------
    AnalysisError
        If ``alpha`` is not in (0, 1) or a pair of levels has no test.
    """
    if not 0.0 < alpha < 1.0:
        raise AnalysisError(f"the pooling alpha must lie between 0 and 1, got {alpha}")
    same: dict[frozenset[str], float] = {}
    reasons = []
    by_pair = {frozenset((str(t.a), str(t.b))): t for t in tests}
    for i, a in enumerate(levels):
        for b in levels[i + 1 :]:
            t = by_pair.get(frozenset((a, b)))
            if t is None:
                raise AnalysisError(f"no paired comparison between {a} and {b}; cannot pool")
            if t.p_bonf is None:
                alike = abs(t.mean_diff) <= 1e-12
                p_eff = 1.0 if alike else 0.0
                why = "identical" if alike else "constant non-zero difference"
                reasons.append(f"{a} vs {b}: zero-variance differences ({why})")
            else:
                p_eff = t.p_bonf
                verdict = "not different" if p_eff >= alpha else "different"
                p_txt = "p < 0.001" if p_eff < 0.001 else f"p = {p_eff:.3f}"
                reasons.append(f"{a} vs {b}: Bonferroni {p_txt} → {verdict}")
            if p_eff >= alpha:
                same[frozenset((a, b))] = p_eff
    group_of = {lv: frozenset([lv]) for lv in levels}
    order = {lv: i for i, lv in enumerate(levels)}
    candidates = sorted(same.items(), key=lambda kv: (-kv[1], sorted(order[x] for x in kv[0])))
    for pair, _p in candidates:
        a, b = sorted(pair, key=order.__getitem__)
        ga, gb = group_of[a], group_of[b]
        if ga == gb:
            continue
        if all(frozenset((x, y)) in same for x in ga for y in gb):
            merged = ga | gb
            for lv in merged:
                group_of[lv] = merged
        else:
            reasons.append(
                f"{a} and {b} not pooled: some level of one group differs from the other group"
            )
    groups = _sorted_groups([list(g) for g in set(group_of.values())])
    return PoolingDecision(groups, "paired", alpha, tuple(reasons))


def explicit_pooling(levels: Sequence[str], groups: Sequence[Sequence[str]]) -> PoolingDecision:
    """Groups given by the analyst; levels not named stay alone.

    Raises
    ------
    AnalysisError
        If a group names a level the experiment does not have, or a level is in two groups.
    """
    known = set(levels)
    seen: dict[str, int] = {}
    for gi, g in enumerate(groups):
        for lv in g:
            if lv not in known:
                raise AnalysisError(
                    f"pooling group {'+'.join(g)} names {lv}, which is not a frequency level of "
                    f"this experiment (levels: {', '.join(sorted(known, key=level_sort_key))})"
                )
            if lv in seen and seen[lv] != gi:
                raise AnalysisError(f"{lv} is in two pooling groups; put each level in one group")
            seen[lv] = gi
    out = [list(dict.fromkeys(g)) for g in groups]
    out += [[lv] for lv in levels if lv not in seen]
    reasons = tuple(f"pooled as given: {'+'.join(g)}" for g in groups if len(g) > 1)
    return PoolingDecision(_sorted_groups(out), "explicit", None, reasons)


def parse_pool_spec(specs: Sequence[str]) -> dict[str | None, list[list[str]]]:
    """Parse ``--pool`` values: ``[EXPERIMENT:]LEVEL+LEVEL[+...]``.

    A LEVEL is an MV stimulus name (``MV120``) or a bare frequency in Hz (``120``, meaning
    ``MV120``). Without ``EXPERIMENT:`` a group applies to every experiment having its levels.

    Returns
    -------
    dict
        Experiment id (or None for "every experiment") → list of groups.

    Raises
    ------
    AnalysisError
        For an empty group, a group of one, or a level that is neither a stimulus nor a number.
    """
    out: dict[str | None, list[list[str]]] = {}
    for spec in specs:
        text = spec.strip()
        exp: str | None = None
        if ":" in text:
            exp, text = (part.strip() for part in text.rsplit(":", 1))
            exp = exp or None
        names = [p.strip() for p in text.split("+") if p.strip()]
        if len(names) < 2:
            raise AnalysisError(
                f"--pool {spec!r}: give two or more levels joined by '+', e.g. "
                "'experiment1:MV120+MV180' or '120+180'"
            )
        group = []
        for name in names:
            if is_stimulus_name(name):
                group.append(parse_stimulus(name).name)
                continue
            try:
                hz = float(name)
            except ValueError:
                raise AnalysisError(
                    f"--pool {spec!r}: {name!r} is neither a stimulus name (MV120) nor a "
                    "frequency in Hz (120)"
                ) from None
            group.append(parse_stimulus(f"MV{hz:g}").name)
        out.setdefault(exp, []).append(group)
    return out


def decide_pooling(
    experiment: str,
    levels: Sequence[str],
    *,
    rule: str,
    alpha: float,
    tests: Sequence[PairedTest] | None,
    explicit: Mapping[str | None, list[list[str]]] | None = None,
) -> PoolingDecision:
    """The pooling of one experiment under the settings.

    Explicit groups for ``experiment`` (or for every experiment, when their levels all exist
    here) win over ``rule``. The ``paired`` rule without tests (no per-participant data) falls
    back to no pooling and says so.
    """
    explicit = explicit or {}
    groups = list(explicit.get(experiment, []))
    groups += [g for g in explicit.get(None, []) if set(g) <= set(levels)]
    if groups:
        return explicit_pooling(levels, groups)
    if len(levels) < 2 or rule == "none":
        return no_pooling(levels)
    if rule == "all":
        return pool_all(levels)
    if rule != "paired":
        raise AnalysisError(f"unknown pooling rule {rule!r}; use one of {', '.join(RULES)}")
    if tests is None:
        d = no_pooling(levels)
        return PoolingDecision(
            d.groups,
            "none",
            None,
            (
                "the 'paired' rule needs paired comparisons, which were not run; every "
                "frequency is fitted alone (give --pool to pool explicitly)",
            ),
        )
    return pool_by_paired_tests(levels, tests, alpha)
