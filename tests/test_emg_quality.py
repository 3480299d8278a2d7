"""Live electrode quality (msk_core.signal.quality) on synthetic Trigno EMG built from the real recording's statistics,
with lift-off, mains hum, saturation and a flat line injected at stated times on stated channels; and on the real
pyomeca-upper Trigno EMG itself."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from msk_core.errors import ConfigError, InputError
from msk_core.io import read_c3d_analogs
from msk_core.signal.quality import (
    CLEAR_HOPS,
    EMG_BAND_HZ,
    HOP_S,
    RAISE_HOPS,
    TRIGNO_EMG_RANGE_V,
    WINDOW_S,
    ElectrodeQualityMonitor,
    ElectrodeState,
    Fault,
    QualityConfig,
    assess_quality,
)

pytestmark = pytest.mark.needs_shared

RATE = 2000.0
DURATION_S = 60.0
# Real Trigno channels (pyomeca-upper) whose levels and spectra the synthetic channels copy, one each.
MODEL_CHANNELS = (
    "Delt_ant.EMG1",
    "Delt_med.EMG2",
    "Delt_post.EMG3",
    "Biceps.EMG4",
    "Triceps.EMG5",
    "Trap_sup.EMG6",
    "Gd_dent.EMG8",
    "Pec.IM EMG12",
)
DETECT_WITHIN_S = 1.0  # flagged within 1 s of a fault's onset ...
CLEAR_WITHIN_S = 1.0  # ... and cleared within 1 s of its end


@dataclass(frozen=True)
class Injected:
    channel: int
    fault: Fault
    t_on: float
    t_off: float
    what: str


FAULTS = (
    Injected(0, Fault.CONTACT_ARTEFACT, 5.0, 9.0, "lift-off: EMG gone, 1.5 mV RMS artefact at 1-10 Hz"),
    Injected(1, Fault.NO_SIGNAL, 12.0, 16.0, "lift-off: EMG gone, the sensor's own 0.5 uV noise left"),
    Injected(2, Fault.MAINS, 33.0, 39.0, "50 Hz hum (+ 150 Hz at 1/3), 2x the channel's active RMS, during a set"),
    Injected(3, Fault.SATURATION, 42.0, 44.0, "offset jump pins the channel at the +11 mV rail"),
    Injected(4, Fault.FLAT_LINE, 50.0, 54.0, "the last sample held (a stalled sensor)"),
)
CLEAN_CHANNELS = (5, 6, 7)


@pytest.fixture(scope="module")
def real_trigno(shared_dir: Path):
    return read_c3d_analogs(shared_dir / "data/pyomeca-upper/markers_analogs.c3d")


def _band_rms(x: np.ndarray, window: int) -> np.ndarray:
    sos = signal.butter(2, EMG_BAND_HZ, btype="bandpass", fs=RATE, output="sos")
    xb = signal.sosfiltfilt(sos, x, axis=0)
    n = xb.shape[0] // window * window
    return np.sqrt(np.mean(xb[:n].reshape(-1, window, xb.shape[1]) ** 2, axis=1))


@pytest.fixture(scope="module")
def real_statistics(real_trigno):
    """Per model channel: the real recording's rest and active 20-450 Hz RMS (10th / 90th percentile of 0.125 s
    windows) and its normalised amplitude spectrum (Welch)."""
    x = real_trigno.select(list(MODEL_CHANNELS)).data
    assert real_trigno.rate_hz == RATE
    rms = _band_rms(x, int(0.125 * RATE))
    freqs, psd = signal.welch(x, RATE, nperseg=256, axis=0)
    return np.percentile(rms, 10, axis=0), np.percentile(rms, 90, axis=0), freqs, psd / psd.sum(axis=0)


def _shaped_noise(rng: np.random.Generator, n: int, freqs: np.ndarray, psd: np.ndarray) -> np.ndarray:
    """Gaussian noise with the given one-sided spectrum shape, unit RMS in 20-450 Hz, per channel."""
    f = np.fft.rfftfreq(n, 1 / RATE)
    gain = np.sqrt(np.stack([np.interp(f, freqs, psd[:, c]) for c in range(psd.shape[1])], axis=1))
    gain[(f < EMG_BAND_HZ[0]) | (f > EMG_BAND_HZ[1])] *= 0.05  # the Trigno's own 20-450 Hz hardware filter
    x = np.fft.irfft(np.fft.rfft(rng.standard_normal((n, psd.shape[1])), axis=0) * gain, n=n, axis=0)
    return x / _band_rms(x, n).reshape(1, -1)


def activity(t: np.ndarray, n_channels: int) -> np.ndarray:
    """0..1 per channel: two sets of 8 reps (2.5 s each, a 1.5 s burst per rep) at 0-20 s and 30-50 s, rest between
    and after; each channel bursts at its own point of the rep (agonists, antagonists)."""
    out = np.zeros((t.size, n_channels))
    for set_start in (0.0, 30.0):
        for c in range(n_channels):
            for rep in range(8):
                start = set_start + 2.5 * rep + 0.12 * c
                inside = (t >= start) & (t < start + 1.5)
                out[inside, c] = np.maximum(out[inside, c], np.sin(np.pi * (t[inside] - start) / 1.5) ** 2)
    return out


def synthetic_session(real_statistics, seed: int = 7, faults=FAULTS) -> tuple[np.ndarray, np.ndarray]:
    """60 s of 8-channel raw Trigno EMG in volts (2 kHz) with ``faults`` injected; and the clean signal."""
    rest, active, freqs, psd = real_statistics
    rng = np.random.default_rng(seed)
    n = int(DURATION_S * RATE)
    t = np.arange(n) / RATE
    level = rest + (active - rest) * activity(t, len(rest))
    clean = _shaped_noise(rng, n, freqs, psd) * level
    x = clean.copy()
    for f in faults:
        span = (t >= f.t_on) & (t < f.t_off)
        c, m = f.channel, int(span.sum())
        if f.fault is Fault.CONTACT_ARTEFACT:
            sos = signal.butter(2, (1.0, 10.0), btype="bandpass", fs=RATE, output="sos")
            artefact = signal.sosfilt(sos, rng.standard_normal(m))
            x[span, c] = 1.5e-3 * artefact / artefact.std() + 0.5e-6 * rng.standard_normal(m)
        elif f.fault is Fault.NO_SIGNAL:
            x[span, c] = 0.5e-6 * rng.standard_normal(m)
        elif f.fault is Fault.MAINS:
            hum = np.sqrt(2) * (np.sin(2 * np.pi * 50.0 * t[span]) + np.sin(2 * np.pi * 150.0 * t[span] + 1.0) / 3)
            x[span, c] += 2.0 * active[c] * hum
        elif f.fault is Fault.SATURATION:
            x[span, c] = np.clip(x[span, c] + 1.05 * TRIGNO_EMG_RANGE_V, -TRIGNO_EMG_RANGE_V, TRIGNO_EMG_RANGE_V)
        elif f.fault is Fault.FLAT_LINE:
            x[span, c] = x[np.argmax(span) - 1, c]
    return x, clean


def _flagged(verdicts, channel: int, fault: Fault) -> tuple[np.ndarray, np.ndarray]:
    times = np.array([v.end_sample / RATE for v in verdicts])
    return times, np.array([fault in v.channels[channel].faults for v in verdicts])


def raise_events(verdicts, channel: int) -> list[tuple[float, Fault]]:
    """(time, fault) of every fault raised on ``channel``."""
    events, before = [], set()
    for v in verdicts:
        now = set(v.channels[channel].faults)
        events += [(v.end_sample / RATE, f) for f in now - before]
        before = now
    return events


@pytest.fixture(scope="module")
def session_verdicts(real_statistics):
    x, _ = synthetic_session(real_statistics)
    return assess_quality(x, QualityConfig(rate_hz=RATE))


def test_synthetic_channels_carry_the_real_recordings_levels(real_statistics) -> None:
    rest, active, _, _ = real_statistics
    _, clean = synthetic_session(real_statistics)
    rms = _band_rms(clean, int(0.125 * RATE))
    # the real recording's spread of amplitudes, reproduced per channel within a third
    assert np.all(np.abs(np.percentile(rms, 10, axis=0) / rest - 1) < 0.35), (np.percentile(rms, 10, axis=0), rest)
    assert np.all(np.abs(np.percentile(rms, 99, axis=0) / active - 1) < 0.35), (np.percentile(rms, 99, axis=0), active)
    print("rest uV", np.round(1e6 * rest, 1), "active uV", np.round(1e6 * active, 1))


@pytest.mark.parametrize("injected", FAULTS, ids=lambda f: f.fault.name.lower())
def test_each_fault_is_flagged_on_its_channel_within_1_s_and_cleared_after(session_verdicts, injected) -> None:
    times, flagged = _flagged(session_verdicts, injected.channel, injected.fault)
    after_onset = times >= injected.t_on
    first = times[after_onset & flagged]
    assert first.size, f"{injected.what}: never flagged as {injected.fault.value}"
    detected_after = first[0] - injected.t_on
    assert detected_after <= DETECT_WITHIN_S, f"{injected.what}: flagged {detected_after:.3f} s after onset"
    during = (times >= first[0]) & (times < injected.t_off)
    assert flagged[during].all(), f"{injected.what}: flag dropped at {times[during & ~flagged]}"
    ended = times >= injected.t_off
    cleared_at = times[ended & ~flagged][0]
    cleared_after = cleared_at - injected.t_off
    assert cleared_after <= CLEAR_WITHIN_S, f"{injected.what}: cleared {cleared_after:.3f} s after"
    assert not flagged[times >= cleared_at].any(), f"{injected.what}: flagged again after clearing"
    state = session_verdicts[int(np.argmax(during))].channels[injected.channel].state
    assert state in (ElectrodeState.CHECK, ElectrodeState.BAD)
    print(
        f"{injected.fault.value}: flagged {detected_after:.3f} s after onset, cleared {cleared_after:.3f} s "
        f"after the end ({state.value})"
    )


def test_no_false_alarm_in_60_s(session_verdicts) -> None:
    """No fault raised on a clean channel, nor on a faulty one away from its fault (counted, reported)."""
    false_alarms = []
    for c in range(len(MODEL_CHANNELS)):
        for t, fault in raise_events(session_verdicts, c):
            inside = [f for f in FAULTS if f.channel == c and f.t_on <= t <= f.t_off + CLEAR_WITHIN_S]
            if not inside:
                false_alarms.append((c, round(t, 3), fault.value))
    clean_states = {v.channels[c].state for v in session_verdicts[RAISE_HOPS:] for c in CLEAN_CHANNELS}
    print(
        f"{len(session_verdicts)} verdicts x {len(MODEL_CHANNELS)} electrodes over {DURATION_S:.0f} s: "
        f"{len(false_alarms)} false alarms {false_alarms}"
    )
    assert false_alarms == []
    assert clean_states == {ElectrodeState.GOOD}


def test_a_clean_session_over_several_seeds_raises_nothing(real_statistics) -> None:
    cfg = QualityConfig(rate_hz=RATE)
    counts = []
    for seed in (1, 2, 3):
        x, _ = synthetic_session(real_statistics, seed=seed, faults=())
        verdicts = assess_quality(x, cfg)
        counts.append(sum(len(raise_events(verdicts, c)) for c in range(x.shape[1])))
    print("false alarms per clean 60 s session of 8 electrodes:", counts)
    assert counts == [0, 0, 0]


def test_60_hz_hum_is_named_as_such(real_statistics) -> None:
    hum = Injected(5, Fault.MAINS, 52.0, 56.0, "60 Hz hum")
    x, _ = synthetic_session(real_statistics, faults=())
    t = np.arange(x.shape[0]) / RATE
    span = (t >= hum.t_on) & (t < hum.t_off)
    x[span, 5] += 30e-6 * np.sqrt(2) * np.sin(2 * np.pi * 60.0 * t[span])  # at rest: 30 uV against ~10 uV of EMG
    verdicts = assess_quality(x, QualityConfig(rate_hz=RATE))
    times, flagged = _flagged(verdicts, 5, Fault.MAINS)
    hit = np.flatnonzero(flagged)
    assert hit.size and times[hit[0]] - hum.t_on <= DETECT_WITHIN_S
    assert times[hit[-1]] < hum.t_off + CLEAR_WITHIN_S
    assert verdicts[hit[0]].metrics.mains_hz[5] == 60.0
    assert "60 Hz lines" in verdicts[hit[0]].describe(5)
    assert [f for _, f in raise_events(verdicts, 5)] == [Fault.MAINS]


def test_a_hum_weaker_than_the_contractions_is_held_through_the_reps(real_statistics) -> None:
    """30 uV of 50 Hz hum on an electrode resting at ~6 uV and contracting at ~200 uV: the reps mask it (they neither
    raise nor clear it), so the flag, raised in the first quiet moment, holds through the set and clears after."""
    channel, t_on, t_off = 6, 31.0, 52.0
    x, _ = synthetic_session(real_statistics, faults=())
    t = np.arange(x.shape[0]) / RATE
    span = (t >= t_on) & (t < t_off)
    x[span, channel] += 30e-6 * np.sqrt(2) * np.sin(2 * np.pi * 50.0 * t[span])
    verdicts = assess_quality(x, QualityConfig(rate_hz=RATE))
    times, flagged = _flagged(verdicts, channel, Fault.MAINS)
    first = times[flagged][0]
    burst_end = 30.0 + 0.12 * channel + 1.5  # the rep under way at the onset
    assert t_on <= first <= burst_end + DETECT_WITHIN_S, first
    assert flagged[(times >= first) & (times < t_off)].all()
    assert times[flagged][-1] < t_off + CLEAR_WITHIN_S
    assert raise_events(verdicts, channel) == [(first, Fault.MAINS)]
    print(
        f"hum under contractions: flagged at {first:.3f} s (onset {t_on} s, rep until {burst_end:.2f} s), held to "
        f"{times[flagged][-1]:.3f} s (hum ends {t_off} s)"
    )


def test_streaming_in_any_chunks_equals_batch(real_statistics) -> None:
    x, _ = synthetic_session(real_statistics)
    x = x[int(40 * RATE) : int(56 * RATE)]  # saturation and flat line inside
    cfg = QualityConfig(rate_hz=RATE)
    batch = assess_quality(x, cfg)
    rng = np.random.default_rng(3)
    for sizes in ([27], [1, 0, 999, 250, 3], [5000]):
        monitor = ElectrodeQualityMonitor(cfg, x.shape[1])
        assert monitor.states == (ElectrodeState.UNKNOWN,) * x.shape[1]
        stream, i = [], 0
        while i < x.shape[0]:
            n = int(sizes[len(stream) % len(sizes)] if len(sizes) > 1 else sizes[0]) or int(rng.integers(1, 60))
            stream += monitor.process(x[i : i + n])
            i += n
        assert [v.end_sample for v in stream] == [v.end_sample for v in batch]
        assert [v.channels for v in stream] == [v.channels for v in batch]
        for a, b in zip(stream, batch):
            for name in ("band_rms_v", "mains_fraction", "rail_fraction", "low_freq_rms_v", "std_v"):
                np.testing.assert_allclose(getattr(a.metrics, name), getattr(b.metrics, name), rtol=1e-9, atol=1e-15)
        assert monitor.latest is stream[-1] and monitor.states == batch[-1].states


def test_windows_and_timing_follow_the_stated_constants() -> None:
    cfg = QualityConfig(rate_hz=RATE)
    monitor = ElectrodeQualityMonitor(cfg, 2)
    verdicts = monitor.process(np.zeros((int(2 * RATE), 2)))
    ends = [v.end_sample for v in verdicts]
    assert ends[0] == int(WINDOW_S * RATE) and np.all(np.diff(ends) == int(HOP_S * RATE))
    # two zero channels: flat from the first window, raised at the RAISE_HOPS-th
    assert verdicts[0].states == (ElectrodeState.UNKNOWN,) * 2
    assert verdicts[RAISE_HOPS - 1].states == (ElectrodeState.BAD,) * 2
    assert verdicts[RAISE_HOPS - 1].channels[0].faults == (Fault.FLAT_LINE,)
    assert verdicts[RAISE_HOPS - 1].describe(0).startswith("bad: flat line (SD 0.00 uV")
    # worst case to clear: the fault leaves the window (WINDOW_S), then CLEAR_HOPS clean windows
    assert WINDOW_S + CLEAR_HOPS * HOP_S <= CLEAR_WITHIN_S
    assert WINDOW_S + RAISE_HOPS * HOP_S <= DETECT_WITHIN_S


def test_bad_input_and_config_are_refused() -> None:
    with pytest.raises(ConfigError, match="rate"):
        QualityConfig(rate_hz=500.0)
    with pytest.raises(ConfigError, match="range"):
        QualityConfig(rate_hz=RATE, range_v=0.0)
    monitor = ElectrodeQualityMonitor(QualityConfig(rate_hz=RATE), 2)
    with pytest.raises(InputError, match="n_samples, 2"):
        monitor.process(np.zeros((10, 3)))
    with pytest.raises(InputError, match="non-finite"):
        monitor.process(np.full((10, 2), np.nan))
    assert monitor.process(np.zeros((0, 2))) == []


def test_the_real_trigno_recording_is_good_where_electrodes_are_on_muscles(real_trigno) -> None:
    """pyomeca-upper (5.8 s, Trigno at 2 kHz): what the monitor says about every EMG slot of the file."""
    labels = [lab for lab in real_trigno.labels if "EMG" in lab]
    verdicts = assess_quality(real_trigno.select(labels).data, QualityConfig(rate_hz=real_trigno.rate_hz))
    settled = verdicts[RAISE_HOPS - 1 :]
    report = {}
    for c, label in enumerate(labels):
        states = [v.channels[c] for v in settled]
        report[label] = {s: sum(q.state.value == s for q in states) for s in ("good", "check", "bad")}
        faults = {f for q in states for f in q.faults}
        if label.startswith("Sensor"):  # unpaired slots: the file holds zeros
            assert all(q.state is ElectrodeState.BAD and q.faults == (Fault.FLAT_LINE,) for q in states), label
        elif label.startswith("Subscap"):  # a deep muscle: a surface electrode sees hardly anything
            assert faults <= {Fault.NO_SIGNAL}, (label, faults)
        else:
            assert faults == set(), (label, faults)
    print(
        f"{len(settled)} verdicts per slot:",
        {k: v for k, v in report.items() if not k.startswith("Sensor")},
        f"{sum(k.startswith('Sensor') for k in report)} unpaired slots all bad (flat line)",
    )
