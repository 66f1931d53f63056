"""Threshold sessions at the rig: the one session frame and the threshold session kind.

- ``frame``: how every kind of session starts and resumes (:func:`start`, :func:`resume`).
- ``opening``, ``resuming``: the checks and openings before a session runs; ``shell``: signals,
  faults and closing (*shell*).
- ``runner``: the threshold kind (:func:`run_session`, :func:`resume_session`);
  ``threshold_plan``: its header and replay checks; ``threshold_loop``: the trial loop.
- ``trials``: pure set and trial planning; ``progress``, ``pace``: the progress line and the
  time left.
"""

from masking_lab.core.exports import lazy_exports

_HOME = {
    "ProgressLine": "progress",
    "RunOptions": "runner",
    "SessionContext": "runner",
    "SessionKind": "frame",
    "SessionOptions": "frame",
    "SessionPlan": "frame",
    "SessionResult": "threshold_loop",
    "ThresholdSession": "threshold_loop",
    "resume": "frame",
    "resume_session": "runner",
    "run_session": "runner",
    "start": "frame",
}
__all__ = sorted(_HOME)
__getattr__, __dir__ = lazy_exports(__name__, _HOME)
