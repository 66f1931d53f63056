"""``masking-lab plan --scene SCENE``: what a scene needs measured, the protocols that measure
it, and the scene's rendering error for a few measurement budgets (issue 19.4).

The imperative shell of :mod:`masking_lab.planning.scene_needs`,
:mod:`~masking_lab.planning.scene_protocols`, :mod:`~masking_lab.planning.scene_budget` and
:mod:`~masking_lab.planning.scene_report`: reads the scene, the parameters, the rig config and
the ground truth, prints the plan, and writes plan.txt, report.html, plan_functions.csv,
plan_budgets.csv and the measurement protocols to the output folder.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from masking_lab.planning.scene_budget import BudgetRow
    from masking_lab.planning.scene_needs import FunctionNeed

__all__ = ["BUDGET_POINTS", "add_scene_options", "run_scene"]

#: Points the budget simulation renders a scene at, at most.
BUDGET_POINTS = 2000


def _int_list(text: str) -> tuple[int, ...]:
    try:
        values = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a comma-separated list of whole numbers"
        ) from None
    if not values or any(v < 1 or v > 5000 for v in values):
        raise argparse.ArgumentTypeError(f"every value must be 1..5000, got {text}")
    return tuple(sorted(set(values)))


def _at_least(n: int):
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if v < n:
            raise argparse.ArgumentTypeError(f"must be ≥ {n}, got {v}")
        return v

    return parse


def add_scene_options(p: argparse.ArgumentParser) -> None:
    """The ``--scene`` path's options of ``masking-lab plan``."""
    g = p.add_argument_group("scene plan (--scene; docs/scenes.md)")
    g.add_argument(
        "--scene",
        metavar="SCENE",
        help="plan the measurements a scene needs instead of simulating a protocol",
    )
    g.add_argument(
        "--params", metavar="FILE", help="masking_params.json (default: nothing measured yet)"
    )
    g.add_argument(
        "--gamut-map",
        choices=("clip", "scale", "compress", "none"),
        default="clip",
        help="gamut mapping the scene will be rendered with (as render; default clip)",
    )
    g.add_argument(
        "--procedure",
        choices=("functional", "quest_plus"),
        default="functional",
        help="procedure of the written protocols: one functional_ramp track over the missing "
        "masker range (default), or QUEST+ per masker level",
    )
    g.add_argument(
        "--participants",
        type=_int_list,
        default=(5, 10, 20),
        metavar="N,N",
        help="participant counts of the budgets (default 5,10,20)",
    )
    g.add_argument(
        "--trials",
        type=_int_list,
        default=(30, 60, 90),
        metavar="T,T",
        help="trials per participant per measured function (default 30,60,90); the protocols "
        "get the largest",
    )
    g.add_argument(
        "--tracks",
        type=_at_least(3),
        default=12,
        help="simulated participants per measured function (default 12)",
    )
    g.add_argument(
        "--studies",
        type=_at_least(10),
        default=80,
        help="simulated studies per budget (default 80)",
    )


def _provenance(path: str | None, default: str) -> str:
    return path if path is not None else default


