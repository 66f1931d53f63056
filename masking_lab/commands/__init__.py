"""The ``masking-lab`` command line: thin argparse handlers, one module per command.

``cli`` builds the parser and dispatches; ``session_kinds`` is the table ``run`` and ``resume``
use to pick the session kind from a protocol or a log. Handlers import their work on use, so
``masking-lab --help`` is fast and PsychoPy stays optional.
"""

from masking_lab.core.exports import lazy_exports

_HOME = {
    "build_parser": "cli",
    "main": "cli",
}
__all__ = sorted(_HOME)
__getattr__, __dir__ = lazy_exports(__name__, _HOME)
