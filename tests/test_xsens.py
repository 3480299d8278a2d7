"""Xsens driver against the pseudo-terminal simulator: configuration, every precision/frame, verbatim replay of a
real capture, injected faults, unplugging, several trackers; USB discovery helpers."""

from __future__ import annotations

import os
import re
import time

import numpy as np
import pytest

from drivers.xsens import usb, xbus
from drivers.xsens.device import TrackerSet, XbusDeviceError, XsensDevice, output_settings
from drivers.xsens.serial_transport import DeviceDisconnected, SerialTransport
from drivers.xsens.simulator import FaultConfig, XsensSimulator
from drivers.xsens.source import load_imu_source, synthetic_imu
from msk_core.errors import ConfigError, FileFormatError, InputError, ProtocolError
from tests.test_xbus import STEP


def read_for(device: XsensDevice, *, count: int = 0, seconds: float = 5.0) -> list:
    readings = []
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and (not count or len(readings) < count):
        readings += device.read()
    return readings


def open_device(sim: XsensSimulator) -> XsensDevice:
    return XsensDevice(SerialTransport(sim.path, baudrate=921600))


def configured_readings(sim: XsensSimulator, count: int) -> tuple[XsensDevice, list]:
    """The simulator's device reset, configured at 100 Hz and read for ``count`` readings; the device closed after."""
    device = open_device(sim)
    try:
        device.reset()
        device.configure(100)
        return device, read_for(device, count=count)
    finally:
        device.close()


@pytest.mark.parametrize("precision", list(xbus.Precision))
@pytest.mark.parametrize("frame", [xbus.CoordinateFrame.ENU, xbus.CoordinateFrame.NED, xbus.CoordinateFrame.NWU])
def test_configure_and_measure_every_precision_and_frame(precision, frame):
    source = synthetic_imu(seconds=5.0, seed=1)
    with XsensSimulator(source, speed=4.0, device_id=0x03700123) as sim:
        device = open_device(sim)
        try:
            assert device.reset() is True  # WakeUp acknowledged: stays in Config
            info = device.configure(100, precision=precision, frame=frame)
            readings = read_for(device, count=40)
        finally:
            device.close()
    assert (
        info["device_id"] == "03700123" and info["product_code"].startswith("MTi-G-710") and info["firmware"] == "1.8.2"
    )
    assert info["outputs"] == output_settings(100, precision=precision, frame=frame)
    assert len(readings) >= 40 and device.stats.packets_lost == 0 and device.stats.decode_errors == 0
    step = STEP[precision]
    for reading in readings:
        k = reading.packet_counter  # the simulator's counter is the recording's sample index here
        assert reading.tracker_id == "03700123" and reading.frame is frame
        assert reading.quaternion_enu() == pytest.approx(tuple(source.arrays["quaternion"][k]), abs=4 * step)
        assert reading.acceleration == pytest.approx(tuple(source.arrays["acceleration"][k]), abs=10 * step)
        assert reading.device_time_ns == round(k * 1e4 / 100) * 100_000


class LosesRequests:
    """A serial line that loses the first ``count`` requests of message id ``mid`` on their way to the device."""

    def __init__(self, transport: SerialTransport, mid: int, count: int) -> None:
        self.transport, self.mid, self.count = transport, mid, count

    def write(self, data: bytes) -> None:
        if data[2] == self.mid and self.count > 0:
            self.count -= 1
            return
        self.transport.write(data)

    def __getattr__(self, name: str):
        return getattr(self.transport, name)


@pytest.mark.parametrize("lost, identified", [(2, True), (3, False)])
def test_a_lost_query_is_asked_again_before_the_device_is_given_up(lost, identified):
    """msk live stopped when one tracker's ReqDID went unanswered for 1 s (the simulator busy on a loaded host)."""
    with XsensSimulator(synthetic_imu(seconds=5.0), speed=4.0, device_id=0x03700123) as sim:
        device = XsensDevice(LosesRequests(SerialTransport(sim.path, baudrate=921600), xbus.Mid.REQ_DID, lost))
        device.reply_timeout_s = 0.3
        try:
            if identified:
                assert device.configure(100)["device_id"] == "03700123"
                assert device.stats.requests_repeated == lost and len(read_for(device, count=10)) >= 10
            else:
                said = rf"{re.escape(sim.path)}: no reply 0x01 to REQ_DID within 0.3 s \(received 0 bytes\) \(asked 3 times\)"
                with pytest.raises(ProtocolError, match=said):
                    device.configure(100)
        finally:
            device.close()


