"""``masking-lab validate FILE...``: check protocols, rig configs, scenes, ground truth,
calibration, masking params, shifts CSVs and session logs.

Check input files of every kind: threshold protocols, user-test protocols, rig (device) configs,
simulation ground truth, scenes, calibration.json, masking_params.json, shifts CSVs and session
logs; the kind is told from the content. Exit 0 if every file is valid; otherwise print one
message per bad file naming the key path, the line and what to do, and exit 1.

Each file's kind is told from its content (never from a name a file could lie about), then the
file goes through that kind's own loader — the same one ``run``, ``render``, ``solve`` and
``analyze`` use — so what validates here is what those commands accept.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from masking_lab.commands.options import command_texts

#: Kinds ``validate`` tells apart, in the order the help text lists them.
KINDS = (
    "protocol",
    "usertest",
    "rig-config",
    "ground-truth",
    "scene",
    "calibration",
    "masking-params",
    "shifts-csv",
    "session-log",
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("validate", **command_texts(__doc__))
    p.add_argument("files", nargs="+", metavar="FILE", help="file(s) to check")
    p.add_argument(
        "--device-config",
        metavar="FILE",
        help="rig config whose per-channel max_level_db_sl limits masker levels and whose "
        "converters must play every level a protocol may ask for within 1 dB "
        "(default: the reference rig, protocols/devices/default.yaml)",
    )
    p.add_argument(
        "--data",
        metavar="DIR",
        help="data folder of the participant a run will use (with --participant): a masked "
        "protocol is then checked against that participant's calibration.json, as `run` does",
    )
    p.add_argument(
        "--participant",
        metavar="ID",
        help="participant id (with --data); without both, a masked protocol's summary lists the "
        "unmasked ALs a run will need",
    )
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from masking_lab.core.errors import MaskingLabError
    from masking_lab.device.rig_limits import max_level_db_sl

    if (args.data is None) != (args.participant is None):
        print(
            "masking-lab validate: error: --data and --participant go together (the "
            "participant's calibration is <data>/<participant>/calibration.json)",
            file=sys.stderr,
        )
        return 2
    limits = max_level_db_sl(args.device_config)
    bad = 0
    for f in args.files:
        try:
            summary = check_file(
                f,
                limits,
                device_config=args.device_config,
                participant=(args.data, args.participant) if args.data is not None else None,
            )
            print(f"ok      {f}: {summary}")
            for note in model_notes(f):
                print(f"warning {f}: {note}")
        except MaskingLabError as exc:
            bad += 1
            print(f"INVALID {exc}", file=sys.stderr)
    return 1 if bad else 0


def check_file(
    path: str,
    limits: dict[str, float],
    device_config: str | None = None,
    participant: tuple[str, str] | None = None,
) -> str:
    """Load ``path`` with its kind's loader; return a one-line summary of what it holds.

    ``participant`` (data folder, participant id) checks a protocol against that participant's
    calibration as ``run`` will; without it a masked protocol's summary names the ALs it needs.

    Raises
    ------
    MaskingLabError
        The loader's error (file, key path, line, what to do), or a ``ProtocolError`` saying
        the kind cannot be told.
    """
    kind, _ = sniff(path)
    if kind == "session-log":
        return _check_log(path)
    if kind == "shifts-csv":
        from masking_lab.formats.shifts_csv import read_shifts_csv

        shifts, _ = read_shifts_csv(path)
        return f"shifts CSV, {len(shifts)} rows"
    if kind == "protocol":
        from masking_lab.formats.protocol import load_protocol

        protocol = load_protocol(path, max_level_db_sl=limits)
        if participant is not None:
            return protocol.summary() + _check_for_participant(protocol, participant, device_config)
        _check_levels_playable(path, protocol, device_config)
        if protocol.kind == "masked":
            needed = ", ".join(sorted(protocol.stimuli()))
            return (
                f"{protocol.summary()}; a run needs the participant's unmasked ALs of {needed} "
                "(calibration.json from the baseline; check with --data and --participant)"
            )
        return protocol.summary()
    if kind == "usertest":
        from masking_lab.usertest.design import load_usertest

        design = load_usertest(path)
        return f"{design.experiment} (usertest, {design.n_trials} trials)"
    if kind == "rig-config":
        from masking_lab.device.config import load_device_config

        config = load_device_config(path)
        return f"rig config {config.name!r}"
    if kind == "ground-truth":
        from masking_lab.simulation.observer import load_ground_truth

        truth = load_ground_truth(path)
        return f"ground truth, {len(truth.masking)} masking functions"
    if kind == "scene":
        from masking_lab.rendering.scene import load_scene

        scene = load_scene(path)
        return f"scene {scene.name!r}"
    if kind == "calibration":
        from masking_lab.formats.calibration import read_calibration

        cal = read_calibration(path)
        return f"calibration of {cal.participant}, {len(cal.unmasked_al_db_v)} stimuli"
    from masking_lab.formats.masking_params import read_masking_params

    doc = read_masking_params(path)
    return f"masking params, {len(doc['functions'])} functions"


def model_notes(path: str) -> list[str]:
    """Warnings of a valid protocol whose Bayesian procedure states a single psychometric
    slope or lapse: its intervals assume them (``procedures.model_note``). Empty for every
    other file."""
    from masking_lab.formats.protocol import load_protocol
    from masking_lab.procedures.model_note import stated_model_note

    if sniff(path)[0] != "protocol":
        return []
    notes = {stated_model_note(s.settings) for s in load_protocol(path).sets}
    return sorted(n for n in notes if n is not None)


def _check_for_participant(
    protocol: Any, participant: tuple[str, str], device_config: str | None
) -> str:
    """What ``run`` checks before its first trial, for every set: the calibration file reads,
    holds the unmasked AL of every stimulus a masked protocol plays, and puts every level the
    sets may ask for within the rig's reach. Returns the summary's tail."""
    from masking_lab.core.errors import CalibrationError, LevelError, ProtocolError
    from masking_lab.session.threshold_plan import checked_calibration

    data_dir, participant_id = participant
    try:
        order = [s.id for s in protocol.sets]
        calibration = checked_calibration(
            protocol, order, Path(data_dir), participant_id, device_config
        )
    except (CalibrationError, LevelError) as exc:
        # Name the protocol being validated first; the message names the calibration file.
        raise ProtocolError(
            protocol.path, "sets", f"`run` would refuse it for {participant_id}: {exc}"
        ) from None
    if protocol.kind == "masked":
        return f"; runs for {participant_id} (calibrated: {', '.join(sorted(calibration))})"
    return f"; runs for {participant_id}"


def _check_levels_playable(path: str, protocol: Any, device_config: str | None) -> None:
    """Refuse a protocol whose level range the rig's converters cannot play within 1 dB.

    dB SL levels are placed with the reference ALs of the simulation ground truth (a
    participant's own ALs are checked again by ``run`` before the first trial).
    """
    from masking_lab.core.errors import ProtocolError
    from masking_lab.device.config import load_device_config
    from masking_lab.device.level_check import level_problems
    from masking_lab.simulation.observer import load_ground_truth

    config = load_device_config(device_config)
    if not config.converters:
        return
    problems = level_problems(
        protocol,
        config.converters,
        load_ground_truth().unmasked_al_db_v,
        config.limits.max_drive_v,
        al_source="protocols/simulation/ground_truth.yaml, the reference participant",
    )
    if problems:
        more = f" (and {len(problems) - 3} more)" if len(problems) > 3 else ""
        raise ProtocolError(
            path,
            "sets",
            f"levels the rig {config.path} cannot play: " + "; ".join(problems[:3]) + more,
        )


def sniff(path: str) -> tuple[str, Any]:
    """Tell a file's kind from its content; return the kind and the parsed data (or None).

    Raises
    ------
    ProtocolError
        If the file cannot be read or parsed, or matches no kind.

    Examples
    --------
    >>> from masking_lab.formats.resources import shipped
    >>> sniff(str(shipped("protocols", "devices/default.yaml")))[0]
    'rig-config'
    """
    from masking_lab.core.errors import ProtocolError
    from masking_lab.formats.reader import decode_utf8, parse_json, parse_yaml, read_limited

    first = _first_line(path)
    if first.startswith(b"{") and _is_record(first):
        return "session-log", None
    if b"," in first and b"shift_db" in first:
        return "shifts-csv", None
    raw = read_limited(path, what="input file")
    text = decode_utf8(raw, path)
    parse = parse_json if text.lstrip().startswith("{") else parse_yaml
    data, _ = parse(text, path)
    kind = _kind_of(data)
    if kind is None and parse is parse_yaml:
        kind = "protocol"  # the historic default: its loader says what a protocol lacks
    if kind is None:
        raise ProtocolError(
            path,
            "(top level)",
            "cannot tell what kind of file this is: expected a protocol (kind: baseline, masked "
            "or usertest), a rig config (channels:), a ground truth (unmasked_al_db_v: and "
            "masking:), a scene (geometry: or texture:), a calibration (participant: and "
            "unmasked_al_db_v:), masking params (functions:), a shifts CSV or a session log",
        )
    return kind, data


def _first_line(path: str, limit: int = 8 * 1024 * 1024) -> bytes:
    """The first line that is not blank or a comment (a log header is long: it carries the
    protocol)."""
    import os
    import stat

    from masking_lab.core.errors import ProtocolError

    try:
        if not stat.S_ISREG(os.stat(path).st_mode):  # a FIFO or device would block or never end
            raise ProtocolError(
                path,
                "",
                "not a regular file (a device, FIFO or folder); give the files one by one, "
                "e.g. protocols/*.yaml",
            )
        with open(path, "rb") as fh:
            for _ in range(64):
                line = fh.readline(limit)
                if not line:
                    break
                if line.strip() and not line.lstrip().startswith(b"#"):
                    return line.strip()
    except OSError as exc:
        msg = f"cannot read the file ({exc.strerror or type(exc).__name__}); check the path"
        raise ProtocolError(path, "", msg) from exc
    return b""


def _is_record(line: bytes) -> bool:
    import json

    try:
        record = json.loads(line)
    except (ValueError, RecursionError):
        return False
    return isinstance(record, dict) and "record" in record


def _kind_of(data: Any) -> str | None:
    if not isinstance(data, dict):
        return None
    kind = data.get("kind")
    if kind == "usertest":
        return "usertest"
    if kind in ("baseline", "masked") or "sets" in data:
        return "protocol"
    if "channels" in data:
        return "rig-config"
    if "functions" in data:
        return "masking-params"
    if "unmasked_al_db_v" in data:
        return "calibration" if "participant" in data else "ground-truth"
    if "masking" in data:
        return "ground-truth"
    if "geometry" in data or "texture" in data or "scene" in data:
        return "scene"
    return None


def _check_log(path: str) -> str:
    from masking_lab.core.errors import LogError
    from masking_lab.formats.session_log import read_log

    log = read_log(path)
    problems = [*log.problems, *log.value_problems, *log.continuity_problems()]
    if problems:
        more = f" (and {len(problems) - 5} more)" if len(problems) > 5 else ""
        shown = "; ".join(problems[:5]) + more
        raise LogError(f"{path}: {shown}")
    state = "ended" if log.ended else "interrupted (resumable)"
    return f"session log, {len(log.records)} records, {state}"