def run_scene(args: argparse.Namespace, out: Path) -> int:
    """Plan the scene ``args.scene`` into ``out`` (see module docstring). Exit status 0."""
    import numpy as np
    import yaml

    from masking_lab.core.errors import ProtocolError, SolverError
    from masking_lab.device.config import load_device_config
    from masking_lab.formats.fileio import write_bytes_atomic, write_text_atomic
    from masking_lab.formats.masking_params import read_masking_params
    from masking_lab.formats.output_dir import staged_output
    from masking_lab.formats.protocol import parse_protocol
    from masking_lab.planning.scene_budget import (
        BudgetRow,
        Observers,
        budget_table,
        participant_errors_chunked,
    )
    from masking_lab.planning.scene_needs import function_needs, measure_ranges, provisional_pair
    from masking_lab.planning.scene_protocols import masker_levels, measurement_protocol
    from masking_lab.planning.scene_report import (
        FUNCTION_FIELDS,
        ScenePlan,
        format_scene_plan,
        function_rows,
        rows_csv,
        scene_plan_html,
    )
    from masking_lab.rendering.scene import load_scene
    from masking_lab.rendering.uncertainty import pair_spread
    from masking_lab.simulation.observer import load_ground_truth

    scene = load_scene(args.scene)
    params = read_masking_params(args.params) if args.params else None
    if args.ground_truth is not None and not Path(args.ground_truth).is_file():
        raise ProtocolError(
            args.ground_truth,
            "",
            "no such ground-truth file; check the path given to --ground-truth",
        )
    truth_name = _provenance(args.ground_truth, "protocols/simulation/ground_truth.yaml")
    gt = load_ground_truth(args.ground_truth)
    rig = load_device_config(args.device_config)
    max_mv, max_ev = rig.max_level_db_sl.get("MV"), rig.max_level_db_sl.get("EV")
    # Participants are simulated in seeded chunks ([seed, tag, function]), the studies on a
    # stream of their own: the tables do not depend on where the chunks run (--scheduler).
    seed = np.random.SeedSequence([args.seed, 0x5CE7E])
    rng_studies = np.random.default_rng(seed.spawn(2)[1])
    header = [
        f"masking-lab plan --scene {args.scene}: scene {scene.name!r}, "
        f"{scene.path.n_points} points",
        f"parameters: {args.params or 'none (nothing measured yet)'}; prior for what is "
        f"missing and simulated participants: {truth_name}",
        f"rig {rig.name}: rated MV {_num(max_mv)}, EV {_num(max_ev)} dB SL; gamut mapping "
        f"{args.gamut_map}; seed {args.seed}",
    ]
    stimuli = scene.stimulus_pairs()
    needs: list[FunctionNeed] = []
    rows: list[BudgetRow] = []
    protocols, docs, floor, as_fitted, notes = [], {}, None, None, []
    pair_line = ""
    if stimuli:
        mv, ev = stimuli[0]
        prior = {(fn.target, fn.masker): fn for fn in gt.masking}
        inputs = provisional_pair(
            params,
            prior,
            mv=mv,
            ev=ev,
            params_source=args.params or "no --params",
            prior_source=truth_name,
        )
        _, needs = function_needs(
            scene, inputs, max_mv_db_sl=max_mv, max_ev_db_sl=max_ev, gamut_map=args.gamut_map
        )
        pair_line = _pair_line(scene)
        observers = Observers(gt.scale_db, gt.lapse, gt.shift_sd_db)
        measured: dict[str, Any] = {}
        trials_cap = max(args.trials)
        for need in needs:
            key = "g" if need.target.startswith("EV") else "f"
            ranges = measure_ranges(need)
            for lo, hi in ranges:
                doc = measurement_protocol(
                    need, lo, hi, procedure=args.procedure, trials=trials_cap, scene_name=scene.name
                )
                name = f"{doc['experiment']}.yaml"
                docs[name] = doc
                protocols.append((name, need, lo, hi, _how(doc, args.procedure)))
            if ranges:
                # One simulated measurement per function: over the hull of its ranges.
                lo, hi = min(r[0] for r in ranges), max(r[1] for r in ranges)
                doc = measurement_protocol(
                    need, lo, hi, procedure=args.procedure, trials=trials_cap, scene_name=scene.name
                )
                measured[key] = participant_errors_chunked(
                    doc["procedure"],
                    args.procedure,
                    (need.intercept_db, need.slope),
                    args.trials,
                    tracks=args.tracks,
                    observers=observers,
                    seed=[args.seed, 0x5CE7E, 1 + len(measured)],
                    masker_levels_db_sl=masker_levels(lo, hi),
                    scheduler=args.scheduler,
                )
        known = {}
        if params is not None:
            try:
                spread = pair_spread(params, mv=mv, ev=ev)
                known = {"f": (spread.a_sd_db, spread.b_sd), "g": (spread.c_sd_db, spread.d_sd)}
            except SolverError:  # a missing direction: it is measured, no SE to carry
                known = {}
        seconds = _seconds_per_trial(docs)
        budget_kw = {
            "studies": args.studies,
            "seconds_per_trial": seconds,
            "max_mv_db_sl": max_mv,
            "max_ev_db_sl": max_ev,
            "gamut_map": args.gamut_map,
            "rng": rng_studies,
        }
        budget_scene = scene
        if scene.path.n_points > BUDGET_POINTS:
            # Hundreds of renderings per budget: the error statistics of a long path are those
            # of an evenly resampled one (its maximum may be a little lower).
            budget_scene = replace(scene, path=replace(scene.path, n_points=BUDGET_POINTS))
            notes.append(
                f"budgets evaluated on {BUDGET_POINTS} of the scene's {scene.path.n_points} "
                "points, evenly spaced along the same path"
            )
        if measured:
            rows, floor = budget_table(
                budget_scene,
                inputs.pair,
                measured,
                known,
                participants=args.participants,
                trials=args.trials,
                **budget_kw,
            )
            notes.append(
                f"{args.studies} simulated studies per budget, {args.tracks} simulated "
                f"participants per measured function; one trial ≈ {seconds:.1f} s; "
                "the truth: the fitted ramps where present, the prior's where missing"
            )
        else:
            rows_fit, floor = budget_table(
                budget_scene, inputs.pair, {}, known, participants=(1,), trials=(1,), **budget_kw
            )
            as_fitted = {"rms_db": rows_fit[0].rms_db, "max_db": rows_fit[0].max_db}
            rows = []
    plan = ScenePlan(header, pair_line, needs, protocols, rows, floor, as_fitted, notes)
    text = format_scene_plan(plan)
    print(text, end="")
    files = {
        "plan.txt": text,
        "plan_functions.csv": rows_csv(function_rows(needs), FUNCTION_FIELDS),
        "plan_budgets.csv": rows_csv(
            [r.as_dict() for r in rows], list(BudgetRow.__dataclass_fields__)
        ),
    }
    pngs = {}
    if rows:
        from masking_lab.planning.figures import png_bytes
        from masking_lab.planning.scene_figure import budget_figure

        pngs["plan_budgets.png"] = png_bytes(
            budget_figure(rows, floor, title=f"{scene.name}: rendering error against the budget")
        )
    files["report.html"] = scene_plan_html(
        plan, title=f"masking-lab plan: scene {scene.name}", figures=pngs
    )
    for name, doc in docs.items():
        body = yaml.safe_dump(doc, sort_keys=False, allow_unicode=True)
        content = f"# Written by masking-lab plan --scene {scene.name}.\n{body}"
        parse_protocol(content.encode("utf-8"), name)  # what validate checks, before writing
        files[name] = content
    protect = [args.scene, *(p for p in (args.params, args.ground_truth) if p)]
    with staged_output(out, protect=protect, markers=("plan.txt",), shared="in_place") as stage:
        for name, content in files.items():
            write_text_atomic(stage / name, content)
        for name, png in pngs.items():
            write_bytes_atomic(stage / name, png)
    print(f"\nwrote {', '.join(str(out / n) for n in [*files, *pngs])}", file=sys.stderr)
    return 0


