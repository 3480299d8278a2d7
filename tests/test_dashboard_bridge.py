"""The dashboard's bridge state (newest frame per topic, reps, device health), its body map and its web app, without
a browser: the state is fed real protobuf payloads, the app is served by uvicorn on a free port."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time
import urllib.request
import xml.etree.ElementTree as ET

import pytest

from msk_core.model import available_packs, load_pack
from msk_core.signal.reps import MIN_REP_S
from services.surfaces.dashboard import bodymap
from services.surfaces.dashboard.bridge import HAS_MEASURED_ENVELOPE, DashboardState, RepCounter
from services.transport import messages
from tests.conftest import free_tcp_port

PREFIX = "msk/t/"


def activation_frame(
    method: str, a: list[float], *, t: float, phase: float | None = None, envelope=None, exercise: str = ""
) -> messages.ActivationFrame:
    frame = messages.ActivationFrame(
        time_s=t,
        method=method,
        groups=["A", "B"],
        activations=a,
        activation_std=[0.1, float("nan")],
        publish_ns=2_000_000,
        input_arrival_ns=1_000_000,
        exercise=exercise,
    )
    frame.torques.add(coordinate="elbow", inverse_dynamics_nm=3.0, model_nm=2.5, residual_nm=0.5)
    if phase is not None:
        frame.phase = phase
    if envelope is not None:
        frame.measured_envelope.extend(envelope)
    return frame


def joints(phase: float, t: float) -> messages.JointAngles:
    return messages.JointAngles(coordinates=["x"], q=[0.0], phase=phase, device_time_ns=int(round(t * 1e9)))


def test_state_keeps_only_the_newest_frame_per_topic():
    state = DashboardState("t")
    seq0, first = state.changes(0)
    assert first["topics"] == {} and first["data_age_s"] is None
    for i in range(50):  # a burst the page did not take: only the last one is left
        state.on_message(PREFIX + "activations/so", activation_frame("so", [i / 50, 0.5], t=i))
    seq, update = state.changes(seq0)
    # no joint angles with a phase: the reps follow the first method's frames (phase unset here: unknown)
    # and the session entry: the names of the frames' groups
    assert sorted(update["topics"]) == ["activations/so", "reps", "session", "sets"]
    assert update["topics"]["reps"]["phase"] is None
    frame = update["topics"]["activations/so"]
    assert frame["time_s"] == 49 and frame["activations"] == [0.98, 0.5]
    assert frame["std"] == [0.1, None]  # NaN -> null: the page gets valid JSON
    assert frame["estimator_latency_ms"] == 1.0 and frame["torques"][0]["model_nm"] == 2.5
    assert json.dumps(update, allow_nan=False)
    assert state.changes(seq)[1]["topics"] == {}  # nothing new since
    state.on_message(PREFIX + "activations/hybrid", activation_frame("hybrid", [0.1, 0.2], t=50))
    assert list(state.changes(seq)[1]["topics"]) == ["activations/hybrid"]
    state.on_message("msk/other/activations/so", activation_frame("so", [1, 1], t=1))  # other session
    assert state.received == 51


def test_measured_envelope_is_forwarded_when_the_schema_has_it():
    state = DashboardState("t")
    if HAS_MEASURED_ENVELOPE:
        frame = activation_frame("so", [0.2, 0.3], t=1, envelope=[0.25, float("nan")])
        expected = [0.25, None]  # NaN where no electrode
    else:
        frame, expected = activation_frame("so", [0.2, 0.3], t=1), []
    state.on_message(PREFIX + "activations/so", frame)
    assert state.changes(0)[1]["topics"]["activations/so"]["envelope"] == expected


def test_rep_counter_counts_rest_transitions_and_wraps_and_restarts_per_set():
    reps = RepCounter()
    reps.new_set()
    for k, p in enumerate([-1, 0.0, 0.3, 0.6, 0.9, -1, -1, 0.1, 0.5, 0.95, 0.05, 0.5, 0.9, -1]):
        reps.update(0.2 * k, p)  # 5 Hz
    assert (reps.in_set, reps.total, reps.sets.number) == (3, 3, 1)
    reps.update(3.0, None)  # unknown phase: no rep invented
    reps.update(3.2, 0.1)  # a flicker into a rep, shorter than MIN_REP_S: not a rep
    reps.update(3.2 + 0.9 * MIN_REP_S, 0.6)
    reps.update(3.8, -1)
    assert (reps.in_set, reps.total) == (3, 3)
    reps.new_set()
    for t, p in ((4.0, 0.2), (4.4, 0.7), (4.8, -1)):
        reps.update(t, p)
    assert (reps.in_set, reps.total, reps.sets.number) == (1, 4, 2)
    reps.sets.stop(5.0)  # set 2 done: the header says "2 done" and its last rep, not "rep 0"
    assert (reps.as_dict()["resting"], reps.as_dict()["rep"]) == (True, 1)


def test_reps_from_joints_phase_and_device_health_from_samples():
    state = DashboardState("t")
    state.on_message(PREFIX + "load", messages.LoadEvent(barbell_mass_kg=60, exercise="deadlift"))
    for k, p in enumerate([-1.0, 0.2, 0.7, -1.0]):
        state.on_message(PREFIX + "joints", joints(p, 0.4 * k))
    now = time.time_ns()
    for first in (0, 100, 300):  # samples 200..299 never arrived
        chunk = messages.EmgChunk(
            source_id="trigno-1",
            first_sample_index=first,
            n_samples=100,
            n_channels=1,
            samples=[0.0] * 100,
            host_time_ns=now,
        )
        state.on_message(PREFIX + "emg/trigno-1", chunk, arrival_ns=now + 3_000_000)
    state.on_message(
        PREFIX + "status/xsens-1",
        messages.DeviceStatus(device_id="xsens-1", kind="xsens", connected=False, samples_lost=7),
    )
    update = state.changes(0, now_ns=now + 4_000_000)[1]
    assert update["topics"]["reps"] == {
        "in_set": 1,
        "rep": 1,
        "total": 1,
        "set": 1,
        "resting": False,
        "time_in_set_s": pytest.approx(1.2),
        "phase": -1.0,
        "movement": None,  # at rest
    }
    (only,) = update["topics"]["sets"]  # the table of sets: msk_core.signal.sets.SetRecord.as_dict
    assert (only["number"], only["reps"], only["ended_by"]) == (1, 1, "")
    assert update["topics"]["load"] == {"mass_kg": 60, "exercise": "deadlift", "set_number": 0, "athlete": ""}
    trigno = update["devices"]["trigno-1"]
    assert trigno["samples"] == 300 and trigno["samples_lost"] == 100 and trigno["delivering"]
    assert trigno["latency_ms"] == pytest.approx(3.0)
    assert update["devices"]["xsens-1"]["connected"] is False and update["devices"]["xsens-1"]["samples_lost"] == 7


@pytest.mark.parametrize("name", available_packs())
def test_body_map_places_every_group_of_every_pack(name):
    pack = load_pack(name)
    body = bodymap.place_groups(pack)
    assert body.unmapped == []
    assert {p.group for p in body.placements} == set(pack.groups)
    svg = ET.fromstring(body.svg(fills={pack.groups[0]: "#123456"}))
    shapes = [e for e in svg.iter() if e.get("class") == "muscle"]
    assert {e.get("data-group") for e in shapes} == set(pack.groups)
    assert {e.get("fill") for e in shapes if e.get("data-group") == pack.groups[0]} == {"#123456"}


def test_body_map_sides_and_colours():
    sides = {(p.group, p.side) for p in bodymap.place_groups(load_pack("lumbar_lift")).placements}
    assert ("latdorsi_r", "r") in sides and ("latdorsi_l", "l") in sides and ("latdorsi_r", "l") not in sides
    bench = {p.group: p for p in bodymap.place_groups(load_pack("bench_press")).placements}
    assert (
        bench["DelAnt"].region == "deltoid_anterior" and bench["DelAnt"].side == "r"
    )  # DELT1 has no suffix: the pack's side
    assert bench["TriLong"].region == "triceps_long" and bodymap.REGIONS["triceps_long"].view == "back"
    assert bodymap.activation_colour(0.0) == "#ffde3c" and bodymap.activation_colour(1.0) == "#640014"
    assert bodymap.activation_colour(math.nan) == bodymap.activation_colour(None) == "#b8bec7"


def _lab(colour: str) -> list[float]:
    """CIE L*a*b* (D65) of an sRGB colour "#rrggbb"."""
    rgb = [int(colour[i : i + 2], 16) / 255 for i in (1, 3, 5)]
    lin = [c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4 for c in rgb]
    rows = ((0.4124, 0.3576, 0.1805), (0.2126, 0.7152, 0.0722), (0.0193, 0.1192, 0.9505))
    white = (0.95047, 1.0, 1.08883)
    x, y, z = (sum(m * c for m, c in zip(row, lin)) / w for row, w in zip(rows, white))
    f = [v ** (1 / 3) if v > (6 / 29) ** 3 else v / (3 * (6 / 29) ** 2) + 4 / 29 for v in (x, y, z)]
    return [116 * f[1] - 16, 500 * (f[0] - f[1]), 200 * (f[1] - f[2])]


def test_low_activations_stand_out_from_the_grey_body_and_the_map_shows_the_exercises_part():
    """0-25 % is far from the grey body (CIE76 difference; 2.3 is a just-noticeable one) and from unknown; an arm
    exercise's map is the upper body, a leg one's the lower body, a lift's the whole figure."""
    body = _lab("#e4e7eb")
    differences = [math.dist(_lab(bodymap.activation_colour(v)), body) for v in (0.0, 0.05, 0.1, 0.25)]
    print("CIE76 from the grey body at 0, 5, 10, 25 %:", [round(d, 1) for d in differences])
    assert min(differences) > 50 and math.dist(_lab("#fff5c8"), body) < 30  # the former 0 % colour did not
    assert math.dist(_lab(bodymap.activation_colour(0.0)), _lab(bodymap.activation_colour(0.25))) > 20
    parts = {name: bodymap.extent(bodymap.place_groups(load_pack(name))) for name in available_packs()}
    assert parts["bench_press"] == bodymap.UPPER_BODY and parts["deadlift"] == bodymap.WHOLE_BODY, parts
    svg = ET.fromstring(bodymap.place_groups(load_pack("bench_press")).svg())
    assert svg.get("data-part") == "upper" and svg.get("viewBox").split()[1:4:2] == ["4", "236"]


