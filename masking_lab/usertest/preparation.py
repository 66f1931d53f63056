"""What a user test needs before its first trial, and what its log header holds.

Pure checks and builders for :mod:`masking_lab.usertest.runner`: stream settings, the device's
watchdog, the participant's calibration (with a baseline protocol written for what is missing),
the masking functions of every stimulus pair (with the measuring protocol written for what is
missing), the rig's rating, the log header, and the design and masking functions rebuilt from a
logged header on resume.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from masking_lab.core.errors import (
    CalibrationError,
    LevelError,
    LogError,
    MaskingLabError,
    ProtocolError,
    SolverError,
)
from masking_lab.device.base import Device
from masking_lab.formats.calibration import calibration_path, load_calibration
from masking_lab.formats.fileio import write_text_atomic
from masking_lab.formats.records import jsonable
from masking_lab.rendering.scene import parse_scene_text
from masking_lab.rendering.solver import MissingMaskingError, MutualMasking, PairProblem
from masking_lab.session.header import session_header
from masking_lab.session.progress import ProgressLine
from masking_lab.usertest.design import (
    UserTestDesign,
    UserTrial,
    parse_usertest,
)
from masking_lab.usertest.stream import (
    REFRESH_S,
    Exceedance,
    StimulusLimit,
)

KIND = "usertest"
RESPONDERS = ("sim", "keys", "psychopy")
RECORD = "usertest_trial"


def check_stream_settings(update_hz: float, deadband_db: float) -> None:
    if not (math.isfinite(update_hz) and 1.0 <= update_hz <= 1000.0):
        raise MaskingLabError(f"update rate {update_hz!r} Hz: choose 1–1000 Hz (default 100)")
    if not (math.isfinite(deadband_db) and 0.0 <= deadband_db <= 6.0):
        raise MaskingLabError(f"dead-band {deadband_db!r} dB: choose 0–6 dB (default 0.5)")


def check_watchdog(device: Device) -> None:
    """The stream re-sends a held level every REFRESH_S s: the device's watchdog must allow it."""
    watchdog_s = float(getattr(device, "watchdog_s", 0.0) or 0.0)
    if 0.0 < watchdog_s < 2 * REFRESH_S:
        raise MaskingLabError(
            f"the device's watchdog zeroes the outputs after {watchdog_s:g} s without a command, "
            f"but a user test may stream a flat stretch with one frame every {REFRESH_S:g} s; "
            f"set serial.watchdog_s to at least {2 * REFRESH_S:g} s in the rig config"
        )


def stimuli_of(design: UserTestDesign) -> set[str]:
    names: set[str] = set()
    for scene in design.scenes.values():
        if scene.geometry is not None:
            names.add(scene.geometry.stimulus)
        if scene.texture is not None:
            names.add(scene.texture.stimulus)
    return names


def require_calibration(
    design: UserTestDesign,
    data_dir: Path,
    participant: str,
    run_options: str = "--device ... --responder ...",
) -> dict[str, float]:
    """The participant's unmasked AL of every stimulus the objects play, dB re 1 V.

    ``run_options`` completes the printed ``masking-lab run`` command (the user test's own
    ``--device`` and ``--responder``), so nothing needs retyping.
    """
    cal = load_calibration(data_dir, participant)
    needed = stimuli_of(design)
    missing = cal.missing(needed)
    if missing:
        written = write_baseline_protocol(missing, data_dir)
        have = ", ".join(sorted(cal.unmasked_al_db_v)) or "none"
        raise CalibrationError(
            f"{calibration_path(data_dir, participant)}: participant {participant} has no "
            f"unmasked AL for {', '.join(missing)} (calibrated: {have}); the user test plays "
            f"its levels in dB SL. Wrote {written}, a baseline of just these stimuli: run "
            f"masking-lab run {written} --participant {participant} --data {data_dir} "
            f"{run_options}, then start the user test again"
        )
    return {name: float(cal.unmasked_al_db_v[name]) for name in sorted(needed)}


