"""``msk live --sim`` with stated device latencies: the estimator's and the kinematics node's status and
``summary.json`` say, per stream, the clock offset applied, its spread, the latency taken off and the method; the
offsets put an EMG sample and an IMU sample of one instant within a joint frame of each other, measured against the
simulators' own trial clock (the truth, not any mapping); and the recording, replayed through an estimator, maps the
EMG clock exactly as the live session did.
"""

from __future__ import annotations

import pytest

from services.nodes.estimator import EmgTiming, EstimatorNode, EstimatorSettings, EstimatorStats
from services.sessions import live
from services.sessions.live_session import load_session_file
from services.transport import messages
from services.transport.mcap_io import read_messages
from tests.live_helpers import run_sim_graph, write_subject

TRIGNO_LATENCY_MS = 60.0  # the simulated base holds each frame this long; the session file states it
TRACKER_LATENCY_MS = 5.0
RUN_S = 8.0
FRAME_S = 1.0 / 60.0  # a joint frame (IMU at 60 Hz)


@pytest.fixture(scope="module")
def live_run(tmp_path_factory):
    """One ``msk live --sim`` session (the graph msk live runs, nodes as processes) on simulators whose trial clock
    this test reads: (summary, plan, truth offsets in ns per stream)."""
    tmp = tmp_path_factory.mktemp("clock")
    path = tmp / "clock.toml"
    path.write_text(
        f'[session]\nname = "clock"\nout = "out"\nmethods = ["so"]\n'
        f"[trigno]\nlatency_ms = {TRIGNO_LATENCY_MS}\n[xsens]\nlatency_ms = {TRACKER_LATENCY_MS}\n"
    )
    session = load_session_file(path, require_devices=False)
    summary, plan, simulators, real_minus_monotonic_ns = run_sim_graph(session, tmp, RUN_S)
    # the truth: device time 0 of each stream is measured at these host instants (CLOCK_REALTIME, ns). The Trigno's
    # sample i (index since START) is trial sample start_index + i, measured on the trial clock; a tracker counts
    # SampleTimeFine from its power-up.
    rate = simulators.trigno.rate_hz
    truth = {
        "emg/trigno": (simulators.clock.start + simulators.trigno.stats.start_index / rate) * 1e9
        + real_minus_monotonic_ns
    }
    truth |= {f"imu/{t}": sim._powered_at * 1e9 + real_minus_monotonic_ns for t, sim in simulators.xsens.items()}
    return summary, plan, truth


def test_status_and_summary_carry_each_streams_clock_with_a_plausible_spread(live_run):
    summary, plan, _ = live_run
    clocks = summary["clocks"]
    trackers = sorted(plan.trackers)
    assert set(clocks) == {"emg/trigno", "joints", *(f"imu/{t}" for t in trackers)}, clocks
    emg = clocks["emg/trigno"]
    assert emg["method"] == "arrival" and emg["node"] == "estimator" and emg["latency_ms"] == TRIGNO_LATENCY_MS
    assert emg["samples"] > 100 and 0 <= emg["spread_ms"] < 50, emg  # ~74 chunks a second over the last 5 s
    for tracker in trackers:
        imu = clocks[f"imu/{tracker}"]
        assert imu["method"] == "arrival" and imu["node"] == "kinematics", imu
        assert imu["latency_ms"] == TRACKER_LATENCY_MS and imu["samples"] > 100 and 0 <= imu["spread_ms"] < 50, imu
    assert clocks["joints"]["method"] == "host" and clocks["joints"]["offset_ms"] == 0  # mapped by the kinematics node
    # the status carries them while the session runs, not only at its end
    running = [
        s
        for part in summary["recordings"]
        for m in read_messages(part)
        if m.type_name == "msk.DeviceStatus"
        and (s := m.decode()).kind == "node"
        and s.connected
        and s.device_id in ("estimator", "kinematics")
    ]
    with_clocks = {(s.device_id, c.source) for s in running for c in s.clocks if c.samples > 0}
    assert ("estimator", "emg/trigno") in with_clocks and {("kinematics", f"imu/{t}") for t in trackers} <= with_clocks


