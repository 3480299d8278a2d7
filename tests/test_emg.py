"""EMG chain on real raw EMG (Rajagopal walking .anc, pyomeca Trigno C3D) against independent scipy references."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import signal

from msk_core.errors import ConfigError, InputError
from msk_core.io import read_anc, read_c3d_analogs
from msk_core.signal.emg import (
    DelayLine,
    EmgEnvelopeFilter,
    EmgFilterConfig,
    NormalisationMode,
    NormalisationReference,
    delay_batch,
    delay_samples,
    envelope_causal,
    envelope_group_delay_s,
    envelope_zero_phase_noncausal,
    normalisation_reference,
)

RAJAGOPAL_EMG = ["SOL", "GAS", "TA", "MH", "BF", "VL", "VM", "RF", "GMAX", "GMED"]


def _reference_envelope(x: np.ndarray, fs: float, *, zero_phase: bool = False) -> np.ndarray:
    """Independent textbook chain: transfer-function (b, a) Butterworth filters, lfilter/filtfilt, per channel."""
    b_bp, a_bp = signal.butter(2, [20.0, 450.0], btype="bandpass", fs=fs)
    b_lp, a_lp = signal.butter(3, 6.0, fs=fs)
    out = np.empty_like(x, dtype=float)
    for j in range(x.shape[1]):
        if zero_phase:
            out[:, j] = signal.filtfilt(
                b_lp,
                a_lp,
                np.abs(
                    signal.filtfilt(b_bp, a_bp, x[:, j], padtype="odd", padlen=3 * (max(len(a_bp), len(b_bp)) - 1) * 2)
                ),
            )
        else:
            out[:, j] = signal.lfilter(b_lp, a_lp, np.abs(signal.lfilter(b_bp, a_bp, x[:, j])))
    return out


def _stream(x: np.ndarray, f: EmgEnvelopeFilter, sizes: list[int]) -> np.ndarray:
    out, i, k = [], 0, 0
    while i < x.shape[0]:
        n = sizes[k % len(sizes)]
        out.append(f.process(x[i : i + n]))
        i += n
        k += 1
    return np.vstack(out)


def _max_rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


@pytest.fixture(scope="module")
def walk_emg(shared_dir: Path):
    rec = read_anc(shared_dir / "data/rajagopal-walk/emg_walk_raw.anc").select(RAJAGOPAL_EMG)
    return rec


@pytest.fixture(scope="module")
def trigno_emg(shared_dir: Path):
    rec = read_c3d_analogs(shared_dir / "data/pyomeca-upper/markers_analogs.c3d")
    # connected Trigno EMG channels: named muscles (unused slots are "Sensor n.*" and all zero)
    labels = [lab for lab in rec.labels if "EMG" in lab and not lab.startswith("Sensor")]
    return rec.select(labels)


def test_rajagopal_raw_emg_matches_independent_reference(walk_emg) -> None:
    assert walk_emg.rate_hz == 2000.0 and walk_emg.data.shape == (4780, 10)
    cfg = EmgFilterConfig(rate_hz=walk_emg.rate_hz)
    env = envelope_causal(walk_emg.data, cfg)
    ref = _reference_envelope(walk_emg.data, walk_emg.rate_hz)
    assert _max_rel(env, ref) < 1e-8
    # Rectified and smoothed: well below the raw amplitude; the linear low-pass may undershoot a little after an
    # abrupt burst end (TA here) and the chain does not hide that.
    assert np.all(np.median(env[1000:], axis=0) > 0)
    assert np.all(env[1000:].min(axis=0) > -0.2 * env.max(axis=0))
    assert np.all(env.max(axis=0) < np.abs(walk_emg.data).max(axis=0))
    # one Trigno frame at a time equals the batch result
    stream = _stream(walk_emg.data, EmgEnvelopeFilter(cfg, 10), [27])
    assert _max_rel(stream, env) < 1e-12


def test_trigno_c3d_emg_matches_reference(trigno_emg) -> None:
    rec = trigno_emg
    assert "Delt_ant.EMG1" in rec.labels and "Biceps.EMG4" in rec.labels and "Pec.IM EMG12" in rec.labels
    assert set(rec.units) == {"V"} and rec.rate_hz == 2000.0
    cfg = EmgFilterConfig(rate_hz=rec.rate_hz)
    env = envelope_causal(rec.data, cfg)
    assert _max_rel(env, _reference_envelope(rec.data, rec.rate_hz)) < 1e-8
    # volts: envelopes are tens to hundreds of microvolts
    assert 1e-6 < float(np.median(env[4000:])) < 1e-3
    zp = envelope_zero_phase_noncausal(rec.data, cfg)
    # sosfiltfilt's default padding differs from filtfilt's; compare away from the edges
    ref = _reference_envelope(rec.data, rec.rate_hz, zero_phase=True)
    assert _max_rel(zp[2000:-2000], ref[2000:-2000]) < 1e-3
    stream = _stream(rec.data, EmgEnvelopeFilter(cfg, len(rec.labels)), [27, 26, 1, 200])
    assert _max_rel(stream, env) < 1e-12


_SIGNAL = np.random.default_rng(7).standard_normal((3000, 3)) * np.array([1e-3, 1.0, 500.0])


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(min_value=0, max_value=150), min_size=1, max_size=30), st.booleans())
def test_streaming_equals_batch_for_any_chunking(sizes: list[int], bandpass: bool) -> None:
    if sum(sizes) == 0:
        sizes = sizes + [1]
    cfg = EmgFilterConfig(rate_hz=2000.0, bandpass_hz=(20.0, 450.0) if bandpass else None)
    f = EmgEnvelopeFilter(cfg, 3)
    out = _stream(_SIGNAL, f, sizes)
    ref = envelope_causal(_SIGNAL, cfg)
    assert out.shape == ref.shape and f.samples_seen == _SIGNAL.shape[0]
    for j in range(3):  # per channel: the channels span six orders of magnitude
        assert _max_rel(out[:, j], ref[:, j]) < 1e-12


def test_reset_returns_to_rest() -> None:
    cfg = EmgFilterConfig(rate_hz=2000.0)
    f = EmgEnvelopeFilter(cfg, 3)
    f.process(_SIGNAL[:500])
    f.reset()
    assert _max_rel(_stream(_SIGNAL, f, [27]), envelope_causal(_SIGNAL, cfg)) < 1e-12


def test_group_delay_of_causal_chain_and_zero_phase() -> None:
    fs, f_mod = 2000.0, 1.0
    t = np.arange(int(20 * fs)) / fs
    modulation = 1.0 + 0.8 * np.sin(2 * np.pi * f_mod * t)
    emg = (np.random.default_rng(3).standard_normal(t.shape) * modulation)[:, None]
    cfg = EmgFilterConfig(rate_hz=fs)
    expected = envelope_group_delay_s(cfg, f_mod)
    assert 0.045 < expected < 0.06  # 3rd-order Butterworth 6 Hz: about 2 / (2 pi 6 Hz) = 53 ms

    def lag_s(env: np.ndarray) -> float:
        sl = slice(int(4 * fs), None)  # skip the start-up transient
        a = env[sl, 0] - env[sl, 0].mean()
        m = modulation[sl] - modulation[sl].mean()
        xc = signal.correlate(a, m, mode="full", method="fft")
        lags = signal.correlation_lags(a.shape[0], m.shape[0], mode="full")
        window = np.abs(lags) <= 200
        return float(lags[window][int(np.argmax(xc[window]))] / fs)

    assert lag_s(envelope_causal(emg, cfg)) == pytest.approx(expected, abs=0.004)
    assert abs(lag_s(envelope_zero_phase_noncausal(emg, cfg))) <= 0.002


def test_mvc_normalisation_on_real_emg(walk_emg) -> None:
    cfg = EmgFilterConfig(rate_hz=walk_emg.rate_hz)
    env = envelope_causal(walk_emg.data, cfg)[400:]  # drop the filter start-up
    mvc, task = env[:2000], env[2000:]
    ref = normalisation_reference([mvc], mode=NormalisationMode.MVC, channels=tuple(RAJAGOPAL_EMG))
    np.testing.assert_allclose(ref.normalise(mvc).max(axis=0), 1.0)
    np.testing.assert_allclose(ref.scale, mvc.max(axis=0))
    normed = ref.normalise(task)
    # the task exceeds this "MVC" on some muscles: values above 1 are kept, never clipped
    above = normed.max(axis=0) > 1.0
    assert above.any()
    np.testing.assert_allclose(normed.max(axis=0)[above], task.max(axis=0)[above] / mvc.max(axis=0)[above])
    both = normalisation_reference([mvc], task_envelopes=[task], mode=NormalisationMode.MAX_ALL_TRIALS)
    np.testing.assert_allclose(np.maximum(both.normalise(mvc).max(0), both.normalise(task).max(0)), 1.0)
    back = NormalisationReference.from_dict(ref.to_dict())
    assert back.mode is NormalisationMode.MVC and back.channels == tuple(RAJAGOPAL_EMG)
    np.testing.assert_array_equal(back.scale, ref.scale)


def test_normalisation_errors() -> None:
    with pytest.raises(InputError, match="channel 1 has no usable reference"):
        normalisation_reference([np.array([[1.0, 0.0], [2.0, 0.0]])])
    with pytest.raises(InputError, match="task trials"):
        normalisation_reference([np.ones((3, 2))], mode=NormalisationMode.MAX_ALL_TRIALS)
    with pytest.raises(ConfigError, match="mode"):
        NormalisationReference.from_dict({"scale": [1.0], "mode": "bogus"})


def test_electromechanical_delay_streaming_equals_batch() -> None:
    n = delay_samples(0.05, 2000.0)
    assert n == 100
    x = _SIGNAL
    ref = delay_batch(x, n)
    np.testing.assert_array_equal(ref[n:], x[:-n])
    assert np.all(ref[:n] == 0.0)
    line = DelayLine(n, 3)
    out = np.vstack([line.process(x[i : i + 37]) for i in range(0, x.shape[0], 37)])
    np.testing.assert_array_equal(out, ref)
    with pytest.raises(ConfigError, match="delay_s"):
        delay_samples(-0.01, 2000.0)


def test_config_errors() -> None:
    with pytest.raises(ConfigError, match="bandpass_hz.*Nyquist"):
        EmgFilterConfig(rate_hz=800.0)
    with pytest.raises(ConfigError, match="lowpass_hz"):
        EmgFilterConfig(rate_hz=2000.0, lowpass_hz=0.0)
    with pytest.raises(InputError, match="expected 2 channels"):
        EmgEnvelopeFilter(EmgFilterConfig(rate_hz=2000.0), 2).process(np.zeros((5, 3)))


def test_streaming_chain_equals_batch_on_trigno(trigno_emg) -> None:
    from msk_core.signal.emg import StreamingEmgChain, emg_chain_batch

    rec = trigno_emg
    cfg = EmgFilterConfig(rate_hz=rec.rate_hz)
    ref = normalisation_reference([envelope_zero_phase_noncausal(rec.data[:6000], cfg)])  # calibration, offline
    chain = StreamingEmgChain(cfg, ref, delay_s=0.04)
    live = _stream(rec.data, chain, [27, 13, 100])
    batch = emg_chain_batch(rec.data, cfg, ref, delay_s=0.04)
    assert live.shape == batch.shape
    np.testing.assert_array_equal(live[:80], 0.0)  # 40 ms delay at 2000 Hz
    assert _max_rel(live, batch) < 1e-12
    chain.reset()
    assert _max_rel(_stream(rec.data, chain, [27]), batch) < 1e-12


def _lag_s(late: np.ndarray, early: np.ndarray, fs: float, max_lag: int = 300) -> float:
    a, b = late - late.mean(), early - early.mean()
    xc = [np.dot(a[k:], b[: b.shape[0] - k]) for k in range(max_lag)]
    return int(np.argmax(xc)) / fs


@pytest.mark.parametrize("source", ["walk", "trigno"])
def test_group_delay_on_real_emg(source: str, walk_emg, trigno_emg) -> None:
    """On real EMG the causal envelope lags the zero-phase one by the low-pass group delay at the frequencies of
    muscle activity modulation (0.5-4 Hz: 53-69 ms for the 6 Hz default)."""
    rec = walk_emg if source == "walk" else trigno_emg
    cfg = EmgFilterConfig(rate_hz=rec.rate_hz)
    causal, zero = envelope_causal(rec.data, cfg), envelope_zero_phase_noncausal(rec.data, cfg)
    lo, hi = envelope_group_delay_s(cfg, 0.5) - 0.005, envelope_group_delay_s(cfg, 4.0)
    lags = [_lag_s(causal[:, j], zero[:, j], rec.rate_hz) for j in range(rec.data.shape[1])]
    assert all(lo <= lag <= hi for lag in lags), lags