def baseline_protocol(stimuli: Sequence[str]) -> dict[str, Any]:
    """A baseline protocol measuring the unmasked ALs of ``stimuli`` (staircase and timing of
    the shipped ``protocols/baseline.yaml``)."""
    from masking_lab.formats.resources import shipped

    template = yaml.safe_load(shipped("protocols", "baseline.yaml").read_text(encoding="utf-8"))
    names = sorted(set(stimuli))
    return {
        "schema_version": 1,
        "experiment": "baseline_" + "_".join(names),
        "description": f"Unmasked ALs of {', '.join(names)}, which a user test plays and the "
        "participant's calibration lacks. Written by masking-lab run.",
        "kind": "baseline",
        "staircase": template["staircase"],
        "timing": template["timing"],
        "order": {"randomize": True},
        "sets": [{"id": n, "target": n} for n in names],
    }


def write_baseline_protocol(stimuli: Sequence[str], folder: Path) -> Path:
    """Validate :func:`baseline_protocol` and write it to ``folder/<experiment>.yaml``."""
    from masking_lab.formats.protocol import parse_protocol

    protocol = baseline_protocol(stimuli)
    text = "# Written by masking-lab run: the baseline a user test needs.\n" + yaml.safe_dump(
        protocol, sort_keys=False, allow_unicode=True
    )
    path = Path(folder) / f"{protocol['experiment']}.yaml"
    parse_protocol(text.encode("utf-8"), str(path))
    return write_text_atomic(path, text)


def masking_pairs(
    design: UserTestDesign, params: Path | None, data_dir: Path
) -> tuple[dict[tuple[str, str], MutualMasking], dict[str, Any] | None]:
    """The fitted masking of every stimulus pair, and the params file's path and hash."""
    from masking_lab.formats.masking_params import determination_warnings, read_masking_params
    from masking_lab.rendering.outputs import measurement_protocols, write_measurement_protocol
    from masking_lab.rendering.solver import pair_from_params

    needed = design.stimulus_pairs()
    if params is None:
        if "compensated" not in design.conditions:
            # Nothing is compensated: the objects' inputs are their targets.
            zero = {(mv, ev): MutualMasking(0.0, 0.0, 0.0, 0.0, mv=mv, ev=ev) for mv, ev in needed}
            return zero, None
        listed = ", ".join(f"{mv} with {ev}" for mv, ev in needed)
        raise SolverError(
            f"{design.path}: the compensated condition needs the masking functions of {listed}: "
            "pass --params masking_params.json (written by `masking-lab fit` or `analyze`)"
        )
    doc = read_masking_params(params)
    for mv, ev in needed:  # a poorly determined function compensates uncertainly: say so
        for warning in determination_warnings(doc, str(params), (mv, ev)):
            print(f"masking-lab run: warning: {warning}", file=sys.stderr)
    pairs: dict[tuple[str, str], MutualMasking] = {}
    problems: list[PairProblem] = []
    for mv, ev in needed:
        try:
            pairs[(mv, ev)] = pair_from_params(doc, mv=mv, ev=ev, source=str(params))
        except MissingMaskingError as exc:
            problems += exc.problems
    if problems:
        written = " and ".join(
            str(write_measurement_protocol(doc, data_dir, writer="run"))
            for doc in measurement_protocols(problems, writer="run")
        )
        listed = "; ".join(
            f"{p.target} masked by {p.masker} ("
            + ("no entry" if p.status == "missing" else f"status {p.status!r}")
            + ")"
            for p in problems
        )
        raise SolverError(
            f"{params}: the user test compensates every object, but these masking functions are "
            f"not fitted: {listed}.\n  wrote {written}: the protocol(s) that measure just these "
            "pairs, one per masking direction. Check them with `masking-lab validate`, run them "
            "after the participants' baseline, analyse them with the rest of the study, and "
            "start the user test again"
        )
    raw = Path(params).read_bytes()
    record = {"path": str(Path(params).resolve()), "sha256": hashlib.sha256(raw).hexdigest()}
    return pairs, record


_MAX_LISTED = 12


