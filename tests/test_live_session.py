"""``msk live``'s session file (pack, channel labels, athlete) and its exit code when a node fails: a session whose
Trigno driver cannot reach its device stops and exits 3 naming the node, its exit code and the end of its log; a
clean stop (SIGTERM) of a ``--sim`` session exits 0."""

from __future__ import annotations

import json
import os
import signal
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from msk_core.errors import ConfigError
from msk_core.model.pack import available_packs
from services.commands.live import EXIT_NODE_FAILED, node_failures
from services.sessions.live_session import TRIGNO_CHANNEL_FORM, is_trigno_channel, load_session_file
from tests.live_helpers import REPO, live_environment, run_msk, start_msk, write_subject

GOOD = """\
[session]
name = "gym"
pack = "bench_press"
subject = "subject.json"
load_kg = 60

[trigno]
host = "192.168.1.20"

[electrodes]
"sensor01.EMG" = "PMCla"
"""


def _write(tmp_path: Path, text: str) -> Path:
    write_subject(tmp_path / "subject.json")
    path = tmp_path / "session.toml"
    path.write_text(text)
    return path


def _refusal(path: Path) -> str:
    with pytest.raises(ConfigError) as error:
        load_session_file(path)
    return str(error.value)


# ------------------------------------------------------------------------------------------------ session.pack


def test_an_unknown_pack_is_refused_naming_file_field_value_and_the_shipped_packs(tmp_path):
    path = _write(tmp_path, GOOD.replace('pack = "bench_press"', 'pack = "bench_pres"'))
    message = _refusal(path)
    assert str(path) in message and "field 'session.pack'" in message and "'bench_pres'" in message, message
    assert all(pack in message for pack in available_packs()) and "bench_press" in available_packs(), message


def test_a_pack_file_is_resolved_against_the_session_file_and_a_missing_one_refused(tmp_path, monkeypatch):
    from msk_core.model import load_pack

    shipped = load_pack("bench_press").path
    (tmp_path / "packs").mkdir()
    (tmp_path / "packs" / "mine.json").write_text(Path(shipped).read_text())
    path = _write(tmp_path, GOOD.replace('pack = "bench_press"', 'pack = "packs/mine.json"'))
    monkeypatch.chdir(REPO)  # not the session file's folder: the path is relative to the file
    session = load_session_file(path)
    assert session.pack == str(tmp_path / "packs" / "mine.json")
    assert load_pack(session.pack).name == "bench_press"  # what plan_for and the nodes load
    path.write_text(GOOD.replace('pack = "bench_press"', 'pack = "packs/theirs.json"'))
    message = _refusal(path)
    assert "field 'session.pack'" in message and "pack file not found" in message
    assert str(tmp_path / "packs" / "theirs.json") in message, message


def test_the_cli_refuses_an_unknown_pack_before_starting_anything(tmp_path):
    path = _write(tmp_path, GOOD.replace('pack = "bench_press"', 'pack = "squat"'))
    result = run_msk("live", str(path), "--no-view")
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert str(path) in result.stderr and "session.pack" in result.stderr and "deadlift" in result.stderr, result.stderr
    assert not (tmp_path / "out").exists() and "running" not in result.stdout


# ------------------------------------------------------------------------------------------------ electrodes.<label>


@pytest.mark.parametrize(
    "label",
    [
        "sensor1.EMG",
        "sensor17.EMG",
        "sensor00.EMG",
        "sensor01.emg",
        "Sensor01.EMG",
        "sensor01.EMG0",
        "sensor01.EMG17",
        "sensor01.ACC",
        "sensor01.AUX",
        "sensor01",
        "PMCla",
        "sensor01.EMG ",
    ],
)
def test_an_electrode_key_the_trigno_does_not_publish_is_refused_with_the_valid_form(tmp_path, label):
    path = _write(tmp_path, GOOD + f'"{label}" = "DelAnt"\n')
    message = _refusal(path)
    assert str(path) in message and f"field 'electrodes.{label}'" in message and repr(label) in message, message
    assert TRIGNO_CHANNEL_FORM in message and "sensorNN.EMG" in message