def test_stated_latencies_put_emg_and_motion_of_one_instant_within_a_joint_frame(live_run):
    """Per stream, error = applied offset - true offset (a sample mapped that much after its instant). A frame at
    host time H shows the motion of H - error(tracker) and reads the EMG of H - error(EMG)."""
    summary, plan, truth = live_run
    clocks = summary["clocks"]
    error_ms = {source: clocks[source]["offset_ms"] - truth[source] / 1e6 for source in truth}
    apart_ms = {t: error_ms[f"imu/{t}"] - error_ms["emg/trigno"] for t in plan.trackers}
    spreads = ", ".join(f"{s} {clocks[s]['spread_ms']:.2f} ms" for s in truth)
    print(
        f"\nmapping error (applied - true offset): {', '.join(f'{s} {e:+.2f} ms' for s, e in error_ms.items())}; "
        f"EMG read minus motion shown, per tracker: {', '.join(f'{t} {a:+.2f} ms' for t, a in apart_ms.items())}; "
        f"spread {spreads}"
    )
    # each mapping is late by its fastest delivery beyond the stated latency: >= 0, a few ms on loopback
    assert all(-0.5 < e < FRAME_S * 1e3 for e in error_ms.values()), error_ms
    assert all(abs(a) <= FRAME_S * 1e3 for a in apart_ms.values()), apart_ms


def test_the_recording_replayed_through_an_estimator_maps_the_emg_clock_as_live_did(live_run):
    """The EMG clock is mapped by the driver's receipt times recorded in each chunk: an estimator fed the recording
    (here at once, arrival times of now) applies the offset and spread the live one reported last, to the ns."""
    summary, plan, _ = live_run
    timing = EmgTiming(joints_clock="host", emg_latency_ns={"trigno": int(TRIGNO_LATENCY_MS * 1e6)})
    settings = EstimatorSettings(
        plan.session.pack, "replay", ("so",), emg=True, emg_clock="host", emg_stall_s=3600.0, timing=timing
    )
    node = EstimatorNode(settings, _profile(plan), EstimatorStats())
    recorded = [m for part in summary["recordings"] for m in read_messages(part)]
    for m in recorded:
        if m.type_name == "msk.EmgChunk":
            node.handle_emg(m.decode(), messages.now_ns())
    replayed = {r.source: r for r in node.clock_report()}["emg/trigno"]
    live_report = summary["clocks"]["emg/trigno"]
    assert replayed.offset_ns / 1e6 == pytest.approx(live_report["offset_ms"], abs=1e-6)
    assert round(replayed.spread_ns / 1e6, 3) == live_report["spread_ms"]
    assert replayed.samples == live_report["samples"] and replayed.latency_ns == TRIGNO_LATENCY_MS * 1e6


def _profile(plan):
    from msk_core.estimate.profile import SubjectProfile

    return SubjectProfile.load(plan.subject)


SESSION_FILE = """
[session]
pack = "bench_press"
subject = "subject.json"
load_kg = 60
[trigno]
host = "10.0.0.5"
{trigno}
[xsens]
ports = ["usb"]
rate_hz = 100
{xsens}
[trackers]
"00B4EB80" = "upper_arm_r"
"00B497B2" = "forearm_r"
[electrodes]
"sensor01.EMG" = "PMCla"
"""


def _session(tmp_path, trigno: str = "", xsens: str = ""):
    from services.sessions.live_session import load_session_file

    write_subject(tmp_path / "subject.json", {"PMCla": {"group": "pec_clav", "divisor": 0.2}})
    path = tmp_path / "session.toml"
    path.write_text(SESSION_FILE.format(trigno=trigno, xsens=xsens))
    return load_session_file(path)


def test_stated_latencies_default_to_the_documented_values_and_reach_the_nodes(tmp_path):
    from services.sessions.live_session import MTI_PROCESSING_MS, TRIGNO_LATENCY_MS

    plan, _ = live.plan_for(_session(tmp_path), sim=False, log=lambda *_: None)
    # an MTi at 115200 baud: its processing plus one 83-byte message (10 bits a byte) on the line
    assert plan.trigno_latency_ms == TRIGNO_LATENCY_MS
    assert plan.tracker_latency_ms == {
        t: pytest.approx(MTI_PROCESSING_MS + 830 / 115200 * 1e3) for t in ("00B4EB80", "00B497B2")
    }
    other = tmp_path / "stated"
    other.mkdir()
    session = _session(
        other, trigno="latency_ms = 14", xsens='latency_ms = 3\ntracker_latency_ms = { "00b497b2" = 7.5 }'
    )
    stated, _ = live.plan_for(session, sim=False, log=lambda *_: None)
    assert stated.trigno_latency_ms == 14 and stated.tracker_latency_ms == {"00B4EB80": 3, "00B497B2": 7.5}
    estimator = live.node_argv(stated, "estimator", tmp_path / "x.mcap")
    assert estimator[estimator.index("--emg-latency-ms") + 1] == "trigno=14"
    assert estimator[estimator.index("--joints-clock") + 1] == "host"
    kinematics = live.node_argv(stated, "kinematics", tmp_path / "x.mcap")
    assert [kinematics[i + 1] for i, a in enumerate(kinematics) if a == "--imu-latency-ms"] == [
        "00B4EB80=3",
        "00B497B2=7.5",
    ]


