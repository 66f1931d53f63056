"""The one-pass layout of an intact typed log gives what the record-by-record routes give.

:func:`masking_lab.formats.typed_layout.intact_layout` stands in, for intact typed logs, for
three loops over the records: grouping by set (``_typed_sets``), the structural continuity
shortcut (``typed_structure_intact``) and the played-level check. Real logs of a simulated
study, intact and damaged at random (records deleted, repeated, swapped, moved; ids, indices,
counts and played levels changed; faults, headers and session ends inserted), must give the
same sets, continuity problems, played-level notes and read results by both routes. The old
route is taken by giving a log no layout (``log.__dict__["intact_layout"] = None``).
"""

from __future__ import annotations

import dataclasses
import random

import msgspec
import pytest

from masking_lab.analysis.log_reading import fast_parse, read_one
from masking_lab.analysis.played_levels import played_level_problems
from masking_lab.analysis.thresholds import EstimatorSettings, session_rows
from masking_lab.formats.log_records import ANALYSIS_DECODER, AFault, ATrial
from masking_lab.formats.session_log import SessionLog, _typed_sets
from masking_lab.formats.typed_layout import intact_layout, typed_structure_intact
from masking_lab.simulation.synthetic_logs import simulate_study


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("study")
    return [fast_parse(p.read_bytes(), p) for p in simulate_study(folder, n_participants=2)]


def _damage(records, rng):
    recs = list(records)
    for _ in range(rng.choice([1, 1, 2])):
        i, j = sorted(rng.sample(range(len(recs)), 2))
        how = rng.choice(
            ["delete", "repeat", "swap", "move", "set_id", "index", "count", "played", "fault",
             "header", "end", "unset_id", "none_id", "cut"]
        )  # fmt: skip
        rec = recs[i]
        if how == "delete":
            del recs[i]
        elif how == "repeat":
            recs.insert(j, rec)
        elif how == "swap":
            recs[i], recs[j] = recs[j], rec
        elif how == "move":
            recs.insert(j, recs.pop(i))
        elif how == "set_id" and hasattr(rec, "set_id"):
            recs[i] = msgspec.structs.replace(rec, set_id=rng.choice(["other", recs[j].set_id]))
        elif how == "index" and isinstance(rec, ATrial):
            recs[i] = msgspec.structs.replace(rec, trial_index=rec.trial_index + 1)
        elif how == "count" and hasattr(rec, "n_trials"):
            recs[i] = msgspec.structs.replace(rec, n_trials=rng.choice([msgspec.UNSET, 0, 1.0]))
        elif how == "played" and isinstance(rec, ATrial):
            recs[i] = msgspec.structs.replace(rec, played_target_v=rng.choice([0.0, 1e-3, None]))
        elif how == "fault":
            recs.insert(i, AFault(set_id=getattr(rec, "set_id", None)))
        elif how == "header":
            recs.insert(i, ANALYSIS_DECODER.decode(b'{"record":"header"}'))
        elif how == "end":
            recs.insert(i, ANALYSIS_DECODER.decode(b'{"record":"session_end"}'))
        elif how in ("unset_id", "none_id") and hasattr(rec, "set_id"):
            sid = msgspec.UNSET if how == "unset_id" else None
            recs = [msgspec.structs.replace(r, set_id=sid) if r.set_id == rec.set_id else r
                    for r in recs]  # fmt: skip
        elif how == "cut":
            recs = recs[:i]
    return recs


def _log(log, records, *, layout=True):
    out = SessionLog(log.path, log.header, records, lines=list(range(2, len(records) + 2)))
    if not layout:
        out.__dict__["intact_layout"] = None  # the record-by-record route
    return out


def _same_sets(a, b):
    assert list(a) == list(b)
    for sid in a:
        assert a[sid].start is b[sid].start
        assert a[sid].end is b[sid].end
        assert len(a[sid].trials) == len(b[sid].trials)
        assert all(x is y for x, y in zip(a[sid].trials, b[sid].trials, strict=True))


def test_intact_logs_have_a_layout(logs):
    for log in logs:
        layout = intact_layout(log.records)
        assert layout is not None and not layout.played
        assert len(layout.spans) == len(_typed_sets(log.records))


@pytest.mark.parametrize("seed", range(4))
def test_damaged_logs_give_the_same_answers_by_both_routes(logs, seed):
    rng = random.Random(seed)
    settings = EstimatorSettings()
    with_layout = 0
    for _ in range(250):
        base = rng.choice(logs)
        recs = _damage(base.records, rng)
        if not recs:
            continue
        layout = intact_layout(recs)
        if layout is not None:
            with_layout += 1
            assert typed_structure_intact(recs)  # never passes what the old shortcut refuses
            if not layout.played:
                assert played_level_problems(recs) == []
        new, old = _log(base, recs), _log(base, recs, layout=False)
        _same_sets(new.sets(), old.sets())
        assert new.continuity_problems() == old.continuity_problems()
        assert session_rows(new, "x", settings) == session_rows(old, "x", settings)
    assert with_layout > 20  # some damage (a changed count or played level) keeps the shape


def test_read_one_gives_the_old_route_s_result(logs, tmp_path, monkeypatch):
    rng = random.Random(11)
    settings = EstimatorSettings()
    for k in range(60):
        base = rng.choice(logs)
        raw = base.path.read_bytes().split(b"\n")[:-1]
        head, body = raw[0], raw[1:]
        if k % 3:  # damage the bytes: lines dropped, repeated or swapped
            for _ in range(2):
                i, j = sorted(rng.sample(range(len(body)), 2))
                body[i], body[j] = body[j], body[i]
                if k % 2:
                    body.insert(j, body[i])
        if k % 5 == 0:
            body = [line.replace(b'"reversal":false', b'"reversal":false,"played_target_v":0.01')
                    for line in body]  # fmt: skip
        path = tmp_path / f"log{k}.jsonl"
        path.write_bytes(b"\n".join([head, *body]) + b"\n")
        new = read_one(path, path.name, settings)
        with monkeypatch.context() as m:
            m.setattr(SessionLog, "intact_layout", property(lambda self: None))
            old = read_one(path, path.name, settings)
        assert dataclasses.astuple(new) == dataclasses.astuple(old)


def test_shared_row_values_are_the_same_values():
    from types import SimpleNamespace

    from masking_lab.analysis.log_reading import _share_values

    nan = float("nan")
    rows = [("P1", 1.5, -0.0, nan, None, 3, True), ("P" + "1", 1.5, 0.0, nan, "x", 3.0, False)]
    results = [SimpleNamespace(rows=[rows[0]]), SimpleNamespace(rows=[rows[1]])]
    _share_values(results)
    a, b = results[0].rows[0], results[1].rows[0]
    assert [type(v) for v in a] == [type(v) for v in rows[0]]
    assert [type(v) for v in b] == [type(v) for v in rows[1]]
    assert repr(a) == repr(rows[0]) and repr(b) == repr(rows[1])  # -0.0 and NaN kept
    assert a[0] is b[0] and a[1] is b[1]  # equal strings and floats: one object
    assert a[2] is not b[2]  # zeros of either sign are left alone
