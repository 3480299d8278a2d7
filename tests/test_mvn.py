"""The Xsens MVN network streamer input (drivers.xsens.mvn, `msk capture/drivers --mvn`): datagrams written from the
protocol facts in ../shared/protocols/xsens-xbus.md, sent over real UDP."""

from __future__ import annotations

import math
import os
import re
import socket
import struct
import threading
import time

import pytest

from drivers.xsens import mvn
from msk_core.errors import ProtocolError
from services.cli import main as msk
from services.transport import messages
from services.transport.mcap_io import read_messages


def body(k: int) -> list[mvn.SegmentPose]:
    """All 23 body segments at sample ``k``: the right forearm turning about z, the others still."""
    angle = 0.01 * k
    poses = []
    for segment_id in range(1, len(mvn.SEGMENTS) + 1):
        turning = mvn.SEGMENTS[segment_id - 1] == "right_forearm"
        q = (math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)) if turning else (1.0, 0.0, 0.0, 0.0)
        poses.append(mvn.SegmentPose(segment_id, (0.1 * segment_id, 0.0, 1.0), q))
    return poses


def test_a_pose_round_trips_through_its_datagrams_and_bad_ones_are_named():
    datagrams = mvn.encode_pose(7, 1234, body(3), per_datagram=10)  # 23 segments in 3 datagrams
    assert len(datagrams) == 3 and datagrams[0][:6] == b"MXTP02"
    parsed = [mvn.parse_datagram(d) for d in datagrams]
    assert [(p.datagram_index, p.last) for p in parsed] == [(0, False), (1, False), (2, True)]
    assert parsed[0].sample_counter == 7 and parsed[0].time_ms == 1234 and parsed[0].items == 10
    items = [s for p in parsed for s in mvn.parse_pose_items(p.payload)]
    assert [s.name for s in items] == list(mvn.SEGMENTS)
    assert items[9].quaternion == pytest.approx((math.cos(0.015), 0.0, 0.0, math.sin(0.015)), abs=1e-7)
    with pytest.raises(ProtocolError, match="not an MVN datagram"):
        mvn.parse_datagram(b"XXXX02" + datagrams[0][6:])
    with pytest.raises(ProtocolError, match="says 320 payload bytes, carries 319"):
        mvn.parse_datagram(datagrams[0][:-1])
    with pytest.raises(ProtocolError, match="shorter than its 24-byte header"):
        mvn.parse_datagram(datagrams[0][:20])


def test_the_receiver_assembles_samples_counts_lost_ones_and_leaves_other_types_out():
    with mvn.MvnReceiver("127.0.0.1", 0) as receiver, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
        target = ("127.0.0.1", receiver.port)
        for k in (0, 1, 2, 5):  # samples 3 and 4 never sent
            for datagram in mvn.encode_pose(k, 10 * k, body(k), per_datagram=12):
                sender.sendto(datagram, target)
        joints = bytearray(mvn.encode_pose(6, 60, [])[0])
        joints[4:6] = b"20"  # a joint-angles message: not read here
        sender.sendto(bytes(joints), target)
        sender.sendto(b"hello", target)
        poses: list[mvn.Pose] = []
        deadline = time.monotonic() + 5
        while receiver.stats.datagrams < 10 and time.monotonic() < deadline:
            poses += receiver.read(0.1)
    assert [p.sample_counter for p in poses] == [0, 1, 2, 5]
    assert all(len(p.segments) == 23 for p in poses)
    stats = receiver.stats
    assert (stats.samples_lost, dict(stats.other_types), stats.errors) == (2, {"20": 1}, 1), stats
    assert "shorter than its 24-byte header" in stats.last_error


