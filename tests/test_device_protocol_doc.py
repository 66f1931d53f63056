"""Every frame example in docs/device-protocol.md carries the right checksum and decodes."""

from __future__ import annotations

import re
from pathlib import Path

from masking_lab.device import protocol as proto

DOC = Path(__file__).resolve().parents[1] / "docs" / "device-protocol.md"
FRAME_LINE = re.compile(r"^(?:host:|device:)?\s*(\S.*)\*([0-9A-F]{4})$")


def crc_reference(data: bytes) -> int:
    """Bit-by-bit CRC-16/CCITT-FALSE, written from the algorithm's definition."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc


def _examples() -> list[tuple[str, str]]:
    found = []
    for line in DOC.read_text(encoding="utf-8").splitlines():
        m = FRAME_LINE.match(line.strip())
        if m:
            found.append((m.group(1), m.group(2)))
    return found


def test_every_checksum_example_in_the_protocol_document_is_right():
    examples = _examples()
    assert len(examples) >= 10  # the worked examples of version 2 are all there
    for body, crc in examples:
        assert f"{crc_reference(body.encode('ascii')):04X}" == crc, body
        frame = proto.decode(f"{body}*{crc}\n".encode("ascii"))
        assert frame.seq >= 0


def test_the_document_describes_version_2():
    text = DOC.read_text(encoding="utf-8")
    assert text.startswith("# Device serial protocol (version 2)")
    hello = next(b for b, _ in _examples() if " OK proto=" in b)
    assert "proto=2" in hello and "att=0,20,40" in hello and "rst=" in hello
