"""``msk live``: the session file's errors, and ``msk live --sim`` end to end as a user runs it (a subprocess, real
simulators over TCP and ptys, real driver/kinematics/estimator/recorder processes over Zenoh), stopped by SIGINT."""

from __future__ import annotations

import json
import os
import re
import signal
import time
from collections import Counter
from pathlib import Path

import pytest

from msk_core.errors import ConfigError
from services.sessions.live_session import check_against_pack, load_session_file, parse_session
from services.transport import messages
from tests.live_helpers import REPO, run_msk, start_msk, wait_running, write_subject

GOOD = {
    "session": {
        "name": "gym",
        "pack": "bench_press",
        "load_kg": 60,
        "subject": "subject.json",
        "methods": ["proposed", "so"],
    },
    "trigno": {"host": "192.168.1.20"},
    "xsens": {"ports": ["usb"], "rate_hz": 100},
    "trackers": {"00B4EB80": "upper_arm_r", "00B497B2": "forearm_r"},
    "electrodes": {"sensor01.EMG": "PMCla"},
}


def _doc(**changes) -> dict:
    doc = json.loads(json.dumps(GOOD))
    for dotted, value in changes.items():
        section, _, key = dotted.partition("__")
        if key:
            if value is None:
                doc[section].pop(key)
            else:
                doc.setdefault(section, {})[key] = value
        elif value is None:
            doc.pop(section)
        else:
            doc[section] = value
    return doc


def _toml(doc: dict) -> str:
    def value(v):
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return str(v)

    return (
        "\n".join(f"[{s}]\n" + "\n".join(f"{json.dumps(k)} = {value(v)}" for k, v in t.items()) for s, t in doc.items())
        + "\n"
    )


def test_a_good_session_file_parses_with_paths_resolved(tmp_path):
    (tmp_path / "subject.json").write_text("{}")
    path = tmp_path / "session.toml"
    path.write_text(_toml(GOOD))
    session = load_session_file(path)
    assert (session.name, session.pack, session.load_kg, session.methods) == (
        "gym",
        "bench_press",
        60.0,
        ("proposed", "so"),
    )
    assert session.subject == tmp_path / "subject.json" and session.out == Path("out/live")  # default: cwd-relative
    assert session.trigno_host == "192.168.1.20" and session.xsens_ports == ("usb",) and session.imu_rate_hz == 100
    assert session.trackers == {"00B4EB80": "upper_arm_r", "00B497B2": "forearm_r"}


@pytest.mark.parametrize(
    "changes, key, value",
    [
        ({"session__pack": None}, "session.pack", None),
        ({"session__load_kg": None}, "session.load_kg", None),
        ({"session__load_kg": -5}, "session.load_kg", "-5"),
        ({"session__methods": ["proposed", "magic"]}, "session.methods", "magic"),
        ({"session__name": "a b"}, "session.name", "a b"),
        ({"session__subject": "missing.json"}, "session.subject", "missing.json"),
        ({"session__colour": "red"}, "session.colour", "colour"),
        ({"trigno__host": None}, "trigno.host", None),
        ({"trigno__emg_port": 70000}, "trigno.emg_port", "70000"),
        ({"xsens__ports": []}, "xsens.ports", "[]"),
        ({"xsens__rate_hz": 5000}, "xsens.rate_hz", "5000"),
        ({"trackers": {"upperarm": "upper_arm_r"}}, "trackers.upperarm", "upperarm"),
        ({"trackers": None}, "trackers", None),
        ({"electrodes": None}, "electrodes", None),
        ({"trigno": None, "xsens": None}, "trigno", None),
        ({"camera": {"fps": 30}}, "camera", "camera"),
    ],
)
def test_a_bad_session_file_names_file_key_and_value(tmp_path, changes, key, value):
    (tmp_path / "subject.json").write_text("{}")
    path = tmp_path / "session.toml"
    path.write_text(_toml(_doc(**changes)))
    with pytest.raises(ConfigError) as error:
        load_session_file(path)
    message = str(error.value)
    assert str(path) in message and f"field {key!r}" in message
    if value is not None:
        assert value in message


