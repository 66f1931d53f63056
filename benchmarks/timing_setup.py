"""Set a source tree up to be timed as an installed package runs: its bytecode compiled, and
its ``masking-lab`` command started through the console-script entry point it declares.

``pip install`` compiles every module's bytecode, and Python writes it on the first import
anyway; a benchmark run from a source tree under ``PYTHONDONTWRITEBYTECODE=1`` (as some
sandboxes and CI images set) would instead recompile ~200 masking_lab modules on every run,
about 0.3 s that no user pays. Both trees of a before/after comparison are compiled alike.
"""

from __future__ import annotations

import compileall
import tomllib
from pathlib import Path


def compile_tree(root: Path) -> None:
    """Write the bytecode of ``root``/masking_lab (a no-op where it is current)."""
    package = Path(root) / "masking_lab"
    if not compileall.compile_dir(str(package), quiet=1, workers=0):
        raise SystemExit(f"could not compile the bytecode of {package}")


def console_code(root: Path) -> str:
    """Python source (for ``python -c``) that runs the tree's ``masking-lab`` console script on
    ``sys.argv[1:]``: the entry point ``root``/pyproject.toml names (``module:function``), as
    the installed ``masking-lab`` calls it (an older tree's may be ``cli:main``)."""
    with open(Path(root) / "pyproject.toml", "rb") as fh:
        entry = tomllib.load(fh)["project"]["scripts"]["masking-lab"]
    module, function = entry.split(":")
    return f"import sys; from {module} import {function}; sys.exit({function}())"


def tree_console_code(root: Path, other_tree: bool) -> str:
    """:func:`console_code` of ``root``; with ``other_tree``, run from ``root`` even where this
    checkout is installed in editable mode (its import hook would win over ``sys.path``, so it
    is dropped first)."""
    code = console_code(root)
    if other_tree:
        code = (
            "import sys; sys.meta_path[:] = [f for f in sys.meta_path if 'editable' not in "
            f"repr(f).lower()]; sys.path.insert(0, {str(root)!r}); " + code
        )
    return code
