"""The firmware Makefile: rig variables, CPU flags that survive them, the build hash, the
vector tables of the images, the verified flash recipe, and an image built with custom limits
answering HELLO with them under QEMU.

Images are built into a temporary BUILD directory, so the shared firmware/build/ is untouched.
Without make/gcc/arm-none-eabi-gcc/qemu-system-arm these tests skip locally and fail under CI.
"""

from __future__ import annotations

import hashlib
import re
import shutil
import struct
import subprocess
from pathlib import Path

import pytest
from firmware_board_support import FIRMWARE, QemuBoard, require_tools

CUSTOM = {
    "LIMIT_EV_UV": "1234567",
    "LIMIT_MV_UV": "7654321",
    "WATCHDOG_MS": "321",
    "SERIAL_NUMBER": "RIG-42",
    "FSV_EV_UV": "8000000",
    "ATT_STEPS_DB": "0,20,40",
}


def make(*args: str, cwd: Path = FIRMWARE, check: bool = True) -> subprocess.CompletedProcess:
    proc = subprocess.run(
        ["make", "--no-print-directory", "-C", str(cwd), *args],
        capture_output=True,
        text=True,
        timeout=600,
    )
    if check and proc.returncode != 0:
        pytest.fail(f"make {' '.join(args)} failed:\n{proc.stdout}\n{proc.stderr}")
    return proc


def build_hash(firmware: Path, board_dir: str) -> str:
    """The documented FW_BUILD recipe, independently: sha256 over the sorted files' bytes."""
    names = [
        p.relative_to(firmware).as_posix()
        for pattern in ("core/*.c", "core/*.h")
        for p in firmware.glob(pattern)
    ]
    names += [
        p.relative_to(firmware).as_posix()
        for ext in ("c", "h", "ld")
        for p in (firmware / board_dir).glob(f"*.{ext}")
    ]
    digest = hashlib.sha256(b"".join((firmware / n).read_bytes() for n in sorted(names)))
    return digest.hexdigest()[:12]


@pytest.fixture(scope="module")
def custom_qemu(tmp_path_factory) -> Path:
    require_tools("make", "arm-none-eabi-gcc", "qemu-system-arm")
    build = tmp_path_factory.mktemp("fw-custom")
    make(f"BUILD={build}", "-j2", "qemu", *(f"{k}={v}" for k, v in CUSTOM.items()))
    return build / "qemu" / "masking-fw.elf"


def test_rig_variables_keep_the_cpu_and_fpu_flags(tmp_path):
    require_tools("make")
    # The old README recipe (ARM_FLAGS+=...) and the new variables both keep -mcpu/-mfpu.
    for extra in (["ARM_FLAGS+=-DRIG_TEST=1"], [f"{k}={v}" for k, v in CUSTOM.items()]):
        out = make("-n", "-B", f"BUILD={tmp_path}", "stm32", "qemu", *extra).stdout
        out = out.replace("\\\n", " ")  # one line per command
        compiles = [line for line in out.splitlines() if "arm-none-eabi-gcc" in line]
        assert len(compiles) == 2, out
        for line in compiles:
            for flag in ("-mcpu=cortex-m4", "-mthumb", "-mfpu=fpv4-sp-d16", "-mfloat-abi=hard"):
                assert flag in line
            if extra[0].startswith("ARM_FLAGS"):
                assert "-DRIG_TEST=1" in line
            else:
                assert "-DLIMIT_EV_UV=1234567LL" in line and "-DLIMIT_MV_UV=7654321LL" in line
                assert "-DWATCHDOG_MS=321u" in line and "-DSERIAL_NUMBER='\"RIG-42\"'" in line


