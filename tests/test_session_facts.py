"""The facts ``msk live`` announces follow the sets every consumer counts: an operator's ``msk load`` made from them
keeps the set under way, where it used to start a new one after rest detection had opened a set."""

from __future__ import annotations

import os

import numpy as np
import pytest

from msk_core.errors import ConfigError
from msk_core.signal.sets import SetTracker
from services.nodes.node_runtime import apply_load_event
from services.sessions.facts import FactsFollower, announced_events, new_facts, set_mark_event
from services.transport import messages

RATE_HZ = 50.0


def frames(start_s: float, reps: int, rest_after_s: float) -> list[messages.ActivationFrame]:
    """``reps`` reps of 2 s (phase 0 -> 1) with 1 s rests between them, then ``rest_after_s`` of rest."""
    out = []
    t = start_s
    for _ in range(reps):
        for phase in np.linspace(0.0, 0.99, int(2 * RATE_HZ)):
            out.append(messages.ActivationFrame(method="so", time_s=t, phase=float(phase)))
            t += 1 / RATE_HZ
        for _ in range(int(RATE_HZ)):
            out.append(messages.ActivationFrame(method="so", time_s=t, phase=-1.0))
            t += 1 / RATE_HZ
    for _ in range(int(rest_after_s * RATE_HZ)):
        out.append(messages.ActivationFrame(method="so", time_s=t, phase=-1.0))
        t += 1 / RATE_HZ
    return out


def _facts(announced: dict) -> dict:
    """The announced facts without the sets as counted (``sets_counted``, ``rep_start_s``: their own tests below)."""
    return {k: v for k, v in announced.items() if k not in ("sets_counted", "rep_start_s")}


def test_msk_load_made_from_the_announced_facts_keeps_the_set_rest_detection_opened(monkeypatch):
    announced: list[dict] = []
    follower = FactsFollower(announced.append)
    consumer = SetTracker()  # what the estimator, the view and the dashboard count
    start = messages.LoadEvent(barbell_mass_kg=50, exercise="bench_press", set_number=1, athlete="Ana")
    for tracker_event in (follower.on_event, lambda e: apply_load_event(consumer, e)):
        tracker_event(start)
    opening = {"exercise": "bench_press", "load_kg": 50, "set_number": 1, "athlete": "Ana", "resting": False}
    assert _facts(announced[-1]) == opening
    # set 1, a rest longer than rest detection's 20 s, and the first rep of the next set
    for frame in frames(0.0, 3, 25.0) + frames(34.0, 1, 0.5):
        follower.on_frame("so", frame)
        follower.on_frame("proposed", messages.ActivationFrame(method="proposed", time_s=frame.time_s, phase=-1.0))
        consumer.update(frame.time_s, frame.phase)
    assert consumer.number == 2 and [len(s.reps) for s in consumer.sets] == [3, 1]
    assert announced[-1]["set_number"] == 2 and not follower.wants("proposed")  # the first method's frames count
    # msk load 60: the load changes within set 2, the athlete stays
    load = new_facts(announced[-1], load_kg=60, set_number=None, next_set=False, exercise=None, athlete=None)
    follower.on_event(load)
    apply_load_event(consumer, load)
    assert consumer.number == 2 and len(consumer.sets) == 2, [s.as_dict() for s in consumer.sets]
    assert _facts(announced[-1]) == opening | {"load_kg": 60, "set_number": 2}
    # msk load --next-set and msk set start from the announced facts: the set after the one under way
    nxt = new_facts(announced[-1], load_kg=None, set_number=None, next_set=True, exercise=None, athlete=None)
    assert nxt.set_number == 3
    follower.on_event(nxt)
    apply_load_event(consumer, nxt)
    assert consumer.number == 3 and announced[-1]["set_number"] == 3
    # the dashboard's button and the view's key: the set after the one they show
    assert set_mark_event(nxt, consumer.number, "start").set_number == 4
    # the operator ends set 3: the facts say the session rests, and a page that starts now is told both
    stop = new_facts(announced[-1], load_kg=None, set_number=None, next_set=False, exercise=None, athlete=None)
    stop.set_mark = "stop"
    follower.on_event(stop)
    apply_load_event(consumer, stop)
    assert consumer.resting and announced[-1]["resting"] and announced[-1]["set_number"] == 3
    late = SetTracker()
    apply_load_event(late, start)  # the opening facts msk live's load publisher keeps
    monkeypatch.setattr("services.sessions.discovery.announced_facts", lambda session: announced[-1])
    for event in announced_events("sim"):
        apply_load_event(late, event)
    assert (late.number, late.resting) == (3, True)
    # a rep that opens set 4 but does not count (too short) is not announced as set 4
    count = len(announced)
    t = consumer._last_t
    for k in range(5):
        follower.on_frame("so", messages.ActivationFrame(method="so", time_s=t + 0.02 * (k + 1), phase=0.1 * k))
    for k in range(60):
        follower.on_frame("so", messages.ActivationFrame(method="so", time_s=t + 0.2 + 0.02 * k, phase=-1.0))
    assert all(a["set_number"] == 3 for a in announced[count:]), announced[count:]
    # an event that names no exercise keeps the one in effect in the facts (as the estimator does)
    follower.on_event(messages.LoadEvent(barbell_mass_kg=62.5, set_number=2, athlete="Ana"))
    assert announced[-1]["exercise"] == "bench_press"