def test_an_unanswered_request_says_what_came_instead():
    """A device that streams but never answers (its requests lost, a wrong bus id) said only "no reply"; the error
    now counts what arrived meanwhile, so a measuring device, line noise and silence read differently."""
    with XsensSimulator(synthetic_imu(seconds=5.0), speed=4.0, wakeup_window_s=0.1) as sim:
        device = XsensDevice(LosesRequests(SerialTransport(sim.path, baudrate=921600), xbus.Mid.GO_TO_CONFIG, 99))
        device.reply_timeout_s = 0.3
        try:
            read_for(device, count=5)  # measuring with the factory outputs
            with pytest.raises(
                ProtocolError, match=r"within 0.3 s \(received \d+ bytes: \d+ Xbus messages \(\d+ MT_DATA2\)"
            ):
                device.request(xbus.Mid.GO_TO_CONFIG)
        finally:
            device.close()


class LosesAcks:
    """A serial line that loses the device's GoToMeasurementAck (FA FF 11 00 F0) on its way to us."""

    ACK = bytes([0xFA, 0xFF, 0x11, 0x00, 0xF0])

    def __init__(self, transport: SerialTransport) -> None:
        self.transport = transport

    def read(self, size: int) -> bytes:
        return self.transport.read(size).replace(self.ACK, b"")

    def __getattr__(self, name: str):
        return getattr(self.transport, name)


def test_a_lost_measurement_ack_with_data_flowing_is_measuring():
    """An independent imitation whose GoToMeasurement ack came late was given up (exit 2) while it streamed."""
    with XsensSimulator(synthetic_imu(seconds=5.0), speed=4.0, device_id=0x03700123) as sim:
        device = XsensDevice(LosesAcks(SerialTransport(sim.path, baudrate=921600)), reply_timeout_s=0.3)
        try:
            assert device.configure(100)["device_id"] == "03700123"
            assert len(read_for(device, count=10)) >= 10
        finally:
            device.close()


class WrongBaud:
    """What a port opened at another baud rate than the device's reads: bytes, never an Xbus frame."""

    name, baudrate = "/dev/ttyUSB9", 921600

    def write(self, data: bytes) -> None:
        pass

    def read(self, size: int) -> bytes:
        time.sleep(0.01)
        return bytes([0x80, 0x00, 0xF8, 0x78, 0x80, 0x00])


def test_a_port_at_another_baud_rate_than_the_device_is_named_as_such():
    device = XsensDevice(WrongBaud(), reply_timeout_s=0.2)
    with pytest.raises(ProtocolError, match=r"bytes but no Xbus frame: is the device's baud rate 921600\?"):
        device.go_to_config()


def test_without_wakeup_ack_the_device_measures_with_factory_outputs():
    with XsensSimulator(synthetic_imu(seconds=5.0), speed=4.0, wakeup_window_s=0.1) as sim:
        device = open_device(sim)
        readings = read_for(device, count=10)
        device.close()
    assert readings and all(r.quaternion is not None and r.acceleration is None for r in readings)


def test_real_capture_is_replayed_verbatim_until_reconfigured(shared_dir):
    path = shared_dir / "data/xsens-captures/mtig710_set3.bin"
    source = load_imu_source(path)
    assert source.rate_hz == pytest.approx(100.0) and len(source.raw_payloads) == 100
    with XsensSimulator(source, speed=5.0, wakeup_window_s=0.05) as sim:
        device = open_device(sim)
        readings = read_for(device, count=30)
        device.go_to_config()
        applied = device.set_output_configuration(output_settings(50, precision=xbus.Precision.FLOAT64))
        device.go_to_measurement()
        reencoded = read_for(device, count=10)
        device.close()
    original = {xbus.decode_mtdata2(p).first("packet_counter"): xbus.decode_mtdata2(p) for p in source.raw_payloads}
    for reading in readings:
        assert reading.data == original[reading.packet_counter]  # the device's own bytes, fixed 16.32
    assert xbus.precision_of(readings[1].data.ids["acceleration"]) is xbus.Precision.FP1632
    assert applied[2].frequency == 50
    # after reconfiguration: values re-encoded as float64 from the recording, the quaternion asked for from the
    # recording's Euler angles (it has no quaternion of its own), as the device computes both from one orientation
    assert all(r.quaternion is not None and r.acceleration is not None for r in reencoded)
    for r in reencoded:  # one of the recording's orientations (the counter restarts with the new configuration)
        assert np.max(np.abs(source.arrays["quaternion"] @ np.asarray(r.quaternion))) > 1 - 1e-9
    assert xbus.precision_of(reencoded[0].data.ids["acceleration"]) is xbus.Precision.FLOAT64


