"""The firmware's parameter checks and converter levels, bit for bit, for the emulator.

Every number on the wire is parsed like ``firmware/core/fixed.c`` (plain decimals into integer
micro-units, no exponents, at most 12 integer digits), every check follows
``firmware/core/commands.c`` (ERR ARGS before ERR LIMIT, the same conditions), and the
converter arithmetic follows ``firmware/core/level.c``: so the emulator, the host build and the
STM32 image give the same answer to every frame (``tests/adversarial_corpus.py``).

Levels: a channel's converter has ``bits`` bits over ±``fsv`` (peak V at the amplifier input,
no attenuation), 1 LSB = 2·fsv/2^bits. Behind ``att`` dB it plays ``amp·10^(att/20)``; the code
amplitude is that in whole LSBs (rounded half up) and the amplitude actually played is
``code·LSB/10^(att/20)``, rounded to the µV.
"""

from __future__ import annotations

import functools
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from masking_lab.core.stimulus import Channel, as_channel

ONE = 1_000_000  # micro-units per unit (µs per s, µV per V, µHz per Hz)
MAX_TRIAL_US = 60_000_000
MAX_AHEAD_VT_US = 86_400 * ONE  # TRIAL_MAX_AHEAD_VT_US of firmware/core/trial.h
MAX_INTERVALS = 9
MAX_STEPS = 4
# the reference DAC's linear range (STM32F4, buffer on: 0.2 V .. VDDA - 0.2 V) is 1798 of its
# 2048 codes each side of mid-scale: LEVEL_REF_LINEAR_CODES / LEVEL_REF_HALF_CODES in level.h
LINEAR_REF_CODES = 1798
LINEAR_REF_HALF = 2048
_QUANTISED = "quantised at this attenuation exceeds"
_PLAIN = re.compile(r"^[-+]?([0-9]*)(?:\.([0-9]*))?$")


class ArgsError(ValueError):
    """A command field the firmware answers with ``ERR ARGS``."""


class LimitError(ValueError):
    """An amplitude the firmware answers with ``ERR LIMIT``."""


# Pure in ``text``; a PLAY carries ~14 numbers and most repeat from trial to trial (carriers,
# timing, attenuation), so the emulator parses each distinct text once.
@functools.lru_cache(maxsize=4096)
def parse_micro(text: str | None) -> int | None:
    """A wire number as integer micro-units, exactly like the firmware; None if refused.

    Parameters
    ----------
    text : str or None
        ``[-+]digits[.digits]``; beyond 6 decimals rounds half away from zero.

    Returns
    -------
    int or None
        Micro-units (µs, µV, µHz), or None for anything ``fx_parse`` refuses (exponents,
        ``nan``, empty, more than 12 integer digits).

    Examples
    --------
    >>> parse_micro("1.8"), parse_micro("-0.0000005"), parse_micro("1e3"), parse_micro(".")
    (1800000, -1, None, None)
    """
    if text is None:
        return None
    m = _PLAIN.match(text)
    if not m or len(m.group(1)) > 12 or (not m.group(1) and not m.group(2)):
        return None
    whole = int(m.group(1) or "0")
    frac_digits = m.group(2) or ""
    frac = int((frac_digits[:6]).ljust(6, "0"))
    up = len(frac_digits) > 6 and frac_digits[6] >= "5"
    value = whole * ONE + frac + int(up)
    return -value if text.startswith("-") else value