def test_the_accelerometers_port_follows_the_session_file(tmp_path):
    """The TCU's AUX port beside its EMG port; a forwarded or simulated base's, as the file says; off with 0. A
    non-TCU EMG port without one is refused (it read the fixed 50044, another base's on a shared machine)."""
    from services.sessions.live import _device_ports

    def aux(trigno: str) -> int | None:
        session = load_session_file(_write(tmp_path, GOOD.replace('host = "192.168.1.20"\n', trigno)))
        return _device_ports(session).trigno_aux_port

    assert aux('host = "192.168.1.20"\n') == 50044
    assert aux('host = "192.168.1.20"\nemg_port = 50041\n') == 50042
    assert aux('host = "127.0.0.2:51740"\nemg_port = 51743\naux_port = 51744\n') == 51744
    assert aux('host = "192.168.1.20"\naux_port = 0\n') is None
    with pytest.raises(ConfigError) as error:
        aux('host = "127.0.0.2:51740"\nemg_port = 51743\n')
    assert error.value.field == "trigno.aux_port" and "51743 is not the TCU's" in str(error.value)


def test_the_accelerometers_layout_is_a_session_key_and_a_wrong_one_is_refused(tmp_path):
    """A base whose ACC port was moved: ``trigno.aux_layout`` says what the port carries (``msk drivers``'
    ``--trigno-aux-layout``), as the file states it; a value that is not a layout is refused naming it."""
    from drivers.trigno.protocol import AuxLayout

    moved = 'host = "127.0.0.2:51740"\nemg_port = 51741\naux_port = 51742\n'
    session = load_session_file(
        _write(tmp_path, GOOD.replace('host = "192.168.1.20"\n', moved + 'aux_layout = "legacy_acc"\n'))
    )
    assert session.trigno_aux_layout is AuxLayout.LEGACY_ACC
    assert load_session_file(_write(tmp_path, GOOD)).trigno_aux_layout is None
    message = _refusal(_write(tmp_path, GOOD.replace('host = "192.168.1.20"\n', moved + 'aux_layout = "acc"\n')))
    assert "field 'trigno.aux_layout'" in message and "'acc'" in message and "avanti, legacy_acc" in message, message


def _published_labels(client) -> list[str]:
    """The channel labels the Trigno driver node puts in EmgChunk.channel_labels for this client."""
    from drivers.trigno.client import EmgBlock
    from services.nodes.driver_nodes import emg_chunk, emg_columns

    block = EmgBlock(np.zeros((2, 16), dtype=np.float32), 0, 2000.0, 0)
    return list(emg_chunk(block, source_id="trigno", columns=emg_columns(client)).channel_labels)


