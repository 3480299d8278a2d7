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
from services import messages
from services.dashboard import bodymap
from services.dashboard.bridge import HAS_MEASURED_ENVELOPE, DashboardState, RepCounter
from tests.conftest import free_tcp_port

PREFIX = "msk/t/"


def activation_payload(method: str, a: list[float], *, t: float, phase: float | None = None, envelope=None) -> bytes:
    frame = messages.ActivationFrame(time_s=t, method=method, groups=["A", "B"], activations=a, activation_std=[0.1, float("nan")],
                                     publish_ns=2_000_000, input_arrival_ns=1_000_000)
    frame.torques.add(coordinate="elbow", inverse_dynamics_nm=3.0, model_nm=2.5, residual_nm=0.5)
    if phase is not None:
        frame.phase = phase
    if envelope is not None:
        frame.measured_envelope.extend(envelope)
    return messages.encode(frame)


def test_state_keeps_only_the_newest_frame_per_topic():
    state = DashboardState("t")
    seq0, first = state.changes(0)
    assert first["topics"] == {} and first["data_age_s"] is None
    for i in range(50):  # a burst the page did not take: only the last one is left
        state.on_sample(PREFIX + "activations/so", "msk.ActivationFrame", activation_payload("so", [i / 50, 0.5], t=i))
    seq, update = state.changes(seq0)
    # no joint angles with a phase: the reps follow the first method's frames (phase unset here: unknown)
    assert sorted(update["topics"]) == ["activations/so", "reps"] and update["topics"]["reps"]["phase"] is None
    frame = update["topics"]["activations/so"]
    assert frame["time_s"] == 49 and frame["activations"] == [0.98, 0.5]
    assert frame["std"] == [0.1, None]  # NaN -> null: the page gets valid JSON
    assert frame["estimator_latency_ms"] == 1.0 and frame["torques"][0]["model_nm"] == 2.5
    assert json.dumps(update, allow_nan=False)
    assert state.changes(seq)[1]["topics"] == {}  # nothing new since
    state.on_sample(PREFIX + "activations/hybrid", "msk.ActivationFrame", activation_payload("hybrid", [0.1, 0.2], t=50))
    assert list(state.changes(seq)[1]["topics"]) == ["activations/hybrid"]
    state.on_sample("msk/other/activations/so", "msk.ActivationFrame", activation_payload("so", [1, 1], t=1))  # other session
    state.on_sample(PREFIX + "activations/so", "msk.ActivationFrame", b"\xff\xff not protobuf")
    assert state.decode_errors == 1 and state.received == 51


def test_measured_envelope_is_forwarded_when_the_schema_has_it():
    state = DashboardState("t")
    if HAS_MEASURED_ENVELOPE:
        payload = activation_payload("so", [0.2, 0.3], t=1, envelope=[0.25, float("nan")])
        expected = [0.25, None]  # NaN where no electrode
    else:
        payload, expected = activation_payload("so", [0.2, 0.3], t=1), []
    state.on_sample(PREFIX + "activations/so", "msk.ActivationFrame", payload)
    assert state.changes(0)[1]["topics"]["activations/so"]["envelope"] == expected


def test_rep_counter_counts_rest_transitions_and_wraps_and_restarts_per_set():
    reps = RepCounter()
    reps.new_set()
    for p in [-1, 0.0, 0.3, 0.6, 0.9, -1, -1, 0.1, 0.5, 0.95, 0.05, 0.5, 0.9, -1]:
        reps.update(p)
    assert (reps.in_set, reps.total, reps.sets) == (3, 3, 1)
    reps.update(None)  # unknown phase: no rep invented
    reps.new_set()
    reps.update(0.2)
    reps.update(-1)
    assert (reps.in_set, reps.total, reps.sets) == (1, 4, 2)