def _follow(follower: FactsFollower, trackers: list[SetTracker], batch: list[messages.ActivationFrame]) -> None:
    for frame in batch:
        follower.on_frame("so", frame)
        for tracker in trackers:
            tracker.update(frame.time_s, frame.phase)


def _session_from_the_start() -> tuple[list[dict], FactsFollower, SetTracker, messages.LoadEvent]:
    """What msk live announces (its FactsFollower), a page that ran from the start, and the opening facts."""
    announced: list[dict] = []
    follower = FactsFollower(announced.append)
    session = SetTracker()
    opening = messages.LoadEvent(barbell_mass_kg=50, exercise="bench_press", set_number=1, athlete="Ana")
    follower.on_event(opening)
    apply_load_event(session, opening)
    return announced, follower, session, opening


def _join(
    monkeypatch, opening: messages.LoadEvent, announced: dict, seen_first: list[messages.ActivationFrame] = ()
) -> SetTracker:
    """A page that starts now: the opening facts msk live's load publisher keeps, then what msk live announces
    (``seen_first``: frames the page took before them, which it does while it waits for msk live's node)."""
    late = SetTracker()
    for frame in seen_first:
        late.update(frame.time_s, frame.phase)
    apply_load_event(late, opening)
    monkeypatch.setattr("services.sessions.discovery.announced_facts", lambda session: announced)
    for event in announced_events("sim"):
        apply_load_event(late, event)
    return late


@pytest.mark.parametrize("frames_first", [0, 30])
@pytest.mark.parametrize("join_after_reps", [2, 3])
def test_a_page_that_joins_during_a_set_counts_it_as_the_session_does(monkeypatch, join_after_reps, frames_first):
    """A page opened after rep 2 of 3, or after the set's last rep and before rest detection ended it: it counted no
    rep of that set, never ended it and put the next set's reps into it (one set behind, reps short). With
    ``frames_first`` it takes that many frames before the facts come (in rep 3: the facts must not drop it)."""
    announced, follower, session, opening = _session_from_the_start()
    set_1 = frames(100.0, 3, 25.0)
    cut = int(join_after_reps * 3 * RATE_HZ + (RATE_HZ if join_after_reps == 3 else 10))
    _follow(follower, [session], set_1[:cut])
    facts = announced[-1]  # read as the page starts
    _follow(follower, [session], set_1[cut : cut + frames_first])
    late = _join(monkeypatch, opening, facts, set_1[cut : cut + frames_first])
    assert late.number == 1 and len(late.sets[0].reps) == join_after_reps
    assert late.sets[0].start_s == session.sets[0].start_s
    _follow(follower, [session, late], set_1[cut + frames_first :] + frames(set_1[-1].time_s + 0.02, 2, 1.0))
    # the rep under way at the join too: from its start as msk live saw it
    assert [(s.number, s.start_s, s.end_s, s.ended_by, s.reps) for s in late.sets] == [
        (s.number, s.start_s, s.end_s, s.ended_by, s.reps) for s in session.sets
    ]
    assert [len(s.reps) for s in late.sets] == [3, 2] and late.sets[0].ended_by == "rest"


