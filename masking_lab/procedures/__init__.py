"""procedures: adaptive threshold procedures behind one interface (:mod:`.base`).

:mod:`.staircase` (transformed up-down, the paper's) and :mod:`.quest_plus` (QUEST+ and
psi-marginal), with vectorised simulators (:mod:`.staircase_batch`, :mod:`.quest_plus_batch`),
estimators (:mod:`.estimators`, :mod:`.ml_batch`), the Cramér-Rao bound (:mod:`.fisher`,
:mod:`.efficiency`) and down/up ratios (:mod:`.downup_ratio`). See docs/procedures.md.
"""
