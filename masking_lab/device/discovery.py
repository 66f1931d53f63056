"""Find a masking-lab board among the serial ports by its HELLO (``--device serial:auto``).

Each candidate port (pyserial's ``list_ports``, at most :data:`MAX_PORTS`) is opened, sent
HELLO and given ``serial.boot_timeout_s`` (boards that reset when the port opens) to answer
with a valid masking-lab HELLO. The probe is bounded: per port and in total. Ports that cannot
be opened (busy, no permission) are skipped and named if no board is found.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import serial
from serial.tools import list_ports

from masking_lab.core.errors import DeviceError
from masking_lab.device import protocol as proto
from masking_lab.device.config import DeviceConfig

MAX_PORTS = 16
TOTAL_BUDGET_S = 30.0


def candidate_ports() -> list[str]:
    """Serial ports pyserial lists (USB CDC first: that is where boards are), at most 16."""
    ports = [p.device for p in list_ports.comports()]
    ports.sort(key=lambda d: (not ("ACM" in d or "usbmodem" in d), d))
    return ports[:MAX_PORTS]


def probe(port: str, config: DeviceConfig, budget_s: float) -> proto.Hello | None:
    """The port's HELLO if a masking-lab board answers within ``budget_s`` s, else None.

    Raises
    ------
    OSError, serial.SerialException
        The port cannot be opened.
    """
    settings = config.serial
    with serial.Serial(
        port, baudrate=settings.baud_rate, timeout=0.05, write_timeout=0.5, exclusive=True
    ) as link:
        link.reset_input_buffer()
        give_up = time.monotonic() + budget_s
        next_hello = 0.0
        buf = b""
        seq = 1
        while time.monotonic() < give_up:
            if time.monotonic() >= next_hello:
                link.write(proto.encode_command(seq, "HELLO"))
                seq = proto.next_seq(seq)
                next_hello = time.monotonic() + settings.hello_retry_s
            buf += link.read(max(1, link.in_waiting))
            while b"\n" in buf:
                line, _, buf = buf.partition(b"\n")
                try:
                    frame = proto.decode(line)
                    if frame.ok and "proto" in frame.fields:
                        return proto.parse_hello(frame)
                except proto.FrameError:
                    continue
            if len(buf) > proto.MAX_FRAME_BYTES:
                buf = b""
    return None


def find_board(config: DeviceConfig, ports: Sequence[str] | None = None) -> str:
    """The first port whose device answers a masking-lab HELLO.

    Parameters
    ----------
    config : DeviceConfig
        Serial settings (baud rate, boot timeout, HELLO retry interval).
    ports : sequence of str, optional
        Candidates (default :func:`candidate_ports`).

    Raises
    ------
    DeviceError
        No port answered: names the ports tried and what to check.
    """
    candidates = list(ports) if ports is not None else candidate_ports()
    per_port = max(config.serial.boot_timeout_s, config.serial.reply_timeout_s, 0.5)
    deadline = time.monotonic() + TOTAL_BUDGET_S
    tried: list[str] = []
    for port in candidates[:MAX_PORTS]:
        left = deadline - time.monotonic()
        if left <= 0:
            tried.append(f"{port} (not probed: {TOTAL_BUDGET_S:g} s budget used)")
            continue
        try:
            hello = probe(port, config, min(per_port, left))
        except (OSError, serial.SerialException) as exc:
            tried.append(f"{port} (cannot open: {exc})")
            continue
        except proto.FrameError:
            hello = None
        if hello is not None:
            return port
        tried.append(f"{port} (no masking-lab HELLO)")
    listed = "; ".join(tried) if tried else "no serial ports found"
    raise DeviceError(
        f"no masking-lab board found among the serial ports ({listed}): plug the board in, "
        "check that it runs masking-lab firmware (make -C firmware flash) and that you may "
        "open the port (Linux: the dialout group), or give serial:PORT"
    )
