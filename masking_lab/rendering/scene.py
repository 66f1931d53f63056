"""Scenes: a 1-D path of haptic interaction points with geometry by EV and texture by MV.

Paper §3.1 and §3.3. The finger (or the cue, at 51 mm/s) moves along +x. Geometry is a surface
height profile h(x) rendered by EV from its gradient; texture is a constant perceived MV level.

Geometry (all four share the same height and the same steepest inclination, as in the paper):

==========  ============================================================  ===================
shape       height h(x), mm                                               width from
==========  ============================================================  ===================
bump        H·exp(−(x − p)²/(2σ²))                                         σ = H·e^(−1/2)/s_max
hole        −H·exp(−(x − p)²/(2σ²))                                        σ = H·e^(−1/2)/s_max
ascending   H·exp((x − p)/λ) for x ≤ p, then H (top of the slope at p)     λ = H/s_max
descending  H for x < p, then H·exp(−(x − p)/λ) (top of the slope at p)    λ = H/s_max
==========  ============================================================  ===================

The EV target is the signed gradient mapped linearly onto the perceived range [lo, hi] dB SL:
``e_p(x) = lo + (hi − lo)·(1 + h'(x)/s_max)/2``. Going uphill feels stronger, downhill weaker,
level ground sits mid-range, so all four shapes give distinct profiles (a gradient *magnitude*
mapping would make a bump and a hole identical). The paper cites gradient-based rendering [21]
without the exact mapping; this is our choice, documented in docs/scenes.md.

Texture: the MV stimulus (carrier, optional envelope, e.g. ``MV120am40``) at a constant perceived
level (smooth 6 dB SL, rough and coarse 12 dB SL in the paper).

Everything here is pure except :func:`load_scene`, which reads a YAML file; it is a thin reader
over :func:`parse_scene_text` (YAML in memory) and :func:`parse_scene` (an already parsed
mapping, validated against ``data_schema/scene.schema.json``).
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from masking_lab.core.errors import ProtocolError
from masking_lab.core.stimulus import parse_stimulus
from masking_lab.formats.reader import decode_utf8, excerpt, parse_yaml, read_limited
from masking_lab.formats.schemas import (
    describe_type_error,
    first_problem,
)

__all__ = [
    "SHAPES",
    "GeometrySpec",
    "PathSpec",
    "Scene",
    "Shape",
    "TextureSpec",
    "load_scene",
    "parse_scene",
    "parse_scene_text",
]

# The most interaction points a scene may ask for: beyond this the arrays and figure of one
# rendering would take minutes and gigabytes (a typo of 919 as 919999999 must not hang).
MAX_POINTS = 100_000

Shape = Literal["bump", "hole", "ascending", "descending"]
SHAPES: tuple[Shape, ...] = ("bump", "hole", "ascending", "descending")


@dataclass(frozen=True)
class PathSpec:
    """The path the finger travels.

    Attributes
    ----------
    length_mm : float
        Path length, mm (91.8 mm: 1.8 s at 51 mm/s).
    n_points : int
        Haptic interaction points, evenly spaced from 0 to ``length_mm``.
    speed_mm_s : float
        Speed of the cue along the path, mm/s.
    """

    length_mm: float = 91.8
    n_points: int = 919
    speed_mm_s: float = 51.0

    def positions_mm(self) -> NDArray[np.float64]:
        """Interaction points along the path, mm."""
        return np.linspace(0.0, self.length_mm, self.n_points)

    @property
    def duration_s(self) -> float:
        """Time the cue takes to cover the path, s."""
        return self.length_mm / self.speed_mm_s


@dataclass(frozen=True)
class GeometrySpec:
    """A surface shape rendered by EV.

    Attributes
    ----------
    shape : {"bump", "hole", "ascending", "descending"}
        Profile (Gaussian for bump and hole, exponential for the slopes).
    stimulus : str
        EV stimulus name, e.g. ``"EV270"``.
    position_mm : float
        Centre of a bump or hole, or the top of a slope (where it is steepest), mm along the path.
    height_mm : float
        Height H of the shape, mm (> 0).
    max_inclination : float
        Steepest gradient s_max, mm/mm (> 0); sets the width.
    perceived_db_sl : tuple[float, float]
        (lo, hi): EV target at the steepest descent and the steepest ascent, dB SL.
    """

    shape: Shape
    stimulus: str = "EV270"
    position_mm: float = 45.9
    height_mm: float = 2.0
    max_inclination: float = 0.25
    perceived_db_sl: tuple[float, float] = (0.0, 10.0)

    @property
    def width_mm(self) -> float:
        """σ of the Gaussian (bump, hole) or length constant λ of the exponential, mm."""
        if self.shape in ("bump", "hole"):
            return self.height_mm * math.exp(-0.5) / self.max_inclination
        return self.height_mm / self.max_inclination

    def height_profile_mm(self, x_mm: ArrayLike) -> NDArray[np.float64]:
        """Surface height h(x) in mm at path positions ``x_mm`` (mm)."""
        z = np.asarray(x_mm, dtype=float) - self.position_mm
        w, h = self.width_mm, self.height_mm
        if self.shape == "bump":
            return h * np.exp(-0.5 * (z / w) ** 2)
        if self.shape == "hole":
            return -h * np.exp(-0.5 * (z / w) ** 2)
        if self.shape == "ascending":
            return h * np.exp(np.minimum(z, 0.0) / w)
        return h * np.exp(-np.maximum(z, 0.0) / w)

    def gradient(self, x_mm: ArrayLike) -> NDArray[np.float64]:
        """Surface gradient dh/dx (mm/mm) at ``x_mm``; its extremes are ±``max_inclination``."""
        z = np.asarray(x_mm, dtype=float) - self.position_mm
        w = self.width_mm
        h = self.height_profile_mm(x_mm)
        if self.shape in ("bump", "hole"):
            return -(z / w) * (h / w)  # not z / w**2: w**2 overflows or underflows first
        if self.shape == "ascending":
            return np.where(z <= 0.0, h / w, 0.0)
        return np.where(z >= 0.0, -h / w, 0.0)

    def target_db_sl(self, x_mm: ArrayLike) -> NDArray[np.float64]:
        """Perceived EV target e_p(x) in dB SL from the signed gradient (module docstring)."""
        lo, hi = self.perceived_db_sl
        unit = np.clip(self.gradient(x_mm) / self.max_inclination, -1.0, 1.0)
        return lo + (hi - lo) * 0.5 * (1.0 + unit)


@dataclass(frozen=True)
class TextureSpec:
    """A texture rendered by MV at a constant perceived level.

    Attributes
    ----------
    name : str
        Texture label (``smooth``, ``rough``, ``coarse``).
    stimulus : str
        MV stimulus name: carrier and optional envelope, e.g. ``"MV180"`` or ``"MV120am40"``.
    perceived_db_sl : float
        Perceived MV target m_p, dB SL.
    """

    name: str
    stimulus: str
    perceived_db_sl: float

    def target_db_sl(self, x_mm: ArrayLike) -> NDArray[np.float64]:
        """Perceived MV target m_p(x) in dB SL (constant along the path)."""
        return np.full(np.shape(x_mm), float(self.perceived_db_sl))


@dataclass(frozen=True)
class Scene:
    """A path with a geometry, a texture, or both.

    Attributes
    ----------
    name : str
        Scene id.
    path : PathSpec
        The interaction points.
    geometry : GeometrySpec or None
        EV channel, or None if the scene has no geometry.
    texture : TextureSpec or None
        MV channel, or None if the scene has no texture.
    description : str
        Free text.
    source : str
        File it came from (or ``"<memory>"``).
    sha256 : str
        Hash of the file's bytes ("" when built in memory).
    """

    name: str
    path: PathSpec
    geometry: GeometrySpec | None
    texture: TextureSpec | None
    description: str = ""
    source: str = "<memory>"
    sha256: str = ""

    def __post_init__(self) -> None:
        if self.geometry is None and self.texture is None:
            raise ProtocolError(
                self.source, "(top level)", "a scene needs `geometry:`, `texture:` or both"
            )

    @property
    def single_channel(self) -> bool:
        """True when only one channel plays: nothing masks it, targets pass straight through."""
        return self.geometry is None or self.texture is None

    def stimulus_pairs(self) -> list[tuple[str, str]]:
        """(MV stimulus, EV stimulus) pairs whose mutual masking this scene needs (0 or 1)."""
        if self.geometry is None or self.texture is None:
            return []
        return [(self.texture.stimulus, self.geometry.stimulus)]

    def targets(
        self,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """``(x_mm, mv_target_db_sl, ev_target_db_sl)`` per point; an absent channel is −inf."""
        x = self.path.positions_mm()
        off = np.full(x.shape, -np.inf)
        mv = self.texture.target_db_sl(x) if self.texture is not None else off
        ev = self.geometry.target_db_sl(x) if self.geometry is not None else off.copy()
        return x, mv, ev


# --------------------------------------------------------------------------------------------
# Files


def load_scene(path: str | Path) -> Scene:
    """Read a scene YAML file and build it with :func:`parse_scene_text`.

    Raises
    ------
    ProtocolError
        Naming the file and key path (and line, for malformed YAML) and what to change.
    """
    p = Path(path)
    return parse_scene_text(read_limited(p, what="scene"), str(p))


def parse_scene_text(raw: bytes | str, source: str = "<memory>") -> Scene:
    """Parse scene YAML already in memory (safe loader) and build it with :func:`parse_scene`.

    Parameters
    ----------
    raw : bytes or str
        The scene file's content (str is encoded as UTF-8 for the hash).
    source : str
        Names the content in messages and on the :class:`Scene`.

    Raises
    ------
    ProtocolError
        Malformed YAML (with its line), a duplicated key, or what :func:`parse_scene` refuses.
    """
    data_bytes = raw.encode("utf-8") if isinstance(raw, str) else raw
    data, lines = parse_yaml(decode_utf8(data_bytes, source), source)
    return parse_scene(data, source, sha256=hashlib.sha256(data_bytes).hexdigest(), lines=lines)


def parse_scene(
    data: Any, source: str = "<memory>", sha256: str = "", lines: Mapping[str, int] | None = None
) -> Scene:
    """Validate an already parsed scene mapping against the schema and build a :class:`Scene`.

    Pure: no file, no YAML.

    Parameters
    ----------
    data : mapping
        The scene's content (what :func:`load_scene` parses from YAML).
    source : str
        Names the data in messages and on the :class:`Scene`.
    sha256 : str
        Hash of the bytes the content came from ("" when built in memory).
    lines : mapping of key path → line, optional
        Where each key stands in the source file, for messages.

    Raises
    ------
    ProtocolError
        Naming ``source``, the key path (and line) and what to change.
    """
    if not isinstance(data, Mapping):
        raise ProtocolError(source, "(top level)", "a scene is a YAML mapping of keys to values")
    problem = first_problem(data, "scene", lines, _describe)
    if problem:
        raise ProtocolError(source, *problem)
    path = PathSpec(**data.get("path", {}))
    if not 2 <= path.n_points <= MAX_POINTS:
        raise ProtocolError(
            source,
            "path.n_points",
            f"needs 2 to {MAX_POINTS:,} points (100 s of a 1 kHz haptic loop), got {path.n_points}",
        )
    geometry = None
    if data.get("geometry") is not None:
        g = dict(data["geometry"])
        if "perceived_db_sl" in g:
            g["perceived_db_sl"] = tuple(float(v) for v in g["perceived_db_sl"])
        geometry = GeometrySpec(**g)
        _check_channel(geometry.stimulus, "EV", source, "geometry.stimulus")
        lo, hi = geometry.perceived_db_sl
        if not lo < hi:
            raise ProtocolError(
                source,
                "geometry.perceived_db_sl",
                f"needs [lo, hi] with lo < hi dB SL, got [{lo:g}, {hi:g}]",
            )
        if not 0.0 <= geometry.position_mm <= path.length_mm:
            raise ProtocolError(
                source,
                "geometry.position_mm",
                f"{geometry.position_mm:g} mm is off the {path.length_mm:g} mm path; place the "
                "shape on it",
            )
    texture = None
    if data.get("texture") is not None:
        texture = TextureSpec(**data["texture"])
        _check_channel(texture.stimulus, "MV", source, "texture.stimulus")
    if geometry is None and texture is None:
        raise ProtocolError(source, "(top level)", "a scene needs `geometry:`, `texture:` or both")
    return Scene(
        name=data["scene"],
        path=path,
        geometry=geometry,
        texture=texture,
        description=str(data.get("description", "")).strip(),
        source=source,
        sha256=sha256,
    )


def _check_channel(name: str, channel: str, source: str, where: str) -> None:
    stim = parse_stimulus(name)
    if stim.channel != channel:
        what = "geometry is rendered by EV" if channel == "EV" else "texture is rendered by MV"
        raise ProtocolError(source, where, f"{name} is an {stim.channel} stimulus but {what}")


def _describe(err: Any) -> str:
    v, inst = err.validator, err.instance
    finite = describe_type_error(err)
    if finite is not None:
        return finite
    if v == "additionalProperties":
        known = ", ".join(err.schema.get("properties", {}))
        return f"{err.message}; known keys: {known}"
    if v == "required":
        return f"{err.message}: add it"
    if v == "enum":
        return f"must be one of {err.validator_value}, got {excerpt(inst)}"
    if v == "pattern":
        return (
            f"{excerpt(inst)} is not a stimulus name: write <EV|MV><carrier Hz>[am<envelope Hz>], "
            "e.g. EV270, MV180, MV120am40"
        )
    if v in ("minimum", "exclusiveMinimum", "maximum", "exclusiveMaximum"):
        op = {"minimum": "≥", "exclusiveMinimum": ">", "maximum": "≤", "exclusiveMaximum": "<"}[v]
        # The bounds keep every accepted scene inside float arithmetic (docs/scenes.md).
        bound = f" (the maximum of {err.validator_value:g})" if "Max" in v or v == "maximum" else ""
        return f"must be {op} {err.validator_value:g}{bound}, got {excerpt(inst)}"
    if v == "type":
        return f"must be of type {err.validator_value}, got {type(inst).__name__} {excerpt(inst)}"
    return excerpt(err.message, 160)
