"""``masking-lab resume LOG``: continue an interrupted session in its own log.

Continue a session stopped by a device fault, Ctrl-C, a kill or a power cut. An incomplete last
line is cut and reported; every set is rebuilt from its logged responses and the session goes on
with the same protocol (the copy in the log), calibration, seed and set order. Exit codes as for
`run`.
"""

from __future__ import annotations

import argparse

from masking_lab.commands.options import command_texts, session_options


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("resume", **command_texts(__doc__))
    p.add_argument("log", metavar="LOG", help="session log (.jsonl) to continue")
    p.add_argument(
        "--device",
        metavar="SPEC",
        help="device spec (default: the log's: sim, emulator, or serial:<logged port>)",
    )
    p.add_argument(
        "--responder",
        choices=("sim", "keys", "psychopy"),
        help="who answers (default: the log's)",
    )
    p.add_argument(
        "--allow-changed-protocol",
        action="store_true",
        help="resume although the protocol file changed since the session started (the copy "
        "stored in the log is used either way)",
    )
    session_options(
        p,
        device_config_help="rig config (default: the one the session started with)",
        tty_help="with --responder keys: the participant's terminal (default: this terminal)",
    )
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from masking_lab.commands.run import device_unavailable
    from masking_lab.commands.session_kinds import for_log
    from masking_lab.core.errors import DeviceError, ResponderError
    from masking_lab.session.frame import SessionOptions, resume

    row = for_log(args.log)
    changes = SessionOptions(
        device=args.device,
        responder=args.responder,
        allow_changed_protocol=args.allow_changed_protocol,
        device_config=Path(args.device_config) if args.device_config else None,
        participant_tty=args.participant_tty,
        progress=args.progress,
    )
    try:
        result = resume(row.kind(), Path(args.log), changes)
    except (DeviceError, ResponderError) as exc:
        return device_unavailable(args.command, exc)
    return row.print_result(result)
