"""Who answers a 3IFC trial: a simulated observer, a terminal keypad, or a PsychoPy window.

- ``base``: the :class:`Responder` interface; ``sim``: a simulated participant; ``keys``: the
  keypad and its terminal, ``KeyReader`` (*shell*); ``psychopy_window``: the 3IFC window and
  ``participant_window``, the window it shares with the user test (*shell*, optional PsychoPy).
- ``cue``: the moving cue's geometry and timing; ``pink_noise``: the masking noise.
"""

from masking_lab.core.exports import lazy_exports

_HOME = {
    "KeyReader": "keys",
    "KeysResponder": "keys",
    "Responder": "base",
    "Response": "base",
    "SimResponder": "sim",
}
__all__ = sorted(_HOME)
__getattr__, __dir__ = lazy_exports(__name__, _HOME)