def test_msk_dashboard_command_serves_the_page_and_stops_on_sigint(zenoh_endpoint):
    port = free_tcp_port()
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.cli",
            "dashboard",
            "--session",
            "gym",
            "--port",
            str(port),
            "--listen",
            zenoh_endpoint,
        ],
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline, body = time.monotonic() + 30, None
        while body is None and time.monotonic() < deadline and process.poll() is None:
            try:
                body = urllib.request.urlopen(f"http://127.0.0.1:{port}/config.json", timeout=2).read()
            except OSError:
                time.sleep(0.2)
        assert body is not None, f"no answer on port {port} within 30 s (exit code {process.poll()})"
        config = json.loads(body)
        assert config["session"] == "gym" and config["packs"]["bench_press"][0] == "BRA"
        assert config["default_methods"][:2] == ["assisted", "proposed"]  # the method shown first, as view and report
        page = urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=5).read().decode()
        assert "chart-4.6.1.umd.min.js" in page and 'id="nodata"' in page
        request = urllib.request.Request(
            f"http://127.0.0.1:{port}/static/vendor/chart-4.6.1.umd.min.js", headers={"Accept-Encoding": "gzip"}
        )
        with urllib.request.urlopen(request, timeout=5) as response:  # compressed for the tablet
            assert response.status == 200 and response.headers["Content-Encoding"] == "gzip"
            assert len(response.read()) < 100_000
        svg = urllib.request.urlopen(f"http://127.0.0.1:{port}/bodymap/deadlift.svg", timeout=5).read().decode()
        assert 'data-group="Gmax"' in svg
        with pytest.raises(urllib.error.HTTPError) as missing:
            urllib.request.urlopen(f"http://127.0.0.1:{port}/bodymap/nope.svg", timeout=5)
        assert missing.value.code == 404
    finally:
        process.send_signal(2)
        try:
            _, stderr = process.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            process.kill()
            raise
    assert process.returncode == 0, stderr
    assert "dashboard of session 'gym' on http://127.0.0.1:" in stderr and "dashboard stopped" in stderr


