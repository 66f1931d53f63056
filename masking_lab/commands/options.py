"""Options that several commands share, declared once so their names and help agree."""

from __future__ import annotations

import argparse
import re
import textwrap
from typing import TypedDict

__all__ = [
    "add_scheduler_option",
    "check_scheduler",
    "command_texts",
    "output_folder",
    "progress_flags",
    "rating_options",
    "session_options",
]


def finite_float(text: str) -> float:
    """argparse type: a finite number (NaN and infinities are refused with a usage error).

    Examples
    --------
    >>> finite_float("30")
    30.0
    >>> finite_float("inf")
    Traceback (most recent call last):
    argparse.ArgumentTypeError: 'inf' is not a finite number
    """
    import math

    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text[:40]!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text[:40]!r} is not a finite number")
    return value


def output_folder(text: str) -> str:
    """argparse type of every ``--out``: a folder name, refusing an empty one.

    ``--out "$OUT"`` with ``OUT`` unset is ``--out ""``, which is the current folder: the demo
    wrote its folders there and ``plan`` ran its whole simulation before failing to replace
    it. Refused before any work, with what to give.

    Examples
    --------
    >>> output_folder("results/study1")
    'results/study1'
    >>> output_folder("")
    Traceback (most recent call last):
    argparse.ArgumentTypeError: an empty name (an unset shell variable?); give the output folder
    """
    if not text.strip():
        raise argparse.ArgumentTypeError(
            "an empty name (an unset shell variable?); give the output folder"
        )
    return text


def add_scheduler_option(p: argparse.ArgumentParser) -> None:
    """``--scheduler`` (plan, study): where the simulations' chunks run.

    Examples
    --------
    >>> p = argparse.ArgumentParser()
    >>> add_scheduler_option(p)
    >>> p.parse_args([]).scheduler, p.parse_args(["--scheduler", "tcp://h:8786"]).scheduler
    ('local', 'tcp://h:8786')
    """
    p.add_argument(
        "--scheduler",
        type=check_scheduler,
        default="local",
        metavar="ADDRESS",
        help="where the simulations run, in chunks of replicates: 'local' (worker processes "
        "on this machine, one per core; default), 'synchronous' (this process) or a Dask "
        "scheduler's address (tcp://host:8786; its workers need masking_lab installed); the "
        "same --seed gives the same tables on any",
    )


_DASK_ADDRESS = re.compile(r"^(tcp|tls|ucx|ws|wss|inproc)://\S+$")


def check_scheduler(text: str) -> str:
    """``--scheduler``'s value: ``local``, ``synchronous`` or a Dask address (argparse type).

    Examples
    --------
    >>> check_scheduler("tcp://10.0.0.5:8786")
    'tcp://10.0.0.5:8786'
    >>> check_scheduler("10.0.0.5")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    argparse.ArgumentTypeError: '10.0.0.5' is not local, synchronous or a Dask scheduler ...
    """
    if text in ("local", "synchronous") or _DASK_ADDRESS.match(text):
        return text
    raise argparse.ArgumentTypeError(
        f"{text[:80]!r} is not local, synchronous or a Dask scheduler address such as "
        "tcp://host:8786"
    )


def rating_options(p: argparse.ArgumentParser, device_config_help: str) -> None:
    """``--max-mv-db-sl``, ``--max-ev-db-sl`` and ``--device-config`` (render, solve).

    Parameters
    ----------
    p : argparse.ArgumentParser
        The command's parser.
    device_config_help : str
        What the rig config means for this command (its default differs).

    Examples
    --------
    >>> p = argparse.ArgumentParser()
    >>> rating_options(p, "rig config")
    >>> p.parse_args(["--max-mv-db-sl", "30"]).max_mv_db_sl
    30.0
    """
    p.add_argument(
        "--max-mv-db-sl", type=finite_float, metavar="DB", help="rated maximum MV input, dB SL"
    )
    p.add_argument(
        "--max-ev-db-sl", type=finite_float, metavar="DB", help="rated maximum EV input, dB SL"
    )
    p.add_argument("--device-config", metavar="FILE", help=device_config_help)


def session_options(p: argparse.ArgumentParser, device_config_help: str, tty_help: str) -> None:
    """``--device-config``, ``--participant-tty`` and the progress flags (run, resume).

    Parameters
    ----------
    p : argparse.ArgumentParser
        The command's parser.
    device_config_help, tty_help : str
        Help texts (a resumed session defaults to the config it started with).

    Examples
    --------
    >>> p = argparse.ArgumentParser()
    >>> session_options(p, "rig config", "terminal")
    >>> p.parse_args(["--no-progress"]).progress
    False
    """
    p.add_argument("--device-config", metavar="FILE", help=device_config_help)
    p.add_argument("--participant-tty", metavar="PATH", help=tty_help)
    progress_flags(p)


def progress_flags(p: argparse.ArgumentParser) -> None:
    """``--progress`` / ``--no-progress``: force the progress line on or off (default: on a tty).

    Examples
    --------
    >>> p = argparse.ArgumentParser()
    >>> progress_flags(p)
    >>> p.parse_args([]).progress is None
    True
    """
    group = p.add_mutually_exclusive_group()
    group.add_argument(
        "--progress",
        dest="progress",
        action="store_const",
        const=True,
        help="show the progress line even when stderr is not a terminal",
    )
    group.add_argument(
        "--no-progress", dest="progress", action="store_const", const=False, help="hide it"
    )


class CommandTexts(TypedDict):
    """The ``help`` and ``description`` keywords of ``add_parser`` (a TypedDict, so that the
    ``**command_texts(...)`` splat is checked against argparse's signature)."""

    help: str
    description: str


def command_texts(doc: str | None) -> CommandTexts:
    """``help`` and ``description`` for a sub-parser, from its command module's docstring.

    The docstring's first paragraph is ``\\`\\`SYNTAX\\`\\`: help.``; its second paragraph is the
    description (later paragraphs are notes for developers). Keeping the texts there puts
    what a command does at the top of its module.

    Examples
    --------
    >>> command_texts("``masking-lab x``: do a thing.\\n\\nLonger\\nwords.\\n\\nDev notes.")
    {'help': 'do a thing', 'description': 'Longer words.'}
    """
    first, description, *_ = [*(doc or "").split("\n\n"), ""]
    help_text = " ".join(first.split()).split(": ", 1)[-1].removesuffix(".")
    return {"help": help_text, "description": textwrap.fill(" ".join(description.split()), 78)}
