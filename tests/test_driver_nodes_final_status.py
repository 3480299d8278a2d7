"""At a clean stop every driver loop's last DeviceStatus of each device says connected = False with its final counts
(the Trigno base and each Xsens tracker), so that `msk live`'s recording and summary.json end with the devices
stopped. Real simulators: the Trigno over TCP, two Xsens trackers on their own pseudo-terminals."""

from __future__ import annotations

import threading

from drivers.trigno.client import TrignoClient, TrignoConfig
from drivers.trigno.simulator import SimulatorConfig, TrignoSimulator
from drivers.trigno.source import synthetic_source
from drivers.xsens.device import TrackerSet, XsensDevice
from drivers.xsens.serial_transport import SerialTransport
from drivers.xsens.simulator import XsensSimulator
from drivers.xsens.source import synthetic_imu
from services.nodes import driver_nodes
from services.transport import messages, topics

EPHEMERAL = dict(command_port=0, emg_port=0, legacy_emg_port=0, aux_port=0)
TRACKERS = {"00B4EB80": 0x00B4EB80, "00B497B2": 0x00B497B2}
SEGMENTS = {"00B4EB80": "upper_arm_r", "00B497B2": "forearm_r"}


def test_last_status_of_every_device_at_a_clean_stop_is_disconnected_with_final_counts():
    published: list[tuple[str, object]] = []
    lock = threading.Lock()

    def sink(key, message, host_time_ns, device_time_ns):
        with lock:
            published.append((key, message))

    imu_source = synthetic_imu(seconds=10.0, seed=2)
    stop = threading.Event()
    simulators = [XsensSimulator(imu_source, speed=1.0, device_id=number).start() for number in TRACKERS.values()]
    trackers = TrackerSet()
    with TrignoSimulator(synthetic_source(seconds=10.0, seed=2), SimulatorConfig(**EPHEMERAL, speed=1.0)) as trigno_sim:
        client = TrignoClient(TrignoConfig(command_port=trigno_sim.ports["command"], emg_port=trigno_sim.ports["emg"]))
        try:
            client.connect()
            for simulator in simulators:
                device = XsensDevice(SerialTransport(simulator.path))
                device.configure(100)
                trackers.add(device)
            threading.Timer(1.0, stop.set).start()  # what SIGINT does in `msk drivers`
            reports = driver_nodes.run_threads(
                [
                    lambda: driver_nodes.trigno_loop(client, session="s", source_id="trigno", sink=sink, stop=stop),
                    lambda: driver_nodes.xsens_loop(
                        trackers, session="s", sink=sink, stop=stop, status_interval_s=0.2, segments=SEGMENTS
                    ),
                ],
                stop,
            )
        finally:
            trackers.close()
            client.close()
            for simulator in simulators:
                simulator.close()
    assert all(isinstance(r, driver_nodes.LoopReport) for r in reports), reports
    statuses = {
        device: [m for k, m in published if k == topics.status_key("s", device)] for device in ["trigno", *TRACKERS]
    }
    emg_samples = sum(m.n_samples for k, m in published if k == topics.emg_key("s", "trigno"))
    assert emg_samples == reports[0].samples > 1000
    last = statuses["trigno"][-1]
    assert (last.kind, last.connected, last.samples_received) == ("trigno", False, emg_samples)
    assert any(s.connected for s in statuses["trigno"])  # it was connected while streaming
    for tracker in TRACKERS:
        readings = sum(1 for k, m in published if k == topics.imu_key("s", tracker))
        last = statuses[tracker][-1]
        assert readings > 50 and isinstance(last, messages.DeviceStatus)
        assert (last.kind, last.connected, last.samples_received) == ("xsens", False, readings), (tracker, last)
        assert all(s.connected for s in statuses[tracker][:-1])  # streaming until the stop
        # the terminal view reads statuses, not the 600 IMU samples a second: each status names the tracker's segment
        assert {s.segment for s in statuses[tracker]} == {SEGMENTS[tracker]}
    assert statuses["trigno"][-1].segment == ""
    from services.surfaces.view import health_tables

    table = health_tables({d: statuses[d][-1] for d in statuses})[0]
    shown = list(table.columns[0].cells)
    assert "00B4EB80 (upper_arm_r)" in shown and "00B497B2 (forearm_r)" in shown and "trigno" in shown, shown


def test_a_tracker_whose_samples_carry_no_orientation_is_said_in_its_status(shared_dir):
    """The real MTi-G-710 capture without its orientation outputs (inertial data and orientation increments only, as
    an MTi-1 gives) played by the simulator: the driver says once, in the tracker's status, that its samples cannot
    drive the kinematics (every reader that needs an orientation refuses them; they were published without a word)."""
    from drivers.xsens.source import load_imu_source

    published: list[tuple[str, object]] = []
    source = load_imu_source(shared_dir / "data/xsens-captures/mtig710_set1.bin")
    for orientation in ("quaternion", "euler"):  # the capture's Euler angles, and the quaternion made from them
        del source.arrays[orientation]
    stop = threading.Event()
    trackers = TrackerSet()
    with XsensSimulator(source, speed=1.0, device_id=0x03700ABC) as simulator:
        try:
            device = XsensDevice(SerialTransport(simulator.path))
            device.configure(100)
            trackers.add(device)
            threading.Timer(1.5, stop.set).start()
            driver_nodes.xsens_loop(
                trackers,
                session="s",
                sink=lambda key, message, *_: published.append((key, message)),
                stop=stop,
                status_interval_s=0.2,
            )
        finally:
            trackers.close()
    samples = [m for k, m in published if k == topics.imu_key("s", "03700ABC")]
    assert samples and not any(m.HasField("orientation") for m in samples)
    assert any(m.HasField("acceleration") for m in samples)
    last = [m for k, m in published if k == topics.status_key("s", "03700ABC")][-1]
    assert "tracker 03700ABC: its samples carry no orientation" in last.last_error, last