def test_split_poses_come_together_in_any_order_once_and_one_character_is_followed():
    """Found by an independent MVN imitation: a sample whose datagrams came reordered or one of them twice was
    dropped ("datagrams missing"), and two characters' segments alternated in one athlete's joint angles."""
    with mvn.MvnReceiver("127.0.0.1", 0) as receiver, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
        target = ("127.0.0.1", receiver.port)
        for k in range(6):
            datagrams = mvn.encode_pose(k, 10 * k, body(k), per_datagram=8)  # 3 datagrams a sample
            if k == 1:
                datagrams = datagrams[::-1]  # reordered
            if k == 2:
                datagrams = [datagrams[0], *datagrams]  # one twice
            if k == 3:
                datagrams = datagrams + datagrams  # the whole sample again
            for datagram in datagrams:
                sender.sendto(datagram, target)
            for datagram in mvn.encode_pose(k, 10 * k, body(k), character=1):  # a second suit
                sender.sendto(datagram, target)
        poses: list[mvn.Pose] = []
        deadline = time.monotonic() + 5
        while receiver.stats.datagrams < 6 * 3 + 1 + 3 + 6 and time.monotonic() < deadline:
            poses += receiver.read(0.1)
    assert [p.sample_counter for p in poses] == list(range(6)) and {p.character for p in poses} == {0}
    stats = receiver.stats
    assert (stats.repeated, stats.incomplete, stats.samples_lost, stats.errors) == (4, 0, 0, 0), stats
    assert stats.other_characters == {1: 6}


