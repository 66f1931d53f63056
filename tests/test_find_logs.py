"""`find_logs` (the folder walk of `analyze`, `usertest-report` and the study overview) finds
exactly what `Path.rglob("*.jsonl")` + `is_file()` found before it was rewritten on
`os.scandir`, on a real folder tree with hidden parts, symlinks and look-alike names."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from masking_lab.analysis.data_folder import find_logs
from masking_lab.core.errors import AnalysisError


def _rglob_reference(data_dir: Path) -> list[Path]:
    """The walk as it was (pathlib's rglob: symlinked folders not entered)."""
    found = [
        p
        for p in data_dir.rglob("*.jsonl")
        if p.is_file() and not any(part.startswith(".") for part in p.relative_to(data_dir).parts)
    ]
    return sorted(found, key=lambda p: p.relative_to(data_dir).as_posix())


def _tree(root: Path) -> None:
    for rel in (
        "S02/S02_baseline.jsonl",
        "S01/S01_experiment1.jsonl",
        "S01/S01_baseline.jsonl",
        "S01/deep/er/x.jsonl",
        "top.jsonl",
        ".trash/S03.jsonl",  # hidden folder
        "S01/.S01_old.jsonl",  # hidden file
        "S01/.cache/y.jsonl",
        "S01/notes.txt",
        "S01/S01_baseline.jsonl.bak",
        "S01/UPPER.JSONL",
        "odd.jsonl/inside.jsonl",  # a folder named like a log: not a log, but walked
        "a b/ü ñ.jsonl",
    ):
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("{}\n")
    outside = root.parent / f"{root.name}_outside"
    (outside / "P9").mkdir(parents=True)
    (outside / "P9" / "P9.jsonl").write_text("{}\n")
    os.symlink(outside, root / "linked_folder")  # rglob does not enter it
    os.symlink(root / "S02" / "S02_baseline.jsonl", root / "S02" / "alias.jsonl")
    os.symlink(root / "gone.jsonl", root / "S02" / "broken.jsonl")


def test_the_same_logs_in_the_same_order_as_rglob(tmp_path):
    root = tmp_path / "data"
    _tree(root)
    found = find_logs(root)
    assert found == _rglob_reference(root)
    assert [p.relative_to(root).as_posix() for p in found] == [
        "S01/S01_baseline.jsonl",
        "S01/S01_experiment1.jsonl",
        "S01/deep/er/x.jsonl",
        "S02/S02_baseline.jsonl",
        "S02/alias.jsonl",
        "a b/ü ñ.jsonl",
        "odd.jsonl/inside.jsonl",
        "top.jsonl",
    ]


def test_a_relative_folder_gives_relative_paths(tmp_path, monkeypatch):
    _tree(tmp_path / "data")
    monkeypatch.chdir(tmp_path)
    assert find_logs(Path("data")) == _rglob_reference(Path("data"))
    assert find_logs(Path("data"))[0] == Path("data/S01/S01_baseline.jsonl")


def test_no_folder_is_named(tmp_path):
    with pytest.raises(AnalysisError, match="no such folder"):
        find_logs(tmp_path / "missing")
    (tmp_path / "file.jsonl").write_text("{}\n")
    with pytest.raises(AnalysisError, match=r"file\.jsonl: a file, not a folder") as err:
        find_logs(tmp_path / "file.jsonl")
    assert f"this file's folder is {tmp_path}" in str(err.value)
