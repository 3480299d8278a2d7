"""What a real MTi does that a well-behaved simulator does not (found with an independent device imitation): late
GNSS samples across the SampleTimeFine wrap, a restart whose WakeUp is lost, a timer-overflow Error while a request
waits, another device on the port at reconnection, orientation given as a rotation matrix or Euler angles."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.xsens import frames, xbus
from drivers.xsens.device import SAMPLE_TIME_FINE_DAY, TrackerSet, XsensDevice

COUNTER, TIME = 0x1020, 0x1060
QUATERNION, MATRIX, EULER = 0x2010, 0x2020, 0x2030


class ScriptedLine:
    """A transport that hands the device the bytes queued for it, and answers requests from a script."""

    name = "scripted"

    def __init__(self, replies: dict[int, list[bytes]] | None = None) -> None:
        self.incoming = bytearray()
        self.replies = replies or {}
        self.written: list[int] = []

    def feed(self, *messages: bytes) -> None:
        for message in messages:
            self.incoming += message

    def read(self, max_bytes: int = 4096) -> bytes:
        out = bytes(self.incoming[:max_bytes])
        del self.incoming[:max_bytes]
        return out

    def write(self, data: bytes) -> None:
        mid = data[2]
        self.written.append(mid)
        for reply in self.replies.get(mid, []):
            self.incoming += reply

    def close(self) -> None:
        pass


def data_message(counter: int | None, sample_time: int | None, **orientation) -> bytes:
    items: list[tuple[int, object]] = []
    if counter is not None:
        items.append((COUNTER, (counter,)))
    if sample_time is not None:
        items.append((TIME, (sample_time,)))
    items += [(data_id, values) for data_id, values in orientation.values()]
    return xbus.encode_message(xbus.Mid.MT_DATA2, xbus.encode_mtdata2(items))


def test_a_late_gnss_sample_across_the_day_wrap_keeps_the_clock_and_the_newest_time():
    """An MTi-G's GNSS message carries a SampleTimeFine ~50 ms older than the message before it; when the day's wrap
    falls between them, the time went a day ahead for good (86400.005 s, then 172799.963 s)."""
    line, day = ScriptedLine(), SAMPLE_TIME_FINE_DAY
    device = XsensDevice(line)
    times = [day - 100, 50, day - 420, 150, 250]  # 0.01 s before the wrap, just after it, a late one from before
    line.feed(*(data_message(k, t) for k, t in enumerate(times)))
    seconds = [r.device_time_ns / 1e9 for r in device.read()]
    expected = [(day - 100) / 1e4, (day + 50) / 1e4, (day - 420) / 1e4, (day + 150) / 1e4, (day + 250) / 1e4]
    assert seconds == pytest.approx(expected, abs=1e-9)
    assert device.stats.restarts == 0 and device.stats.packets_lost == 0


def test_a_late_sample_does_not_move_the_clock_back_for_the_wrap_that_follows():
    line, day = ScriptedLine(), SAMPLE_TIME_FINE_DAY
    device = XsensDevice(line)
    line.feed(*(data_message(k, t) for k, t in enumerate([day - 300, day - 200, day - 700, day - 100, 0, 100])))
    seconds = [r.device_time_ns / 1e9 for r in device.read()]
    assert seconds == pytest.approx([(day - 300) / 1e4, (day - 200) / 1e4, (day - 700) / 1e4, (day - 100) / 1e4,
                                     day / 1e4, (day + 100) / 1e4], abs=1e-9)  # fmt: skip


def test_a_restart_whose_wakeup_was_lost_is_a_restart_not_65386_lost_packets():
    line = ScriptedLine()
    device = XsensDevice(line)
    line.feed(*(data_message(k, 5_000_000 + 100 * k) for k in range(150)))
    line.feed(*(data_message(k, 100 * k) for k in range(20)))  # counter and clock start again, no WakeUp seen
    readings = device.read()
    assert device.stats.packets_lost == 0 and device.stats.restarts == 1
    assert "device restarted" in device.stats.last_error and "WakeUp was not received" in device.stats.last_error
    assert readings[150].device_time_ns == 0 and readings[-1].device_time_ns == 19 * 100 * 100_000
    line.feed(data_message(21, 2100))  # one lost after the restart is counted as such
    device.read()
    assert device.stats.packets_lost == 1


def test_a_counter_wrap_with_losses_is_still_counted_as_losses():
    line = ScriptedLine()
    device = XsensDevice(line)
    line.feed(*(data_message(c, 100 * k) for k, c in enumerate([65533, 65534, 2, 3])))
    device.read()
    assert device.stats.packets_lost == 3 and device.stats.restarts == 0


def test_a_timer_overflow_error_while_a_request_waits_is_counted_and_the_reply_still_taken():
    """A device already measuring sent Error 0x1E (timer overflow) before its GoToConfigAck: the start failed."""
    error = xbus.encode_message(xbus.Mid.ERROR, bytes((0x1E,)))
    ack = xbus.encode_message(xbus.Mid.GO_TO_CONFIG + 1)
    line = ScriptedLine({xbus.Mid.GO_TO_CONFIG: [error, ack]})
    device = XsensDevice(line, reply_timeout_s=0.2)
    device.go_to_config()
    assert device.stats.device_errors == 1 and "0x1E (timer overflow) while measuring" in device.stats.last_error
    refused = ScriptedLine({xbus.Mid.GO_TO_CONFIG: [xbus.encode_message(xbus.Mid.ERROR, bytes((0x04,)))]})
    with pytest.raises(xbus.ProtocolError, match="0x04"):  # an error that answers the request still ends it
        XsensDevice(refused, reply_timeout_s=0.2).go_to_config()


def _rotation_matrix_column_by_column(q) -> tuple[float, ...]:
    w, x, y, z = q
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return tuple(float(rows[r][c]) for c in range(3) for r in range(3))


def test_orientation_given_as_rotation_matrix_or_euler_angles_becomes_the_quaternion():
    """A device that applied these instead of the quaternion asked for (and the real MTi-G-710 captures, which carry
    Euler angles only): 0 of 200 samples had an orientation."""
    rng = np.random.default_rng(4)
    line = ScriptedLine()
    device = XsensDevice(line)
    truths = []
    for k in range(40):
        q = rng.normal(size=4)
        q = tuple(float(v) for v in (q if q[0] >= 0 else -q) / np.linalg.norm(q))
        truths.append(q)
        if k % 2:
            line.feed(data_message(k, 100 * k, o=(MATRIX, _rotation_matrix_column_by_column(q))))
        else:  # Euler angles of q: roll about x, then pitch about y, then yaw about z (global axes)
            w, x, y, z = q
            roll = math.degrees(math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)))
            pitch = math.degrees(math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x)))))
            yaw = math.degrees(math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))
            line.feed(data_message(k, 100 * k, o=(EULER | 0x3, (roll, pitch, yaw))))  # float64
    readings = device.read()
    assert len(readings) == 40
    for reading, truth in zip(readings, truths, strict=True):
        assert abs(float(np.dot(reading.quaternion, truth))) == pytest.approx(1.0, abs=1e-6)
    line.feed(data_message(41, 4100))  # a message without any orientation (an MTi-G's GNSS message) stays without
    assert device.read()[0].quaternion is None
    assert frames.quat_from_rotation_matrix((1, 0, 0, 0, 1, 0, 0, 0, 1)) == (1.0, 0.0, 0.0, 0.0)


class Reopens(ScriptedLine):
    """A port that comes back with another device behind it."""

    def __init__(self, replies) -> None:
        super().__init__(replies)

    def reopen(self) -> Reopens:
        return self


def test_another_device_at_reconnection_is_refused_before_it_is_configured():
    """It used to be sent SetOutputConfiguration and GoToMeasurement (a real MTi stores the outputs), then refused."""
    ack = {mid: [xbus.encode_message(mid + 1)] for mid in (xbus.Mid.GO_TO_CONFIG, xbus.Mid.GO_TO_MEASUREMENT)}
    other = Reopens(ack | {xbus.Mid.REQ_DID: [xbus.encode_message(xbus.Mid.REQ_DID + 1, bytes.fromhex("0388FFFF"))]})
    device = XsensDevice(other, reply_timeout_s=0.2)
    device.device_id, device.device_id_size = 0x03700ABC, 4
    device._configured = (100, xbus.Precision.FLOAT32, xbus.CoordinateFrame.ENU)
    with pytest.raises(xbus.ProtocolError, match="device 0388FFFF answered where 03700ABC was; left unconfigured"):
        device.reconnect()
    assert xbus.Mid.SET_OUTPUT_CONFIGURATION not in other.written and xbus.Mid.GO_TO_MEASUREMENT not in other.written
    assert device.tracker_id == "03700ABC"


def test_a_reconnect_failure_is_forgotten_once_the_tracker_is_back():
    trackers = TrackerSet()
    device = XsensDevice(ScriptedLine())
    device.stats.last_error = "reconnect failed: cannot open serial port /dev/ttyUSB0"
    trackers._lost["T"], trackers._next_attempt["T"], trackers._delay["T"] = device, 0.0, 0.5
    trackers.disconnected["T"] = "unplugged"

    class Done:
        def is_alive(self) -> bool:
            return False

    trackers._attempts["T"], trackers._failures["T"] = Done(), None  # the attempt ended with the device back
    trackers._try_reconnect()
    assert trackers.devices == {"T": device} and device.stats.last_error == ""


def test_one_sample_without_orientation_is_no_fault_a_run_of_them_is_said_and_taken_back():
    """The real MTi-G-710's first message and its GNSS messages carry no orientation: one such sample left a false
    "carry no orientation" in the tracker's status for the rest of the session."""
    from types import SimpleNamespace

    from services.nodes import driver_nodes

    device = XsensDevice(ScriptedLine())
    without: dict[str, int] = {}

    def reading(oriented: bool):
        return SimpleNamespace(tracker_id="T", quaternion=(1.0, 0.0, 0.0, 0.0) if oriented else None)

    for oriented in [False] + [True] * 5 + [False] * (driver_nodes.NO_ORIENTATION_READINGS - 1) + [True]:
        driver_nodes._count_orientation(reading(oriented), without, device)
    assert device.stats.last_error == ""
    for _ in range(driver_nodes.NO_ORIENTATION_READINGS):
        driver_nodes._count_orientation(reading(False), without, device)
    assert "tracker T: its samples carry no orientation" in device.stats.last_error
    driver_nodes._count_orientation(reading(True), without, device)
    assert device.stats.last_error == ""
    assert (
        driver_nodes._tracker_error("unplugged", "reconnect failed: no reply")
        == "unplugged; reconnect failed: no reply"
    )
    assert (
        driver_nodes._tracker_error(None, "x") == "x" and driver_nodes._tracker_error("unplugged", "x") == "unplugged"
    )


