"""The settings of an analysis (:class:`AnalysisSettings`) and the parsing of their options.

Every setting is checked when the object is made and recorded in the export's provenance.
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass
from typing import Any

from masking_lab.analysis.pooling import RULES, parse_pool_spec
from masking_lab.core.errors import AnalysisError
from masking_lab.procedures.estimators import ESTIMATORS

# Here, not in thresholds.py: checking settings must not import pandas (the demo checks them
# before its sessions start, and that import is seconds on a busy machine).
UNMASKED_SOURCES = ("auto", "baseline", "calibration")

__all__ = [
    "EPOCH_UTC",
    "FIGURES",
    "UNCERTAINTY",
    "AnalysisSettings",
    "is_utc_stamp",
    "parse_lapse",
]

UNCERTAINTY = ("bootstrap", "asymptotic")
FIGURES = ("all", "summary", "none")
EPOCH_UTC = "1970-01-01T00:00:00Z"
_UTC_RE = re.compile(r"^\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}Z$")


def is_utc_stamp(text: str) -> bool:
    """Whether ``text`` is a UTC time stamp to the second, as written in logs and exports.

    Parameters
    ----------
    text : str
        Candidate, e.g. ``"2024-05-01T12:00:00Z"``.

    Returns
    -------
    bool
        True for ``YYYY-MM-DDTHH:MM:SSZ``.

    Examples
    --------
    >>> is_utc_stamp("2024-05-01T12:00:00Z"), is_utc_stamp("2024-05-01 12:00")
    (True, False)
    """
    return bool(_UTC_RE.match(text))


def parse_lapse(text: str) -> float | None:
    """The value of a ``--lapse`` option: a rate, or ``fit`` to estimate it.

    Parameters
    ----------
    text : str
        ``"fit"`` or a number such as ``"0.02"`` (a proportion of trials, no unit).

    Returns
    -------
    float or None
        The lapse rate, or None to fit it. The range is checked by :class:`AnalysisSettings`.

    Raises
    ------
    AnalysisError
        If ``text`` is neither ``fit`` nor a number.

    Examples
    --------
    >>> parse_lapse("0.02"), parse_lapse("fit")
    (0.02, None)
    """
    if text == "fit":
        return None
    try:
        return float(text)
    except ValueError:
        raise AnalysisError(f"--lapse {text!r}: give a rate such as 0.02, or 'fit'") from None


@dataclass(frozen=True)
class AnalysisSettings:
    """Every setting of an analysis; all of them are recorded in the export's provenance.

    Attributes
    ----------
    estimator : {"reversals", "ml"}
        AL estimator (``analyze`` only).
    n_reversals_averaged : int or None
        Last reversals averaged (None: as logged, 8 in the paper).
    lapse : float or None
        Lapse rate of the ML estimator (None: fitted).
    unmasked_al : {"auto", "baseline", "calibration"}
        Source of unmasked ALs (see :mod:`masking_lab.analysis.thresholds`).
    pooling : {"paired", "none", "all"}
        Pooling rule (see :mod:`masking_lab.analysis.pooling`).
    pool_alpha : float
        Significance level of the ``paired`` rule (on Bonferroni-corrected p).
    pool_groups : tuple[str, ...]
        Explicit groups, ``[EXPERIMENT:]LEVEL+LEVEL``; they override the rule.
    uncertainty : {"bootstrap", "asymptotic"}
        Ramp uncertainty: participant bootstrap, or asymptotic least-squares SEs.
    n_boot : int
        Bootstrap replicates.
    ci_level : float
        Confidence level of the intervals.
    seed : int
        Bootstrap seed.
    test_alpha : float
        Level at which a one-sample t-test marks a cell as masked.
    created_utc : str or None
        Value for ``created_utc`` in the export (None: derived, see docs).
    figures : {"all", "summary", "none"}
        Figures to draw (default ``summary``: the masking functions; ``all`` adds one
        staircase-track figure per session, slow for big studies).
    pf_boot : int
        Parametric-bootstrap data sets per psychometric function of ``psychometric.csv``
        (0: point estimates and deviance only, no intervals or deviance p).
    trial_tables : bool
        Write ``trials.csv`` (and Parquet) and ``psychometric.csv`` (``analyze`` only; off
        saves a second read of every log and the fits, for very large studies).
    """

    estimator: str = "reversals"
    n_reversals_averaged: int | None = None
    lapse: float | None = 0.02
    unmasked_al: str = "auto"
    pooling: str = "paired"
    pool_alpha: float = 0.05
    pool_groups: tuple[str, ...] = ()
    uncertainty: str = "bootstrap"
    n_boot: int = 2000
    ci_level: float = 0.95
    seed: int = 0
    test_alpha: float = 0.05
    created_utc: str | None = None
    figures: str = "summary"
    pf_boot: int = 200
    trial_tables: bool = True

    def __post_init__(self) -> None:
        checks = [
            (self.estimator in ESTIMATORS, f"estimator must be one of {ESTIMATORS}"),
            (
                self.unmasked_al in UNMASKED_SOURCES,
                f"unmasked_al must be one of {UNMASKED_SOURCES}",
            ),
            (self.pooling in RULES, f"pooling must be one of {RULES}"),
            (self.uncertainty in UNCERTAINTY, f"uncertainty must be one of {UNCERTAINTY}"),
            (self.figures in FIGURES, f"figures must be one of {FIGURES}"),
            (0 < self.pool_alpha < 1, "the pooling alpha must lie in (0, 1)"),
            (0 < self.test_alpha < 1, "the test alpha must lie in (0, 1)"),
            (0 < self.ci_level < 1, "the confidence level must lie in (0, 1)"),
            (self.n_boot >= 100, "use at least 100 bootstrap replicates"),
            (
                self.pf_boot == 0 or self.pf_boot >= 50,
                "psychometric bootstrap: 0 (none) or at least 50 data sets",
            ),
            (
                self.created_utc is None or is_utc_stamp(self.created_utc),
                "created_utc must look like 2024-05-01T12:00:00Z",
            ),
        ]
        for ok, msg in checks:
            if not ok:
                raise AnalysisError(f"analysis settings: {msg}")
        if self.lapse is not None and not 0 <= self.lapse < 2 / 3:
            raise AnalysisError(f"analysis settings: lapse must lie in [0, 2/3), got {self.lapse}")
        parse_pool_spec(self.pool_groups)  # fail early on a malformed --pool

    def as_dict(self, source: str = "analyze") -> dict[str, Any]:
        """Settings that shape the numbers, for provenance (JSON types only).

        ``figures`` is left out (it changes no number); ``fit`` also leaves out the settings
        that only apply to logs.
        """
        d = asdict(self)
        d["pool_groups"] = list(self.pool_groups)
        d.pop("figures")  # drawing figures changes no number
        if source == "fit":
            for key in (
                "estimator",
                "n_reversals_averaged",
                "lapse",
                "unmasked_al",
                "pf_boot",
                "trial_tables",
            ):
                d.pop(key)
        return d