def test_device_error_reply_raises_with_code_name():
    with XsensSimulator(synthetic_imu(seconds=2.0), speed=2.0, wakeup_window_s=0.05) as sim:
        device = open_device(sim)
        time.sleep(0.1)
        with pytest.raises(XbusDeviceError, match="0x04 \\(invalid message\\).*SET_OUTPUT_CONFIGURATION"):
            device.set_output_configuration(output_settings(100))  # not allowed in Measurement state
        device.close()


def test_injected_faults_every_intact_message_recovered_and_corrupted_counted():
    faults = FaultConfig(bit_flip=0.05, drop_byte=0.05, garbage=0.05, unplug_after_messages=600, seed=11)
    source = synthetic_imu(seconds=10.0, seed=3)
    with XsensSimulator(source, speed=10.0, faults=faults) as sim:
        device = open_device(sim)
        device.reset()
        device.configure(100, precision=xbus.Precision.FP1220)
        readings = []
        with pytest.raises(DeviceDisconnected):
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline:
                readings += device.read()
        stats = sim.stats
    corrupted = set(stats.corrupted_counters)
    assert stats.messages_sent == 600 and len(corrupted) > 30 and stats.garbage_inserts > 10
    assert [r.packet_counter for r in readings] == [k for k in range(600) if k not in corrupted]
    # the last message may be the corrupted one: lost packets are counted from counter jumps
    trailing = sum(1 for k in range(599, -1, -1) if k in corrupted and all(j in corrupted for j in range(k, 600)))
    assert device.stats.packets_lost == len(corrupted) - trailing
    assert device.parser.stats.errors >= len(corrupted) - trailing
    # the errors are described for the status, not only counted (they were: last_error stayed empty)
    assert re.search(r"^\d+ bad Xbus frames so far \(checksum \d+.*\); \d+ bytes skipped", device.stats.last_error)


def test_tracker_set_keys_devices_by_id_and_survives_an_unplug():
    source = synthetic_imu(seconds=5.0)
    with (
        XsensSimulator(source, speed=4.0, device_id=0x00B41001) as sim_a,
        XsensSimulator(source, speed=4.0, device_id=0x00B41002) as sim_b,
    ):
        trackers = TrackerSet()
        for sim in (sim_a, sim_b):
            device = open_device(sim)
            device.reset()
            device.configure(100)
            trackers.add(device)
        assert sorted(trackers.devices) == ["00B41001", "00B41002"]
        seen = set()
        deadline = time.monotonic() + 5
        while len(seen) < 2 and time.monotonic() < deadline:
            seen |= {r.tracker_id for r in trackers.read()}
        sim_a.unplug()
        later = []
        deadline = time.monotonic() + 5
        while len(later) < 20 and time.monotonic() < deadline:
            later += trackers.read()
        trackers.close()
    assert seen == {"00B41001", "00B41002"}
    assert "00B41001" in trackers.disconnected and {r.tracker_id for r in later} == {"00B41002"}


class FallsSilent:
    """A serial line on which the device stops streaming while its port stays open (found by an independent
    imitation: the status said connected, 0 errors, through 7 s of silence)."""

    def __init__(self, transport: SerialTransport) -> None:
        self.transport, self.silent = transport, False

    def read(self, size: int) -> bytes:
        data = self.transport.read(size)
        return b"" if self.silent else data

    def __getattr__(self, name: str):
        return getattr(self.transport, name)


