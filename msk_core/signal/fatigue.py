"""EMG fatigue index per electrode and rep: median and mean frequency of the raw EMG during the rep's active part, and
their trend across the set.

As a muscle tires its EMG spectrum shifts towards lower frequencies (slower conduction of the muscle fibre action
potentials): the median frequency (MDF, the frequency that halves the power) and the mean frequency (MNF, the power-
weighted mean) fall. Their decline across a series of contractions is the standard spectral fatigue index (Merletti,
Knaflitz, De Luca 1990, J Appl Physiol 69:1810; Cifrek, Medved, Tonkovic, Ostojic 2009, Clin Biomech 24:327, for
dynamic contractions). Here, for each rep (its start and end times come from the rep segmenter,
:mod:`msk_core.signal.reps`, or the operator):

1. the rep's **active part** per electrode: from the first to the last sample whose envelope (the EMG chain's zero-phase
   envelope, :func:`msk_core.signal.emg.envelope_zero_phase_noncausal`, over the rep's samples: the rep has ended,
   so this uses no sample after it) reaches ``ACTIVE_FRACTION_OF_PEAK`` of the rep's envelope peak; at least
   ``MIN_ACTIVE_S`` long (widened around the peak inside the rep);
2. its power spectrum by Welch's method (``scipy.signal.welch``: Hann segments of ``WELCH_SEGMENT_S``, half
   overlapping, mean removed per segment) and MDF, MNF over 20-450 Hz;
3. across the set: the least-squares slope per rep and the change of the last reps from the first ones, in Hz and
   in % of the first reps' mean (:func:`fatigue_trend`).

Causal at the rep's scale: a rep's values exist when the rep ends, the trend updates with every rep.
:class:`FatigueTracker` takes the raw EMG in chunks of any size and the reps as they end; it returns exactly what
:func:`rep_spectra` computes on the whole recording.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from msk_core.errors import ConfigError, InputError
from msk_core.signal.emg import EmgFilterConfig, envelope_zero_phase_noncausal
from msk_core.signal.quality import EMG_BAND_HZ, NOISE_FLOOR_RMS_V, check_emg_rate
from msk_core.signal.spectrum import hann_welch

# 0.128 s segments (256 samples at 2 kHz): 7.8 Hz resolution, and a 1 s burst still gives ~14 half-overlapping
# segments to average (EMG spectral estimates for fatigue use 0.25-1 s epochs: Merletti et al. 1990).
WELCH_SEGMENT_S = 0.128
# The active part of a rep: where its envelope is at least half its peak (the burst, not the quiet lead-in and
# lead-out where the noise floor and the antagonist's cross-talk would bias the spectrum).
ACTIVE_FRACTION_OF_PEAK = 0.5
MIN_ACTIVE_S = 0.25  # at least three half-overlapping Welch segments
BASELINE_REPS = 3  # "the set's first reps": change = mean of the last 3 reps - mean of the first 3 (fewer: half each)
MAX_HISTORY_S = 30.0  # the live tracker keeps this much raw EMG: a rep may last up to this long


@dataclass(frozen=True)
class FatigueConfig:
    rate_hz: float
    welch_segment_s: float = WELCH_SEGMENT_S
    active_fraction: float = ACTIVE_FRACTION_OF_PEAK
    min_active_s: float = MIN_ACTIVE_S
    baseline_reps: int = BASELINE_REPS
    max_history_s: float = MAX_HISTORY_S

    def __post_init__(self) -> None:
        check_emg_rate(self.rate_hz)
        if not 0 < self.active_fraction < 1:
            raise ConfigError(
                "the active fraction of the peak must be in (0, 1)", field="active_fraction", value=self.active_fraction
            )
        if self.segment_samples < 32:
            raise ConfigError(
                "a Welch segment must hold at least 32 samples", field="welch_segment_s", value=self.welch_segment_s
            )
        if self.min_active_samples < self.segment_samples:
            raise ConfigError(
                "the shortest active part must hold a Welch segment", field="min_active_s", value=self.min_active_s
            )
        if self.baseline_reps < 1:
            raise ConfigError("need at least one baseline rep", field="baseline_reps", value=self.baseline_reps)

    @property
    def segment_samples(self) -> int:
        return int(round(self.welch_segment_s * self.rate_hz))

    @property
    def min_active_samples(self) -> int:
        return int(round(self.min_active_s * self.rate_hz))


def median_and_mean_frequency(
    freqs: np.ndarray, psd: np.ndarray, band_hz: tuple[float, float] = EMG_BAND_HZ
) -> tuple[np.ndarray, np.ndarray]:
    """MDF and MNF (Hz) of a one-sided spectrum ``psd[..., f]`` sampled at ``freqs`` (uniform), over ``band_hz``.

    Each bin holds the power of ``[f - df/2, f + df/2]`` spread evenly (cut at the band's edges); MDF is where the
    cumulative power reaches half the band's, MNF the power-weighted mean bin frequency. ``nan`` for an empty band.
    """
    f = np.asarray(freqs, dtype=float)
    p = np.asarray(psd, dtype=float)
    df = f[1] - f[0]
    lo_edge, hi_edge = np.maximum(f - df / 2, band_hz[0]), np.minimum(f + df / 2, band_hz[1])
    width = np.clip(hi_edge - lo_edge, 0.0, None)
    inside = width > 0
    lo_edge, width, fb = lo_edge[inside], width[inside], f[inside]
    power = p[..., inside] * width / df  # power of the part of each bin inside the band
    total = power.sum(axis=-1)
    cumulative = np.cumsum(power, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        mean_hz = (power * np.clip(fb, band_hz[0], band_hz[1])).sum(axis=-1) / total
        k = np.argmax(cumulative >= total[..., None] / 2, axis=-1)
        in_bin = np.take_along_axis(power, k[..., None], axis=-1)[..., 0]
        before = np.take_along_axis(cumulative, k[..., None], axis=-1)[..., 0] - in_bin
        share = (total / 2 - before) / in_bin
        median_hz = lo_edge[k] + share * width[k]
    empty = ~(total > 0)
    return np.where(empty, np.nan, median_hz), np.where(empty, np.nan, mean_hz)


def welch_psd(emg: np.ndarray, config: FatigueConfig) -> tuple[np.ndarray, np.ndarray]:
    """Welch spectrum of raw EMG ``(n_samples, ...)`` (at least one segment long): ``(freqs, psd[..., f])``, by
    :func:`msk_core.signal.spectrum.hann_welch` (scipy's ``welch`` numbers, every segment at once)."""
    x = np.moveaxis(np.asarray(emg, dtype=float), 0, -1)
    n = config.segment_samples
    if x.shape[-1] < n:
        raise InputError(f"need at least one Welch segment of {n} samples", field="emg", value=x.shape[-1])
    return hann_welch(x, config.rate_hz, n)


@dataclass(frozen=True)
class RepSpectrum:
    """One rep's spectral values per electrode (arrays ``(n_channels,)``; ``nan`` where the electrode shows no EMG
    above the noise floor in the rep). ``active_start``/``active_end``: sample indices (end exclusive) of each
    electrode's active part, counted from the recording's (tracker's) first sample."""

    rep: int  # 1-based number in the set
    t_start: float
    t_end: float
    median_hz: np.ndarray
    mean_hz: np.ndarray
    active_rms_v: np.ndarray  # 20-450 Hz RMS of the active part
    active_start: np.ndarray
    active_end: np.ndarray


def active_part(rep_emg: np.ndarray, config: FatigueConfig) -> tuple[np.ndarray, np.ndarray]:
    """Per channel, ``(start, end)`` sample offsets (end exclusive) of the active part of one rep's raw EMG."""
    x = np.asarray(rep_emg, dtype=float)
    n = x.shape[0]
    envelope = envelope_zero_phase_noncausal(x, EmgFilterConfig(rate_hz=config.rate_hz, bandpass_hz=EMG_BAND_HZ))
    peak = envelope.max(axis=0)
    above = envelope >= config.active_fraction * peak
    start = np.argmax(above, axis=0)
    end = n - np.argmax(above[::-1], axis=0)
    short = end - start < config.min_active_samples
    if np.any(short):  # widen around the peak, inside the rep
        centre = np.argmax(envelope, axis=0)
        wide_start = np.clip(centre - config.min_active_samples // 2, 0, max(n - config.min_active_samples, 0))
        start = np.where(short, wide_start, start)
        end = np.where(short, np.minimum(wide_start + config.min_active_samples, n), end)
    return start.astype(np.int64), end.astype(np.int64)


def rep_spectrum(
    rep_emg: np.ndarray, config: FatigueConfig, *, rep: int, t_start: float, t_end: float, first_sample: int
) -> RepSpectrum:
    """Spectral values of one rep from its raw EMG ``(n_samples, n_channels)`` (sample 0 = ``first_sample``)."""
    x = np.asarray(rep_emg, dtype=float)
    n_channels = x.shape[1]
    nan = np.full(n_channels, np.nan)
    if x.shape[0] < config.min_active_samples:
        empty = np.full(n_channels, first_sample, dtype=np.int64)
        return RepSpectrum(rep, t_start, t_end, nan, nan.copy(), nan.copy(), empty, empty.copy())
    start, end = active_part(x, config)
    median, mean, rms = nan.copy(), nan.copy(), nan.copy()
    for c in range(n_channels):
        freqs, psd = welch_psd(x[start[c] : end[c], c], config)
        in_band = (freqs >= EMG_BAND_HZ[0]) & (freqs <= EMG_BAND_HZ[1])
        rms[c] = np.sqrt(psd[in_band].sum() * (freqs[1] - freqs[0]))
        if rms[c] >= NOISE_FLOOR_RMS_V:
            median[c], mean[c] = median_and_mean_frequency(freqs, psd)
    return RepSpectrum(rep, t_start, t_end, median, mean, rms, start + first_sample, end + first_sample)


@runtime_checkable
class _Span(Protocol):
    """Anything with a start and an end time, such as a :class:`~.reps.Rep`."""

    @property
    def t_start(self) -> float: ...

    @property
    def t_end(self) -> float: ...


def _rep_times(rep: _Span | Iterable[float]) -> tuple[float, float]:
    """``(t_start, t_end)`` of a pair or of anything with ``t_start``/``t_end`` (a :class:`~.reps.Rep`)."""
    if isinstance(rep, _Span):
        t0, t1 = float(rep.t_start), float(rep.t_end)
    else:
        t0, t1 = (float(v) for v in rep)
    if not (np.isfinite(t0) and np.isfinite(t1) and t1 > t0):
        raise InputError("a rep must end after it starts", field="rep", value=(t0, t1))
    return t0, t1


def _rep_samples(t_start: float, t_end: float, t0: float, rate_hz: float) -> tuple[int, int]:
    """Sample range ``[i0, i1)`` of the samples at ``t0 + i / rate`` with ``t_start <= t < t_end``."""
    return int(np.ceil((t_start - t0) * rate_hz - 1e-9)), int(np.ceil((t_end - t0) * rate_hz - 1e-9))


def rep_spectra(emg: np.ndarray, reps: list, config: FatigueConfig, *, t0: float = 0.0) -> list[RepSpectrum]:
    """Each rep's spectral values from a whole recording ``(n_samples, n_channels)`` whose sample ``i`` is at
    ``t0 + i / rate``; ``reps``: ``(t_start, t_end)`` pairs or :class:`~msk_core.signal.reps.Rep`, in order."""
    x = np.asarray(emg, dtype=float)
    if x.ndim != 2:
        raise InputError("EMG must be shaped (n_samples, n_channels)", field="emg", value=x.shape)
    out = []
    for number, rep in enumerate(reps, start=1):
        t_start, t_end = _rep_times(rep)
        i0, i1 = _rep_samples(t_start, t_end, t0, config.rate_hz)
        if i0 < 0 or i1 > x.shape[0]:
            raise InputError(
                f"rep {number} ({t_start:.3f}-{t_end:.3f} s) is outside the recording "
                f"({t0:.3f}-{t0 + x.shape[0] / config.rate_hz:.3f} s)",
                field="reps",
            )
        out.append(rep_spectrum(x[i0:i1], config, rep=number, t_start=t_start, t_end=t_end, first_sample=i0))
    return out


@dataclass(frozen=True)
class SpectralTrend:
    """Trend of one spectral value across the set's reps, per electrode (arrays ``(n_channels,)``; ``nan`` with fewer
    than two reps with a value)."""

    slope_hz_per_rep: np.ndarray  # least-squares slope against the rep number
    slope_se_hz_per_rep: np.ndarray  # its standard error from the residuals (nan with fewer than 3 reps)
    slope_pct_per_rep: np.ndarray  # the slope in % of the first reps' mean
    first_hz: np.ndarray  # mean of the first reps
    last_hz: np.ndarray  # mean of the last reps
    change_hz: np.ndarray  # last - first
    change_pct: np.ndarray
    n_reps: np.ndarray  # reps with a value


@dataclass(frozen=True)
class FatigueTrend:
    median: SpectralTrend
    mean: SpectralTrend


def _trend(rep_numbers: np.ndarray, values: np.ndarray, baseline_reps: int) -> SpectralTrend:
    n_channels = values.shape[1]
    fields = {
        k: np.full(n_channels, np.nan)
        for k in (
            "slope_hz_per_rep",
            "slope_se_hz_per_rep",
            "slope_pct_per_rep",
            "first_hz",
            "last_hz",
            "change_hz",
            "change_pct",
        )
    }
    counts = np.zeros(n_channels, dtype=np.int64)
    for c in range(n_channels):
        ok = np.isfinite(values[:, c])
        x, y = rep_numbers[ok].astype(float), values[ok, c]
        counts[c] = y.size
        if y.size < 2:
            continue
        k = min(baseline_reps, y.size // 2)
        first, last = y[:k].mean(), y[-k:].mean()
        slope, intercept = np.polyfit(x, y, 1)
        fields["slope_hz_per_rep"][c] = slope
        if y.size > 2:  # one rep's value scatters by several Hz: the slope of a set is uncertain, and says so
            residuals = y - (slope * x + intercept)
            spread = ((x - x.mean()) ** 2).sum()
            fields["slope_se_hz_per_rep"][c] = np.sqrt(residuals @ residuals / (y.size - 2) / spread)
        fields["slope_pct_per_rep"][c] = 100.0 * slope / first
        fields["first_hz"][c], fields["last_hz"][c] = first, last
        fields["change_hz"][c] = last - first
        fields["change_pct"][c] = 100.0 * (last - first) / first
    return SpectralTrend(n_reps=counts, **fields)


def fatigue_trend(spectra: list[RepSpectrum], *, baseline_reps: int = BASELINE_REPS) -> FatigueTrend:
    """The set's trend of median and mean frequency from its reps' values (in rep order). The first/last reps are
    the first/last ``baseline_reps`` reps with a value (half of them each when there are fewer than twice that)."""
    if not spectra:
        raise InputError("no reps to take a trend over", field="spectra")
    numbers = np.array([s.rep for s in spectra])
    return FatigueTrend(
        median=_trend(numbers, np.stack([s.median_hz for s in spectra]), baseline_reps),
        mean=_trend(numbers, np.stack([s.mean_hz for s in spectra]), baseline_reps),
    )


class FatigueTracker:
    """Live fatigue index of ``n_channels`` electrodes over one set at a time.

    ``process(chunk)`` appends raw EMG ``(n_samples, n_channels)`` (sample ``i`` at ``t0 + i / rate``);
    ``end_rep(t_start, t_end)`` reports a rep that ended. A rep's values are computed as soon as the EMG up to its end
    has arrived (by whichever call completes it) and returned by that call; :attr:`spectra` and :attr:`trend` hold the
    current set. ``start_set()`` begins the next set (rep numbers restart at 1).

    State: the last ``max_history_s`` of raw EMG, the reps waiting for their EMG and the set's values."""

    def __init__(self, config: FatigueConfig, n_channels: int, *, t0: float = 0.0) -> None:
        if n_channels < 1:
            raise ConfigError("need at least one channel", field="n_channels", value=n_channels)
        self.config = config
        self.n_channels = n_channels
        self.t0 = float(t0)
        self.samples_seen = 0
        self._keep = int(round(config.max_history_s * config.rate_hz))
        # history: rows [0, _filled) of a buffer twice the kept length, shifted down when full (amortised O(1))
        self._buffer = np.zeros((2 * self._keep, n_channels))
        self._filled = 0
        self._pending: list[tuple[float, float]] = []
        self.spectra: list[RepSpectrum] = []

    @property
    def trend(self) -> FatigueTrend | None:
        """The current set's trend (``None`` before its first rep)."""
        return fatigue_trend(self.spectra, baseline_reps=self.config.baseline_reps) if self.spectra else None

    def start_set(self) -> None:
        """The next reps belong to a new set. Reps still waiting for their EMG stay in the set they ended in."""
        self.spectra = []

    def process(self, chunk: np.ndarray) -> list[RepSpectrum]:
        x = np.asarray(chunk, dtype=float)
        if x.ndim == 1:
            x = x[:, None]
        if x.ndim != 2 or x.shape[1] != self.n_channels:
            raise InputError(f"EMG must be shaped (n_samples, {self.n_channels})", field="emg", value=x.shape)
        if x.shape[0] >= self._keep:
            self._buffer[: self._keep] = x[-self._keep :]
            self._filled = self._keep
        else:
            if self._filled + x.shape[0] > self._buffer.shape[0]:
                kept = self._keep - x.shape[0]
                self._buffer[:kept] = self._buffer[self._filled - kept : self._filled]
                self._filled = kept
            self._buffer[self._filled : self._filled + x.shape[0]] = x
            self._filled += x.shape[0]
        self.samples_seen += x.shape[0]
        return self._complete()

    def end_rep(self, t_start: float, t_end: float) -> list[RepSpectrum]:
        t_start, t_end = _rep_times((t_start, t_end))
        self._pending.append((t_start, t_end))
        return self._complete()

    def _complete(self) -> list[RepSpectrum]:
        done = []
        while self._pending:
            t_start, t_end = self._pending[0]
            i0, i1 = _rep_samples(t_start, t_end, self.t0, self.config.rate_hz)
            if i1 > self.samples_seen:
                break  # its EMG has not all arrived
            self._pending.pop(0)
            first_kept = self.samples_seen - self._filled
            if i0 < first_kept:
                raise InputError(
                    f"rep {t_start:.3f}-{t_end:.3f} s starts before the EMG the tracker keeps "
                    f"({self.config.max_history_s:g} s)",
                    field="rep",
                )
            spectrum = rep_spectrum(
                self._buffer[i0 - first_kept : i1 - first_kept],
                self.config,
                rep=len(self.spectra) + 1,
                t_start=t_start,
                t_end=t_end,
                first_sample=i0,
            )
            self.spectra.append(spectrum)
            done.append(spectrum)
        return done
