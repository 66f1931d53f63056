"""A session's protocol parsed once per distinct content: what load_protocol gives, re-read
every time, re-parsed when the file changes, and a refusal raised every time."""

from __future__ import annotations

import dataclasses
import shutil

import pytest

from masking_lab.core.errors import ProtocolError
from masking_lab.formats.protocol import load_protocol
from masking_lab.formats.resources import shipped
from masking_lab.session.runner import load_protocol_once

LIMITS = {"EV": 40.0, "MV": 45.0}


def _fields(protocol):
    return {f.name: getattr(protocol, f.name) for f in dataclasses.fields(protocol)}


def test_the_same_protocol_as_load_protocol_and_one_object_per_content(tmp_path):
    path = tmp_path / "experiment1.yaml"
    shutil.copy(str(shipped("protocols", "experiment1.yaml")), path)
    once = load_protocol_once(path, LIMITS)
    assert _fields(once) == _fields(load_protocol(path, max_level_db_sl=LIMITS))
    assert load_protocol_once(str(path), dict(LIMITS)) is once
    assert load_protocol_once(path, {"EV": 30.0, "MV": 45.0}) is not once
    # an edited file is parsed again, not answered from memory
    path.write_text(path.read_text().replace("max_trials: 150", "max_trials: 120"))
    edited = load_protocol_once(path, LIMITS)
    assert edited.sha256 != once.sha256
    assert edited.content["staircase"]["max_trials"] == 120
    assert _fields(edited) == _fields(load_protocol(path, max_level_db_sl=LIMITS))


def test_a_refused_protocol_is_refused_every_time(tmp_path):
    path = tmp_path / "broken.yaml"
    path.write_text("schema_version: 1\nexperiment: [\n")
    for _ in range(2):
        with pytest.raises(ProtocolError):
            load_protocol_once(path, LIMITS)
    with pytest.raises(ProtocolError):
        load_protocol_once(tmp_path / "missing.yaml", LIMITS)
