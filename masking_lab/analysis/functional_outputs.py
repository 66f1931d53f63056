"""What ``analyze`` writes for functional-procedure sets (*shell*: reads logs, writes files).

``ramp_posteriors.csv``: one row per participant and (target, masker): the ramp's posterior
means, SDs, 95 % credible intervals and correlation (:mod:`masking_lab.analysis.functional`).
``group_ramps.csv``: per (target, masker), the partial-pooling (random-effects) estimate and
the paper's route on the same data. ``masking_params.json`` gains one function per pair that
only the functional procedure measured (its random-effects estimate), each entry naming its
``procedure`` and ``estimate``; a pair also measured by the paper's route keeps that fit.
Intercepts in dB, slopes in dB/dB, levels in dB SL.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from masking_lab import __version__
from masking_lab.analysis.functional import GroupRamp, group_ramps, ramp_posteriors_from_logs
from masking_lab.core.stimulus import parse_stimulus
from masking_lab.formats.csv_table import csv_text_rows
from masking_lab.formats.fileio import write_text_atomic
from masking_lab.formats.masking_params import write_masking_params

__all__ = ["GROUP_COLUMNS", "POSTERIOR_COLUMNS", "write_functional_outputs"]

POSTERIOR_COLUMNS = [
    "participant", "target", "masker", "intercept_db", "intercept_sd_db", "intercept_ci_low_db",
    "intercept_ci_high_db", "slope", "slope_sd", "slope_ci_low", "slope_ci_high", "rho",
    "n_trials", "status", "procedure", "estimate",
]  # fmt: skip
GROUP_COLUMNS = [
    "target", "masker", "estimate", "procedure", "intercept_db", "intercept_se_db",
    "intercept_ci_low_db", "intercept_ci_high_db", "slope", "slope_se", "slope_ci_low",
    "slope_ci_high", "tau_intercept_db", "tau_slope", "n_participants", "status", "message",
]  # fmt: skip


def _num(v: float | None) -> float | None:
    """Non-finite numbers never reach an output: they are written empty."""
    return float(v) if v is not None and math.isfinite(v) else None


def _interval(ci: tuple[float, float]) -> list[float] | None:
    return [float(v) for v in ci] if all(math.isfinite(v) for v in ci) else None


def _function_entry(g: GroupRamp, levels: Sequence[float]) -> dict[str, Any]:
    knee = -g.intercept_db / g.slope if g.slope > 0 else None
    masker = parse_stimulus(g.masker)
    return {
        "target": g.target,
        "masker": g.masker,
        "masker_frequencies_hz": [float(masker.carrier_hz)],
        "intercept_db": _num(g.intercept_db),
        "slope": _num(g.slope),
        "intercept_se_db": _num(g.intercept_se_db),
        "slope_se": _num(g.slope_se),
        "intercept_ci_db": _interval(g.intercept_ci_db),
        "slope_ci": _interval(g.slope_ci),
        "fitted_range_db_sl": [float(min(levels)), float(max(levels))],
        "knee_db_sl": _num(knee),
        "adj_r2": None,
        "n_points": g.n_participants,
        "pooled_pairs": [f"{g.target}|{g.masker}"],
        "status": "fitted",
        "message": None,
        "uncertainty": "asymptotic",
        "ci_level": 0.95,
        "n_participants": g.n_participants,
        "procedure": g.procedure,
        "estimate": g.estimate,
        **(
            {"intercept_slope_cov": _num(g.intercept_slope_cov)}
            if _num(g.intercept_slope_cov) is not None
            else {}
        ),
    }


def write_functional_outputs(
    out: Path,
    log_paths: Sequence[Path],
    *,
    inputs: Sequence[dict[str, str]],
    settings: dict[str, Any],
    created_utc: str,
) -> tuple[list[Path], list[str]]:
    """Write the functional sets' outputs into ``out``; return the files and problems.

    Nothing is written when no log holds a finished functional set.
    """
    from masking_lab.formats.session_log import read_log

    posteriors, problems = ramp_posteriors_from_logs(read_log(p) for p in log_paths)
    if not posteriors:
        return [], problems
    rows = [
        [
            p.participant, p.target, p.masker, _num(p.intercept_db), _num(p.intercept_sd_db),
            _num(p.intercept_ci_db[0]), _num(p.intercept_ci_db[1]), _num(p.slope),
            _num(p.slope_sd), _num(p.slope_ci[0]), _num(p.slope_ci[1]), _num(p.rho),
            p.n_trials, p.status, "functional_ramp", "posterior",
        ]
        for p in sorted(posteriors, key=lambda p: (p.target, p.masker, p.participant))
    ]  # fmt: skip
    groups = group_ramps(posteriors)
    group_rows = [
        [
            g.target, g.masker, g.estimate, g.procedure, _num(g.intercept_db),
            _num(g.intercept_se_db), _num(g.intercept_ci_db[0]), _num(g.intercept_ci_db[1]),
            _num(g.slope), _num(g.slope_se), _num(g.slope_ci[0]), _num(g.slope_ci[1]),
            _num(g.tau_intercept_db), _num(g.tau_slope), g.n_participants, g.status, g.message,
        ]
        for g in groups
    ]  # fmt: skip
    files = [
        write_text_atomic(out / "ramp_posteriors.csv", csv_text_rows(POSTERIOR_COLUMNS, rows)),
        write_text_atomic(out / "group_ramps.csv", csv_text_rows(GROUP_COLUMNS, group_rows)),
    ]
    files.append(_add_to_masking_params(out, posteriors, groups, inputs, settings, created_utc))
    return files, problems


def _add_to_masking_params(
    out: Path,
    posteriors: Sequence[Any],
    groups: Sequence[GroupRamp],
    inputs: Sequence[dict[str, str]],
    settings: dict[str, Any],
    created_utc: str,
) -> Path:
    path = out / "masking_params.json"
    if path.is_file():
        doc = json.loads(path.read_text(encoding="utf-8"))
    else:
        doc = {
            "schema_version": 1,
            "software_version": __version__,
            "created_utc": created_utc,
            "provenance": {
                "source": "analyze",
                "inputs": [dict(i) for i in inputs],
                "settings": settings,
            },
            "functions": [],
        }
    have = {(f["target"], f["masker"]) for f in doc["functions"]}
    for f in doc["functions"]:
        f.setdefault("estimate", "paper_route")
    for g in groups:
        if g.estimate != "random_effects" or (g.target, g.masker) in have:
            continue
        levels = [
            v for p in posteriors if (p.target, p.masker) == (g.target, g.masker)
            for v in p.masker_levels_db_sl
        ]  # fmt: skip
        if g.slope > 0 and math.isfinite(g.intercept_db):
            doc["functions"].append(_function_entry(g, levels))
    doc["functions"].sort(key=lambda f: (f["target"], f["masker"]))
    return write_masking_params(path, doc)