def test_a_late_sample_across_the_wrap_of_a_clock_that_counts_past_a_day():
    """Devices whose SampleTimeFine goes past a day wrap at 2^32; after the wrap the newest time is small again, and a
    late sample from before it was judged with the day's period."""
    line, top = ScriptedLine(), 1 << 32
    device = XsensDevice(line)
    times = [top - 100, 50, top - 420, 150]
    line.feed(*(data_message(k, t) for k, t in enumerate(times)))
    seconds = [r.device_time_ns / 1e9 for r in device.read()]
    assert seconds == pytest.approx([(top - 100) / 1e4, (top + 50) / 1e4, (top - 420) / 1e4, (top + 150) / 1e4])


@pytest.mark.parametrize("capture", ["mtig710_set1.bin", "mtig710_set2.bin", "mtig710_set3.bin", "mtig710_set4.bin"])
def test_the_real_captures_euler_angles_turn_their_accelerometer_into_gravity_up(shared_dir, capture):
    """The driver path on the real MTi-G-710's own bytes (Euler angles, no quaternion): the orientation it makes turns
    the device's accelerometer reading at rest into gravity, up, in ENU, which checks the Euler convention on the
    device's data rather than on this code's own inverse."""
    line = ScriptedLine()
    device = XsensDevice(line)
    line.feed((shared_dir / "data" / "xsens-captures" / capture).read_bytes())
    readings = []
    while line.incoming:  # 4 kB a read, as from a serial port
        readings += [r for r in device.read() if r.quaternion is not None and r.acceleration is not None]
    assert len(readings) >= 90
    up = np.array([frames.rotate(r.quaternion_enu(), r.acceleration) for r in readings])
    assert np.allclose(up.mean(axis=0), (0.0, 0.0, 9.79), atol=0.05), up.mean(axis=0)


