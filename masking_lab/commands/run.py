"""``masking-lab run PROTOCOL --participant ID --device SPEC --responder R``: run a protocol's sets
(3IFC staircases or QUEST+) for one participant.

Run the sets of a protocol as 3IFC one-up three-down staircases (or QUEST+, where the protocol
says `procedure: {kind: quest_plus}`) and write a crash-safe session log to DATA/<participant>/.
Baseline sessions write the participant's calibration; masked sessions need it. Exit 0 when the
session completes, 2 on bad input, 3 on a device fault (or a device that cannot be opened), 130
when interrupted (a fault or interruption mid-session prints the `masking-lab resume` command
that continues it).
"""

from __future__ import annotations

import argparse
import sys

from masking_lab.commands.options import command_texts, session_options


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", **command_texts(__doc__))
    p.add_argument("protocol", metavar="PROTOCOL", help="protocol YAML file")
    p.add_argument("--participant", required=True, metavar="ID", help="participant id, e.g. S01")
    p.add_argument(
        "--device",
        required=True,
        metavar="SPEC",
        help="sim (in-process), emulator (firmware emulator on a pseudo-terminal) or "
        "serial:PORT (the rig)",
    )
    p.add_argument(
        "--responder",
        required=True,
        choices=("sim", "keys", "psychopy"),
        help="who answers: a simulated observer, a terminal keypad, or the PsychoPy window",
    )
    p.add_argument("--data", default="data", metavar="DIR", help="data folder (default: ./data)")
    p.add_argument("--seed", type=int, metavar="N", help="session seed (default: drawn, logged)")
    p.add_argument(
        "--sets",
        nargs="+",
        metavar="ID",
        help="run only these set ids (space- or comma-separated), in the seed's order",
    )
    p.add_argument(
        "--real-time",
        action="store_true",
        help="use the real clock with the sim responder (default: virtual time with sim and "
        "emulator devices, so a session takes seconds)",
    )
    p.add_argument(
        "--ground-truth",
        metavar="FILE",
        help="ground truth of the simulated observer (default: protocols/simulation/"
        "ground_truth.yaml)",
    )
    p.add_argument(
        "--info",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="participant metadata the protocol's info section asks for (age, handedness, "
        "...), e.g. --info age=24 --info handedness=right; repeatable; the missing fields "
        "are asked on the terminal, or in the window with --responder psychopy",
    )
    usertest = p.add_argument_group("user tests (protocols with kind: usertest)")
    usertest.add_argument(
        "--params",
        metavar="FILE",
        help="masking_params.json (from `masking-lab fit`) for the compensated condition",
    )
    usertest.add_argument(
        "--allow-clipping",
        action="store_true",
        help="play inputs above the rig's limits clipped to them (logged per trial) instead of "
        "refusing the session",
    )
    usertest.add_argument(
        "--gamut-map",
        choices=("none", "clip", "scale", "compress"),
        default="none",
        help="map each scene into the rig's gamut before rendering (see `masking-lab render`); "
        "the report names the strategy",
    )
    session_options(
        p,
        device_config_help="rig config: drive limits, serial settings, display (default: "
        "protocols/devices/default.yaml)",
        tty_help="with --responder keys: the participant's terminal (e.g. /dev/pts/3); "
        "default: this terminal",
    )
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from masking_lab.commands.session_kinds import for_protocol
    from masking_lab.core.errors import DeviceError, ResponderError
    from masking_lab.session.frame import start

    row = for_protocol(args.protocol)
    try:
        result = start(row.kind(), row.options(args))
    except (DeviceError, ResponderError) as exc:
        return device_unavailable(args.command, exc)
    return row.print_result(result)


def device_unavailable(command: str, exc: Exception) -> int:
    """The device (or the participant's window/terminal) could not be opened: exit 3."""
    from masking_lab.core.errors import ResponderError

    # A keypad or window problem is not the rig's: say which part to fix.
    what, part = (
        ("responder error", "the participant's terminal or window")
        if isinstance(exc, ResponderError)
        else ("device error", "the device")
    )
    print(
        f"masking-lab {command}: {what}: {exc}\nNothing was played; fix {part} and run "
        "the same command again.",
        file=sys.stderr,
    )
    return 3