@pytest.mark.parametrize(
    ("setting", "named"),
    [
        ("LIMIT_EV_UV=5V", "LIMIT_EV_UV must be a positive whole number"),
        ("LIMIT_MV_UV=-1", "LIMIT_MV_UV must be a positive whole number"),
        ("WATCHDOG_MS=", "WATCHDOG_MS must be a positive whole number"),
        ("SERIAL_NUMBER=two words", "SERIAL_NUMBER must be 1-24 characters"),
        ("ATT_STEPS_DB=0,40,20", "ATT_STEPS_DB must be 1-4 ascending"),
        ("ATT_STEPS_DB=20,40", "ATT_STEPS_DB must be 1-4 ascending"),
        # the old recipe for limits now says what to do instead of redefining them
        ("ARM_FLAGS+=-DLIMIT_EV_UV=1000000", "make LIMIT_EV_UV=..."),
        ("EXTRA_CFLAGS=-DSERIAL_NUMBER=x", "make SERIAL_NUMBER=..."),
    ],
)
def test_a_bad_rig_variable_is_refused_by_name(setting, named, tmp_path):
    require_tools("make")
    proc = make("-n", f"BUILD={tmp_path}", "stm32", setting, check=False)
    assert proc.returncode != 0
    assert named in proc.stderr


@pytest.mark.parametrize(
    ("settings", "too_high"),
    [
        # the old default: 10 V on a 10 V stage, whose linear range ends at 8.779 V
        (["LIMIT_MV_UV=10000000"], True),
        (["LIMIT_MV_UV=8779296"], False),
        # a 12 V stage: 1798 of 2048 codes are linear, 10.535 V
        (["FSV_MV_UV=12000000", "LIMIT_MV_UV=10600000"], True),
        (["FSV_MV_UV=12000000", "LIMIT_MV_UV=10535000"], False),
    ],
)
def test_a_limit_beyond_the_dac_linear_range_does_not_build(settings, too_high, tmp_path):
    require_tools("make", "arm-none-eabi-gcc")
    proc = make(f"BUILD={tmp_path}", "stm32", *settings, check=False)
    assert (proc.returncode != 0) == too_high, proc.stderr
    if too_high:
        assert "LIMIT_MV_UV exceeds the linear range of the MV output" in proc.stderr


def test_the_build_hash_follows_the_documented_recipe_and_the_sources(tmp_path):
    require_tools("make", "sha256sum")
    ids = dict(line.split() for line in make("build-id").stdout.splitlines())
    assert ids["host"] == build_hash(FIRMWARE, "host")
    assert ids["stm32"] == ids["qemu"] == build_hash(FIRMWARE, "stm32")
    assert ids["host"] != ids["stm32"]
    # ... and is what every image is compiled with
    out = make("-n", "-B", f"BUILD={tmp_path}", "host", "stm32", "qemu").stdout
    out = out.replace("\\\n", " ")
    builds = re.findall(r"-DFW_BUILD='\"([0-9a-f]+)\"'", out)
    assert builds == [ids["host"], ids["stm32"], ids["qemu"]]
    # One byte more in a core file is another build.
    copy = tmp_path / "firmware"
    shutil.copytree(FIRMWARE, copy, ignore=shutil.ignore_patterns("build"))
    with open(copy / "core" / "fw.c", "a") as f:
        f.write("\n")
    changed = dict(line.split() for line in make("build-id", cwd=copy).stdout.splitlines())
    assert changed["stm32"] == build_hash(copy, "stm32") != ids["stm32"]


def test_every_image_carries_its_build_hash(custom_qemu):
    ids = dict(line.split() for line in make("build-id").stdout.splitlines())
    image = custom_qemu.read_bytes()
    assert f"masking-fw build={ids['qemu']} sn=RIG-42 att=0,20,40".encode() in image


def _vectors(elf: Path, tmp: Path) -> list[int]:
    out = tmp / "vectors.bin"
    subprocess.run(
        ["arm-none-eabi-objcopy", "-O", "binary", "-j", ".isr_vector", str(elf), str(out)],
        check=True,
    )
    data = out.read_bytes()
    return list(struct.unpack(f"<{len(data) // 4}I", data))