def _exact_gain(att_db: int) -> int:
    return 10 ** (att_db // 20) if att_db % 20 == 0 else 0


@dataclass(frozen=True)
class Converter:
    """One channel's converter: resolution and full scale at the amplifier input.

    Attributes
    ----------
    bits : int
        Resolution, bits (2–16).
    fsv_uv : int
        Full scale, µV peak at the amplifier input with no attenuation.
    linear : int
        Largest |code| around mid-scale the output stage plays linearly (HELLO ``lin``);
        0 = the reference fraction 1798/2048 of the half range (``level_default_linear()``).

    Examples
    --------
    >>> dac = Converter(12, 10_000_000)
    >>> dac.code(1_000, 40), dac.played_uv(dac.code(1_000, 40), 40)
    (20, 977)
    >>> dac.code_limit(5_000_000, 0), dac.code_limit(5_000_000, 20), dac.lin
    (1024, 1798, 1798)
    """

    bits: int
    fsv_uv: int
    linear: int = 0

    def code(self, amp_uv: int, att_db: int) -> int:
        """Code amplitude (whole LSBs, half up) of ``amp_uv`` µV behind ``att_db`` dB."""
        g, den = _exact_gain(att_db), 2 * self.fsv_uv
        if g:
            return (2 * amp_uv * g * (1 << self.bits) + den) // (2 * den)
        x = float(amp_uv) * math.pow(10.0, att_db / 20.0) * float(1 << self.bits) / float(den)
        return math.floor(x + 0.5)

    def played_uv(self, code: int, att_db: int) -> int:
        """What a code amplitude plays at the amplifier input, µV (rounded half up)."""
        g, num = _exact_gain(att_db), code * 2 * self.fsv_uv
        if g:
            den = (1 << self.bits) * g
            return (2 * num + den) // (2 * den)
        return math.floor(num / (float(1 << self.bits) * math.pow(10.0, att_db / 20.0)) + 0.5)

    def code_limit(self, limit_uv: int, att_db: int) -> int:
        """Largest code magnitude within ``limit_uv`` that the converter can produce."""
        g, den = _exact_gain(att_db), 2 * self.fsv_uv
        if g:
            code = limit_uv * g * (1 << self.bits) // den
        else:
            code = math.floor(
                float(limit_uv) * math.pow(10.0, att_db / 20.0) * float(1 << self.bits) / den
            )
        return min(code, self.lin)

    @property
    def top(self) -> int:
        """Largest code magnitude the converter produces: 2^(bits-1) − 1."""
        return (1 << (self.bits - 1)) - 1

    @property
    def lin(self) -> int:
        """Largest code magnitude played linearly: ``linear``, or the reference fraction."""
        if 0 < self.linear <= self.top:
            return self.linear
        return (LINEAR_REF_CODES << self.bits) // (2 * LINEAR_REF_HALF)


@dataclass(frozen=True)
class Part:
    """One tone of a PLAY, checked: channel, µHz, µV, attenuator step, levels."""

    channel: Channel
    carrier_uhz: int
    envelope_uhz: int
    amp_uv: int
    att_idx: int = 0
    code: int = 0
    played_uv: int = 0


@dataclass(frozen=True)
class CheckedPlay:
    """A PLAY whose fields passed the firmware's checks (integer µs / µV / µHz)."""

    target: Part
    masker: Part | None
    ti: int
    n: int
    stim_us: int
    gap_us: int
    lead_us: int
    at_us: int


class Checker:
    """The firmware's command checks for one device configuration.

    Parameters
    ----------
    limits_uv : Mapping[str, int]
        The device's own limit per channel (``EV``, ``MV``), µV.
    converters : Mapping[str, Converter]
        Converter per channel.
    att_db : Sequence[int]
        The board's attenuator steps, dB, ascending, first 0.
    fs_hz : int
        Sample rate, Hz.

    Examples
    --------
    >>> c = Checker({"EV": 5_000_000, "MV": 10_000_000},
    ...             {ch: Converter(12, 10_000_000) for ch in ("EV", "MV")}, (0, 20, 40), 20_000)
    >>> c.level("EV", 1_000_000, 0)
    (205, 1000977)
    """

    def __init__(
        self,
        limits_uv: Mapping[str, int],
        converters: Mapping[str, Converter],
        att_db: Sequence[int],
        fs_hz: int,
    ) -> None:
        self.limits_uv = dict(limits_uv)
        self.converters = dict(converters)
        self.att_db = tuple(int(a) for a in att_db)
        self.fs_hz = int(fs_hz)

    def hello_fields(self) -> dict[str, object]:
        """HELLO's converter fields: ``bits_ev`` ``bits_mv`` ``fsv_ev`` ``fsv_mv`` ``att`` ``lin``.

        Examples
        --------
        >>> c = Checker({"EV": 1, "MV": 1}, {ch: Converter(12, 10_000_000) for ch in "EM"},
        ...             (0, 20), 1000)
        >>> c.converters = {"EV": Converter(12, 10_000_000), "MV": Converter(16, 2_500_000)}
        >>> c.hello_fields()
        {'bits_ev': 12, 'bits_mv': 16, 'fsv_ev': 10.0, 'fsv_mv': 2.5, 'att': [0, 20], \
'lin': [1798, 28768]}
        """
        ev, mv = self.converters["EV"], self.converters["MV"]
        return {
            "bits_ev": ev.bits,
            "bits_mv": mv.bits,
            "fsv_ev": ev.fsv_uv / ONE,
            "fsv_mv": mv.fsv_uv / ONE,
            "att": list(self.att_db),
            "lin": [ev.lin, mv.lin],
        }

    # ---- fields (ERR ARGS)

    @staticmethod
    def number(fields: Mapping[str, str], key: str) -> int:
        """Field ``key`` in micro-units; ArgsError if missing or not a plain decimal."""
        v = parse_micro(fields.get(key))
        if v is None:
            raise ArgsError(f"{key} is missing or not a plain decimal number")
        return v

    @staticmethod
    def channel(fields: Mapping[str, str], key: str) -> Channel:
        """Field ``key`` as ``EV``/``MV``; ArgsError otherwise."""
        ch = fields.get(key)
        if ch not in ("EV", "MV"):
            raise ArgsError(f"{key} is not EV or MV")
        return as_channel(ch, key)

    def amplitude(self, fields: Mapping[str, str], key: str) -> int:
        """An amplitude field, µV ≥ 0 (its limit is checked later)."""
        v = self.number(fields, key)
        if v < 0:
            raise ArgsError(f"{key} must be >= 0 V")
        return v

    def frequencies(self, car: int, env: int) -> None:
        """ArgsError unless 0 < carrier < fs/2 and 0 <= envelope < fs/2 (µHz)."""
        nyquist = self.fs_hz * ONE // 2
        if not (0 < car < nyquist and 0 <= env < nyquist):
            raise ArgsError("car/env out of range: frequencies must be in (0, fs/2) Hz")

    def attenuation(self, fields: Mapping[str, str], key: str) -> int:
        """Optional attenuation field: index of the board's step (default 0 dB)."""
        if key not in fields:
            return 0
        v = parse_micro(fields[key])
        if v is None:
            raise ArgsError(f"{key} is not a plain decimal number")
        for k, att in enumerate(self.att_db):
            if v == att * ONE:
                return k
        raise ArgsError(f"{key} is not one of the board's attenuation steps (HELLO att)")

    def stream(self, fields: Mapping[str, str], *, setup: bool) -> tuple[Channel, int, int, int]:
        """SETUP (``setup``) or AMP fields: (channel, carrier µHz, envelope µHz, amp µV)."""
        ch = self.channel(fields, "ch")
        car = env = 0
        if setup:
            car, env = self.number(fields, "car"), self.number(fields, "env")
        amp = self.amplitude(fields, "amp")
        if setup:
            self.frequencies(car, env)
        return ch, car, env, amp

    def play(
        self, fields: Mapping[str, str], now_us: int, virtual_time: bool = False
    ) -> CheckedPlay:
        """A PLAY's fields checked like ``parse_plan()``; ArgsError if one is bad."""
        tch = self.channel(fields, "tch")
        target = Part(tch, self.number(fields, "tcar"), self.number(fields, "tenv"), 0)
        target = Part(tch, target.carrier_uhz, target.envelope_uhz, self.amplitude(fields, "tamp"))
        self.frequencies(target.carrier_uhz, target.envelope_uhz)
        masker = None
        if fields.get("mch", "-") != "-":
            mch = self.channel(fields, "mch")
            car, env = self.number(fields, "mcar"), self.number(fields, "menv")
            self.frequencies(car, env)
            masker = Part(mch, car, env, self.amplitude(fields, "mamp"))
        n = int(self.number(fields, "n") / ONE)  # C integer division truncates toward 0
        ti = int(self.number(fields, "ti") / ONE)
        if not 1 <= ti <= n <= MAX_INTERVALS:
            raise ArgsError("ti/n out of range: need 1 <= ti <= n <= 9")
        stim = self.number(fields, "stim")
        gap, lead = self.number(fields, "gap"), self.number(fields, "lead")
        if not 0 < stim <= MAX_TRIAL_US or not 0 <= gap <= MAX_TRIAL_US:
            raise ArgsError("stim/gap out of range")
        if not 0 <= lead <= MAX_TRIAL_US:
            raise ArgsError("lead out of range")
        if lead + n * stim + (n - 1) * gap > MAX_TRIAL_US:
            raise ArgsError("durations: need lead + n*stim + (n-1)*gap <= 60 s")
        at = self.number(fields, "at")
        # real time: no trial armed more than 60 s ahead; virtual time: the clock moves only at
        # PLAY, so the participant's responses and breaks since the last trial lie in between
        if virtual_time and not 0 <= at <= now_us + MAX_AHEAD_VT_US:
            raise ArgsError("at out of range: need 0 <= at <= device time + 1 day")
        if not virtual_time and not 0 <= at <= now_us + MAX_TRIAL_US:
            raise ArgsError("at out of range: need 0 <= at <= device time + 60 s")
        target = _with_att(target, self.attenuation(fields, "tatt"))
        if masker is not None:
            masker = _with_att(masker, self.attenuation(fields, "matt"))
            if masker.channel == target.channel and masker.att_idx != target.att_idx:
                raise ArgsError("matt must equal tatt when target and masker share a channel")
        return CheckedPlay(target, masker, ti, n, stim, gap, lead, at)

    # ---- levels (ERR LIMIT)

    def level(self, ch: str, amp_uv: int, att_idx: int) -> tuple[int, int]:
        """(code, played µV) of one stream amplitude; LimitError if not playable."""
        limit = self.limits_uv[ch]
        if amp_uv > limit:
            raise LimitError(_limit_text(ch, amp_uv, limit, "exceeds"))
        cv, att = self.converters[ch], self.att_db[att_idx]
        code = cv.code(amp_uv, att)
        played = cv.played_uv(code, att)
        if played > limit:
            raise LimitError(
                _limit_text(ch, amp_uv, limit, "quantised at this attenuation exceeds")
            )
        if code > cv.lin:
            raise LimitError(linear_text(ch, amp_uv, att, cv))
        return code, played

    def play_levels(self, play: CheckedPlay) -> CheckedPlay:
        """Quantise both parts and check each channel's sum like ``plan_levels()``."""
        asked = {"EV": 0, "MV": 0}
        code = {"EV": 0, "MV": 0}
        played = {"EV": 0, "MV": 0}
        att_idx = {"EV": 0, "MV": 0}
        parts: list[Part | None] = []
        for part in (play.target, play.masker):
            if part is None:
                parts.append(None)
                continue
            asked[part.channel] += part.amp_uv
            att_idx[part.channel] = part.att_idx
            if part.amp_uv > self.limits_uv[part.channel]:
                parts.append(part)
                continue
            cv, att = self.converters[part.channel], self.att_db[part.att_idx]
            c = cv.code(part.amp_uv, att)
            p = cv.played_uv(c, att)
            code[part.channel] += c
            played[part.channel] += p
            parts.append(Part(**{**part.__dict__, "code": c, "played_uv": p}))
        for ch in ("EV", "MV"):
            limit = self.limits_uv[ch]
            if asked[ch] > limit:
                raise LimitError(_limit_text(ch, asked[ch], limit, "exceeds"))
            if played[ch] > limit:
                raise LimitError(_limit_text(ch, asked[ch], limit, _QUANTISED))
            if code[ch] > self.converters[ch].lin:  # parts on one channel share its step
                att = self.att_db[att_idx[ch]]
                raise LimitError(linear_text(ch, asked[ch], att, self.converters[ch]))
        target, masker = parts
        assert target is not None
        return CheckedPlay(target, masker, *_rest(play))


def _with_att(part: Part, att_idx: int) -> Part:
    return Part(part.channel, part.carrier_uhz, part.envelope_uhz, part.amp_uv, att_idx)


def _rest(play: CheckedPlay) -> tuple[int, int, int, int, int, int]:
    return (play.ti, play.n, play.stim_us, play.gap_us, play.lead_us, play.at_us)


def _limit_text(ch: str, amp_uv: int, limit_uv: int, what: str) -> str:
    return f"{ch} amplitude {amp_uv / ONE:g} V {what} the {limit_uv / ONE:g} V limit"


def linear_text(ch: str, amp_uv: int, att_db: int, cv: Converter) -> str:
    """ERR LIMIT's text for a level beyond the output's linear range, as the firmware words it.

    Examples
    --------
    >>> linear_text("MV", 90_000, 40, Converter(12, 10_000_000))
    "MV amplitude 0.09 V at 40 dB exceeds the output's linear range of 1798 codes (0.087793 V)"
    """
    top_v = fmt_micro(cv.played_uv(cv.lin, att_db))
    return (
        f"{ch} amplitude {fmt_micro(amp_uv)} V at {att_db} dB exceeds the output's linear "
        f"range of {cv.lin} codes ({top_v} V)"
    )


def fmt_micro(value: int) -> str:
    """Integer micro-units as the firmware's shortest plain decimal (``fx_format``).

    Examples
    --------
    >>> fmt_micro(87_793), fmt_micro(8_000_000), fmt_micro(-5)
    ('0.087793', '8', '-0.000005')
    """
    sign = "-" if value < 0 else ""
    whole, frac = divmod(abs(value), ONE)
    text = f"{whole}.{frac:06d}".rstrip("0").rstrip(".")
    return sign + text
