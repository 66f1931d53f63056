"""Planning: what a protocol's sessions will cost and buy, before a participant sits down.

Simulated observers run the protocol's staircases under a grid of settings; every setting is
judged by session length (trials, minutes) and threshold accuracy (bias and SD in dB).

- :mod:`~masking_lab.planning.settings`: stop rules, step schedules, the settings grid, defaults
  from a protocol, and the observers' true thresholds.
- :mod:`~masking_lab.planning.plan`: :func:`run_plan`, the simulation and its summaries
  (:class:`PlanResult`); re-exports the settings names.
- :mod:`~masking_lab.planning.report`: the text table, per-set rows, answers and CSV.
- :mod:`~masking_lab.planning.figures`: the speed–accuracy and convergence figures.
- :mod:`~masking_lab.planning.study`: the study of docs/speed-accuracy.md
  (``python -m masking_lab.planning.study``).
- :mod:`~masking_lab.planning.scene_needs`, :mod:`~masking_lab.planning.scene_protocols`,
  :mod:`~masking_lab.planning.scene_budget`, :mod:`~masking_lab.planning.scene_report`:
  ``plan --scene``, the masking functions a scene needs, the protocols that measure what is
  missing, and the scene's rendering error per budget of participants × trials.

Pure except the study's command entry point; ``masking-lab plan`` (:mod:`masking_lab.commands
.plan`) reads the protocol and writes the files.
"""

from masking_lab.core.exports import lazy_exports

_HOME = {
    "PlanResult": "plan",
    "PlanSettings": "settings",
    "format_table": "report",
    "run_plan": "plan",
}
__all__ = sorted(_HOME)
__getattr__, __dir__ = lazy_exports(__name__, _HOME)