def test_every_label_the_trigno_driver_publishes_is_accepted(tmp_path):
    """Labels from the driver itself: a real handshake with the simulator (16 paired sensors), multi-channel sensors
    (sensorNN.EMGk) and the fallback when the server names no sensor."""
    from drivers.trigno.client import SensorInfo, TrignoClient, TrignoConfig
    from drivers.trigno.simulator import SimulatorConfig, TrignoSimulator
    from drivers.trigno.source import EmgSource

    source = EmgSource(
        np.zeros((400, 16), dtype=np.float32), 2000.0, tuple(f"m{k}" for k in range(16)), (True,) * 16, "test"
    )
    simulator = TrignoSimulator(
        source, SimulatorConfig(command_port=0, emg_port=0, legacy_emg_port=None, aux_port=None)
    ).start()
    try:
        client = TrignoClient(
            TrignoConfig(
                host="127.0.0.1",
                command_port=simulator.ports["command"],
                emg_port=simulator.ports["emg"],
                emg_port_fallback=0,
            )
        )
        with client:
            from_simulator = _published_labels(client)
    finally:
        simulator.close()
    assert len(from_simulator) == 16 and from_simulator[0] == "sensor01.EMG", from_simulator
    multi = TrignoClient(TrignoConfig())
    multi.sensors = (
        SensorInfo(3, True, start_index=2, active=True, emg_channels=4),
        SensorInfo(16, True, start_index=15, active=True),
    )
    from_multi = _published_labels(multi)
    assert from_multi == ["sensor03.EMG1", "sensor03.EMG2", "sensor03.EMG3", "sensor03.EMG4", "sensor16.EMG"]
    fallback = _published_labels(TrignoClient(TrignoConfig()))
    labels = sorted(set(from_simulator + from_multi + fallback))
    assert all(is_trigno_channel(label) for label in labels), [x for x in labels if not is_trigno_channel(x)]
    path = _write(tmp_path, GOOD.replace('"sensor01.EMG" = "PMCla"\n', "".join(f'"{x}" = "PMCla"\n' for x in labels)))
    assert sorted(load_session_file(path).electrodes) == labels


# ------------------------------------------------------------------------------------------------ session.athlete


def test_the_athlete_is_parsed_and_checked(tmp_path):
    path = _write(tmp_path, GOOD)
    assert load_session_file(path).athlete == ""
    path.write_text(GOOD.replace('name = "gym"', 'name = "gym"\nathlete = "Anna K."'))
    assert load_session_file(path).athlete == "Anna K."
    for bad in ("42", '"Anna\\nK."', '["Anna"]'):
        path.write_text(GOOD.replace('name = "gym"', f'name = "gym"\nathlete = {bad}'))
        message = _refusal(path)
        assert str(path) in message and "field 'session.athlete'" in message, message


# ------------------------------------------------------------------------------------------------ [names]


def test_the_session_files_names_override_the_packs_and_reach_the_session_facts(tmp_path):
    from msk_core.model.pack import pack_display_names
    from services.sessions.live import SessionFacts, plan_for
    from services.sessions.live_session import session_names

    names = '\n[names]\nPMCla = "Upper chest"\nelbow_flex_r = "Elbow bend"\n'
    path = _write(tmp_path, GOOD.replace("load_kg = 60", 'load_kg = 60\nout = "out"') + names)
    plan, _ = plan_for(load_session_file(path), sim=False, log=lambda *_: None)
    assert plan.names == {"PMCla": "Upper chest", "elbow_flex_r": "Elbow bend"}
    event = SessionFacts(exercise=plan.exercise, load_kg=60, names=plan.names).message()
    assert dict(event.names) == plan.names  # on the wire: every surface shows them
    bench = pack_display_names("bench_press")
    for table, field, message in (
        ('PMCl = "Upper chest"', "names.PMCl", "closest: PMCla"),
        ("PMCla = 3", "names.PMCla", "must be a display name"),
        ('PMCla = "Upper\\nchest"', "names.PMCla", "one line of printable text"),
    ):
        path.write_text(GOOD + "\n[names]\n" + table + "\n")
        with pytest.raises(ConfigError) as error:
            session_names(load_session_file(path), bench)
        assert str(path) in str(error.value) and error.value.field == field and message in str(error.value)
    path.write_text('names = "Upper chest"\n' + GOOD)
    assert "field 'names'" in _refusal(path)  # a table, not a value


# ------------------------------------------------------------------------------------------------ exit code


def _summary(stopped_by: str, **codes) -> dict:
    """The two keys run_graph puts in summary.json, as a real run writes them."""
    base = {"drivers-xsens": 0, "drivers-trigno": 0, "kinematics": 0, "estimator": 0, "recorder": 0}
    return {"duration_s": 5.0, "stopped_by": stopped_by, "exit_codes": {**base, **codes}}


