"""Session logs of simulated participants, in the real log format (for tests, demos, benchmarks).

:func:`simulate_study` runs, for each simulated participant, the baseline protocol (unmasked ALs
in dB re 1 V), takes its completed ALs as the participant's calibration, then runs the masked
protocols in dB SL, exactly as a rig would: each set's procedure (the 1-up-3-down staircase of
:mod:`masking_lab.procedures.staircase`, or QUEST+), driven through the
:class:`~masking_lab.procedures.base.Procedure` interface and answered by
:class:`masking_lab.simulation.observer.SimulatedParticipant`.

The masker's *true* sensation level follows from the calibration, so a baseline error misplaces
the masker as it would at a real rig. Records follow ``data_schema/session_log.schema.json``
and are written by :class:`masking_lab.formats.session_log.SessionLogWriter`, each file in one
write and one fsync (fixtures, not a live session).
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from masking_lab import __version__
from masking_lab.formats.protocol import ThresholdProtocol, load_protocol, parse_protocol
from masking_lab.formats.resources import shipped
from masking_lab.formats.session_log import SessionLogWriter
from masking_lab.procedures.log_fields import end_fields, start_fields, trial_fields
from masking_lab.simulation.observer import (
    GroundTruth,
    SimulatedParticipant,
    load_ground_truth,
    make_participant,
)

PAPER_PROTOCOLS = ("baseline", "experiment1", "experiment2")
_EPOCH = datetime(2024, 3, 4, 9, 0, 0, tzinfo=UTC)


def baseline_near(truth: GroundTruth, *, start_above_db: float = 10.0) -> ThresholdProtocol:
    """The shipped baseline protocol with each set starting near the population's AL.

    The shipped protocol starts every baseline staircase at 0 dB re 1 V, 14–32 dB above the
    simulated ALs; from that far above, the mean of the last 8 reversals comes out ~0.3–0.5 dB
    high (see docs/analysis.md). Starting ``start_above_db`` above the population mean AL of
    each target removes that bias, which matters when the fitted ramps are compared with the
    ground truth.
    """
    data = yaml.safe_load(shipped("protocols", "baseline.yaml").read_text(encoding="utf-8"))
    for spec in data["sets"]:
        mean_al = truth.unmasked_al_db_v[spec["target"]]
        spec["start_level_db"] = round(mean_al + start_above_db, 1)
    text = yaml.safe_dump(data, sort_keys=False)
    return parse_protocol(text.encode("utf-8"), "baseline_near.yaml")


def simulate_session(
    protocol: ThresholdProtocol,
    participant: SimulatedParticipant,
    *,
    calibration: dict[str, float],
    seed: int,
    session_id: str,
    created_utc: str,
) -> list[dict[str, Any]]:
    """Every record of one simulated session, header first.

    Parameters
    ----------
    protocol : ThresholdProtocol
        What to run.
    participant : SimulatedParticipant
        Who answers.
    calibration : dict
        Unmasked AL per stimulus, dB re 1 V, as the rig knows it (empty for a baseline session).
    seed : int
        Seeds the set order and the answers.
    session_id, created_utc : str
        Logged identity and time.
    """
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0xA11]))
    order = protocol.set_order(seed)
    header = {
        "record": "header",
        "schema_version": 1,
        "session_id": session_id,
        "created_utc": created_utc,
        "software_version": __version__,
        "protocol": {
            "path": Path(protocol.path).name,
            "sha256": protocol.sha256,
            "experiment": protocol.experiment,
            "content": dict(protocol.content),
        },
        "participant": participant.participant,
        "calibration": dict(sorted(calibration.items())) if protocol.kind == "masked" else {},
        "device": {"backend": "simulated", "model": "synthetic", "firmware_version": "n/a"},
        "responder": "simulated",
        "seed": int(seed),
        "set_order": order,
        "clock": "virtual",
    }
    records: list[dict[str, Any]] = [header]
    t = 0.0
    trial_s = protocol.timing.trial_s
    for set_id in order:
        spec = protocol.set_by_id(set_id)
        target = spec.target.name
        masker = spec.masker.name if spec.masker is not None else None
        masked = protocol.kind == "masked"
        unmasked = calibration[target] if masked else None
        masker_db_v = None
        true_masker_sl = None
        if masker is not None:
            # a set with a masker has its level (the protocol loader checks that)
            masker_db_v = float(spec.masker_level_db_sl) + calibration[masker]  # type: ignore[arg-type]
            true_masker_sl = masker_db_v - participant.unmasked_al_db_v[masker]
        settings = spec.settings
        records.append(
            {
                "record": "set_start",
                "set_id": set_id,
                "target": target,
                "masker": masker,
                "masker_level_db_sl": spec.masker_level_db_sl,
                "masker_level_db_v": masker_db_v,
                "unmasked_al_db_v": unmasked,
                "level_unit": protocol.level_unit,
                "max_level_db": settings.max_level_db,
                "min_level_db": settings.min_level_db,
                **start_fields(settings),
                "t_s": round(t, 3),
            }
        )
        sc = settings.start()
        while not sc.finished:
            level = sc.next_level()
            level_v = level + unmasked if masked else level
            p = participant.p_correct(target, level_v, masker, true_masker_sl or 0.0)
            correct = bool(rng.random() < p)
            interval = int(rng.integers(1, 4))
            response = (
                interval if correct else int(rng.choice([i for i in (1, 2, 3) if i != interval]))
            )
            rt = float(0.4 + rng.gamma(2.0, 0.25))
            onsets = [
                t
                + protocol.timing.lead_in_s
                + i * (protocol.timing.stimulus_s + protocol.timing.gap_s)
                for i in range(3)
            ]
            before = sc
            sc = sc.update(correct)
            records.append(
                {
                    "record": "trial",
                    "set_id": set_id,
                    "trial_index": sc.n_trials - 1,
                    "level_db_sl": level if masked else None,
                    "level_db_v": level_v,
                    "target_interval": interval,
                    "response_interval": response,
                    "correct": correct,
                    **_trial_fields(before, sc, level),
                    "planned_onsets_s": [round(o, 3) for o in onsets],
                    "actual_onsets_s": [round(o + 0.001, 3) for o in onsets],
                    "response_time_s": round(rt, 3),
                }
            )
            t += trial_s + rt + protocol.timing.inter_trial_s
        ends = end_fields(sc)
        al = ends["al_db"]
        end = {
            "record": "set_end",
            "set_id": set_id,
            "status": sc.status,
            "al_db": al,
            "al_db_v": None if al is None else (al + unmasked if masked else al),
            "al_db_sl": al if masked else None,
            "n_trials": sc.n_trials,
            "reversal_levels_db": ends["reversal_levels_db"],
            "t_s": round(t, 3),
        }
        if "sd_db" in ends:  # the staircase's records stay as they were
            end |= {"method": ends["method"], "sd_db": ends["sd_db"]}
        records.append(end)
        t += protocol.timing.rest_between_sets_s
    ended = _parse_utc(created_utc) + timedelta(seconds=t)
    records.append({"record": "session_end", "status": "completed", "ended_utc": _utc(ended)})
    return records


def write_log(path: str | Path, records: Sequence[dict[str, Any]]) -> Path:
    """Write records (header first) as a session log, through the session-log writer.

    The lines are those a live session writes (with ``seq``); the file is written in one go
    and fsynced once. An existing file at ``path`` is replaced.
    """
    p = Path(path)
    p.unlink(missing_ok=True)
    header, *rest = records
    with SessionLogWriter.create(p, header, sync="set") as writer:
        writer.append_many(rest)
    return p


def simulate_study(
    out_dir: str | Path,
    *,
    n_participants: int = 10,
    seed: int = 0,
    truth: GroundTruth | None = None,
    protocols: Sequence[str | ThresholdProtocol] = PAPER_PROTOCOLS,
    baseline_start_above_db: float | None = None,
) -> list[Path]:
    """Simulate a whole study and write one log per participant and protocol.

    Parameters
    ----------
    out_dir : path
        Folder for the logs (``<participant>/<participant>_<experiment>.jsonl``).
    n_participants : int
        Participants ``P01``, ``P02``, ...
    seed : int
        Seeds participants and sessions; the same seed gives byte-identical logs.
    truth : GroundTruth, optional
        Population to draw from (default: ``protocols/simulation/ground_truth.yaml``).
    protocols : sequence
        Protocol names or objects; a ``baseline`` one runs first and yields the calibration.
    baseline_start_above_db : float, optional
        Replace the protocol named ``"baseline"`` by :func:`baseline_near` with this offset.

    Returns
    -------
    list[Path]
        Files written, in order.
    """
    truth = truth or load_ground_truth()

    def load(p: str | ThresholdProtocol) -> ThresholdProtocol:
        if isinstance(p, ThresholdProtocol):
            return p
        if p == "baseline" and baseline_start_above_db is not None:
            return baseline_near(truth, start_above_db=baseline_start_above_db)
        return load_protocol(str(shipped("protocols", f"{p}.yaml")))  # a shipped protocol

    loaded = [load(p) for p in protocols]
    loaded.sort(key=lambda pr: pr.kind != "baseline")
    out = Path(out_dir)
    written = []
    width = max(2, len(str(n_participants)))
    for i in range(n_participants):
        pid = f"P{i + 1:0{width}d}"
        person = make_participant(truth, pid, seed)
        calibration: dict[str, float] = {}
        for j, protocol in enumerate(loaded):
            session_seed = _session_seed(seed, pid, protocol.experiment)
            created = _utc(_EPOCH + timedelta(days=i, hours=2 * j))
            records = simulate_session(
                protocol,
                person,
                calibration=calibration,
                seed=session_seed,
                session_id=f"{pid}-{protocol.experiment}-{session_seed % 100000:05d}",
                created_utc=created,
            )
            if protocol.kind == "baseline":
                calibration = _calibration_from(records, person)
            path = out / pid / f"{pid}_{protocol.experiment}.jsonl"
            written.append(write_log(path, records))
    return written


def _calibration_from(
    records: list[dict[str, Any]], person: SimulatedParticipant
) -> dict[str, float]:
    """Completed baseline ALs by target; a failed set falls back to the true AL (a rig re-runs)."""
    starts = {r["set_id"]: r["target"] for r in records if r.get("record") == "set_start"}
    cal = dict(person.unmasked_al_db_v)
    for r in records:
        if r.get("record") == "set_end" and r["status"] == "completed":
            cal[starts[r["set_id"]]] = float(r["al_db"])
    return cal


def _trial_fields(before: Any, after: Any, level: float) -> dict[str, Any]:
    """The procedure's keys of a trial record (these fixtures log the staircase's step as the
    level change and its next level even after the last trial, as they always have)."""
    fields = {k: v for k, v in trial_fields(before, after).items() if v is not None}
    if "posterior" not in fields:
        fields |= {"step_db": after.next_level() - level, "next_level_db": after.next_level()}
        fields["at_bound"] = after.at_bound
    return fields


def _session_seed(seed: int, participant: str, experiment: str) -> int:
    digest = hashlib.sha256(f"{seed}|{participant}|{experiment}".encode()).digest()
    return int.from_bytes(digest[:4], "little")


def _utc(t: datetime) -> str:
    return t.strftime("%Y-%m-%dT%H:%M:%SZ")


def _parse_utc(text: str) -> datetime:
    return datetime.strptime(text, "%Y-%m-%dT%H:%M:%SZ").replace(tzinfo=UTC)
