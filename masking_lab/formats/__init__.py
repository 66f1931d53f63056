"""One reader and one writer per file kind, on one safe YAML/JSON reader.

- ``reader``: the shared reader (size, alias and depth limits, strict UTF-8, duplicate keys).
- ``protocol``: threshold protocols; ``calibration``: a participant's unmasked ALs;
  ``masking_params``: the exported masking functions; ``shifts_csv``: a table of AL shifts.
- ``session_log``: session logs (reader and crash-safe writer); ``records``: the one record
  encoding and its policy for non-finite numbers.
- ``schemas``: the JSON Schemas of ``data_schema/``; ``resources``: shipped files.
- ``fileio``, ``output_dir``: atomic fsynced writes and output folders swapped in when complete
  (*shell*).
"""

from masking_lab.core.exports import lazy_exports

_HOME = {
    "Calibration": "calibration",
    "SessionLog": "session_log",
    "SessionLogWriter": "session_log",
    "SetSpec": "protocol",
    "ThresholdProtocol": "protocol",
    "encode_record": "records",
    "jsonable": "records",
    "load_calibration": "calibration",
    "load_masking_params": "masking_params",
    "load_protocol": "protocol",
    "parse_protocol": "protocol",
    "protocol_from_mapping": "protocol",
    "read_log": "session_log",
    "read_shifts_csv": "shifts_csv",
    "shipped": "resources",
    "write_bytes_atomic": "fileio",
    "write_masking_params": "masking_params",
    "write_text_atomic": "fileio",
}
__all__ = sorted(_HOME)
__getattr__, __dir__ = lazy_exports(__name__, _HOME)