def test_maps_must_name_the_packs_segments_and_the_profiles_electrodes():
    session = parse_session(_doc(session__subject=None), require_devices=False)
    check_against_pack(session, ["PMCla_group"], ["upper_arm_r", "forearm_r"], {"PMCla": {"group": "x"}})
    session.trackers["00B4E1AE"] = "torso"
    with pytest.raises(ConfigError, match="trackers.00B4E1AE.*torso"):
        check_against_pack(session, [], ["upper_arm_r", "forearm_r"], {"PMCla": {}})
    session = parse_session(_doc(session__subject=None, electrodes={"sensor02.EMG": "nowhere"}), require_devices=False)
    with pytest.raises(ConfigError, match="electrodes.sensor02.EMG.*nowhere"):
        check_against_pack(session, ["biceps"], ["upper_arm_r", "forearm_r"], {"PMCla": {}})


@pytest.mark.parametrize(
    ("trackers", "said"),
    [
        ({"00B4EB80": "upper_arm_r"}, "field 'trackers': no tracker on forearm_r"),
        ({"00B4EB80": "upper_arm_r", "00B497B2": "upper_arm_r"}, "trackers.00B497B2': tracker 00B4EB80 is on it too"),
        ({"00B4EB80": "upper_arm_r", "00b4eb80": "forearm_r"}, "the same tracker as '00B4EB80' (ids ignore case)"),
    ],
)
def test_every_segment_of_the_pack_has_one_tracker(trackers, said):
    """A segment without a tracker, two trackers on one, or one tracker listed twice in another case: the session ran
    20 s without a single joint frame, exit 0 (found by exploratory QA)."""
    with pytest.raises(ConfigError) as error:
        session = parse_session(_doc(session__subject=None, trackers=trackers), require_devices=False)
        check_against_pack(session, ["PMCla_group"], ["upper_arm_r", "forearm_r"], {"PMCla": {"group": "x"}})
    assert said in str(error.value), error.value


def test_cli_reports_a_bad_session_file_without_a_traceback(tmp_path):
    path = tmp_path / "session.toml"
    path.write_text('[session]\npack = "bench_press"\nload_kg = "heavy"\n')
    result = run_msk("live", str(path), "--no-view")
    assert result.returncode != 0 and "Traceback" not in result.stderr
    assert "session.load_kg" in result.stderr and "heavy" in result.stderr and str(path) in result.stderr


