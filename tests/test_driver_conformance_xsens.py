"""The Xsens driver against a *different* device than our simulator: a minimal MTi imitation on a real
pseudo-terminal, written here from the protocol facts (../shared/protocols/xsens-xbus.md) with its own framing code.
It does what the facts allow and our simulator never does: replies from bus id 0x01, an ack echoing a configuration
other than the request, extended-length MTData2 with unknown items (GNSS PVT, satellite info, raw sensor readout),
NED fixed 16.32 orientation, Warning and Error messages between data, a WakeUp mid-stream (the device restarted),
bytes written in odd-sized pieces. Also: reconnection after an unplug, and the real recorded output configuration.
"""

from __future__ import annotations

import itertools
import logging
import os
import select
import struct
import threading
import time
import tty

import numpy as np
import pytest

from drivers.xsens import xbus
from drivers.xsens.device import DeviceStats, TrackerSet, XsensDevice
from drivers.xsens.serial_transport import SerialTransport
from drivers.xsens.simulator import XsensSimulator
from drivers.xsens.source import load_imu_source, synthetic_imu
from msk_core.errors import ProtocolError

DEVICE_ID = 0x03701234


def frame(bid: int, mid: int, data: bytes = b"") -> bytes:
    """Xbus frame, written independently of drivers.xsens.xbus: extended length above 254 bytes."""
    length = bytes([len(data)]) if len(data) < 255 else bytes([0xFF, len(data) >> 8, len(data) & 0xFF])
    body = bytes([bid, mid]) + length + data
    return b"\xfa" + body + bytes([(-sum(body)) & 0xFF])


def item(data_id: int, data: bytes) -> bytes:
    return struct.pack(">HB", data_id, len(data)) + data


def fp1632(values) -> bytes:
    out = b""
    for v in values:
        i = round(v * 2**32)
        out += struct.pack(">Ih", i & 0xFFFFFFFF, i >> 32)
    return out


def fp1220(values) -> bytes:
    return struct.pack(f">{len(values)}i", *[round(v * 2**20) for v in values])


QUAT_NED = (0.5, 0.5, -0.5, 0.5)  # any unit quaternion; fixed 16.32 carries it almost exactly
ACC = (0.125, -7.26, -1.2)
GYRO = (0.01, -0.02, 0.03)
MAG = (0.4, 0.1, -0.9)


def mtdata2(counter: int, stf0: int = 0) -> bytes:
    sample_time = (stf0 + 100 * counter) % 864_000_000  # 10 kHz ticks at 100 Hz; wraps after one day
    payload = item(0x1020, struct.pack(">H", counter)) + item(0x1060, struct.pack(">I", sample_time))
    payload += item(0x2016, fp1632(QUAT_NED))  # quaternion, NED (bits 3-2 = 0x4), fixed 16.32 (bits 1-0 = 2)
    payload += item(0x4023, struct.pack(">3d", *ACC))  # acceleration, float64
    payload += item(0x8021, fp1220(GYRO))  # rate of turn, fixed 12.20
    payload += item(0xC020, struct.pack(">3f", *MAG))
    payload += item(0xA010, bytes(range(9)))  # raw sensor readout: unknown to the driver, skipped by size
    if counter % 4 == 0:
        payload += item(0x7010, bytes(94))  # GNSS PVT at a quarter of the rate
        payload += item(0x7020, bytes(range(200)))  # satellite info: the message needs an extended length
    return payload


