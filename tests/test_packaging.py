"""pyproject.toml ships every sub-package and every schema/protocol file."""

from __future__ import annotations

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _config() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"][
        "setuptools"
    ]


def test_every_subpackage_is_listed():
    listed = set(_config()["packages"])
    found = {
        ".".join(init.parent.relative_to(ROOT).parts)
        for init in (ROOT / "masking_lab").rglob("__init__.py")
    }
    assert found <= listed, f"add to [tool.setuptools] packages: {sorted(found - listed)}"


def test_every_shipped_data_file_matches_a_package_data_pattern():
    data = _config()["package-data"]
    for package, folder in (
        ("masking_lab.data_schema", "data_schema"),
        ("masking_lab.protocols", "protocols"),
    ):
        patterns = data[package]
        for f in (ROOT / folder).rglob("*"):
            if f.is_file() and f.suffix in (".json", ".yaml", ".csv"):
                rel = f.relative_to(ROOT / folder)
                assert any(rel.match(p) for p in patterns), f"{folder}/{rel} would not ship"