@pytest.mark.parametrize(
    ("trigno", "xsens", "key"),
    [
        ("latency_ms = -1", "", "trigno.latency_ms"),
        ('latency_ms = "60"', "", "trigno.latency_ms"),
        ("", "latency_ms = 1e9", "xsens.latency_ms"),
        ("", 'tracker_latency_ms = { "00B4EB80" = "fast" }', "xsens.tracker_latency_ms.00B4EB80"),
        ("", 'tracker_latency_ms = { "00B4EB8" = 1 }', "xsens.tracker_latency_ms.00B4EB8"),
        ("", 'tracker_latency_ms = { "00000001" = 1 }', "xsens.tracker_latency_ms.00000001"),
        ("", "tracker_latency_ms = 4", "xsens.tracker_latency_ms"),
    ],
)
def test_a_bad_stated_latency_is_refused_naming_the_file_the_key_and_the_value(tmp_path, trigno, xsens, key):
    from msk_core.errors import ConfigError

    with pytest.raises(ConfigError) as error:
        _session(tmp_path, trigno=trigno, xsens=xsens)
    assert error.value.field == key and str(tmp_path / "session.toml") in str(error.value), str(error.value)


def test_clock_reports_travel_in_the_node_status_in_ms():
    from msk_core.signal.host_clock import ClockReport
    from services.nodes.node_runtime import clock_offsets

    status = messages.DeviceStatus(
        device_id="estimator",
        kind="node",
        connected=True,
        clocks=clock_offsets(
            [ClockReport("emg/trigno", 1_764_000_000_123_456_789, 850_000, 60_000_000, "arrival", 370)]
        ),
    )
    clock = messages.decode("msk.DeviceStatus", messages.encode(status)).clocks[0]
    assert (clock.source, clock.method, clock.samples) == ("emg/trigno", "arrival", 370)
    assert clock.offset_ms == pytest.approx(1_764_000_000_123.456789, abs=1e-3)
    assert (clock.spread_ms, clock.latency_ms) == (0.85, 60.0)


def test_the_kinematics_node_maps_each_tracker_less_its_own_latency():
    from services.nodes.kinematics_node import KinematicsNode, KinematicsSettings, KinematicsStats

    settings = KinematicsSettings(
        "bench_press", "s", clock="host", latency_ns={"00B4EB80": 9_000_000}, default_latency_ns=2_000_000
    )
    node = KinematicsNode(settings, KinematicsStats())
    for k in range(30):
        for tracker, segment, power_up_ns in (
            ("00B4EB80", "upper_arm_r", 7_000_000_000),
            ("00B497B2", "forearm_r", 3_000_000_000),
        ):
            measured_ns = 1_764_000_000_000_000_000 + k * 16_666_667
            node.handle(
                f"msk/s/imu/{tracker}",
                messages.ImuSample(
                    tracker_id=tracker,
                    segment=segment,
                    orientation=messages.Quaternion(w=1.0),
                    device_time_ns=measured_ns - 1_764_000_000_000_000_000 + power_up_ns,
                    host_time_ns=measured_ns + (9_000_000 if tracker == "00B4EB80" else 2_000_000),
                ),
            )
    reports = {r.source: r for r in node.clock_report()}
    assert reports["imu/00B4EB80"].offset_ns == 1_764_000_000_000_000_000 - 7_000_000_000
    assert reports["imu/00B497B2"].offset_ns == 1_764_000_000_000_000_000 - 3_000_000_000
    assert (reports["imu/00B4EB80"].latency_ns, reports["imu/00B497B2"].latency_ns) == (9_000_000, 2_000_000)
    assert node.stats.frames_synced == 30  # the two trackers' samples of one instant meet
