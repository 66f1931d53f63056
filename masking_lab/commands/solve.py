"""``masking-lab solve``: input intensities that produce wanted perceived MV/EV intensities (Table
4).

Invert the mutual masking of an MV stimulus and EV (paper §3.2, Table 4): for each wanted
perceived pair (m_p, e_p) in dB SL print the input pair (m_i, e_i) in dB SL, the case that
applied and whether the answer is unique. Points whose answer needs more than the device's rated
level are flagged, never clipped.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any

from masking_lab.commands.options import command_texts, rating_options
from masking_lab.formats.records import json_number

EPILOG = """\
examples:
  masking-lab solve --mv-masked-by-ev 1.39,1.09 --ev-masked-by-mv=-6.22,0.66 \\
      --mv-target 12 --ev-target 0,5,10
  masking-lab solve --params masking_params.json --mv MV180 --mv-target 12 --ev-target 5 --json

Values that start with '-' need '=': --ev-target=-3,0,3 or --mv-target=-inf (MV off).
Exit status: 0 when every target has exactly one answer, 1 when some have none or several,
2 on bad input.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "solve",
        **command_texts(__doc__),
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    src = p.add_argument_group("masking functions (give --params, or both ramps directly)")
    src.add_argument("--params", metavar="FILE", help="masking_params.json from `masking-lab fit`")
    src.add_argument("--mv", metavar="NAME", help="MV stimulus in --params, e.g. MV180")
    src.add_argument("--ev", metavar="NAME", default="EV270", help="EV stimulus (default EV270)")
    src.add_argument(
        "--mv-masked-by-ev",
        metavar="A,B",
        help="f: MV's AL shift = max(0, A + B·EV level); intercept A in dB, slope B",
    )
    src.add_argument(
        "--ev-masked-by-mv",
        metavar="C,D",
        help="g: EV's AL shift = max(0, C + D·MV level); intercept C in dB, slope D",
    )
    p.add_argument(
        "--mv-target", required=True, metavar="DB", help="wanted perceived MV, dB SL (list: a,b,c)"
    )
    p.add_argument(
        "--ev-target", required=True, metavar="DB", help="wanted perceived EV, dB SL (list: a,b,c)"
    )
    rating_options(
        p,
        "take the rated maxima from this rig config's channels.<EV|MV>.max_level_db_sl "
        "unless --max-* say otherwise (default: the reference rig, "
        "protocols/devices/default.yaml, as render)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object (for programs)")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from masking_lab.core.errors import SolverError
    from masking_lab.rendering.solver import MutualMasking, Status, pair_from_params, solve

    mv_t = _numbers(args.mv_target, "--mv-target")
    ev_t = _numbers(args.ev_target, "--ev-target")
    if len(mv_t) != len(ev_t) and 1 not in (len(mv_t), len(ev_t)):
        raise SolverError(
            f"--mv-target has {len(mv_t)} values and --ev-target {len(ev_t)}: give lists of "
            "equal length (or one number to use with every value of the other)"
        )
    direct = args.mv_masked_by_ev is not None or args.ev_masked_by_mv is not None
    if direct and args.params:
        raise SolverError("give either --params or --mv-masked-by-ev/--ev-masked-by-mv, not both")
    if direct:
        if args.mv_masked_by_ev is None or args.ev_masked_by_mv is None:
            raise SolverError(
                "give both --mv-masked-by-ev A,B and --ev-masked-by-mv C,D (intercept, slope)"
            )
        a, b = _pair(args.mv_masked_by_ev, "--mv-masked-by-ev")
        c, d = _pair(args.ev_masked_by_mv, "--ev-masked-by-mv")
        mm = MutualMasking(a, b, c, d, mv=args.mv or "MV", ev=args.ev)
    elif args.params:
        from masking_lab.formats.masking_params import (
            determination_warnings,
            read_masking_params,
        )

        params = read_masking_params(args.params)
        mv = args.mv or _only_mv(params, args.ev, args.params)
        mm = pair_from_params(params, mv=mv, ev=args.ev, source=args.params)
        for warning in determination_warnings(params, args.params, (mv, args.ev)):
            print(f"masking-lab solve: warning: {warning}", file=sys.stderr)
    else:
        raise SolverError(
            "no masking functions: give --params masking_params.json (with --mv NAME), or "
            "--mv-masked-by-ev A,B --ev-masked-by-mv C,D"
        )
    from masking_lab.device.rig_limits import max_level_db_sl

    # The reference rig's ratings unless a config or --max-* say otherwise (as render does).
    limits = max_level_db_sl(args.device_config)
    max_mv = limits.get("MV") if args.max_mv_db_sl is None else args.max_mv_db_sl
    max_ev = limits.get("EV") if args.max_ev_db_sl is None else args.max_ev_db_sl
    sol = solve(mm, np.array(mv_t), np.array(ev_t), max_mv_db_sl=max_mv, max_ev_db_sl=max_ev)
    if args.json:
        print(json.dumps(as_json(mm, sol), allow_nan=False))
    else:
        print(as_table(mm, sol))
    return 0 if bool(np.all(sol.status == Status.UNIQUE)) else 1


