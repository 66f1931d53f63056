"""One adversarial frame corpus for every device implementation (issue 23, item 8).

A seeded, grammar-based generator writes checksum-valid frames with extreme values: numbers
at and just past every limit (amplitudes, Nyquist, 60 s durations, 9 intervals, attenuator
steps), 12- and 13-digit numbers, exponents, ``nan``, signs, many decimals, missing, unknown
and duplicated fields, and frame-level damage (bad sequence numbers, names, empty tokens, too
many fields, too long, non-ASCII, bad checksums). Frames come in short episodes that end with
``STOP`` so a real-time device never carries state into the next one.

:func:`run` sends the same frames to several implementations and records, per frame, the
answer (``OK``, ``ERR <CODE>`` or ``FAULT <CODE>``); any difference is a mismatch. After
every batch it reads DIAG's ``pk_ev``/``pk_mv`` (largest sample output) against the limits.
Used by ``tests/test_adversarial_corpus.py`` (CI, ≥ 5,000 frames) and
``benchmarks/fw_corpus.py`` (100,000).
"""

from __future__ import annotations

import os
import random
import time
from collections import Counter
from dataclasses import dataclass, field

import serial
from firmware_support import Link, start

from masking_lab.device import protocol as proto
from masking_lab.device.config import parse_device_config
from masking_lab.device.emulator import FirmwareEmulator

SENTINEL_SEQ = 65000  # corpus frames use 1..60000, so the batch-end PING is unmistakable
# Bytes sent before the sentinel's reply is awaited: with the sentinel PING, within the STM32
# image's 512-byte RX ring (firmware/stm32/usart.c RX_SIZE), so QEMU never drops a byte
IN_FLIGHT_BYTES = 448
HUGE = "999999999999.999999"


@dataclass(frozen=True)
class Profile:
    """What the generator aims at: one device configuration (from its HELLO)."""

    max_ev: float
    max_mv: float
    fs_hz: int
    att: tuple[str, ...]
    real_time: bool = False  # a PLAY only as an episode's last command (BUSY is timing)
    lin: int = 1798  # HELLO lin: codes played linearly each side of mid-scale
    lsb_v: float = 20.0 / 4096  # one code at 0 dB, V at the amplifier input (12 bits, ±10 V)


def linear_edge_v(p: Profile, codes: float, att_db: int) -> float:
    """The request (V, whole µV) that is ``codes`` LSBs behind ``att_db`` dB.

    Examples
    --------
    >>> p = Profile(2.5, 8.0, 1000, ("0", "20", "40"))
    >>> linear_edge_v(p, p.lin, 40), linear_edge_v(p, p.lin + 1, 40)
    (0.087793, 0.087842)
    """
    return round(codes * p.lsb_v / 10 ** (att_db / 20), 6)


def _num(x: float) -> str:
    return proto.fmt_number(x)


def _amplitude(rng: random.Random, limit: float) -> str:
    pick = rng.random()
    if pick < 0.55:
        return _num(round(rng.uniform(0, limit * 1.05), 6))
    return rng.choice(
        [
            _num(limit),
            _num(limit + 1e-6),
            _num(round(limit / 2 + 1e-6, 6)),
            "0",
            "-0",
            "-0.000001",
            "-3.9",
            "8.9",
            "0.0000004",
            "0.0000005",
            "0.0024",
            "1e-3",
            "nan",
            "inf",
            HUGE,
            "9999999999999",
            "+1",
            ".5",
            "5.",
            "0.12345678",
        ]
    )


def _frequency(rng: random.Random, fs: int) -> str:
    nyq = fs / 2
    if rng.random() < 0.6:
        return _num(round(rng.uniform(0.000001, nyq), 6))
    return rng.choice(
        [_num(nyq), _num(nyq - 1e-6), "0", "0.000001", "-270", "1e2", HUGE, "0.05", "270"]
    )


def _envelope(rng: random.Random, fs: int) -> str:
    return "0" if rng.random() < 0.4 else _frequency(rng, fs)


def _duration(rng: random.Random, long: bool = False) -> str:
    if rng.random() < 0.6:
        return _num(round(rng.uniform(0, 8.0 if long else 1.0), 6))
    return rng.choice(
        ["0", "0.000001", "60", "60.000001", "59.999999", "6.6", "6.7", "-1", HUGE, "1e1", "x"]
    )


