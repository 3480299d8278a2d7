"""`msk view` driven in a real pseudo-terminal (tmux) while the demo session is replayed through an estimator node:
the screen shows bars, torques, load, rep/phase and device health, muscles and joints by their display names with
units, the time in the set, and ends on the newest frame (not a queue)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import threading
import uuid

import pytest

from services.nodes import estimator
from services.sessions.graph import Graph, wait_for
from services.surfaces.view import ViewState, main, render
from services.transport import messages, topics
from services.transport.zenoh_session import ZenohOptions, declare_data_publisher, open_session, publish
from tests.dashboard_helpers import replay_demo_without_raw

SESSION = "viewtest"


def capture(name: str) -> str:
    return subprocess.run(["tmux", "capture-pane", "-p", "-t", name], capture_output=True, text=True, check=True).stdout


@pytest.mark.skipif(shutil.which("tmux") is None, reason="tmux is needed to drive the view in a pseudo-terminal")
def test_view_in_a_terminal_during_a_replay(repo_root, zenoh_endpoint):
    name = f"mskview-{uuid.uuid4().hex[:8]}"
    last: dict[str, messages.ActivationFrame] = {}
    with Graph(SESSION, zenoh_endpoint) as graph:
        graph.add_thread(
            "estimator", estimator.main, estimator.EstimatorSettings("bench_press", SESSION, ("so", "hybrid"))
        )
        graph.wait_ready(60)
        # COLUMNS/LINES: the pane size as rich should see it even when a tmux server with another default size runs
        command = (
            f"env COLUMNS=160 LINES=60 {sys.executable} -m services.cli view --session {SESSION} --method so --connect {zenoh_endpoint} "
            "--duration 120 --refresh-hz 20"
        )
        subprocess.run(
            ["tmux", "new-session", "-d", "-s", name, "-x", "160", "-y", "60", "-c", str(repo_root), command],
            check=True,
        )
        try:
            with open_session(ZenohOptions(connect=(zenoh_endpoint,))) as zsession:
                probe = declare_data_publisher(zsession, topics.status_key(SESSION, "trigno-test"), "msk.DeviceStatus")
                wait_for(
                    "the view to subscribe",
                    lambda: probe.matching_status.matching,
                    lambda: "no subscriber on the status key; screen:\n" + capture(name),
                    60,
                )
                publish(
                    probe,
                    messages.DeviceStatus(
                        device_id="trigno-test", kind="trigno", connected=True, samples_received=123456, samples_lost=27
                    ),
                )
                lock = threading.Lock()

                # device times of the load events: a mass starts a set, none ends it (msk_core.signal.sets)
                set_marks: list[tuple[float, bool]] = []

                def keep_last(sample):
                    frame = messages.decode("msk.ActivationFrame", sample.payload.to_bytes())
                    with lock:
                        last[frame.method] = frame

                def keep_set_start(sample):
                    load = messages.decode("msk.LoadEvent", sample.payload.to_bytes())
                    set_marks.append((load.device_time_ns / 1e9, load.barbell_mass_kg > 0))

                sub = zsession.declare_subscriber(f"msk/{SESSION}/activations/*", keep_last)
                loads = zsession.declare_subscriber(topics.load_key(SESSION), keep_set_start)
                stats = replay_demo_without_raw(zenoh_endpoint, SESSION)
                assert stats.published > 5000
                est = graph._threads[0]  # noqa: SLF001 - the node's thread is idle once its inbox is empty

                def settled() -> bool:  # the newest frame's time from its set's start, or from its end at rest
                    with lock:
                        frame = last.get("so")
                    if frame is None or not set_marks:
                        return False
                    mark_s, starts = set_marks[-1]
                    since = frame.time_s - mark_s
                    if starts:
                        return f"{since:.1f} s in set " in capture(name)
                    # a frame from before the end of the set cannot say how long the rest has lasted
                    return (f"resting for {since:.1f} s" if since >= 0 else "resting · latency") in capture(name)

                # the screen reaches the newest frame soon after the estimator does: it never replays a backlog
                wait_for(
                    "the view to show the newest frame",
                    settled,
                    lambda: (
                        f"newest so frame t={last.get('so').time_s if 'so' in last else None}; screen:\n"
                        + capture(name)
                    ),
                    120,
                )
                sub.undeclare()
                loads.undeclare()
                # the view redraws 20 times a second: a capture taken during a redraw holds only part of the screen
                shown = [""]

                def whole() -> bool:
                    shown[0] = capture(name)
                    return all(e in shown[0] for e in SCREEN_SHOWS)

                wait_for(
                    "a whole screen",
                    whole,
                    lambda: f"missing {[e for e in SCREEN_SHOWS if e not in shown[0]]}; screen:\n{shown[0]}",
                    10,
                )
            screen = shown[0]
        finally:
            subprocess.run(["tmux", "kill-session", "-t", name], capture_output=True)
    assert est.error == []
    for expected in SCREEN_SHOWS:
        assert expected in screen, (expected, screen)
    assert any(said in screen for said in ("· lifting ·", "· lowering ·", "· turning ·", "· rest ·", "· resting ")), (
        screen
    )
    assert "BicLong" not in screen and "elbow_flex_r" not in screen  # 160 columns: no abbreviation needed
    assert "█" in screen or "▓" in screen


#: what the view's screen shows during the replay of test_view_in_a_terminal_during_a_replay
SCREEN_SHOWS = (
    "activations · so",
    "Biceps brachii, long head",
    "Triceps brachii, long head",
    "hybrid %",
    "activation %",
    "EMG envelope %",
    "torque tracking",
    "Elbow flexion",
    "Shoulder flexion",
    "N·m",
    "inverse dynamics",
    "trigno-test",
    "123456",
    "27",
    "load ",
    " kg",
    "set ",  # "set N · rep n", or "set N done · resting" after the replay's last set
)


def test_render_without_frames_and_rep_counter():
    state = ViewState()
    text = "".join(str(r) for r in render(state, "s").renderables)
    assert "waiting for activations" in text
    for k, phase in enumerate((-1, -1, 0.0, 0.3, 0.7, 0.95, 0.1, 0.6, 0.9, -1, -1, 0.05, 0.5, 0.8)):
        state.on_message("msk/s/activations/so", messages.ActivationFrame(method="so", time_s=0.2 * k, phase=phase))
    assert (state.sets.number, state.sets.rep) == (1, 3)  # the third rep is under way: a set opened by the first
    assert "set 1 · rep 3 · 80 % through the rep" in screen_text(state)  # no joint velocities: how far through
    # with the frame's inverse-dynamics torques and the joints' velocities: the direction of the load
    frame = messages.ActivationFrame(method="so", time_s=3.0, phase=0.85)
    frame.torques.add(coordinate="elbow_flex_r", inverse_dynamics_nm=25.0, model_nm=25.0, residual_nm=0.0)
    state.on_message("msk/s/activations/so", frame)
    state.on_message("msk/s/joints", messages.JointAngles(coordinates=["elbow_flex_r"], q=[1.0], qd=[-1.5]))
    assert "set 1 · rep 3 · lowering" in screen_text(state)  # the elbow extends against a flexing torque


def screen_text(state: ViewState, session: str = "s", width: int = 200) -> str:
    from io import StringIO

    from rich.console import Console

    console = Console(file=StringIO(), width=width, color_system=None)
    console.print(render(state, session, width=width))
    return console.file.getvalue()


def test_display_names_units_and_the_time_in_the_set():
    state = ViewState()
    torque = messages.CoordinateTorque(
        coordinate="elbow_flex_r", inverse_dynamics_nm=12.5, model_nm=12.0, residual_nm=0.5
    )
    groups = ["TriLat", "PMCla"]
    state.on_message(
        "msk/s/load",
        messages.LoadEvent(barbell_mass_kg=60, exercise="bench_press", set_number=1, device_time_ns=100_000_000_000),
    )
    state.on_message(
        "msk/s/activations/so",
        messages.ActivationFrame(
            method="so",
            time_s=112.34,
            groups=groups,
            activations=[0.42, 0.071],
            measured_envelope=[0.38, float("nan")],
            torques=[torque],
            exercise="bench_press",
        ),
    )
    text = screen_text(state)
    for expected in (
        "muscle",
        "activation %",
        "EMG envelope %",
        "Triceps brachii, lateral and medial heads",
        "Pectoralis major, clavicular part",
        " 42 ",
        " 38 ",
        " 7 ",
        "Elbow flexion",
        "12.5",
        "N·m",
        "12.3 s in set 1",
    ):
        assert expected in text, (expected, text)
    assert "TriLat" not in text and "elbow_flex_r" not in text and "1795" not in text
    # too narrow for the display names: the model names, explained by a legend
    narrow = screen_text(state, width=80)
    assert "│ TriLat " in narrow and "TriLat: Triceps brachii, lateral and medial heads" in narrow.replace("\n", " ")
    # the session file's names (LoadEvent.names) replace the pack's, and stay when a later event carries none
    state.on_message(
        "msk/s/load",
        messages.LoadEvent(
            barbell_mass_kg=60,
            exercise="bench_press",
            set_number=1,
            names={"PMCla": "Upper chest", "elbow_flex_r": "Elbow"},
        ),
    )
    state.on_message("msk/s/load", messages.LoadEvent(barbell_mass_kg=62.5, exercise="bench_press", set_number=1))
    text = screen_text(state)
    assert "Upper chest" in text and "Elbow " in text and "Pectoralis major" not in text
    assert "Triceps brachii, lateral and medial heads" in text
    # frames of a pack the view does not know: their model names
    state.on_message(
        "msk/s/activations/so",
        messages.ActivationFrame(method="so", time_s=113.0, groups=["X1"], activations=[0.5], exercise="my_pack"),
    )
    state.on_message("msk/s/load", messages.LoadEvent(barbell_mass_kg=60, exercise="my_pack", set_number=2))
    assert "│ X1 " in screen_text(state)


def frame(exercise: str = "bench_press") -> messages.ActivationFrame:
    return messages.ActivationFrame(time_s=1.0, method="so", groups=["BicLong"], activations=[0.4], exercise=exercise)


def test_session_facts_come_from_the_load_event_else_the_frames():
    state = ViewState()
    state.on_message("msk/s/activations/so", frame())
    text = screen_text(state)
    assert "exercise bench press · load unknown · set –" in text  # no load event: the frame's exercise
    state.on_message(
        "msk/s/load", messages.LoadEvent(barbell_mass_kg=60, exercise="bench_press", set_number=2, athlete="Ana")
    )
    assert "exercise bench press · load 60 kg · set 2 · rep 0 · Ana" in screen_text(state)
    for k, phase in enumerate((-1.0, 0.1, 0.7, -1.0)):
        state.on_message(
            "msk/s/activations/so",
            messages.ActivationFrame(method="so", phase=phase, time_s=2.0 + 0.4 * k, exercise="bench_press"),
        )
    assert state.sets.rep == 1
    state.on_message("msk/s/load", messages.LoadEvent(barbell_mass_kg=62.5, exercise="bench_press", set_number=2))
    text = screen_text(state)
    assert state.sets.rep == 1 and "load 62.5 kg · set 2 · rep 1" in text  # a correction within the set
    assert "set 2 peak / mean %" in text and "under tension" in text  # the set's figures and the table of sets
    state.on_message("msk/s/load", messages.LoadEvent(barbell_mass_kg=70, exercise="bench_press", set_number=3))
    assert state.sets.rep == 0 and "load 70 kg · set 3 · rep 0" in screen_text(state)  # the next set at rep 0
    # the operator ends it (msk set stop, the key e): resting
    state.on_message(
        "msk/s/load", messages.LoadEvent(barbell_mass_kg=70, exercise="bench_press", set_number=3, set_mark="stop")
    )
    text = screen_text(state)
    assert "set 3 done · resting for " in text and "rest ·" not in text, text  # said once
    # a load event the estimator refuses (an exercise no pack has and no frame named) is no fact of the session
    state.on_message(
        "msk/s/load", messages.LoadEvent(barbell_mass_kg=5, exercise="upper_arm_r", set_number=4, athlete="Bob")
    )
    text = screen_text(state)
    assert "exercise bench press · load 70 kg · set 3 done · resting" in text and "Bob" not in text, text
    assert "upper" not in text
    assert state.sets.number == 3 and state.inputs.as_dict()["dropped"] == {"msk/s/load": {"invalid": 1}}
    assert "paused" not in text
    # another shipped pack declared: the estimator of this bench session pauses, and the view says why
    state.on_message("msk/s/load", messages.LoadEvent(barbell_mass_kg=80, exercise="deadlift", set_number=4))
    text = " ".join(screen_text(state).split())
    assert (
        "Estimates paused. The operator's load event declares deadlift, and this session estimates bench press" in text
    )
    assert "(msk load --exercise bench_press)" in text, text
    state.on_message("msk/s/load", messages.LoadEvent(barbell_mass_kg=80, exercise="bench_press", set_number=4))
    assert "paused" not in screen_text(state)
    # a view started while the estimator is paused has no frame: the exercise msk live announces tells it
    late = ViewState()
    late.on_message("msk/s/load", messages.LoadEvent(barbell_mass_kg=80, exercise="deadlift", set_number=4))
    assert "waiting for activations" in screen_text(late)
    late.loads.session_exercise = "bench_press"
    text = " ".join(screen_text(late).split())
    assert "Estimates paused. The operator's load event declares deadlift, and this session estimates bench" in text


def test_view_drops_and_counts_unusable_inputs_over_zenoh_and_goes_on(zenoh_endpoint):
    """Garbage, an empty payload, another type and a 50 MB payload on the session's topics: the view drops and counts
    each (its header says so), keeps running, and shows the valid frame and load published after them."""
    from io import StringIO

    from rich.console import Console

    from tests.dashboard_helpers import BadInputs

    stop = threading.Event()
    result: list[ViewState] = []
    console = Console(file=StringIO(), width=200, height=60, color_system=None, force_terminal=True)  # Live redraws
    view = threading.Thread(
        target=lambda: result.append(
            main(ZenohOptions(listen=(zenoh_endpoint,)), session="bad", refresh_hz=20, stop_event=stop, console=console)
        ),
        daemon=True,
    )
    view.start()
    try:
        with open_session(ZenohOptions(connect=(zenoh_endpoint,))) as zsession:
            inputs = BadInputs(zsession, "bad")
            inputs.every_kind_then(
                {
                    "activations/so": frame("deadlift"),
                    "load": messages.LoadEvent(barbell_mass_kg=80, exercise="deadlift", set_number=1),
                }
            )
            wait_for(
                "the view to show the valid frame and load",
                lambda: "load 80 kg" in console.file.getvalue() and "5 dropped" in console.file.getvalue(),
                lambda: console.file.getvalue()[-3000:],
                30,
            )
            inputs.close()
    finally:
        stop.set()
        view.join(10)
    assert not view.is_alive() and result
    state = result[0]
    assert {(d.key, d.reason): d.count for d in state.inputs.drops()} == inputs.expected
    assert state.received == 2 and state.frames["so"].exercise == "deadlift"
    text = screen_text(state, "bad")
    assert "5 dropped (msk/bad/activations/so: invalid 1, msk/bad/activations/so: undecodable 1" in text
    assert "msk/bad/joints: oversized 1" in text and "exercise deadlift · load 80 kg · set 1" in text


def test_the_view_shows_assisted_where_it_ran_else_proposed_and_names_it():
    """One default method on every surface (services.sessions.live_session.default_method): ``assisted`` where EMG is live,
    else ``proposed``, whatever order the frames arrive in; the muscle table's title names it."""
    state = ViewState()
    for method in ("so", "proposed"):
        state.on_message(
            f"msk/s/activations/{method}",
            messages.ActivationFrame(method=method, time_s=1.0, groups=["BicLong"], activations=[0.4]),
        )
    assert "activations · proposed" in screen_text(state)
    state.on_message(
        "msk/s/activations/assisted",
        messages.ActivationFrame(
            method="assisted", time_s=1.0, groups=["BicLong"], activations=[0.4], measured_envelope=[0.3]
        ),
    )
    assert "activations · assisted" in screen_text(state)