def _num(v: float | None) -> str:
    return "unrated" if v is None else f"{v:g}"


def _pair_line(scene: object) -> str:
    tex, geo = scene.texture, scene.geometry  # type: ignore[attr-defined]
    lo, hi = geo.perceived_db_sl
    return (
        f"pair {tex.stimulus} (texture {tex.name}, {tex.perceived_db_sl:g} dB SL) with "
        f"{geo.stimulus} (geometry {geo.shape}, {lo:g}–{hi:g} dB SL)"
    )


def _how(doc: dict, procedure: str) -> str:
    proc = doc["procedure"]
    if procedure == "functional":
        return f"functional_ramp, {proc['max_trials']} trials per participant"
    return f"QUEST+ at {len(doc['sets'])} masker levels, {proc['max_trials']} trials each"


def _seconds_per_trial(docs: dict) -> float:
    """Stimuli of one trial plus ~1 s to answer and the pause, s (the protocols' timing)."""
    from masking_lab.formats.resources import shipped

    if docs:
        timing = next(iter(docs.values()))["timing"]
    else:
        timing = _yaml_load(shipped("protocols", "experiment1_functional.yaml"))["timing"]
    stimuli = timing["lead_in_s"] + 3 * timing["stimulus_s"] + 2 * timing["gap_s"]
    return float(stimuli + 1.0 + timing["inter_trial_s"])


def _yaml_load(resource: object) -> dict:
    import yaml

    return yaml.safe_load(resource.read_text(encoding="utf-8"))  # type: ignore[attr-defined]
