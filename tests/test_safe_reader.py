"""The shared YAML/JSON reader (``masking_lab.formats.reader``): every limit, on real files."""

from __future__ import annotations

import os

import pytest

from masking_lab.core.errors import CalibrationError, ProtocolError
from masking_lab.formats.reader import (
    MAX_BYTES,
    decode_utf8,
    excerpt,
    load_document,
    non_finite,
    parse_json,
    parse_yaml,
    read_limited,
)


def bomb(levels: int, width: int = 9) -> str:
    rows = ["a0: &a0 [" + ", ".join(['"x"'] * width) + "]"]
    rows += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * width) + "]" for i in range(1, levels)]
    return "\n".join(rows) + "\n"


def test_plain_data_with_lines():
    data, lines = parse_yaml("a: 1\nb:\n  - {c: x}\n  - 2.5\n", "f.yaml")
    assert data == {"a": 1, "b": [{"c": "x"}, 2.5]}
    assert lines["b[0].c"] == 3 and lines["b[1]"] == 4
    data, lines = parse_json('{"a": 1,\n "b": [{"c": "x"},\n 2.5]}', "f.json")
    assert data == {"a": 1, "b": [{"c": "x"}, 2.5]} and lines["b[1]"] == 3


def test_an_alias_bomb_is_refused_before_it_expands_and_small_aliases_pass():
    # Refused by counting what the aliases would expand to, never by expanding them (the
    # CLI test in test_hardening_inputs.py runs the same bomb in a subprocess with a timeout).
    with pytest.raises(ProtocolError, match="expands to more than 50000 values"):
        parse_yaml(bomb(9), "bomb.yaml")  # 9**9 ≈ 3.9e8 values
    data, _ = parse_yaml(bomb(3), "ok.yaml")  # 9**3 = 729 values
    assert len(data["a2"]) == 9


@pytest.mark.parametrize("depth", [33, 1000, 100_000])
def test_deep_nesting_is_refused(depth):
    with pytest.raises(ProtocolError, match="nested more than 32 levels deep"):
        parse_yaml("[" * depth + "]" * depth, "deep.yaml")
    with pytest.raises(ProtocolError, match="nested more than 32 levels deep"):
        parse_json("[" * depth + "]" * depth, "deep.json")


def test_32_levels_are_fine():
    assert parse_yaml("[" * 32 + "]" * 32, "ok.yaml")[0] is not None
    assert parse_json("[" * 32 + "]" * 32, "ok.json")[0] is not None


@pytest.mark.parametrize(
    ("text", "where"),
    [("a: 1\nb: 2\na: 3\n", "a (line 3)"), ("x:\n  y: 1\n  y: 1\n", "x.y (line 3)")],
)
def test_duplicate_yaml_keys_name_their_line(text, where):
    with pytest.raises(ProtocolError) as info:
        parse_yaml(text, "d.yaml")
    assert info.value.where == where and "appears twice" in info.value.message


def test_duplicate_json_keys_name_their_line():
    with pytest.raises(ProtocolError) as info:
        parse_json('{"a": {"b": 1,\n"c": 2,\n"b": 3}}', "d.json")
    assert info.value.where == "a.b (line 3)"


@pytest.mark.parametrize(
    ("text", "where"),
    [
        ("a: .nan\n", "a (line 1)"),
        ("a:\n  - 1\n  - -.inf\n", "a[1] (line 3)"),
        ("a: 1.0e+999\n", "a (line 1)"),
        ("a: " + "9" * 400 + "\n", "a (line 1)"),
    ],
)
def test_non_finite_yaml_numbers_are_refused_where_they_stand(text, where):
    with pytest.raises(ProtocolError) as info:
        parse_yaml(text, "n.yaml")
    assert info.value.where == where and "not a finite number" in info.value.message


@pytest.mark.parametrize("token", ["NaN", "Infinity", "-Infinity", "1e999"])
def test_non_finite_json_numbers_are_refused(token):
    with pytest.raises(ProtocolError, match=r"x\[1\] \(line 2\)"):
        parse_json('{"x": [1,\n' + token + "]}", "n.json")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("a: !!python/object/apply:os.system [id]\n", "is not allowed"),
        ("a: !!binary aGk=\n", "is not allowed"),
        ("a: !!set {x}\n", "is not allowed"),
        ("1: a\n", "is not text"),
        ("on: a\n", "is not text"),
        ("a: [1\n", "malformed YAML"),
        ("a: 1\nb: \x07\n", "line 2"),
    ],
)
def test_anything_but_plain_data_is_refused(text, message):
    with pytest.raises(ProtocolError, match=message):
        parse_yaml(text, "t.yaml")


def test_dates_stay_text():
    assert parse_yaml("when: 2020-01-01\n", "d.yaml")[0] == {"when": "2020-01-01"}


def test_bytes_that_are_not_utf8_name_line_and_column():
    with pytest.raises(ProtocolError) as info:
        decode_utf8(b"a: 1\nb: caf\xe9\n", "u.yaml")
    assert info.value.where == "line 2, column 7" and "0xe9" in info.value.message
    assert decode_utf8("\ufeffa: 1".encode(), "bom.yaml") == "a: 1"


def test_size_limit_and_files_that_are_not_files(tmp_path):
    big = tmp_path / "big.yaml"
    big.write_bytes(b"#" * (MAX_BYTES + 1))
    with pytest.raises(ProtocolError, match="larger than 4096 kB"):
        read_limited(big, what="protocol")
    with pytest.raises(ProtocolError, match="not a regular file") as err:
        read_limited("/dev/zero", what="protocol")  # would never end
    assert "give the path of the protocol itself" in str(err.value)
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)
    with pytest.raises(ProtocolError, match="not a regular file"):
        read_limited(fifo, what="protocol")  # would wait for a writer
    with pytest.raises(ProtocolError, match="cannot read the protocol"):
        read_limited(tmp_path / "missing.yaml", what="protocol")


def test_the_error_type_is_the_loaders(tmp_path):
    def cal_error(file, where, message):
        return CalibrationError(f"{file}: {where}: {message}")

    path = tmp_path / "calibration.json"
    path.write_text('{"a": NaN}', encoding="utf-8")
    with pytest.raises(CalibrationError, match=r"a \(line 1\): nan is not a finite number"):
        load_document(path, what="calibration", error=cal_error)


def test_excerpts_are_short_and_escaped():
    text = excerpt("root:x:0:0:\x1b[31m" + "y" * 500)
    assert len(text) <= 40 and "\x1b" not in text and text.endswith("…")


def test_non_finite_walks_iteratively():
    deep: list = [float("inf")]
    for _ in range(5000):  # deeper than the recursion limit
        deep = [deep]
    assert len(list(non_finite(deep))) == 1