def test_a_session_gone_quiet_is_said_over_the_last_values():
    """After msk live stopped, the view kept showing the last set, rep and latency as if live."""
    import time

    from services.surfaces.view import QUIET_S

    state = ViewState()
    state.on_message("msk/s/activations/so", messages.ActivationFrame(method="so", time_s=1.0, phase=-1.0))
    assert "Nothing received" not in screen_text(state)
    state.last_message_at = time.monotonic() - QUIET_S - 3.0
    assert "Nothing received for 8 s: the session has ended or stopped sending." in screen_text(state)


def _methods_frames(t: float, phase: float) -> list[messages.ActivationFrame]:
    """One instant of three methods, proposed first: their activations differ (proposed 0.2, assisted 0.6, so 0.9)."""
    return [
        messages.ActivationFrame(method=m, time_s=t, phase=phase, groups=["TriLat"], activations=[a])
        for m, a in (("proposed", 0.2), ("assisted", 0.6), ("so", 0.9))
    ]


def _a_set(on_message, key: str) -> None:
    for k, phase in enumerate((-1, -1, 0.0, 0.3, 0.7, 0.95, -1, -1)):
        for frame in _methods_frames(0.5 * k, phase):
            on_message(f"{key}/{frame.method}", frame)


def test_the_sets_figures_are_of_the_method_shown_not_of_the_first_to_arrive():
    """The view drew assisted's bars beside proposed's set figures (the method that came first); the report has
    assisted's."""
    state = ViewState()
    _a_set(state.on_message, "msk/s/activations")
    assert (state.sets.sets[0].peak, state.sets.sets[0].mean) == ([0.6], [0.6])
    chosen = ViewState(figures_method="so")  # msk view --method so
    _a_set(chosen.on_message, "msk/s/activations")
    assert chosen.sets.sets[0].peak == [0.9]


