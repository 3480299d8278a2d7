"""Input outages (services/nodes/node_runtime.py, InputContinuity): a node counts its input streams' silences longer than the
threshold, overlapping silences as one outage, and the publications its history publishers skipped; the counts travel
in its DeviceStatus and ``summary.json``. Without network namespaces (tests/test_hosts.py does it across hosts)."""

from __future__ import annotations

import time

from services.nodes.node_runtime import (
    OUTAGE_MIN_S,
    STREAM_MESSAGES,
    InputContinuity,
    NodeInputs,
    StatusReporter,
    outages_summary,
    outages_text,
)
from services.transport import messages, topics
from services.transport.zenoh_session import ZenohOptions, declare_history_publisher, open_session, publish

S = 1_000_000_000
EMG, IMU, LOAD = topics.emg_key("o", "trigno"), topics.imu_key("o", "T1"), topics.load_key("o")


def _stream(continuity: InputContinuity, key: str, begin_ns: int, end_ns: int, period_ns: int) -> None:
    for t in range(begin_ns, end_ns, period_ns):
        continuity.arrived(key, t)


def test_streams_silent_together_are_one_outage_events_and_short_pauses_are_none():
    continuity = InputContinuity()
    # EMG every 13.5 ms and a tracker every 10 ms for 2 s; both silent from about 2 s to 5 s (the network cut at
    # 2.0 s, each stream's last message a little before, its first after at its own time); then 2 s more
    _stream(continuity, EMG, 0, 2 * S, 13_500_000)
    _stream(continuity, IMU, 0, 2 * S, 10_000_000)
    _stream(continuity, EMG, 5 * S + 40_000_000, 8 * S, 13_500_000)
    _stream(continuity, IMU, 5 * S + 10_000_000, 7 * S, 10_000_000)
    continuity.arrived(LOAD, 1 * S)  # an event: its 9 s of quiet are no outage
    continuity.arrived(LOAD, 10 * S)
    _stream(continuity, IMU, 7 * S + 300_000_000, 8 * S, 10_000_000)  # 0.3 s: under the threshold
    report = continuity.report(8 * S)
    assert report.count == 1, report
    assert 3.0 < report.longest_s == report.total_s < 3.1, report
    assert set(report.last_keys) == {EMG, IMU}
    assert 1.98 * S < report.last_start_ns < 2 * S and report.last_end_ns == 5 * S + 40_000_000
    assert report.silent_s == 0 and report.threshold_s == OUTAGE_MIN_S
    # a second cut; then the streams stop for good: silent now, not counted (they may have ended)
    _stream(continuity, IMU, 9 * S, 10 * S, 10_000_000)
    later = continuity.report(12 * S)
    assert later.count == 2 and abs(later.longest_s - 3.05) < 0.01 and later.last_keys == [IMU]
    assert abs(later.total_s - later.longest_s - 1.01) < 0.001, later
    assert later.silent_keys == [EMG, IMU] and abs(later.silent_s - 4.0) < 0.01  # since EMG's last, at 8 s
    summary = outages_summary(later)
    assert summary["count"] == 2 and summary["last_start"].startswith("1970-01-01T00:00:0")
    assert outages_text(later).startswith("2 input outages (")


def test_a_stream_is_judged_on_its_own_period_and_only_after_its_first_messages():
    continuity = InputContinuity()
    slow = topics.activations_key("o", "so")
    _stream(continuity, slow, 0, 30 * S, S)  # once a second: 10 s threshold
    _stream(continuity, slow, 36 * S, 40 * S, S)  # 7 s silence: under 10 periods
    assert continuity.report(40 * S).count == 0
    early = InputContinuity()
    _stream(early, EMG, 0, (STREAM_MESSAGES - 2) * 13_500_000, 13_500_000)
    _stream(early, EMG, 3 * S, 4 * S, 13_500_000)  # silent before its period was known: not judged
    assert early.report(4 * S).count == 0