def test_a_page_that_joins_in_set_2_shows_set_1_as_the_session_counted_it(monkeypatch):
    """It showed set 1 with the opening facts' start, no rep and ended by "next set" at the join."""
    announced, follower, session, opening = _session_from_the_start()
    both = frames(100.0, 3, 25.0) + frames(134.0, 3, 25.0)
    cut = len(frames(100.0, 3, 25.0)) + int(2.5 * RATE_HZ)  # rep 1 of set 2 done; in the rest before rep 2
    _follow(follower, [session], both[:cut])
    facts = announced[-1]
    seen_first = both[cut : cut + int(1.0 * RATE_HZ)]  # the page takes the start of rep 2 before the facts
    _follow(follower, [session], seen_first)
    late = _join(monkeypatch, opening, facts, seen_first)
    _follow(follower, [session, late], both[cut + len(seen_first) :])
    assert [len(s.reps) for s in session.sets] == [3, 3]
    assert [(s.number, s.start_s, s.started_by, s.end_s, s.ended_by, len(s.reps)) for s in late.sets] == [
        (s.number, s.start_s, s.started_by, s.end_s, s.ended_by, len(s.reps)) for s in session.sets
    ]
    assert [s.started_by for s in late.sets] == ["session", "rep"]  # set 2 by rest detection, as msk live said


def test_a_page_that_joins_during_a_rest_shows_the_set_before_it(monkeypatch):
    announced, follower, session, opening = _session_from_the_start()
    _follow(follower, [session], frames(100.0, 3, 25.0))
    assert announced[-1]["resting"] and announced[-1]["sets_counted"][-1]["end_s"] == session.sets[0].end_s
    late = _join(monkeypatch, opening, announced[-1])
    assert late.resting and late.number == 1
    assert late.sets[0].as_dict() == session.sets[0].as_dict() | {"groups": [], "peak": [], "mean": []}
    assert late.sets[0].ended_by == "rest"


def test_one_shot_commands_refuse_a_misspelt_session_and_unknown_facts(tmp_path, monkeypatch, capsys):
    """``msk load --session Sim`` while ``sim`` runs names the running sessions (it used to publish on msk/Sim/load and
    succeed); ``--connect`` to a session not announced here refuses to publish facts made from none (the bar off,
    set 0) unless every fact is given."""
    import os

    from services import cli
    from services.sessions import discovery

    monkeypatch.setenv(discovery.REGISTRY_ENV, str(tmp_path / "registry"))
    facts = {"exercise": "bench_press", "load_kg": 50.0, "set_number": 2, "athlete": "Ana"}
    info = discovery.SessionInfo("sim", ["tcp/127.0.0.1:1"], os.getpid(), str(tmp_path / "out"), facts=facts)
    discovery.announce(info, tmp_path / "out")
    assert discovery.announced_facts("sim") == facts and discovery.announced_facts("other") is None
    # a view, dashboard or subscriber may look for a graph msk live did not start (a replay) on the usual endpoint
    assert discovery.find_session("replay") is None
    for argv in (["load", "60", "--session", "Sim"], ["set", "start", "--session", "Sim"]):
        assert cli.main(argv) != 0
        error = capsys.readouterr().err
        assert "--session" in error and "Sim" in error and "running: sim on tcp/127.0.0.1:1" in error, error
    elsewhere = ["--session", "gym2", "--connect", "tcp/127.0.0.1:1"]
    for argv in (["load", "60", *elsewhere], ["set", "stop", *elsewhere]):
        assert cli.main(argv) != 0
        error = capsys.readouterr().err
        assert "'gym2' does not announce them on this machine" in error and "--set N --exercise PACK" in error, error


