"""The demo's session scheduler: sessions in worker processes write what one by one would."""

from __future__ import annotations

import io
import json
import subprocess
import sys
from pathlib import Path

from masking_lab import demo
from masking_lab.demo import DemoSettings, SessionDone


def _logs(data: Path) -> dict[str, list[dict]]:
    """Each log by participant/protocol, without the wall-clock stamps of the run (``*_utc``
    and the session id, named after the start)."""
    out = {}
    for path in sorted(data.rglob("*.jsonl")):
        records = [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]
        for r in records:
            for key in [k for k in r if k.endswith("_utc") or k == "session_id"]:
                del r[key]
        out[f"{path.parent.name}/{path.name.split('-')[0]}"] = records
    return out


def test_sessions_in_three_workers_log_exactly_what_one_by_one_does(tmp_path):
    said: list[str] = []
    for jobs in (1, 3):
        settings = DemoSettings(
            out=tmp_path / f"jobs{jobs}", participants=2, device="sim", jobs=jobs
        )
        done = demo._collect(settings, io.StringIO(), said.append)
        assert [(s.participant, s.protocol, s.exit_code) for s in done] == [
            (f"S{i:02d}", name, 0) for i in (1, 2) for name in demo.PROTOCOLS
        ]
    one, three = _logs(tmp_path / "jobs1" / "data"), _logs(tmp_path / "jobs3" / "data")
    assert sorted(one) == sorted(three) and len(one) == 6
    for name in one:
        assert one[name] == three[name], name
    for who in ("S01", "S02"):
        cal = [
            json.loads((tmp_path / d / "data" / who / "calibration.json").read_text())
            for d in ("jobs1", "jobs3")
        ]
        assert cal[0]["unmasked_al_db_v"] == cal[1]["unmasked_al_db_v"]
    assert len(said) == 12 and said[-1].startswith("  [ 6/6]")


def fake_session(out: str, device: str, seed: int, index: int, k: int) -> SessionDone:
    """A stand-in for a session (no device): participant 2's baseline fails."""
    failed = index == 2 and k == 0
    return SessionDone(
        participant=f"S{index:02d}",
        protocol=demo.PROTOCOLS[k],
        log_path=f"{out}/S{index:02d}-{k}.jsonl",
        exit_code=3 if failed else 0,
        n_sets=1,
        n_completed=0 if failed else 1,
        n_trials=10,
        seconds=0.0,
        message="device refused" if failed else "",
    )


def test_a_failed_baseline_starts_none_of_that_participants_experiments(tmp_path):
    settings = DemoSettings(out=tmp_path, participants=3, device="sim", jobs=2)
    done = list(demo._run_in_pool(str(tmp_path), settings, 2, run=fake_session))
    ran = sorted((s.participant, s.protocol) for s in done)
    assert ran == sorted(
        [(p, name) for p in ("S01", "S03") for name in demo.PROTOCOLS] + [("S02", "baseline")]
    )
    # Baselines are handed out first: each unlocks two experiments.
    assert [s.protocol for s in done[:2]] == ["baseline", "baseline"]


def test_the_warm_up_loads_what_the_analysis_would_import_on_its_critical_path():
    # A fresh interpreter: this one may have imported them already (then the test could not
    # fail). After the warm-up, the modules the analysis imports lazily are loaded.
    code = (
        "import sys\n"
        "from masking_lab import demo\n"
        "lazy = ('jinja2', 'masking_lab.analysis.batch')\n"
        "before = [m in sys.modules for m in lazy]\n"
        "demo._warm_imports()\n"
        "from masking_lab.formats.html_report import _environment\n"
        "compiled = [key[1] for key in _environment().cache.keys()]\n"
        "after = [m in sys.modules for m in lazy]\n"
        "print(before, after, compiled, 'scipy.optimize' in sys.modules)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    # ... and report.html's template is loaded, off the analysis' critical path; scipy.optimize,
    # which the staircases' target p needed before masking_lab.core.roots, is not loaded.
    assert done.stdout.strip() == "[False, False] [True, True] ['analysis.html.j2'] False"
