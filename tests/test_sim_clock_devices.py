"""One world for the simulators: a Trigno and two Xsens simulators on one trial clock, read through the real drivers.

Each device starts streaming at a moment of its own (as the driver nodes of ``msk live --sim`` start them), yet each
streams the trial from the instant it started, delivered ``latency_s`` after the instant the content belongs to, while
its own clock and counters stay its own (Trigno sample index from START, Xsens SampleTimeFine from power-up). The
host-clock mapping of the live path (smallest arrival minus device time, per stream; for EMG taken at the last
sample of each delivered block) then leaves as residual between two streams the difference of their delivery
latencies, and nothing of the Trigno's 13.5 ms block duration.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import numpy as np
import pytest

from drivers.trial_clock import TrialClock
from drivers.trigno.client import EmgBlock
from drivers.trigno.simulator import SimulatorConfig, TrignoSimulator
from drivers.trigno.source import synthetic_source
from drivers.xsens.device import XsensDevice
from drivers.xsens.serial_transport import SerialTransport
from drivers.xsens.simulator import XsensSimulator
from drivers.xsens.source import synthetic_imu
from msk_core.errors import ConfigError
from msk_core.estimate.emg_chunk import RawEmgChunk
from msk_core.estimate.live_emg import ClockMode, EmgSetup, LiveEmg
from tests.device_helpers import keeping_errors, trigno_streaming

TRIGNO_LATENCY_S = 0.030  # a base buffering its frames
XSENS_LATENCY_S = 0.004  # an MTi over USB
IMU_RATE = 100
STARTS_S = {"trigno": 0.4, "A": 0.9, "B": 1.5}  # after the trial clock's start: each device starts at its own moment
READ_S = 3.0
TRIAL_S = 20.0


@dataclass
class Stream:
    """What a driver received: content rows, the sample index (device count) of each, device and host times."""

    rows: list[np.ndarray] = field(default_factory=list)
    index: list[int] = field(default_factory=list)  # Trigno: sample index from START; Xsens: unwrapped PacketCounter
    device_ns: list[int] = field(default_factory=list)  # per row
    host_ns: list[int] = field(default_factory=list)  # per row: arrival of the bytes completing its block
    last_in_block: list[bool] = field(default_factory=list)


@dataclass
class OneWorld:
    trial_start: float  # time.monotonic()
    real_minus_mono_ns: int
    emg_source: np.ndarray
    imu_source: np.ndarray  # quaternions
    trigno: Stream
    xsens: dict[str, Stream]
    powered_at: dict[str, float]
    start_index: dict[str, int | None]
    live_emg_offset_ns: int


def _read_trigno(sim: TrignoSimulator, stream: Stream, live: LiveEmg, start_at: float, stop: threading.Event) -> None:
    with trigno_streaming(sim, start_at) as client:
        while not stop.is_set():
            for block in client.poll(0.01):
                if not isinstance(block, EmgBlock):
                    continue
                n = len(block.samples)
                live.add_chunk(
                    RawEmgChunk(
                        "trigno",
                        ("s1", "s2", "s3", "s4"),
                        block.rate_hz,
                        block.first_sample_index,
                        block.device_time_ns,
                        block.samples[:, :4],
                    ),
                    block.host_time_ns,
                )
                for k in range(n):
                    stream.rows.append(block.samples[k, :4])
                    stream.index.append(block.first_sample_index + k)
                    stream.device_ns.append(int(round((block.first_sample_index + k) * 1e9 / block.rate_hz)))
                    stream.host_ns.append(block.host_time_ns)
                    stream.last_in_block.append(k == n - 1)


def _read_xsens(sim: XsensSimulator, stream: Stream, start_at: float, stop: threading.Event) -> None:
    device = XsensDevice(SerialTransport(sim.path, baudrate=921600))
    try:
        time.sleep(max(0.0, start_at - time.monotonic()))
        device.configure(IMU_RATE)
        while not stop.is_set():
            for reading in device.read():
                wraps = stream.index[-1] // 65536 if stream.index else 0
                index = wraps * 65536 + reading.packet_counter
                if stream.index and index < stream.index[-1]:
                    index += 65536
                stream.rows.append(np.asarray(reading.quaternion_enu()))
                stream.index.append(index)
                stream.device_ns.append(reading.device_time_ns)
                stream.host_ns.append(reading.host_time_ns)
                stream.last_in_block.append(True)
    finally:
        device.close()


@pytest.fixture(scope="module")
def one_world() -> OneWorld:
    emg = synthetic_source(seconds=TRIAL_S, seed=7)
    imu = synthetic_imu(seconds=TRIAL_S, seed=7, rate_hz=float(IMU_RATE))
    trial_start = time.monotonic()
    clock = TrialClock(trial_start)
    real_minus_mono_ns = time.time_ns() - time.monotonic_ns()
    trigno = TrignoSimulator(
        emg,
        SimulatorConfig(
            command_port=0,
            emg_port=0,
            legacy_emg_port=None,
            aux_port=None,
            trial_clock=clock,
            latency_s=TRIGNO_LATENCY_S,
        ),
    ).start()
    xsens = {}
    for name in ("A", "B"):  # powered up 0.2 s apart: their SampleTimeFine clocks differ by that
        xsens[name] = XsensSimulator(
            imu, device_id=0x03700A00 + len(xsens), wakeup_window_s=3600.0, trial_clock=clock, latency_s=XSENS_LATENCY_S
        ).start()
        time.sleep(0.2)
    live = LiveEmg(
        ["g1", "g2", "g3", "g4"],
        EmgSetup({f"s{k}": f"g{k}" for k in range(1, 5)}, {f"s{k}": 1e-3 for k in range(1, 5)}),
        clock=ClockMode.HOST,
    )
    streams = {"trigno": Stream(), "A": Stream(), "B": Stream()}
    stop = threading.Event()
    errors: list[BaseException] = []
    threads = [
        threading.Thread(
            target=keeping_errors(_read_trigno, errors),
            args=(trigno, streams["trigno"], live, trial_start + STARTS_S["trigno"], stop),
        )
    ]
    threads += [
        threading.Thread(
            target=keeping_errors(_read_xsens, errors), args=(xsens[n], streams[n], trial_start + STARTS_S[n], stop)
        )
        for n in ("A", "B")
    ]
    try:
        for thread in threads:
            thread.start()
        time.sleep(max(STARTS_S.values()) + READ_S)
    finally:
        stop.set()
        for thread in threads:
            thread.join(10)
        trigno.close()
        for sim in xsens.values():
            sim.close()
    if errors:
        raise errors[0]
    return OneWorld(
        trial_start,
        real_minus_mono_ns,
        emg.samples[:, :4],
        imu.arrays["quaternion"],
        streams["trigno"],
        {n: streams[n] for n in ("A", "B")},
        {n: s._powered_at for n, s in xsens.items()},
        {"trigno": trigno.stats.start_index, **{n: s.stats.start_index for n, s in xsens.items()}},
        live.sources["trigno"].offset_ns,
    )


def _trial_index_of_first_row(rows: np.ndarray, source: np.ndarray, *, exact: bool) -> int:
    """The trial sample the stream's first row is, from the content: every row must then be the trial's next sample
    (the looped trial from there), bit for bit for EMG, to float32 precision for quaternions."""
    n = len(source)
    m = min(len(rows), n)
    if exact:
        candidates = np.flatnonzero(np.all(source == rows[0], axis=1))
    else:
        errors = [np.sum((source[(k + np.arange(m)) % n] - rows[:m]) ** 2) for k in range(n)]
        candidates = [int(np.argmin(errors))]
    for k in candidates:
        expected = source[(k + np.arange(len(rows))) % n]
        if np.array_equal(expected, rows) if exact else np.allclose(expected, rows, atol=1e-5):
            return int(k)
    raise AssertionError("the stream is not the trial played on from one sample")


def _delivery_s(world: OneWorld, stream: Stream, source: np.ndarray, rate: float, *, exact: bool) -> np.ndarray:
    """Per row ending a delivered block: host arrival minus the trial instant its content belongs to (realtime)."""
    rows = np.array(stream.rows)
    k0 = _trial_index_of_first_row(rows, source, exact=exact)
    index = np.array(stream.index) - stream.index[0]
    instant_ns = (world.trial_start + (k0 + index) / rate) * 1e9 + world.real_minus_mono_ns
    last = np.array(stream.last_in_block)
    return ((np.array(stream.host_ns) - instant_ns) / 1e9)[last]


def test_each_device_streams_the_trial_from_the_instant_it_starts_on_its_own_clock(one_world):
    world = one_world
    assert len(world.trigno.rows) > 2000 * (READ_S - 0.5) and all(
        len(s.rows) > IMU_RATE * (READ_S - 0.5) for s in world.xsens.values()
    )
    # the content: each stream is the trial from the sample of the instant its device started (stated in its stats)
    k0 = {"trigno": _trial_index_of_first_row(np.array(world.trigno.rows), world.emg_source, exact=True)}
    k0 |= {
        n: _trial_index_of_first_row(np.array(s.rows), world.imu_source, exact=False) for n, s in world.xsens.items()
    }
    assert k0 == world.start_index, (k0, world.start_index)
    for name, rate in (("trigno", 2000.0), ("A", IMU_RATE), ("B", IMU_RATE)):
        started_s = k0[name] / rate
        assert STARTS_S[name] < started_s < STARTS_S[name] + 0.5, (name, started_s)  # configuring takes a moment
    # ... delivered its latency after the instant it belongs to (the smallest delay: the fastest delivery)
    delays = {"trigno": _delivery_s(world, world.trigno, world.emg_source, 2000.0, exact=True)}
    delays |= {n: _delivery_s(world, s, world.imu_source, IMU_RATE, exact=False) for n, s in world.xsens.items()}
    for name, latency in (("trigno", TRIGNO_LATENCY_S), ("A", XSENS_LATENCY_S), ("B", XSENS_LATENCY_S)):
        fastest = float(delays[name].min())
        assert latency - 0.0005 < fastest < latency + 0.004, (name, fastest, latency)
    # the devices' own clocks: the Trigno counts from START, each tracker from its own power-up
    assert world.trigno.index[0] == 0 and world.trigno.device_ns[0] == 0
    a, b = world.xsens["A"], world.xsens["B"]
    a_device_ns = a.device_ns[k0["B"] - k0["A"]]  # A's sample of the instant of B's first one (A started first)
    powered_apart_ns = (world.powered_at["B"] - world.powered_at["A"]) * 1e9
    assert powered_apart_ns > 1e8
    assert abs((a_device_ns - b.device_ns[0]) - powered_apart_ns) < 2e5, (a_device_ns, b.device_ns[0])


def test_host_mapping_leaves_the_difference_of_the_delivery_latencies_not_the_block_duration(one_world):
    """With every device sampling the same instant, the live path's host mapping (per stream: smallest arrival minus
    device time; the EMG's from the last sample of each block, LiveEmg) puts an EMG sample and an IMU sample of the
    same trial instant (Xsens latency - Trigno latency) apart on the host clock: -26 ms here. Mapping the EMG by the
    first sample of its 27-sample blocks would add the block duration (13 ms)."""
    world = one_world
    k0_emg = _trial_index_of_first_row(np.array(world.trigno.rows), world.emg_source, exact=True)
    trial_emg_ns = lambda index: (k0_emg + index) * 1e9 / 2000.0  # noqa: E731 - trial time of EMG sample `index`
    for name, stream in world.xsens.items():
        k0 = _trial_index_of_first_row(np.array(stream.rows), world.imu_source, exact=False)
        imu_offset_ns = min(h - d for h, d in zip(stream.host_ns, stream.device_ns))  # the kinematics node's rule
        # one trial instant: the tracker's first sample; the EMG sample of the same instant
        instant_ns = k0 * 1e9 / IMU_RATE
        emg_index = round((instant_ns - trial_emg_ns(0)) * 2000.0 / 1e9)
        assert 0 <= emg_index < len(world.trigno.index)
        emg_host_ns = world.trigno.device_ns[emg_index] + world.live_emg_offset_ns
        imu_host_ns = stream.device_ns[0] + imu_offset_ns
        residual_s = (imu_host_ns - emg_host_ns) / 1e9
        expected_s = XSENS_LATENCY_S - TRIGNO_LATENCY_S
        print(
            f"tracker {name}: IMU minus EMG host-mapped time of one trial instant {residual_s * 1e3:+.2f} ms "
            f"(latencies say {expected_s * 1e3:+.1f} ms)"
        )
        assert abs(residual_s - expected_s) < 0.003, (name, residual_s, expected_s)


def test_live_emg_host_offset_uses_the_last_sample_of_each_block_whatever_the_block_size():
    """A device that sends blocks delivers each block's last sample ``latency`` after it is measured and its first
    one a block earlier: the mapping (smallest arrival minus device time) must come out as clock offset + latency
    for blocks of 1, 27 or 100 samples, not + the block duration."""
    rate, clock_offset_ns, latency_ns = 2000.0, 5_000_000_000, 20_000_000
    rng = np.random.default_rng(3)
    for block in (1, 27, 100):
        live = LiveEmg(["g"], EmgSetup({"c": "g"}, {"c": 1.0}), clock=ClockMode.HOST)
        for b in range(40):
            first = b * block
            last_ns = int(round((first + block - 1) * 1e9 / rate))
            late_ns = 0 if b == 17 else int(rng.integers(1, 3_000_000))  # one block delivered at the fastest
            live.add_chunk(
                RawEmgChunk(
                    "emg", ("c",), rate, first, int(round(first * 1e9 / rate)), rng.standard_normal((block, 1))
                ),
                clock_offset_ns + last_ns + latency_ns + late_ns,
            )
        assert live.sources["emg"].offset_ns == clock_offset_ns + latency_ns, block


def test_simulators_refuse_a_bad_latency_and_a_clock_a_bad_start():
    with pytest.raises(ConfigError, match="latency_s"):
        SimulatorConfig(latency_s=-0.01)
    with pytest.raises(ConfigError, match="latency_s"):
        XsensSimulator(synthetic_imu(seconds=1.0), latency_s=float("nan"))
    with pytest.raises(ConfigError, match="start"):
        TrialClock(float("inf"))


def test_a_clock_made_without_a_start_begins_with_the_first_device_to_stream():
    clock = TrialClock()
    with pytest.raises(ConfigError, match="not started"):
        clock.instant(0, 60.0)
    assert clock.first_index(100.0, 60.0) == 0 and clock.start == 100.0  # the first one starts the trial
    assert clock.first_index(100.5, 2000.0) == 1000  # a later one starts where the trial is then
    assert clock.first_index(100.5001, 60.0) == 31 and clock.instant(31, 60.0) == pytest.approx(100.0 + 31 / 60)
    assert clock.first_index(101.0, 60.0, speed=2.0) == 120  # the trial runs twice as fast


@pytest.mark.parametrize("pack", ["bench_press", "deadlift"])
def test_msk_live_sim_sources_span_one_duration_so_the_simulators_loop_together(pack):
    from services.sessions.live import RECORDINGS, sim_sources

    sources = sim_sources(RECORDINGS / "demo_session.mcap", pack)
    durations = {"emg": sources.emg.n_samples / sources.emg.rate_hz}
    durations |= {tracker: source.n_samples / source.rate_hz for tracker, (_, source) in sources.imu.items()}
    assert len(durations) >= 3 and max(durations.values()) - min(durations.values()) < 1e-9, durations
    trial_s = {"bench_press": 15.07, "deadlift": 14.07}[pack]  # the held-out trials' lengths
    assert trial_s - 0.05 - 0.02 < durations["emg"] <= trial_s, durations  # cut to a multiple of 50 ms