def test_bad_values_are_named_before_anything_starts(tmp_path, monkeypatch, capsys):
    """Each refused at once with its flag and value (they used to end in a traceback, name an inner field, or say
    "no running msk live" instead of the bad value)."""
    from services import cli
    from services.sessions import discovery

    monkeypatch.setenv(discovery.REGISTRY_ENV, str(tmp_path / "empty"))
    cases = {
        ("load", "--", "-5"): "field 'KG': must be a finite mass >= 0 kg (got -5.0)",
        ("load", "nan"): "field 'KG': must be a finite mass >= 0 kg (got nan)",
        # a new user's typo (or grams): the estimate chased 99 % unexplained torque, reported "solved"
        (
            "load",
            "60000",
        ): "field 'KG': 60000 kg is more than any lift's load (at most 1000 kg here): is it in grams (60 kg)?",
        ("load", "--set", "0"): "field '--set': sets are counted from 1 (got 0)",
        ("set", "start", "--set", "0"): "field '--set': sets are counted from 1 (got 0)",
        ("live", "--sim", "--listen", "foo"): "field '--listen': not a Zenoh endpoint",
        (
            "subscribe",
            "msk/s/joints",
            "--connect",
            "tcp/localhost",
        ): "field '--connect': a tcp endpoint is tcp/HOST:PORT",
        ("live", "--sim", "--sim-fault", "99:hum:1-2"): "field '--sim-fault': sensor: a sensor is numbered",
        # the text given once, not once per wrapping
        ("live", "--sim", "--sim-fault", "x:y:1-2"): "fault: expected SENSOR:KIND:START-END with a sensor number, "
        "one of lift_off, hum, saturation, flat and times in seconds (got 'x:y:1-2')\n",
        ("view", "--refresh-hz", "0"): "field '--refresh-hz': redraws per second must be in (0, 100]",
        ("dashboard", "--port", "99999"): "field '--port': port must be in 1..65535 (got 99999)",
        # every fact given, to a session whose endpoint nobody answers (a one-shot Zenoh client fails at once)
        ("load", "60", "--set", "2", "--exercise", "bench_press", "--session", "x", "--connect", "tcp/127.0.0.1:1"): (
            "cannot reach session 'x' at tcp/127.0.0.1:1 (Unable to connect to any of"
        ),
    }
    for argv, said in cases.items():
        assert cli.main(list(argv)) == 2, argv
        error = capsys.readouterr().err
        assert said in error, (argv, error)


def test_a_second_msk_live_of_the_same_name_or_folder_is_refused(tmp_path, monkeypatch, capsys):
    """Two sessions called "sim" could not be told apart by the attach commands, and a second recorder in the same
    folder would truncate the first one's recording: both refused before anything starts."""
    import os

    from services import cli
    from services.sessions import discovery

    monkeypatch.setenv(discovery.REGISTRY_ENV, str(tmp_path / "registry"))
    running = tmp_path / "running"
    discovery.announce(discovery.SessionInfo("sim", ["tcp/127.0.0.1:1"], os.getpid(), str(running)), running)
    assert cli.main(["live", "--sim", "--no-view", "--out", str(tmp_path / "other")]) == 2
    error = capsys.readouterr().err
    assert "field 'session'" in error and "a session of this name runs now" in error and str(running) in error, error
    for path in (tmp_path / "registry").glob("*.json"):
        discovery.withdraw(path)
    discovery.announce(discovery.SessionInfo("monday", ["tcp/127.0.0.1:1"], os.getpid(), str(running)), running)
    assert cli.main(["live", "--sim", "--no-view", "--out", str(running)]) == 2
    error = capsys.readouterr().err
    assert "'monday'" in error and "is recording there now; choose another --out" in error, error


