"""The ground truth parsed and validated once per content: the same data as reading it
afresh, a copy for each caller, re-parsed when the file changes, a refusal every time."""

from __future__ import annotations

import shutil

import pytest

from masking_lab.core.errors import ProtocolError
from masking_lab.formats.reader import load_document
from masking_lab.formats.resources import shipped
from masking_lab.simulation.observer import read_ground_truth

SHIPPED = str(shipped("protocols", "simulation/ground_truth.yaml"))


def test_the_shipped_truth_as_read_afresh_and_a_copy_for_each_caller():
    data, source = read_ground_truth()
    assert source == "protocols/simulation/ground_truth.yaml"
    assert data == load_document(SHIPPED, what="x").data
    data["unmasked_al_db_v"]["EV270"] = 99.0  # a caller's copy is its own
    assert read_ground_truth()[0] == load_document(SHIPPED, what="x").data


def test_an_edited_file_is_parsed_again_and_a_bad_one_refused_every_time(tmp_path):
    path = tmp_path / "truth.yaml"
    shutil.copy(SHIPPED, path)
    first, source = read_ground_truth(path)
    assert source == str(path)
    path.write_text(path.read_text().replace("participant_sd_db: 2.0", "participant_sd_db: 3.0"))
    assert read_ground_truth(path)[0]["participant_sd_db"] == 3.0 != first["participant_sd_db"]
    path.write_text(path.read_text().replace("participant_sd_db: 3.0", "participant_sd_db: -1"))
    for _ in range(2):
        with pytest.raises(ProtocolError, match="participant_sd_db"):
            read_ground_truth(path)
