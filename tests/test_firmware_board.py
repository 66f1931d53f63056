"""The STM32 board layer: its pure logic compiled on the host, and the QEMU image.

firmware/stm32/board_logic.c (reset-cause decoding, interlock debounce, DAC codes, PLL and DMA
register values, attenuator steps) is built as a shared library with gcc and called through
ctypes: the register-level facts QEMU does not model (RCC_CSR flags, HSE, IWDG, debounce
timing, DAC buffer range) are checked there. The QEMU image then shows the board functions
working on the emulated STM32F405: TIM2 as the free-running 1 MHz device clock, a device
clock that never steps back, and the deterministic
reset cause and clock source QEMU's missing RCC model gives (registers and RAM read through the
QEMU monitor while the machine is paused).
"""

from __future__ import annotations

import ctypes
import itertools
import math
import subprocess
import time

import pytest
from firmware_board_support import FIRMWARE, QemuBoard, require_tools

POR, BOR, PIN, SFT, IWDG, WWDG, LPWR = (1 << b for b in (27, 25, 26, 28, 29, 30, 31))


@pytest.fixture(scope="module")
def logic(tmp_path_factory):
    require_tools("gcc")
    lib = tmp_path_factory.mktemp("board-logic") / "board_logic.so"
    subprocess.run(
        [
            *("gcc", "-std=c11", "-Wall", "-Wextra", "-Werror", "-O2", "-shared", "-fPIC"),
            *("-o", str(lib), str(FIRMWARE / "stm32" / "board_logic.c"), "-lm"),
        ],
        check=True,
    )
    so = ctypes.CDLL(str(lib))
    so.reset_cause_word.restype = ctypes.c_char_p
    so.reset_cause_word.argtypes = [ctypes.c_uint32]
    so.debounce_init.argtypes = [ctypes.c_void_p, ctypes.c_bool, ctypes.c_uint32]
    so.debounce_step.argtypes = [ctypes.c_void_p, ctypes.c_bool] + [ctypes.c_uint32] * 3
    so.debounce_step.restype = ctypes.c_bool
    so.dac_code.argtypes = [ctypes.c_float, ctypes.c_float, ctypes.POINTER(ctypes.c_bool)]
    so.dac_code.restype = ctypes.c_uint32
    so.dac_linear_max_uv.argtypes = [ctypes.c_int64]
    so.dac_linear_max_uv.restype = ctypes.c_int64
    so.pll_cfgr_168mhz.argtypes = [ctypes.c_uint32, ctypes.c_bool]
    so.pll_cfgr_168mhz.restype = ctypes.c_uint32
    so.dma_stream_flag_mask.argtypes = [ctypes.c_uint, ctypes.POINTER(ctypes.c_uint)]
    so.dma_stream_flag_mask.restype = ctypes.c_uint32
    so.att_parse.argtypes = [ctypes.c_char_p, ctypes.POINTER(ctypes.c_uint8)]
    so.att_parse.restype = ctypes.c_uint
    so.att_line_code.argtypes = [ctypes.c_uint, ctypes.c_uint]
    so.att_line_code.restype = ctypes.c_uint32
    return so


@pytest.mark.parametrize(
    ("flags", "word"),
    [
        (POR | BOR | PIN, "power"),  # power-on sets BOR and pulses NRST too
        (BOR | PIN, "brownout"),
        (IWDG | PIN, "watchdog"),  # every internal reset also drives NRST
        (WWDG | PIN, "watchdog"),
        (IWDG | POR | BOR | PIN, "watchdog"),
        (SFT | PIN, "software"),
        (PIN, "pin"),
        (LPWR | PIN, "unknown"),
        (0, "unknown"),  # QEMU: RCC not modelled, reads 0
        (1 << 0 | 1 << 1, "unknown"),  # LSION/LSIRDY are not reset flags
    ],
)
def test_reset_cause_from_rcc_csr(logic, flags, word):
    assert logic.reset_cause_word(flags).decode() == word


class Debounce(ctypes.Structure):
    _fields_ = [
        ("stable_open", ctypes.c_bool),
        ("cand_open", ctypes.c_bool),
        ("cand_since_us", ctypes.c_uint32),
        ("cand_count", ctypes.c_uint32),
    ]


def run_debounce(logic, samples, start_us=0, open_at_start=True):
    """Feed (dt_us, raw_open) samples; the debounced state after each."""
    d = Debounce()
    now = start_us
    logic.debounce_init(ctypes.byref(d), open_at_start, now)
    states = []
    for dt, raw in samples:
        now = (now + dt) % 2**32
        states.append(logic.debounce_step(ctypes.byref(d), raw, now, 5000, 5))
    return states