def test_skipped_sequence_numbers_are_missed_publications():
    continuity = InputContinuity()
    publisher = ("zid", 7)
    assert [continuity.arrived(EMG, i, (*publisher, n)) for i, n in enumerate((0, 1, 2, 5, 6, 4, 10))] == [
        0,
        0,
        0,
        2,  # 3 and 4 skipped
        0,
        0,  # 4 late (a history reply): no new miss
        3,
    ]
    assert continuity.arrived(EMG, 8, ("other", 7, 100)) == 0  # another publisher: its own numbers
    assert continuity.report(0).missed == 5


def test_a_paused_publisher_over_zenoh_is_one_outage_in_the_nodes_status(zenoh_endpoint):
    with (
        open_session(ZenohOptions(listen=(zenoh_endpoint,))) as node_session,
        open_session(ZenohOptions(connect=(zenoh_endpoint,))) as sender,
    ):
        inputs = NodeInputs(node_session, "probe")
        inputs.subscribe("msk/o/emg/*")
        reporter = StatusReporter(node_session, "o", "probe", inputs)
        publisher = declare_history_publisher(sender, EMG, "msk.EmgChunk")
        time.sleep(0.5)  # the subscription reaches the sender
        pause_s = 1.2

        def burst(first: int, n: int) -> None:
            for index in range(first, first + n):
                chunk = messages.EmgChunk(source_id="trigno", channel_labels=["c"], sample_rate_hz=2000.0,
                                          first_sample_index=27 * index, n_samples=1, n_channels=1, samples=[0.0])  # fmt: skip
                publish(publisher, chunk)
                time.sleep(0.01)

        burst(0, 3 * STREAM_MESSAGES)
        paused_ns = time.time_ns()
        time.sleep(pause_s)
        resumed_ns = time.time_ns()
        burst(3 * STREAM_MESSAGES, 20)
        deadline = time.monotonic() + 10
        got = 0
        while got < 4 * STREAM_MESSAGES and time.monotonic() < deadline:
            got += inputs.get(0.1) is not None
        assert got == 4 * STREAM_MESSAGES, f"waited 10 s for {4 * STREAM_MESSAGES} chunks, got {got}"
        status = messages.decode(messages.DeviceStatus, messages.encode(reporter.message()))  # as it travels
    outages = status.outages
    assert outages.count == 1 and outages.last_keys == [EMG], outages
    # the silence spans the publisher's pause: its last chunk before, its first after
    assert outages.last_start_ns <= paused_ns + 10**8 and outages.last_end_ns >= resumed_ns, outages
    assert outages.longest_s >= pause_s - 0.1 and outages.missed == 0, outages


def test_msk_live_summary_carries_each_nodes_outages(tmp_path):
    from services.sessions.live import summarise, summary_text
    from services.transport.mcap_io import McapRecorderWriter

    outages = messages.InputOutages(count=1, total_s=3.2, longest_s=3.2, last_start_ns=5 * S, last_end_ns=8 * S + 2 * 10**8,
                                    last_keys=[EMG, IMU], threshold_s=OUTAGE_MIN_S, missed=40, recovered=40)  # fmt: skip
    status = messages.DeviceStatus(device_id="estimator", kind="node", connected=False, outages=outages)
    with McapRecorderWriter(tmp_path / "s.mcap") as writer:
        writer.write(topics.status_key("o", "estimator"), "msk.DeviceStatus", messages.encode(status), 9 * S, 9 * S)
    summary = summarise(tmp_path / "s.mcap", 10.0)
    said = summary["input_outages"]["estimator"]
    assert said["count"] == 1 and said["longest_s"] == 3.2 and said["last_keys"] == [EMG, IMU]
    assert said["last_start"] == "1970-01-01T00:00:05.000+00:00" and said["missed"] == said["recovered"] == 40
    assert "estimator: 1 input outage (3.2 s, longest 3.2 s); 40 publications missed, 40 recovered" in summary_text(
        summary
    )


