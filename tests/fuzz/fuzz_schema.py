"""Schema-driven inputs for the campaign: random documents drawn from a JSON Schema (the subset
the project's schemas use), leaning on the edges a hand-written file rarely reaches.

Numbers are drawn at and next to their bounds (one ulp inside), at 0, ±1e-300, denormals and
±1e300 when unbounded; strings follow their ``pattern`` where a small pattern sampler knows it,
else come from short stimulus-like names; objects get their required keys and a random share of
the optional ones. Most draws are valid by construction, so the commands behind ``validate`` are
exercised too (what ``validate`` accepts must run: issue 21.2, 21.3).
"""

from __future__ import annotations

import json
import math
import random
import re
from typing import Any

from masking_lab.formats.resources import shipped

__all__ = ["draw", "schema"]

_STIMULI = ["EV270", "MV120", "MV180", "MV270", "MV120am40", "EV120", "MV90.5", "EV270am10"]
_SPECIAL = [0.0, 1e-300, -1e-300, 5e-324, 1e300, -1e300, 1.0, -1.0, 0.5]


def schema(name: str) -> dict[str, Any]:
    """The shipped ``data_schema/<name>.schema.json``."""
    return json.loads(shipped("data_schema", f"{name}.schema.json").read_text(encoding="utf-8"))


def draw(s: dict[str, Any], rng: random.Random, root: dict[str, Any] | None = None) -> Any:
    """One random instance of schema ``s`` (``root`` resolves ``$ref``)."""
    return _draw(s, rng, root or s, 0)


def _draw(s: Any, rng: random.Random, root: dict[str, Any], depth: int) -> Any:
    if not isinstance(s, dict):
        return None
    if "$ref" in s:
        target: Any = root
        for part in s["$ref"].removeprefix("#/").split("/"):
            target = target[part]
        return _draw({**target, **{k: v for k, v in s.items() if k != "$ref"}}, rng, root, depth)
    if "const" in s:
        return s["const"]
    if "enum" in s:
        return rng.choice(s["enum"])
    for key in ("oneOf", "anyOf"):
        if key in s:
            rest = {k: v for k, v in s.items() if k != key}
            branch = rng.choice(s[key])
            merged = {**rest, **branch}
            if "required" in rest and "required" in branch:
                merged["required"] = [*rest["required"], *branch["required"]]
            if "properties" in rest and "properties" in branch:
                merged["properties"] = {**rest["properties"], **branch["properties"]}
            return _draw(merged, rng, root, depth)
    if "allOf" in s:
        merged = {k: v for k, v in s.items() if k != "allOf"}
        for part in s["allOf"]:
            merged.update(part)
        return _draw(merged, rng, root, depth)
    kind = s.get("type")
    if isinstance(kind, list):
        kind = rng.choice(kind)
    if kind is None:
        kind = "object" if "properties" in s else ("array" if "items" in s else "number")
    if kind == "object":
        return _object(s, rng, root, depth)
    if kind == "array":
        lo = s.get("minItems", 0)
        hi = min(s.get("maxItems", lo + 4), lo + (4 if depth < 3 else 1))
        items = s.get("items", {})
        return [_draw(items, rng, root, depth + 1) for _ in range(rng.randint(lo, max(lo, hi)))]
    if kind in ("number", "integer"):
        return _number(s, rng, integer=kind == "integer")
    if kind == "string":
        return _string(s, rng)
    if kind == "boolean":
        return rng.random() < 0.5
    return None


def _object(s: dict[str, Any], rng: random.Random, root: dict[str, Any], depth: int) -> Any:
    props = s.get("properties", {})
    required = set(s.get("required", []))
    out: dict[str, Any] = {}
    for key, sub in props.items():
        if key in required or (depth < 4 and rng.random() < 0.5):
            out[key] = _draw(sub, rng, root, depth + 1)
    extra = s.get("additionalProperties")
    if isinstance(extra, dict) and not props:
        names = s.get("propertyNames", {})
        n = max(s.get("minProperties", 0), rng.randint(1, 3))
        for _ in range(n):
            out[_string(names, rng) if names else rng.choice(_STIMULI)] = _draw(
                extra, rng, root, depth + 1
            )
    return out


def _number(s: dict[str, Any], rng: random.Random, *, integer: bool) -> Any:
    lo, hi = s.get("minimum"), s.get("maximum")
    xlo, xhi = s.get("exclusiveMinimum"), s.get("exclusiveMaximum")
    if xlo is not None and (lo is None or xlo >= lo):
        lo = math.nextafter(xlo, math.inf) if not integer else math.floor(xlo) + 1
    if xhi is not None and (hi is None or xhi <= hi):
        hi = math.nextafter(xhi, -math.inf) if not integer else math.ceil(xhi) - 1
    if integer:
        a = int(lo) if lo is not None else -5
        b = int(hi) if hi is not None else a + 1000
        return rng.choice([a, b, rng.randint(a, max(a, b)), rng.randint(a, max(a, min(b, a + 5)))])
    candidates = [v for v in (lo, hi) if v is not None]
    if lo is not None and hi is not None:
        candidates.append(rng.uniform(lo, hi))
    candidates += [v for v in _SPECIAL if (lo is None or v >= lo) and (hi is None or v <= hi)]
    return float(rng.choice(candidates or [0.0]))


_PATTERN_STIMULUS = re.compile(r"\^\(EV\|MV\)")


def _string(s: dict[str, Any], rng: random.Random) -> str:
    pattern = s.get("pattern", "")
    if _PATTERN_STIMULUS.match(pattern) or "EV|MV" in pattern:
        return rng.choice(_STIMULI)
    lo = s.get("minLength", 1)
    letters = "abcdefghijklmnopqrstuvwxyz_0123456789"
    text = "".join(rng.choice(letters) for _ in range(rng.randint(max(1, lo), max(lo, 8))))
    if pattern and not re.search(pattern, text):
        return rng.choice(["a", "x1", "set_1", *_STIMULI])
    return text