def test_interlock_closes_only_after_5_ms_and_5_equal_samples(logic):
    closed_every_ms = [(1000, False)] * 8
    states = run_debounce(logic, closed_every_ms)
    # the first closed sample starts the window; 5 ms later (6th sample) it is taken
    assert states == [True] * 5 + [False] * 3


def test_a_bouncing_contact_never_changes_the_state(logic):
    bounce = [(400, i % 2 == 0) for i in range(100)]  # 40 ms of chatter
    assert run_debounce(logic, bounce, open_at_start=False) == [False] * 100
    assert run_debounce(logic, bounce, open_at_start=True) == [True] * 100


def test_too_few_samples_over_a_long_time_are_not_enough(logic):
    # 4 closed samples over 12 ms: enough time, too few samples (a stalled loop)
    assert run_debounce(logic, [(4000, False)] * 4) == [True] * 4
    assert run_debounce(logic, [(4000, False)] * 5)[-1] is False


def test_an_open_interlock_is_taken_after_the_same_debounce(logic):
    states = run_debounce(logic, [(1000, True)] * 7, open_at_start=False)
    assert states == [False] * 5 + [True] * 2


def test_debounce_works_across_the_32_bit_clock_wrap(logic):
    states = run_debounce(logic, [(1000, False)] * 8, start_us=2**32 - 2500)
    assert states == [True] * 5 + [False] * 3


def code(logic, v, fsv):
    clamped = ctypes.c_bool()
    c = logic.dac_code(v, fsv, ctypes.byref(clamped))
    return c, clamped.value


def test_dac_codes_stay_inside_the_buffer_linear_range(logic):
    # VDDA 3.3 V, V = VDDA * code / 4095: 0.2 V is code 248.2, VDDA - 0.2 V is 3846.8
    lo, hi = 2048 - 1798, 2048 + 1798
    assert 3.3 * lo / 4095 >= 0.2 and 3.3 * hi / 4095 <= 3.3 - 0.2
    fsv = 12.0
    lsb = 2 * fsv / 4096  # the protocol's LSB at the amplifier input
    assert code(logic, 0.0, fsv) == (2048, False)
    assert code(logic, lsb, fsv) == (2049, False)
    assert code(logic, -lsb, fsv) == (2047, False)
    assert code(logic, 1798 * lsb, fsv) == (hi, False)
    assert code(logic, -1798 * lsb, fsv) == (lo, False)
    assert code(logic, 1799 * lsb, fsv) == (hi, True)  # flagged, never beyond the range
    assert code(logic, -fsv, fsv) == (lo, True)
    assert code(logic, math.nan, fsv) == (2048, True)
    assert code(logic, math.inf, fsv) == (hi, True)


def test_the_linear_range_of_a_full_scale(logic):
    # a 10 V stage (the default): 8.779 V linear, so the MV limit is 8.7 V, not 10 V
    assert logic.dac_linear_max_uv(10_000_000) == 8_779_296
    assert logic.dac_linear_max_uv(12_000_000) == 10_535_156  # 10 V needs a 12 V stage


@pytest.mark.parametrize(("in_hz", "hse", "m"), [(8_000_000, True, 4), (16_000_000, False, 8)])
def test_pll_input_is_2_mhz_and_sysclk_168_mhz(logic, in_hz, hse, m):
    cfgr = logic.pll_cfgr_168mhz(in_hz, hse)
    pllm, plln = cfgr & 0x3F, (cfgr >> 6) & 0x1FF
    pllp = 2 * (((cfgr >> 16) & 3) + 1)
    assert pllm == m and in_hz / pllm == 2_000_000  # RM0390: 1-2 MHz, 2 MHz recommended
    vco = in_hz / pllm * plln
    assert 100e6 <= vco <= 432e6 and vco / pllp == 168e6
    assert (cfgr >> 22) & 1 == (1 if hse else 0)  # PLLSRC
    pllq, pllr = (cfgr >> 24) & 0xF, (cfgr >> 28) & 7
    assert pllq >= 2 and pllr >= 2 and vco / pllq <= 48e6  # valid even though unused


@pytest.mark.parametrize("in_hz", [7_000_000, 3_000_000, 50_000_000, 0])
def test_pll_refuses_an_input_it_cannot_divide_to_2_mhz(logic, in_hz):
    assert logic.pll_cfgr_168mhz(in_hz, True) == 0


def test_dma_flags_of_each_stream(logic):
    high = ctypes.c_uint()
    # stream 5 (DAC1 request): HIFCR bits 6, 8, 9, 10, 11 (FEIF5 DMEIF5 TEIF5 HTIF5 TCIF5)
    assert logic.dma_stream_flag_mask(5, ctypes.byref(high)) == 0xF40 and high.value == 1
    masks = {0: 0, 1: 0}
    for stream in range(8):
        m = logic.dma_stream_flag_mask(stream, ctypes.byref(high))
        assert bin(m).count("1") == 5 and masks[high.value] & m == 0
        masks[high.value] |= m
    assert masks == {0: 0x0F7D0F7D, 1: 0x0F7D0F7D}
    assert logic.dma_stream_flag_mask(8, ctypes.byref(high)) == 0


