"""`commands.plan_simulation.simulation`: the work `plan PROTOCOL` hands its workers, from its
options (the chunks `benchmarks/bench_commands.py --floors` times alone)."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from masking_lab.commands.cli import build_parser, main
from masking_lab.commands.plan_simulation import simulation
from masking_lab.core.errors import AnalysisError, ProtocolError
from masking_lab.formats.protocol import load_protocol
from masking_lab.formats.resources import shipped
from masking_lab.planning.procedure_plan import MARGINAL_QUEST_REPLICATES, QUEST_REPLICATES


def _args(name: str, *extra: str):
    return build_parser().parse_args(["plan", str(shipped("protocols", f"{name}.yaml")), *extra])


@pytest.mark.parametrize(
    ("name", "replicates"),
    [("experiment2", QUEST_REPLICATES), ("experiment1_questplus", MARGINAL_QUEST_REPLICATES)],
)
def test_default_quest_replicates_without_touching_the_options(name, replicates):
    args = _args(name, "--replicates", "20")
    sim = simulation(args, load_protocol(shipped("protocols", f"{name}.yaml")))
    assert args.quest_replicates is None  # the options stay what the user gave
    assert sim.quest_kw["quest_replicates"] == replicates
    assert sim.thresholds_db.shape == (len(load_protocol(args.protocol).sets), 20)
    assert sim.staircase and sim.quest
    for fn, fn_args in [*sim.staircase, *sim.quest]:
        pickle.dumps((fn, fn_args))  # each chunk can reach a worker


def test_no_quest_chunks_when_asked_for_none():
    args = _args("experiment2", "--replicates", "20", "--quest-replicates", "0")
    sim = simulation(args, load_protocol(args.protocol))
    assert sim.quest == [] and sim.staircase


def test_the_same_seed_gives_the_same_observers_and_another_seed_others():
    protocol = load_protocol(shipped("protocols", "experiment2.yaml"))
    a = simulation(_args("experiment2", "--replicates", "20"), protocol)
    b = simulation(_args("experiment2", "--replicates", "20"), protocol)
    c = simulation(_args("experiment2", "--replicates", "20", "--seed", "1"), protocol)
    assert np.array_equal(a.thresholds_db, b.thresholds_db)
    assert not np.array_equal(a.thresholds_db, c.thresholds_db)


def test_a_missing_ground_truth_file_is_named(tmp_path):
    missing = tmp_path / "gt.yaml"
    args = _args("experiment2", "--ground-truth", str(missing))
    with pytest.raises(ProtocolError, match="no such ground-truth file") as err:
        simulation(args, load_protocol(args.protocol))
    assert str(missing) in str(err.value)


@pytest.mark.parametrize("flag", ["--lapse", "--ml-lapse"])
def test_a_lapse_that_never_reaches_the_threshold_is_refused(flag):
    args = _args("experiment2", flag, "0.3")
    with pytest.raises(AnalysisError, match=f"{flag} 0.3: p\\(correct\\) could never reach"):
        simulation(args, load_protocol(args.protocol))


def test_plan_runs_as_many_chunks_as_the_simulation_holds(tmp_path, capsys):
    extra = ("--replicates", "20", "--ml-replicates", "10", "--quest-replicates", "5")
    args = _args("experiment2", *extra)
    sim = simulation(args, load_protocol(args.protocol))
    assert main([*["plan", args.protocol, "--out", str(tmp_path / "p")], *extra]) == 0
    n = len(sim.staircase) + len(sim.quest)
    assert f"simulating {n} chunks" in capsys.readouterr().err