def _count(rng: random.Random) -> str:
    return rng.choice(["1", "2", "3", "3", "9", "10", "0", "-1", "3.7", "9.999999", HUGE])


def _at(rng: random.Random) -> str:
    return rng.choice(["0", "0", "0", "-0.000001", "-1", HUGE, "1e9", "abc", "0.5"])


def _channel(rng: random.Random) -> str:
    return rng.choice(["EV", "MV", "EV", "MV", "XX", "ev", "-"])


def _att(rng: random.Random, att: tuple[str, ...]) -> str:
    return rng.choice([*att, *att, "10", "-20", "20.0", "2e1", "60", "0.0000001", "nan"])


def _valid_play(rng: random.Random, p: Profile) -> dict[str, str]:
    """A PLAY every implementation should accept (amplitudes within each channel's limit)."""
    tch, mch = rng.choice(["EV", "MV"]), rng.choice(["EV", "MV", "-"])
    nyq = p.fs_hz / 2
    limit = {"EV": p.max_ev, "MV": p.max_mv}
    share = 0.5 if mch == tch else 1.0
    f = {"tch": tch, "tcar": _num(round(rng.uniform(1, nyq * 0.9), 3))}
    f["tenv"] = rng.choice(["0", _num(round(rng.uniform(0.01, 50), 3))])
    f["tamp"] = _num(round(rng.uniform(0, limit[tch] * share * 0.99), 6))
    n = rng.randint(1, 9)
    f.update(ti=str(rng.randint(1, n)), n=str(n), mch=mch)
    if mch != "-":
        f.update(mcar=_num(round(rng.uniform(1, nyq * 0.9), 3)), menv="0")
        f["mamp"] = _num(round(rng.uniform(0, limit[mch] * share * 0.99), 6))
    stim = rng.uniform(0.001, 60 / n * 0.8)
    rest = (60 - n * stim) * 0.9
    f.update(stim=_num(round(stim, 6)), gap=_num(round(rest / max(1, n) * rng.random(), 6)))
    f.update(lead=_num(round(rest / 10 * rng.random(), 6)), at="0")
    if rng.random() < 0.3:
        f["tatt"] = rng.choice(p.att)
        if mch == tch:
            f["matt"] = f["tatt"]
    return f


def linear_edge_frames(eps: list[list[bytes]], p: Profile) -> int:
    """How many frames of ``eps`` are PLAYs whose target sits at the linear range's edge
    (the codes of :func:`_linear_play`, alone, at a deep step)."""
    edges = {
        (_num(linear_edge_v(p, p.lin + d, int(a))), a)
        for a in p.att
        for d in (-1, 0, 1, 0.49, 0.51, -0.51)
    }
    n = 0
    for fr in (f for ep in eps for f in ep):
        if b" PLAY " not in fr:
            continue
        fields = dict(
            t.split("=", 1) for t in fr.decode("latin-1").split("*")[0].split()[2:] if "=" in t
        )
        n += (fields.get("tamp"), fields.get("tatt")) in edges
    return n


def _linear_play(rng: random.Random, p: Profile) -> dict[str, str]:
    """A valid PLAY at, one code below or above the linear range (or half an LSB around its
    edge), mostly at the deepest attenuator steps; sometimes target and masker share the
    channel and split the codes."""
    f = _valid_play(rng, p)
    att = int(rng.choice([p.att[-1], p.att[-1], p.att[-2] if len(p.att) > 1 else p.att[0]]))
    codes = p.lin + rng.choice([-1, 0, 0, 1, 1, 0.49, 0.51, -0.51])
    f.update(tatt=str(att), mch="-")
    f.pop("matt", None)
    if rng.random() < 0.3:  # target + masker on one channel: their codes add up
        part = rng.randint(1, int(codes) - 1)
        f.update(mch=f["tch"], mcar="120", menv="0", matt=str(att))
        f["mamp"] = _num(linear_edge_v(p, codes - part, att))
        codes = part
    f["tamp"] = _num(linear_edge_v(p, codes, att))
    return f


def _play_fields(rng: random.Random, p: Profile) -> dict[str, str]:
    f = _valid_play(rng, p)
    extreme = _extreme_play(rng, p)
    for key in rng.sample(sorted(extreme), rng.choice([0, 0, 1, 1, 2, 3, len(extreme)])):
        f[key] = extreme[key]
    if f.get("mch") == "-":
        for key in ("mcar", "menv", "mamp"):
            if rng.random() < 0.5:
                f.pop(key, None)
    return f


