"""Simulated participants and synthetic session logs.

- ``observer``: ground truth (unmasked ALs, masking ramps, psychometric slope) and simulated
  participants drawn from it.
- ``synthetic_logs``: whole studies of session logs written without running sessions, for
  tests and benchmarks.
"""

from masking_lab.core.exports import lazy_exports

_HOME = {
    "GroundTruth": "observer",
    "SimulatedParticipant": "observer",
    "ground_truth_from_dict": "observer",
    "load_ground_truth": "observer",
    "make_participant": "observer",
    "simulate_session": "synthetic_logs",
    "simulate_study": "synthetic_logs",
}
__all__ = sorted(_HOME)
__getattr__, __dir__ = lazy_exports(__name__, _HOME)
