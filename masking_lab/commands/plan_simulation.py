"""What ``masking-lab plan PROTOCOL`` simulates: its settings, observers and chunks, from the
command's options (*shell*: reads the ground-truth file).

:func:`simulation` is the part of ``plan`` that turns options into work: the staircase plan's
chunks and the QUEST+ comparison's, each a module-level function and its arguments that run
anywhere, in any order (each has its own seed). ``plan`` runs them on its workers;
``benchmarks/bench_commands.py --floors`` runs the same chunks in one process to time the
simulation alone.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

    from masking_lab.formats.protocol import ThresholdProtocol
    from masking_lab.planning.parallel import Task
    from masking_lab.planning.plan import PlanSettings
    from masking_lab.simulation.observer import GroundTruth

__all__ = ["Simulation", "simulation"]


@dataclass(frozen=True)
class Simulation:
    """What ``plan PROTOCOL`` simulates (see :func:`simulation`).

    Attributes
    ----------
    settings : PlanSettings
        Stop rules, schedules, observer, replicates, seed.
    truth : GroundTruth
        The simulated observers' ground truth.
    truth_name : str
        Where it came from (a file, or the embedded default's name).
    thresholds_db : ndarray, shape (sets, replicates)
        The observers' true thresholds, in the protocol's level unit (dB).
    staircase, quest : list of Task
        The staircase plan's chunks and the QUEST+ comparison's, each a module-level function
        and its arguments (:mod:`masking_lab.planning.parallel`).
    quest_kw : dict
        The QUEST+ options :func:`~masking_lab.planning.procedure_plan.compare_procedures`
        takes beside the chunks' outcomes.
    """

    settings: PlanSettings
    truth: GroundTruth
    truth_name: str
    thresholds_db: NDArray[np.float64]
    staircase: list[Task]
    quest: list[Task]
    quest_kw: dict[str, Any]


def simulation(args: argparse.Namespace, protocol: ThresholdProtocol) -> Simulation:
    """The simulation ``plan`` runs for a staircase or QUEST+ protocol with these options: its
    settings, observers and chunks (run anywhere, in any order: each has its own seed).

    Raises
    ------
    ProtocolError
        If ``--ground-truth`` names no file.
    AnalysisError
        If a lapse rate leaves p(correct) below the threshold's 0.794, or an option's text
        (stop rules, schedules, ratios) does not parse.

    Examples
    --------
    >>> from masking_lab.commands.cli import build_parser
    >>> from masking_lab.formats.protocol import load_protocol
    >>> from masking_lab.formats.resources import shipped
    >>> path = shipped("protocols", "experiment2.yaml")
    >>> args = build_parser().parse_args(
    ...     ["plan", str(path), "--replicates", "20", "--quest-replicates", "10"])
    >>> sim = simulation(args, load_protocol(path))
    >>> sim.thresholds_db.shape[1], len(sim.staircase) > 0, len(sim.quest) > 0
    (20, True, True)
    """
    import numpy as np

    from masking_lab.core.errors import AnalysisError, ProtocolError
    from masking_lab.core.psychometric import LEVITT_1U3D
    from masking_lab.planning import plan as P
    from masking_lab.planning.procedure_plan import default_quest_replicates, quest_tasks
    from masking_lab.procedures.staircase_batch import Observer
    from masking_lab.simulation.observer import load_ground_truth

    if args.ground_truth is not None and not Path(args.ground_truth).is_file():
        raise ProtocolError(
            args.ground_truth,
            "",
            "no such ground-truth file; check the path given to --ground-truth",
        )
    truth = load_ground_truth(args.ground_truth)
    truth_name = args.ground_truth or "protocols/simulation/ground_truth.yaml"
    scale = truth.scale_db if args.scale_db is None else args.scale_db
    lapse = truth.lapse if args.lapse is None else args.lapse
    # The threshold is the 0.794 point, so p(correct) must be able to exceed it.
    for flag, value in (("--lapse", lapse), ("--ml-lapse", args.ml_lapse)):
        if not value < 1 - LEVITT_1U3D:
            raise AnalysisError(
                f"{flag} {value:g}: p(correct) could never reach the 0.794 that defines the "
                f"threshold; use a lapse rate below {1 - LEVITT_1U3D:.3f} (typically 0–0.05)"
            )
    observer = Observer(scale, lapse, truth.guess)

    rules = (
        P.parse_stop_rules(args.stop_rules) if args.stop_rules else P.default_stop_rules(protocol)
    )
    ratios = P.parse_ratios(args.ratios) if args.ratios else None
    if args.schedules:
        schedules = P.parse_schedules(
            args.schedules, ratios or (P.protocol_schedule(protocol).down_up_ratio,)
        )
    else:
        schedules = P.default_schedules(protocol, ratios)
    settings = P.PlanSettings(
        stop_rules=rules,
        schedules=schedules,
        observer=observer,
        replicates=args.replicates,
        ml_replicates=args.ml_replicates,
        response_s=args.response_s,
        precision_db=args.precision_db,
        z=args.z,
        max_reversals=max(args.max_reversals, max(r.n_reversals for r in rules)),
        ml_lapse=args.ml_lapse,
        ml_fit_scale=not args.ml_fixed_scale,
        seed=args.seed,
    )
    thresholds = P.true_thresholds_db(
        protocol,
        truth,
        settings.replicates,
        np.random.default_rng(np.random.SeedSequence([args.seed, 0x7412])),
        spread=not args.no_spread,
        override_db=args.true_threshold_db,
        truth_source=truth_name,
    )
    reps = args.quest_replicates
    if reps is None:
        reps = default_quest_replicates(protocol)
    quest_kw: dict[str, Any] = {"quest_replicates": reps, "psi": args.psi}
    quest_kw["quest_max_trials"] = args.quest_max_trials
    staircase = P.plan_tasks(protocol, settings, thresholds)
    quest = quest_tasks(protocol, settings, thresholds, **quest_kw) if reps else []
    return Simulation(settings, truth, truth_name, thresholds, staircase, quest, quest_kw)
