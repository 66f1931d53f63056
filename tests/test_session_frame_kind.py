"""A third session kind, defined here, runs through the frame's start and resume on the simulator.

The worked example of docs/architecture.md ("Adding a kind of session"): a tap session plays a
fixed number of one-interval trials and logs one ``trial`` record each, in one set ``taps`` (the
log's record kinds are fixed). Everything a kind does not say (participant and device checks,
the seed, the clock, the log, locks, signals, faults, the resume records) is the frame's.
"""

from __future__ import annotations

import hashlib
import io
import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from masking_lab.core.errors import LogError, MaskingLabError
from masking_lab.core.stimulus import Stimulus
from masking_lab.core.trial import TrialPlan
from masking_lab.device.base import Device
from masking_lab.formats.session_log import SessionLog, read_log
from masking_lab.session import frame
from masking_lab.session.header import session_header
from masking_lab.session.progress import ProgressLine
from masking_lab.session.shell import EXIT_COMPLETED, EXIT_INTERRUPTED, SessionShell

TAP = Stimulus("EV", 270.0)


@dataclass(frozen=True)
class TapOptions(frame.SessionOptions):
    taps: int = 4  # the kind's own option


@dataclass(frozen=True)
class TapSource:  # what the header's "protocol" block describes (session.header.RunSource)
    path: str
    sha256: str
    experiment: str
    content: Any


@dataclass(frozen=True)
class TapResult:
    log_path: Path
    exit_code: int
    taps_logged: int


class Tapper:
    """The kind's default responder: answers every tap with its index (sim only)."""

    def answer(self, index: int) -> int:
        return index

    def close(self) -> None:
        pass


@dataclass
class TapPlan(frame.SessionPlan[TapResult]):
    source: TapSource
    taps: int
    done: int  # taps already logged (> 0 after a resume)

    @property
    def experiment(self) -> str:
        return self.source.experiment

    def context(self, opening: frame.Opening) -> frame.Opening:
        return opening  # a tap responder needs nothing else

    def header(self, opening: frame.Opening, device: Device) -> dict[str, Any]:
        return session_header(
            source=self.source,
            calibration={},
            device=device.identity,
            order=[],
            tap={"taps": self.taps},
            **opening.header_fields(),
        )

    def position(self) -> tuple[str | None, int | None]:
        return None, self.done

    def session(self, opening: frame.Opening, opened: frame.Opened) -> TapSession:
        return TapSession(self, opening.clock, opened)


class TapSession(SessionShell[TapResult]):
    def __init__(self, plan: TapPlan, clock: Any, opened: frame.Opened) -> None:
        super().__init__(clock=clock, **vars(opened))
        self.plan = plan

    def run(self) -> TapResult:
        return self.run_guarded(self._taps)

    def _taps(self) -> None:
        if self.plan.done == 0:
            self._append({"record": "set_start", "set_id": "taps", "target": TAP.name})
        while self.plan.done < self.plan.taps:
            i = self.plan.done
            played = self.device.play_trial(
                TrialPlan(TAP, 0.05, 1, n_intervals=1), self.clock.now()
            )
            answer = self.responder.answer(i)
            # Records are the log's known kinds (formats.log_records): a tap is a one-trial set.
            self._append(
                {
                    "record": "trial",
                    "set_id": "taps",
                    "trial_index": i,
                    "response_interval": answer,
                    "actual_onsets_s": played.actual_onsets_s,
                }
            )
            self.plan.done += 1
        self._append({"record": "set_end", "set_id": "taps", "status": "completed"})

    def _result(self, code: int, message: str) -> TapResult:
        return TapResult(self.writer.path, code, self.plan.done)

    def _where_text(self) -> str:
        return f"tap {self.plan.done + 1}"

    def _position(self) -> tuple[str | None, int | None]:
        return None, self.plan.done


class TapKind:
    responders = ("sim",)

    def default_responder(self, name: str, context: frame.Opening) -> Tapper:
        return Tapper()

    def check_log(self, header: Mapping[str, Any], path: Path) -> None:
        if "tap" not in header:
            raise LogError(f"{path}: not a tap session log")

    def plan_start(
        self, options: TapOptions, participant: str, seed: int, out: ProgressLine
    ) -> TapPlan:
        text = Path(str(options.protocol)).read_bytes()
        source = TapSource(
            str(options.protocol), hashlib.sha256(text).hexdigest(), "taps", {"taps": 1}
        )
        return TapPlan(source, options.taps, 0)

    def plan_resume(
        self,
        header: Mapping[str, Any],
        log: SessionLog,
        path: Path,
        options: frame.SessionOptions,
        out: ProgressLine,
    ) -> TapPlan:
        p = header["protocol"]
        source = TapSource(p["path"], p["sha256"], p["experiment"], p["content"])
        done = sum(1 for r in log.records if r.get("record") == "trial")
        return TapPlan(source, int(header["tap"]["taps"]), done)


TAPS = TapKind()


class StopAfter(Tapper):
    """A responder hook whose participant presses Esc at tap ``n`` (0-based)."""

    def __init__(self, n: int) -> None:
        self.n = n

    def answer(self, index: int) -> int:
        if index == self.n:
            raise KeyboardInterrupt
        return index


@pytest.fixture
def options(tmp_path: Path) -> TapOptions:
    protocol = tmp_path / "taps.yaml"
    protocol.write_text("taps: 1\n")
    return TapOptions(
        protocol=protocol, participant="S01", device="sim", data_dir=tmp_path / "data", seed=5
    )


def test_a_third_kind_starts_stops_and_resumes_in_one_log(options: TapOptions) -> None:
    stopped = frame.start(
        TAPS, options, make_responder=lambda name, ctx: StopAfter(2), stream=io.StringIO()
    )
    assert (stopped.exit_code, stopped.taps_logged) == (EXIT_INTERRUPTED, 2)

    out = io.StringIO()
    resumed = frame.resume(TAPS, stopped.log_path, stream=out)

    assert (resumed.exit_code, resumed.taps_logged) == (EXIT_COMPLETED, 4)
    assert resumed.log_path == stopped.log_path
    log = read_log(resumed.log_path)
    records = log.records
    stopped_part = ["set_start", "trial", "trial", "fault"]
    resumed_part = ["resume", "trial", "trial", "set_end", "session_end"]
    assert [r["record"] for r in records] == stopped_part + resumed_part
    assert [r["response_interval"] for r in records if r["record"] == "trial"] == [0, 1, 2, 3]
    assert log.header["tap"] == {"taps": 4} and log.header["seed"] == 5
    assert records[3]["kind"] == "interrupted" and records[3]["trial_index"] == 2
    assert f"resuming {resumed.log_path}" in out.getvalue()


def test_the_frame_refuses_what_the_kind_does_not_take(options: TapOptions, tmp_path) -> None:
    from dataclasses import replace

    with pytest.raises(MaskingLabError, match="--responder 'keys': choose one of sim"):
        frame.start(TAPS, replace(options, responder="keys"))
    with pytest.raises(MaskingLabError, match="--participant"):
        frame.start(TAPS, replace(options, participant="S 01"))
    assert not (tmp_path / "data").exists()  # refused before any log

    done = frame.start(TAPS, options, stream=io.StringIO())
    with pytest.raises(LogError, match="finished"):
        frame.resume(TAPS, done.log_path)
    other = tmp_path / "other.jsonl"  # a log of another kind
    header = json.loads(done.log_path.read_text().splitlines()[0])
    del header["tap"]
    other.write_text(json.dumps(header) + "\n")
    with pytest.raises(LogError, match="not a tap session log"):
        frame.resume(TAPS, other)
