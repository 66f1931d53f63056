"""``masking-lab demo --out DIR``: simulated study end to end: sessions over the firmware,
analysis, export, a scene.

Run baseline, experiment I and experiment II for simulated participants through the C
firmware's host build (or, where it cannot be built, the firmware emulator) on pseudo-terminals
(virtual clock), analyse the logs, export masking_params.json and
render the paper's bump-with-rough-texture scene with and without compensation. Prints where
everything went and the fitted masking parameters beside the simulation's ground truth.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from masking_lab.commands.options import command_texts, output_folder
from masking_lab.commands.progress_bars import add_progress_options, progress_wanted, step_bar


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", **command_texts(__doc__))
    p.add_argument(
        "--out",
        type=output_folder,
        default=None,
        help="output folder [demo_out, or demo_out-2, -3, ... when that holds a demo already]",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="overwrite the demo already in --out (its data/, analysis/ and render/ folders)",
    )
    p.add_argument("--participants", type=int, default=10, help="simulated participants [10]")
    p.add_argument("--seed", type=int, default=2020, help="master seed [2020]")
    p.add_argument(
        "--device",
        choices=("auto", "firmware", "emulator", "sim"),
        default="auto",
        help="firmware: the C firmware's host build over real pseudo-terminals (compiled once "
        "with the system's C compiler, then cached); emulator: the Python firmware emulator "
        "over a real pseudo-terminal (the same trials); auto: firmware if it can be built "
        "here, else emulator [default]; sim: in-process",
    )
    p.add_argument("--jobs", type=int, default=None, help="worker processes [cores, at most 4]")
    p.add_argument("--n-boot", type=int, default=1000, help="bootstrap replicates of the fits")
    add_progress_options(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from masking_lab.core.errors import MaskingLabError
    from masking_lab.demo import DemoSettings, default_jobs, new_demo_folder, run_demo

    if args.participants < 2:
        raise MaskingLabError("--participants: the statistics need at least 2 participants")
    if args.jobs is not None and args.jobs < 1:
        raise MaskingLabError(
            f"--jobs {args.jobs}: use at least 1 worker process, or leave --jobs out for the "
            "default (the cores, at most 4)"
        )
    settings = DemoSettings(
        out=Path(args.out) if args.out is not None else new_demo_folder(Path("demo_out")),
        force=args.force,
        participants=args.participants,
        seed=args.seed,
        device=args.device,
        jobs=args.jobs if args.jobs is not None else default_jobs(),
        n_boot=args.n_boot,
    )
    # A bar over sessions, analysis and rendering on a terminal (or with --progress); else a
    # line per session as before.
    bar = None
    if progress_wanted(args.progress):
        from masking_lab.demo_summary import PROTOCOLS

        bar = step_bar("demo", True, total=args.participants * len(PROTOCOLS) + 3)
    return run_demo(settings, progress=bar)