def test_live_sim_records_every_sample_the_simulators_sent_and_stops_cleanly_when_its_terminal_closes(tmp_path):
    """SIGHUP (the terminal closed, an SSH link dropped) stops it as Ctrl-C does; it killed msk live at once and left
    every node running (they are in their own process groups), the recorder still writing. Ctrl-C: tests/live_helpers."""
    from services.transport.mcap_io import McapRecorderWriter, read_messages
    from services.transport.zenoh_session import ZenohOptions, declare_data_publisher, open_session, publish

    out = tmp_path / "live"
    # an earlier run in this folder, killed: its recording and its logs (all that is left of it) are kept
    (out / "logs").mkdir(parents=True)
    (out / "logs" / "estimator.log").write_text("the earlier run's log\n")
    earlier_summary = json.dumps({"recordings": [str(out / "session.mcap")]}) + "\n"
    (out / "summary.json").write_text(earlier_summary)  # a run that ended: its summary was overwritten (a new user)
    with McapRecorderWriter(out / "session.mcap"):
        pass
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache"), "PYTHONUNBUFFERED": "1"}
    # no --no-view: its output is a pipe, where a view would draw unseen (a new user's `| tee` showed "+ view")
    process = start_msk("live", "--sim", "--duration", "120", "--out", str(out), env=env)
    lines: list[str] = []
    try:
        wait_running(process, lines)
        while not any("recording to" in line for line in lines):  # the next line (the buffer communicate skips)
            lines.append(line := process.stdout.readline())
            assert line, "".join(lines)  # msk live ended without it
        # another session on this endpoint (a replay, a second rack): not this athlete's, not recorded
        endpoint = re.search(r"running on (\S+?);", "".join(lines)).group(1)
        with open_session(ZenohOptions(connect=(endpoint,))) as other:
            publisher = declare_data_publisher(other, "msk/other/joints", "msk.JointAngles")
            for k in range(20):
                publish(publisher, messages.JointAngles(coordinates=["elbow_flex_r"], q=[0.1 * k], device_time_ns=k))
            time.sleep(6.0)  # some seconds of live data
        os.killpg(process.pid, signal.SIGHUP)  # as a closing terminal: to the whole foreground process group
        rest, _ = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(10)
    output = "".join(lines) + rest
    assert process.returncode == 0, output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stopped_by"] == "SIGHUP" and summary["duration_s"] < 120, summary
    assert all(code == 0 for code in summary["exit_codes"].values()), summary["exit_codes"]
    pids = json.loads((out / "logs" / "pids.json").read_text())
    assert set(pids) == {"recorder", "estimator", "kinematics", "drivers-trigno", "drivers-xsens"}
    for pid in pids.values():  # every node process ended with msk live
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)

    # the MCAP is readable and holds every sample each simulator sent (counted independently of the summary)
    emg, imu, frames = Counter(), Counter(), Counter()
    joints = 0
    assert (out / "logs-001" / "estimator.log").read_text() == "the earlier run's log\n"
    assert (out / "logs-001" / "summary.json").read_text() == earlier_summary
    assert "no view: the output is not a terminal; watch from one with msk view --session sim" in output, output
    assert "+ view" not in output
    assert f"{out} held an earlier run: its logs and summary are now in {out / 'logs-001'}" in output, output
    assert (out / "logs" / "estimator.log").is_file()  # this run's
    assert f"recording to {out / 'session-001.mcap'}" in output, output
    assert summary["recordings"] == [str(out / "session-001.mcap")], summary["recordings"]
    keys = {m.topic for m in read_messages(out / "session-001.mcap")}
    assert keys and all(key.startswith("msk/sim/") for key in keys), sorted(keys)
    for m in read_messages(out / "session-001.mcap"):
        if m.type_name == "msk.EmgChunk":
            emg[m.decode().source_id] += m.decode().n_samples
        elif m.type_name == "msk.ImuSample":
            imu[m.decode().tracker_id] += 1
        elif m.type_name == "msk.ActivationFrame":
            frames[m.decode().method] += 1
        elif m.type_name == "msk.JointAngles":
            joints += 1
    sent = summary["simulators_sent"]
    assert sent["trigno"]["samples"] > 2000 * 3, sent  # seconds of EMG, not a handful
    assert emg == {"trigno": sent["trigno"]["samples"]}, (emg, sent)
    trackers = {k: v["samples"] for k, v in sent.items() if k != "trigno"}
    assert len(trackers) == 2 and min(trackers.values()) > 60 * 3, sent
    assert dict(imu) == trackers, (imu, sent)
    assert all(v["bytes_dropped"] == 0 for k, v in sent.items() if k != "trigno")

    # activations of every requested method (default proposed, assisted, so) for every joint frame
    assert summary["methods"] == ["proposed", "assisted", "so"]
    assert joints > 60 * 2 and set(frames) == {"proposed", "assisted", "so"}, (joints, frames)
    assert all(n == joints for n in frames.values()), (joints, frames)
    assert summary["frames_estimated"] == dict(frames) and summary["samples"]["emg/trigno"] == sent["trigno"]["samples"]
    assert "emg/trigno" in output and "frames estimated" in output


def test_the_documented_session_file_is_accepted_and_documents_every_key(tmp_path):
    import re

    from services.sessions.live_session import _SECTIONS

    text = (REPO / "docs" / "live.md").read_text()
    block = re.search(r"```toml\n(.*?)```", text, re.S).group(1)
    (tmp_path / "subject_bench_press.json").write_text("{}")
    path = tmp_path / "session.toml"
    path.write_text(block)
    session = load_session_file(path)
    assert session.pack == "bench_press" and session.trackers and session.electrodes and session.trigno_host
    documented = set(re.findall(r"^\| `([a-z_]+\.[a-z_<>]+)` \|", text, re.M))
    keys = {f"{s}.{k}" for s, ks in _SECTIONS.items() if ks for k in ks} | {"trackers.<id>", "electrodes.<channel>"}
    assert documented == keys