class FakeMti:
    """Answers configuration from bus id 0x01, echoes the configuration it applied (rates capped at 100 Hz), and
    after GoToMeasurement streams ``count`` messages with a restart (WakeUp, counter from 0) after ``restart_at``."""

    def __init__(
        self,
        *,
        count: int = 40,
        restart_at: int | None = 20,
        stf0: int = 0,
        pieces=(1, 7, 3, 64, 17, 250),
        device_id: bytes = struct.pack(">I", DEVICE_ID),
        garbage_at: int | None = None,
    ) -> None:
        self.device_id = device_id
        self.garbage_at = garbage_at  # a frame with a wrong checksum before this message (line noise)
        self.master, slave = os.openpty()
        tty.setraw(slave)
        self._slave = slave
        self.path = os.ttyname(slave)
        self.count, self.restart_at, self.stf0, self.pieces = count, restart_at, stf0, pieces
        self.received_mids: list[int] = []
        self.applied: list[tuple[int, int]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        os.close(self.master)
        os.close(self._slave)

    def _write(self, data: bytes) -> None:
        sizes = itertools.cycle(self.pieces)
        pos = 0
        while pos < len(data):
            size = next(sizes)
            os.write(self.master, data[pos : pos + size])
            pos += size
            time.sleep(0.0005)

    def _requests(self, buffer: bytearray):
        """Complete host frames (the host only sends short, standard-length frames)."""
        while True:
            start = buffer.find(b"\xfa")
            if start < 0 or len(buffer) - start < 4 or len(buffer) - start < 5 + buffer[start + 3]:
                return
            n = buffer[start + 3]
            mid, data = buffer[start + 2], bytes(buffer[start + 4 : start + 4 + n])
            del buffer[: start + 5 + n]
            yield mid, data

    def _run(self) -> None:
        buffer = bytearray()
        while not self._stop.is_set():
            if not select.select([self.master], [], [], 0.02)[0]:
                continue
            buffer += os.read(self.master, 4096)
            for mid, data in self._requests(buffer):
                self.received_mids.append(mid)
                self._answer(mid, data)

    def _answer(self, mid: int, data: bytes) -> None:
        if mid == 0x30:
            self._write(frame(0x01, 0x31))
        elif mid == 0x00:
            self._write(frame(0x01, 0x01, self.device_id))
        elif mid == 0x1C:
            self._write(frame(0x01, 0x1D, b"MTi-630-2A8G4\x00\x00"))
        elif mid == 0x12:
            self._write(frame(0x01, 0x13, bytes([1, 12, 0, 0, 0, 0, 0])))  # newer firmware sends build info too
        elif mid == 0x18 and not data:
            self._write(frame(0x01, 0x19, b"\x80"))
        elif mid == 0xC0:
            entries = [struct.unpack_from(">HH", data, k) for k in range(0, len(data), 4)]
            self.applied = [(i, f if f in (0, 0xFFFF) else min(f, 100)) for i, f in entries]
            self._write(frame(0x01, 0xC1, b"".join(struct.pack(">HH", i, f) for i, f in self.applied)))
        elif mid == 0x10:
            self._write(frame(0x01, 0x11))
            threading.Thread(target=self._stream, daemon=True).start()
        else:
            self._write(frame(0x01, 0x42, b"\x04"))

    def _stream(self) -> None:
        for k in range(self.count):
            restarted = self.restart_at is not None and k >= self.restart_at
            counter = k - self.restart_at if restarted else k
            if k == self.restart_at:
                self._write(frame(0xFF, 0x3E))  # WakeUp: the device restarted; no ack -> back to Measurement
            if k == 5:
                self._write(frame(0xFF, 0x43, struct.pack(">I", 0x1234)))  # a Warning between data
            if k == 25:
                self._write(frame(0xFF, 0x42, b"\x1e"))  # Error: timer overflow
            if k == self.garbage_at:
                bad = bytearray(frame(0xFF, 0x36, mtdata2(counter, self.stf0)))
                bad[-1] ^= 0xFF
                self._write(bytes(bad))
            self._write(frame(0xFF, 0x36, mtdata2(counter, self.stf0)))
            time.sleep(0.002)


def test_independent_device_bus_01_replies_modified_echo_extended_unknown_items_restart(caplog):
    fake = FakeMti()
    device = XsensDevice(SerialTransport(fake.path, baudrate=921600))
    try:
        with caplog.at_level(logging.WARNING, logger="drivers.xsens.device"):
            identity = device.configure(200, precision=xbus.Precision.FP1632, frame=xbus.CoordinateFrame.NED)
        assert identity["device_id"] == f"{DEVICE_ID:08X}" and identity["product_code"] == "MTi-630-2A8G4"
        assert identity["firmware"] == "1.12.0"
        # the ack echoes what was applied (rates capped at 100 Hz); the driver keeps that, and says so
        assert [(s.data_id, s.frequency) for s in device.output_configuration] == fake.applied
        assert all(s.frequency == 100 for s in device.output_configuration if s.frequency not in (0, 0xFFFF))
        assert "at 100 Hz instead of 200" in caplog.text
        readings = read_until(device, lambda got: len(got) >= fake.count)
    finally:
        device.close()
        fake.close()
    assert [r.packet_counter for r in readings] == list(range(20)) + list(range(20))
    first = readings[0]
    assert first.frame is xbus.CoordinateFrame.NED
    assert first.quaternion == pytest.approx(QUAT_NED, abs=2**-32)
    assert first.acceleration == ACC
    assert first.rate_of_turn == pytest.approx(GYRO, abs=2**-20)
    assert first.magnetic_field == pytest.approx(MAG, rel=1e-7)
    assert first.sample_time_fine == 0 and readings[3].device_time_ns == 3 * 100 * 100_000
    assert [(i, len(raw)) for i, raw in first.data.unknown] == [(0xA010, 9), (0x7010, 94), (0x7020, 200)]
    assert [i for i, _ in readings[1].data.unknown] == [0xA010]
    stats = device.stats
    assert stats.packets_lost == 0 and stats.restarts == 1 and stats.decode_errors == 0
    assert stats.device_errors == 1 and "timer overflow" in stats.last_error
    assert stats.device_warnings == 1  # the Warning at message 5: counted (it was dropped without a trace)
    assert device.parser.stats.errors == 0 and device.parser.stats.bytes_skipped == 0


def test_line_noise_does_not_hide_a_device_error_in_the_status():
    """Found by an independent imitation: "device error 0x28" and "device restarted" were replaced in last_error by
    "N bad Xbus frames so far" within a second. Line noise and warnings are said only over what they said themselves;
    their counts go on."""
    fake = FakeMti(restart_at=None, garbage_at=30)
    device, readings = readings_of(fake, baudrate=921600)
    assert len(readings) == fake.count  # every good frame; the corrupted copy before message 30 left out
    assert device.parser.stats.errors == 1 and device.stats.device_errors == 1
    assert device.stats.last_error == "device error 0x1E (timer overflow)", device.stats.last_error
    stats = DeviceStats()
    stats.note("3 bad Xbus frames so far", minor=True)
    stats.note("4 bad Xbus frames so far", minor=True)  # a minor message replaces its own kind
    assert stats.last_error == "4 bad Xbus frames so far"
    stats.note("device restarted (WakeUp while measuring)")
    stats.note("1 device warning(s) (Xbus Warning 0x43) so far, the last", minor=True)
    assert stats.last_error == "device restarted (WakeUp while measuring)"


def test_baudrate_request_to_independent_device_and_simulator():
    fake = FakeMti()
    device = XsensDevice(SerialTransport(fake.path))
    try:
        device.go_to_config()
        assert device.request_baudrate() == 921600  # code 0x80
    finally:
        device.close()
        fake.close()
    assert xbus.baud_code(115200) == 0x02 and xbus.baud_code(921600) == 0x80
    with pytest.raises(ProtocolError, match="no Xbus baud-rate code"):
        xbus.baud_code(1234)
    with XsensSimulator(synthetic_imu(seconds=1.0)) as sim:
        device = XsensDevice(SerialTransport(sim.path))
        device.reset()
        assert device.request_baudrate() == 115200
        device.close()


def test_simulator_accepts_the_real_recorded_output_configuration(shared_dir):
    """A real MTi-G-710 was configured with GNSS PVT (0x7010): a faithful device must accept it, not Error 0x21."""
    payload = (shared_dir / "data/xsens-captures/mtig710_set1_outputconfig.bin").read_bytes()
    recorded = xbus.decode_output_configuration(payload)
    assert 0x7010 in [s.data_id for s in recorded]
    # the fixed 12.20 capture (set 2) re-encoded in the float32 configuration of set 1
    source = load_imu_source(shared_dir / "data/xsens-captures/mtig710_set2.bin")
    with XsensSimulator(source, speed=4.0) as sim:
        device = XsensDevice(SerialTransport(sim.path))
        device.reset()
        assert device.set_output_configuration(recorded) == recorded
        device.go_to_measurement()
        readings = read_until(device, lambda got: len(got) >= 5)
        device.close()
    assert readings and readings[0].data.ids["euler"] == 0x2030 and readings[0].data.ids["acceleration"] == 0x4020
    assert readings[0].acceleration == pytest.approx(source.arrays["acceleration"][0], abs=1e-5)


def test_tracker_reconnects_after_unplug_through_a_stable_port_name(tmp_path):
    """/dev/serial/by-id names survive a replug while /dev/ttyUSBn may not: a symlink plays that stable name."""
    link = tmp_path / "usb-Xsens_MTi-G-710-if00"
    source = synthetic_imu(seconds=20.0)
    sim = XsensSimulator(source, speed=2.0, device_id=0x03700ABC, stable_link=link).start()
    trackers = TrackerSet(retry_interval_s=0.05)
    try:
        device = XsensDevice(SerialTransport(str(link), baudrate=921600))
        device.configure(100, precision=xbus.Precision.FP1220, frame=xbus.CoordinateFrame.NWU)
        trackers.add(device)
        before = read_until(trackers, lambda r: len(r) >= 20)
        sim.unplug()
        down = read_until(trackers, lambda r: "03700ABC" in trackers.disconnected, seconds=3)
        assert not trackers.devices
        deadline = time.monotonic() + 0.2
        while time.monotonic() < deadline:  # reconnection attempts fail while the device is away
            assert trackers.read() == []
            time.sleep(0.02)
        assert "03700ABC" in trackers.disconnected and "reconnect failed" in device.stats.last_error
        assert not link.exists()  # unplugged: udev removed the stable name
        sim = XsensSimulator(source, speed=2.0, device_id=0x03700ABC, stable_link=link).start()  # replugged
        after = read_until(trackers, lambda r: len(r) >= 20, seconds=8)
        connected = list(trackers.devices)
    finally:
        trackers.close()
        sim.close()
    assert len(before) >= 20 and len(after) >= 20
    assert {r.tracker_id for r in before + down + after} == {"03700ABC"}
    assert trackers.disconnected == {} and connected == ["03700ABC"]
    assert device.stats.reconnects == 1
    # reconfigured as before: fixed 12.20 orientation in NWU
    assert after[-1].frame is xbus.CoordinateFrame.NWU and after[-1].data.ids["quaternion"] == 0x2019
    assert [r.packet_counter for r in after[1:]] == [r.packet_counter + 1 for r in after[:-1]]


def test_reconnect_refuses_another_device_on_the_same_port(tmp_path):
    link = tmp_path / "tracker"
    source = synthetic_imu(seconds=5.0)
    sim = XsensSimulator(source, speed=2.0, device_id=0x03700001, stable_link=link).start()
    device = XsensDevice(SerialTransport(str(link)))
    device.configure(100)
    sim.unplug()
    other = XsensSimulator(source, speed=2.0, device_id=0x03700002, stable_link=link).start()
    try:
        with pytest.raises(ProtocolError, match="device 03700002 answered where 03700001 was"):
            device.reconnect()
    finally:
        device.close()
        other.close()
    assert device.tracker_id == "03700001" and device.stats.reconnects == 0


def _wait_attempts(trackers: TrackerSet, seconds: float = 5.0) -> None:
    deadline = time.monotonic() + seconds
    while trackers.reconnecting:
        assert time.monotonic() < deadline, f"reconnection attempts still under way after {seconds} s"
        time.sleep(0.005)


def test_a_tracker_that_answers_slowly_while_reconnecting_does_not_stall_the_others(tmp_path):
    """A port back whose device acknowledges GoToConfig and then nothing: its configure() asks each request three
    times (seconds). The reconnection used to run inside read(), so the other tracker's samples waited that long."""
    healthy = XsensSimulator(synthetic_imu(seconds=30.0), speed=1.0, device_id=0x03700002).start()
    link = tmp_path / "slow"
    lost = XsensSimulator(synthetic_imu(seconds=5.0), speed=2.0, device_id=0x03700001, stable_link=link).start()
    trackers = TrackerSet(retry_interval_s=0.01)
    master, slave = os.openpty()
    answering = threading.Event()
    try:
        for port in (healthy.path, str(link)):
            device = XsensDevice(SerialTransport(port))
            device.configure(100)
            trackers.add(device)
        read_until(trackers, lambda r: {x.tracker_id for x in r} == {"03700001", "03700002"})
        lost.unplug()
        read_until(trackers, lambda r: "03700001" in trackers.disconnected)
        tty.setraw(slave)

        def acknowledge_go_to_config_only() -> None:  # the device behind the port answers the probe, then stalls
            answering.set()
            while answering.is_set():
                if select.select([master], [], [], 0.05)[0] and xbus.encode_message(xbus.Mid.GO_TO_CONFIG) in (
                    os.read(master, 4096)
                ):
                    os.write(master, xbus.encode_message(xbus.Mid.GO_TO_CONFIG + 1))

        threading.Thread(target=acknowledge_go_to_config_only, daemon=True).start()
        link.symlink_to(os.ttyname(slave))
        started = time.monotonic()
        arrivals = []
        while time.monotonic() - started < 2.5:
            readings = trackers.read()
            arrivals += [time.monotonic() for r in readings if r.tracker_id == "03700002"]
        attempting = trackers.reconnecting
    finally:
        answering.clear()
        trackers.close()
        healthy.close()
        lost.close()
        os.close(master)
        os.close(slave)
    assert attempting == ["03700001"], "the slow device's attempt should still be under way"
    gaps = np.diff([started, *arrivals])
    assert len(arrivals) > 150 and gaps.max() < 0.5, (len(arrivals), gaps.max())  # 100 Hz went on, no stall


def readings_of(fake: FakeMti, **transport) -> tuple[XsensDevice, list]:
    """The device on ``fake``'s port configured at 100 Hz and every message it streams read, then both closed."""
    device = XsensDevice(SerialTransport(fake.path, **transport))
    try:
        device.configure(100)
        readings = read_until(device, lambda got: len(got) >= fake.count)
    finally:
        device.close()
        fake.close()
    return device, readings


def read_until(source: XsensDevice | TrackerSet, done, *, seconds: float = 5.0) -> list:
    """``source.read()`` until ``done(readings)`` or ``seconds`` pass."""
    readings: list = []
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        readings += source.read()
        if done(readings):
            break
    return readings


def test_sample_time_fine_wrapping_after_a_day_keeps_device_time_continuous():
    fake = FakeMti(count=30, restart_at=None, stf0=864_000_000 - 1000)  # wraps after 10 messages
    _, readings = readings_of(fake)
    ticks = [r.sample_time_fine for r in readings]
    assert len(readings) == 30 and ticks[9] == 863_999_900 and ticks[10] == 0
    times = [r.device_time_ns for r in readings]
    assert all(b - a == 100 * 100_000 for a, b in zip(times, times[1:]))


def test_eight_byte_device_id_is_kept_whole():
    fake = FakeMti(device_id=bytes.fromhex("0123456789ABCDEF"))
    device = XsensDevice(SerialTransport(fake.path))
    try:
        device.go_to_config()
        assert device.request_device_id() == 0x0123456789ABCDEF
        assert device.tracker_id == "0123456789ABCDEF"
    finally:
        device.close()
        fake.close()


@pytest.mark.parametrize("set_number", [1, 2, 3, 4])
def test_line_load_estimate_matches_the_real_captures(shared_dir, set_number):
    """The serial load predicted from a real output configuration vs the bytes the real device sent at 100 Hz."""
    folder = shared_dir / "data/xsens-captures"
    settings = xbus.decode_output_configuration((folder / f"mtig710_set{set_number}_outputconfig.bin").read_bytes())
    messages = xbus.iter_capture((folder / f"mtig710_set{set_number}.bin").read_bytes())[50:]  # filter running
    measured = 10 * 100 * sum(len(xbus.encode_message(m.mid, m.data)) for m in messages) / len(messages)
    predicted = xbus.output_bits_per_second(settings)
    assert measured <= predicted <= 1.05 * measured
    assert predicted > 115200  # that real configuration could not run at the factory baud rate


def test_configure_warns_when_the_outputs_exceed_the_baud_rate(caplog):
    with (
        XsensSimulator(synthetic_imu(seconds=2.0)) as sim,
        caplog.at_level(logging.WARNING, logger="drivers.xsens.device"),
    ):
        slow = XsensDevice(SerialTransport(sim.path, baudrate=115200))
        slow.configure(100, precision=xbus.Precision.FLOAT64)  # about 135 kbit/s
        assert "line carries 115 kbit/s" in slow.stats.last_error and "135 kbit/s" in caplog.text
        slow.close()
        caplog.clear()
        fast = XsensDevice(SerialTransport(sim.path, baudrate=921600))
        fast.configure(100, precision=xbus.Precision.FLOAT64)
        fast.close()
    assert "kbit/s" not in caplog.text and fast.stats.last_error == ""


def test_switching_the_baud_rate_through_a_reset():
    with XsensSimulator(synthetic_imu(seconds=2.0), speed=2.0) as sim:
        device = XsensDevice(SerialTransport(sim.path))  # factory 115200
        device.reset()
        with pytest.raises(ProtocolError, match="no Xbus baud-rate code"):
            device.set_baudrate(1000)
        device.set_baudrate(921600)
        assert device.transport.baudrate == 921600 and sim.baudrate == 921600
        assert device.request_baudrate() == 921600
        device.configure(100, precision=xbus.Precision.FLOAT64)  # fits at 921600: no line-capacity warning
        assert device.stats.last_error == ""
        readings = read_until(device, lambda got: len(got) >= 5)
        device.close()
    assert len(readings) >= 5


def test_a_port_back_without_its_device_is_probed_once_and_retried_ever_more_slowly(tmp_path):
    """A USB-serial converter can come back while the sensor behind it is off: a silent tty."""
    link = tmp_path / "tracker"
    sim = XsensSimulator(synthetic_imu(seconds=5.0), speed=2.0, device_id=0x03700001, stable_link=link).start()
    trackers = TrackerSet(retry_interval_s=0.01, retry_max_s=0.04)
    device = XsensDevice(SerialTransport(str(link)))
    device.configure(100)
    trackers.add(device)
    read_until(trackers, lambda r: len(r) >= 3)
    sim.unplug()
    read_until(trackers, lambda r: "03700001" in trackers.disconnected)
    master, slave = os.openpty()  # the silent port
    tty.setraw(slave)
    link.symlink_to(os.ttyname(slave))
    try:
        delays = []
        for _ in range(4):
            trackers._next_attempt["03700001"] = 0.0  # attempt now
            assert trackers.read() == []  # starts the attempt in its thread
            _wait_attempts(trackers)
            assert trackers.read() == []  # takes its outcome
            delays.append(trackers.retry_delay("03700001"))
        time.sleep(0.05)
        received = os.read(master, 4096)
    finally:
        trackers.close()
        os.close(master)
        os.close(slave)
    assert delays == [0.02, 0.04, 0.04, 0.04]  # doubling, capped
    # each attempt sent exactly one GoToConfig probe and gave up: no full configure() against a silent port
    assert received == xbus.encode_message(xbus.Mid.GO_TO_CONFIG) * 4
    assert "reconnect failed" in device.stats.last_error and "03700001" in trackers.disconnected


def test_capture_with_two_bus_ids_and_a_cut_last_frame_keeps_one_tracker(tmp_path, caplog):
    own = [frame(0xFF, 0x36, mtdata2(k)) for k in range(6)]
    other = [frame(0x02, 0x36, mtdata2(100 + k)) for k in range(6)]
    stream = b"".join(a + b for a, b in zip(own, other)) + own[0][:20]
    path = tmp_path / "two_trackers.bin"
    path.write_bytes(stream)
    with caplog.at_level(logging.WARNING, logger="drivers.xsens.source"):
        source = load_imu_source(path)
    assert [xbus.decode_mtdata2(p).first("packet_counter") for p in source.raw_payloads] == list(range(6))
    assert source.rate_hz == pytest.approx(100.0)  # SampleTimeFine steps of 100 ticks
    assert "bus ids [2, 255]; using 0xFF only" in caplog.text and "20 trailing bytes" in caplog.text
