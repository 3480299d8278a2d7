"""MVC amplitude as the highest 0.5 s mean of the envelope: unbiased on a sustained contraction, unlike the peak."""

from __future__ import annotations

import numpy as np
import pytest

from msk_core.errors import ConfigError, InputError
from msk_core.signal.emg import EmgFilterConfig, envelope_zero_phase_noncausal, normalisation_reference, windowed_peak


def _sustained_contraction(rate=2000.0, seconds=3.0, level=1.0, seed=0):
    """Band-limited noise whose amplitude follows rest -> 2 s plateau at ``level`` -> rest."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(rate * seconds)) / rate
    drive = np.interp(t, [0, 0.4, 0.5, 2.5, 2.6, seconds], [0, 0, level, level, 0, 0])
    noise = rng.standard_normal(t.size)
    return t, drive, (0.01 + drive) * noise * 1e-4


def test_windowed_peak_recovers_the_plateau_where_the_plain_peak_overshoots():
    rate = 2000.0
    _, drive, emg = _sustained_contraction(rate)
    env = envelope_zero_phase_noncausal(emg, EmgFilterConfig(rate_hz=rate))
    plateau = env[(drive >= 1.0)][400:-400].mean()  # mean envelope over the plateau, away from the ramps
    peak = windowed_peak(env, 1)[0]
    windowed = windowed_peak(env, int(0.5 * rate))[0]
    assert peak > 1.05 * plateau, "the plain peak sits on the envelope ripple"
    assert abs(windowed / plateau - 1.0) < 0.03
    ref = normalisation_reference([env], window_samples=int(0.5 * rate))
    assert ref.scale[0] == pytest.approx(windowed)


def test_windowed_peak_equals_a_direct_moving_mean_and_checks_its_input():
    x = np.random.default_rng(1).random((50, 3))
    w = 7
    direct = np.max([x[i : i + w].mean(axis=0) for i in range(50 - w + 1)], axis=0)
    np.testing.assert_allclose(windowed_peak(x, w), direct, rtol=1e-12)
    np.testing.assert_array_equal(windowed_peak(x, 1), x.max(axis=0))
    with pytest.raises(ConfigError, match="window"):
        windowed_peak(x, 0)
    with pytest.raises(InputError, match="shorter than the window"):
        windowed_peak(x, 51)