def test_msk_view_shows_each_nodes_outages():
    from rich.console import Console

    from services.surfaces.view import health_tables

    outages = messages.InputOutages(count=2, total_s=7.5, longest_s=4.0, silent_s=1.5, silent_keys=[EMG])
    status = {"estimator": messages.DeviceStatus(device_id="estimator", kind="node", connected=True, outages=outages)}
    console = Console(width=160, record=True)
    for table in health_tables(status):
        console.print(table)
    text = console.export_text()
    assert "outages" in text and "2 (7.5 s), silent 1.5 s" in text, text


def test_msk_live_summary_says_a_tracker_lost_during_the_session(tmp_path):
    """Found by an independent tracker imitation unplugged mid-session: the printed summary said "799 samples, 0 lost"
    and nothing else. Its losses and why are now on its line; a tracker connected until the stop is not a loss."""
    from services.sessions.live import summarise, summary_text
    from services.transport.mcap_io import McapRecorderWriter

    def status(device: str, connected: bool, error: str = "") -> bytes:
        return messages.encode(
            messages.DeviceStatus(device_id=device, kind="xsens", connected=connected, last_error=error)
        )

    gone = "/dev/pts/4: device unplugged (read failed: [Errno 5] Input/output error)"
    timeline = {"A": [True, True, True, False], "B": [True, False, False, False]}  # the last: the stop's status
    with McapRecorderWriter(tmp_path / "s.mcap") as writer:
        for k in range(4):
            for device, states in timeline.items():
                error = gone if device == "B" and not states[k] else ""
                writer.write(
                    topics.status_key("o", device), "msk.DeviceStatus", status(device, states[k], error), k * S, k * S
                )
                sample = messages.ImuSample(tracker_id=device, orientation=messages.Quaternion(w=1.0))
                writer.write(topics.imu_key("o", device), "msk.ImuSample", messages.encode(sample), k * S, k * S)
    summary = summarise(tmp_path / "s.mcap", 4.0)
    assert summary["devices"]["A"]["disconnections"] == 0 and summary["devices"]["B"]["disconnections"] == 1
    text = summary_text(summary)
    assert "imu/A: 4 samples, 0 lost\n" in text + "\n", text
    assert f"imu/B: 4 samples, 0 lost; connection lost 1x; last said: {gone}" in text, text


def test_msk_live_summary_says_what_an_mvn_suit_lost_and_said():
    """An MVN suit's status is keyed `mvn`, its samples `mvn-<segment>`: the printed summary showed neither its 120
    lost samples nor why it stopped (independent MVN imitation)."""
    from services.sessions.live import summary_text

    summary = {
        "duration_s": 30.0,
        "samples": {"imu/mvn-right_upper_arm": 1440, "imu/mvn-right_forearm": 1440},
        "samples_lost": {"mvn": 120},
        "devices": {"mvn": {"kind": "mvn", "connected": False, "errors": 0, "last_error": "", "disconnections": 0,
                            "problem": "no MVN quaternion pose (type 02) on UDP 0.0.0.0:9763 for 3 s"}},
        "joint_frames": 0, "envelopes": 0, "frames_estimated": {}, "flags": {},
    }  # fmt: skip
    text = summary_text(summary)
    assert "  mvn: 120 samples lost; last said: no MVN quaternion pose (type 02) on UDP 0.0.0.0:9763 for 3 s" in text
    assert "imu/mvn-right_forearm: 1440 samples, 0 lost\n" in text


def test_a_session_without_a_joint_frame_prints_no_set_of_0_reps():
    """Found by a new user's walk: `msk live` that failed at the start (no device) printed "sets: 1: 0 reps"."""
    from services.sessions.live import summary_text

    summary = {
        "duration_s": 2.0, "samples": {}, "samples_lost": {}, "devices": {}, "joint_frames": 0, "envelopes": 0,
        "frames_estimated": {}, "flags": {}, "sets": [{"number": 1, "reps": 0, "time_under_tension_s": 0.0, "ended_by": "end of data"}],
    }  # fmt: skip
    assert "sets:" not in summary_text(summary)
    summary["joint_frames"] = 120  # frames but no rep yet: the set is said, with its 0 reps
    assert "  sets: 1: 0 reps" in summary_text(summary)