def as_json(mm: Any, sol: Any) -> dict[str, Any]:
    """The JSON object printed by ``--json`` (equal-length arrays, one entry per target)."""
    from masking_lab.rendering.ramp_inverse import REPRODUCE_TOL_DB
    from masking_lab.rendering.solver import REASON_TEXT, Reason

    n = sol.status.size
    solutions = []
    for i in range(n):
        entries = [
            {"mv_input_db": json_number(m), "ev_input_db": json_number(e), "case": c}
            for m, e, c in sol.solutions(i)
        ]
        if sol.continuum[i]:
            for entry in entries:
                if entry["case"] == 4:
                    entry["direction"] = [1.0, mm.d]
        solutions.append(entries)
    return {
        "mv_stimulus": mm.mv,
        "ev_stimulus": mm.ev,
        "a_db": mm.a_db,
        "b": mm.b,
        "c_db": mm.c_db,
        "d": mm.d,
        "bd": mm.bd,
        "one_minus_bd": mm.one_minus_bd,
        "reproduce_tol_db": REPRODUCE_TOL_DB,
        "units": "dB SL",
        "notes": list(mm.notes),
        "max_mv_db_sl": sol.max_mv_db_sl,
        "max_ev_db_sl": sol.max_ev_db_sl,
        "mv_target_db": [json_number(v) for v in sol.mv_target_db_sl],
        "ev_target_db": [json_number(v) for v in sol.ev_target_db_sl],
        "mv_input_db": [json_number(v) for v in sol.mv_input_db_sl],
        "ev_input_db": [json_number(v) for v in sol.ev_input_db_sl],
        "case": [int(c) or None for c in sol.case],
        "status": sol.status_names(),
        "reason": [REASON_TEXT[Reason(int(r))] or None for r in sol.reason],
        "continuum": [bool(v) for v in sol.continuum],
        "mv_exceeds_rating": [bool(v) for v in sol.mv_exceeds_rating],
        "ev_exceeds_rating": [bool(v) for v in sol.ev_exceeds_rating],
        "solutions": solutions,
    }


def as_table(mm: Any, sol: Any) -> str:
    """A plain-text table, one row per target."""
    from masking_lab.rendering.solver import REASON_TEXT, Reason

    head = (
        f"{mm.mv} masked by {mm.ev}: max(0, {mm.a_db:g} + {mm.b:g}·e_i);  "
        f"{mm.ev} masked by {mm.mv}: max(0, {mm.c_db:g} + {mm.d:g}·m_i);  b·d = {mm.bd_text}"
    )
    lines = [head, *(f"note: {n}" for n in mm.notes), ""]
    lines.append(f"{'m_p':>9} {'e_p':>9} {'m_i':>10} {'e_i':>10} case  status    notes")
    lines.append("  (all levels in dB SL)")
    names = sol.status_names()
    for i in range(sol.status.size):
        notes = []
        if sol.mv_exceeds_rating[i]:
            notes.append(f"MV above its rating ({sol.max_mv_db_sl:g} dB SL)")
        if sol.ev_exceeds_rating[i]:
            notes.append(f"EV above its rating ({sol.max_ev_db_sl:g} dB SL)")
        if sol.reason[i]:
            notes.append(REASON_TEXT[Reason(int(sol.reason[i]))])
        if names[i] == "multiple":
            sols = "; ".join(f"({m:.4g}, {e:.4g}) case {c}" for m, e, c in sol.solutions(i))
            notes.append(f"answers: {sols}")
            if sol.continuum[i]:
                notes.append(f"and every (m_i + t, e_i + {mm.d:g}·t), t ≥ 0, from the case-4 one")
        case = str(int(sol.case[i])) if sol.case[i] else "-"
        lines.append(
            f"{_f(sol.mv_target_db_sl[i]):>9} {_f(sol.ev_target_db_sl[i]):>9} "
            f"{_f(sol.mv_input_db_sl[i]):>10} {_f(sol.ev_input_db_sl[i]):>10} "
            f"{case:>4}  {names[i]:<9} {'; '.join(notes)}".rstrip()
        )
    return "\n".join(lines)


def _numbers(text: str, flag: str) -> list[float]:
    from masking_lab.core.errors import SolverError

    out = []
    for part in str(text).split(","):
        try:
            out.append(float(part.strip()))
        except ValueError:
            raise SolverError(
                f"{flag}: {part.strip()!r} is not a number; give dB SL values separated by "
                "commas, e.g. 0,5,10 (write -inf for a channel that is off)"
            ) from None
    return out


def _pair(text: str, flag: str) -> tuple[float, float]:
    from masking_lab.core.errors import SolverError

    values = _numbers(text, flag)
    if len(values) != 2:
        raise SolverError(
            f"{flag}: give two numbers, intercept (dB) and slope, e.g. 1.39,1.09; got {text!r}"
        )
    return values[0], values[1]


def _only_mv(params: dict[str, Any], ev: str, source: str) -> str:
    from masking_lab.core.errors import SolverError

    names = sorted(
        {
            str(f.get("target"))
            for f in params.get("functions", [])
            if isinstance(f, dict)
            and f.get("masker") == ev
            and str(f.get("target")).startswith("MV")
        }
    )
    if len(names) == 1:
        return names[0]
    listed = ", ".join(names) or "none"
    raise SolverError(
        f"{source}: say which MV stimulus with --mv NAME (masked by {ev} in the file: {listed})"
    )


def _f(x: float) -> str:
    x = float(x)
    if math.isnan(x):
        return "-"
    return f"{x:.4g}" if math.isfinite(x) else ("-inf" if x < 0 else "inf")