def test_the_real_mti_gs_gnss_messages_are_recorded_in_their_count_not_dropped_as_a_loss(shared_dir):
    """The real MTi-G-710 sends a GNSS message (PVT, no orientation) every ~25 samples, numbered by the same
    PacketCounter. The recorder and the kinematics refused those as "no orientation": every one a dropped input, and the
    counter stepping by 2 around it, which the session report counted as a lost sample (4 % of a tracker's samples
    "lost" that the device never lost). Now they are taken as the device's own messages with no pose in them."""
    from services.nodes import driver_nodes, kinematics_node, node_runtime
    from services.transport import topics

    line = ScriptedLine()
    device = XsensDevice(line)
    line.feed((shared_dir / "data" / "xsens-captures" / "mtig710_set1.bin").read_bytes())
    readings = []
    while line.incoming:  # 4 kB a read, as from a serial port
        readings += device.read()
    without = [r for r in readings if r.quaternion is None]
    assert len(readings) == 100 and len(without) == 5  # the capture: its first message and four GNSS messages
    node = kinematics_node.KinematicsNode(
        kinematics_node.KinematicsSettings(pack="bench_press", session="s", static_s=0.2, clock="device"),
        kinematics_node.KinematicsStats(),
    )
    segments = list(node.mapper.segments)
    for reading in readings:  # the one device worn on every segment the pack needs, as that many trackers
        for k, segment in enumerate(segments):
            key = topics.imu_key("s", f"T{k}")
            checked = node_runtime.check_payload(
                key, driver_nodes.imu_sample(reading, segment=segment).SerializeToString()
            )
            node.handle(key, checked)
    stats = node.stats
    assert stats.rejected == 0 and stats.without_orientation == 5 * len(segments), stats
    assert stats.frames_synced >= 90 and stats.resumes == 0 and stats.restarts == 0, stats
    counters = [r.packet_counter for r in readings]  # what the recording holds, in the report's loss count
    assert np.all(np.diff(counters) % 65536 == 1)


def test_without_a_packet_counter_losses_are_counted_by_the_devices_own_period():
    """A device without PacketCounter: losses come from SampleTimeFine steps. A review found the configured rate taken
    as the period, so a tracker sending slower than configured (an Awinda MTw's rate limit: 50 Hz for 100 asked)
    counted every message as one lost; late GNSS messages and a restart of the clock must count nothing either."""
    line = ScriptedLine()
    device = XsensDevice(line)
    device.output_configuration = [xbus.OutputSetting(0x1060, 100), xbus.OutputSetting(QUATERNION, 100)]
    q = {"q": (QUATERNION, (1.0, 0.0, 0.0, 0.0))}
    times = [1000 + 200 * k for k in range(40)]  # 50 Hz: a step of 200 ticks
    del times[20:23]  # three messages lost on the line
    times.insert(10, times[9] - 450)  # a late GNSS-like message, 45 ms older than the one before
    line.feed(*(data_message(None, t, **q) for t in times))
    while line.incoming:
        device.read()
    assert device.stats.packets_lost == 3, device.stats
    line.feed(*(data_message(None, 500 + 200 * k, **q) for k in range(10)))  # the clock starts again (a restart)
    while line.incoming:
        device.read()
    assert device.stats.packets_lost == 3, device.stats