def _extreme_play(rng: random.Random, p: Profile) -> dict[str, str]:
    tch = _channel(rng)
    f = {"tch": tch, "tcar": _frequency(rng, p.fs_hz), "tenv": _envelope(rng, p.fs_hz)}
    f["tamp"] = _amplitude(rng, p.max_ev if tch == "EV" else p.max_mv)
    n = _count(rng)
    f["ti"] = rng.choice(["1", n, "2", "0", "10"])
    if rng.random() < 0.75:
        mch = rng.choice(["EV", "MV", tch])
        f.update(mch=mch, mcar=_frequency(rng, p.fs_hz), menv=_envelope(rng, p.fs_hz))
        f["mamp"] = _amplitude(rng, p.max_ev if mch == "EV" else p.max_mv)
    else:
        f["mch"] = "-"
    f.update(stim=_duration(rng, True), gap=_duration(rng), lead=_duration(rng), n=n)
    f["at"] = _at(rng)
    if rng.random() < 0.4:
        f["tatt"] = _att(rng, p.att)
    if rng.random() < 0.3:
        f["matt"] = _att(rng, p.att)
    return f


def _command(rng: random.Random, p: Profile) -> tuple[str, dict[str, str]]:
    kind = rng.random()
    if kind < 0.06:
        return "PLAY", _linear_play(rng, p)
    if kind < 0.45:
        return "PLAY", _play_fields(rng, p)
    if kind < 0.65:
        ch = _channel(rng)
        limit = p.max_ev if ch == "EV" else p.max_mv
        f = {"ch": ch, "car": _frequency(rng, p.fs_hz), "env": _envelope(rng, p.fs_hz)}
        return "SETUP", {**f, "amp": _amplitude(rng, limit)}
    if kind < 0.78:
        ch = _channel(rng)
        return "AMP", {"ch": ch, "amp": _amplitude(rng, p.max_ev if ch == "EV" else p.max_mv)}
    return rng.choice(["HELLO", "TIME", "PING", "DIAG", "STOP", "BLINK", "PLAYX"]), {}


def _mutate_fields(rng: random.Random, fields: dict[str, str]) -> list[tuple[str, str]]:
    items = list(fields.items())
    r = rng.random()
    if r < 0.06 and items:
        items.pop(rng.randrange(len(items)))  # a missing field
    elif r < 0.10:
        items.append((rng.choice(["x", "zz9", "at_", "tamp2"]), "1"))  # an unknown field
    elif r < 0.12 and items:
        items.append((items[0][0], items[0][1]))  # a duplicated key: garbage
    if rng.random() < 0.3:
        rng.shuffle(items)
    return items


def _frame(body: str) -> bytes:
    data = body.encode("latin-1")
    return data + b"*%04X\n" % proto.crc16(data)


def _damaged(rng: random.Random, seq: int, name: str, items: list[tuple[str, str]]) -> bytes:
    fields = "".join(f" {k}={v}" for k, v in items)
    choice = rng.randrange(10)
    if choice == 0:
        return _frame(f"{seq} {name.lower()}{fields}")
    if choice == 1:
        return _frame(f"0{seq} {name}{fields}")
    if choice == 2:
        return _frame(f"{rng.choice(['70000', '65536', '-1', 'x'])} {name}{fields}")
    if choice == 3:
        return _frame(f"!{seq} {name}{fields}")
    if choice == 4:
        return _frame(f"{seq} {rng.choice(['OK', 'ERR LIMIT x'])}")
    if choice == 5:
        return _frame(f"{seq} {name} {fields}")  # an empty token
    if choice == 6:
        return _frame(f"{seq} {name}" + "".join(f" f{i}=1" for i in range(25)))
    if choice == 7:
        return _frame(f"{seq} {name} pad={'9' * 260}")
    if choice == 8:
        return _frame(f"{seq} {name}{fields} k=\xe9")
    good = _frame(f"{seq} {name}{fields}")
    return good[:-5] + (b"0000" if good[-5:-1] != b"0000" else b"FFFF") + b"\n"


