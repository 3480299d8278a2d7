"""Driver nodes end to end: simulators -> drivers -> Zenoh topics, and ``msk capture`` / ``msk sim`` on the CLI."""

from __future__ import annotations

import re
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import replace

import numpy as np
import pytest

from drivers.trigno.client import TrignoClient, TrignoConfig
from drivers.trigno.simulator import SimulatorConfig, TrignoSimulator
from drivers.trigno.source import load_source, synthetic_source
from drivers.xsens import xbus
from drivers.xsens.device import TrackerSet, XsensDevice
from drivers.xsens.serial_transport import SerialTransport
from drivers.xsens.simulator import XsensSimulator
from drivers.xsens.source import synthetic_imu
from services.cli import main
from services.nodes import driver_nodes
from services.transport import messages, topics, zenoh_session
from services.transport.mcap_io import McapRecorderWriter, read_messages

EPHEMERAL = dict(command_port=0, emg_port=0, legacy_emg_port=0, aux_port=0)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_nodes_publish_emg_imu_and_status_on_zenoh():
    emg_source = synthetic_source(seconds=3.0, seed=4)
    imu_source = synthetic_imu(seconds=3.0, seed=4)
    options = zenoh_session.ZenohOptions(listen=(f"tcp/127.0.0.1:{free_port()}",))
    received: list = []
    with (
        TrignoSimulator(emg_source, SimulatorConfig(**EPHEMERAL, speed=4.0)) as trigno_sim,
        XsensSimulator(imu_source, speed=4.0, device_id=0x00B40001) as xsens_sim,
    ):
        with zenoh_session.open_session(options) as session:
            subscriber = session.declare_subscriber(
                "msk/nodetest/**",
                lambda sample: received.append(
                    (str(sample.key_expr), zenoh_session.type_name_of_sample(sample), bytes(sample.payload.to_bytes()))
                ),
            )
            client = TrignoClient(
                TrignoConfig(command_port=trigno_sim.ports["command"], emg_port=trigno_sim.ports["emg"])
            )
            client.connect()
            trackers = TrackerSet()
            device = XsensDevice(SerialTransport(xsens_sim.path))
            device.configure(100)
            trackers.add(device)
            sink = driver_nodes.ZenohSink(session)
            stop = threading.Event()
            reports = driver_nodes.run_threads(
                [
                    lambda: driver_nodes.trigno_loop(
                        client, session="nodetest", source_id="trigno", sink=sink, stop=stop, duration_s=0.6
                    ),
                    lambda: driver_nodes.xsens_loop(
                        trackers,
                        session="nodetest",
                        sink=sink,
                        stop=stop,
                        segments={"00B40001": "upper_arm_r"},
                        duration_s=0.6,
                    ),
                ],
                stop,
            )
            time.sleep(0.3)
            sink.close()
            subscriber.undeclare()
            trackers.close()
    assert all(isinstance(r, driver_nodes.LoopReport) for r in reports)
    by_key: dict[str, list] = {}
    for key, type_name, payload in received:
        assert topics.message_type_for_key(key) == type_name
        by_key.setdefault(key, []).append(messages.decode(type_name, payload))
    chunks = by_key[topics.emg_key("nodetest", "trigno")]
    samples = np.concatenate(
        [np.asarray(c.samples, dtype=np.float32).reshape(c.n_samples, c.n_channels) for c in chunks]
    )
    assert chunks[0].channel_labels == ["sensor01.EMG", "sensor02.EMG", "sensor03.EMG", "sensor04.EMG"]
    assert samples.shape[0] == reports[0].samples and samples.shape[0] > 500
    assert np.array_equal(samples, emg_source.samples[: len(samples), :4])  # float32, bit for bit
    imu = by_key[topics.imu_key("nodetest", "00B40001")]
    assert len(imu) == reports[1].samples > 50 and imu[0].segment == "upper_arm_r" and imu[0].coordinate_frame == "ENU"
    k = imu[5].packet_counter
    assert (imu[5].orientation.w, imu[5].orientation.z) == pytest.approx(
        (imu_source.arrays["quaternion"][k][0], imu_source.arrays["quaternion"][k][3]), abs=1e-6
    )
    statuses = by_key[topics.status_key("nodetest", "trigno")] + by_key[topics.status_key("nodetest", "00B40001")]
    assert {s.kind for s in statuses} == {"trigno", "xsens"}
    assert any(s.kind == "trigno" and s.samples_received == reports[0].samples for s in statuses)