def refuse_or_warn(
    over: Sequence[Exceedance], allow_clipping: bool, participant: str, out: ProgressLine
) -> None:
    if not over:
        return
    lines = [f"  {e.describe()}" for e in over[:_MAX_LISTED]]
    if len(over) > _MAX_LISTED:
        lines.append(f"  ... and {len(over) - _MAX_LISTED} more")
    listed = "\n".join(lines)
    if not allow_clipping:
        raise LevelError(
            f"the user test cannot be played as designed for participant {participant}: "
            f"{len(over)} object/condition/channel combination(s) need more than the rig "
            f"allows:\n{listed}\nNothing was played. Either use a rig config whose limits cover "
            "these levels (--device-config: channels.<EV|MV>.max_level_db_sl and max_drive_v, "
            "only if the hardware is rated for them), or pass --allow-clipping to play them "
            "clipped at the limit (every trial then logs what was clipped, and compensation is "
            "only partial where it clips)"
        )
    out.message(
        f"--allow-clipping: {len(over)} object/condition/channel combination(s) will be "
        f"clipped at the rig's limits (logged per trial):\n{listed}"
    )


# --------------------------------------------------------------------------------------------
# The header and what resume rebuilds from it


def header_record(
    *,
    design: UserTestDesign,
    participant: str,
    calibration: Mapping[str, float],
    device: Device,
    responder: str,
    seed: int,
    virtual: bool,
    observer: dict[str, Any] | None,
    device_config: Path | None,
    pairs: Mapping[tuple[str, str], MutualMasking],
    params_record: dict[str, Any] | None,
    stream_settings: dict[str, float],
    allow_clipping: bool,
    rig_max: Mapping[str, float],
    limits: Mapping[str, StimulusLimit],
    over: Sequence[Exceedance],
    gamut_map: str = "none",
) -> dict[str, Any]:
    protocol_text = _text_with_hash(Path(design.path), design.sha256)
    scenes = []
    for (g, t), scene in sorted(design.scenes.items()):
        scenes.append(
            {
                "object": f"{g}_{t}",
                "path": str(Path(scene.source).resolve()),
                "sha256": scene.sha256,
                "text": _text_with_hash(Path(scene.source), scene.sha256),
            }
        )
    return session_header(
        source=design,
        participant=participant,
        calibration=calibration,
        device=device.identity,
        responder=responder,
        seed=seed,
        order=[],
        virtual=virtual,
        observer=observer,
        device_config=device_config,
        kind=KIND,
        usertest={
            "protocol_text": protocol_text,
            "scenes": scenes,
            "masking": [
                {
                    "mv": p.mv,
                    "ev": p.ev,
                    "a_db": p.a_db,
                    "b": p.b,
                    "c_db": p.c_db,
                    "d": p.d,
                    "f_fitted_range_db_sl": jsonable(p.f_fitted_range_db_sl),
                    "g_fitted_range_db_sl": jsonable(p.g_fitted_range_db_sl),
                }
                for _, p in sorted(pairs.items())
            ],
            "params": params_record,
            "n_trials": design.n_trials,
            "stream": stream_settings,
            "allow_clipping": bool(allow_clipping),
            "gamut_map": gamut_map,
            "rig_max_level_db_sl": {k: float(v) for k, v in sorted(rig_max.items())},
            "max_level_db_sl": {k: round(v.max_db_sl, 6) for k, v in sorted(limits.items())},
            "clipped_objects": [e.as_record() for e in over],
        },
    )


def _text_with_hash(path: Path, sha256: str) -> str:
    """The file's text, checked against the hash it was loaded with."""
    raw = path.read_bytes()
    if hashlib.sha256(raw).hexdigest() != sha256:
        raise ProtocolError(
            str(path), "", "the file changed while the session was starting; start it again"
        )
    return raw.decode("utf-8")


