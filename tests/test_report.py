"""`msk report` on the demo recording run through live estimators (two methods per exercise): sets, reps, per-muscle
per-rep numbers, balance, the method comparison and device health, and the HTML renders in headless Chromium."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from msk_core.model import load_pack
from msk_core.model.spec import BalanceSpec
from services.surfaces.dashboard import report
from services.transport import messages
from services.transport.mcap_io import McapRecorderWriter, read_messages
from tests.dashboard_helpers import (
    ARTIFACTS,
    DEMO_MCAP,
    launch_chromium,
    record_with_estimates,
    require_chromium,
    timed_recording,
)

METHODS = {"bench_press": ["so", "hybrid"], "deadlift": ["so", "hybrid"]}


@pytest.fixture(scope="module")
def demo_with_estimates(tmp_path_factory):
    from services.transport.zenoh_session import free_loopback_endpoint

    out = tmp_path_factory.mktemp("report") / "live.mcap"
    counts = record_with_estimates(DEMO_MCAP, out, free_loopback_endpoint(), packs=METHODS)
    return out, counts


@pytest.fixture(scope="module")
def demo_report(demo_with_estimates, tmp_path_factory):
    recording, _ = demo_with_estimates
    out = tmp_path_factory.mktemp("report") / "out"
    result = subprocess.run(
        [sys.executable, "-m", "services.cli", "report", str(recording), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    assert "4 sets, 12 reps, methods hybrid, so" in result.stderr
    return recording, out


@pytest.mark.slow
def test_report_of_the_demo_session(demo_report):
    recording, out = demo_report
    summary = json.loads((out / "report.json").read_text())
    assert summary["methods"] == ["hybrid", "so"]
    sets = summary["sets"]
    # The demo session: bench press 40 and 50 kg, deadlift 45 and 75 kg, three reps each (load events + joint phase).
    assert [(s["exercise"], s["load_kg"]) for s in sets] == [
        ("bench_press", 40),
        ("bench_press", 50),
        ("deadlift", 45),
        ("deadlift", 75),
    ]
    for s in sets:
        assert len(s["reps"]) == 3 and s["rep_source"] == "phase of the joint angles"
        assert s["time_under_tension_s"] == pytest.approx(sum(r["duration_s"] for r in s["reps"]))
        assert 2.0 < s["time_under_tension_s"] < s["end_s"] - s["start_s"]
        assert set(s["methods"]) == {"so", "hybrid"} and s["primary"] == "so"
        so = s["methods"]["so"]
        assert so["frames"] > 500 and so["rms_difference_to_primary"] == 0.0
        assert s["methods"]["hybrid"]["rms_difference_to_primary"] > 0.0
        for g, v in so["groups"].items():
            assert len(v["peak"]) == len(v["mean"]) == 3
            for peak, mean in zip(v["peak"], v["mean"]):
                assert 0.0 <= mean <= peak <= 1.0 + 1e-9, g
        # balance: exactly the pairs the pack declares, one row per rep
        declared = load_pack(s["exercise"]).balance
        joints = s["balance"]["agonist_antagonist"]
        assert [j["label"] for j in joints] == [j.label for j in declared.agonist_antagonist]
        assert all(len(j["per_rep"]) == 3 for j in joints)
        assert s["balance"]["left_right"] == []  # both packs model one side and declare no pair
    assert [j["label"] for j in sets[0]["balance"]["agonist_antagonist"]] == [
        "Elbow flexors / extensors",
        "Shoulder flexors / extensors",
    ]
    # heavier set, larger back extensor activation (set mean over reps)
    lumbar = [next(j for j in s["balance"]["agonist_antagonist"] if j["coordinate"] == "L5_S1_FE") for s in sets[2:]]
    assert sum(p for p, _, _ in lumbar[1]["per_rep"]) > sum(p for p, _, _ in lumbar[0]["per_rep"])
    # per-rep peaks agree with the recorded frames of the first rep
    first_rep = sets[0]["reps"][0]
    frames = [r.decode() for r in read_messages(recording) if r.topic.endswith("/activations/so")]
    inside = [f for f in frames if first_rep["start_s"] <= f.time_s <= first_rep["end_s"] and f.groups[0] == "BRA"]
    tri = list(inside[0].groups).index("TriLat")
    assert sets[0]["methods"]["so"]["groups"]["TriLat"]["peak"][0] == pytest.approx(
        max(f.activations[tri] for f in inside)
    )
    devices = summary["devices"]
    assert (
        devices["trigno-synth"]["samples"] > 100_000 and devices["trigno-synth"]["gaps"] == 3
    )  # the pauses between trials
    assert sum(1 for d in devices.values() if d["kind"] == "IMU") == 6  # each tracker under its own id
    assert {p.name for p in out.glob("*.png")} >= {
        "set1_activation.png",
        "set1_peaks.png",
        "set1_methods.png",
        "devices.png",
    }


@pytest.mark.slow
def test_report_renders_in_chromium(demo_report):
    require_chromium()
    from playwright import sync_api

    _, out = demo_report
    with sync_api.sync_playwright() as playwright:
        browser = launch_chromium(playwright)
        page = browser.new_page(viewport={"width": 1100, "height": 1400})
        page.goto((out / "report.html").as_uri())
        page.wait_for_load_state("load")
        images = page.evaluate("[...document.images].map(i => [i.getAttribute('src'), i.complete && i.naturalWidth])")
        assert images and all(width > 100 for _, width in images), images
        assert page.locator("section.set").count() == 4
        assert page.locator("section.set svg.bodymap .muscle").count() > 20
        text = page.inner_text("body")
        assert "Agonist / antagonist balance" in text and "Methods compared" in text
        assert "Left / right balance" not in text  # no pack of the session declares left/right pairs
        # muscles by their display names, joints by the labels of the pairs the packs declare; the model names only
        # where the method plot needs them, explained
        assert "Triceps brachii, lateral and medial heads" in text and "Back extensors / abdominals" in text
        assert "Elbow flexors / extensors" in text and "L5_S1_FE" not in text and "elbow_flex_r" not in text
        assert "Abbreviations: BRA: Brachialis · BRD: Brachioradialis" in text
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(ARTIFACTS / "report.png"), full_page=False)
        browser.close()


def test_report_without_activations_says_so(tmp_path):
    short = tmp_path / "raw.mcap"
    with McapRecorderWriter(short) as writer:
        for k, recorded in enumerate(read_messages(DEMO_MCAP)):
            if k > 3000:
                break
            writer.write(
                recorded.topic, recorded.type_name, recorded.data, recorded.log_time_ns, recorded.publish_time_ns
            )
    summary = report.write_report(short, tmp_path / "out")
    assert summary["methods"] == [] and summary["sets"] == []
    assert "No activation frames" in (tmp_path / "out" / "report.html").read_text()


def test_report_names_a_missing_recording(tmp_path):
    from msk_core.errors import InputError

    with pytest.raises(InputError, match="recording not found"):
        report.write_report(tmp_path / "nope.mcap", tmp_path / "out")


def test_reps_without_any_phase_come_from_msk_core_rep_detection():
    """Joint angles without a phase (e.g. an older recording): the reps of the first bench press set are found by
    msk_core's kinematic rep detection on the pack's phase coordinate (elbow_flex_r)."""
    from msk_core.model import load_pack

    data = report.SessionData()
    for recorded in read_messages(DEMO_MCAP):
        if recorded.type_name == "msk.JointAngles":
            j = recorded.decode()
            data.joint_time.append(j.device_time_ns / 1e9)
            data.joint_phase.append(math.nan)
            data.joint_q.setdefault(tuple(j.coordinates), []).append((j.device_time_ns / 1e9, list(j.q)))
        elif recorded.type_name == "msk.LoadEvent":
            e = recorded.decode()
            data.loads.append(report.Load(e.device_time_ns / 1e9, e.barbell_mass_kg, e.exercise))
    window = report.set_windows(data)[0]
    assert (window.exercise, window.load_kg) == ("bench_press", 40)
    series = report.MethodSeries(groups=("BRA",), time=[window.start_s], phase=[math.nan])
    reps, source = report.reps_in_set(data, window, series, load_pack("bench_press"))
    assert source == "rep detection on elbow_flex_r (msk_core.signal.reps)"
    assert len(reps) == 3 and all(1.0 < b - a < 6.0 for a, b in reps)


def write_small_session(
    path, *, loads: list, start_ns: int = 1_773_480_600_000_000_000, groups: tuple[str, str] = ("A", "B")
) -> None:
    """Two sets of three reps (phase of the joint angles), frames of the bench press with ``exercise`` set (two
    ``groups``), and the given load events as (seconds after the start, LoadEvent)."""
    from services.transport import messages

    with timed_recording(path, start_ns) as recording:
        recording.load_events(loads)
        for t_s, connected in ((0.0, True), (5.0, False), (6.0, True), (19.9, False)):  # lost once, then the stop
            recording.write(
                messages.DeviceStatus(device_id="00B4EB80", kind="xsens", connected=connected), t_s, "status/00B4EB80"
            )
        recording.write(
            messages.DeviceStatus(
                device_id="estimator",
                kind="node",
                connected=False,
                dropped=[messages.InputDrop(key="msk/s/joints", reason="undecodable", count=2)],
            ),
            19.9,
            "status/estimator",
        )
        for k in range(400):  # 20 s at 20 Hz: reps of 2 s at 1-3, 4-6, 7-9 s of each 10 s set
            t_s = k * 0.05
            in_set = t_s % 10.0
            phase = ((in_set - 1.0) % 3.0) / 2.0 if 1.0 <= in_set < 10.0 and (in_set - 1.0) % 3.0 < 2.0 else -1.0
            recording.joints_and_frame(t_s, phase, list(groups), [0.5 + 0.4 * max(phase, 0.0), 0.1])


def test_report_header_names_athlete_date_exercise_and_load(tmp_path):
    import datetime

    from services.transport import messages

    recording = tmp_path / "session.mcap"
    write_small_session(
        recording,
        loads=[
            (0.0, messages.LoadEvent(barbell_mass_kg=60, exercise="bench_press", set_number=1, athlete="Ana Lima")),
            (
                0.5,
                messages.LoadEvent(barbell_mass_kg=62.5, exercise="bench_press", set_number=1, athlete="Ana Lima"),
            ),  # corrected
            (10.0, messages.LoadEvent(barbell_mass_kg=70, exercise="bench_press", set_number=2, athlete="Ana Lima")),
        ],
    )
    summary = report.write_report(recording, tmp_path / "out")
    started = datetime.datetime.fromtimestamp(1_773_480_600).astimezone()
    assert summary["athlete"] == "Ana Lima" and summary["exercises"] == ["bench_press"]
    assert summary["loads_kg"] == [60, 62.5, 70] and summary["date"].startswith(started.strftime("%Y-%m-%d %H:%M"))
    assert [(s["name"], len(s["reps"])) for s in summary["sets"]] == [
        ("set 1: bench press, 62.5 kg", 3),
        ("set 2: bench press, 70 kg", 3),
    ]
    page = (tmp_path / "out" / "report.html").read_text()
    header = page[page.index("<header>") : page.index("</header>")]
    assert f"Session report: Ana Lima, {summary['date']}" in header and "bench press · 60, 62.5, 70 kg" in header
    assert "1773480600" not in header
    assert summary["devices"]["00B4EB80"]["disconnected_reports"] == 1  # the loss, not the driver's final status
    assert "estimator" not in summary["devices"] and summary["node_inputs_dropped"] == {"estimator": 2}  # a node


def test_report_header_names_the_estimated_exercise_and_its_loads_only(tmp_path):
    """A replay of a bench press and deadlift recording into a bench-press estimator declares both; the header says
    what was estimated, and the other exercise in a note (it listed "bench press, deadlift · 60, 100 kg")."""
    from services.transport import messages

    recording = tmp_path / "session.mcap"
    write_small_session(
        recording,
        loads=[
            (0.0, messages.LoadEvent(barbell_mass_kg=60, exercise="bench_press", set_number=1)),
            (19.95, messages.LoadEvent(barbell_mass_kg=100, exercise="deadlift", set_number=3)),
        ],
    )
    summary = report.write_report(recording, tmp_path / "out")
    assert summary["exercises"] == ["bench_press"] and summary["loads_kg"] == [60]
    assert summary["declared_not_estimated"] == ["deadlift"]
    page = (tmp_path / "out" / "report.html").read_text()
    assert "bench press · 60 kg" in page.split("</header>")[0]
    assert "Also declared, without estimates (the estimator ran another exercise's model): deadlift." in page


def test_report_without_load_events_takes_the_exercise_of_the_frames(tmp_path):
    recording = tmp_path / "session.mcap"
    write_small_session(recording, loads=[])
    summary = report.write_report(recording, tmp_path / "out")
    assert [s["name"] for s in summary["sets"]] == ["set 1: bench press, load unknown"]
    assert summary["athlete"] is None and summary["exercises"] == ["bench_press"] and summary["loads_kg"] == []
    header = (tmp_path / "out" / "report.html").read_text().split("</header>")[0]
    assert "athlete not named" in header and "bench press · load unknown" in header and "exercise 0 kg" not in header


def test_report_names_muscles_by_their_display_names_and_the_sessions(tmp_path):
    from services.transport import messages

    recording = tmp_path / "session.mcap"
    write_small_session(
        recording,
        groups=("TriLat", "PMCla"),
        loads=[
            (
                0.0,
                messages.LoadEvent(
                    barbell_mass_kg=60, exercise="bench_press", set_number=1, names={"PMCla": "Upper chest"}
                ),
            ),  # the session file's name, from msk live
            (
                10.0,
                messages.LoadEvent(barbell_mass_kg=70, exercise="bench_press", set_number=2),
            ),  # msk load: names stay
        ],
    )
    summary = report.write_report(recording, tmp_path / "out")
    for s in summary["sets"]:
        assert s["names"]["groups"]["TriLat"] == "Triceps brachii, lateral and medial heads"
        assert s["names"]["groups"]["PMCla"] == "Upper chest"
    page = (tmp_path / "out" / "report.html").read_text()
    rows = [row.split("</td>")[0] for row in page.split("<tr><td>")[1:]]
    # one per set's table and one in the peak / mean per set
    assert rows.count("Triceps brachii, lateral and medial heads") == rows.count("Upper chest") == 3
    assert "TriLat" not in rows and "PMCla" not in rows


def test_balance_only_of_the_declared_pairs():
    """lumbar_lift declares 7 left/right pairs and back extensors / abdominals: the balance has those and nothing
    else, with per-rep means; a pack declaring none has none, and the report says so in one note."""
    pack = load_pack("lumbar_lift")
    groups = list(pack.groups)
    t = np.arange(100) / 100
    activations = np.full((100, len(groups)), 0.1)
    activations[:, groups.index("iliocost_l")] = 0.2
    activations[:, groups.index("iliocost_r")] = np.where(t < 0.5, 0.4, 0.6)
    masks = [t < 0.5, t >= 0.5, t > 2]  # the last rep holds no frame: left out
    bal = report.balance(pack, groups, activations, masks)
    assert [(p["left"], p["right"]) for p in bal["left_right"]] == list(pack.balance.left_right)
    ilio = next(p for p in bal["left_right"] if p["left"] == "iliocost_l")
    assert ilio["per_rep"] == [pytest.approx((0.2, 0.4)), pytest.approx((0.2, 0.6))]
    (back,) = bal["agonist_antagonist"]
    assert back["label"] == "Back extensors / abdominals" and back["antagonists"] == ["rectabd_l", "rectabd_r"]
    assert back["per_rep"][0][1] == pytest.approx(0.1) and back["per_rep"][0][0] > 0.1
    assert back["per_rep"][0][2] == pytest.approx(0.1 / back["per_rep"][0][0])
    names = pack.display_names
    rendered = report._balance_html(bal, names, 2)
    assert "Iliocostalis lumborum, left / Iliocostalis lumborum, right" in rendered and "20 / 40" in rendered
    # frames lacking a declared group: its pairs are left out
    assert len(report.balance(pack, groups[:2], activations[:, :2], masks)["left_right"]) == 1
    undeclared = SimpleNamespace(balance=BalanceSpec(), groups=groups, f_max_ref=pack.f_max_ref)
    empty = report.balance(undeclared, groups, activations, masks)
    assert empty == {"left_right": [], "agonist_antagonist": []}
    note = report._balance_html(empty, names, 2)
    assert "declares no left/right or agonist/antagonist pairs" in note and "<table" not in note


def _two_racks(path, n: int = 3000) -> int:
    """The demo's first ``n`` messages as recorded session "synth" and again as "rack2", interleaved (one recorder
    of ``msk/**`` on a machine with two racks); returns how many each has."""
    from services.transport import topics

    with McapRecorderWriter(path) as writer:
        for k, recorded in enumerate(read_messages(DEMO_MCAP)):
            if k >= n:
                break
            for topic in (recorded.topic, topics.rename_session(recorded.topic, "rack2")):
                writer.write(topic, recorded.type_name, recorded.data, recorded.log_time_ns, recorded.publish_time_ns)
    return n


def test_a_recording_of_two_sessions_is_reported_one_session_at_a_time(tmp_path):
    from msk_core.errors import InputError
    from services.transport.mcap_io import recorded_sessions

    both = tmp_path / "both.mcap"
    n = _two_racks(both)
    assert recorded_sessions(both) == {"synth": n, "rack2": n}
    with pytest.raises(InputError) as error:
        report.write_report(both, tmp_path / "out")
    said = str(error.value)
    assert "2 sessions: 'synth' (3000 messages), 'rack2' (3000 messages); name one with --session" in said, said
    assert "field '--session'" in said and "both.mcap" in said, said
    with pytest.raises(InputError, match="holds no session 'rack3'"):
        report.read_session(both, session="rack3")
    one = report.read_session(both, session="rack2")
    alone = tmp_path / "alone.mcap"
    with McapRecorderWriter(alone) as writer:
        for k, recorded in enumerate(read_messages(DEMO_MCAP)):
            if k >= n:
                break
            writer.write(
                recorded.topic, recorded.type_name, recorded.data, recorded.log_time_ns, recorded.publish_time_ns
            )
    single = report.read_session(alone)
    assert {k: len(v) for k, v in one.imu.items()} == {k: len(v) for k, v in single.imu.items()} != {}
    assert len(one.joint_time) == len(single.joint_time) and len(one.loads) == len(single.loads)
    # a recording cut short has no summary: its sessions are read through
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(both.read_bytes()[: both.stat().st_size * 2 // 3])
    sessions = recorded_sessions(cut)
    assert set(sessions) == {"synth", "rack2"} and 0 < sum(sessions.values()) < 2 * n
    for short in (9, 43, 95, 350):  # its summary or footer cut: struct.error inside mcap, read through instead
        cut.write_bytes(both.read_bytes()[:-short])
        assert set(recorded_sessions(cut)) == {"synth", "rack2"}


def test_a_sets_peak_and_time_active_are_under_tension_as_the_caption_says(tmp_path):
    """The table says its figures are over the set's reps; the set peak and 'time > 20 %' counted the rests between
    them too (a triceps 42 s 'active' in a set with 25 s under tension)."""
    from services.transport import messages

    recording = tmp_path / "session.mcap"
    write_small_session(
        recording, loads=[(0.0, messages.LoadEvent(barbell_mass_kg=60, exercise="bench_press", set_number=1))]
    )
    summary = report.write_report(recording, tmp_path / "out")
    for s in summary["sets"]:
        primary = s["methods"][s["primary"]]["groups"]
        tension = s["time_under_tension_s"]
        for g, figures in primary.items():
            # each frame stands for the time to the next one in its rep: never more than the time under tension (a
            # frame count x the median interval overshot it by a frame per rep: 38.6 s above 20 % in 38.3 s)
            assert figures["time_active_s"] <= tension + 1e-9, (g, figures, tension)
            assert figures["set_peak"] == pytest.approx(max(p for p in figures["peak"] if p is not None)), (g, figures)


def test_the_session_length_is_that_of_its_frames_not_of_the_start_up_before_them(tmp_path):
    """A live session's recording starts with the nodes' start-up (statuses, seconds before the first frame): its
    report said "106 s recorded" of a 100 s session."""
    from services.transport import messages

    recording = tmp_path / "session.mcap"
    with timed_recording(recording, 1_773_480_600_000_000_000) as session:
        session.write(
            messages.DeviceStatus(device_id="estimator", kind="node", connected=True), 0.0, "status/estimator"
        )
        for k in range(200):  # frames from 6 s to 15.95 s
            session.joints_and_frame(6.0 + 0.05 * k, -1.0, ["A", "B"], [0.1, 0.1])
    summary = report.write_report(recording, tmp_path / "out")
    assert summary["duration_s"] == pytest.approx(9.95), summary["duration_s"]


def test_a_folder_that_cannot_be_made_is_said_without_a_traceback(tmp_path, capsys):
    """The file system's refusals (no such folder, a file in the way, no permission, disk full) ended in tracebacks
    of msk report, msk recorder and msk live (found by exploratory QA)."""
    from services import cli

    recording = tmp_path / "session.mcap"
    write_small_session(recording, loads=[])
    in_the_way = tmp_path / "a_file"
    in_the_way.write_text("not a folder")
    assert cli.main(["report", str(recording), "--out", str(in_the_way / "report")]) == 2
    said = capsys.readouterr().err
    assert said.startswith("msk report: error: ") and str(in_the_way) in said and "Traceback" not in said, said


def test_payloads_that_are_not_their_message_are_counted_not_fatal(tmp_path, capsys):
    """Four garbage payloads on an activation topic stopped the whole report with "12 bytes are not a valid
    msk.ActivationFrame", naming neither the file nor the topic (found by exploratory QA)."""
    from services import cli

    recording = tmp_path / "session.mcap"
    with timed_recording(recording, 1_773_480_600_000_000_000) as session:
        for k in range(200):
            session.joints_and_frame(0.05 * k, -1.0, ["A", "B"], [0.1, 0.1])
            if k % 50 == 0:
                ns = session.start_ns + int(0.05 * k * 1e9)
                session.writer.write("msk/s/activations/so", "msk.ActivationFrame", b"\\xff" * 12, ns, ns)
    assert cli.main(["report", str(recording), "--out", str(tmp_path / "out")]) == 0
    summary = json.loads((tmp_path / "out" / "report.json").read_text())
    assert summary["undecodable_payloads"] == {"msk/s/activations/so": 4} and summary["recording_damage"] == ""
    said = capsys.readouterr().err
    assert (
        f"warning: {recording}: payloads that were not their topic's message, left out: 4 on msk/s/activations/so"
        in said
    )


def test_the_session_length_of_two_exercises_replayed_together_and_of_a_restarted_clock(tmp_path):
    """``msk demo`` replays a bench press and a deadlift together: their frames interleave in the log, 40 s apart on
    the devices' clock, and the report said "16 s recorded" (the fast replay's log span) of a 60 s session. Each
    pack's frames are one stream; a stream whose clock starts again (a power cycle) still falls back to the log."""
    from services.transport import messages

    def frame(t_s: float, bench: bool) -> messages.ActivationFrame:
        return messages.ActivationFrame(
            time_s=1_773_480_600 + t_s,
            method="so",
            groups=["A", "B"] if bench else ["C", "D", "E"],
            activations=[0.1, 0.1] if bench else [0.1, 0.1, 0.1],
            exercise="bench_press" if bench else "deadlift",
        )

    together, restarted = tmp_path / "together.mcap", tmp_path / "restarted.mcap"
    with timed_recording(together, 1_773_480_600_000_000_000) as session:
        for k in range(200):  # 10 s of log time: bench 0-20 s, deadlift 40-60 s of device time, interleaved
            session.write(frame(0.1 * k, True), 0.05 * k, "activations/so")
            session.write(frame(40.0 + 0.1 * k, False), 0.05 * k + 0.01, "activations/so")
    assert report.write_report(together, tmp_path / "a")["duration_s"] == pytest.approx(59.9)
    with timed_recording(restarted, 1_773_480_600_000_000_000) as session:
        for k in range(200):  # 10 s of frames at 5000 s of the device's clock, then it starts again at 0
            session.write(frame(0.1 * (k % 100) + (5000.0 if k < 100 else 0.0), True), 0.1 * k, "activations/so")
    assert report.write_report(restarted, tmp_path / "b")["duration_s"] == pytest.approx(19.9)


def test_a_series_keeps_one_row_per_frame_in_typed_arrays():
    """The frames are kept flat in typed arrays (a 16-minute session's report read 181 MB of Python floats, now 81);
    each field still gives one row per frame, and a frame whose torque count differs from the first's has NaN
    residuals rather than shifting every later row."""
    series = report.MethodSeries(groups=("A", "B"))
    for k, torques in enumerate([2, 2, 0, 2]):
        frame = messages.ActivationFrame(time_s=float(k), method="so", groups=["A", "B"], activations=[0.1 * k, 0.2])
        if k == 1:
            frame.phase = 0.5
            frame.flags.append("reserve")
        for c in range(torques):
            frame.torques.add(coordinate=f"c{c}", residual_nm=float(10 * k + c))
        series.add(frame)
    assert series.array("activations").shape == (4, 2) and series.array("activations")[3].tolist() == [0.1 * 3, 0.2]
    residual = series.array("residual")
    assert residual.shape == (4, 2) and np.isnan(residual[2]).all() and residual[3].tolist() == [30.0, 31.0]
    assert series.array("flagged").tolist() == [False, True, False, False]
    assert np.isnan(series.array("phase")[[0, 2, 3]]).all() and series.array("phase")[1] == 0.5