@pytest.mark.parametrize("stopped_by", ["duration", "SIGINT", "SIGTERM"])
def test_a_clean_stop_has_no_failed_node(tmp_path, stopped_by):
    assert node_failures(_summary(stopped_by), tmp_path) == []


def test_failed_nodes_are_named_with_exit_code_and_log_tail(tmp_path):
    (tmp_path / "drivers-trigno.log").write_text("".join(f"line {k}\n" for k in range(30)) + "\n\nthe last words\n")
    failed = node_failures(_summary("node failed: ['drivers-trigno: exit 2']", **{"drivers-trigno": 2}), tmp_path)
    assert [(f.node, f.exit_code, f.during_session) for f in failed] == [("drivers-trigno", 2, True)]
    text = failed[0].text()
    assert "node drivers-trigno failed" in text and "exited with code 2 while the session ran" in text, text
    assert str(tmp_path / "drivers-trigno.log") in text and "the last words" in text and "line 19" in text
    assert "line 18" not in text, text  # the last 12 non-blank lines only

    # ended by itself with 0 while the session ran: still what stopped the session
    failed = node_failures(_summary("node failed: ['drivers-xsens: exit 0']"), tmp_path)
    assert [(f.node, f.exit_code) for f in failed] == [("drivers-xsens", 0)]
    assert "exited with code 0 while the session ran" in failed[0].text()
    assert f"no log at {tmp_path / 'drivers-xsens.log'}" in failed[0].text()

    # a clean stop, but a node failed on its way out, one had to be killed, one died of a signal
    failed = node_failures(_summary("SIGINT", estimator=1, recorder=None, kinematics=-9), tmp_path)
    texts = {f.node: f.text() for f in failed}
    assert set(texts) == {"estimator", "recorder", "kinematics"}
    assert "exited with code 1 when stopped" in texts["estimator"]
    assert "did not stop when asked (SIGINT) and was killed" in texts["recorder"]
    assert "killed by signal 9 (SIGKILL)" in texts["kinematics"]

    # after a node failed, the others stopped by the signal or killed when they did not answer it only followed it
    failed = node_failures(
        _summary("node failed: ['recorder: exit 1']", recorder=1, estimator=-2, kinematics=None, drivers=3), tmp_path
    )
    assert [(f.node, f.during_session) for f in failed] == [("recorder", True), ("drivers", False)]

    # a thread node of msk live itself (no process, no exit code)
    failed = node_failures(_summary("node failed: [\"monitor: RuntimeError('zenoh closed')\"]"), tmp_path)
    assert [f.node for f in failed] == ["monitor"] and "zenoh closed" in failed[0].text()


# ------------------------------------------------------------------------------------------------ real runs


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory) -> tuple[Path, dict]:
    """A calibrated bench-press subject (as ``msk live --sim`` makes it) and an environment whose cache holds it: the
    user's cache, as the other live-session tests use it (calibrated there if it is not yet; test_live calibrates one
    in a fresh cache)."""
    from services.sessions import live

    env = live_environment(tmp_path_factory.mktemp("live_session"))
    return live.sim_subject("bench_press", lambda *_: None), env


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]  # nobody listens on it once closed: connect is refused at once