def test_a_tracker_that_stops_streaming_is_lost_with_the_reason_and_the_others_read_on():
    source = synthetic_imu(seconds=10.0)
    with (
        XsensSimulator(source, speed=1.0, device_id=0x00B41001) as sim_a,
        XsensSimulator(source, speed=1.0, device_id=0x00B41002) as sim_b,
    ):
        trackers = TrackerSet(reconnect=False, stall_s=0.5)
        line = FallsSilent(SerialTransport(sim_a.path, baudrate=921600))
        for device in (XsensDevice(line), open_device(sim_b)):
            device.configure(100)
            trackers.add(device)
        assert len(read_for(trackers, count=20)) >= 20
        line.silent = True
        started, later = time.monotonic(), []
        while "00B41001" not in trackers.disconnected and time.monotonic() - started < 5:
            later += trackers.read()
        noticed_s = time.monotonic() - started
        later += read_for(trackers, count=20)
        trackers.close()
    assert noticed_s < 2.0, noticed_s  # its stall_s (0.5 s) after its last reading, which came before the silence
    said = re.search(r"no reading from tracker 00B41001 for ([\d.]+) s", trackers.disconnected["00B41001"])
    assert said is not None and float(said.group(1)) >= 0.5, trackers.disconnected
    assert "it stopped streaming" in trackers.disconnected["00B41001"]
    assert "00B41002" in {r.tracker_id for r in later[-20:]}


def test_imu_npz_source_and_errors(tmp_path):
    path = tmp_path / "imu.npz"
    q = np.tile([1.0, 0.0, 0.0, 0.0], (50, 1))
    np.savez(path, rate_hz=60.0, quaternion=q, acceleration=np.zeros((50, 3)))
    source = load_imu_source(path)
    assert source.rate_hz == 60.0 and set(source.arrays) == {"quaternion", "acceleration"}
    bad = tmp_path / "bad.npz"
    np.savez(bad, rate_hz=60.0, quaternion=np.zeros((50, 3)))
    with pytest.raises(FileFormatError, match="field 'quaternion'"):
        load_imu_source(bad)
    with pytest.raises(InputError, match="not found"):
        load_imu_source(tmp_path / "none.bin")


def test_usb_identities_and_port_matching():
    assert usb.classify(0x2639, 0x0017) == "MTi-G-700 (native USB)"
    assert usb.classify(0x2639, 0x0101) == "Awinda Station"
    assert usb.classify(0x0403, 0xD38D) == "Awinda Station (FTDI)"
    assert usb.classify(0x0403, 0x6001) is None and usb.classify(0x1234, 0x0001) is None
    devices = [usb.UsbDevice(0x2639, 0x0200, "MTw", "A1"), usb.UsbDevice(0x2639, 0x0200, "MTw", "B2")]
    ports = [
        usb.PortInfo("/dev/ttyUSB1", 0x2639, 0x0200, "B2"),
        usb.PortInfo("/dev/ttyUSB0", 0x2639, 0x0200, "A1"),
        usb.PortInfo("/dev/ttyUSB2", 0x0403, 0xD388, "X"),
        usb.PortInfo("/dev/ttyS0", None, None),
    ]
    matched = usb.match_ports(devices, ports)
    assert [(d.serial_number, d.port) for d in matched] == [
        ("A1", "/dev/ttyUSB0"),
        ("B2", "/dev/ttyUSB1"),
        ("X", "/dev/ttyUSB2"),
    ]
    assert isinstance(usb.list_devices(), list)  # real enumeration runs (no Xsens hardware on CI)


def test_usb_find_port_without_devices_is_a_clear_error(monkeypatch):
    monkeypatch.setattr(usb, "list_devices", lambda: [])
    with pytest.raises(ConfigError, match="no Xsens device"):
        usb.find_port()


def _capture_without_time(path, n: int = 20) -> None:
    """A capture of quaternion-only MTData2 messages (no SampleTimeFine): the rate is not in the data."""
    frames = []
    for k in range(n):
        angle = 0.01 * k
        payload = xbus.encode_mtdata2([(0x2010, [np.cos(angle), np.sin(angle), 0.0, 0.0])])
        frames.append(xbus.encode_message(0x36, payload))
    path.write_bytes(b"".join(frames))


def test_capture_rate_from_time_else_output_configuration_else_default_with_warning(tmp_path, caplog):
    path = tmp_path / "quat_only.bin"
    _capture_without_time(path)
    with caplog.at_level("WARNING", logger="drivers.xsens.source"):
        assert load_imu_source(path).rate_hz == 100.0
    assert "quat_only.bin" in caplog.text and "assuming the factory default of 100 Hz" in caplog.text
    caplog.clear()
    config = [xbus.OutputSetting(0x1020, 0xFFFF), xbus.OutputSetting(0x2010, 60)]
    (tmp_path / "quat_only_outputconfig.bin").write_bytes(xbus.encode_output_configuration(config))
    with caplog.at_level("WARNING", logger="drivers.xsens.source"):
        source = load_imu_source(path)
    assert source.rate_hz == 60.0 and caplog.text == ""
    assert source.arrays["quaternion"].shape == (20, 4)