@pytest.mark.parametrize(
    ("last_phase", "reps"),
    [
        (0.6, 1),  # cut in the middle by the end of the session: not a rep done (nor its time under tension)
        (0.95, 2),  # nearly through its cycle: counted
    ],
)
def test_when_the_estimator_stops_the_rep_under_way_is_judged_as_in_the_report(last_phase, reps):
    """A session stopped during a rep: the report (SetTracker.finish at the end of the recording), the view and the
    dashboard (the estimator's last status, its node stopped) close the rep and the set alike. The rep under way counts
    when its phase got through its cycle (``MIN_FINISHED_PHASE``): a session report counted a rep the stop had cut at
    2.1 s of a 2.6-3.0 s rep, peaking at 36 % against 78-96 %, while its fatigue table did not."""
    from msk_core.signal.sets import SetTracker
    from services.surfaces.dashboard.bridge import DashboardState

    phases = (-1, 0.0, 0.3, 0.7, 0.95, -1, -1, 0.0, 0.3, last_phase)  # one rep, then one under way at the stop
    report = SetTracker()
    for k, phase in enumerate(phases):
        report.update(0.5 * k, phase)
    report.finish()
    view, dashboard = ViewState(), DashboardState("s")
    for k, phase in enumerate(phases):
        for frame in _methods_frames(0.5 * k, phase):
            for on_message in (view.on_message, dashboard.on_message):
                on_message(f"msk/s/activations/{frame.method}", frame)
    assert len(view.sets.sets[-1].reps) == 1  # the one under way not counted yet
    other_node = messages.DeviceStatus(device_id="recorder", kind="node", connected=False)
    stopped = messages.DeviceStatus(device_id="estimator", kind="node", connected=False)
    for status in (other_node, stopped):
        view.on_message(f"msk/s/status/{status.device_id}", status)
        dashboard.on_message(f"msk/s/status/{status.device_id}", status)
    (reported,) = report.sets
    assert len(reported.reps) == reps and reported.ended_by == "end of data"
    assert [(len(s.reps), s.ended_by) for s in view.sets.sets] == [(reps, "end of data")]
    (shown,) = dashboard.changes(0)[1]["topics"]["sets"]
    assert (shown["reps"], shown["ended_by"]) == (reps, "end of data")
    assert dashboard.changes(0)[1]["topics"]["reps"]["total"] == reps