def test_msk_capture_writes_samples_exactly_as_received(tmp_path, shared_dir, capsys):
    emg_source = load_source(shared_dir / "data/pyomeca-upper/markers_analogs.c3d")
    out = tmp_path / "session.mcap"
    with (
        TrignoSimulator(emg_source, SimulatorConfig(**EPHEMERAL, speed=2.0)) as trigno_sim,
        XsensSimulator(synthetic_imu(seconds=5.0), speed=2.0) as xsens_sim,
    ):
        code = main(
            [
                "capture",
                "--trigno",
                f"127.0.0.1:{trigno_sim.ports['command']}",
                "--trigno-emg-port",
                str(trigno_sim.ports["emg"]),
                "--xsens",
                xsens_sim.path,
                "--imu-precision",
                "fp1632",
                "--imu-frame",
                "NED",
                "--segment",
                "03700abc=thorax",
                "--duration",
                "0.8",
                "--out",
                str(out),
                "--session",
                "rec1",
            ]
        )
    assert code == 0
    recorded = list(read_messages(out))
    emg = [m.decode() for m in recorded if m.topic == "msk/rec1/emg/trigno"]
    rows = np.concatenate([np.asarray(c.samples, dtype=np.float32).reshape(c.n_samples, c.n_channels) for c in emg])
    assert rows.shape[1] == 13 and len(rows) > 1000
    assert np.array_equal(rows, emg_source.samples[: len(rows), :13])
    assert [c.first_sample_index for c in emg] == list(np.cumsum([0] + [c.n_samples for c in emg[:-1]]))
    imu = [m.decode() for m in recorded if m.topic == "msk/rec1/imu/03700ABC"]
    assert len(imu) > 50 and imu[0].segment == "thorax" and imu[0].coordinate_frame == "NED"
    status = [m.decode() for m in recorded if m.type_name == "msk.DeviceStatus"]
    assert {s.device_id for s in status} == {"trigno", "03700ABC"}
    final = [s for s in status if s.device_id == "trigno"][-1]
    assert final.samples_received == len(rows) and final.samples_lost == 0
    assert "wrote" in capsys.readouterr().out


def test_msk_capture_never_writes_over_a_recording_and_leaves_none_when_a_device_fails(tmp_path, capsys):
    """A capture whose device does not open used to leave an empty MCAP over the file given; and a second capture
    to the same name continues into the next part, as msk recorder does."""
    kept = tmp_path / "keep.mcap"
    with McapRecorderWriter(kept) as writer:
        writer.write_message(topics.load_key("s"), messages.LoadEvent(barbell_mass_kg=60.0), log_time_ns=1)
    before = kept.read_bytes()
    handler = signal.getsignal(signal.SIGINT)
    argv = ["capture", "--xsens", str(tmp_path / "no-such-tty"), "--duration", "1", "--out", str(kept)]
    assert main(argv) == 2
    assert signal.getsignal(signal.SIGINT) is handler  # Ctrl-C is the caller's again
    assert "no-such-tty" in capsys.readouterr().err
    assert kept.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["keep.mcap"]
    with XsensSimulator(synthetic_imu(seconds=5.0), speed=2.0) as xsens_sim:
        assert main(["capture", "--xsens", xsens_sim.path, "--duration", "0.5", "--out", str(kept)]) == 0
    said = capsys.readouterr().out
    assert kept.read_bytes() == before and (tmp_path / "keep-001.mcap").stat().st_size > 1000
    assert f"({kept} exists: this capture continues into the next part)" in said, said
    assert re.search(r"xsens: \d+ samples in \d+ messages, 0 lost", said), said


def test_msk_capture_says_what_a_faulty_tracker_lost(tmp_path, capsys):
    from drivers.xsens.simulator import FaultConfig

    faults = FaultConfig(bit_flip=0.05, drop_byte=0.05, garbage=0.05, seed=1)
    with XsensSimulator(synthetic_imu(seconds=8.0), speed=2.0, faults=faults) as xsens_sim:
        assert main(["capture", "--xsens", xsens_sim.path, "--duration", "2", "--out", str(tmp_path / "f.mcap")]) == 0
    said = capsys.readouterr().out
    lost, errors = map(int, re.search(r"xsens: \d+ samples in \d+ messages, (\d+) lost, (\d+) errors", said).groups())
    status = [m.decode() for m in read_messages(tmp_path / "f.mcap") if m.type_name == "msk.DeviceStatus"][-1]
    assert lost == status.samples_lost > 0 and errors == status.errors > 0, (said, status)


