"""Raw surface EMG: band-limited Gaussian noise amplitude-modulated by activation, as an electrode records it.

Per channel: source s_k(t) = a_k(t + emd) · n_k(t) with n_k unit-RMS noise band-passed 30–300 Hz (the bulk of the
surface-EMG power spectrum, e.g. De Luca 1997, J Appl Biomech 13:135); optional cross-talk mixes neighbouring sources;
the electrode multiplies by its gain (RMS volts at a = 1) and adds a white noise floor and occasional motion
artefacts (damped 2–8 Hz transients, mostly removed by a 20 Hz high-pass as in real recordings); the result is
quantised to the sensor's ADC step.

Fatigue (``spectral_scale``): the carrier of sample t is read at the warped time tau(t) = integral of s(t') dt', so
its spectrum is the fresh one compressed by s(t) (P(f / s) / s: every frequency, the median and mean frequency too,
times s), as slowing muscle-fibre conduction stretches the action potentials (Lindstrom & Magnusson 1977).
:func:`spectral_scale` makes the per-rep steps ``1 - f (k - 1)`` of the ``fatigue`` effect.
"""

from __future__ import annotations

import numpy as np
from scipy import signal

from msk_core.errors import ConfigError
from msk_core.synth.rng import stream

CARRIER_BAND_HZ = (30.0, 300.0)
#: ADC step: a Trigno EMG sensor digitises ±11 mV with 16 bits (Delsys Trigno user guide), ~0.34 µV.
ADC_STEP_V = 22e-3 / 2**16


def _carrier_sos(rate_hz: float) -> tuple[np.ndarray, float]:
    sos = signal.butter(2, CARRIER_BAND_HZ, btype="bandpass", fs=rate_hz, output="sos")
    impulse = np.zeros(int(rate_hz))
    impulse[0] = 1.0
    rms_gain = float(np.sqrt(np.sum(signal.sosfilt(sos, impulse) ** 2)))  # output RMS for unit white input
    return sos, rms_gain


def carrier(n: int, rate_hz: float, rng: np.random.Generator) -> np.ndarray:
    sos, gain = _carrier_sos(rate_hz)
    warm = int(0.1 * rate_hz)  # drop the filter's start-up transient
    return signal.sosfilt(sos, rng.normal(size=n + warm))[warm:] / gain


#: The warped carrier is read from one made at this multiple of the EMG rate (linear interpolation loses < 0.5 % of
#: the power at 300 Hz) and is not otherwise filtered; without fatigue the carrier is the one at the EMG rate.
WARP_OVERSAMPLING = 4


def warped_carrier(scale: np.ndarray, rate_hz: float, rng: np.random.Generator) -> np.ndarray:
    """Unit-RMS carrier whose spectrum at sample i is the fresh one compressed by ``scale[i]`` (0 < scale <= 1)."""
    s = np.asarray(scale, dtype=float)
    if s.ndim != 1 or not np.all((s > 0) & (s <= 1)):
        raise ConfigError("a spectral scale is in (0, 1] per sample", field="spectral_scale")
    tau = np.concatenate([[0.0], np.cumsum(s[:-1])]) * WARP_OVERSAMPLING  # in samples of the oversampled carrier
    fine = carrier(int(np.ceil(tau[-1])) + 2, rate_hz * WARP_OVERSAMPLING, rng)
    return np.interp(tau, np.arange(fine.size), fine)


def carrier_spectrum(freqs: np.ndarray, rate_hz: float, scale: float = 1.0) -> np.ndarray:
    """The (relative) power spectrum at ``freqs`` of :func:`warped_carrier` at a constant ``scale``: the truth a
    fatigue index is checked against (the 20-450 Hz median frequency falls a little less than the scale, as power
    from above 450 Hz moves into the band)."""
    sos, _ = _carrier_sos(rate_hz * WARP_OVERSAMPLING)
    _, h = signal.sosfreqz(sos, worN=np.asarray(freqs, dtype=float) / scale, fs=rate_hz * WARP_OVERSAMPLING)
    return np.abs(h) ** 2


def spectral_scale(time: np.ndarray, rep_starts: np.ndarray, per_rep: float) -> np.ndarray:
    """Per sample, the spectral compression of the ``fatigue`` effect: ``1 - per_rep (k - 1)`` from the start of rep k
    (1-based) to the start of rep k + 1; 1 before the first rep."""
    k = np.searchsorted(np.asarray(rep_starts, dtype=float), np.asarray(time, dtype=float), side="right")
    scale = 1.0 - per_rep * np.maximum(k - 1, 0)
    if not np.all(scale > 0):
        raise ConfigError(
            "the spectral shift per rep leaves no spectrum by the last rep", field="fatigue", value=per_rep
        )
    return scale


