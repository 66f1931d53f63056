"""``masking-lab emulate``: run the device firmware emulator on a pseudo-terminal (prints its
port).

Start the firmware emulator on a fresh pseudo-terminal, print 'emulator listening on PORT', and
serve it until Ctrl-C or SIGTERM; outputs are zeroed on exit. Connect with --device serial:PORT.
SIGUSR1 opens or closes the emulated interlock input.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading

from masking_lab.commands.options import command_texts


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("emulate", **command_texts(__doc__))
    p.add_argument(
        "--config", metavar="FILE", help="device config (default: protocols/devices/default.yaml)"
    )
    p.add_argument(
        "--virtual-time",
        action="store_true",
        help="complete PLAY at once with planned onsets (for sessions on a virtual clock)",
    )
    p.add_argument(
        "--watchdog-ms",
        type=_non_negative_int,
        metavar="N",
        help="watchdog period in ms (0 disables; default: serial.watchdog_s of the config)",
    )
    p.add_argument(
        "--boot-delay-s",
        type=float,
        default=0.0,
        metavar="S",
        help="imitate a board that resets on open: ignore input for S seconds after start",
    )
    p.add_argument(
        "--interlock-open",
        action="store_true",
        help="start with the interlock input open (HV enable off, E-stop pressed, wristband "
        "off); SIGUSR1 toggles it, to rehearse the safety chain without a rig",
    )
    p.add_argument(
        "--bits",
        type=_bits,
        default=12,
        metavar="N",
        help="converter resolution of both channels, bits (2-16; default 12, HELLO bits_ev/mv)",
    )
    p.add_argument(
        "--fsv",
        type=_full_scale,
        default=10.0,
        metavar="V",
        help="converter full scale at the amplifier input, peak V (default 10, HELLO fsv_ev/mv)",
    )
    p.add_argument(
        "--att",
        type=_att_steps,
        default=(0, 20, 40),
        metavar="DB,DB,..",
        help="attenuator steps the emulated board switches, dB, ascending from 0 "
        "(default 0,20,40; '0' for none; HELLO att, PLAY tatt/matt)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of simulated onset lateness")
    p.add_argument("--log", metavar="FILE", help="also append the emulator's event log to FILE")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from masking_lab.device.config import load_device_config
    from masking_lab.device.emulator import FirmwareEmulator

    config = load_device_config(args.config)
    stop = threading.Event()

    def on_signal(signum: int, frame: object) -> None:
        stop.set()

    toggle = threading.Event()

    def on_toggle(signum: int, frame: object) -> None:
        toggle.set()  # the main loop toggles it: a handler must not take the emulator's lock

    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, on_signal)
    signal.signal(signal.SIGUSR1, on_toggle)
    emulator = FirmwareEmulator(
        config,
        virtual_time=args.virtual_time,
        watchdog_s=None if args.watchdog_ms is None else args.watchdog_ms / 1000.0,
        boot_delay_s=args.boot_delay_s,
        seed=args.seed,
        log_path=args.log,
        interlock_open=args.interlock_open,
        bits=args.bits,
        fsv_v=args.fsv,
        att_db=args.att,
    ).start()
    interlock_open = args.interlock_open
    try:
        mode = "virtual" if args.virtual_time else "real"
        print(f"emulator listening on {emulator.port}", flush=True)
        print(
            f"  {mode} time, limits EV {emulator.limits['EV']:g} V / MV "
            f"{emulator.limits['MV']:g} V, watchdog {emulator.watchdog_s * 1000:g} ms, "
            f"interlock {'open' if interlock_open else 'closed'}; "
            f"connect with --device serial:{emulator.port}; Ctrl-C to stop",
            file=sys.stderr,
            flush=True,
        )
        while not stop.wait(0.05):
            if toggle.is_set():
                toggle.clear()
                interlock_open = not interlock_open
                emulator.set_interlock(interlock_open)
                state = "open: outputs zeroed" if interlock_open else "closed"
                print(f"interlock {state}", file=sys.stderr, flush=True)
    finally:
        emulator.close()
        print("emulator stopped: outputs zeroed, port closed", file=sys.stderr, flush=True)
    return 0


def _non_negative_int(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be ≥ 0, got {value}")
    return value


def _bits(text: str) -> int:
    value = int(text)
    if not 2 <= value <= 16:
        raise argparse.ArgumentTypeError(f"must be 2..16 bits, got {value}")
    return value


def _full_scale(text: str) -> float:
    value = float(text)
    if not 0 < value <= 1000:  # also refuses nan
        raise argparse.ArgumentTypeError(f"must be in (0, 1000] V, got {text}")
    return value


def _att_steps(text: str) -> tuple[int, ...]:
    try:
        steps = tuple(int(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"need whole dB steps like 0,20,40, got {text!r}"
        ) from None
    ok = steps[0] == 0 and list(steps) == sorted(set(steps)) and steps[-1] <= 60
    if not ok or len(steps) > 4:
        raise argparse.ArgumentTypeError(
            f"need up to 4 ascending whole dB steps in 0..60 starting at 0, got {text!r}"
        )
    return steps
