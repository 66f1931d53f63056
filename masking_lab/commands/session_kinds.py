"""The session kinds ``run`` and ``resume`` dispatch on, in one table.

Each row names a kind's :class:`~masking_lab.session.frame.SessionKind` (imported on use), how to
recognise its protocol and its log, how to turn the command line into its options and how to
print its result; :mod:`masking_lab.session.frame` starts and resumes it. A new kind of session
is one more row.
"""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from masking_lab.core.errors import MaskingLabError

if TYPE_CHECKING:  # imported on use: `--help` loads no numpy
    from masking_lab.session.frame import SessionKind, SessionOptions


@dataclass(frozen=True)
class SessionCommand:
    """How ``run`` and ``resume`` handle one kind of session.

    Attributes
    ----------
    name : str
        The kind's name (``"threshold"``, ``"usertest"``).
    home : str
        ``module:NAME`` of the kind's :class:`~masking_lab.session.frame.SessionKind`.
    is_protocol, is_log : callable
        Recognise the kind's protocol file and session log by their content.
    options : callable
        ``args -> options``: the kind's options from the ``run`` arguments.
    print_result : callable
        Print the result; return the exit code.
    """

    name: str
    home: str
    is_protocol: Callable[[str], bool]
    is_log: Callable[[str], bool]
    options: Callable[[argparse.Namespace], SessionOptions]
    print_result: Callable[[Any], int]

    def kind(self) -> SessionKind[Any, Any]:
        """The session kind, imported now."""
        module, name = self.home.split(":")
        kind: SessionKind[Any, Any] = getattr(importlib.import_module(module), name)
        return kind


def _common(args: argparse.Namespace) -> dict[str, Any]:
    return {
        "protocol": Path(args.protocol),
        "participant": args.participant,
        "device": args.device,
        "responder": args.responder,
        "data_dir": Path(args.data),
        "seed": args.seed,
        "real_time": args.real_time,
        "ground_truth": Path(args.ground_truth) if args.ground_truth else None,
        "device_config": Path(args.device_config) if args.device_config else None,
        "progress": args.progress,
        "participant_tty": args.participant_tty,
    }


def _threshold_options(args: argparse.Namespace) -> SessionOptions:
    from masking_lab.session.participant_info import parse_info_args
    from masking_lab.session.runner import RunOptions

    sets = None
    if args.sets:
        sets = tuple(s for item in args.sets for s in item.split(",") if s)
    info = parse_info_args(getattr(args, "info", None) or [])
    return RunOptions(sets=sets, info=info, **_common(args))


def _print_threshold(result: Any) -> int:
    print(f"log: {result.log_path}")
    for outcome in result.outcomes:
        print(f"  {outcome.summary()}")
    # result.message (a fault or an interruption, with the resume command) was shown on stderr
    # by the session itself when it stopped: printing it again doubled it (issue 17).
    return int(result.exit_code)


def _is_usertest_protocol(path: str) -> bool:
    from masking_lab.usertest.runner import is_usertest_protocol

    return is_usertest_protocol(path)


def _is_usertest_log(path: str) -> bool:
    from masking_lab.usertest.runner import is_usertest_log

    return is_usertest_log(path)


def _usertest_options(args: argparse.Namespace) -> SessionOptions:
    from masking_lab.usertest.runner import UserTestOptions

    if args.sets:
        raise MaskingLabError("--sets: a user-test protocol has no sets; leave it out")
    if getattr(args, "info", None):
        raise MaskingLabError("--info: a user-test protocol has no info section; leave it out")
    return UserTestOptions(
        params=Path(args.params) if args.params else None,
        allow_clipping=args.allow_clipping,
        gamut_map=args.gamut_map,
        **_common(args),
    )


def _print_usertest(result: Any) -> int:
    print(f"log: {result.log_path}")
    for line in result.summary_lines():
        print(f"  {line}")
    return int(result.exit_code)  # result.message was shown when the session stopped


# The first row whose test matches wins; the threshold session is the default.
KINDS: tuple[SessionCommand, ...] = (
    SessionCommand(
        "usertest",
        "masking_lab.usertest.runner:USERTEST",
        _is_usertest_protocol,
        _is_usertest_log,
        _usertest_options,
        _print_usertest,
    ),
    SessionCommand(
        "threshold",
        "masking_lab.session.runner:THRESHOLD",
        lambda _: True,
        lambda _: True,
        _threshold_options,
        _print_threshold,
    ),
)


def for_protocol(path: str) -> SessionCommand:
    """The kind that runs the protocol at ``path``."""
    return next(k for k in KINDS if k.is_protocol(path))


def for_log(path: str) -> SessionCommand:
    """The kind that resumes the session log at ``path``."""
    return next(k for k in KINDS if k.is_log(path))