def crosstalk_matrix(n_channels: int, fraction: float) -> np.ndarray:
    """Each electrode sees (1 − c) of its own source and c split over its neighbours in site order."""
    m = np.eye(n_channels)
    if fraction <= 0 or n_channels < 2:
        return m
    for k in range(n_channels):
        neighbours = [j for j in (k - 1, k + 1) if 0 <= j < n_channels]
        m[k, k] = 1.0 - fraction
        for j in neighbours:
            m[k, j] = fraction / len(neighbours)
    return m


def motion_artefact(time: np.ndarray, t0: float, amplitude_v: float, freq_hz: float) -> np.ndarray:
    dt = time - t0
    out = np.zeros_like(time)
    on = dt >= 0
    out[on] = amplitude_v * np.exp(-dt[on] / 0.08) * np.sin(2 * np.pi * freq_hz * dt[on])
    return out


def raw_emg(
    time: np.ndarray,
    drive: np.ndarray,
    channels: list[str],
    gains_uv: dict[str, float],
    noise_floor_uv: float,
    *,
    rate_hz: float,
    seed: int,
    key: tuple,
    crosstalk: float = 0.0,
    artefact_times: np.ndarray | None = None,
    artefact_probability: float = 0.15,
    spectral_scale: np.ndarray | None = None,
) -> np.ndarray:
    """Raw EMG in volts, shape (n_samples, n_channels). ``drive`` (n_samples, n_channels) is the activation that
    modulates each site (already time-shifted for EMD); ``artefact_times`` are candidate moments (e.g. bar touches);
    ``spectral_scale`` (n_samples,): every site's spectrum compressed by it (fatigue), None: fresh throughout."""
    n, n_ch = drive.shape
    sources = np.empty((n, n_ch))
    for k, ch in enumerate(channels):
        rng = stream(seed, "emg", *key, ch)
        noise = carrier(n, rate_hz, rng) if spectral_scale is None else warped_carrier(spectral_scale, rate_hz, rng)
        sources[:, k] = np.clip(drive[:, k], 0.0, None) * noise
    sources = sources @ crosstalk_matrix(n_ch, crosstalk).T
    out = np.empty_like(sources)
    for k, ch in enumerate(channels):
        rng = stream(seed, "electrode-noise", *key, ch)
        x = sources[:, k] * gains_uv[ch] * 1e-6 + rng.normal(0.0, noise_floor_uv * 1e-6, n)
        for t0 in artefact_times if artefact_times is not None else ():
            if rng.uniform() < artefact_probability:
                x += motion_artefact(time, t0 + rng.uniform(-0.1, 0.1), rng.uniform(100, 500) * 1e-6, rng.uniform(2, 8))
        out[:, k] = np.round(x / ADC_STEP_V) * ADC_STEP_V
    return out


MVC_BLOCK_S = 4.0  # one maximal contraction: rest, ramp, plateau, ramp down, rest


def mvc_drive(
    channels: list[str], rate_hz: float, *, seed: int, block_s: float = MVC_BLOCK_S
) -> tuple[np.ndarray, np.ndarray]:
    """Activation of a block of maximal voluntary contractions, one channel after another: rest, 0.8 s ramp, 1.6 s
    plateau at a ≈ 1 (3 % tremor), ramp down; the other sites co-activate at 5-15 %. Returns (time, drive)."""
    n_block = int(round(block_s * rate_hz))
    t_block = np.arange(n_block) / rate_hz
    shape = np.interp(t_block, [0, 0.6, 1.4, 3.0, 3.6, block_s], [0, 0, 1, 1, 0, 0])
    drive = np.full((n_block * len(channels), len(channels)), 0.01)
    for k, ch in enumerate(channels):
        rng = stream(seed, "mvc", ch)
        sl = slice(k * n_block, (k + 1) * n_block)
        tremor = 1.0 + 0.03 * np.sin(2 * np.pi * rng.uniform(8, 12) * t_block + rng.uniform(0, 6.28))
        drive[sl, k] = np.maximum(0.01, shape * np.minimum(tremor, 1.0))
        co = rng.uniform(0.05, 0.15, len(channels))
        for j in range(len(channels)):
            if j != k:
                drive[sl, j] = np.maximum(drive[sl, j], co[j] * shape)
    return np.arange(drive.shape[0]) / rate_hz, drive
