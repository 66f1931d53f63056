"""Tactile output devices behind one small interface (:class:`masking_lab.device.base.Device`).

Back-ends: ``serial:PORT`` (our line protocol over pyserial), ``emulator`` (our firmware emulator
on a real pseudo-terminal, same protocol), ``sim`` (in-process), ``nidaq`` (optional, NI-DAQmx).
"""