@pytest.mark.parametrize(
    ("text", "steps"),
    [
        ("0", [0]),
        ("0,20", [0, 20]),
        ("0,20,40", [0, 20, 40]),
        ("0,6,12,18", [0, 6, 12, 18]),
        ("", []),
        ("20,40", []),
        ("0,40,20", []),
        ("0,20,20", []),
        ("0,1,2,3,4", []),
        ("0,,20", []),
        ("0;20", []),
        ("0,999", []),
    ],
)
def test_attenuator_step_lists(logic, text, steps):
    buf = (ctypes.c_uint8 * 4)()
    n = logic.att_parse(text.encode(), buf)
    assert list(buf)[:n] == steps


def test_attenuator_lines_rest_on_the_largest_attenuation(logic):
    # 0/20/40 dB on lines A (bit 0) and B (bit 1): all low = 40 dB, the reset state
    assert [logic.att_line_code(k, 3) for k in range(3)] == [2, 1, 0]
    assert [logic.att_line_code(k, 2) for k in range(2)] == [1, 0]
    assert logic.att_line_code(0, 1) == 0
    assert logic.att_line_code(3, 3) == 0  # an invalid step selects the largest too


# --- the QEMU image -----------------------------------------------------------------------


@pytest.fixture(scope="module")
def qemu_board(tmp_path_factory):
    require_tools("make", "arm-none-eabi-gcc", "qemu-system-arm")
    build = tmp_path_factory.mktemp("fw-board")
    proc = subprocess.run(
        ["make", "-C", str(FIRMWARE), f"BUILD={build}", "-j2", "qemu"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    with QemuBoard(build / "qemu" / "masking-fw.elf") as board:
        yield board


TIM2_CR1, TIM2_CNT, TIM2_PSC, TIM2_ARR = 0x40000000, 0x40000024, 0x40000028, 0x4000002C


def test_the_device_clock_is_tim2(qemu_board):
    """TIME lies between two reads of TIM2_CNT taken while the machine was stopped."""
    with qemu_board.paused():
        before = qemu_board.read_word(TIM2_CNT)
    t_us = round(float(qemu_board.call("TIME")["t"]) * 1e6)
    with qemu_board.paused():
        after = qemu_board.read_word(TIM2_CNT)
    assert before <= t_us % 2**32 <= after


def test_tim2_is_set_up_as_a_free_running_1_mhz_counter(qemu_board):
    """QEMU 7.2 clocks TIM2-5 at 1 GHz and computes CNT from its virtual clock
    (hw/timer/stm32f2xx_timer.c): prescaler 999 makes CNT the virtual time in µs.

    SysTick is no reference for the rate: QEMU drops its ticks (measured 4-150 % fewer than
    TIM2 under -icount auto, exactly half under shift=4,sleep=off), which is why the device
    clock no longer counts them.
    """
    with qemu_board.paused():
        psc, arr = qemu_board.read_word(TIM2_PSC), qemu_board.read_word(TIM2_ARR)
        cr1 = qemu_board.read_word(TIM2_CR1)
    assert (psc, arr) == (999, 0xFFFFFFFF)
    assert cr1 & 0x1 and not cr1 & 0x10  # counting, upwards


def test_the_device_clock_never_steps_back(qemu_board):
    times = [float(qemu_board.call("TIME")["t"]) for _ in range(150)]
    steps = [b - a for a, b in itertools.pairwise(times)]
    assert min(steps) >= 0
    assert times[-1] > times[0]


def test_qemu_reports_its_reset_cause_and_the_hsi_fallback(qemu_board):
    # QEMU's RCC is an unimplemented device: RCC_CSR reads 0 (no flag: "unknown") and HSERDY
    # never sets, so the real HSE probe times out and the image reports the HSI fallback.
    assert qemu_board.symbol_word("reset_csr_raw") == 0
    rst = qemu_board.read_cstring(qemu_board.symbol_word("board_reset_word"))
    clk = qemu_board.read_cstring(qemu_board.symbol_word("board_clock_word"))
    assert (rst, clk) == ("unknown", "hsi")
    hello = qemu_board.call("HELLO")
    if int(hello["proto"]) >= 2:  # the v2 core (fw-core) puts them in HELLO
        assert (hello["rst"], hello["clk"]) == ("unknown", "hsi")


def test_the_main_loop_feeds_the_modelled_iwdg(qemu_board):
    before = qemu_board.symbol_word("iwdg_feeds")
    qemu_board.call("PING")
    time.sleep(0.05)
    qemu_board.call("PING")
    assert qemu_board.symbol_word("iwdg_feeds") > before
