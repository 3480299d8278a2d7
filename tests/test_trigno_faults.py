"""The Trigno simulator's electrode faults (``SimulatorConfig.faults``), read back through the real driver over TCP:
each kind does what the module docstring says to its sensor only and only in its span (the rest bit-exact), at its
physical amplitude; and the estimator's quality monitor (msk_core.estimate.live_quality) flags each on the right
electrode within 1 s, clears it within 1 s of its end, and flags no clean electrode over 60 s of the bench press."""

from __future__ import annotations

import time

import numpy as np
import pytest
from scipy import signal

from drivers.trigno.client import EmgBlock, TrignoClient, TrignoConfig
from drivers.trigno.simulator import (
    DEFAULT_FAULT_AMPLITUDE_V,
    HUM_HARMONICS,
    IMPACT_RATE_HZ,
    LIFT_OFF_FADE_S,
    FaultKind,
    SensorFault,
    SimulatorConfig,
    TrignoSimulator,
)
from drivers.trigno.source import EmgSource, synthetic_source
from msk_core.errors import ConfigError
from msk_core.estimate.emg_chunk import RawEmgChunk
from msk_core.estimate.live_quality import LiveQuality
from msk_core.signal.quality import TRIGNO_EMG_RANGE_V, Fault

EPHEMERAL = dict(command_port=0, emg_port=0, legacy_emg_port=None, aux_port=None)
RATE = 2000.0
#: what the monitor may call each injected fault
EXPECTED = {
    FaultKind.LIFT_OFF: {Fault.CONTACT_ARTEFACT, Fault.NO_SIGNAL},
    FaultKind.HUM: {Fault.MAINS},
    FaultKind.SATURATION: {Fault.SATURATION},
    FaultKind.FLAT: {Fault.FLAT_LINE},
}


def stream(source: EmgSource, faults: tuple[SensorFault, ...], seconds: float, speed: float) -> tuple[np.ndarray, list]:
    """``seconds`` of the simulator's EMG (all 16 slots) through the real client, and the blocks as they came."""
    with (
        TrignoSimulator(source, SimulatorConfig(**EPHEMERAL, speed=speed, faults=faults)) as sim,
        TrignoClient(TrignoConfig(command_port=sim.ports["command"], emg_port=sim.ports["emg"])) as client,
    ):
        assert client.rate_hz == pytest.approx(RATE)
        client.start()
        blocks, got = [], 0
        wanted = int(seconds * RATE)
        deadline = time.monotonic() + seconds / speed + 20.0
        while got < wanted and time.monotonic() < deadline:
            for event in client.poll(0.05):
                if isinstance(event, EmgBlock):
                    blocks.append(event)
                    got += len(event.samples)
        columns = client.emg_columns
    assert got >= wanted, f"waited {seconds / speed + 20:.0f} s for {wanted} EMG samples, got {got}"
    return np.concatenate([b.samples for b in blocks])[:wanted], [blocks, columns]


def test_fault_options_are_checked_and_parsed():
    assert SensorFault.parse("5:hum:10-15") == SensorFault(5, FaultKind.HUM, 10.0, 15.0)
    assert SensorFault.parse("2:lift-off:0-2.5").kind is FaultKind.LIFT_OFF
    for text in ("5:hum", "5:buzz:1-2", "x:hum:1-2", "17:hum:1-2", "5:hum:3-2", "5:hum:-1-2"):
        with pytest.raises(ConfigError):
            SensorFault.parse(text)
    with pytest.raises(ConfigError, match="amplitude"):
        SensorFault(1, FaultKind.HUM, 0, 1, amplitude_v=-1e-3)
    with pytest.raises(ConfigError, match="mains"):
        SensorFault(1, FaultKind.HUM, 0, 1, mains_hz=100.0)
    with pytest.raises(ConfigError, match="sensor 9 is not paired"):
        TrignoSimulator(synthetic_source(seconds=1.0), SimulatorConfig(faults=(SensorFault(9, FaultKind.FLAT, 0, 1),)))