def test_msk_live_exits_3_naming_the_node_that_failed_and_why(tmp_path, calibrated):
    subject, env = calibrated
    (tmp_path / "subject.json").write_text(subject.read_text())
    port = _closed_port()
    path = tmp_path / "session.toml"
    path.write_text(
        GOOD.replace('host = "192.168.1.20"', f'host = "127.0.0.1:{port}"').replace(
            'name = "gym"', 'name = "gym-fail"\nout = "out"\nmethods = ["proposed"]'
        )
    )
    started = time.monotonic()
    result = run_msk("live", str(path), "--no-view", "--duration", "100", env=env, timeout=150)
    elapsed = time.monotonic() - started
    out = tmp_path / "out"
    assert result.returncode == EXIT_NODE_FAILED, result.stdout + result.stderr
    assert elapsed < 90, elapsed  # stopped when the driver failed, not at --duration
    summary = json.loads((out / "summary.json").read_text())
    assert summary["exit_codes"]["drivers-trigno"] == 2, summary
    # the nodes msk live stopped itself (SIGINT) exit 0: they are not reported
    assert {n: c for n, c in summary["exit_codes"].items() if n != "drivers-trigno"} == {
        "kinematics": 0,
        "estimator": 0,
        "recorder": 0,
    }, summary
    errors = [line for line in result.stderr.splitlines() if line.startswith("msk live: error:")]
    assert len(errors) == 1 and "node drivers-trigno failed" in errors[0], result.stderr
    assert "exited with code 2" in errors[0] and str(out / "logs" / "drivers-trigno.log") in errors[0], result.stderr
    assert "cannot reach the Trigno server" in result.stderr and str(port) in result.stderr, result.stderr
    assert "stopped by node failed" in result.stdout, result.stdout


def test_msk_live_exits_0_after_a_clean_stop_by_sigterm(tmp_path, calibrated):
    _, env = calibrated
    out = tmp_path / "live"
    process = start_msk("live", "--sim", "--no-view", "--duration", "100", "--out", str(out), env=env)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(process.stdout), daemon=True)  # every line as it comes
    reader.start()
    try:
        deadline = time.monotonic() + 120
        while not any(
            "running" in line and "recording to" in line for line in list(lines)
        ):  # the stop handlers are set
            assert time.monotonic() < deadline and process.poll() is None, "msk live --sim did not start:\n" + "".join(
                lines
            )
            time.sleep(0.1)
        time.sleep(2.0)
        process.send_signal(signal.SIGTERM)  # to msk live alone, as a service manager does
        process.wait(60)
        reader.join(10)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(10)
    output = "".join(lines)
    assert process.returncode == 0, output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stopped_by"] == "SIGTERM" and summary["duration_s"] < 60, output
    assert node_failures(summary, out / "logs") == [] and set(summary["exit_codes"].values()) == {0}, summary
    assert "stopped by SIGTERM" in output and "msk live: error" not in output, output


def test_an_endpoint_msk_live_cannot_listen_on_fails_at_once_naming_it(tmp_path, calibrated):
    """--listen on a port another program holds: the recorder, which listens for the session, cannot open it. msk
    live said "running", then hung for minutes while the other nodes waited on that endpoint (each given 20 s to
    stop, one after the other). Then it exited 3 once the recorder failed, with simulators and nodes started and a
    recorder's traceback in their logs; now the port is checked before anything starts."""
    _, env = calibrated
    with socket.socket() as holder:  # another program on the port: it accepts, but speaks no Zenoh
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        started = time.monotonic()
        result = run_msk(
            "live", "--sim", "--no-view", "--listen", f"tcp/127.0.0.1:{port}", "--duration", "60",
            "--out", str(tmp_path / "live"), env=env, timeout=150,
        )  # fmt: skip
        elapsed = time.monotonic() - started
    assert result.returncode == 2, result.stdout + result.stderr
    assert elapsed < 20, elapsed  # the command's start-up only: nothing else was started
    assert "running" not in result.stdout and not (tmp_path / "live" / "logs").exists(), result.stdout
    errors = [line for line in result.stderr.splitlines() if line.startswith("msk live: error:")]
    assert len(errors) == 1 and "field '--listen': is in use by another program" in errors[0], result.stderr
    assert f"tcp/127.0.0.1:{port}" in errors[0], result.stderr


def test_the_summary_lists_the_sets_and_how_each_ended():
    from services.sessions.live import set_summary

    assert set_summary({"number": 1, "reps": 9, "time_under_tension_s": 25.06, "ended_by": "rest"}) == (
        "1: 9 reps, 25.1 s under tension, ended by rest"
    )
    assert set_summary({"number": 2, "reps": 1, "time_under_tension_s": 2.0, "ended_by": "end of data"}) == (
        "2: 1 rep, 2.0 s under tension, ended with the session"
    )


