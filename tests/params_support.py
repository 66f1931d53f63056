"""Build masking_params.json entries for tests (the export's schema, minimal uncertainty)."""

from __future__ import annotations

from typing import Any


def masking_entry(
    target: str, masker: str, a: float, b: float, status: str = "fitted"
) -> dict[str, Any]:
    """One ``functions`` entry: ``target`` masked by ``masker`` with ramp intercept ``a`` dB and
    slope ``b``; ``masker_frequencies_hz`` is the MV stimulus's carrier, as the export writes."""
    mv = target if target.startswith("MV") else masker
    return {
        "target": target,
        "masker": masker,
        "masker_frequencies_hz": [float(mv[2:5])],
        "intercept_db": a,
        "slope": b,
        "intercept_se_db": None,
        "slope_se": None,
        "intercept_ci_db": None,
        "slope_ci": None,
        "fitted_range_db_sl": [5.0, 25.0],
        "knee_db_sl": None,
        "adj_r2": None,
        "n_points": 5,
        "pooled_pairs": [f"{target}|{masker}"],
        "status": status,
        "message": None,
    }
