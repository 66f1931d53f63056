"""The layer contract holds: imports point inward, toward core (import-linter, pyproject.toml)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_import_linter_layers_contract_is_kept():
    exe = shutil.which("lint-imports", path=str(Path(sys.executable).parent)) or shutil.which(
        "lint-imports"
    )
    assert exe, "lint-imports is missing: pip install '.[test]' installs import-linter"
    res = subprocess.run([exe], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "KEPT" in res.stdout and "BROKEN" not in res.stdout


def test_every_module_is_at_most_600_lines_and_the_top_level_is_small():
    package = REPO / "masking_lab"
    long = {
        str(p.relative_to(REPO)): n
        for p in package.rglob("*.py")
        if (n := len(p.read_text(encoding="utf-8").splitlines())) > 600
    }
    assert not long, f"split these modules by idea: {long}"
    top = sorted(p.name for p in package.glob("*.py"))
    assert len(top) <= 8, top


def test_every_sub_package_says_what_it_holds_and_its_exports_resolve():
    code = """
import importlib, pkgutil, sys
import masking_lab
for info in pkgutil.iter_modules(masking_lab.__path__):
    if not info.ispkg:
        continue
    pkg = importlib.import_module(f"masking_lab.{info.name}")
    assert len((pkg.__doc__ or "").split()) >= 8, f"{info.name}: say what the package holds"
    assert pkg.__all__ and pkg.__all__ == sorted(pkg.__all__), info.name
    for name in pkg.__all__:
        getattr(pkg, name)
    assert set(pkg.__all__) <= set(dir(pkg)), info.name
"""
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr


def test_importing_the_packages_loads_no_heavy_library():
    code = """
import importlib, pkgutil, sys
import masking_lab
for info in pkgutil.iter_modules(masking_lab.__path__):
    if info.ispkg:
        importlib.import_module(f"masking_lab.{info.name}")
print(sorted({"scipy", "pandas", "matplotlib", "psychopy"} & set(sys.modules)))
"""
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "[]", res.stdout