@pytest.mark.parametrize(("board", "irqs"), [("stm32", 97), ("qemu", 82)])
def test_the_vector_table_has_every_interrupt_of_the_part(board, irqs, tmp_path):
    require_tools("make", "arm-none-eabi-gcc", "arm-none-eabi-objcopy")
    make(f"BUILD={tmp_path}", "-j2", board)
    vectors = _vectors(tmp_path / board / "masking-fw.elf", tmp_path)
    # RM0390 (F446): 16 system entries + IRQ 0..96 (FMPI2C1 error); RM0090 (F405): 0..81.
    assert len(vectors) == 16 + irqs
    assert vectors[0] == 0x20020000  # initial stack: top of the 128 KiB SRAM
    # Every handler is a Thumb address inside flash: no null vector anywhere.
    for i, v in enumerate(vectors[1:], start=1):
        assert v & 1 and 0x08000000 <= v < 0x08100000, f"vector {i} = {v:#x}"


def test_make_flash_writes_reads_back_compares_and_only_then_resets(tmp_path):
    require_tools("make")
    out = make("-n", f"BUILD={tmp_path}", "flash").stdout.splitlines()
    steps = [line for line in out if line.startswith(("st-flash", "cmp"))]
    assert re.match(r"st-flash +write \S+/stm32/masking-fw\.bin 0x08000000$", steps[0])
    assert re.match(r"st-flash +read \S+/readback\.bin 0x08000000 \$\(wc -c < \S+\)$", steps[1])
    assert re.match(r"cmp \S+/masking-fw\.bin \S+/readback\.bin$", steps[2])
    assert re.match(r"st-flash +reset$", steps[3])
    assert len(steps) == 4
    openocd = make("-n", f"BUILD={tmp_path}", "flash-openocd").stdout
    assert re.search(r'-c "program \S+/stm32/masking-fw\.elf verify reset exit"', openocd)


def test_an_image_built_with_rig_limits_reports_them_in_hello(custom_qemu):
    with QemuBoard(custom_qemu) as board:
        hello = board.call("HELLO")
    assert hello["max_ev"] == "1.234567" and hello["max_mv"] == "7.654321"
    assert hello["wd_ms"] == "321" and hello["sn"] == "RIG-42"
    if int(hello["proto"]) >= 2:  # the v2 core (fw-core) reports the converter and build too
        ids = dict(line.split() for line in make("build-id").stdout.splitlines())
        assert hello["build"] == ids["qemu"]
        assert (hello["fsv_ev"], hello["fsv_mv"]) == ("8", "10")
        assert (hello["bits_ev"], hello["bits_mv"], hello["att"]) == ("12", "12", "0,20,40")


PLAY = {
    "tch": "EV",
    "tcar": 270.0,
    "tenv": 0.0,
    "ti": 1,
    "mch": "-",
    "mcar": 0.0,
    "menv": 0.0,
    "mamp": 0.0,
    "stim": 0.05,
    "gap": 0.03,
    "lead": 0.02,
    "n": 1,
}


def test_a_code_beyond_the_dac_linear_range_is_refused_before_it_plays(custom_qemu):
    """EV: full scale 8 V, limit 1.234567 V, steps 0/20/40 dB. At 20 dB the voltage limit
    allows the converter's 2047 codes, the DAC buffer's linear range only 1798 (0.702344 V
    here): 0.70 V plays, 0.75 V is refused at PLAY (ERR LIMIT naming the level and the range)
    and nothing reaches the output stage: the board's own clamp counter stays 0."""
    with QemuBoard(custom_qemu) as board:
        hello = board.call("HELLO")
        assert hello["lin"] == "1798,1798"
        t = float(board.call("TIME")["t"])
        board.call("PLAY", at=round(t + 0.2, 6), tamp=0.70, tatt=20, **PLAY)
        done = board.event("DONE")
        assert float(done.fields["tamp"]) == pytest.approx(0.7, abs=2 * 8 / 4096 / 10)
        t = float(board.call("TIME")["t"])
        err = board.answer("PLAY", at=round(t + 0.2, 6), tamp=0.75, tatt=20, **PLAY)
        assert (err.name, err.code) == ("ERR", "LIMIT")
        assert err.text == (
            "EV amplitude 0.75 V at 20 dB exceeds the output's linear range of 1798 codes "
            "(0.702344 V)"
        )
        diag = board.call("DIAG")
        assert (float(diag["dac_ev"]), float(diag["dac_mv"]), diag["playing"]) == (0, 0, "0")
        assert board.symbol_word("dac_clamped") == 0
        assert not [e for e in board.events if e.name == "FAULT"]