def test_msk_capture_records_the_packs_segments_of_an_mvn_stream(tmp_path, capsys):
    """A suit streaming at 60 Hz: the recording holds, per pack segment, its MVN orientation as sent (NWU), named
    by the pack's segment; a stream that stops is said."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    sent: list[int] = []
    stop = threading.Event()

    def stream() -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
            for k in range(90):  # 1.5 s, then silence
                if stop.is_set():
                    return
                for datagram in mvn.encode_pose(k, 1000 + 16 * k, body(k)):
                    sender.sendto(datagram, ("127.0.0.1", port))
                sent.append(k)
                time.sleep(1 / 60)

    out = tmp_path / "mvn.mcap"
    threading.Timer(0.5, stream).start()
    try:
        code = msk(["capture", "--mvn", f"127.0.0.1:{port}", "--duration", "5.5", "--out", str(out)])
    finally:
        stop.set()
    said = capsys.readouterr()
    assert code == 0, said
    samples = [r.decode() for r in read_messages(out) if r.type_name == "msk.ImuSample"]
    by_tracker: dict[str, list[messages.ImuSample]] = {}
    for sample in samples:
        by_tracker.setdefault(sample.tracker_id, []).append(sample)
    assert set(by_tracker) == {f"mvn-{name}" for name in mvn.PACK_SEGMENTS.values()}
    forearm = by_tracker["mvn-right_forearm"]
    assert {s.segment for s in forearm} == {"forearm_r"} and {s.coordinate_frame for s in forearm} == {"NWU"}
    assert len(forearm) == len(sent) and [s.packet_counter for s in forearm] == sent
    last = forearm[-1]
    k = last.packet_counter
    assert last.device_time_ns == (1000 + 16 * k) * 1_000_000
    assert (last.orientation.w, last.orientation.z) == pytest.approx((math.cos(0.005 * k), math.sin(0.005 * k)))
    statuses = [r.decode() for r in read_messages(out) if r.type_name == "msk.DeviceStatus"]
    assert any(f"no MVN quaternion pose (type 02) on UDP 127.0.0.1:{port}" in s.last_error for s in statuses)
    assert f"mvn: {len(sent) * len(mvn.PACK_SEGMENTS)} samples" in said.out, said.out


def test_a_bad_mvn_address_is_refused(tmp_path, capsys):
    out = tmp_path / "never.mcap"
    assert msk(["capture", "--mvn", "host:port", "--duration", "1", "--out", str(out)]) == 2
    assert "field '--mvn'" in capsys.readouterr().err and not out.exists()
    assert struct.calcsize(">4s2sIBBIBBBB2xH") == mvn.HEADER.size == 24


def test_msk_sim_mvn_streams_a_recordings_segments_that_msk_capture_records_as_they_were(tmp_path, capsys):
    """`msk sim mvn` (the demo's deadlift as a suit) into `msk capture --mvn`: each pack segment's orientation,
    brought back from MVN's NWU to ENU, is the recording's."""
    from drivers.xsens import frames, xbus
    from services.commands.sim import recorded_segment_poses
    from tests.dashboard_helpers import DEMO_MCAP

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    sim = threading.Thread(
        target=msk, args=(["sim", "mvn", "--to", f"127.0.0.1:{port}", "--exercise", "deadlift", "--duration", "3"],)
    )
    threading.Timer(0.5, sim.start).start()
    out = tmp_path / "sim.mcap"
    assert msk(["capture", "--mvn", f"127.0.0.1:{port}", "--duration", "2.5", "--out", str(out)]) == 0
    sim.join(10)
    segments = ["pelvis", "torso", "thigh_r", "shank_r"]
    sent = recorded_segment_poses(DEMO_MCAP, segments)
    every = [r.decode() for r in read_messages(out) if r.type_name == "msk.ImuSample"]
    assert {s.segment for s in every} == set(mvn.PACK_SEGMENTS)  # the suit sends the whole body
    recorded = [s for s in every if s.segment in segments]
    assert len(recorded) > 4 * 60
    for sample in recorded[:: len(recorded) // 20]:
        o = sample.orientation
        back = frames.to_enu((o.w, o.x, o.y, o.z), xbus.CoordinateFrame.NWU)
        k = sample.packet_counter % len(sent)
        assert back == pytest.approx(sent[k][1][sample.segment], abs=1e-6), (sample.segment, k)
    assert "sent " in capsys.readouterr().err


@pytest.mark.slow
def test_msk_live_estimates_a_bench_press_from_an_mvn_suit(tmp_path):
    """`[xsens] mvn = PORT` in a session file: the suit's stream through the drivers, the kinematics node and the
    estimator of a real `msk live` (no subject profile: static optimisation). The elbow angle of the joint frames
    spans the demo's (15-126 degrees)."""
    from services.transport.zenoh_session import free_loopback_endpoint
    from tests.live_helpers import run_msk, start_msk

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    session = tmp_path / "session.toml"
    session.write_text(
        f'[session]\nname = "suit"\npack = "bench_press"\nload_kg = 50\nout = "out"\n\n[xsens]\nmvn = "127.0.0.1:{port}"\n'
    )
    process = start_msk("live", str(session), "--no-view", "--duration", "13", "--listen", free_loopback_endpoint(),
                        env={**os.environ, "PYTHONUNBUFFERED": "1"})  # fmt: skip
    try:
        lines: list[str] = []
        deadline = time.monotonic() + 60
        while not any(line.startswith("running:") for line in lines) and time.monotonic() < deadline:
            line = process.stdout.readline()
            assert line, "msk live ended before it ran:\n" + "".join(lines)
            lines.append(line)
        assert time.monotonic() < deadline, "msk live did not start within 60 s:\n" + "".join(lines)
        simulated = run_msk("sim", "mvn", "--to", f"127.0.0.1:{port}", "--duration", "12", timeout=60)
        assert simulated.returncode == 0, simulated.stderr
        output = "".join(lines) + process.communicate(timeout=60)[0]
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(10)
    assert process.returncode == 0, output
    assert "running: monitor, recorder, estimator, kinematics, drivers-xsens" in output, output
    assert "reps not counted live: no subject profile: no rep template" in output, output
    elbow = [
        j.q[list(j.coordinates).index("elbow_flex_r")]
        for j in (
            r.decode() for r in read_messages(tmp_path / "out" / "session.mcap") if r.type_name == "msk.JointAngles"
        )
    ]
    # every joint frame estimated, as the estimator counts them (the recorder may drop activation frames on a busy
    # machine: they are newest-wins, services.transport.topics)
    estimated = re.search(r"estimated (\d+) frames", (tmp_path / "out" / "logs" / "estimator.log").read_text())
    assert estimated is not None and len(elbow) > 500 and int(estimated.group(1)) == len(elbow), (len(elbow), estimated)
    assert math.degrees(min(elbow)) < 25 and math.degrees(max(elbow)) > 115, (min(elbow), max(elbow))
