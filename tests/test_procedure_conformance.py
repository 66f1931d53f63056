"""The procedure conformance suite: every registered kind, every check (as scikit-learn's
``parametrize_with_checks`` runs every estimator through every check).

A new procedure registered in :mod:`masking_lab.procedures.registry` is picked up here with
no edit: its ``examples()`` settings run through each check below against simulated observers
(true thresholds drawn per case, answers from a seeded generator).
"""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

from masking_lab.core.psychometric import Psychometric
from masking_lab.formats.schemas import load_schema
from masking_lab.procedures.base import Procedure, replay
from masking_lab.procedures.log_fields import end_fields, start_fields, trial_fields
from masking_lab.procedures.registry import (
    kind_named,
    kind_of,
    kinds,
    protocol_schema_fragment,
    settings_from_start,
)


def _cases() -> Iterator[Any]:
    for kind in kinds():
        for i, settings in enumerate(kind.examples()):
            yield pytest.param(kind.name, settings, id=f"{kind.name}-{i}")


CASES = list(_cases())
CHECKS: list[Callable[[str, Any], None]] = []


def check(fn: Callable[[str, Any], None]) -> Callable[[str, Any], None]:
    CHECKS.append(fn)
    return fn


def _levels_of(state: Procedure) -> list[float]:
    return list(state.levels_db)  # type: ignore[attr-defined]


def _observer_answers(settings: Any, seed: int) -> Callable[[Procedure], bool]:
    """A simulated observer answering the track's next trial (threshold inside its range)."""
    rng = np.random.default_rng(seed)
    lo = getattr(settings, "min_level_db", None)
    hi = getattr(settings, "max_level_db", None)
    lo = -10.0 if lo is None else lo
    hi = 30.0 if hi is None else hi
    truth = float(rng.uniform(lo + 0.3 * (hi - lo), hi - 0.3 * (hi - lo)))
    psy = Psychometric(truth, 1.5, 1 / 3, 0.02)

    def answer(state: Procedure) -> bool:
        return bool(rng.random() < psy.p_correct(state.next_level()))

    return answer


def _run(settings: Any, seed: int) -> tuple[Procedure, list[bool], list[Procedure]]:
    answer = _observer_answers(settings, seed)
    state = settings.start()
    states = [state]
    responses: list[bool] = []
    cap = kind_of(settings).trial_cap(settings)
    while not state.finished:
        assert state.n_trials < cap, "the track ran past its own trial cap"
        r = answer(state)
        responses.append(r)
        state = state.update(r)
        states.append(state)
    return state, responses, states


def _finite_numbers(value: Any) -> Iterator[float]:
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return
    if isinstance(value, int | float):
        yield float(value)
    elif isinstance(value, dict):
        for v in value.values():
            yield from _finite_numbers(v)
    elif isinstance(value, list | tuple):
        for v in value:
            yield from _finite_numbers(v)


@check
def check_replay_gives_the_same_track(name: str, settings: Any) -> None:
    final, responses, _ = _run(settings, seed=1)
    again = replay(settings, responses)
    assert again == final
    assert _levels_of(again) == _levels_of(final)


