"""``masking_params.json``: the exported masking functions (schema ``data_schema/
masking_params.schema.json``).

Other tools read it with :func:`load_masking_params`, which validates the file and returns one
:class:`MaskingParamsEntry` per ``(target, masker)`` stimulus pair. Writing is deterministic
(fixed key order, floats rounded to 9 significant digits, ``\\n`` line ends) and atomic
(temp file, fsync, rename).
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from masking_lab.core.errors import AnalysisError, ProtocolError
from masking_lab.core.masking import MaskingFunction
from masking_lab.formats.fileio import write_text_atomic
from masking_lab.formats.reader import load_document, parse_document
from masking_lab.formats.schemas import (
    first_problem,
)

SCHEMA = "masking_params"

#: Bounds of a stored joint draw (the schema's): intercept in dB, slope in dB/dB SL.
DRAW_INTERCEPT_LIMIT_DB = 500.0
DRAW_SLOPE_LIMIT = 100.0
#: Most joint draws one function stores, and the decimals they keep (the file stays small).
MAX_STORED_DRAWS = 200
DRAW_DECIMALS = 4


class MaskingParamsError(ProtocolError):
    """A masking_params.json file is unreadable or does not follow its schema."""


@dataclass(frozen=True)
class MaskingParamsEntry:
    """One exported masking function (fields as in the schema).

    Attributes
    ----------
    target, masker : str
        Stimulus names: the masked stimulus and the masker.
    status : {"fitted", "no_masking", "insufficient_data"}
        Only ``"fitted"`` and ``"no_masking"`` carry a usable ramp.
    intercept_db : float or None
        Ramp intercept a, dB.
    slope : float or None
        Ramp slope b, dB of shift per dB SL of masker.
    intercept_se_db, slope_se : float or None
        Standard errors.
    intercept_ci_db, slope_ci : tuple or None
        Confidence intervals.
    fitted_range_db_sl : tuple[float, float]
        Masker levels fitted, dB SL; outside it the ramp is an extrapolation.
    knee_db_sl : float or None
        −a/b, dB SL.
    adj_r2 : float or None
        Adjusted R² of the fit.
    n_points : int
        Points fitted (cell means).
    masker_frequencies_hz : tuple[float, ...]
        MV carrier frequencies of the pooled pairs.
    pooled_pairs : tuple[str, ...]
        ``"target|masker"`` of every pair sharing these parameters.
    message : str or None
        Caveat or reason for the status.
    extra : dict
        Optional keys (experiment, uncertainty, ci_level, n_participants,
        intercept_slope_cov, draws).
    """

    target: str
    masker: str
    status: str
    intercept_db: float | None
    slope: float | None
    intercept_se_db: float | None
    slope_se: float | None
    intercept_ci_db: tuple[float, float] | None
    slope_ci: tuple[float, float] | None
    fitted_range_db_sl: tuple[float, float]
    knee_db_sl: float | None
    adj_r2: float | None
    n_points: int
    masker_frequencies_hz: tuple[float, ...]
    pooled_pairs: tuple[str, ...]
    message: str | None
    extra: dict[str, Any]

    @property
    def usable(self) -> bool:
        """True if the entry carries a ramp (fitted, or no masking over the fitted range)."""
        return self.status in ("fitted", "no_masking")

    def masking_function(self) -> MaskingFunction:
        """The ramp as a :class:`~masking_lab.core.masking.MaskingFunction`.

        Raises
        ------
        AnalysisError
            If the entry has no parameters (``insufficient_data``).
        """
        if not self.usable or self.intercept_db is None or self.slope is None:
            raise AnalysisError(
                f"{self.target} masked by {self.masker} has no fitted ramp (status "
                f"{self.status}: {self.message}); measure more masker levels and fit again"
            )
        return MaskingFunction(self.target, self.masker, self.intercept_db, self.slope)


def validate_masking_params(
    doc: Any, source: str = "masking_params.json", lines: Mapping[str, int] | None = None
) -> None:
    """Check a parsed document against the schema and the one-entry-per-pair rule.

    Raises
    ------
    MaskingParamsError
        Naming the key path of the first problem.
    """
    problem = first_problem(doc, SCHEMA, lines)
    if problem:
        at, what = problem
        raise MaskingParamsError(
            source,
            at,
            f"{what}; regenerate the file with `masking-lab analyze` or `masking-lab fit`",
        )
    seen: dict[tuple[str, str], int] = {}
    for i, f in enumerate(doc["functions"]):
        key = (f["target"], f["masker"])
        if key in seen:
            raise MaskingParamsError(
                source,
                f"functions[{i}]",
                f"{key[0]} masked by {key[1]} appears twice (also functions[{seen[key]}]); "
                "keep one entry per (target, masker) pair",
            )
        seen[key] = i
        draws = f.get("draws")
        if draws is not None and len(draws["intercept_db"]) != len(draws["slope"]):
            raise MaskingParamsError(
                source,
                f"functions[{i}].draws",
                f"{len(draws['intercept_db'])} intercepts but {len(draws['slope'])} slopes; "
                "the draws are joint pairs: give as many of each",
            )
        pair = f"{key[0]}|{key[1]}"
        if pair not in f["pooled_pairs"]:
            raise MaskingParamsError(
                source, f"functions[{i}].pooled_pairs", f"must list the entry's own pair {pair}"
            )


# A draws array (the only arrays under these keys) on one line, not one number per line.
_DRAW_ARRAY = re.compile(r'("(?:intercept_db|slope)": )\[([^\]\[]*)\]')


def masking_params_json(doc: dict[str, Any]) -> str:
    """Deterministic JSON text of a document (validated first)."""
    validate_masking_params(doc, "<document to write>")
    text = json.dumps(_rounded(doc), indent=2, ensure_ascii=False, allow_nan=False)
    text = _DRAW_ARRAY.sub(
        lambda m: m.group(1) + "[" + ", ".join(v.strip() for v in m.group(2).split(",")) + "]",
        text,
    )
    return text + "\n"


def write_masking_params(path: str | Path, doc: dict[str, Any]) -> Path:
    """Validate and write ``doc`` atomically (temp file, fsync, rename)."""
    return write_text_atomic(path, masking_params_json(doc))


def read_masking_params(path: str | Path) -> dict[str, Any]:
    """Read and validate a masking_params.json file.

    Raises
    ------
    MaskingParamsError
        If the file cannot be read, is not JSON, or breaks the schema.
    """
    doc = load_document(path, what="file", fmt="json", error=MaskingParamsError)
    validate_masking_params(doc.data, doc.source, doc.lines)
    return doc.data


def parse_masking_params(text: str, source: str) -> dict[str, Any]:
    """A masking_params document from its JSON text, checked as :func:`read_masking_params`
    checks the file (``source`` names it in messages).

    Raises
    ------
    MaskingParamsError
        If the text is not JSON or breaks the schema.

    Examples
    --------
    >>> try:
    ...     parse_masking_params("{", "params.json")
    ... except MaskingParamsError as exc:
    ...     print(str(exc).split(" (")[0])
    params.json: line 1: not valid JSON
    """
    doc = parse_document(text.encode("utf-8"), source, fmt="json", error=MaskingParamsError)
    validate_masking_params(doc.data, doc.source, doc.lines)
    data: dict[str, Any] = doc.data
    return data


def load_masking_params(path: str | Path) -> dict[tuple[str, str], MaskingParamsEntry]:
    """Entries of a masking_params.json keyed by ``(target, masker)``.

    Raises
    ------
    MaskingParamsError
        If the file is unreadable or invalid (see :func:`read_masking_params`).
    """
    doc = read_masking_params(path)
    out: dict[tuple[str, str], MaskingParamsEntry] = {}
    required = {
        "target",
        "masker",
        "status",
        "intercept_db",
        "slope",
        "intercept_se_db",
        "slope_se",
        "intercept_ci_db",
        "slope_ci",
        "fitted_range_db_sl",
        "knee_db_sl",
        "adj_r2",
        "n_points",
        "masker_frequencies_hz",
        "pooled_pairs",
        "message",
    }
    for f in doc["functions"]:
        entry = MaskingParamsEntry(
            target=f["target"],
            masker=f["masker"],
            status=f["status"],
            intercept_db=f["intercept_db"],
            slope=f["slope"],
            intercept_se_db=f["intercept_se_db"],
            slope_se=f["slope_se"],
            intercept_ci_db=_pair(f["intercept_ci_db"]),
            slope_ci=_pair(f["slope_ci"]),
            # the schema (checked above) requires this pair: _pair never returns None for it
            fitted_range_db_sl=_pair(f["fitted_range_db_sl"]),  # type: ignore[arg-type]
            knee_db_sl=f["knee_db_sl"],
            adj_r2=f["adj_r2"],
            n_points=int(f["n_points"]),
            masker_frequencies_hz=tuple(float(v) for v in f["masker_frequencies_hz"]),
            pooled_pairs=tuple(f["pooled_pairs"]),
            message=f["message"],
            extra={k: v for k, v in f.items() if k not in required},
        )
        out[(entry.target, entry.masker)] = entry
    return out


def determination_warnings(
    doc: Mapping[str, Any],
    source: str = "masking_params.json",
    pair: tuple[str, str] | None = None,
) -> list[str]:
    """One warning per poorly determined function of a ``masking_params.json`` document.

    With ``pair`` (two stimulus names, e.g. ``("MV120", "EV270")``), only the two functions
    of that pair (each masking the other) are checked.

    A function is poorly determined when the file marks it so (``poorly_determined``), or, in
    a file written before that field existed, when its fitted slope's interval includes 0.

    Examples
    --------
    >>> doc = {"functions": [{"target": "EV270", "masker": "MV120", "status": "fitted",
    ...     "slope_ci": [-0.34, 1.36]}]}
    >>> determination_warnings(doc, "p.json")[0][:60]
    'p.json: EV270 masked by MV120 is poorly determined (slope in'
    """
    out = []
    for f in doc.get("functions", []):
        if pair is not None and {f.get("target"), f.get("masker")} != set(pair):
            continue
        why = f.get("determination")
        poor = f.get("poorly_determined")
        if poor is None and f.get("status") == "fitted" and f.get("slope_ci"):
            lo, hi = f["slope_ci"]
            poor = lo <= 0.0 <= hi
            why = f"slope interval [{lo:.2f}, {hi:.2f}] includes 0"
        if poor:
            out.append(
                f"{source}: {f['target']} masked by {f['masker']} is poorly determined ({why}); "
                "levels compensated with it are uncertain: measure the pair again with more "
                "participants or masker levels"
            )
    return out


def draws_field(
    method: str, seed: int | None, n_replicates: int, draws: Any
) -> dict[str, Any] | None:
    """The optional ``draws`` entry of an exported function: joint (intercept, slope) draws.

    Keeps the first :data:`MAX_STORED_DRAWS` finite draws within the schema's bounds
    (intercept ±500 dB, slope 0–100 dB/dB SL), rounded to 4 decimals so that the file is small
    and byte-stable for a seed; None when none is left.

    Parameters
    ----------
    method : {"bootstrap", "posterior"}
        Where the draws come from.
    seed : int or None
        Seed of the generator that made them (reproducibility).
    n_replicates : int
        Replicates the fit's standard errors and intervals were computed from.
    draws : iterable of (float, float)
        (intercept dB, slope dB/dB SL) pairs.

    Examples
    --------
    >>> f = draws_field("bootstrap", 0, 3, [(-4.123456, 0.81), (float("nan"), 0.8), (-3.9, 0.79)])
    >>> f["intercept_db"], f["slope"], f["seed"]
    ([-4.1235, -3.9], [0.81, 0.79], 0)
    """
    kept = [
        (round(float(a), DRAW_DECIMALS) + 0.0, round(float(b), DRAW_DECIMALS) + 0.0)
        for a, b in draws
        if math.isfinite(a)
        and math.isfinite(b)
        and abs(a) <= DRAW_INTERCEPT_LIMIT_DB
        and 0.0 <= b <= DRAW_SLOPE_LIMIT
    ][:MAX_STORED_DRAWS]
    if len(kept) < 2:
        return None
    return {
        "method": method,
        "seed": seed,
        "n_replicates": int(n_replicates),
        "intercept_db": [a for a, _ in kept],
        "slope": [b for _, b in kept],
    }


def _pair(v: Any) -> tuple[float, float] | None:
    return None if v is None else (float(v[0]), float(v[1]))


def _rounded(obj: Any) -> Any:
    """Floats to 9 significant digits: stable bytes across platforms' last-bit differences."""
    if isinstance(obj, float):
        if not math.isfinite(obj):
            raise AnalysisError(f"refusing to export the non-finite number {obj!r}")
        r = float(f"{obj:.9g}")
        return 0.0 if r == 0 else r
    if isinstance(obj, dict):
        return {k: _rounded(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_rounded(v) for v in obj]
    return obj
