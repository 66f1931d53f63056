"""Rendering: the inverse of mutual masking, applied to scenes (paper §3).

Given fitted masking functions, the rendering wing turns what a scene should *feel* like (perceived
MV and EV levels, dB SL, per haptic interaction point) into the inputs to play.

- :mod:`~masking_lab.rendering.pair`: :class:`MutualMasking`, the two masking ramps of one MV/EV
  pair, and :func:`pair_from_params` (from a parsed ``masking_params.json``).
- :mod:`~masking_lab.rendering.ramp_inverse`: the four-case closed form and how many answers a
  target has (none, one, several).
- :mod:`~masking_lab.rendering.solver`: the public solver (:func:`solve` on arrays,
  :func:`forward`); re-exports the names of the two modules above.
- :mod:`~masking_lab.rendering.gamut`: the perceptual gamut, the exact image of the rated input
  box (:func:`perceptual_gamut`); :mod:`~masking_lab.rendering.mapping`: bringing a scene's
  targets into it (clip, scale, compress); :mod:`~masking_lab.rendering.uncertainty`: the fits'
  uncertainty carried to per-point intervals of what is felt.
- :mod:`~masking_lab.rendering.scene`: scenes (path, geometry by EV, texture by MV);
  :func:`parse_scene` is pure, :func:`load_scene` reads a file.
- :mod:`~masking_lab.rendering.render`: :func:`render_scene` and :func:`summarize` (pure).
- :mod:`~masking_lab.rendering.outputs`: ``points.csv``, ``summary.json``, the figure and the
  measurement protocol written to disk.
- :mod:`~masking_lab.rendering.figures`: the Figure-4-like PNG;
  :mod:`~masking_lab.rendering.gamut_figure`: the gamut after the paper's Figure 6.

Imports point one way: ramp_inverse ← pair ← solver ← gamut ← mapping ← render ← uncertainty ←
figures ← outputs.
"""

from masking_lab.core.exports import lazy_exports

_HOME = {
    "MutualMasking": "pair",
    "Rendering": "render",
    "Scene": "scene",
    "Solution": "solver",
    "forward": "solver",
    "perceptual_gamut": "gamut",
    "load_scene": "scene",
    "pair_from_params": "pair",
    "parse_scene": "scene",
    "render_scene": "render",
    "solve": "solver",
    "summarize": "render",
}
__all__ = sorted(_HOME)
__getattr__, __dir__ = lazy_exports(__name__, _HOME)