def test_reps_from_joints_phase_and_device_health_from_samples():
    state = DashboardState("t")
    state.on_sample(PREFIX + "load", "msk.LoadEvent", messages.encode(messages.LoadEvent(barbell_mass_kg=60, exercise="deadlift")))
    for p in [-1.0, 0.2, 0.7, -1.0]:
        state.on_sample(PREFIX + "joints", "msk.JointAngles", messages.encode(messages.JointAngles(coordinates=["x"], q=[0.0], phase=p)))
    now = time.time_ns()
    for first in (0, 100, 300):  # samples 200..299 never arrived
        chunk = messages.EmgChunk(source_id="trigno-1", first_sample_index=first, n_samples=100, n_channels=1,
                                  samples=[0.0] * 100, host_time_ns=now)
        state.on_sample(PREFIX + "emg/trigno-1", "msk.EmgChunk", messages.encode(chunk), arrival_ns=now + 3_000_000)
    state.on_sample(PREFIX + "status/xsens-1", "msk.DeviceStatus",
                    messages.encode(messages.DeviceStatus(device_id="xsens-1", kind="xsens", connected=False, samples_lost=7)))
    update = state.changes(0, now_ns=now + 4_000_000)[1]
    assert update["topics"]["reps"] == {"in_set": 1, "total": 1, "set": 1, "phase": -1.0}
    assert update["topics"]["load"] == {"mass_kg": 60, "exercise": "deadlift"}
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
    assert bench["DelAnt"].region == "deltoid_anterior" and bench["DelAnt"].side == "r"  # DELT1 has no suffix: the pack's side
    assert bench["TriLong"].region == "triceps_long" and bodymap.REGIONS["triceps_long"].view == "back"
    assert bodymap.activation_colour(0.0) == "#fff5c8" and bodymap.activation_colour(1.0) == "#8c0a14"
    assert bodymap.activation_colour(math.nan) == bodymap.activation_colour(None) == "#b8bec7"


def test_msk_dashboard_command_serves_the_page_and_stops_on_sigint(zenoh_endpoint):
    port = free_tcp_port()
    process = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "dashboard", "--session", "gym", "--port", str(port), "--listen", zenoh_endpoint],
        stderr=subprocess.PIPE, text=True,
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
        page = urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=5).read().decode()
        assert "chart-4.6.1.umd.min.js" in page and 'id="nodata"' in page
        request = urllib.request.Request(f"http://127.0.0.1:{port}/static/vendor/chart-4.6.1.umd.min.js", headers={"Accept-Encoding": "gzip"})
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
        result = subprocess.run([sys.executable, "-m", "services.cli", "dashboard", "--port", str(port)],
                                capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and f"cannot listen on 127.0.0.1:{port}" in result.stderr


def test_bad_session_name_is_refused():
    from msk_core.errors import ConfigError
    from services.dashboard.app import DashboardConfig, DashboardServer
    from services.zenoh_session import ZenohOptions

    with pytest.raises(ConfigError, match="--session"):
        DashboardServer(ZenohOptions(), DashboardConfig(session="a/b"), port=free_tcp_port())


def test_devices_without_estimates_are_not_live_data():
    from services.dashboard.bridge import _message_class

    state = DashboardState("t")
    chunk = messages.EmgChunk(source_id="trigno-1", first_sample_index=0, n_samples=1, n_channels=1, samples=[0.0])
    now = time.time_ns()
    state.on_sample(PREFIX + "emg/trigno-1", "msk.EmgChunk", messages.encode(chunk), arrival_ns=now)
    update = state.changes(0, now_ns=now + 500_000_000)[1]
    assert update["data_age_s"] == pytest.approx(0.5) and update["activation_age_s"] is None  # the page says "no data"
    state.on_sample(PREFIX + "activations/so", "msk.ActivationFrame", activation_payload("so", [0.1, 0.2], t=1), arrival_ns=now)
    assert state.changes(0, now_ns=now + 10**9)[1]["activation_age_s"] == pytest.approx(1.0)
    # message types are looked up in the schema itself, so types added to msk.proto later are decoded too
    assert _message_class("msk.DeviceStatus") is messages.DeviceStatus
    assert _message_class("msk.NoSuchType") is None and _message_class("other.EmgChunk") is None and _message_class(None) is None
