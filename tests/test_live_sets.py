"""Sets in a live session, as a user runs it: ``msk live --sim`` playing sets of 1 rep with 8 s rests (a session
file with a 4 s rest detection), ``msk set start`` and ``msk set stop`` (the command, run in this process: the marks
must land within the rest detection's time, which a fresh interpreter's start-up on busy cores can exceed), sent as the
test sees
the reps go by in the estimates (``msk/<s>/activations/assisted``: the phase the live frames carry); the recording holds the operator's marks and its report splits the session as
the view and the dashboard do: a set ended by rest detection, then the operator's set from his start to his stop with
the rep between the marks. About 30 s of session after it is up."""

from __future__ import annotations

import json
import queue
import time

import numpy as np

from msk_core.signal.reps import PhaseRepCounter, phase_rep_spans
from services.surfaces.dashboard import report
from services.transport import messages
from services.transport.mcap_io import read_messages
from services.transport.zenoh_session import ZenohOptions, open_session
from tests.live_helpers import LiveProcess, live_environment

SESSION = "setslive"
REST_S = 4.0  # the session's rest detection
METHOD = "assisted"  # the method the report details (its frames' phase: the reps it counts)
WAIT_S = 50.0  # for a rep, or for the rest after one (a cycle: about 6 s of set and 8 s of rest)


class Reps:
    """The session's reps as the activation frames show them (their phase, counted by the one segmenter)."""

    def __init__(self, frames: queue.Queue) -> None:
        self.frames, self.counter, self.spans, self.last_t = frames, PhaseRepCounter(), [], 0.0

    @property
    def fresh(self) -> bool:
        """The newest frame is less than 1 s old (host clock): what the test sees is now, not a backlog."""
        return time.time() - self.last_t < 1.0

    def wait(self, what: str, done) -> None:
        deadline = time.monotonic() + WAIT_S
        seen, phases = 0, []
        while not done(self):
            assert time.monotonic() < deadline, (
                f"waited {WAIT_S:g} s for {what}: {seen} frames, reps {self.spans}; phases of those frames: "
                f"{len(phases)} set, {sum(p < 0 for p in phases)} between reps, "
                f"range {min(phases, default=float('nan')):.2f}-{max(phases, default=float('nan')):.2f}"
            )
            try:
                frame = self.frames.get(timeout=0.5)
            except queue.Empty:
                continue
            seen += 1
            if frame.HasField("phase"):
                phases.append(frame.phase)
            self.last_t = frame.time_s
            span = self.counter.update(self.last_t, frame.phase if frame.HasField("phase") else None)
            if span is not None:
                self.spans.append(span)


def msk_set(action: str, capsys) -> str:
    """``msk set ACTION`` as the command line runs it (services.cli.main), in this process; what it printed."""
    from services.cli import main

    assert main(["set", action]) == 0
    return capsys.readouterr().out


def test_msk_set_marks_sets_in_a_live_session_and_its_report(tmp_path, monkeypatch, capsys):
    env = live_environment(tmp_path)
    monkeypatch.setenv("MSK_SESSIONS_DIR", env["MSK_SESSIONS_DIR"])  # msk set finds the session msk live announced
    session_file = tmp_path / "sets.toml"
    session_file.write_text(f'[session]\nname = "{SESSION}"\npack = "bench_press"\nrest_s = {REST_S:g}\n')
    out = tmp_path / "live"
    from services.cli import build_parser

    build_parser()  # every command imported now: msk set's marks then leave within a second of the call
    live = LiveProcess(out, env, str(session_file), "--sim-reps", "1", "--sim-rest", "6")
    try:
        live.wait_running()
        info = json.loads((out / "session.json").read_text())
        frames: queue.Queue = queue.Queue()
        with open_session(ZenohOptions(connect=tuple(info["connect"]))) as zsession:
            subscriber = zsession.declare_subscriber(
                f"msk/{SESSION}/activations/{METHOD}",
                lambda s: frames.put(messages.decode("msk.ActivationFrame", s.payload.to_bytes())),
            )
            reps = Reps(frames)
            # a rep, then rest detection's time at rest after it: that set has ended; the operator starts the next
            reps.wait("a rep", lambda r: bool(r.spans))
            reps.wait(
                "the rest after it",
                lambda r: r.fresh and not r.counter.in_rep and r.last_t - r.spans[-1][1] > REST_S + 0.5,
            )
            assert "starts" in msk_set("start", capsys)
            started = time.time()  # the mark is older: a rep that starts after this is the operator's set's
            reps.wait("the operator's rep", lambda r: r.fresh and bool(r.spans) and r.spans[-1][0] > started)
            assert "the set under way ends" in msk_set("stop", capsys)
            subscriber.undeclare()
        code, output, summary = live.stop()
    finally:
        live.kill()
    assert code == 0, output
    assert "as sets of 1 rep with 6 s rests" in output
    assert summary["trial_clock"]["cycle_s"] > 0 and summary["trial_clock"]["schedule"]  # the schedule is stated
    recording = out / "session.mcap"
    loads = [m.decode(messages.LoadEvent) for m in read_messages(recording) if m.type_name == "msk.LoadEvent"]
    marks = [(e.set_mark, e.set_number, e.device_time_ns / 1e9) for e in loads if e.set_mark]
    assert [mark for mark, _, _ in marks] == ["start", "stop"], marks  # (the numbers: msk live's facts, +1)
    assert loads[0].set_rest_s == REST_S  # msk live's facts carry the session's rest detection
    start_s, stop_s = marks[0][2], marks[1][2]
    frames_of = [
        f
        for m in read_messages(recording)
        if m.type_name == "msk.ActivationFrame" and (f := m.decode(messages.ActivationFrame)).method == METHOD
    ]
    spans = phase_rep_spans(np.array([f.time_s for f in frames_of]), np.array([f.phase for f in frames_of]))
    between = [span for span in spans if start_s <= span[0] and span[1] < stop_s]

    sets = [s["set"] for s in report.write_report(recording, tmp_path / "report")["sets"]]
    described = [(s["number"], s["reps"], s["started_by"], s["ended_by"]) for s in sets]
    k = next((i for i, s in enumerate(sets) if s["start_s"] == start_s), None)
    assert k is not None and k > 0, (described, marks)
    operator, before = sets[k], sets[k - 1]
    assert (operator["started_by"], operator["ended_by"], operator["end_s"]) == ("operator", "operator", stop_s)
    assert operator["reps"] == len(between) == 1, (described, between, marks, spans[-4:])
    assert before["ended_by"] == "rest" and before["reps"] >= 1, described
    assert all(p is not None for p in operator["peak"] + operator["mean"])  # the set's figures per muscle group
    print(f"sets: {described}; marks {marks}; reps between the marks: {between}")