def test_msk_capture_needs_a_device(tmp_path, capsys):
    assert main(["capture", "--duration", "1", "--out", str(tmp_path / "x.mcap")]) == 2
    assert "msk capture: error: field 'devices': name at least one device" in capsys.readouterr().err


def test_msk_sim_xsens_prints_a_pty_a_driver_can_open():
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.cli",
            "sim",
            "xsens",
            "--from",
            "synthetic:5",
            "--speed",
            "2",
            "--duration",
            "8",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        path = process.stdout.readline().strip()
        assert path.startswith("/dev/")
        device = XsensDevice(SerialTransport(path))
        info = device.configure(50, precision=xbus.Precision.FLOAT64)
        readings = []
        deadline = time.monotonic() + 5
        while len(readings) < 10 and time.monotonic() < deadline:
            readings += device.read()
        device.close()
    finally:
        process.terminate()
        process.wait(timeout=10)
    assert info["device_id"] == "03700ABC" and len(readings) >= 10


def test_msk_sim_trigno_serves_a_client():
    ports = [free_port() for _ in range(5)]
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.cli",
            "sim",
            "trigno",
            "--from",
            "synthetic:5",
            "--port",
            str(ports[0]),
            "--emg-port",
            str(ports[1]),
            "--legacy-emg-port",
            str(ports[2]),
            "--aux-port",
            str(ports[3]),
            "--legacy-acc-port",
            str(ports[4]),
            "--speed",
            "4",
            "--duration",
            "8",
            "--start-index-base",
            "0",
            "--banner-space",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        line = process.stdout.readline()
        assert "Trigno simulator" in line, process.stderr.read() if not line else line
        assert f"legacy acc {ports[4]}" in line
        with (
            TrignoClient(TrignoConfig(command_port=ports[0], emg_port=ports[2])) as client,
            socket.create_connection(("127.0.0.1", ports[4]), timeout=5) as acc,
        ):
            client.start()
            got = 0
            deadline = time.monotonic() + 5
            while got < 300 and time.monotonic() < deadline:
                got += sum(len(e.samples) for e in client.poll(0.05) if hasattr(e, "samples"))
            acc_bytes = b""
            while len(acc_bytes) < 10 * 192 and time.monotonic() < deadline:
                acc_bytes += acc.recv(65536)
    finally:
        process.terminate()
        process.wait(timeout=10)
    assert got >= 300
    assert len(acc_bytes) >= 10 * 192  # legacy ACC port: 48 float32 per sample


def test_msk_drivers_publishes_to_a_connected_peer():
    port = free_port()
    received: list = []
    source = synthetic_source(seconds=3.0, seed=6)
    listen = zenoh_session.ZenohOptions(listen=(f"tcp/127.0.0.1:{port}",))
    with (
        zenoh_session.open_session(listen) as session,
        TrignoSimulator(source, SimulatorConfig(**EPHEMERAL, speed=2.0)) as sim,
    ):
        subscriber = session.declare_subscriber(
            "msk/drv/**", lambda s: received.append((str(s.key_expr), bytes(s.payload.to_bytes())))
        )
        time.sleep(0.2)
        code = main(
            [
                "drivers",
                "--trigno",
                f"127.0.0.1:{sim.ports['command']}",
                "--trigno-emg-port",
                str(sim.ports["emg"]),
                "--session",
                "drv",
                "--duration",
                "0.8",
                "--connect",
                f"tcp/127.0.0.1:{port}",
            ]
        )
        time.sleep(0.3)
        subscriber.undeclare()
    assert code == 0
    chunks = [messages.decode("msk.EmgChunk", p) for k, p in received if k == "msk/drv/emg/trigno"]
    assert len(chunks) > 10
    first = chunks[0].first_sample_index  # 0 unless the peers were still exchanging declarations
    rows = np.concatenate([np.asarray(c.samples, dtype=np.float32).reshape(c.n_samples, c.n_channels) for c in chunks])
    assert np.array_equal(rows, source.samples[first : first + len(rows), :4])
    assert any(k == "msk/drv/status/trigno" for k, _ in received)


