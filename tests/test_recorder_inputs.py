"""The recorder's inputs over real Zenoh sessions on loopback, into real MCAP files: payloads that are not messages of
their topic's type stay out of the typed channels (and out of what reads them), identical messages are all kept,
nothing received is lost at stop, and a restarted recorder's parts join once each."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from mcap.reader import make_reader

from services.nodes import recorder, replayer
from services.sessions import live
from services.sessions.graph import wait_for
from services.surfaces.dashboard import report as session_report
from services.transport import messages, topics
from services.transport.mcap_io import REJECTED_ENCODING, REJECTED_REASON, McapRecorderWriter, ReadReport, read_messages
from services.transport.zenoh_session import (
    ZenohOptions,
    declare_data_publisher,
    declare_history_publisher,
    open_session,
    publish,
)
from tests.conftest import emg_chunk

SESSION = "lab"
JOINTS = topics.joints_key(SESSION)
LOAD = topics.load_key(SESSION)
EMG = topics.emg_key(SESSION, "trigno")
OUTSIDE = f"msk/{SESSION}/not_a_topic"
STATUS = topics.status_key(SESSION, recorder.NODE_NAME)


def _wait(condition: Callable[[], bool], timeout_s: float, what: str, have: Callable[[], object] = lambda: "") -> None:
    wait_for(what, condition, lambda: str(have()), timeout_s, poll_s=0.02)  # the graph's bounded wait


@contextlib.contextmanager
def _recording(
    endpoint: str, out: Path, *, connect: bool = False, **kwargs
) -> Iterator[tuple[recorder.RecorderStats, threading.Event]]:
    """``recorder.main`` in a thread listening on ``endpoint`` (``connect``: connecting to it) until its first history
    fetch is in; stopped (and joined) on exit."""
    stop, ready, stats = threading.Event(), threading.Event(), recorder.RecorderStats()
    options = ZenohOptions(connect=(endpoint,)) if connect else ZenohOptions(listen=(endpoint,))
    thread = threading.Thread(
        target=recorder.main,
        args=(options, out),
        kwargs={"stop_event": stop, "ready_event": ready, "stats": stats, **kwargs},
        daemon=True,
    )
    thread.start()
    try:
        assert ready.wait(20), "the recorder did not start"
        _wait(lambda: stats.history_fetches >= 1 or not kwargs.get("history", True), 20, "the first history fetch")
        yield stats, stop
    finally:
        stop.set()
        thread.join(30)
    assert not thread.is_alive(), "the recorder did not stop within 30 s"


def _matched(publisher) -> None:
    _wait(lambda: publisher.matching_status.matching, 10, "the recorder's subscriber")


def _key_matched(session, key: str) -> None:
    """Wait until ``session`` knows a subscriber of ``key`` (an AdvancedPublisher has no matching status)."""
    probe = session.declare_publisher(key)
    try:
        _matched(probe)
    finally:
        probe.undeclare()


def _joints(value: float) -> messages.JointAngles:
    return messages.JointAngles(coordinates=["elbow_flexion"], q=[value], device_time_ns=1_000 + int(value))


def _emg(index: int) -> messages.EmgChunk:
    return emg_chunk(index, labels=["s1.EMG"], value=1e-3, units="V", host_time_ns=1_700_000_000_000_000_000 + index)


def _typed(path: Path, key: str) -> list[bytes]:
    return [m.data for m in read_messages(path) if m.topic == key]


BAD = [  # (key, type named by the publisher's encoding, payload, reasons check_payload may give)
    (JOINTS, "msk.JointAngles", b"\xff\xff\xff\xff\x0f", {"undecodable"}),
    (JOINTS, "msk.JointAngles", b"", {"invalid"}),  # decodes to a JointAngles without coordinates
    (
        JOINTS,
        "msk.JointAngles",
        messages.encode(messages.DeviceStatus(device_id="trigno", kind="trigno", errors=3)),
        {"wrong_type", "undecodable"},
    ),  # another type's bytes under this topic's encoding
    (
        JOINTS,
        "msk.ImuSample",
        messages.encode(messages.ImuSample(tracker_id="00B4", orientation=messages.Quaternion(w=1.0))),
        {"wrong_type"},
    ),  # a valid message of another type, saying so
    (OUTSIDE, "msk.JointAngles", messages.encode(_joints(9.0)), {"unknown_key"}),  # a key outside the topic table
]


def test_payloads_that_are_not_their_topics_messages_stay_out_of_the_typed_channels(tmp_path, zenoh_endpoint):
    """Garbage, an empty JointAngles, another type's bytes, a key outside the table and a 50 MB payload among valid
    joint angles: the typed channel holds the valid ones only; the others (but the 50 MB one, counted and never
    copied) are kept byte for byte in channels without a schema labelled with the reason; the recorder's status counts
    them per key and reason; read_messages, the replay, the session report and msk live's summary all work on the
    file and see the valid messages only."""
    out = tmp_path / "session.mcap"
    valid = [messages.encode(_joints(float(i))) for i in range(6)]
    statuses: list[messages.DeviceStatus] = []
    with (
        _recording(zenoh_endpoint, out, flush_interval_s=0.2, session=SESSION) as (stats, _),
        open_session(ZenohOptions(connect=(zenoh_endpoint,))) as session,
    ):
        session.declare_subscriber(
            STATUS, lambda s: statuses.append(messages.decode("msk.DeviceStatus", s.payload.to_bytes()))
        )
        publishers = {
            (key, type_name): declare_data_publisher(session, key, type_name)
            for key, type_name in {
                (JOINTS, "msk.JointAngles"),
                (EMG, "msk.EmgChunk"),
                *((key, type_name) for key, type_name, _, _ in BAD),
            }
        }
        for publisher in publishers.values():
            _matched(publisher)
        for payload in valid[:3]:
            publishers[(JOINTS, "msk.JointAngles")].put(payload)
        for key, type_name, payload, _ in BAD:
            publishers[(key, type_name)].put(payload)
        publishers[(EMG, "msk.EmgChunk")].put(bytes(50 * 1024 * 1024))  # 50 MB
        for payload in valid[3:]:
            publishers[(JOINTS, "msk.JointAngles")].put(payload)
        _wait(
            lambda: (
                stats.written >= len(valid)
                and stats.rejected >= len(BAD)
                and stats.inputs.total_dropped >= len(BAD) + 1
            ),
            20,
            "every payload at the recorder",
            lambda: stats,
        )
        _wait(
            lambda: any(sum(d.count for d in s.dropped) == len(BAD) + 1 for s in statuses),
            10,
            "the recorder's status counting them",
            lambda: statuses[-1:],
        )
    assert out.stat().st_size < 1024 * 1024, "the 50 MB payload went into the file"

    # the typed channels: the valid messages only, in order, each of its topic's type
    report = ReadReport()
    typed = list(read_messages(out, report=report))
    assert [m.data for m in typed if m.topic == JOINTS] == valid
    assert {m.topic for m in typed} == {JOINTS, STATUS}
    for m in typed:
        m.decode()
    kept = list(read_messages(out, include_rejected=True))
    rejected = [m for m in kept if m.rejected]
    assert [(m.topic, m.data) for m in rejected] == [(key, payload) for key, _, payload, _ in BAD]
    for m, (_, _, _, reasons) in zip(rejected, BAD):
        assert m.rejected in reasons and m.type_name == ""
    assert sum(report.left_out.values()) == len(BAD) and set(report.left_out) == {
        (m.topic, m.rejected) for m in rejected
    }
    with open(out, "rb") as stream:
        channels = make_reader(stream).get_summary().channels.values()
    labelled = [c for c in channels if c.message_encoding == REJECTED_ENCODING]
    assert {(c.topic, c.metadata[REJECTED_REASON]) for c in labelled} == set(report.left_out)
    assert all(c.schema_id == 0 for c in labelled)

    # the recorder's counts: in its status (live and the last one, in the file) and in its stats
    drops = {(d.key, d.reason): d.count for d in statuses[-1].dropped}
    assert drops[(EMG, "oversized")] == 1 and sum(drops.values()) == len(BAD) + 1
    assert statuses[-1].kind == "node" and statuses[-1].device_id == recorder.NODE_NAME
    last = [m.decode() for m in typed if m.topic == STATUS][-1]
    assert not last.connected and {(d.key, d.reason): d.count for d in last.dropped} == drops
    assert stats.rejected == len(BAD) and stats.inputs.as_dict()["dropped"][EMG] == {"oversized": 1}

    # what reads recordings: msk live's summary, the session report, a replay
    summary = live.summarise(out, 1.0)
    assert (
        summary["joint_frames"] == len(valid)
        and sum(sum(reasons.values()) for reasons in summary["inputs_dropped"][recorder.NODE_NAME].values())
        == len(BAD) + 1
    )
    session_report.write_report(out, tmp_path / "report")
    received: list[tuple[str, bytes]] = []
    with open_session(ZenohOptions(listen=(zenoh_endpoint,))) as session:
        session.declare_subscriber("msk/**", lambda s: received.append((str(s.key_expr), s.payload.to_bytes())))
        replayed = replayer.main(
            ZenohOptions(connect=(zenoh_endpoint,)), out, rate=None, session_name="again", wait_subscribers_s=5.0
        )
        _wait(lambda: len(received) >= replayed.published, 10, "the replayed messages", lambda: len(received))
        time.sleep(0.2)
    assert replayed.published == len(typed) and replayed.left_out == dict(report.left_out)
    assert [payload for key, payload in received if key == topics.joints_key("again")] == valid
    assert {key for key, _ in received} == {topics.joints_key("again"), topics.status_key("again", recorder.NODE_NAME)}


def test_identical_valid_messages_are_each_recorded(tmp_path, zenoh_endpoint):
    """20 byte-identical valid messages (no host time) from a plain publisher and 20 from a publisher that keeps a
    history (its cache answers the recorder's fetch with copies of what also arrives live): 20 of each are written."""
    out = tmp_path / "same.mcap"
    joints, load = messages.encode(_joints(1.0)), messages.encode(messages.LoadEvent(barbell_mass_kg=60.0))
    with (
        _recording(zenoh_endpoint, out) as (stats, _),
        open_session(ZenohOptions(connect=(zenoh_endpoint,))) as session,
    ):
        plain = declare_data_publisher(session, JOINTS, "msk.JointAngles")
        cached = declare_history_publisher(session, LOAD, "msk.LoadEvent")
        _matched(plain)
        _key_matched(session, LOAD)
        for _ in range(20):
            plain.put(joints)
            cached.put(load)
        _wait(lambda: stats.received >= 40, 20, "40 messages at the recorder", lambda: stats)
        time.sleep(0.3)  # anything more (a copy from the cache) would show below
    assert _typed(out, JOINTS) == [joints] * 20
    assert _typed(out, LOAD) == [load] * 20
    assert stats.history_fetches >= 2 and stats.already_recorded == stats.history_fetched


class _SlowWriter(McapRecorderWriter):
    """Writes take 10 ms: the recorder falls behind what it receives, as on a slow disk."""

    def write(self, *args, **kwargs) -> None:
        time.sleep(0.01)
        super().write(*args, **kwargs)


def test_what_is_received_before_the_stop_is_all_written(tmp_path, zenoh_endpoint, monkeypatch):
    """The recorder is stopped while hundreds of received messages still wait in its queue: it writes them all."""
    monkeypatch.setattr(recorder, "McapRecorderWriter", _SlowWriter)
    out, sent = tmp_path / "drained.mcap", 300
    arrived: list[int] = []
    with (
        _recording(zenoh_endpoint, out, history=False) as (stats, stop),
        open_session(ZenohOptions(connect=(zenoh_endpoint,))) as session,
    ):
        session.declare_subscriber(EMG, lambda s: arrived.append(1))
        publisher = declare_data_publisher(session, EMG, "msk.EmgChunk")
        _matched(publisher)
        for index in range(sent):
            publish(publisher, _emg(index))
        _wait(lambda: len(arrived) == sent, 10, "the messages on the network", lambda: len(arrived))
        time.sleep(0.1)  # they reached the recorder's queue too (same link, same moment)
        written_at_stop = stats.written
        stop.set()
    assert written_at_stop < sent / 2, f"the recorder had written {written_at_stop} at the stop: nothing to drain"
    assert [messages.decode("msk.EmgChunk", data).first_sample_index // 27 for data in _typed(out, EMG)] == list(
        range(sent)
    )


def test_a_restarted_recorder_continues_into_the_next_part_and_the_parts_join_once_each(tmp_path, zenoh_endpoint):
    """A driver publishing with a history; the recorder is stopped, the driver goes on, the recorder is started again
    with the same --out (as `msk recorder` does: FILE-001.mcap, leaving out what FILE.mcap holds): the two parts
    hold every chunk once, in order, and the restart took the chunks published while it was down from the cache."""
    out = tmp_path / "rec.mcap"
    with open_session(ZenohOptions(listen=(zenoh_endpoint,))) as driver_session:
        driver = declare_history_publisher(driver_session, EMG, "msk.EmgChunk")
        first = _run_part(zenoh_endpoint, out, driver_session, driver, range(0, 30), expected=30)
        for index in range(30, 50):  # while no recorder runs
            publish(driver, _emg(index))
        continuation = recorder.next_part_path(out)
        assert continuation == tmp_path / "rec-001.mcap"
        second = _run_part(
            zenoh_endpoint,
            continuation,
            driver_session,
            driver,
            range(50, 60),
            expected=30,
            already_recorded=recorder.recorded_tail_in(recorder.part_paths(out)),
        )
    assert first.written == 30 and second.history_fetched == 50 and second.already_recorded == 30
    chunks = [
        messages.decode("msk.EmgChunk", data).first_sample_index // 27
        for path in recorder.part_paths(out)
        for data in _typed(path, EMG)
    ]
    assert chunks == list(range(60))


def _run_part(
    endpoint: str, out: Path, driver_session, driver, indices: range, *, expected: int, **kwargs
) -> recorder.RecorderStats:
    """A recorder connected to the driver's session, recording while ``indices`` are published, until it has written
    ``expected`` chunks."""
    with _recording(endpoint, out, connect=True, **kwargs) as (stats, _):
        _key_matched(driver_session, EMG)
        for index in indices:
            publish(driver, _emg(index))
        _wait(lambda: stats.written >= expected, 20, f"{expected} chunks written", lambda: stats)
        time.sleep(0.2)  # anything more (a copy from the cache) would show in the parts
    return stats


def test_a_folder_given_as_the_recording_is_said_as_such(tmp_path, capsys):
    """It was taken for an earlier part of the recording: "MCAP file not found"."""
    from services import cli

    assert cli.main(["recorder", "--out", str(tmp_path), "--duration", "1"]) == 2
    assert "field '--out': is a folder: give the recording's file" in capsys.readouterr().err
