"""The Hann-Welch spectrum of the live path (msk_core/signal/spectrum.py) against scipy, and the quality monitor's
window powers (one matrix product with ``spectral_weights``) against the bins summed one line at a time."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from msk_core.signal.quality import EMG_BAND_HZ, MAINS_BASELINE_HZ, MAINS_MAX_HZ, QualityConfig, window_metrics
from msk_core.signal.spectrum import hann_welch


@pytest.mark.parametrize("n", [963, 1000, 1074])
def test_one_segment_is_scipys_periodogram(n: int) -> None:
    x = 1e-4 * np.random.default_rng(n).standard_normal((2, 3, n)) + 2e-4
    f, p = hann_welch(x, 2148.1481, n)
    f_ref, p_ref = signal.periodogram(x, 2148.1481, window="hann", detrend="constant", axis=-1)
    np.testing.assert_array_equal(f, f_ref)
    np.testing.assert_allclose(p, p_ref, rtol=1e-10, atol=0)


@pytest.mark.parametrize("rate_hz", [2148.1481, 1925.9259, 2000.0])
@pytest.mark.parametrize("mains_hz", [50.0, 60.0])
def test_a_pure_mains_line_is_measured_whole_at_the_trigno_rates(rate_hz: float, mains_hz: float) -> None:
    """The window is 1 / 2 Hz long whatever the rate, so a 50 or 60 Hz line and its harmonics sit on bins and its
    power is measured whole (a window rounded to another length put a 50 Hz line 0.14-0.5 bin off: 10 % lost)."""
    config = QualityConfig(rate_hz=rate_hz)
    n = config.window_samples
    assert n == round(0.5 * rate_hz)
    t = np.arange(n) / rate_hz
    amplitude = 2e-5
    tone = amplitude * np.sin(2 * np.pi * 3 * mains_hz * t + 0.3)  # a harmonic inside the EMG band
    noise = 1e-6 * np.random.default_rng(1).standard_normal(n)
    metrics = window_metrics((tone + noise)[None, None, :], config)
    line_power = amplitude**2 / 2
    assert metrics.mains_hz[0, 0] == mains_hz
    assert metrics.mains_fraction[0, 0] * metrics.band_rms_v[0, 0] ** 2 == pytest.approx(line_power, rel=0.02)


def _powers_line_by_line(psd: np.ndarray, freqs: np.ndarray, mains_hz: float) -> tuple[float, float, float]:
    """Band, low and one mains family's excess power, summed bin by bin (the definition the weights encode)."""
    df = freqs[1] - freqs[0]
    band = (freqs >= EMG_BAND_HZ[0]) & (freqs <= EMG_BAND_HZ[1])
    low = (freqs > 0) & (freqs < EMG_BAND_HZ[0])
    lines = np.array([h for f0 in (50.0, 60.0) for h in np.arange(f0, MAINS_MAX_HZ + 1e-9, f0)])
    away = np.min(np.abs(freqs[:, None] - lines[None, :]), axis=1) > 2 * 1.01 * df
    excess = 0.0
    for h in np.arange(mains_hz, MAINS_MAX_HZ + 1e-9, mains_hz):
        on = band & (np.abs(freqs - h) <= 1.01 * df)
        beside = band & away & (np.abs(freqs - h) <= MAINS_BASELINE_HZ)
        if on.any() and beside.any():
            excess += (psd[on].sum() - psd[beside].mean() * on.sum()) * df
    return psd[band].sum() * df, psd[low].sum() * df, excess


def test_window_powers_equal_the_bins_summed_line_by_line() -> None:
    config = QualityConfig(rate_hz=2148.1481)
    n = config.window_samples
    t = np.arange(n) / config.rate_hz
    rng = np.random.default_rng(7)
    emg = 1e-4 * rng.standard_normal((1, 2, n))
    emg[0, 1] += 4e-5 * np.sin(2 * np.pi * 60.3 * t) + 2e-5 * np.sin(2 * np.pi * 180.9 * t)  # hum, 60 Hz family
    metrics = window_metrics(emg, config)
    freqs, psd = signal.periodogram(emg[0], config.rate_hz, window="hann", detrend="constant", axis=-1)
    for c in range(2):
        band, low, excess_60 = _powers_line_by_line(psd[c], freqs, 60.0)
        assert metrics.band_rms_v[0, c] == pytest.approx(np.sqrt(band), rel=1e-10)
        assert metrics.low_freq_rms_v[0, c] == pytest.approx(np.sqrt(low), rel=1e-10)
        if c == 1:
            assert metrics.mains_hz[0, c] == 60.0
            assert metrics.mains_fraction[0, c] == pytest.approx(excess_60 / band, rel=1e-9)
            assert 0.05 < metrics.mains_fraction[0, c] < 0.9