def episodes(seed: int, frames: int, profile: Profile) -> list[list[bytes]]:
    """``frames`` frames in episodes of 1–3 commands closed by a STOP (deterministic).

    Examples
    --------
    >>> p = Profile(2.5, 8.0, 1000, ("0", "20", "40"))
    >>> eps = episodes(7, 50, p)
    >>> sum(len(e) for e in eps) >= 50, eps == episodes(7, 50, p), eps[0][-1].split(b"*")[0]
    (True, True, b'3 STOP')
    """
    rng = random.Random(seed)
    out: list[list[bytes]] = []
    seq, total = 0, 0
    while total < frames:
        ep: list[bytes] = []
        size = rng.choice([1, 1, 2, 3])
        for k in range(size):
            seq = seq % 60000 + 1
            name, fields = _command(rng, profile)
            while profile.real_time and name == "PLAY" and k < size - 1:
                name, fields = _command(rng, profile)  # a trial may end before the next
            items = _mutate_fields(rng, fields)
            if rng.random() < 0.05:
                ep.append(_damaged(rng, seq, name, items))
            else:
                ep.append(_frame(f"{seq} {name}" + "".join(f" {k}={v}" for k, v in items)))
        seq = seq % 60000 + 1
        ep.append(_frame(f"{seq} STOP"))
        out.append(ep)
        total += len(ep)
    return out


@dataclass
class Result:
    """One implementation's answers to a corpus."""

    name: str
    answers: list[str] = field(default_factory=list)
    side_events: Counter[str] = field(default_factory=Counter)
    peak_v: dict[str, float] = field(default_factory=lambda: {"EV": 0.0, "MV": 0.0})
    longest_silence_s: float = 0.0  # longest wait for a byte within one batch, s


def cpu_seconds(pid: int | None) -> float | None:
    """User + system CPU time a process has used so far, s (None if unknown or gone)."""
    if pid is None:
        return None
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rpartition(")")[2].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


class Port:
    """A raw pyserial link that sends a batch and reads its answers, in order.

    Real time is legitimate here (QEMU runs on ``-icount auto``), but a loaded machine can
    starve an implementation: the wait ends only after ``timeout`` seconds *without a byte*
    (a slow but progressing device is waited for), and the error then says what happened:
    how much of the batch was answered, whether the process is alive, and how much CPU it got
    meanwhile (little CPU: starved by the machine; CPU but no bytes: the image hung).
    """

    def __init__(self, path: str, name: str = "device", pid: int | None = None) -> None:
        self.ser = serial.Serial(path, timeout=0.05)
        self.buf = b""
        self.name, self.pid = name, pid
        self.stalls: list[float] = []  # longest silence of each batch, s (the figures)

    def _frames_until_sentinel(self, timeout: float) -> list[proto.Frame]:
        got: list[proto.Frame] = []
        last_byte = t0 = time.monotonic()
        cpu0 = cpu_seconds(self.pid)
        longest = 0.0
        while True:
            while b"\n" not in self.buf:
                now = time.monotonic()
                if now - last_byte > timeout:
                    raise TimeoutError(self._stalled(got, now - t0, now - last_byte, cpu0))
                chunk = self.ser.read(max(1, self.ser.in_waiting))
                if chunk:
                    longest = max(longest, time.monotonic() - last_byte)
                    last_byte = time.monotonic()
                self.buf += chunk
            line, _, self.buf = self.buf.partition(b"\n")
            try:
                f = proto.decode(line + b"\n")
            except proto.FrameError:
                continue  # boot chatter
            if f.kind == "reply" and f.seq == SENTINEL_SEQ:
                self.stalls.append(longest)
                return got
            got.append(f)

    def _alive(self, within: float) -> bool:
        """Does the device answer a fresh PING now (its reply seen within ``within`` s)?"""
        probe = SENTINEL_SEQ - 2
        self.ser.write(proto.encode_command(probe, "PING"))
        marker = f"{probe} OK".encode()
        deadline = time.monotonic() + within
        while time.monotonic() < deadline:
            self.buf += self.ser.read(max(1, self.ser.in_waiting))
            if marker in self.buf:
                return True
        return False

    def _stalled(self, got: list, waited: float, silent: float, cpu0: float | None) -> str:
        cpu1 = cpu_seconds(self.pid)
        if self.pid is not None and cpu1 is not None and self._alive(min(silent, 10.0)):
            state = (
                "it answers a fresh PING, so it is alive and the batch's sentinel was lost on "
                "the way (bytes dropped: device RX overflow?)"
            )
        elif self.pid is not None and cpu1 is None:
            state = "its process has exited"
        elif cpu0 is not None and cpu1 is not None:
            used = cpu1 - cpu0
            verdict = (
                "starved: the machine gave it almost no CPU"
                if used < 0.05 * silent
                else "hung: it ran but sent nothing"
            )
            state = f"it used {used:.1f} s of CPU in {waited:.1f} s ({verdict})"
        else:
            state = "no process to inspect"
        return (
            f"{self.name}: no sentinel reply after {waited:.1f} s, {silent:.1f} s without a byte "
            f"({len(got)} answers of this batch read); {state}; last bytes {self.buf[-200:]!r}"
        )

    def batch(self, frames: list[bytes], timeout: float) -> list[proto.Frame]:
        """Send frames, each chunk of at most :data:`IN_FLIGHT_BYTES` followed by a sentinel PING
        whose reply is awaited; every frame the device sent before the last sentinel's reply.

        A real link paces bytes at its baud rate, but a pty into QEMU delivers them as fast as
        the guest takes them, and the image's 512-byte RX ring then overflows while its main
        loop refills the DAC: bytes are dropped (a garbled frame, a lost sentinel). Keeping no
        more bytes in flight than the ring holds is what a host does anyway (one command at a
        time), and the same chunks go to every implementation.
        """
        got: list[proto.Frame] = []
        chunk: list[bytes] = []
        for frame in frames:
            if chunk and sum(map(len, chunk)) + len(frame) > IN_FLIGHT_BYTES:
                got += self._send(chunk, timeout)
                chunk = []
            chunk.append(frame)
        return got + self._send(chunk, timeout)

    def _send(self, frames: list[bytes], timeout: float) -> list[proto.Frame]:
        self.ser.write(b"".join(frames) + proto.encode_command(SENTINEL_SEQ, "PING"))
        return self._frames_until_sentinel(timeout)

    def diag(self, timeout: float) -> proto.Frame:
        self.ser.write(proto.encode_command(SENTINEL_SEQ - 1, "DIAG"))
        self.ser.write(proto.encode_command(SENTINEL_SEQ, "PING"))
        frames = self._frames_until_sentinel(timeout)
        return next(f for f in frames if f.kind == "reply" and f.seq == SENTINEL_SEQ - 1)

    def close(self) -> None:
        self.ser.close()


