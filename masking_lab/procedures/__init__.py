"""Adaptive threshold procedures behind one interface (:mod:`.base`).

:mod:`.staircase` (transformed up-down, the paper's) and :mod:`.quest_plus` (QUEST+ and
psi-marginal), with vectorised simulators (:mod:`.staircase_batch`, :mod:`.quest_plus_batch`,
both returning a :class:`~.batch.TrackBatch`),
estimators (:mod:`.estimators`, :mod:`.ml_batch`), the Cramér-Rao bound (:mod:`.fisher`,
:mod:`.efficiency`) and down/up ratios (:mod:`.downup_ratio`). See docs/procedures.md.
"""

from masking_lab.core.exports import lazy_exports

_HOME = {
    "Procedure": "base",
    "ProcedureSettings": "base",
    "QuestPlus": "quest_plus",
    "QuestPlusSettings": "quest_plus",
    "Staircase": "staircase",
    "StaircaseSettings": "staircase",
    "ThresholdEstimate": "base",
    "TrackBatch": "batch",
    "cramer_rao_sd": "fisher",
    "fisher_information": "fisher",
    "ml_threshold": "estimators",
    "replay": "base",
    "reversal_mean_al": "estimators",
}
__all__ = sorted(_HOME)
__getattr__, __dir__ = lazy_exports(__name__, _HOME)
