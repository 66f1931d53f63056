"""Opening a session: entry-point checks, the clock kind, the device and the responder, the log.

Everything a session does before its first trial and that every session kind shares; the frame
(:mod:`masking_lab.session.frame`) calls these in order.
"""

from __future__ import annotations

import datetime as dt
import re
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import KW_ONLY, dataclass
from pathlib import Path
from typing import Any

from masking_lab.core.clock import Clock
from masking_lab.core.errors import LogError, MaskingLabError
from masking_lab.device.base import Device
from masking_lab.device.registry import check_device_spec as check_device_spec  # the one grammar
from masking_lab.formats.session_log import SessionLogWriter, SyncPolicy
from masking_lab.session.shell import Closable, close_quietly
from masking_lab.simulation.observer import GroundTruth, ground_truth_from_dict, read_ground_truth

# Matched whole (fullmatch: "$" alone would let a trailing newline through); the length limit
# keeps every file name built from the id far below NAME_MAX.
MAX_PARTICIPANT_CHARS = 64
_PARTICIPANT = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")

DeviceOpener = Callable[[str, Clock], Device]


def check_participant(participant: object) -> str:
    """The participant id, if it can name a data folder.

    Raises
    ------
    MaskingLabError
        Empty, longer than :data:`MAX_PARTICIPANT_CHARS`, or characters other than letters,
        digits, ``_``, ``-`` and ``.`` (a trailing newline included).

    Examples
    --------
    >>> check_participant("S01")
    'S01'
    """
    if not isinstance(participant, str) or len(participant) > MAX_PARTICIPANT_CHARS:
        shown = participant[:20] + "…" if isinstance(participant, str) else type(participant)
        raise MaskingLabError(
            f"--participant {shown!r}: at most {MAX_PARTICIPANT_CHARS} characters (it names the "
            "participant's data folder and log files), e.g. S01"
        )
    if not _PARTICIPANT.fullmatch(participant):
        raise MaskingLabError(
            f"--participant {participant[:40]!a}: use letters, digits, '_', '-' and '.' only "
            "(it names the participant's data folder), e.g. S01"
        )
    return participant


def use_virtual_clock(device: str, responder: str, real_time: bool) -> bool:
    """True if nothing real waits on the session: a sim responder on a simulated device.

    Then a virtual clock runs the session as fast as the computer can (``real_time`` forbids it).
    """
    if real_time or responder != "sim":
        return False
    return device == "sim" or device == "emulator"


def observer_record(ground_truth: Path | None) -> dict[str, Any]:
    """The simulated observer for the header: ground-truth path, population seed and truth.

    Parameters
    ----------
    ground_truth : Path or None
        A ground-truth YAML or JSON file; None: the shipped simulation ground truth.

    Raises
    ------
    ProtocolError
        Unreadable or malformed, or not a valid ground truth.
    """
    # Read through the shared reader and validated now, before the session starts.
    truth, source = read_ground_truth(ground_truth)
    return {"ground_truth_path": source, "population_seed": 0, "truth": truth}


@dataclass
class ResponderContext:
    """What every responder factory may need, whatever the session kind.

    Each kind's context adds what its responders play (the protocol, the rendered objects).

    Attributes
    ----------
    participant : str
        Participant id.
    seed : int
        Session seed.
    clock : Clock
        The session clock (s).
    simulated_observer : dict or None
        ``{"ground_truth_path", "population_seed", "truth"}`` for the sim responder.
    device_config : Path or None
        The rig config (the PsychoPy window reads the monitor size from it).
    participant_tty : str or None
        The participant's terminal for the keys responder (None: this one).
    """

    participant: str
    seed: int
    clock: Clock
    _: KW_ONLY
    simulated_observer: dict[str, Any] | None = None
    device_config: Path | None = None
    participant_tty: str | None = None

    def simulated_truth(self) -> tuple[GroundTruth, int, str]:
        """The sim responder's ground truth, population seed and where the truth came from.

        Without a simulated observer (a responder built outside a session), the shipped
        simulation ground truth with population seed 0.

        Examples
        --------
        >>> from masking_lab.core.clock import VirtualClock
        >>> context = ResponderContext("P01", 1, VirtualClock())
        >>> truth, population_seed, source = context.simulated_truth()
        >>> population_seed, source.endswith(".yaml")
        (0, True)
        """
        obs = self.simulated_observer or observer_record(None)
        source = str(obs.get("ground_truth_path") or "")
        seed = obs.get("population_seed")
        # the header is data: a simulated observer without its truth or seed cannot be rebuilt
        if (
            not isinstance(obs.get("truth"), dict)
            or isinstance(seed, bool)
            or not isinstance(seed, int)
        ):
            raise LogError(
                "the log header's simulated_observer lacks its 'truth' mapping or integer "
                "'population_seed', so the simulated participant cannot be rebuilt; the header "
                "was edited: restore it from a backup or start a new session"
            )
        truth = ground_truth_from_dict(obs["truth"], source or "the ground truth")
        return truth, seed, source


# --------------------------------------------------------------------------------------------
# Closing what opened if a later step fails, creating the log


@contextmanager
def close_on_failure(device: Device, responder: Closable) -> Iterator[None]:
    """Close ``device`` and ``responder`` if the block raises, then re-raise.

    For the steps between opening them and handing them to the session loop (which closes
    them itself), so a refused start never leaves a port or a window open.
    """
    try:
        yield
    except BaseException:
        close_quietly(device, responder)
        raise


def sync_policy(virtual: bool) -> SyncPolicy:
    """When the log is fsynced: per set in virtual time, per record in real time.

    In virtual time (simulation, the emulator, host firmware with ``--virtual-time``) nobody's
    time is lost with a trial and the fsync would be half the run time; at a rig every trial is
    a participant's time. Either way a completed set is never lost (see
    :mod:`masking_lab.formats.session_log`).

    Examples
    --------
    >>> sync_policy(True), sync_policy(False)
    ('set', 'record')
    """
    return "set" if virtual else "record"


def create_log(
    data_dir: Path,
    experiment: str,
    participant: str,
    header: Mapping[str, Any],
    *,
    sync: SyncPolicy = "record",
) -> SessionLogWriter:
    """Create a new session log under ``data_dir/<participant>/`` and write its header.

    Parameters
    ----------
    data_dir : Path
        The data folder.
    experiment, participant : str
        Name parts of the log file (see :func:`new_log_path`).
    header : mapping
        The header record; ``session_id`` (the file's stem) is added.
    sync : {"record", "set"}
        When records are fsynced (:func:`sync_policy`).

    Returns
    -------
    SessionLogWriter
        Open for appending; ``writer.path`` is the new log.
    """
    log_path = new_log_path(data_dir, experiment, participant)
    return SessionLogWriter.create(
        log_path, {**dict(header), "session_id": log_path.stem}, sync=sync
    )


def new_log_path(data_dir: Path, experiment: str, participant: str) -> Path:
    """A new log path ``data_dir/<participant>/<experiment>-<participant>-<UTC>.jsonl``.

    A session started in the same second as an existing log gets ``-2``, ``-3``, … appended.
    """
    stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%SZ")
    folder = data_dir / participant
    base = f"{experiment}-{participant}-{stamp}"
    path = folder / f"{base}.jsonl"
    n = 2
    while path.exists():  # two sessions in one second: never overwrite, number the newer one
        path = folder / f"{base}-{n}.jsonl"
        n += 1
    return path
