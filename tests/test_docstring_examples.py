"""The Examples sections of the package's docstrings run and print what they say."""

from __future__ import annotations

import doctest
import importlib
import pkgutil

import pytest

import masking_lab

# These open a PsychoPy window on import of their examples' context; they have their own tests.
NEEDS_WINDOW = {"masking_lab.responders.psychopy_window", "masking_lab.usertest.window_responder"}

MODULES = sorted(
    info.name
    for info in pkgutil.walk_packages(masking_lab.__path__, "masking_lab.")
    if info.name not in NEEDS_WINDOW
)


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.failed == 0, f"{name}: {result.failed} of {result.attempted} examples failed"


def test_most_modules_show_an_example():
    finder = doctest.DocTestFinder()
    shown = [n for n in MODULES if any(t.examples for t in finder.find(importlib.import_module(n)))]
    # Not every module has a public function worth an example (argparse handlers, __init__s).
    assert len(shown) >= 0.55 * len(MODULES), sorted(set(MODULES) - set(shown))
