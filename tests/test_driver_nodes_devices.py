"""Driver nodes follow what the devices say: the Trigno node publishes every EMG channel of the active sensors (one
column per channel of a multi-channel sensor) and nothing of a paired but switched-off sensor (the independent fake
TCU of the conformance tests, real TCP); the Xsens node reports a tracker that is unplugged and comes back (real
pseudo-terminals)."""

from __future__ import annotations

import threading
import time

import numpy as np

from drivers.trigno import protocol as tp
from drivers.trigno.client import TrignoClient, TrignoConfig
from drivers.xsens.device import TrackerSet, XsensDevice
from drivers.xsens.serial_transport import SerialTransport
from drivers.xsens.simulator import XsensSimulator
from drivers.xsens.source import synthetic_imu
from services.nodes import driver_nodes
from services.transport import topics
from tests.test_driver_conformance_trigno import FakeTcu, base_answers, known_rows


def test_trigno_node_publishes_each_emg_channel_of_active_sensors_only():
    rows = known_rows(400, 16, paired=(1, 2, 3, 4, 5, 9))
    answers = {
        **base_answers({1: 1, 5: 5, 9: 9}),  # 1-based start indices
        "UPSAMPLING?": "NO",
        "SENSOR 1 ACTIVE?": "YES",
        "SENSOR 5 ACTIVE?": "YES",
        "SENSOR 9 ACTIVE?": "NO",
        "SENSOR 1 EMGCHANNELCOUNT?": "4",
        "SENSOR 5 EMGCHANNELCOUNT?": "1",
    }
    server = FakeTcu(answers=answers, emg=tp.encode_samples(rows))
    client = TrignoClient(TrignoConfig(command_port=server.ports["command"], emg_port=server.ports["emg"]))
    published: list = []
    try:
        client.connect()
        report = driver_nodes.trigno_loop(
            client,
            session="lab",
            source_id="trigno",
            sink=lambda key, msg, log_ns, pub_ns: published.append((key, msg)),
            stop=threading.Event(),
            duration_s=1.0,
            status_interval_s=10.0,
        )
    finally:
        client.close()
        server.close()
    chunks = [m for k, m in published if k == topics.emg_key("lab", "trigno")]
    assert chunks and report.samples == sum(c.n_samples for c in chunks) > 100
    assert chunks[0].channel_labels == [
        "sensor01.EMG1",
        "sensor01.EMG2",
        "sensor01.EMG3",
        "sensor01.EMG4",
        "sensor05.EMG",
    ]
    got = np.concatenate([np.asarray(c.samples, dtype=np.float32).reshape(c.n_samples, c.n_channels) for c in chunks])
    assert np.array_equal(got, rows[: len(got), :5])  # slots 1-5 bit for bit; sensor 9 (slot 9) left out


def test_xsens_node_reports_an_unplugged_tracker_and_its_return(tmp_path):
    link = tmp_path / "usb-Xsens_MTi-if00"  # a stable port name, as /dev/serial/by-id gives
    source = synthetic_imu(seconds=30.0)
    sim = XsensSimulator(source, speed=1.0, device_id=0x03700ABE, stable_link=link).start()
    trackers = TrackerSet(retry_interval_s=0.05)
    published: list = []
    stop = threading.Event()
    try:
        device = XsensDevice(SerialTransport(str(link)))
        device.configure(100)
        trackers.add(device)
        loop = threading.Thread(
            target=lambda: published.append(
                driver_nodes.xsens_loop(
                    trackers,
                    session="lab",
                    sink=lambda key, msg, log_ns, pub_ns: published.append((key, msg)),
                    stop=stop,
                    status_interval_s=0.2,
                )
            )
        )
        loop.start()
        time.sleep(0.5)
        sim.unplug()
        deadline = time.monotonic() + 3.0
        while "03700ABE" not in trackers.disconnected and time.monotonic() < deadline:
            time.sleep(0.02)
        time.sleep(0.3)
        sim.close()
        sim = XsensSimulator(source, speed=1.0, device_id=0x03700ABE, stable_link=link).start()  # replugged
        deadline = time.monotonic() + 8.0
        while "03700ABE" in trackers.disconnected and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)
    finally:
        stop.set()
        loop.join(10)
        trackers.close()
        sim.close()
    report = published.pop()
    assert report.states == ["disconnected", "reconnected"]
    connected = [m.connected for k, m in published if k == topics.status_key("lab", "03700ABE")]
    # up, down for a while, up again; the last status, at the driver's stop, says disconnected
    assert connected[0] and not all(connected) and connected[-2] and not connected[-1]
    imu = [m for k, m in published if k == topics.imu_key("lab", "03700ABE")]
    assert len(imu) == report.samples > 50