def test_stable_link_names_the_plugged_tracker_only(tmp_path):
    """``stable_link`` plays udev's /dev/serial/by-id name: there while plugged in, gone at unplug. A replugged
    successor that gets the freed pty number keeps its name when the old simulator is closed later; a path that is
    not a link is refused, not overwritten."""
    link = tmp_path / "usb-Xsens_MTi-if00"
    source = synthetic_imu(seconds=2.0)
    old = XsensSimulator(source, stable_link=link).start()
    assert os.readlink(link) == old.path
    old.unplug()
    assert not os.path.lexists(link)
    new = XsensSimulator(source, stable_link=link).start()
    try:
        old.close()  # after the replug, possibly on the same pty number
        assert os.readlink(link) == new.path
    finally:
        new.close()
    assert not os.path.lexists(link)
    link.write_text("not a tty")
    with pytest.raises(ConfigError, match="not a symbolic link"):
        XsensSimulator(source, stable_link=link).start()
    assert link.read_text() == "not a tty" and sorted(p.name for p in tmp_path.iterdir()) == [link.name]


@pytest.mark.needs_shared
@pytest.mark.parametrize("capture", ["mtig710_set1.bin", "mtig710_set4.bin"])
def test_a_capture_of_euler_angles_gives_the_quaternion_a_configured_device_would(shared_dir, capture):
    """The real captures carry Euler angles and no quaternion; replayed, a driver that asks for quaternions got
    samples without orientation. The quaternion made from them (Xsens: x by roll, then y by pitch, then z by yaw)
    turns the capture's own accelerometer reading at rest into gravity, up, in ENU: the convention checked on the
    device's data."""
    from drivers.xsens.frames import rotate
    from drivers.xsens.source import load_imu_source

    source = load_imu_source(shared_dir / "data" / "xsens-captures" / capture)
    up = np.array([rotate(q, a) for q, a in zip(source.arrays["quaternion"], source.arrays["acceleration"])])
    assert np.allclose(up.mean(axis=0), (0.0, 0.0, 9.79), atol=0.05), up.mean(axis=0)
    assert np.allclose(np.linalg.norm(source.arrays["quaternion"], axis=1), 1.0)


@pytest.mark.parametrize("unsupported", [{0x1060}, {0x1060, 0x1020}])
def test_a_device_without_sample_time_fine_is_timed_by_its_counter_else_by_arrival(unsupported):
    # valid per the protocol (any item may be absent; the ack echoes what was applied): device time must still move
    source = synthetic_imu(seconds=5.0, seed=2)
    with XsensSimulator(source, speed=4.0, unsupported_outputs=frozenset(unsupported)) as sim:
        device, readings = configured_readings(sim, 40)
    assert len(readings) >= 40 and all(r.sample_time_fine is None for r in readings)
    times = np.array([r.device_time_ns for r in readings], dtype=float)
    assert np.all(np.diff(times) >= 0) and times[-1] > times[0]
    if 0x1020 not in unsupported:  # "+1 per message" at the applied 100 Hz: 10 ms a message, from the first one
        counters = np.array([r.packet_counter for r in readings])
        assert np.array_equal(times, (counters - counters[0]) * 1e7)
        assert "timed by its PacketCounter at 100 Hz" in device.stats.last_error
    else:  # nothing to count: their arrival (the host clock, ns)
        assert np.all(np.abs(times - np.array([r.host_time_ns for r in readings])) == 0)
        assert "timed by their arrival" in device.stats.last_error


