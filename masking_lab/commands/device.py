"""``masking-lab device check PORT``: the bring-up self-test of a board.

Checks the handshake (protocol 2, firmware >= fw-2.0.0, build hash), clock source, reset cause,
limits, converter and attenuator steps against the rig config, interlock state, PING and PLAY
latency, and measures the watchdog's trip time (it streams 10 mV on EV until the watchdog zeroes
it: run it with nobody touching the rig). Prints a report; exit 0 when every check passes, 1 when
one fails, 3 when no board can be opened. ``--device serial:auto`` finds the board among the
serial ports by its HELLO.
"""

from __future__ import annotations

import argparse

from masking_lab.commands.options import command_texts


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("device", **command_texts(__doc__))
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    check = actions.add_parser(
        "check", help="bring-up self-test of a board; exit 1 if a check fails"
    )
    check.add_argument("port", nargs="?", metavar="PORT", help="serial port, e.g. /dev/ttyACM0")
    check.add_argument(
        "--device",
        metavar="SPEC",
        help="serial:PORT, or serial:auto to find the board by its HELLO among the serial ports",
    )
    check.add_argument(
        "--device-config",
        metavar="FILE",
        help="rig config: limits, converter, serial settings (default: "
        "protocols/devices/default.yaml)",
    )
    check.add_argument(
        "--no-watchdog",
        action="store_true",
        help="skip the watchdog trip-time measurement (it streams 10 mV on EV)",
    )
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    import sys

    from masking_lab.core.errors import DeviceError, MaskingLabError
    from masking_lab.device import registry
    from masking_lab.device.check import format_report, run_checks
    from masking_lab.device.config import load_device_config
    from masking_lab.device.discovery import find_board

    config = load_device_config(args.device_config)
    spec = args.device or (f"serial:{args.port}" if args.port else "")
    try:
        kind, port = registry.parse_spec(spec)  # the one spec grammar
    except MaskingLabError:
        kind, port = None, ""
    if kind is None or kind.name != "serial":
        print(
            "masking-lab device check: give PORT (e.g. /dev/ttyACM0) or --device serial:PORT "
            "or --device serial:auto",
            file=sys.stderr,
        )
        return 2
    if port == "auto":
        try:
            port = find_board(config)
        except DeviceError as exc:
            print(f"masking-lab device check: {exc}", file=sys.stderr)
            return 3
        print(f"found a masking-lab board on {port}")
    checks = run_checks(port, config, watchdog=not args.no_watchdog)
    print(format_report(port, checks))
    if any(c.status == "FAIL" for c in checks):
        return 3 if checks[0].name == "handshake" and checks[0].status == "FAIL" else 1
    return 0