def test_two_msk_live_starting_together_cannot_share_a_name_or_folder(tmp_path, monkeypatch, capsys):
    """Neither has announced itself yet when both start: the claim on the name and on the folder decides, and the
    kernel releases it however its holder ends (killed: no stale claim)."""
    import signal
    import subprocess
    import sys

    from services import cli
    from services.sessions import discovery

    monkeypatch.setenv(discovery.REGISTRY_ENV, str(tmp_path / "registry"))
    first = tmp_path / "first"
    with discovery.claimed("sim", first):
        assert cli.main(["live", "--sim", "--no-view", "--out", str(tmp_path / "second")]) == 2
        error = capsys.readouterr().err
        assert "field 'session'" in error and "a session named 'sim' starts or runs now" in error, error
        assert f"(pid {os.getpid()})" in error, error
        with pytest.raises(ConfigError, match="an msk live writes to .*first now"):
            with discovery.claimed("monday", first):
                pass
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from pathlib import Path; from services.sessions import discovery\n"
            f"with discovery.claimed('sim', Path({str(first)!r})):\n    print('held', flush=True); time.sleep(60)",
        ],
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, discovery.REGISTRY_ENV: str(tmp_path / "registry")},
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(ConfigError, match=f"pid {holder.pid}"):
            with discovery.claimed("sim", tmp_path / "third"):
                pass
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait(timeout=10)
        holder.stdout.close()
    with discovery.claimed("sim", first):  # released with its holder
        pass
    # its announcement outlived it, and its pid now belongs to another program (here: this one): stale, not running
    discovery.announce(discovery.SessionInfo("sim", ["tcp/127.0.0.1:1"], os.getpid(), str(first)), first)
    assert [s.session for s in discovery.running_sessions()] == []  # and its entry withdrawn
    # a stale announcement by a live pid (1: init), found by the msk live that now holds the name itself
    discovery.announce(discovery.SessionInfo("sim", ["tcp/127.0.0.1:1"], 1, str(first)), first)
    from services.sessions.live import check_not_running

    with discovery.claimed("sim", tmp_path / "fourth"):
        check_not_running("sim", tmp_path / "fourth")  # was: "a session of this name runs now (pid 1 ...)"
    assert not list((tmp_path / "registry").glob("sim-1.json"))
    with discovery.claimed("sim", first):
        discovery.announce(discovery.SessionInfo("sim", ["tcp/127.0.0.1:1"], os.getpid(), str(first)), first)
        assert [s.session for s in discovery.running_sessions()] == ["sim"]


def test_zenoh_endpoints_as_zenoh_reads_them():
    """What Zenoh accepts passes (metadata, interface config, IPv6, Unix sockets); what it refuses, and a HOST:PORT
    protocol without a port in range, is a ConfigError naming the flag."""
    import pytest

    from msk_core.errors import ConfigError
    from services.transport.zenoh_session import check_endpoint

    for good in (
        "tcp/127.0.0.1:7447",
        "tcp/[::1]:7447",
        "tcp/localhost:7447#iface=lo",
        "tcp/127.0.0.1:7447?prio=1-7;rel=1",
        "udp/224.0.0.224:7446#iface=eth0",
        "tls/gym-router.local:7447",
        "unixsock-stream//tmp/msk.sock",
        "tcp/127.0.0.1:0",
    ):
        assert check_endpoint(good, "--connect") == good
    for bad in ("foo", "tcp/localhost", "tcp/127.0.0.1:99999", "tcp/:7447"):
        with pytest.raises(ConfigError, match="--listen"):
            check_endpoint(bad, "--listen")


def test_a_subject_profile_that_does_not_fit_stops_msk_live_before_anything_starts(tmp_path, monkeypatch, capsys):
    """A bench-press subject in a deadlift session, and a file that is no subject profile: refused with the session
    file's subject (it used to start the whole graph, then fail in the estimator naming its session copy, and a
    non-JSON file was a traceback)."""
    import numpy as np

    from msk_core.estimate.profile import SubjectProfile
    from msk_core.model import load_pack
    from services import cli
    from services.sessions import discovery

    monkeypatch.setenv(discovery.REGISTRY_ENV, str(tmp_path / "registry"))
    bench = load_pack("bench_press")
    groups = list(bench.groups)
    subject = tmp_path / "ana_bench.json"
    SubjectProfile("bench_press", str(bench.version), groups, np.ones(len(groups)), np.ones(len(groups))).save(subject)
    session_file = tmp_path / "monday.toml"
    for pack, subject_file, said in (
        ("deadlift", subject, f"subject profile {subject} was calibrated for pack 'bench_press' (13 groups), not for"),
        ("bench_press", session_file, "not valid JSON"),
    ):
        session_file.write_text(
            f'[session]\nname = "monday"\npack = "{pack}"\nsubject = "{subject_file}"\nload_kg = 60\n'
            f'out = "{tmp_path / "out"}"\n'
        )
        assert cli.main(["live", str(session_file), "--sim", "--no-view", "--duration", "1"]) == 2
        error = capsys.readouterr().err
        assert said in error and str(subject_file) in error, error
    assert not (tmp_path / "out" / "logs").exists()  # no node was started