def answers_of(frames: list[proto.Frame], result: Result) -> None:
    """Append each command's answer (reply or FAULT event) in order; count other events."""
    for f in frames:
        if f.kind == "reply":
            result.answers.append("OK" if f.ok else f"ERR {f.code}")
        elif f.name == "FAULT":
            result.answers.append(f"FAULT {f.fields.get('code')}")
        else:
            result.side_events[f.name] += 1


def run(
    ports: dict[str, str],
    eps: list[list[bytes]],
    *,
    batch: int = 40,
    timeout: float = 60.0,
    pids: dict[str, int] | None = None,
) -> dict[str, Result]:
    """Send the same episodes to every port; each implementation's answers and peaks.

    ``timeout`` is the longest silence (s) tolerated from one implementation; ``pids`` (name
    → process id) lets a stall say whether the process starved or hung.
    """
    pids = pids or {}
    links = {name: Port(path, name, pids.get(name)) for name, path in ports.items()}
    results = {name: Result(name) for name in ports}
    try:
        for i in range(0, len(eps), batch):
            frames = [fr for ep in eps[i : i + batch] for fr in ep]
            for name, link in links.items():
                answers_of(link.batch(frames, timeout), results[name])
                diag = link.diag(timeout)
                for ch, key in (("EV", "pk_ev"), ("MV", "pk_mv")):
                    pk = diag.number(key)
                    results[name].peak_v[ch] = max(results[name].peak_v[ch], pk)
    finally:
        for name, link in links.items():
            results[name].longest_silence_s = max(link.stalls, default=0.0)
            link.close()
    return results


def first_mismatch(results: dict[str, Result], eps: list[list[bytes]]) -> str | None:
    """A readable description of the first frame the implementations answer differently."""
    frames = [fr for ep in eps for fr in ep]
    names = list(results)
    ref = results[names[0]].answers
    for other in names[1:]:
        ans = results[other].answers
        for k in range(max(len(ref), len(ans))):
            a = ref[k] if k < len(ref) else "<none>"
            b = ans[k] if k < len(ans) else "<none>"
            if a != b:
                frame = frames[k] if k < len(frames) else b"?"
                return f"frame {k} {frame!r}: {names[0]} {a} / {other} {b}"
    return None


