"""Test-suite settings shared by every file.

Property tests (hypothesis) draw their examples from a fixed seed, so a CI run is repeatable:
a failure found once is found again by the same command. ``HYPOTHESIS_PROFILE=explore`` draws
fresh random examples instead, for hunting locally.
"""

from __future__ import annotations

import os

from hypothesis import settings

settings.register_profile("repeatable", derandomize=True, print_blob=True)
settings.register_profile("explore", derandomize=False, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "repeatable"))
