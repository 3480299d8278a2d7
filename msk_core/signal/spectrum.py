"""Power spectral density by Welch's method with Hann segments, for every segment and channel at once.

The numbers of ``scipy.signal.welch(x, rate, window="hann", nperseg=n, noverlap=n // 2, detrend="constant",
scaling="density", axis=-1)`` (and, with one segment as long as ``x``, of ``scipy.signal.periodogram(x, rate,
window="hann", detrend="constant")``); tests/test_spectrum.py compares them. scipy's loop over segments and its
argument handling cost ~60 ms per channel and rep (fatigue) and ~0.5 ms per 0.5 s window of 16 channels (live
quality, every 0.125 s on the estimator's thread), too slow for the live path."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy import signal


@lru_cache(maxsize=16)
def hann_window(n: int) -> np.ndarray:
    """scipy's periodic Hann window of ``n`` samples (``signal.get_window("hann", n)``), made once per length."""
    window = signal.get_window("hann", n)
    window.flags.writeable = False
    return window


def hann_welch(x: np.ndarray, rate_hz: float, segment_samples: int) -> tuple[np.ndarray, np.ndarray]:
    """``(freqs, psd[..., f])`` of ``x[..., n_samples]`` (at least one segment long), segments overlapping by half."""
    n = segment_samples
    segments = np.lib.stride_tricks.sliding_window_view(x, n, axis=-1)[..., :: n - n // 2, :]
    window = hann_window(n)
    spectra = np.fft.rfft((segments - segments.mean(axis=-1, keepdims=True)) * window, axis=-1)
    psd = (spectra.real**2 + spectra.imag**2).mean(axis=-2) / (rate_hz * float(window @ window))
    psd[..., 1 : None if n % 2 else -1] *= 2.0  # one-sided: every bin but DC (and Nyquist for even n) twice
    return np.fft.rfftfreq(n, 1.0 / rate_hz), psd


#: Surface EMG's power lies at about 20-450 Hz (its electrodes' and amplifiers' band; motion artefacts below 20 Hz are
#: a few per cent of it): on the real recordings of ../shared, 0-4 % of every EMG channel's power lies below
#: SLOW_BAND_HZ, 97-100 % of every force-plate and load-cell channel's. A channel this slow is not surface EMG.
SLOW_BAND_HZ = 10.0
NOT_EMG_SLOW_FRACTION = 0.9


def slow_power_fraction(x: np.ndarray, rate_hz: float, below_hz: float = SLOW_BAND_HZ) -> np.ndarray:
    """Per channel of ``x[n_samples, n_channels]``, the share of its power (mean removed, Welch, ~0.5 Hz bins) below
    ``below_hz``; NaN for a channel with no power (zero throughout) or a recording too short for 4 such bins."""
    x = np.atleast_2d(np.asarray(x, dtype=float).T)  # (channels, samples)
    n = int(2 ** np.ceil(np.log2(max(rate_hz, 1.0) * 2.0)))  # segments of ~2 s: bins ~0.5 Hz
    if x.shape[-1] < n or below_hz * n / rate_hz < 4:
        return np.full(x.shape[0], np.nan)
    freqs, psd = hann_welch(x, rate_hz, n)
    total = psd.sum(axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total > 0, psd[..., freqs < below_hz].sum(axis=-1) / total, np.nan)
