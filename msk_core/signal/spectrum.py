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
