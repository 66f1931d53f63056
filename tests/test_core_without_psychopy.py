"""The core package works on a machine without PsychoPy (it is an optional extra)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

# Modules allowed to need optional extras, imported only when their back-end is chosen.
OPTIONAL = {"masking_lab.responders.psychopy_window", "masking_lab.device.nidaq"}

PROBE = textwrap.dedent(
    """
    import importlib, pkgutil, sys

    class Block:
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in ("psychopy", "nidaqmx"):
                raise ImportError(f"{name} is blocked for this test")
            return None

    sys.meta_path.insert(0, Block())
    import masking_lab
    optional = set(sys.argv[1].split(","))
    names = [m.name for m in pkgutil.walk_packages(masking_lab.__path__, "masking_lab.")]
    for name in names:
        if name not in optional:
            importlib.import_module(name)
    from masking_lab.commands.cli import main
    try:
        main(["--help"])
    except SystemExit as exc:
        assert exc.code == 0
    loaded = sorted(m for m in sys.modules if m.split(".")[0] in ("psychopy", "nidaqmx"))
    assert not loaded, loaded
    print("imported", len(names) - len(optional & set(names)), "modules")
    """
)


def test_every_core_module_imports_with_psychopy_blocked():
    res = subprocess.run(
        [sys.executable, "-c", PROBE, ",".join(sorted(OPTIONAL))],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 0, res.stderr[-3000:]
    assert "imported" in res.stdout
    # --help lists every command, and every command module registers (none silently skipped)
    from masking_lab.commands.cli import COMMANDS, build_parser

    assert set(build_parser()._subparsers._group_actions[0].choices) == set(COMMANDS)
    for command in COMMANDS:
        assert command in res.stdout, command