def test_sim_plays_a_session_files_own_trackers_by_segment_and_says_which_electrodes_differ(tmp_path):
    """Under --sim a session file naming the ids printed on its own trackers is played by the simulated tracker of
    each segment (it was a KeyError traceback), a segment the simulator has no tracker for is refused, and an
    electrode map that differs from the simulated sensors is said."""
    import pytest

    from msk_core.errors import ConfigError
    from services.sessions import live
    from services.sessions.live_session import LiveSession

    sources = live.sim_sources(live.RECORDINGS / "demo_session.mcap", "bench_press")
    said: list[str] = []
    own = LiveSession(tmp_path / "s.toml", trackers={"00B40001": "upper_arm_r", "00B497B2": "forearm_r"})
    trackers = live._sim_trackers(own, sources, ["upper_arm_r", "forearm_r"], said.append)
    assert trackers == {"00B4EB80": "upper_arm_r", "00B497B2": "forearm_r"}
    assert said == ["--sim: 00B40001 (upper_arm_r) is played by the simulated 00B4EB80"]
    with pytest.raises(ConfigError, match="--sim plays trackers on forearm_r, upper_arm_r only"):
        live._sim_trackers(LiveSession(tmp_path / "s.toml", trackers={"00B40002": "pelvis"}), sources, [], said.append)


def test_a_listen_endpoint_in_use_is_one_line_naming_the_flag(capsys):
    """A second node on a taken endpoint used to end in a zenoh.ZError traceback."""
    from services import cli
    from services.transport.zenoh_session import ZenohOptions, free_loopback_endpoint, open_session

    endpoint = free_loopback_endpoint()
    with open_session(ZenohOptions(listen=(endpoint,))):
        assert cli.main(["subscribe", "msk/s/joints", "--listen", endpoint, "--count", "1"]) == 2
    said = capsys.readouterr().err
    assert (
        f"field '--listen': cannot open the Zenoh session: Can not create a new TCP listener bound to {endpoint}"
        in said
    )
    assert "Address already in use" in said and "Traceback" not in said, said


def test_msk_set_stop_during_a_rest_says_nothing_changes(monkeypatch, capsys):
    """It printed "the set under way ends" when rest detection had ended the set already."""
    from services import cli
    from services.commands import sets

    def publish(args, make_event, command, **_):
        facts = {"load_kg": 60.0, "set_number": 2, "exercise": "bench_press", "athlete": "", "resting": True}
        return "gym", make_event(facts), "msk/gym/load"

    monkeypatch.setattr(sets, "publish_facts", publish)
    assert cli.main(["set", "stop"]) == 0
    assert "msk set: gym: no set was under way (set 2 had ended): nothing changes" in capsys.readouterr().out


def test_a_tool_probing_the_claim_does_not_stop_msk_live_from_taking_it(tmp_path, monkeypatch):
    """A view or dashboard that looks for sessions probes each announced one's claim with a shared lock for a moment
    (discovery._claim_held); an msk live claiming its name at that moment was refused as if the name were taken."""
    import fcntl
    import threading
    import time

    from services.sessions import discovery

    monkeypatch.setenv(discovery.REGISTRY_ENV, str(tmp_path / "registry"))
    path = discovery._claim_path("sim")  # noqa: SLF001
    path.parent.mkdir(parents=True)
    path.touch()
    probing, released = threading.Event(), threading.Event()

    def probe() -> None:  # as _claim_held, held a little longer than it does
        with open(path) as handle:
            fcntl.flock(handle, fcntl.LOCK_SH | fcntl.LOCK_NB)
            probing.set()
            time.sleep(0.05)
        released.set()

    threading.Thread(target=probe, daemon=True).start()
    assert probing.wait(5)
    with discovery.claimed("sim", tmp_path / "out"):
        assert released.is_set()  # it waited the probe out
        assert discovery._claim_held("sim", os.getpid())  # noqa: SLF001


