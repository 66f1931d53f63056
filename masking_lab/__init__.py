"""masking_lab: tactile masking psychophysics after Ryu et al. (2020).

The functional core (staircase, levels, masking functions, solver, fits, statistics) is pure and
importable without PsychoPy or hardware; devices, files, clocks and windows live at the edges.
"""

__version__ = "0.1.0"