def test_each_fault_changes_its_sensor_in_its_span_only_at_its_physical_size():
    source = synthetic_source(seconds=8.0, seed=4, sensors=5)
    faults = (
        SensorFault(1, FaultKind.HUM, 1.0, 3.0),
        SensorFault(2, FaultKind.LIFT_OFF, 2.0, 4.0),
        SensorFault(3, FaultKind.SATURATION, 3.0, 5.0),
        SensorFault(4, FaultKind.FLAT, 4.0, 6.0),
    )
    got, _ = stream(source, faults, 7.0, speed=10.0)
    clean = source.samples[: len(got)]
    changed = got != clean
    spans = {f.sensor - 1: slice(int(f.start_s * RATE), int(f.end_s * RATE)) for f in faults}
    for column in range(16):  # outside each fault's span, and on sensor 5 throughout, the source bit for bit
        outside = np.ones(len(got), dtype=bool)
        if column in spans:
            outside[spans[column]] = False
        assert not changed[outside, column].any(), column

    hum = (got - clean)[spans[0], 0].astype(float)  # the added interference, exactly
    t = np.arange(hum.size) / RATE
    amplitude = DEFAULT_FAULT_AMPLITUDE_V[FaultKind.HUM]
    for harmonic, share in ((1, 1.0), *HUM_HARMONICS):
        line = np.exp(-2j * np.pi * 50.0 * harmonic * t)
        assert abs(2 * np.mean(hum * line)) == pytest.approx(share * amplitude, rel=0.01), harmonic
    freqs, psd = signal.periodogram(hum, RATE)
    lines = np.isin(np.round(freqs), [50, 150, 250])
    assert psd[~lines].sum() < 1e-4 * psd.sum()  # nothing but the mains lines

    fade = int(LIFT_OFF_FADE_S * RATE)
    off = got[spans[1], 1][fade:-fade].astype(float)  # the electrode off the skin
    low = signal.sosfiltfilt(signal.butter(4, 20.0, fs=RATE, output="sos"), off)
    assert 1.5e-3 < np.std(low) < 2.5e-3  # a baseline wander of mV below 20 Hz ...
    on_skin = clean[spans[1], 1][fade:-fade].astype(float)
    assert abs(np.corrcoef(off, on_skin)[0, 1]) < 0.1  # ... and the muscle's EMG is gone

    saturated = got[spans[2], 2]
    at_rail = np.abs(saturated) >= np.float32(TRIGNO_EMG_RANGE_V)
    assert np.abs(got).max() <= np.float32(TRIGNO_EMG_RANGE_V)  # the converter clips at its range
    assert 0.01 < at_rail.mean() < 0.2 and not (np.abs(clean) >= 0.95 * TRIGNO_EMG_RANGE_V).any()
    clipped_from = np.flatnonzero(np.diff(np.r_[0, at_rail.astype(int)]) == 1) / RATE
    impacts = 1 + np.sum(np.diff(clipped_from) > 0.1)  # clipped stretches closer than 0.1 s are one impact
    assert abs(impacts - IMPACT_RATE_HZ * 2.0) <= 1

    flat = got[spans[3], 3]
    assert np.all(flat == clean[spans[3].start - 1, 3])  # the last value the sensor sent, held


def test_monitor_flags_each_fault_on_its_electrode_and_no_clean_one_over_60_s():
    """60 s of the bench press of ``msk live --sim`` (10 sensors) with four faults, through the driver, judged as the
    estimator judges it; false alarms: episodes on a clean electrode, or outside a faulty one's span."""
    from services.sessions.live import RECORDINGS, sim_sources

    source = sim_sources(RECORDINGS / "demo_session.mcap", "bench_press").emg
    faults = (
        SensorFault(2, FaultKind.LIFT_OFF, 10.0, 15.0),
        SensorFault(5, FaultKind.HUM, 22.0, 27.0),
        SensorFault(9, FaultKind.SATURATION, 34.0, 39.0),
        SensorFault(4, FaultKind.FLAT, 46.0, 51.0),
    )
    _, (blocks, columns) = stream(source, faults, 60.0, speed=20.0)
    quality = LiveQuality({label: source.labels[slot] for label, slot in columns})
    for block in blocks:
        quality.add_chunk(
            RawEmgChunk(
                "trigno",
                [label for label, _ in columns],
                block.rate_hz,
                block.first_sample_index,
                block.device_time_ns,
                block.samples[:, [slot for _, slot in columns]],
            )
        )
    reports = {r.channel: r for r in quality.report()}
    assert len(reports) == 10
    by_channel = {f"sensor{f.sensor:02d}.EMG": f for f in faults}
    for channel, report in reports.items():
        fault = by_channel.get(channel)
        if fault is None:
            assert report.episodes == 0 and report.check_s == report.bad_s == 0.0, (channel, report.recent)
            continue
        assert report.episodes == 1, (channel, report.recent)
        episode = report.recent[0]
        assert fault.start_s < episode.start_ns / 1e9 <= fault.start_s + 1.0, (channel, episode)
        assert fault.end_s < episode.end_ns / 1e9 <= fault.end_s + 1.0, (channel, episode)
        assert set(episode.faults) <= EXPECTED[fault.kind] and episode.faults, (channel, episode)
        assert report.state.value == "good"
