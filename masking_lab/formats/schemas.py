"""Find and apply the JSON Schemas shipped in ``data_schema/``.

The schemas are installed as the package ``masking_lab.data_schema`` so that a plain
``pip install .`` finds them; an editable install maps the same folder.
"""

from __future__ import annotations

import json
from functools import cache
from typing import Any

import jsonschema

from masking_lab.formats.resources import shipped


@cache
def load_schema(name: str) -> dict[str, Any]:
    """Return the parsed schema ``data_schema/<name>.schema.json``.

    Parameters
    ----------
    name : str
        Schema stem, e.g. ``"protocol"`` or ``"masking_params"``.
    """
    text = shipped("data_schema", f"{name}.schema.json").read_text(encoding="utf-8")
    return json.loads(text)


def schema_errors(instance: Any, name: str) -> list[jsonschema.ValidationError]:
    """All validation errors of ``instance`` against schema ``name``, in document order."""
    validator_cls = jsonschema.validators.validator_for(load_schema(name))
    validator = validator_cls(load_schema(name), format_checker=jsonschema.FormatChecker())
    return sorted(validator.iter_errors(instance), key=lambda e: [str(p) for p in e.absolute_path])


def key_path(error: jsonschema.ValidationError) -> str:
    """A dotted key path such as ``sets[3].masker_level_db_sl`` for a validation error."""
    out = ""
    for part in error.absolute_path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "(top level)"
