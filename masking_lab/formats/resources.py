"""Locate files shipped with the package: schemas (``data_schema/``) and protocols.

Installed, the two top-level folders are the packages ``masking_lab.data_schema`` and
``masking_lab.protocols``. Run from a source checkout without installing (or with the checkout
shadowing an installed copy on ``sys.path``), they are the folders beside ``masking_lab/``.
"""

from __future__ import annotations

from importlib import resources
from importlib.abc import Traversable
from pathlib import Path

_SOURCE_ROOT = Path(__file__).resolve().parents[2]


def shipped(folder: str, relative: str) -> Traversable:
    """The shipped file ``<folder>/<relative>``, e.g. ``shipped("protocols", "baseline.yaml")``.

    Parameters
    ----------
    folder : {"data_schema", "protocols"}
        Top-level folder of the source tree.
    relative : str
        Path inside it, with ``/`` separators.
    """
    try:
        base: Traversable = resources.files(f"masking_lab.{folder}")
    except ModuleNotFoundError:
        base = _SOURCE_ROOT / folder
    target = base.joinpath(*relative.split("/"))
    if not target.is_file() and (_SOURCE_ROOT / folder / relative).is_file():
        return _SOURCE_ROOT / folder / relative
    return target