def test_a_refusal_names_the_line_of_the_key_in_the_session_file(tmp_path):
    """A coach's session file of 40 lines: the refusal points at the line, for the parse and for the checks against
    the pack and the profile made after it (quoted channel keys too)."""
    from services.sessions.live_session import check_against_pack

    message = _refusal(_write(tmp_path, GOOD.replace("load_kg = 60", "load_kg = -5")))
    assert "session.toml, line 5, field 'session.load_kg'" in message, message
    message = _refusal(_write(tmp_path, GOOD.replace("load_kg = 60", "load_kg = 60000")))
    assert "field 'session.load_kg': 60000 kg is more than any lift's load" in message, message
    session = load_session_file(_write(tmp_path, GOOD.replace('"sensor01.EMG" = "PMCla"', '"sensor01.EMG" = "Pec"')))
    with pytest.raises(ConfigError) as error:
        check_against_pack(session, ["pec_clav"], [], {"PMCla": {}})
    assert error.value.line == 11 and "line 11, field 'electrodes.sensor01.EMG'" in str(error.value), error.value
    # a typo gets the closest name (found by a new user: "PMCal" for "PMCla" was said without one)
    session = load_session_file(_write(tmp_path, GOOD.replace('"sensor01.EMG" = "PMCla"', '"sensor01.EMG" = "PMCal"')))
    with pytest.raises(ConfigError, match="did you mean 'PMCla'"):
        check_against_pack(session, ["pec_clav"], [], {"PMCla": {}})


def test_a_secured_session_refuses_a_swapped_role_certificate_and_a_missing_folder_before_it_starts(tmp_path):
    """The tablet's certificate copied over the estimator's: the router refused the estimator's subscriptions and
    msk live waited 88 s for it, then hung (found by QA). Each role's certificate is checked to be that role's. A
    folder without a router certificate is refused before the calibration and the simulators start."""
    import shutil

    from services.sessions.live import check_roles
    from services.transport import security
    from tests.live_helpers import run_msk

    pki = security.write_pki(tmp_path / "pki", router_hosts=("localhost",)).directory
    configs = security.write_configs(
        tmp_path / "zenoh", pki, router_listen=("tls/127.0.0.1:1",), client_connect=("tls/localhost:1",)
    )
    check_roles(pki, configs)  # as msk certs made them
    for suffix in (".pem", ".key"):
        shutil.copy(pki / f"estimator{suffix}", tmp_path / f"estimator{suffix}")
        shutil.copy(pki / f"tablet{suffix}", pki / f"estimator{suffix}")
    with pytest.raises(ConfigError) as swapped:
        check_roles(pki, configs)
    assert swapped.value.path == pki / "estimator.pem" and "the tablet's (CN msk-tablet)" in str(swapped.value)
    for suffix in (".pem", ".key"):
        shutil.copy(tmp_path / f"estimator{suffix}", pki / f"estimator{suffix}")
    (pki / "kinematics.key").write_bytes((pki / "recorder.key").read_bytes())  # another role's key: said here
    with pytest.raises(ConfigError) as mismatched:
        check_roles(pki, configs)
    assert mismatched.value.path == pki / "kinematics.key", mismatched.value
    env = {**os.environ, "MSK_SESSIONS_DIR": str(tmp_path / "registry"), "XDG_CACHE_HOME": str(tmp_path / "cache")}
    done = run_msk("live", "--sim", "--pki", str(tmp_path / "nosuchdir"), "--out", str(tmp_path / "out"), env=env)
    said = done.stdout + done.stderr
    assert done.returncode == 2 and "no router certificate" in said and "nosuchdir" in said, said
    assert "calibrat" not in said and "simulators:" not in said, said
