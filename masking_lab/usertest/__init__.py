"""The user test (paper §3.3): objects played with and without compensation, identified by
participants.

- ``design``: the protocol, its trial order and objects (pure); ``playback``, ``stream``: the
  levels a trial streams, with limits, clipping and dead-band.
- ``runner``: the user-test kind in the session frame; ``preparation``: checks and header;
  ``session_loop``: the trial loop.
- ``responder_base``, ``sim_responder``, ``keys_responder``, ``window_responder``: who answers.
- ``observer``, ``stats``, ``report``: simulated identification and the analysis of user-test
  logs.
"""

from masking_lab.core.exports import lazy_exports

_HOME = {
    "UserTestDesign": "design",
    "UserTestOptions": "runner",
    "UserTestResult": "session_loop",
    "analyze_usertest": "stats",
    "load_usertest": "design",
    "parse_usertest": "design",
    "resume_usertest": "runner",
    "run_usertest": "runner",
    "trial_list": "design",
    "write_usertest_report": "report",
}
__all__ = sorted(_HOME)
__getattr__, __dir__ = lazy_exports(__name__, _HOME)