def _sim_trigno(*argv: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "services.cli", "sim", "trigno", "--from", "synthetic:5", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_two_msk_sim_trigno_with_port_0_take_free_data_ports_too():
    """``--port 0`` alone: every port free, so a second simulator (a second rack on one machine) does not collide
    with the first on the TCU's fixed data ports; a data port given stays as given."""
    given = free_port()
    first, second = (
        _sim_trigno("--port", "0", "--duration", "8"),
        _sim_trigno("--port", "0", "--emg-port", str(given), "--duration", "8"),
    )
    try:
        lines = [p.stdout.readline() for p in (first, second)]
        for process, line in zip((first, second), lines):
            assert "Trigno simulator" in line, process.stderr.read() if not line else line
        ports = [dict(re.findall(r"(command|emg|legacy emg|aux|legacy acc) (\d+)", line)) for line in lines]
        assert set(ports[0]) == set(ports[1]) == {"command", "emg", "legacy emg", "aux", "legacy acc"}
        tcu = {50040, 50041, 50042, 50043, 50044}
        assert not {int(p) for p in ports[0].values()} & tcu and int(ports[1]["emg"]) == given
        assert not {int(p) for p in ports[0].values()} & {int(p) for p in ports[1].values()}
        with TrignoClient(TrignoConfig(command_port=int(ports[1]["command"]), emg_port=given)) as client:
            client.start()
            got, deadline = 0, time.monotonic() + 5
            while got < 100 and time.monotonic() < deadline:
                got += sum(len(e.samples) for e in client.poll(0.05) if hasattr(e, "samples"))
        assert got >= 100, f"the second simulator sent {got} EMG samples in 5 s"
    finally:
        for process in (first, second):
            process.terminate()
            process.wait(timeout=10)
            process.stdout.close()
            process.stderr.close()


def test_msk_sim_trigno_refuses_a_bad_data_port():
    process = _sim_trigno("--port", "0", "--aux-port", "-1", "--duration", "1")
    _, err = process.communicate(timeout=30)
    assert process.returncode != 0 and "--aux-port" in err and "-1" in err, err


def test_msk_sim_trigno_names_the_port_that_is_taken():
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    try:
        port = taken.getsockname()[1]  # the command port free and bound first: it was blamed too
        # every other data port free and given: a parallel test may hold the TCU's fixed ones (CI did)
        others = [
            flag_value
            for flag in ("--legacy-emg-port", "--aux-port", "--legacy-acc-port")
            for flag_value in (flag, str(free_port()))
        ]
        process = _sim_trigno("--port", str(free_port()), "--emg-port", str(port), *others, "--duration", "1")
        _, err = process.communicate(timeout=30)
    finally:
        taken.close()
    assert process.returncode == 2 and "field '--emg-port': cannot listen on 127.0.0.1" in err, err
    assert f"(the emg port {port}) (got '{port}')" in err, err


def test_msk_capture_says_when_another_client_stopped_the_base(tmp_path, capsys):
    """A second client's STOP stops a Trigno base for every client: the first capture kept 'connected, 0 lost' and
    said nothing of the missing seconds."""
    source = synthetic_source(seconds=20.0, seed=3)
    with TrignoSimulator(source, SimulatorConfig(**EPHEMERAL)) as sim:
        ports = ["--trigno", f"127.0.0.1:{sim.ports['command']}", "--trigno-emg-port", str(sim.ports["emg"])]
        out = tmp_path / "first.mcap"
        capture = threading.Thread(target=main, args=(["capture", *ports, "--duration", "4", "--out", str(out)],))
        capture.start()
        time.sleep(1.5)
        second = TrignoClient(TrignoConfig(command_port=sim.ports["command"], emg_port=sim.ports["emg"]))
        with second:  # a second capture of half a second: its START, then its STOP, stop the base for both
            second.start()
            deadline = time.monotonic() + 0.5
            while time.monotonic() < deadline:
                second.poll(0.05)
        capture.join(timeout=30)
    said = capsys.readouterr().out
    covered = float(re.search(r"trigno: \d+ samples in \d+ messages, ([\d.]+) s of data", said).group(1))
    assert covered < 3.0 and f"trigno: its data cover {covered:.1f} s of the 4 s asked" in said, said


def test_msk_capture_counts_its_duration_from_the_bases_first_data(tmp_path, capsys):
    """A real base sends its first data ~2 s after START: a 5 s capture held 3 s (independent imitation). The
    duration now counts the data, from the first EMG."""
    from drivers.trigno.simulator import TrignoQuirks

    quirks = TrignoQuirks(start_delay_s=1.5)
    with TrignoSimulator(synthetic_source(seconds=20.0, seed=3), SimulatorConfig(**EPHEMERAL, quirks=quirks)) as sim:
        ports = ["--trigno", f"127.0.0.1:{sim.ports['command']}", "--trigno-emg-port", str(sim.ports["emg"])]
        assert main(["capture", *ports, "--duration", "2", "--out", str(tmp_path / "late.mcap")]) == 0
    said = capsys.readouterr().out
    covered = float(re.search(r"trigno: \d+ samples in \d+ messages, ([\d.]+) s of data", said).group(1))
    assert covered >= 1.7 and "of the 2 s asked" not in said, said  # 0.5 s without the start delay counted


def test_msk_capture_stopped_by_ctrl_c_ends_cleanly_with_its_summary(tmp_path):
    import signal as signals

    with XsensSimulator(synthetic_imu(seconds=30.0)) as xsens_sim:
        out = tmp_path / "ctrl_c.mcap"
        process = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "capture", "--xsens", xsens_sim.path, "--duration", "30"]
            + ["--out", str(out)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        time.sleep(4.0)
        process.send_signal(signals.SIGINT)
        said, err = process.communicate(timeout=30)
    assert process.returncode == 0 and re.search(r"xsens: \d+ samples in \d+ messages, 0 lost", said), (said, err)
    status = [m.decode() for m in read_messages(out) if m.type_name == "msk.DeviceStatus"]
    assert not status[-1].connected  # the final status, not the last periodic one


def test_a_device_summary_says_reconnections_and_a_silent_base():
    report = driver_nodes.LoopReport(device="trigno", seconds_of_data=0.0)
    assert report.summary_line() == "trigno: 0 samples in 0 messages, 0.0 s of data, 0 lost"
    report.states = ["streaming", "reconnecting", "streaming", "reconnecting"]
    assert report.summary_line().endswith("disconnected 2x, reconnected 1x")
    trackers = driver_nodes.LoopReport(device="xsens", states=["disconnected", "disconnected", "reconnected"])
    said = trackers.summary_line("published")
    assert said == "xsens: published 0 samples in 0 messages, 0 lost, disconnected 2x, reconnected 1x"


def test_msk_capture_reads_a_legacy_acc_stream_on_a_port_of_its_own(tmp_path):
    """A base whose legacy ACC stream was moved off 50042 was read with the Avanti layout (16 x 9 slots): a third of
    the samples at the wrong times, sensor 3's accelerometer all zeros (found with an independent server imitation).
    --trigno-aux-layout says what the port carries."""
    from drivers.trigno.source import synthetic_source

    config = SimulatorConfig(command_port=0, emg_port=0, legacy_emg_port=None, aux_port=None, legacy_acc_port=0)
    out = tmp_path / "acc.mcap"
    with TrignoSimulator(synthetic_source(seconds=5.0), replace(config, speed=2.0)) as sim:
        argv = ["capture", "--trigno", f"127.0.0.1:{sim.ports['command']}", "--trigno-emg-port", str(sim.ports["emg"])]
        argv += ["--trigno-aux-port", str(sim.ports["legacy_acc"]), "--trigno-aux-layout", "legacy_acc"]
        assert main([*argv, "--duration", "0.8", "--out", str(out), "--session", "acc"]) == 0
    chunks = [m.decode() for m in read_messages(out) if m.topic == "msk/acc/acc/trigno"]
    assert chunks
    rows = np.concatenate([np.asarray(c.samples).reshape(c.n_samples, -1, 3) for c in chunks])
    assert np.all(rows[:, :, 2] == 1.0) and not np.any(rows[:, :, :2])  # the 4 sensors lie flat: z = 1 g, x = y = 0