def test_a_set_closed_by_the_estimators_stop_goes_on_when_its_frames_come_back():
    """An estimator restarted alone (its last status, then frames again within the rest time): the page's set goes on
    as msk live's does, rather than a new set being opened under another number."""
    view = ViewState()
    phases = (-1, 0.0, 0.3, 0.7, 0.95, -1, -1)
    for k, phase in enumerate(phases):
        for frame in _methods_frames(0.5 * k, phase):
            view.on_message(f"msk/s/activations/{frame.method}", frame)
    view.on_message("msk/s/status/estimator", messages.DeviceStatus(device_id="estimator", kind="node"))
    assert [(s.number, len(s.reps), s.ended_by) for s in view.sets.sets] == [(1, 1, "end of data")]
    for k, phase in enumerate((-1, 0.0, 0.3, 0.7, 0.95, -1), start=len(phases) + 4):  # 2 s later: a second rep
        for frame in _methods_frames(0.5 * k, phase):
            view.on_message(f"msk/s/activations/{frame.method}", frame)
    assert [(s.number, len(s.reps), s.ended_by) for s in view.sets.sets] == [(1, 2, "")]


def test_set_keys_typed_among_other_keys_mark_nothing_and_a_key_pressed_alone_marks_one_set():
    """Typed into a running view by mistake, ``clear; msk view --session rackB`` published its letters s and e as
    set marks (found by QA: 4 empty sets, the athlete's first set called set 5). Through a real pseudo-terminal:
    the typed line marks nothing and the view says so; ``s`` pressed on its own marks one set start, stamped when it
    was pressed; ``e`` alone then ends it."""
    import os
    import pty
    import time

    from services.surfaces.view import TYPING_GAP_S, SetKeys, read_keys

    master, slave = pty.openpty()
    published: list[messages.LoadEvent] = []
    keys, stop = SetKeys(), threading.Event()
    pressed: list[int] = []

    def make_event(mark: str) -> messages.LoadEvent:
        event = messages.LoadEvent(set_mark=mark, device_time_ns=time.monotonic_ns())
        pressed.append(event.device_time_ns)
        return event

    reader = threading.Thread(target=read_keys, args=(keys, make_event, published.append, stop, slave), daemon=True)
    reader.start()
    try:
        line = "clear; msk view --session rackB\n"
        for char in line:  # typed at 50 ms a key
            os.write(master, char.encode())
            time.sleep(0.05)
        time.sleep(2 * TYPING_GAP_S)
        assert published == [] and keys.ignored == sum(c in "se" for c in line), (published, keys.ignored)
        assert "press s (start a set) or e (end it) on its own" in keys.notice(time.monotonic())
        os.write(master, b"s")
        time.sleep(2 * TYPING_GAP_S)
        os.write(master, b"E")  # case aside
        deadline = time.monotonic() + 5.0
        while len(published) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert [e.set_mark for e in published] == ["start", "stop"], published
        assert [e.device_time_ns for e in published] == pressed  # made when pressed, sent after the gap
    finally:
        stop.set()
        reader.join(5.0)
        os.close(master)
        os.close(slave)


def test_a_view_waiting_for_a_session_nobody_runs_names_the_ones_that_run(tmp_path, monkeypatch):
    """Found by a new user: `msk view --session simm` (a typo) waited in silence under its full screen, while `sim` ran."""
    import os

    from services.sessions import discovery
    from services.surfaces import view
    from services.surfaces.view import waiting_text

    monkeypatch.setenv(discovery.REGISTRY_ENV, str(tmp_path / "registry"))
    monkeypatch.setattr(view, "RUNNING_SCAN_S", 0.0)  # each call scans (a render reuses a scan for 2 s)
    assert str(waiting_text("simm", "")) == "waiting for activations on msk/simm/activations/* ..."  # nothing runs
    running = tmp_path / "running"
    discovery.announce(discovery.SessionInfo("sim", ["tcp/127.0.0.1:1"], os.getpid(), str(running)), running)
    said = str(waiting_text("simm", ""))
    assert "No msk live here is named 'simm' (running: sim): msk view --session NAME" in said, said
    assert "No msk live" not in str(waiting_text("sim", ""))  # the session runs: it is only starting