def test_the_silence_notice_names_what_the_tool_waits_for_now(capsys):
    """A dashboard that followed a session started later said it still waited for the first one's topics."""
    import threading
    import time

    from services.sessions import discovery
    from services.transport.zenoh_session import ZenohOptions

    target = {"what": "msk/lab/**", "options": ZenohOptions(connect=("tcp/127.0.0.1:7447",))}
    received, stop = [0], threading.Event()
    thread = discovery.silence_notice(
        "msk dashboard", lambda: (target["what"], target["options"]), lambda: received[0], first_s=0.05, every_s=0.1,
        stop=stop,
    )  # fmt: skip
    time.sleep(0.1)
    target.update(what="msk/sim/**", options=ZenohOptions(connect=("tcp/127.0.0.1:7500",)))
    time.sleep(0.25)
    received[0] = 1
    thread.join(2.0)
    stop.set()
    said = capsys.readouterr().err.splitlines()
    assert not thread.is_alive() and len(said) >= 2, said
    assert "for msk/lab/** on tcp/127.0.0.1:7447" in said[0] and "0 messages so far" in said[0], said
    assert "for msk/sim/** on tcp/127.0.0.1:7500" in said[-1], said


def test_a_view_follows_the_next_session_once_the_one_it_shows_has_ended(tmp_path, monkeypatch):
    """A tablet left open between athletes: the view or dashboard stayed on the ended session while the next one ran.
    It moves once its announced session is gone and another is announced; it stays while its own runs, and a tool on
    a session nobody announced (a replay) that receives stays."""
    from services.sessions import discovery
    from services.transport.zenoh_session import ZenohOptions

    monkeypatch.setenv(discovery.REGISTRY_ENV, str(tmp_path / "registry"))
    first = discovery.SessionInfo("sim", ["tcp/127.0.0.1:40001"], os.getpid(), str(tmp_path / "a"))
    (first_entry,) = discovery.announce(first, tmp_path / "a")[1:]
    follower = discovery.SessionFollower(None, first.options(), every_s=0.0)
    assert follower.next_session(received=0) is None  # its own session is the only one
    assert follower.next_session(received=120) is None
    second = discovery.SessionInfo("monday", ["tcp/127.0.0.1:40002"], os.getpid(), str(tmp_path / "b"))
    discovery.announce(second, tmp_path / "b")
    assert follower.next_session(received=120) is None  # two run, none named, its own among them: stays
    discovery.withdraw(first_entry)  # the first athlete's session ends
    assert follower.next_session(received=120) == second
    follower.moved(second.options())
    assert follower.next_session(received=3) is None
    replay = discovery.SessionFollower(None, ZenohOptions(connect=("tcp/127.0.0.1:7447",)), every_s=0.0)
    assert replay.next_session(received=50) is None  # never announced: a replay it shows, not an ended session
    assert replay.next_session(received=0) == second  # opened before any session: follows the one that starts


def test_a_view_shows_the_next_session_on_its_endpoint_from_its_start(tmp_path, monkeypatch):
    """The next athlete's msk live often takes the same endpoint and name: the data simply resumed on the same keys,
    and the tablet showed the new session's sets after the last one's. A new msk live announced where the tool is now
    makes it start again (fresh state); its own session announced on stays."""
    from services.sessions import discovery

    monkeypatch.setenv(discovery.REGISTRY_ENV, str(tmp_path / "registry"))
    first = discovery.SessionInfo("sim", ["tcp/127.0.0.1:7447"], os.getpid(), str(tmp_path / "a"))
    (entry,) = discovery.announce(first, tmp_path / "a")[1:]
    follower = discovery.SessionFollower(None, first.options(), every_s=0.0)
    assert follower.next_session(received=10) is None  # its own session: stays
    discovery.announce(first, tmp_path / "a")  # announced again (facts changed): the same msk live
    assert follower.next_session(received=20) is None
    discovery.withdraw(entry)  # ended
    assert follower.next_session(received=20) is None  # nothing runs: stays on its last values
    second = discovery.SessionInfo("sim", ["tcp/127.0.0.1:7447"], os.getppid(), str(tmp_path / "b"))  # another pid
    discovery.announce(second, tmp_path / "b")
    assert follower.next_session(received=20) == second


