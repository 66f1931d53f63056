"""The part of a session log's header every session kind writes the same way.

The fields are those of ``data_schema/session_log.schema.json`` (``header``): what was run
(the protocol's path, hash, experiment and a copy of its content, so resume never re-reads the
file), who and with what (participant, calibration in dB re 1 V, device identity, responder,
seed, set order, clock kind), the simulated observer, the rig config's path and its rig record.
A kind adds its own fields (the user test: ``kind`` and ``usertest``) after the clock.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

from masking_lab import __version__
from masking_lab.device.base import DeviceIdentity
from masking_lab.device.config import load_device_config
from masking_lab.formats.records import jsonable
from masking_lab.session.shell import device_record, utc_now

__all__ = ["RunSource", "session_header"]


class RunSource(Protocol):
    """What a session runs: a threshold protocol or a user-test design (read-only)."""

    @property
    def path(self) -> str: ...
    @property
    def sha256(self) -> str: ...
    @property
    def experiment(self) -> str: ...
    @property
    def content(self) -> Any: ...


def session_header(
    *,
    source: RunSource,
    participant: str,
    calibration: Mapping[str, float],
    device: DeviceIdentity,
    responder: str,
    seed: int,
    order: Sequence[str],
    virtual: bool,
    observer: dict[str, Any] | None,
    device_config: Path | None,
    **kind_fields: Any,
) -> dict[str, Any]:
    """A new session's header record, in the schema's key order.

    Parameters
    ----------
    source : RunSource
        The protocol or user-test design (its file's path and sha256, experiment id, content).
    participant : str
        Participant id.
    calibration : mapping of str to float
        Unmasked AL per stimulus, dB re 1 V (empty for a baseline session).
    device : DeviceIdentity
        The opened device.
    responder : str
        The responder's name.
    seed : int
        Session seed.
    order : sequence of str
        Set ids in the order they run (empty for a user test).
    virtual : bool
        True for a virtual clock.
    observer : dict or None
        The simulated observer record.
    device_config : Path or None
        The rig config (None: the packaged reference rig).
    **kind_fields
        The kind's own fields, placed after ``clock``.

    Returns
    -------
    dict
        The header (``created_utc`` now, UTC).
    """
    header: dict[str, Any] = {
        "schema_version": 1,
        "created_utc": utc_now(),
        "software_version": __version__,
        "protocol": {
            # Absolute, so resume can compare the file from any working directory.
            "path": str(Path(source.path).resolve()),
            "sha256": source.sha256,
            "experiment": source.experiment,
            "content": jsonable(source.content),
        },
        "participant": participant,
        "calibration": dict(calibration),
        "device": device_record(device),
        "responder": responder,
        "seed": int(seed),
        "set_order": list(order),
        "clock": "virtual" if virtual else "real",
        **kind_fields,
    }
    if observer is not None:
        header["simulated_observer"] = observer
    if device_config is not None:
        header["device_config"] = str(Path(device_config).resolve())
    header["rig"] = load_device_config(device_config).rig_record()
    return header