@check
def check_resume_equals_an_uninterrupted_run(name: str, settings: Any) -> None:
    final, responses, states = _run(settings, seed=2)
    for cut in sorted({1, len(responses) // 2, len(responses) - 1}):
        if not 0 < cut < len(responses):
            continue
        resumed = replay(settings, responses[:cut])
        assert resumed == states[cut]
        for r in responses[cut:]:
            resumed = resumed.update(r)
        assert resumed == final


@check
def check_state_round_trips_through_the_log(name: str, settings: Any) -> None:
    final, responses, states = _run(settings, seed=3)
    start = json.loads(json.dumps(start_fields(settings), allow_nan=False))
    rebuilt = settings_from_start(start, None)
    assert rebuilt == settings
    assert replay(rebuilt, responses) == final
    for before, after in itertools.pairwise(states):
        record = trial_fields(before, after)
        json.dumps(record, allow_nan=False)
    json.dumps(end_fields(final), allow_nan=False)


@check
def check_trials_are_bounded(name: str, settings: Any) -> None:
    kind = kind_named(name)
    cap = kind.trial_cap(settings)
    assert isinstance(cap, int) and 0 < cap < 100_000
    for always in (True, False):
        state = settings.start()
        while not state.finished:
            assert state.n_trials < cap
            state = state.update(always)
        assert state.n_trials <= cap
        assert state.status != "running"


@check
def check_outputs_are_finite(name: str, settings: Any) -> None:
    kind = kind_named(name)
    final, _, states = _run(settings, seed=4)
    for before, after in itertools.pairwise(states):
        for x in _finite_numbers(trial_fields(before, after)):
            assert math.isfinite(x)
        if not after.finished:
            assert math.isfinite(after.next_level())
            left = kind.trials_left(after, [])
            assert math.isfinite(left) and 0 <= left <= kind.trial_cap(settings)
            assert kind.progress(after, "dB SL")
    for x in _finite_numbers(end_fields(final)):
        assert math.isfinite(x)
    est = final.estimate()
    assert est.level_db is None or math.isfinite(est.level_db)
    assert est.sd_db is None or math.isfinite(est.sd_db)
    if final.status != "completed":
        assert kind.no_al_reason(final, "dB SL", 1.0)


@check
def check_same_seed_same_session(name: str, settings: Any) -> None:
    a, ra, _ = _run(settings, seed=5)
    b, rb, _ = _run(settings, seed=5)
    assert ra == rb and a == b


@check
def check_batch_equals_scalar(name: str, settings: Any) -> None:
    kind = kind_named(name)
    runs = [_run(settings, seed=10 + i) for i in range(4)]
    width = max(len(r) for _, r, _ in runs)
    answers = np.zeros((len(runs), width), dtype=bool)
    for i, (_, r, _) in enumerate(runs):
        answers[i, : len(r)] = r
    batch = kind.replay_batch(settings, answers)
    for i, (final, r, _) in enumerate(runs):
        assert int(batch.n_trials[i]) == final.n_trials == len(r)
        np.testing.assert_allclose(batch.levels_db[i, : len(r)], _levels_of(final), atol=1e-9)


@check
def check_simulated_batch_is_bounded_and_seeded(name: str, settings: Any) -> None:
    kind = kind_named(name)
    thresholds = np.full(6, 5.0)
    one = kind.simulate_batch(
        settings, thresholds, scale_db=1.5, lapse=0.02, rng=np.random.default_rng(9)
    )
    two = kind.simulate_batch(
        settings, thresholds, scale_db=1.5, lapse=0.02, rng=np.random.default_rng(9)
    )
    assert np.array_equal(one.n_trials, two.n_trials)
    assert int(one.n_trials.max()) <= kind.trial_cap(settings)


@pytest.mark.parametrize("check_fn", CHECKS, ids=lambda f: f.__name__)
@pytest.mark.parametrize(("name", "settings"), CASES)
def test_conformance(check_fn: Callable[[str, Any], None], name: str, settings: Any) -> None:
    check_fn(name, settings)


def test_every_kind_is_registered_once_and_found_from_its_settings_and_states() -> None:
    names = [k.name for k in kinds()]
    assert len(names) == len(set(names)) and {"staircase", "quest_plus"} <= set(names)
    for kind in kinds():
        assert kind.examples(), f"{kind.name} gives the suite no settings to run"
        for settings in kind.examples():
            assert kind_of(settings) is kind
            assert kind_of(settings.start()) is kind
            assert settings.kind == kind.name


def test_protocol_schema_holds_exactly_the_registered_keys() -> None:
    schema = load_schema("protocol")["$defs"]["procedure"]
    fragment = protocol_schema_fragment()
    keys = set(schema["properties"]) | set(fragment["properties"])
    differ = sorted(k for k in keys if schema["properties"].get(k) != fragment["properties"].get(k))
    # The kinds' fragments (procedures/*_kind.py) are the source; the file is written from them.
    assert schema == fragment, (
        f"$defs.procedure differs from the registered kinds at {differ}: edit the kind's schema "
        "fragment, then write registry.protocol_schema_fragment() into "
        "data_schema/protocol.schema.json's $defs.procedure"
    )


def test_an_unknown_kind_is_a_clean_error_naming_the_known_ones() -> None:
    from masking_lab.core.errors import ProcedureError

    with pytest.raises(ProcedureError, match="quest_plus"):
        kind_named("psi_plus_plus")
    with pytest.raises(ProcedureError, match="unknown procedure kind"):
        settings_from_start({"procedure": {"kind": "nope"}}, None)


NEEDLES = (
    "isinstance(state, Staircase",
    "isinstance(state, QuestPlus",
    '== "quest_plus"',
    '!= "quest_plus"',
    "QuestPlusSettings.from_mapping",
    '== "functional_ramp"',
)


def test_nothing_outside_procedures_dispatches_on_a_procedure_kind() -> None:
    """The session, formats and analysis ask the registry; they name no procedure class."""
    import pathlib

    root = pathlib.Path(__file__).resolve().parents[1] / "masking_lab"
    offenders = []
    for sub in ("session", "analysis", "formats"):
        for path in (root / sub).glob("*.py"):
            text = path.read_text(encoding="utf-8")
            for needle in NEEDLES:
                if needle in text:
                    offenders.append(f"{path.relative_to(root)}: {needle}")
    assert offenders == []