def test_a_past_set_number_is_refused_where_it_would_have_started_the_next_set():
    """``msk load 65 --set 2`` during set 3 used to start set 4 without a word (a tracker takes a number it has
    passed as "the next set"); the facts apply from now on, so a past set's number is refused, naming both sets."""
    during_set_3 = {"exercise": "bench_press", "load_kg": 60, "set_number": 3, "athlete": "Ana", "resting": False}
    with pytest.raises(ConfigError) as refused:
        new_facts(during_set_3, load_kg=65, set_number=2, next_set=False, exercise=None, athlete=None)
    assert refused.value.field == "--set" and refused.value.value == 2
    assert "set 2 is over" in str(refused.value) and "set 3" in str(refused.value)
    # what the message offers works: the set under way, or the next one
    assert (
        new_facts(during_set_3, load_kg=65, set_number=3, next_set=False, exercise=None, athlete=None).set_number == 3
    )
    assert (
        new_facts(during_set_3, load_kg=65, set_number=None, next_set=True, exercise=None, athlete=None).set_number == 4
    )
    # a later number is still the operator's numbering of the next set
    assert (
        new_facts(during_set_3, load_kg=None, set_number=5, next_set=False, exercise=None, athlete=None).set_number == 5
    )


def test_two_sessions_starting_at_once_do_not_both_take_the_well_known_endpoint(tmp_path, monkeypatch):
    """Two ``msk live`` started together (a squad's racks) both found the well-known endpoint free, both took it,
    and the second one's recorder could not listen: that athlete's session stopped after 0.1 s (found by QA). The
    first claims it for its whole run; the second, meanwhile, takes a free port."""
    import contextlib

    from services.sessions import discovery
    from services.sessions.live import default_live_endpoint
    from services.transport.zenoh_session import DEFAULT_ENDPOINT, endpoint_is_free

    monkeypatch.setenv(discovery.REGISTRY_ENV, str(tmp_path / "registry"))
    with contextlib.ExitStack() as first:
        taken = default_live_endpoint(first)
        with contextlib.ExitStack() as second:
            other = default_live_endpoint(second)  # neither has bound its endpoint yet
            assert other != taken and other != DEFAULT_ENDPOINT, (taken, other)
    if endpoint_is_free(DEFAULT_ENDPOINT):  # else another program holds it on this machine
        assert taken == DEFAULT_ENDPOINT
        with contextlib.ExitStack() as after:  # the first run ended: its claim went with it
            assert default_live_endpoint(after) == DEFAULT_ENDPOINT


def test_msk_load_and_msk_set_with_a_role_that_may_not_publish_facts_are_refused(tmp_path):
    """With the tablet's config, ``msk load 65`` printed "-> msk/sim/load" and the router dropped it: the estimator
    kept 60 kg while the operator read 65 (found by QA of the secured mode). The role is asked first, as the
    dashboard's set buttons do, and the command says why, naming the config."""
    from services.transport import security
    from tests.live_helpers import run_msk

    pki = security.write_pki(tmp_path / "pki", router_hosts=("localhost",))
    configs = security.write_configs(
        tmp_path / "zenoh", pki.directory, router_listen=("tls/127.0.0.1:1",), client_connect=("tls/localhost:1",)
    )
    env = {**os.environ, "MSK_SESSIONS_DIR": str(tmp_path / "registry")}
    for argv in (
        ("load", "65", "--set", "1", "--exercise", "bench_press", "--session", "sim"),
        ("set", "start", "--session", "sim"),
    ):
        done = run_msk(*argv, "--zenoh-config", str(configs["tablet"]), env=env)
        said = done.stdout + done.stderr
        assert done.returncode == 2, said
        assert "role 'tablet' may publish only" in said and "msk/sim/load" in said, said
        assert str(configs["tablet"]) in said and "publishing anyway" not in said and "Traceback" not in said, said