def test_a_reply_behind_noise_that_looks_like_a_header_is_found_once_the_line_is_quiet():
    # a real line: the device's reply sits behind noise claiming a 200-byte frame, and nothing more comes
    import pty
    import threading

    controller, line = pty.openpty()
    answer = bytes.fromhex("0102030405FAFF36C8112233") + xbus.encode_message(xbus.Mid.GO_TO_CONFIG_ACK)
    try:
        device = XsensDevice(SerialTransport(os.ttyname(line), baudrate=115200), reply_timeout_s=1.0)
        try:
            threading.Timer(0.05, os.write, (controller, answer)).start()  # once the port is open and asked
            started = time.monotonic()
            reply = device.request(xbus.Mid.GO_TO_CONFIG)
            assert reply.mid == xbus.Mid.GO_TO_CONFIG_ACK and time.monotonic() - started < 0.8
        finally:
            device.close()
    finally:
        os.close(controller)
        os.close(line)


def test_an_error_to_the_informative_queries_leaves_the_device_configured_and_says_so():
    # the product code and firmware only inform; an Error to a request that matters still stops the start
    source = synthetic_imu(seconds=5.0, seed=3)
    errors = {xbus.Mid.REQ_PRODUCT_CODE: 0x04, xbus.Mid.REQ_FW_REV: 0x04}
    with XsensSimulator(source, speed=4.0, error_replies=errors) as sim:
        device = open_device(sim)
        try:
            device.reset()
            info = device.configure(100)
            readings = read_for(device, count=20)
        finally:
            device.close()
    assert info["product_code"] == "unknown" and info["firmware"] == "unknown" and len(readings) >= 20
    assert "its firmware is not known, the device is configured without it" in device.stats.last_error
    with XsensSimulator(source, speed=4.0, error_replies={xbus.Mid.SET_OUTPUT_CONFIGURATION: 0x21}) as sim:
        device = open_device(sim)
        try:
            device.reset()
            with pytest.raises(
                XbusDeviceError, match=r"0x21 .*after SET_OUTPUT_CONFIGURATION; asked for 0x1020 .*--imu-rate"
            ):
                device.configure(100)
        finally:
            device.close()


class _Line:
    """Bytes a device sent, read once (what a serial port returns); writes go nowhere."""

    name = "line"

    def __init__(self, data: bytes) -> None:
        self.data = data

    def read(self, max_bytes: int = 4096) -> bytes:
        data, self.data = self.data, b""
        return data

    def write(self, data: bytes) -> None:
        pass

    def close(self) -> None:
        pass


def test_messages_without_sample_time_fine_between_ones_with_it_stay_on_its_clock():
    # a device that sends SampleTimeFine at a lower rate than its other outputs: every message on one clock
    quaternion = xbus.make_data_id(0x2010, xbus.Precision.FLOAT32, xbus.CoordinateFrame.ENU)
    messages = [(0, 1000), (1, None), (2, 1200), (3, None)]  # (PacketCounter, SampleTimeFine in 10 kHz ticks)
    data = b"".join(
        xbus.encode_message(
            xbus.Mid.MT_DATA2,
            xbus.encode_mtdata2(
                [(0x1020, (counter,))]
                + ([(0x1060, (ticks,))] if ticks is not None else [])
                + [(quaternion, (1, 0, 0, 0))]
            ),
        )
        for counter, ticks in messages
    )
    device = XsensDevice(_Line(data))
    device.output_configuration = output_settings(50)  # messages at 50 Hz: 20 ms apart
    times = [reading.device_time_ns for reading in device.read()]
    assert times == [100_000_000, 120_000_000, 120_000_000, 140_000_000]


def test_a_device_without_packet_counter_counts_what_its_sample_time_says_was_lost():
    """Found by an independent device imitation: a device that did not apply PacketCounter lost 1 message in 10 and
    `packets_lost` stayed 0. Its SampleTimeFine says how many message periods (of the applied output rate) each
    step spans; the missing ones are now counted as the counter would have counted them."""
    source = synthetic_imu(seconds=5.0, seed=3)
    faults = FaultConfig(bit_flip=0.1, seed=5)  # a corrupted message fails its checksum: lost on the line
    with XsensSimulator(source, speed=2.0, unsupported_outputs=frozenset({0x1020}), faults=faults) as sim:
        device, readings = configured_readings(sim, 150)
        corrupted = len(sim.stats.corrupted_counters)
    ticks = np.array([r.sample_time_fine for r in readings if r.packet_counter is None], dtype=np.int64)
    assert len(ticks) == len(readings) >= 150
    missing = int(np.sum(np.round(np.diff(ticks) / 100.0) - 1))  # 100 ticks a message at 100 Hz
    assert 5 <= missing <= corrupted, (missing, corrupted)
    assert device.stats.packets_lost == missing