def test_an_mvn_suit_is_a_device_of_the_session_file(tmp_path):
    """`[xsens] mvn = PORT` (a suit's network stream) needs no serial ports and no [trackers]: its segments come
    named; the xsens driver node listens for it. A value that is no port is refused, naming the key."""
    from services.sessions import live

    path = tmp_path / "session.toml"
    doc = _doc(
        trigno=None, electrodes=None, trackers=None, xsens={"mvn": 9763}, session__subject=None, session__methods=None
    )
    path.write_text(_toml(doc))
    plan, _ = live.plan_for(load_session_file(path), sim=False, log=lambda *_: None)
    argv = live.driver_argv(plan, "xsens")
    assert argv[argv.index("--mvn") + 1] == "9763" and "--xsens" not in argv
    path.write_text(_toml({**doc, "xsens": {"mvn": "suit:port"}}))
    with pytest.raises(ConfigError, match=r"field 'xsens.mvn'.*must be a UDP port"):
        load_session_file(path)


def test_an_athlete_not_calibrated_yet_runs_static_optimisation_alone(tmp_path):
    """A session file without a subject profile was refused ("missing: the subject profile"), so a lab could not even
    see its devices in msk live before calibrating. It now runs `so` (the estimates need no EMG; the EMG is
    recorded, not used: there is no MVC), says so, and refuses the methods that need a profile, naming them."""
    from services.sessions import live

    said: list[str] = []
    doc = _doc(session__subject=None, session__methods=None, electrodes={"sensor01.EMG": "PMCla"}, session__out="rec")
    path = tmp_path / "session.toml"
    path.write_text(_toml(doc))
    plan, _ = live.plan_for(load_session_file(path), sim=False, log=said.append)
    assert plan.subject is None and plan.methods == ("so",)
    assert live.estimator_settings(plan).subject_path is None
    assert any("no subject profile" in line and "estimating with so only" in line for line in said), said
    path.write_text(_toml(_doc(session__subject=None, session__methods=["proposed", "so"])))
    with pytest.raises(ConfigError, match=r"field 'session.methods'.*proposed need session.subject"):
        live.plan_for(load_session_file(path), sim=False, log=said.append)


def test_a_device_session_file_becomes_driver_commands_and_a_session_profile(tmp_path):
    from services.sessions import live

    write_subject(tmp_path / "subject.json", {"PMCla": {"group": "pec_clav", "divisor": 0.2}})
    doc = _doc(
        session__out="rec",
        trigno={"host": "10.0.0.5:50040", "emg_port": 50041, "aux_layout": "legacy_acc"},
        xsens={"ports": ["/dev/ttyUSB0", "usb"], "rate_hz": 60},
        electrodes={"sensor01.EMG": "PMCla", "sensor02.EMG": "BRA"},
    )  # BRA: a group
    path = tmp_path / "session.toml"
    path.write_text(_toml(doc))
    plan, simulators = live.plan_for(load_session_file(path), sim=False, log=lambda *_: None)
    assert simulators is None and plan.methods == ("proposed", "so")
    trigno = live.driver_argv(plan, "trigno")
    assert (
        trigno[trigno.index("--trigno") + 1] == "10.0.0.5:50040"
        and trigno[trigno.index("--trigno-emg-port") + 1] == "50041"
    )
    # the legacy EMG port's ACC beside it (50042), read as the file says it carries (a driver option since stop 45)
    assert trigno[trigno.index("--trigno-aux-port") + 1] == "50042"
    assert trigno[trigno.index("--trigno-aux-layout") + 1] == "legacy_acc"
    xsens = live.driver_argv(plan, "xsens")
    assert [xsens[i + 1] for i, a in enumerate(xsens) if a == "--xsens"] == ["/dev/ttyUSB0", "usb"]
    assert xsens[xsens.index("--imu-rate") + 1] == "60"
    assert "--segment=00B4EB80=upper_arm_r" in xsens and "--segment=00B497B2=forearm_r" in xsens
    live_profile = json.loads(plan.subject.read_text())["emg_normalisation"]
    assert plan.subject == tmp_path / "rec" / "subject_session.json"
    assert live_profile["sensor01.EMG"] == {"group": "pec_clav", "divisor": 0.2}  # the electrode's group and MVC
    assert "divisor" not in live_profile["sensor02.EMG"]  # a bare group: no MVC, flagged no_mvc, never raw volts