def design_from_header(
    header: Mapping[str, Any], path: Path, allow_changed: bool, out: ProgressLine
) -> UserTestDesign:
    """The design as the session started it, from the copies in the header."""
    meta = header["protocol"]
    ut = header["usertest"]
    logged = [(str(meta["path"]), str(meta["sha256"]), "protocol")] + [
        (str(s["path"]), str(s["sha256"]), f"scene {s['object']}") for s in ut["scenes"]
    ]
    changed = []
    for file, sha, what in logged:
        on_disk = Path(file)
        if on_disk.is_file() and hashlib.sha256(on_disk.read_bytes()).hexdigest() != sha:
            changed.append(f"{what} {file}")
    if changed:
        if not allow_changed:
            raise LogError(
                f"{path}: changed since this session started: {'; '.join(changed)}. Restore "
                "them, or resume with --allow-changed-protocol to continue with the copies "
                "stored in the log (the files on disk are never used by resume)"
            )
        out.message(
            f"note: {'; '.join(changed)} changed since the session started; continuing with the "
            "copies stored in the log"
        )
    try:
        # The stored copies are parsed as they are: nothing is written to disk or parsed twice.
        scenes = {
            str(s["object"]): parse_scene_text(str(s["text"]), str(s["path"])) for s in ut["scenes"]
        }
        design = parse_usertest(
            dict(meta["content"]), scenes, source=str(meta["path"]), sha256=str(meta["sha256"])
        )
    except ProtocolError as exc:
        raise LogError(f"{path}: the user test stored in the header is invalid: {exc}") from exc
    sources = {s["object"]: (str(s["path"]), str(s["sha256"])) for s in ut["scenes"]}
    by_pair = {}
    for (g, t), scene in design.scenes.items():
        source, sha = sources[f"{g}_{t}"]
        if scene.sha256 != sha:
            raise LogError(f"{path}: the stored copy of scene {g}_{t} does not match its hash")
        by_pair[(g, t)] = dataclasses.replace(scene, source=source)
    return dataclasses.replace(
        design,
        path=str(meta["path"]),
        sha256=str(meta["sha256"]),
        content=dict(meta["content"]),
        scenes=by_pair,
    )


def pairs_from_header(ut: Mapping[str, Any], path: Path) -> dict[tuple[str, str], MutualMasking]:
    pairs = {}
    try:
        for m in ut["masking"]:
            pair = MutualMasking(
                float(m["a_db"]),
                float(m["b"]),
                float(m["c_db"]),
                float(m["d"]),
                mv=str(m["mv"]),
                ev=str(m["ev"]),
                f_fitted_range_db_sl=_pair_or_none(m.get("f_fitted_range_db_sl")),
                g_fitted_range_db_sl=_pair_or_none(m.get("g_fitted_range_db_sl")),
            )
            pairs[(pair.mv, pair.ev)] = pair
    except (KeyError, TypeError, ValueError, SolverError) as exc:
        raise LogError(f"{path}: the header's usertest.masking is unusable ({exc})") from exc
    return pairs


def _pair_or_none(value: Any) -> tuple[float, float] | None:
    return None if value is None else (float(value[0]), float(value[1]))


def check_logged(
    path: Path, trials: Sequence[UserTrial], logged: Sequence[Mapping[str, Any]], participant: str
) -> None:
    """Logged trials must be the seed's first trials, in order, each once."""
    if len(logged) > len(trials):
        raise LogError(
            f"{path}: {len(logged)} trials logged but the design has {len(trials)}; the log has "
            "been edited or merged and cannot be resumed"
        )
    for i, rec in enumerate(logged):
        t = trials[i]
        want = (i, t.geometry, t.texture, t.condition, t.repeat, participant)
        got = (
            rec.get("trial"),
            rec.get("geometry"),
            rec.get("texture"),
            rec.get("condition"),
            rec.get("repeat"),
            rec.get("participant"),
        )
        if got != want:
            raise LogError(
                f"{path}: logged trial {i} is {got[1]}_{got[2]} {got[3]} (index {got[0]}) but "
                f"the session's seed puts {t.geometry}_{t.texture} {t.condition} there; the log "
                "does not match its design and cannot be resumed"
            )
