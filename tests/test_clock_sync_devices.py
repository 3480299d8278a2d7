"""The EMG clock against a tracker's clock from their accelerations, through the real drivers and simulators.

A synthetic bench press (msk_core.synth) is written as device files (services.sessions.synth_export) and streamed by a Trigno
simulator (real TCP: EMG and AUX ports, 60 ms device latency) and an Xsens simulator (pty) on one trial clock, the
tracker started 300 ms after the Trigno. The drivers read the Trigno sensors' accelerometers (AUX port, g, EMG clock)
and the upper-arm tracker's accelerations (m/s², its own SampleTimeFine clock); clock_sync must find the offset
between the two device clocks within ±10 ms of the truth, which the trial clock gives: the trial instant of the
Trigno's sample 0 (its start index) and of the tracker's power-up (its SampleTimeFine origin). The arrival-time
mapping alone (smallest arrival minus device time, per stream) is off by the Trigno's latency: reported beside it.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import numpy as np
import pytest

from drivers.trial_clock import TrialClock
from drivers.trigno import protocol as tp
from drivers.trigno.client import AuxBlock
from drivers.trigno.simulator import SimulatorConfig, TrignoSimulator
from drivers.trigno.source import load_source
from drivers.xsens.device import XsensDevice
from drivers.xsens.serial_transport import SerialTransport
from drivers.xsens.simulator import XsensSimulator
from drivers.xsens.source import load_imu_source
from msk_core.model import load_pack
from msk_core.signal.clock_sync import AccUnit, ClockSync, SyncStatus
from msk_core.synth import SPECS, Exercise, SynthConfig, generate_trial, make_subject
from services.sessions.synth_export import write_trial_device_streams
from tests.device_helpers import keeping_errors, trigno_streaming

TRIGNO_LATENCY_S = 0.060  # a base station buffering its frames
XSENS_LATENCY_S = 0.004  # an MTi over USB
TRACKER_AFTER_S = 0.300  # the tracker starts this long after the Trigno
TRIGNO_START_S = 0.2  # after the trial clock's start
READ_S = 10.5  # enough for the first window with movement: 6 s plus the search and filter margins after the rest
SEGMENT = "upper_arm_r"


@dataclass
class Received:
    aux: list[AuxBlock] = field(default_factory=list)
    imu_time_ns: list[int] = field(default_factory=list)
    imu_acc: list[tuple[float, float, float]] = field(default_factory=list)
    imu_host_ns: list[int] = field(default_factory=list)


def _read_trigno(sim: TrignoSimulator, got: Received, start_at: float, stop: threading.Event) -> None:
    with trigno_streaming(sim, start_at, aux=True) as client:
        while not stop.is_set():
            got.aux += [e for e in client.poll(0.01) if isinstance(e, AuxBlock)]


def _read_xsens(sim: XsensSimulator, got: Received, rate_hz: int, stop: threading.Event) -> None:
    device = XsensDevice(SerialTransport(sim.path, baudrate=921600))
    try:
        device.configure(rate_hz)
        while not stop.is_set():
            for reading in device.read():
                got.imu_time_ns.append(reading.device_time_ns)
                got.imu_acc.append(reading.acceleration)
                got.imu_host_ns.append(reading.host_time_ns)
    finally:
        device.close()


@pytest.fixture(scope="module")
def device_files(tmp_path_factory):
    spec = SPECS[Exercise.BENCH_PRESS]
    pack = load_pack(spec.pack)
    channels = spec.channels(pack.groups)
    config = SynthConfig(n_reps=3)
    trial = generate_trial(spec, pack, make_subject(7, pack.groups, channels), 50.0, config, channels)
    folder = tmp_path_factory.mktemp("bench")
    write_trial_device_streams(trial, folder, emg_rate_hz=config.emg_rate_hz, imu_rate_hz=config.imu_rate_hz)
    return folder, trial


def test_the_synthetic_trigno_sensors_carry_their_sites_accelerations(device_files):
    """The bench press's sensors on the upper arm and forearm move, the ones on the trunk (still on the bench) read
    1 g; each sensor's reading is its site's specific force in g, whatever its orientation."""
    folder, trial = device_files
    source = load_source(folder / "trigno.npz")
    assert source.acc is not None and source.acc_rate_hz == pytest.approx(2 / tp.FRAME_INTERVAL_S)
    magnitude = np.linalg.norm(source.acc, axis=2)  # (m, 16) g
    for k, (channel, body) in enumerate(zip(trial.emg_acc.channels, trial.emg_acc.bodies)):
        spread = float(magnitude[:, k].std())
        assert abs(float(magnitude[:, k].mean()) - 1.0) < 0.01, channel
        assert (spread > 0.01) if body is not None else (spread < 0.005), (channel, body, spread)
    assert {b for b in trial.emg_acc.bodies} == {None, "humerus_r", "radius_r"}


def test_offset_between_trigno_and_tracker_clocks_from_accelerations_within_10_ms(device_files):
    folder, trial = device_files
    emg_source = load_source(folder / "trigno.npz")
    imu_source = load_imu_source(folder / f"xsens_{SEGMENT}.npz")
    imu_rate = int(round(imu_source.rate_hz))
    trial_start = time.monotonic()
    clock = TrialClock(trial_start)
    trigno = TrignoSimulator(
        emg_source,
        SimulatorConfig(
            command_port=0, emg_port=0, legacy_emg_port=None, aux_port=0, trial_clock=clock, latency_s=TRIGNO_LATENCY_S
        ),
    ).start()
    got = Received()
    stop = threading.Event()
    errors: list[BaseException] = []
    xsens = None
    trigno_thread = threading.Thread(
        target=keeping_errors(_read_trigno, errors), args=(trigno, got, trial_start + TRIGNO_START_S, stop)
    )
    threads = [trigno_thread]
    try:
        trigno_thread.start()
        deadline = time.monotonic() + 5.0
        while trigno.stats.start_index is None and time.monotonic() < deadline:
            time.sleep(0.002)
        assert trigno.stats.start_index is not None, "the Trigno driver did not START within 5 s"
        started = clock.instant(trigno.stats.start_index, trigno.rate_hz)
        time.sleep(max(0.0, started + TRACKER_AFTER_S - time.monotonic()))
        xsens = XsensSimulator(
            imu_source, device_id=0x03700A01, wakeup_window_s=3600.0, trial_clock=clock, latency_s=XSENS_LATENCY_S
        ).start()
        threads.append(threading.Thread(target=keeping_errors(_read_xsens, errors), args=(xsens, got, imu_rate, stop)))
        threads[-1].start()
        time.sleep(READ_S)
    finally:
        stop.set()
        for thread in threads:
            thread.join(10)
        trigno.close()
        if xsens is not None:
            xsens.close()
    if errors:
        raise errors[0]
    n_aux = sum(len(b.samples) for b in got.aux)
    assert n_aux > 148 * (READ_S - 1) and len(got.imu_time_ns) > imu_rate * (READ_S - 1.5), (
        n_aux,
        len(got.imu_time_ns),
    )

    # the truth from the trial clock: trial instant of the Trigno's sample 0 and of the tracker's clock origin
    emg_origin_s = trigno.stats.start_index / trigno.rate_hz
    tracker_origin_s = xsens._powered_at - trial_start
    truth_ns = round((emg_origin_s - tracker_origin_s) * 1e9)  # tracker device time - EMG device time, one instant
    tracker_started_s = xsens.stats.start_index / imu_source.rate_hz - emg_origin_s
    assert TRACKER_AFTER_S - 0.05 < tracker_started_s < TRACKER_AFTER_S + 0.5, tracker_started_s
    # what the AUX port carried: AUX sample k is each sensor's acceleration at the trial instant of EMG device time
    # k / 148.1 Hz (the source's, linearly interpolated)
    aux = np.concatenate([b.samples for b in got.aux]).reshape(-1, tp.N_SENSORS, tp.AUX_SLOTS_PER_SENSOR)
    assert got.aux[0].first_sample_index == 0
    instants = emg_origin_s + np.arange(len(aux)) / got.aux[0].rate_hz
    source_t = np.arange(emg_source.acc.shape[0]) / emg_source.acc_rate_hz
    for k in (k for k in range(tp.N_SENSORS) if emg_source.paired[k]):
        expected = np.column_stack([np.interp(instants, source_t, emg_source.acc[:, k, j]) for j in range(3)])
        assert np.allclose(aux[:, k, :3], expected, atol=1e-5), emg_source.labels[k]
        assert not np.any(aux[:, k, 3:])  # the sensors answer 3 AUX channels: ACC only

    # the arrival-time mapping (smallest arrival minus device time, per stream): the prior, and what it misses
    aux_ends = [(b.host_time_ns, round((b.first_sample_index + len(b.samples) - 1) * 1e9 / b.rate_hz)) for b in got.aux]
    emg_host_ns = min(h - d for h, d in aux_ends)
    imu_host_ns = min(h - d for h, d in zip(got.imu_host_ns, got.imu_time_ns))
    prior_ns = emg_host_ns - imu_host_ns

    sync = ClockSync(prior_ns)
    sensors = [k for k in range(tp.N_SENSORS) if emg_source.paired[k]]
    imu_time = np.array(got.imu_time_ns, dtype=np.int64)
    imu_acc = np.array(got.imu_acc, dtype=float)
    fed = 0
    for block in got.aux:  # as they arrived: each AUX block with the tracker samples that had arrived by then
        times = np.round((block.first_sample_index + np.arange(len(block.samples))) * 1e9 / block.rate_hz)
        rows = block.samples.reshape(len(block.samples), tp.N_SENSORS, tp.AUX_SLOTS_PER_SENSOR)
        for k in sensors:
            sync.add_emg_sensor(emg_source.labels[k], times.astype(np.int64), rows[:, k, :3], AccUnit.G)
        upto = int(np.searchsorted(got.imu_host_ns, block.host_time_ns, side="right"))
        if upto > fed:
            sync.add_tracker(imu_time[fed:upto], imu_acc[fed:upto])
            fed = upto
        answer = sync.update()
    error_ms = (answer.offset_ns - truth_ns) / 1e6 if answer.offset_ns is not None else None
    print(
        f"truth {truth_ns / 1e6:.2f} ms; arrival-time mapping {prior_ns / 1e6:.2f} ms (error "
        f"{(prior_ns - truth_ns) / 1e6:+.2f} ms); accelerations: {answer.status.value}, error "
        f"{error_ms if error_ms is None else f'{error_ms:+.2f}'} ms, {answer.windows} window(s), "
        f"r {answer.peak_correlation}, sensor {answer.sensor}, spread {answer.spread_ns}"
    )
    assert answer.status is SyncStatus.LOCKED, answer.reason
    assert abs(answer.offset_ns - truth_ns) <= 10_000_000, (answer.offset_ns, truth_ns)
    assert trial.emg_acc.bodies[trial.emg_acc.channels.index(answer.sensor)] == "humerus_r", answer.sensor
    # the arrival-time mapping alone misses by about the Trigno's latency (its AUX blocks end mid-frame: +6.75 ms)
    assert 0.5 * TRIGNO_LATENCY_S < (prior_ns - truth_ns) / 1e9 < TRIGNO_LATENCY_S + 0.03, prior_ns - truth_ns
