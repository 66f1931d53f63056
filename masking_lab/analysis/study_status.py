"""The study at a glance (pure): completion matrix, unmasked ALs, outlier flags.

``masking-lab status DATA`` prints it and ``analyze`` puts it in its reports:

* the **participant × protocol matrix**: per participant and protocol (the header's
  ``protocol.experiment``) ``complete`` (every set of the session's ``set_order`` has a
  completed threshold), ``partial`` (sets and trials done so far), ``refused`` (the device
  refused a set: it was logged as aborted with the reason and nothing more was played), or
  ``missing`` (no log of that protocol for that participant);
* the **unmasked ALs** per participant (completed baseline sets, dB re 1 V);
* **outlier flags**, with the rule stated: a value further than :data:`OUTLIER_Z` standard
  deviations from the mean of the *other* participants' values for the same cell
  (leave-one-out z, so the value cannot hide its own deviation), for AL shifts per
  experiment × pair × masker level and for unmasked ALs per stimulus. A median/MAD rule does
  not suit staircase ALs: they fall on the step grid, so half a cell often shares one value
  and the MAD collapses to 0.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    import pandas as pd

__all__ = [
    "OUTLIER_RULE",
    "OUTLIER_Z",
    "CellStatus",
    "Outlier",
    "SessionInfo",
    "outliers",
    "status_matrix",
    "unmasked_als",
]

OUTLIER_Z = 3.5
OUTLIER_RULE = (
    f"|x − mean| > {OUTLIER_Z} × SD, mean and SD of the other participants' values in the same "
    "cell (leave-one-out z; needs at least 4 other participants)"
)
_MIN_OTHERS = 4


@dataclass(frozen=True)
class SessionInfo:
    """What the matrix needs of one session log.

    Attributes
    ----------
    participant, experiment, log : str
        Who, which protocol, and the log (relative path).
    set_order : tuple of str
        The sets the session was to run.
    ended : bool
        The log has its ``session_end`` record.
    """

    participant: str
    experiment: str
    log: str
    set_order: tuple[str, ...]
    ended: bool


def session_of(
    header: Mapping[str, Any], log: str, ended: bool
) -> tuple[SessionInfo, Mapping[str, Any] | None, list[dict[str, Any]]]:
    """A log's session, the participant's ``info`` answers and the protocol's ``info`` field
    specifications, from its header.

    Parameters
    ----------
    header : mapping
        The log's header record (a malformed field reads as absent).
    log : str
        The log, relative to the data folder.
    ended : bool
        The log has its ``session_end`` record.

    Examples
    --------
    >>> h = {"participant": "P1", "protocol": {"experiment": "e1"}, "set_order": ["A", "B"]}
    >>> session_of(h, "P1/a.jsonl", True)
    (SessionInfo(participant='P1', experiment='e1', log='P1/a.jsonl', set_order=('A', 'B'), \
ended=True), None, [])
    """
    raw_protocol, raw_order = header.get("protocol"), header.get("set_order")
    protocol = raw_protocol if isinstance(raw_protocol, Mapping) else {}
    order = raw_order if isinstance(raw_order, list) else []
    session = SessionInfo(
        str(header.get("participant", "?")),
        str(protocol.get("experiment", "?")),
        log,
        tuple(str(s) for s in order),
        ended,
    )
    info = header.get("info")
    raw_content = protocol.get("content")
    content = raw_content if isinstance(raw_content, Mapping) else {}
    specs = [
        dict(spec)
        for spec in content.get("info") or []
        if isinstance(spec, Mapping) and isinstance(spec.get("name"), str)
    ]
    return session, info if isinstance(info, Mapping) else None, specs


@dataclass(frozen=True)
class CellStatus:
    """One participant × protocol cell of the matrix.

    Attributes
    ----------
    participant, experiment : str
        The cell.
    status : {"complete", "partial", "refused", "missing"}
        See the module docstring.
    sets_done, sets_planned : int
        Distinct sets with a completed threshold, and sets in the protocol's order.
    trials : int
        Trials logged in the participant's sessions of that protocol.
    sessions : int
        Logs of that protocol.
    """

    participant: str
    experiment: str
    status: str
    sets_done: int
    sets_planned: int
    trials: int
    sessions: int

    @property
    def text(self) -> str:
        """The cell as the status command prints it, e.g. ``partial 3/15 sets, 212 trials``."""
        if self.status == "missing":
            return "missing"
        if self.status == "complete":
            return f"complete ({self.trials} trials)"
        return f"{self.status} {self.sets_done}/{self.sets_planned} sets, {self.trials} trials"


def status_matrix(sessions: Sequence[SessionInfo], thresholds: pd.DataFrame) -> list[CellStatus]:
    """The participant × protocol matrix, participants then protocols sorted.

    Parameters
    ----------
    sessions : sequence of SessionInfo
        Every analysed session log.
    thresholds : DataFrame
        The thresholds table (columns ``participant, experiment, set_id, status, trials, log,
        note``).

    Returns
    -------
    list of CellStatus
        One per participant × protocol seen anywhere in the study.

    Examples
    --------
    >>> s = [SessionInfo("P1", "e1", "a.jsonl", ("A", "B"), True)]
    >>> import pandas as pd
    >>> t = pd.DataFrame({"participant": ["P1"], "experiment": ["e1"], "set_id": ["A"],
    ...                   "status": ["completed"], "trials": [50], "log": ["a.jsonl"],
    ...                   "note": [None]})
    >>> [c.text for c in status_matrix(s + [SessionInfo("P2", "e1", "b.jsonl", (), False)], t)]
    ['partial 1/2 sets, 50 trials', 'partial 0/0 sets, 0 trials']
    """
    participants = sorted({s.participant for s in sessions})
    experiments = sorted({s.experiment for s in sessions})
    by_cell: dict[tuple[str, str], list[SessionInfo]] = {}
    for s in sessions:
        by_cell.setdefault((s.participant, s.experiment), []).append(s)
    # Each log's (set_id, status, trials) rows, grouped once: a table filter per cell costs
    # cells x rows (minutes at 10,000 sessions).
    by_log: dict[Any, list[tuple[Any, Any, Any]]] = {}
    columns = [thresholds[c].tolist() for c in ("log", "set_id", "status", "trials")]
    for log, sid, status, n in zip(*columns, strict=True):
        by_log.setdefault(log, []).append((sid, status, n))
    out = []
    for p in participants:
        for e in experiments:
            logs = by_cell.get((p, e), [])
            if not logs:
                out.append(CellStatus(p, e, "missing", 0, 0, 0, 0))
                continue
            rows = [r for log in dict.fromkeys(s.log for s in logs) for r in by_log.get(log, ())]
            planned = set().union(*(set(s.set_order) for s in logs)) or {r[0] for r in rows}
            done = {r[0] for r in rows if r[1] in ("completed", "superseded")}
            trials = int(sum(int(r[2] or 0) for r in rows))
            refused = any(r[1] == "aborted" for r in rows)
            if planned and planned <= done:
                status = "complete"
            elif refused:
                status = "refused"
            else:
                status = "partial"
            out.append(
                CellStatus(p, e, status, len(done & planned), len(planned), trials, len(logs))
            )
    return out


def unmasked_als(thresholds: pd.DataFrame) -> dict[str, dict[str, float]]:
    """Each participant's unmasked AL per stimulus (latest completed baseline set), dB re 1 V.

    Examples
    --------
    >>> import pandas as pd
    >>> t = pd.DataFrame({"participant": ["P1"], "target": ["EV270"], "masker": [None],
    ...                   "status": ["completed"], "al_db_v": [-31.5]})
    >>> unmasked_als(t)
    {'P1': {'EV270': -31.5}}
    """
    rows = thresholds[(thresholds["status"] == "completed") & thresholds["masker"].isna()]
    out: dict[str, dict[str, float]] = {}
    columns = [rows[c].tolist() for c in ("participant", "target", "al_db_v")]
    for participant, target, al in zip(*columns, strict=True):
        if al is not None:
            out.setdefault(str(participant), {})[str(target)] = float(al)
    return out


@dataclass(frozen=True)
class Outlier:
    """A value flagged by :data:`OUTLIER_RULE`.

    Attributes
    ----------
    participant : str
        Whose value.
    what : str
        The cell (``experiment target|masker @ level dB SL`` or ``unmasked AL of EV270``).
    value_db : float
        The value, dB.
    others_mean_db : float
        The other participants' mean, dB (the reference of the rule).
    z : float
        (value − mean of the others) / SD of the others.
    """

    participant: str
    what: str
    value_db: float
    others_mean_db: float
    z: float


def _flag(values: Mapping[str, float], what: str) -> list[Outlier]:
    out: list[Outlier] = []
    items = list(values.items())
    every = np.array([v for _, v in items], dtype=float)
    if every.size - 1 < _MIN_OTHERS:
        return out
    for i in _may_be_flagged(every):
        p, v = items[i]
        others = np.delete(every, i)  # the others, in order: the same sums as a new array
        if others.size < _MIN_OTHERS:
            continue
        med = float(np.mean(others))
        mad = float(np.std(others, ddof=1))
        if mad <= 0.0:
            continue
        z = (v - med) / mad
        if abs(z) > OUTLIER_Z:
            out.append(Outlier(p, what, float(v), med, float(z)))
    return out


def _may_be_flagged(every: NDArray[np.float64]) -> list[int]:
    """Indices whose leave-one-out |z| may exceed :data:`OUTLIER_Z`: a superset, so only these
    are computed exactly (a cell of hundreds of participants needed hundreds of array copies).

    Every leave-one-out z at once from the centred values (exact algebra): a value whose
    screened |z| is below 0.9 of the rule's cannot be flagged. The centred values are exact to
    ~n × 1e-16 × max|x|, so a cell whose spread is within 1e-6 × n × max|x| (values equal but
    for rounding, or non-finite) is computed exactly throughout; otherwise the others' squared
    deviations (``rest``) lose at most ~1e-10 × total, and a value whose ``rest`` is below
    1e-6 × total (its others nearly equal) is kept, so the screen errs by < 1e-4 relative,
    inside the 10 % margin. (With half the rule, ~8 % of normal values passed: 10,000 exact
    computations, ~0.3 s at 10,000 sessions.)
    """
    n = every.size
    d = every - every.mean()
    total = float(d @ d)
    bound = 1e-6 * n * float(np.max(np.abs(every)))  # (a float's ** 2 could raise overflow)
    if not total > bound * bound:  # rounding-level spread, or a non-finite value
        return list(range(n))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        # sum of squared deviations of the others about their own mean: total − d²·n/(n − 1)
        rest = total - d * d * (n / (n - 1))
        z = d * (n / (n - 1)) / np.sqrt(rest / (n - 2))
        keep = ~np.isfinite(z) | (np.abs(z) > 0.9 * OUTLIER_Z) | (rest <= 1e-6 * total)
    return np.flatnonzero(keep).tolist()


def outliers(thresholds: pd.DataFrame) -> list[Outlier]:
    """Values flagged by :data:`OUTLIER_RULE`: AL shifts per cell and unmasked ALs.

    Examples
    --------
    >>> import pandas as pd
    >>> t = pd.DataFrame({"participant": [f"P{i}" for i in range(6)], "experiment": ["e"] * 6,
    ...     "target": ["EV270"] * 6, "masker": ["MV120"] * 6, "masker_level_db_sl": [10.0] * 6,
    ...     "status": ["completed"] * 6, "shift_db": [1.0, 1.2, 0.9, 1.1, 1.0, 9.0],
    ...     "al_db_v": [None] * 6})
    >>> [(o.participant, round(o.z)) for o in outliers(t)]
    [('P5', 70)]
    """
    out: list[Outlier] = []
    keys = ["experiment", "target", "masker", "masker_level_db_sl"]
    ok = thresholds["status"] == "completed"
    ok &= thresholds["masker"].notna() & thresholds["shift_db"].notna()
    masked = thresholds.loc[ok, ["participant", "shift_db", *keys]]  # not the other columns
    # The cells as pandas groups them (sorted keys, NaN keys dropped), walked on plain lists:
    # a DataFrame per cell cost ~1 s at 10,000 sessions, before the shift figures could start.
    cell = masked.groupby(keys, sort=True).ngroup().to_numpy(dtype=float)
    order = np.argsort(cell, kind="stable")  # within a cell, the rows keep their order
    cell = cell[order]
    ends = [*np.flatnonzero(np.diff(cell)).tolist(), cell.size - 1]
    participant = masked["participant"].to_numpy()[order].tolist()
    shift = masked["shift_db"].astype(float).to_numpy()[order].tolist()
    e_t_m_lv = [masked[c].to_numpy()[order].tolist() for c in keys]
    start = 0
    for end in ends:
        if end < 0 or np.isnan(cell[end]):  # none, or the rows with a missing key (last)
            break
        e, t, m, lv = (col[start] for col in e_t_m_lv)
        vals: dict[str, Any] = dict(
            zip(participant[start : end + 1], shift[start : end + 1], strict=True)
        )
        out += _flag(vals, f"{e} {t}|{m} @ {float(lv):g} dB SL (AL shift)")
        start = end + 1
    for target, als in sorted(_by_target(unmasked_als(thresholds)).items()):
        out += _flag(als, f"unmasked AL of {target}")
    return out


def _by_target(als: Mapping[str, Mapping[str, float]]) -> dict[str, dict[str, float]]:
    out: dict[str, dict[str, float]] = {}
    for p, per in als.items():
        for t, v in per.items():
            out.setdefault(t, {})[p] = v
    return out
