"""``masking-lab validate FILE...``: check protocol files before a participant sits down."""

from __future__ import annotations

import argparse
import sys


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "validate",
        help="check protocol YAML files against the schema and the rig's limits",
        description="Check protocol files. Exit 0 if every file is valid; otherwise print one "
        "message per bad file naming the key path, the line and what to do, and exit 1.",
    )
    p.add_argument("files", nargs="+", metavar="FILE", help="protocol YAML file(s)")
    p.add_argument(
        "--device-config",
        metavar="FILE",
        help="rig config whose per-channel max_level_db_sl limits masker levels "
        "(default: the reference rig, protocols/devices/default.yaml)",
    )
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from masking_lab.core.errors import ProtocolError
    from masking_lab.device.rig_limits import max_level_db_sl
    from masking_lab.formats.protocol import load_protocol

    limits = max_level_db_sl(args.device_config)
    bad = 0
    for f in args.files:
        if _is_usertest(f):
            # User-test protocols (kind: usertest) have their own schema and loader.
            from masking_lab.usertest.design import load_usertest

            try:
                design = load_usertest(f)
            except ProtocolError as exc:
                bad += 1
                print(f"INVALID {exc}", file=sys.stderr)
                continue
            print(f"ok      {f}: {design.experiment} (usertest, {design.n_trials} trials)")
            continue
        try:
            protocol = load_protocol(f, max_level_db_sl=limits)
        except ProtocolError as exc:
            bad += 1
            print(f"INVALID {exc}", file=sys.stderr)
            continue
        print(f"ok      {f}: {protocol.experiment} ({protocol.kind}, {len(protocol.sets)} sets)")
    return 1 if bad else 0


def _is_usertest(path: str) -> bool:
    """True if ``path`` parses as a mapping with ``kind: usertest`` (else load_protocol reports)."""
    import yaml

    try:
        with open(path, encoding="utf-8") as fh:
            data = yaml.safe_load(fh)
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return False
    return isinstance(data, dict) and data.get("kind") == "usertest"