@dataclass
class CorpusRun:
    """One corpus run: what was sent, each implementation's answers, the figures."""

    frames: int
    results: dict[str, Result]
    mismatch: str | None
    stderr: str  # of the sanitizer build
    limits: tuple[float, float]
    seconds: float
    linear_frames: int = 0  # PLAYs at the linear range's edge (linear_edge_frames)


def _rig(max_ev: float, max_mv: float, fs: int, wd_s: float, ramp_s: float) -> str:
    return (
        "schema_version: 1\n"
        f"channels:\n  EV: {{max_drive_v: {max_ev}}}\n  MV: {{max_drive_v: {max_mv}}}\n"
        f"serial: {{reply_timeout_s: 0.5, watchdog_s: {wd_s}}}\n"
        f"waveform: {{sample_rate_hz: {fs}, ramp_s: {ramp_s}}}\n"
        "emulator: {model: TEST-EMU, serial_number: T-42, onset_jitter_s: 0.00005}\n"
    )


def _finish(ports, eps, limits, stop, pids, profile: Profile) -> CorpusRun:
    t0 = time.monotonic()
    try:
        results = run(ports, eps, pids=pids)
    finally:
        stderr = stop()
    n = sum(len(e) for e in eps)
    mismatch = first_mismatch(results, eps)
    seconds = time.monotonic() - t0
    return CorpusRun(
        n, results, mismatch, stderr, limits, seconds, linear_edge_frames(eps, profile)
    )


def virtual_time_run(frames: int, seed: int) -> CorpusRun:
    """Emulator vs the sanitizer host build, virtual time, every trial rendered at 1 kHz."""
    config = parse_device_config(_rig(2.5, 8, 1000, 0.3, 0.002), "corpus rig")
    host = start("host-asan", virtual_time=True, host_args=("--vt-render", "--fs", "1000"))
    emu = FirmwareEmulator(config, virtual_time=True, render_buffers=True).start()
    profile = Profile(2.5, 8.0, 1000, ("0", "20", "40"))
    eps = episodes(seed, frames, profile)

    def stop() -> str:
        emu.close()
        return host.close()

    ports = {"emulator": emu.port, "host-asan": host.port}
    return _finish(ports, eps, (2.5, 8.0), stop, {"host-asan": host.proc.pid}, profile)


def real_time_run(frames: int, seed: int, image: str = "qemu-att") -> CorpusRun:
    """QEMU vs the sanitizer host build vs the emulator, real time, configured from QEMU.

    ``image`` ``qemu-att`` (default) is the STM32 image with 0/20/40 dB attenuator steps, so
    the frames at the linear range's edge reach the deep steps; ``qemu`` the bare default.
    """
    qemu = start(image)
    link = Link(qemu.port)
    hello = link.call("HELLO")
    link.close()
    max_ev, max_mv, fs = hello.number("max_ev"), hello.number("max_mv"), int(hello.number("fs"))
    wd_ms, steps = int(hello.number("wd_ms")), tuple(hello.fields["att"].split(","))
    lin_ev, lin_mv = (int(v) for v in hello.fields["lin"].split(","))
    assert lin_ev == lin_mv, hello.fields["lin"]  # the emulator takes one value for both
    args = ["--max-ev", hello.fields["max_ev"], "--max-mv", hello.fields["max_mv"]]
    args += ["--fs", str(fs), "--wd-ms", str(wd_ms), "--att", hello.fields["att"]]
    args += ["--lin-ev", str(lin_ev), "--lin-mv", str(lin_mv)]
    host = start("host-asan", host_args=(*args, "--ramp-us", "10000"))
    config = parse_device_config(_rig(max_ev, max_mv, fs, wd_ms / 1000, 0.01), "qemu rig")
    emu = FirmwareEmulator(
        config, att_db=tuple(map(int, steps)), linear_codes=lin_ev, render_buffers=False
    ).start()
    profile = Profile(max_ev, max_mv, fs, steps, real_time=True, lin=lin_ev)
    eps = episodes(seed, frames, profile)

    def stop() -> str:
        emu.close()
        qemu.close()
        return host.close()

    ports = {"qemu": qemu.port, "host-asan": host.port, "emulator": emu.port}
    pids = {"qemu": qemu.proc.pid, "host-asan": host.proc.pid}
    return _finish(ports, eps, (max_ev, max_mv), stop, pids, profile)