def test_port_in_use_is_a_clear_error():
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        result = subprocess.run(
            [sys.executable, "-m", "services.cli", "dashboard", "--port", str(port)],
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert result.returncode == 2 and f"cannot listen on 127.0.0.1:{port}" in result.stderr


def test_bad_session_name_is_refused():
    from msk_core.errors import ConfigError
    from services.surfaces.dashboard.app import DashboardConfig, DashboardServer
    from services.transport.zenoh_session import ZenohOptions

    with pytest.raises(ConfigError, match="--session"):
        DashboardServer(ZenohOptions(), DashboardConfig(session="a/b"), port=free_tcp_port())


def test_devices_without_estimates_are_not_live_data():
    state = DashboardState("t")
    chunk = messages.EmgChunk(source_id="trigno-1", first_sample_index=0, n_samples=1, n_channels=1, samples=[0.0])
    now = time.time_ns()
    state.on_message(PREFIX + "emg/trigno-1", chunk, arrival_ns=now)
    update = state.changes(0, now_ns=now + 500_000_000)[1]
    assert update["data_age_s"] == pytest.approx(0.5) and update["activation_age_s"] is None  # the page says "no data"
    state.on_message(PREFIX + "activations/so", activation_frame("so", [0.1, 0.2], t=1), arrival_ns=now)
    assert state.changes(0, now_ns=now + 10**9)[1]["activation_age_s"] == pytest.approx(1.0)


def imu(tracker: str, counter: int, host_time_ns: int, segment: str = "") -> messages.ImuSample:
    sample = messages.ImuSample(tracker_id=tracker, segment=segment, packet_counter=counter, host_time_ns=host_time_ns)
    sample.orientation.w = 1.0
    return sample


def test_every_tracker_and_the_trigno_base_are_rows_of_their_own():
    """Each Xsens tracker under its own id (the one its DeviceStatus uses), with its own samples; one that stops goes
    silent while the other delivers; the Trigno base under its EmgChunk.source_id, merged with its status."""
    from tests.dashboard_helpers import trigno_chunk

    state = DashboardState("t")
    t0 = time.time_ns()
    for k in range(20):  # both trackers stream for 0.2 s
        for tracker, segment in (("00B4EB80", "upper_arm_r"), ("00B497B2", "forearm_r")):
            state.on_message(PREFIX + f"imu/{segment}", imu(tracker, k, t0, segment), arrival_ns=t0 + k * 10_000_000)
    for k in range(20, 320):  # then only the forearm tracker, for 3 s more
        state.on_message(PREFIX + "imu/forearm_r", imu("00B497B2", k, t0, "forearm_r"), arrival_ns=t0 + k * 10_000_000)
    for tracker in ("00B4EB80", "00B497B2"):
        state.on_message(
            PREFIX + f"status/{tracker}", messages.DeviceStatus(device_id=tracker, kind="xsens", connected=True)
        )
    state.on_message(PREFIX + "emg/trigno", trigno_chunk(0, t0), arrival_ns=t0 + 3_190_000_000)
    state.on_message(
        PREFIX + "status/trigno",
        messages.DeviceStatus(device_id="trigno", kind="trigno", connected=True, samples_lost=3),
    )
    devices = state.changes(0, now_ns=t0 + 3_200_000_000)[1]["devices"]
    assert sorted(devices) == ["00B497B2", "00B4EB80", "trigno"]  # no phantom "xsens" row, one row per device
    upper, forearm, trigno = devices["00B4EB80"], devices["00B497B2"], devices["trigno"]
    assert (upper["kind"], upper["segment"], upper["samples"], upper["delivering"]) == (
        "xsens",
        "upper_arm_r",
        20,
        False,
    )
    assert (forearm["kind"], forearm["segment"], forearm["samples"], forearm["delivering"]) == (
        "xsens",
        "forearm_r",
        320,
        True,
    )
    assert upper["connected"] is True and upper["age_s"] == pytest.approx(
        3.01
    )  # its status says connected: silent still
    assert (trigno["kind"], trigno["samples"], trigno["samples_lost"], trigno["delivering"]) == ("trigno", 27, 3, True)


def test_session_facts_from_the_load_event_else_from_the_frames():
    state = DashboardState("t")
    state.on_message(PREFIX + "activations/so", activation_frame("so", [0.1, 0.2], t=1, exercise="bench_press"))
    facts = state.changes(0)[1]["topics"]["session"]
    assert facts.pop("names")["groups"] == {"A": "A", "B": "B"}  # not the groups of the pack: by their model names
    # no load event yet: the frames'
    assert facts == {
        "exercise": "bench_press",
        "load_kg": None,
        "athlete": None,
        "paused": None,
        "set_figures_method": "so",  # the only method: the sets' figures are its
    }
    for k, p in enumerate((-1.0, 0.2, 0.8, -1.0)):
        state.on_message(PREFIX + "joints", joints(p, 0.4 * k))
    seq, _ = state.changes(0)
    state.on_message(
        PREFIX + "load", messages.LoadEvent(barbell_mass_kg=60, exercise="bench_press", set_number=2, athlete="Ana")
    )
    update = state.changes(seq)[1]["topics"]
    assert update["session"] | {"names": None} == {
        "exercise": "bench_press",
        "load_kg": 60,
        "athlete": "Ana",
        "names": None,
        "paused": None,
        "set_figures_method": "so",
    }
    assert update["reps"]["set"] == 2 and update["reps"]["in_set"] == 0
    for k, p in enumerate((0.2, 0.8, -1.0)):
        state.on_message(PREFIX + "joints", joints(p, 2.0 + 0.4 * k))
    # the operator corrects the load within set 2: same set, the reps of the set are kept
    state.on_message(
        PREFIX + "load", messages.LoadEvent(barbell_mass_kg=62.5, exercise="bench_press", set_number=2, athlete="Ana")
    )
    topics_now = state.changes(0)[1]["topics"]
    assert (
        topics_now["reps"]["set"] == 2
        and topics_now["reps"]["in_set"] == 1
        and topics_now["session"]["load_kg"] == 62.5
    )
    state.on_message(
        PREFIX + "load", messages.LoadEvent(barbell_mass_kg=70, exercise="bench_press", set_number=3, athlete="Ana")
    )
    now = state.changes(0)[1]["topics"]
    assert (now["reps"]["in_set"], now["reps"]["total"], now["reps"]["set"]) == (0, 2, 3)
    # the rep before any load event opened set 1 (rest detection's rule); the operator's numbers follow
    assert [(s["number"], s["reps"], s["ended_by"]) for s in now["sets"]] == [
        (1, 1, "next set"),
        (2, 1, "next set"),
        (3, 0, ""),
    ]
    # a load event the estimator refuses (an exercise no pack has and no frame named): not shown, counted
    seq = state.changes(0)[0]
    state.on_message(PREFIX + "load", messages.LoadEvent(barbell_mass_kg=5, exercise="upper_arm_r", set_number=4))
    update = state.changes(seq)[1]
    assert "session" not in update["topics"] and "reps" not in update["topics"], update["topics"]
    assert update["nodes"]["dashboard"]["drops"] == [[PREFIX + "load", "invalid", 1]], update["nodes"]
    # another shipped pack declared: the bench estimator pauses; the page is told why, and no longer once it resumes
    state.on_message(PREFIX + "load", messages.LoadEvent(barbell_mass_kg=80, exercise="deadlift", set_number=4))
    paused = state.changes(0)[1]["topics"]["session"]["paused"]
    assert paused.startswith("The operator's load event declares deadlift, and this session estimates bench press")
    assert paused.endswith("(msk load --exercise bench_press)."), paused
    state.on_message(PREFIX + "load", messages.LoadEvent(barbell_mass_kg=80, exercise="bench_press", set_number=4))
    assert state.changes(0)[1]["topics"]["session"]["paused"] is None


def test_a_subject_pack_named_before_its_frames_is_applied_when_they_come():
    """A session of a subject's own pack: its opening facts arrive before any frame; they are shown once the first
    frame names that pack, and another unknown exercise held beside them is refused."""
    state = DashboardState("t")
    state.on_message(PREFIX + "load", messages.LoadEvent(barbell_mass_kg=40, exercise="ana_bench", set_number=1))
    state.on_message(PREFIX + "load", messages.LoadEvent(barbell_mass_kg=99, exercise="squat", set_number=7))
    assert "session" not in state.changes(0)[1]["topics"]
    # the operator starts a set before the first frame: the mark carries the facts that wait, not 0 kg
    mark = state.set_mark_event("start")
    assert (mark.barbell_mass_kg, mark.exercise, mark.set_mark) == (99, "squat", "start")
    state.on_message(PREFIX + "activations/so", activation_frame("so", [0.1, 0.2], t=1, exercise="ana_bench"))
    now = state.changes(0)[1]
    assert now["topics"]["session"]["exercise"] == "ana_bench" and now["topics"]["session"]["load_kg"] == 40
    assert now["topics"]["reps"]["set"] == 1
    assert now["nodes"]["dashboard"]["drops"] == [[PREFIX + "load", "invalid", 1]]


def test_display_names_of_the_frames_pack_and_the_sessions_reach_the_page():
    state = DashboardState("t")
    groups = list(load_pack("bench_press").groups)
    frame = messages.ActivationFrame(
        time_s=1.0, method="so", groups=groups, activations=[0.1] * len(groups), exercise="bench_press"
    )
    state.on_message(PREFIX + "activations/so", frame)
    names = state.changes(0)[1]["topics"]["session"]["names"]
    assert names["groups"]["TriLat"] == "Triceps brachii, lateral and medial heads" and list(names["groups"]) == groups
    assert names["coordinates"]["elv_angle_r"] == {"name": "Shoulder flexion", "unit": "deg", "torque_unit": "N·m"}
    # the session file's names (msk live's first load event) replace the pack's and stay through an operator's event
    state.on_message(
        PREFIX + "load",
        messages.LoadEvent(barbell_mass_kg=60, exercise="bench_press", set_number=1, names={"PMCla": "Upper chest"}),
    )
    seq, update = state.changes(0)
    assert update["topics"]["session"]["names"]["groups"]["PMCla"] == "Upper chest"
    state.on_message(PREFIX + "load", messages.LoadEvent(barbell_mass_kg=62.5, exercise="bench_press", set_number=2))
    names = state.changes(seq)[1]["topics"]["session"]["names"]
    assert names["groups"]["PMCla"] == "Upper chest" and names["groups"]["BRA"] == "Brachialis"
    # the body map's tooltips name the groups
    svg = bodymap.place_groups(load_pack("bench_press")).svg(names=load_pack("bench_press").display_names.groups)
    titles = [e.text for e in ET.fromstring(svg).iter("{http://www.w3.org/2000/svg}title")]
    assert "Pectoralis major, clavicular part (right)" in titles, titles
    assert "PMCla (pectoralis major, clavicular, right)" in ET.tostring(
        ET.fromstring(bodymap.place_groups(load_pack("bench_press")).svg()), encoding="unicode"
    )  # without names: model name and region


def test_node_statuses_are_nodes_with_their_dropped_inputs_not_devices():
    state = DashboardState("t")
    status = messages.DeviceStatus(
        device_id="estimator-bench_press",
        kind="node",
        connected=True,
        samples_received=900,
        samples_lost=4,
        dropped=[
            messages.InputDrop(key="msk/t/joints", reason="undecodable", count=3),
            messages.InputDrop(key="msk/t/load", reason="invalid", count=1),
        ],
    )
    state.on_message(PREFIX + "status/estimator-bench_press", status)
    update = state.changes(0)[1]
    assert "estimator-bench_press" not in update.get("devices", {})
    node = update["nodes"]["estimator-bench_press"]
    assert (node["running"], node["received"], node["dropped"]) == (True, 900, 4)
    assert node["drops"] == [["msk/t/joints", "undecodable", 3], ["msk/t/load", "invalid", 1]]
    assert update["nodes"]["dashboard"]["dropped"] == 0  # the bridge's own inputs


def test_bridge_drops_and_counts_unusable_inputs_over_zenoh_and_goes_on(zenoh_endpoint):
    """Garbage, an empty payload, another type and a 50 MB payload on the session's topics: each is dropped and
    counted per key and reason (shown as the dashboard's node row); the valid messages after them are shown."""
    from services.surfaces.dashboard.bridge import Bridge
    from services.transport.zenoh_session import ZenohOptions, open_session
    from tests.dashboard_helpers import BadInputs

    state = DashboardState("t")
    bridge = Bridge(ZenohOptions(listen=(zenoh_endpoint,)), state)
    bridge.start()
    try:
        with open_session(ZenohOptions(connect=(zenoh_endpoint,))) as zsession:
            inputs = BadInputs(zsession, "t")
            inputs.every_kind_then(
                {
                    "activations/so": activation_frame("so", [0.25, 0.5], t=7.0, exercise="deadlift"),
                    "load": messages.LoadEvent(barbell_mass_kg=80, exercise="deadlift", set_number=1),
                    "status/trigno": messages.DeviceStatus(device_id="trigno", kind="trigno", connected=True),
                }
            )
            deadline = time.monotonic() + 30
            expected_dropped = sum(inputs.expected.values())
            while time.monotonic() < deadline:
                update = state.changes(0)[1]
                if (
                    update["nodes"]["dashboard"]["dropped"] >= expected_dropped
                    and "load" in update["topics"]
                    and "activations/so" in update["topics"]
                    and "trigno" in update.get("devices", {})
                ):
                    break
                time.sleep(0.05)
            inputs.close()
    finally:
        bridge.stop()
    update = state.changes(0)[1]
    assert update["topics"]["activations/so"]["activations"] == [0.25, 0.5]
    session = update["topics"]["session"]
    expected = {
        "exercise": "deadlift",
        "load_kg": 80,
        "athlete": None,
        "names": None,
        "paused": None,
        "set_figures_method": "so",
    }
    assert session | {"names": None} == expected
    assert update["devices"]["trigno"]["connected"] is True
    node = update["nodes"]["dashboard"]
    assert {(key, reason): n for key, reason, n in node["drops"]} == inputs.expected
    assert node["dropped"] == 5 and state.received == 3


def _triceps_fatigue(**fields) -> messages.ElectrodeFatigue:
    """The fatigue index of the lateral triceps' electrode (sensor 3) with ``fields``."""
    return messages.ElectrodeFatigue(source="trigno", channel="sensor03.EMG", group="TriLat", **fields)


def test_the_bridge_forwards_each_electrodes_fatigue_with_no_value_as_null():
    state = DashboardState("s")
    nan = float("nan")
    fatigue = _triceps_fatigue(
        set_number=2,
        median_hz=[120.0, nan, 110.0],
        mean_hz=[130.0, nan, 121.0],
        rep_end_s=[3.0, 6.0, 9.0],
        median_slope_hz_per_rep=-5.0,
        median_slope_se_hz_per_rep=nan,
        median_slope_pct_per_rep=-4.17,
        median_change_pct=-8.33,
        mean_slope_pct_per_rep=-3.5,
        mean_change_pct=-6.9,
    )
    state.on_message(
        "msk/s/status/estimator", messages.DeviceStatus(device_id="estimator", kind="node", fatigue=[fatigue])
    )
    seq, update = state.changes(0)
    (row,) = update["topics"]["fatigue"]
    assert row["group"] == "TriLat" and row["set_number"] == 2 and row["median_hz"] == [120.0, None, 110.0]
    assert row["median_change_pct"] == -8.33 and row["median_slope_pct_per_rep"] == -4.17
    json.dumps(update, allow_nan=False)  # what the page is sent
    state.on_message("msk/s/status/estimator", messages.DeviceStatus(device_id="estimator", kind="node"))
    _, update = state.changes(seq)
    assert update["topics"]["fatigue"] == []  # an estimator restarted without EMG: no stale rows


@pytest.mark.parametrize(
    ("torque", "velocity", "said"),
    [(-300.0, -0.8, "lifting"), (-300.0, 0.8, "lowering"), (-300.0, 0.001, "turning"), (40.0, 0.8, "lifting")],
)
def test_lifting_or_lowering_comes_from_the_joint_power_not_the_half_of_the_rep(torque, velocity, said):
    """A deadlift from the floor lifts in the first half of its rep, a bench press lowers: the page said "lowering"
    for every first half. The sign of the inverse-dynamics torque times the joint velocity says which."""
    state = DashboardState("t")
    frame = activation_frame("so", [0.5, 0.2], t=1.0, phase=0.3, exercise="deadlift")
    frame.torques.add(coordinate="hip_flexion_r", inverse_dynamics_nm=torque, model_nm=torque, residual_nm=0.0)
    state.on_message(PREFIX + "activations/so", frame)
    moving = messages.JointAngles(
        coordinates=["hip_flexion_r"], q=[1.0], qd=[velocity], phase=0.3, device_time_ns=1_010_000_000
    )
    state.on_message(PREFIX + "joints", moving)
    assert state.changes(0)[1]["topics"]["reps"]["movement"] == said
    still = messages.JointAngles(coordinates=["hip_flexion_r"], q=[1.0], phase=0.4, device_time_ns=1_020_000_000)
    state.on_message(PREFIX + "joints", still)  # joints without velocities: no word rather than a stale one
    assert state.changes(0)[1]["topics"]["reps"]["movement"] is None


def test_the_set_buttons_refuse_when_the_session_sends_nothing(zenoh_endpoint):
    """After msk live stopped, the page's start button said "set 5 started" and nothing recorded it (msk set refuses
    when no msk live runs). Now the bridge refuses while the session is silent, and publishes once it speaks."""
    from services.surfaces.dashboard.bridge import SET_MARK_QUIET_S, Bridge
    from services.transport.zenoh_session import ZenohOptions

    state = DashboardState("t")
    bridge = Bridge(ZenohOptions(listen=(zenoh_endpoint,)), state)
    bridge.start()
    try:
        with pytest.raises(RuntimeError, match="session 't' sends nothing yet: is msk live running"):
            bridge.publish_set_mark("start")
        state.last_data_ns = messages.now_ns() - int((SET_MARK_QUIET_S + 5) * 1e9)  # the session ended 15 s ago
        with pytest.raises(RuntimeError, match="sends nothing for 15 s"):
            bridge.publish_set_mark("start")
        state.last_data_ns = messages.now_ns()  # it speaks
        assert bridge.publish_set_mark("start").set_mark == "start"
    finally:
        bridge.stop()


def test_a_set_mark_the_routers_access_control_would_drop_is_refused_saying_why(zenoh_endpoint):
    """A tablet's dashboard under --pki answered 200 to the set buttons while the router dropped every mark without a
    word (found by exploratory QA): the role is asked first, as the nodes ask for their subscriptions."""
    import dataclasses

    from services.surfaces.dashboard.bridge import Bridge
    from services.transport.zenoh_session import ZenohOptions

    @dataclasses.dataclass(frozen=True)
    class TabletOptions(ZenohOptions):  # the role a secured tablet config's certificate names
        @property
        def role(self) -> str | None:
            return "tablet"

    state = DashboardState("t")
    bridge = Bridge(TabletOptions(listen=(zenoh_endpoint,)), state)
    bridge.start()
    try:
        state.last_data_ns = messages.now_ns()
        with pytest.raises(
            RuntimeError, match="this dashboard's role cannot mark sets: role 'tablet' may publish only"
        ):
            bridge.publish_set_mark("start")
    finally:
        bridge.stop()


@pytest.mark.parametrize(
    ("median_hz", "slope", "se", "change", "tiring"),
    [
        ([120.0, 102.0], -18.0, float("nan"), -15.0, False),  # 2 reps: rep-to-rep scatter, not a trend
        ([120.0, 104.0, 118.0, 101.0], -4.0, 5.0, -12.0, False),  # 4 reps, the slope within its scatter
        ([120.0, 114.0, 108.0, 101.0], -6.3, 0.4, -14.0, True),  # a steady fall over 4 reps
        ([120.0, 118.0, 117.0], -1.5, 0.2, -2.5, False),  # falling, but by less than 10 %
    ],
)
def test_a_muscle_reads_as_tiring_only_on_a_trend(median_hz, slope, se, change, tiring):
    state = DashboardState("s")
    fatigue = _triceps_fatigue(
        set_number=1,
        median_hz=median_hz,
        median_slope_hz_per_rep=slope,
        median_slope_se_hz_per_rep=se,
        median_change_pct=change,
    )
    state.on_message(
        "msk/s/status/estimator", messages.DeviceStatus(device_id="estimator", kind="node", fatigue=[fatigue])
    )
    (row,) = state.changes(0)[1]["topics"]["fatigue"]
    assert row["tiring"] is tiring


def test_the_dashboards_set_figures_are_of_the_reports_method_not_of_the_first_to_arrive():
    from tests.test_view import _a_set

    state = DashboardState("s")
    _a_set(state.on_message, "msk/s/activations")
    topics = state.changes(0)[1]["topics"]
    (only,) = topics["sets"]
    assert (only["reps"], only["peak"], only["mean"]) == (1, [0.6], [0.6])
    assert topics["session"]["set_figures_method"] == "assisted"  # the page says whose figures they are


def test_a_set_mark_from_another_sites_page_is_refused(zenoh_endpoint):
    """Any web page open in the coach's browser could POST /set/start to a dashboard on the gym network (found by
    exploratory QA): a request that carries another origin is refused; the dashboard's own page's goes on to the
    session (none runs here, which it says)."""
    import urllib.error
    import urllib.request

    from services.surfaces.dashboard.app import DashboardConfig, DashboardServer
    from services.transport.zenoh_session import ZenohOptions

    server = DashboardServer(ZenohOptions(listen=(zenoh_endpoint,)), DashboardConfig(session="s"), port=free_tcp_port())
    server.start()
    try:
        own = server.url.rstrip("/")

        def post(origin: str) -> tuple[int, dict]:
            request = urllib.request.Request(f"{own}/set/start", method="POST", headers={"Origin": origin})
            try:
                with urllib.request.urlopen(request, timeout=10) as answer:
                    return answer.status, json.loads(answer.read())
            except urllib.error.HTTPError as error:
                return error.code, json.loads(error.read())

        code, answer = post("http://evil.example")
        assert code == 403 and "not http://evil.example" in answer["error"], answer
        code, answer = post(own)  # past the gate: refused only because no msk live is running
        assert code == 503 and "sends nothing yet: is msk live running?" in answer["error"], answer
    finally:
        server.stop()


def test_a_session_the_dashboard_cannot_open_is_said_before_the_server_starts():
    """Under --pki with the tablet's config and no router where it says: uvicorn printed 'Application startup
    failed' and a traceback (found by exploratory QA). The bridge opens its session before the server starts, so the
    command says it in one line."""
    from msk_core.errors import MskError
    from services.surfaces.dashboard.app import DashboardConfig, DashboardServer
    from services.transport.zenoh_session import ZenohOptions

    nowhere = ZenohOptions(mode="client", connect=(f"tcp/127.0.0.1:{free_tcp_port()}",))
    server = DashboardServer(nowhere, DashboardConfig(session="s"), port=free_tcp_port())
    with pytest.raises(MskError, match="cannot open the Zenoh session"):
        server.run()
    assert not server.server.started
