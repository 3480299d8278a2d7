"""Live signal quality of each EMG electrode from its raw samples: good, check or bad, with the reasons.

Every ``hop`` (0.125 s) the last ``window`` (0.5 s) of raw EMG of each channel is measured (:func:`window_metrics`)
and five faults are judged, each at one or two levels with hysteresis (raised after ``RAISE_HOPS`` windows in a row
that show it, cleared after ``CLEAR_HOPS`` windows in a row that show it gone, and level thresholds that clear at
``CLEAR_RATIO`` of the raise level), so a state neither chatters nor lingers:

==================  =====  =========================================================================================
fault               level  rule (per 0.5 s window)
==================  =====  =========================================================================================
saturation          check  at least ``SATURATION_CHECK_FRACTION`` of the samples at the rail (``|x| >=
                    bad    RAIL_FRACTION_OF_RANGE * range``); bad from ``SATURATION_BAD_FRACTION``
flat line           bad    standard deviation below ``FLAT_STD_V`` or ``FLAT_REPEAT_FRACTION`` of consecutive samples
                           identical (samples at the rail excepted: that is saturation)
contact: artefact   check  power below 20 Hz at least the 20-450 Hz power and its RMS at least ``LOW_FREQ_CHECK_V``;
                    bad    bad from ``LOW_FREQ_BAD_V``
contact: no signal  check  20-450 Hz RMS below ``NOISE_FLOOR_RMS_V`` (an electrode off the skin, or a muscle so
                           silent that nothing can be told from it)
mains               check  the 50/60 Hz lines and harmonics hold at least ``MAINS_CHECK_FRACTION`` of the 20-450 Hz
                    bad    power; bad from ``MAINS_BAD_FRACTION``
==================  =====  =========================================================================================

An electrode's state is the worst level of its raised faults (``unknown`` until ``RAISE_HOPS`` windows are
measured: 0.625 s). A lifted electrode shows as a contact fault (its inputs float: a large low-frequency artefact,
often driven to the rail, often with mains pickup) or as no signal; a broadband test above 450 Hz is not made, because
the Trigno's own 450 Hz low-pass removes what it would look at, and broadband noise inside 20-450 Hz cannot be told
from EMG by its spectrum. Mains interference is judged against the EMG it corrupts, so a contraction masks it: a
window in which the interference last measured would stay under the raise level neither raises nor clears it (the
flag holds through a rep and clears at the first window that could see the hum and does not).
Where each threshold comes from is written beside it. The monitor is causal with explicit state (the last window's
samples, the detectors' counters); :class:`ElectrodeQualityMonitor` fed in chunks of any size gives exactly the
verdicts of :func:`assess_quality` on the whole recording.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from msk_core.errors import ConfigError, InputError
from msk_core.signal.spectrum import hann_welch
from msk_core.units import TRIGNO_EMG_RANGE_V

# --- device and analysis window ---------------------------------------------------------------------------------------

# Delsys Trigno EMG input range (+-11 mV): msk_core.units, where the simulated Trigno reads it too.
# The EMG band: the Trigno's own hardware band-pass (2-pole high-pass at 20 Hz, 4-pole low-pass at 450 Hz, MAN-039)
# and the band the envelope chain keeps (msk_core.signal.emg.EmgFilterConfig.bandpass_hz).
EMG_BAND_HZ = (20.0, 450.0)
MAINS_FREQUENCIES_HZ = (50.0, 60.0)  # both families are checked: the session need not know the country
WINDOW_S = 0.5  # 2 Hz spectral resolution: a 50 Hz line and a 60 Hz line land on their own bins
HOP_S = 0.125  # a verdict 8 times a second
RAISE_HOPS = 2  # a fault shows in 2 windows in a row before it is raised: no single-window blip raises it
CLEAR_HOPS = 3  # ... and is gone from 3 in a row before it clears: worst case 0.5 + 3 * 0.125 s after it ends


#: A channel with this share of its power below the EMG band is not surface EMG (a force, a load cell, a goniometer, a
#: trigger): on the real recordings of ../shared, 0.2-43 % of every EMG channel's power lies below 20 Hz (the most, a
#: quiet electrode), 99.3-100 % of every force-plate and load-cell channel's
NOT_EMG_BELOW_BAND_SHARE = 0.9


def below_band_share(x: np.ndarray, rate_hz: float) -> np.ndarray:
    """Per channel of a whole recording ``x[n_samples, n_channels]``, the share of its power (Welch, ~2 s Hann segments,
    each segment's mean removed) below the EMG band (:data:`EMG_BAND_HZ`); its finite samples only; NaN for a channel
    with no power (zero throughout) or fewer finite samples than a segment. One channel at a time (memory: a segment
    matrix of one channel, not of all)."""
    x = np.asarray(x, dtype=float).reshape(len(x), -1)
    n = int(2 ** np.ceil(np.log2(max(rate_hz, 1.0) * 2.0)))  # ~2 s segments: ~0.5 Hz bins
    shares = np.full(x.shape[1], np.nan)
    for c in range(x.shape[1]):
        column = x[np.isfinite(x[:, c]), c]  # a gap left out (a NaN would make every bin NaN)
        if column.size < n:
            continue
        freqs, psd = hann_welch(column, rate_hz, n)
        total = psd.sum()
        if total > 0:
            shares[c] = psd[freqs < EMG_BAND_HZ[0]].sum() / total
    return shares


def check_emg_rate(rate_hz: float) -> None:
    """Refuse an EMG rate that cannot carry the 20-450 Hz band (the quality monitor's and the fatigue index's)."""
    if not (np.isfinite(rate_hz) and rate_hz > 2 * EMG_BAND_HZ[1]):
        raise ConfigError(
            f"the EMG rate must exceed {2 * EMG_BAND_HZ[1]:.0f} Hz (twice the band's top)",
            field="rate_hz",
            value=rate_hz,
        )


# --- thresholds -------------------------------------------------------------------------------------------------------

# Saturation. A sample "at the rail" is within 5 % of the range: the Trigno's range is "about" 11 mV, so its exact
# clipping level is not known to better than that; surface EMG of the pyomeca-upper Trigno recording peaks at 4.6 mV.
RAIL_FRACTION_OF_RANGE = 0.95
SATURATION_CHECK_FRACTION = 0.001  # any clipping (1 sample in a 0.5 s window at 2 kHz) caps the amplitude seen
SATURATION_BAD_FRACTION = 0.01  # 1 % of the samples clipped: the envelope is capped over whole bursts
PINNED_FRACTION = 0.5  # most of the window at the rail: the channel is pinned there (not judged flat nor silent)
# Flat line. A live Trigno channel never holds still: the quietest 0.5 s window of a connected channel of the
# pyomeca-upper recording has a standard deviation of 0.9 uV, the 16-bit converter's step over 22 mV is 0.34 uV;
# 0.1 uV is below one step, so only a held or zero-filled channel is that still.
FLAT_STD_V = 0.1e-6
# Trigno IM sensors (native 1111 Hz) are upsampled to 2 kHz by repeating samples: 45 % of their consecutive samples
# are equal in the pyomeca-upper recording (the other channels: under 1 %). 90 % means the signal stopped moving.
FLAT_REPEAT_FRACTION = 0.9
# Contact (low-frequency artefact). Movement artefacts and electrode-skin potentials live below 20 Hz (De Luca,
# Gilmore, Kuznetsov, Roy 2010, J Biomech 43:1573, the reason for the 20 Hz corner of the EMG band). An artefact is
# a contact fault when it outweighs the EMG (power below 20 Hz >= the 20-450 Hz power) and is large in absolute terms:
# on the pyomeca-upper recording (electrodes in good contact, arm movements) the low-frequency RMS of a 0.5 s window
# reaches 0.15 mV at most (trapezius) and exceeds the band power only at rest, at under 30 uV.
LOW_FREQ_RATIO = 1.0
LOW_FREQ_CHECK_V = 0.25e-3  # 1.7x the largest artefact of a well-attached electrode measured on the real recording
LOW_FREQ_BAD_V = 1.0e-3  # 9 % of the range: an electrode rocking or lifting off the skin
# Contact (no signal). Quietest 0.5 s windows of the connected pyomeca-upper channels: 3.2-35 uV (20-450 Hz RMS),
# except the subscapularis (a deep muscle out of reach of a surface electrode): 0.7 uV. Below 1.5 uV nothing but the
# sensor's own noise is left: an electrode off the skin reads the same.
NOISE_FLOOR_RMS_V = 1.5e-6
# Mains. CleanEMG (Abser, MacIsaac, Chan, Green 2011, CMBES 34) puts the point where power-line interference starts to
# matter at a signal-to-interference ratio of about 9 dB (interference = 11 % of the power). One 0.5 s window cannot
# resolve that: on the pyomeca-upper recording (no visible hum: line bins within 1-3x their neighbours over the 5.8 s)
# the line-power estimate of single windows reaches 30 % from the EMG's own spectral fluctuation. So: check when the
# lines hold half the band power (interference as strong as the EMG, 0 dB), bad at 80 % (interference 4x the EMG).
MAINS_CHECK_FRACTION = 0.5
MAINS_BAD_FRACTION = 0.8
MAINS_MAX_HZ = EMG_BAND_HZ[1]  # harmonics up to the top of the EMG band
MAINS_BASELINE_HZ = 20.0  # the EMG under a line: mean of the bins within 20 Hz of it that are not near any line
NUMERICAL_FLOOR_V = 1e-9  # below 1 nV of band RMS (a constant window's rounding) no spectral share is computed
CLEAR_RATIO = 0.5  # a raised fault clears below half its raise level (level hysteresis beside the window counts)


class ElectrodeState(enum.Enum):
    """Verdict on one electrode, in increasing severity (``unknown`` before its first window)."""

    UNKNOWN = "unknown"
    GOOD = "good"
    CHECK = "check"
    BAD = "bad"

    @property
    def severity(self) -> int:
        return _SEVERITY[self]


_SEVERITY = {ElectrodeState.UNKNOWN: -1, ElectrodeState.GOOD: 0, ElectrodeState.CHECK: 1, ElectrodeState.BAD: 2}


class Fault(enum.Enum):
    """Why an electrode is not good."""

    SATURATION = "saturation"
    FLAT_LINE = "flat line"
    CONTACT_ARTEFACT = "contact: low-frequency artefact"
    NO_SIGNAL = "contact: no signal above the noise floor"
    MAINS = "mains interference"


@dataclass(frozen=True)
class QualityConfig:
    """Device facts and the analysis window. ``range_v``: the EMG input range (the rail is ``+-range_v``)."""

    rate_hz: float
    range_v: float = TRIGNO_EMG_RANGE_V
    mains_hz: tuple[float, ...] = MAINS_FREQUENCIES_HZ
    window_s: float = WINDOW_S
    hop_s: float = HOP_S

    def __post_init__(self) -> None:
        check_emg_rate(self.rate_hz)
        if not (np.isfinite(self.range_v) and self.range_v > 0):
            raise ConfigError("the input range must be a positive voltage", field="range_v", value=self.range_v)
        if not self.mains_hz or not all(0 < f < MAINS_MAX_HZ for f in self.mains_hz):
            raise ConfigError(
                f"mains frequencies must lie in (0, {MAINS_MAX_HZ:.0f}) Hz", field="mains_hz", value=self.mains_hz
            )
        if not 0 < self.hop_s <= self.window_s:
            raise ConfigError("need 0 < hop_s <= window_s", field="hop_s", value=(self.hop_s, self.window_s))
        if self.window_samples < 64:
            raise ConfigError("the window holds fewer than 64 samples", field="window_s", value=self.window_s)

    @property
    def window_samples(self) -> int:
        """``window_s`` in samples, exactly (not a faster FFT length: the bins' spacing 1 / ``window_s`` is what puts
        the mains lines on bins; 1080 samples instead of the Trigno's 1074 measured 10 % of a 50 Hz line
        off it)."""
        return int(round(self.window_s * self.rate_hz))

    @property
    def hop_samples(self) -> int:
        return max(1, int(round(self.hop_s * self.rate_hz)))

    @property
    def rail_v(self) -> float:
        return RAIL_FRACTION_OF_RANGE * self.range_v


@dataclass(frozen=True)
class WindowMetrics:
    """What the detectors look at, per window and channel (arrays ``(n_windows, n_channels)``; one window: ``(n,)``)."""

    band_rms_v: np.ndarray  # 20-450 Hz RMS
    low_freq_rms_v: np.ndarray  # RMS below 20 Hz (window mean removed)
    mains_fraction: np.ndarray  # share of the 20-450 Hz power in the mains lines (the stronger family)
    mains_hz: np.ndarray  # that family's fundamental
    rail_fraction: np.ndarray  # share of samples at the rail
    repeat_fraction: np.ndarray  # share of consecutive samples equal (off the rail)
    std_v: np.ndarray  # standard deviation of the raw window

    @property
    def low_freq_ratio(self) -> np.ndarray:
        """Power below 20 Hz over the 20-450 Hz power (``inf`` when only the low part is above rounding)."""
        low, band, floor = np.asarray(self.low_freq_rms_v) ** 2, np.asarray(self.band_rms_v) ** 2, NUMERICAL_FLOOR_V**2
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(band > floor, low / np.where(band > floor, band, 1.0), np.where(low > floor, np.inf, 0.0))

    def row(self, k: int) -> WindowMetrics:
        return WindowMetrics(*(np.asarray(getattr(self, f))[k] for f in _METRIC_FIELDS))


_METRIC_FIELDS = (
    "band_rms_v",
    "low_freq_rms_v",
    "mains_fraction",
    "mains_hz",
    "rail_fraction",
    "repeat_fraction",
    "std_v",
)


@lru_cache(maxsize=16)
def spectral_weights(window_samples: int, rate_hz: float, mains_hz: tuple[float, ...]) -> np.ndarray:
    """Weights ``(n_freqs, 2 + n_families)`` that turn a window's PSD into powers (× the bin width): the 20-450 Hz
    band, below 20 Hz (DC excluded), and per mains family the power its lines hold above the EMG baseline beside each
    line (a harmonic's line bins minus, per line bin, the mean of its baseline bins). All three are linear in the
    PSD, so one matrix product measures every window and channel; made once per configuration."""
    freqs = np.fft.rfftfreq(window_samples, 1.0 / rate_hz)
    df = freqs[1] - freqs[0]
    lo, hi = EMG_BAND_HZ
    band = (freqs >= lo) & (freqs <= hi)
    lines = np.array([h for f0 in mains_hz for h in np.arange(f0, MAINS_MAX_HZ + 1e-9, f0)])
    distance_to_any_line = np.min(np.abs(freqs[:, None] - lines[None, :]), axis=1)
    # A Hann window spreads an on-bin line over 3 bins (and 2 Hz of mains drift moves it by at most one bin).
    line_half_width = 1.01 * df
    away_from_lines = distance_to_any_line > 2 * line_half_width
    weights = np.zeros((freqs.size, 2 + len(mains_hz)))
    weights[band, 0] = 1.0
    weights[(freqs > 0) & (freqs < lo), 1] = 1.0
    for i, f0 in enumerate(mains_hz):
        for h in np.arange(f0, MAINS_MAX_HZ + 1e-9, f0):
            on_line = band & (np.abs(freqs - h) <= line_half_width)
            beside = band & away_from_lines & (np.abs(freqs - h) <= MAINS_BASELINE_HZ)
            if on_line.any() and beside.any():
                weights[on_line, 2 + i] += 1.0
                weights[beside, 2 + i] -= on_line.sum() / beside.sum()
    weights *= df
    weights.flags.writeable = False
    return weights


def window_metrics(windows: np.ndarray, config: QualityConfig) -> WindowMetrics:
    """Metrics of raw EMG windows ``(n_windows, n_channels, window_samples)`` in volts."""
    w = np.asarray(windows, dtype=np.float64)
    if w.ndim != 3 or w.shape[2] != config.window_samples:
        raise InputError(
            f"windows must be shaped (n_windows, n_channels, {config.window_samples})", field="windows", value=w.shape
        )
    _, psd = hann_welch(w, config.rate_hz, w.shape[2])  # one segment: scipy's periodogram
    powers = psd @ spectral_weights(w.shape[2], config.rate_hz, tuple(config.mains_hz))
    band_power, low_power = powers[..., 0], powers[..., 1]
    excess = np.moveaxis(powers[..., 2:], -1, 0)
    strongest = np.argmax(excess, axis=0)
    line_power = np.maximum(np.take_along_axis(excess, strongest[None], axis=0)[0], 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        mains_fraction = np.where(band_power > NUMERICAL_FLOOR_V**2, np.minimum(line_power / band_power, 1.0), 0.0)
    at_rail = np.abs(w) >= config.rail_v
    repeats = (np.diff(w, axis=-1) == 0) & ~at_rail[..., 1:]
    return WindowMetrics(
        band_rms_v=np.sqrt(band_power),
        low_freq_rms_v=np.sqrt(low_power),
        mains_fraction=mains_fraction,
        mains_hz=np.asarray(config.mains_hz, dtype=float)[strongest],
        rail_fraction=at_rail.mean(axis=-1),
        repeat_fraction=repeats.mean(axis=-1),
        std_v=w.std(axis=-1),
    )


# --- detectors --------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Detector:
    fault: Fault
    level: ElectrodeState


DETECTORS = (
    _Detector(Fault.SATURATION, ElectrodeState.CHECK),
    _Detector(Fault.SATURATION, ElectrodeState.BAD),
    _Detector(Fault.FLAT_LINE, ElectrodeState.BAD),
    _Detector(Fault.CONTACT_ARTEFACT, ElectrodeState.CHECK),
    _Detector(Fault.CONTACT_ARTEFACT, ElectrodeState.BAD),
    _Detector(Fault.NO_SIGNAL, ElectrodeState.CHECK),
    _Detector(Fault.MAINS, ElectrodeState.CHECK),
    _Detector(Fault.MAINS, ElectrodeState.BAD),
)


def _evidence(m: WindowMetrics, line_power_seen: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per detector and channel: does this window show the fault (present), show it gone (absent), or neither?

    ``line_power_seen``: per channel, the mains line power of the last window that showed mains interference. A
    window whose EMG is so strong that this interference would not reach the raise level cannot tell whether it is
    gone (a contraction masks it): such a window neither raises nor clears mains."""
    sat, flat_still = m.rail_fraction, (m.std_v < FLAT_STD_V) | (m.repeat_fraction >= FLAT_REPEAT_FRACTION)
    pinned = sat >= PINNED_FRACTION  # saturated: neither flat nor silent, whatever it looks like
    flat = flat_still & ~pinned
    ratio = m.low_freq_ratio
    band_power = m.band_rms_v**2
    present, absent = [], []  # one row per detector, in the order of DETECTORS
    for threshold in (SATURATION_CHECK_FRACTION, SATURATION_BAD_FRACTION):
        present.append(sat >= threshold)
        absent.append(sat < CLEAR_RATIO * threshold)
    present.append(flat)
    absent.append(~flat)
    for threshold in (LOW_FREQ_CHECK_V, LOW_FREQ_BAD_V):
        present.append((ratio >= LOW_FREQ_RATIO) & (m.low_freq_rms_v >= threshold))
        absent.append((ratio < CLEAR_RATIO * LOW_FREQ_RATIO) | (m.low_freq_rms_v < CLEAR_RATIO * threshold))
    quiet = (m.band_rms_v < NOISE_FLOOR_RMS_V) & ~flat & ~pinned
    present.append(quiet)
    absent.append((m.band_rms_v >= NOISE_FLOOR_RMS_V / CLEAR_RATIO) | flat | pinned)
    for threshold in (MAINS_CHECK_FRACTION, MAINS_BAD_FRACTION):
        visible = line_power_seen >= threshold * band_power
        present.append(m.mains_fraction >= threshold)
        absent.append((m.mains_fraction < CLEAR_RATIO * threshold) & visible)
    return np.array(present), np.array(absent)


@dataclass(frozen=True)
class ChannelQuality:
    """One electrode's verdict: its state and the faults behind it, worst first."""

    state: ElectrodeState
    faults: tuple[Fault, ...] = ()
    clearing: tuple[Fault, ...] = ()  # raised faults this window no longer shows (cleared once enough windows agree)

    def describe(self, metrics: WindowMetrics | None = None, range_v: float = TRIGNO_EMG_RANGE_V) -> str:
        """``"bad: saturation (3.2 % of samples at the +-11 mV rail)"``; the numbers need this window's metrics."""
        if not self.faults:
            return self.state.value
        parts = [f"{f.value} (clearing)" if f in self.clearing else _describe(f, metrics, range_v) for f in self.faults]
        return f"{self.state.value}: " + "; ".join(parts)


def _describe(fault: Fault, m: WindowMetrics | None, range_v: float) -> str:
    if m is None:
        return fault.value
    if fault is Fault.SATURATION:
        return f"{fault.value} ({100 * float(m.rail_fraction):.1f} % of samples at the +-{1e3 * range_v:g} mV rail)"
    if fault is Fault.FLAT_LINE:
        return f"{fault.value} (SD {1e6 * float(m.std_v):.2f} uV, {100 * float(m.repeat_fraction):.0f} % repeats)"
    if fault is Fault.CONTACT_ARTEFACT:
        return f"{fault.value} ({1e3 * float(m.low_freq_rms_v):.2f} mV RMS below 20 Hz)"
    if fault is Fault.NO_SIGNAL:
        return f"{fault.value} ({1e6 * float(m.band_rms_v):.2f} uV RMS in 20-450 Hz)"
    share = 100 * float(m.mains_fraction)
    return f"{fault.value} ({float(m.mains_hz):g} Hz lines: {share:.0f} % of the EMG band power)"


@dataclass(frozen=True)
class QualityVerdict:
    """The electrodes' states after the window that ends at sample ``end_sample`` (exclusive, counted from the
    monitor's first sample), with that window's metrics (arrays ``(n_channels,)``)."""

    end_sample: int
    channels: tuple[ChannelQuality, ...]
    metrics: WindowMetrics
    range_v: float = TRIGNO_EMG_RANGE_V

    @property
    def states(self) -> tuple[ElectrodeState, ...]:
        return tuple(c.state for c in self.channels)

    def describe(self, channel: int) -> str:
        """One electrode's verdict in words, with this window's numbers."""
        return self.channels[channel].describe(self.metrics.row(channel), self.range_v)


@dataclass
class _Hysteresis:
    """Raised/cleared flags of every detector and channel and their run counters (the monitor's decision state)."""

    n_channels: int
    raised: np.ndarray = field(init=False)
    run_present: np.ndarray = field(init=False)
    run_absent: np.ndarray = field(init=False)
    line_power_seen: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        shape = (len(DETECTORS), self.n_channels)
        self.raised = np.zeros(shape, dtype=bool)
        self.run_present = np.zeros(shape, dtype=np.int64)
        self.run_absent = np.zeros(shape, dtype=np.int64)
        self.line_power_seen = np.zeros(self.n_channels)
        self.windows = 0

    def step(self, m: WindowMetrics) -> tuple[ChannelQuality, ...]:
        present, absent = _evidence(m, self.line_power_seen)
        self.windows += 1
        showing_mains = m.mains_fraction >= MAINS_CHECK_FRACTION
        self.line_power_seen = np.where(showing_mains, m.mains_fraction * m.band_rms_v**2, self.line_power_seen)
        # Runs count windows in a row. To raise, every window of the run shows the fault; to clear, an inconclusive
        # window (neither present nor absent: mains under a contraction) holds the run where it is.
        self.run_present = np.where(present, self.run_present + 1, 0)
        self.run_absent = np.where(absent, self.run_absent + 1, np.where(present, 0, self.run_absent))
        raise_now = ~self.raised & (self.run_present >= RAISE_HOPS)
        clear_now = self.raised & (self.run_absent >= CLEAR_HOPS)
        self.raised = (self.raised | raise_now) & ~clear_now
        return tuple(self._channel(c, present[:, c]) for c in range(self.n_channels))

    def _channel(self, c: int, present: np.ndarray) -> ChannelQuality:
        worst: dict[Fault, ElectrodeState] = {}
        for d, detector in enumerate(DETECTORS):
            if self.raised[d, c] and detector.level.severity > worst.get(detector.fault, ElectrodeState.GOOD).severity:
                worst[detector.fault] = detector.level
        if not worst:  # good only once a fault had the windows it needs to show
            return ChannelQuality(ElectrodeState.GOOD if self.windows >= RAISE_HOPS else ElectrodeState.UNKNOWN)
        order = sorted(worst, key=lambda f: (-worst[f].severity, list(Fault).index(f)))
        shown = {detector.fault for d, detector in enumerate(DETECTORS) if present[d]}
        return ChannelQuality(worst[order[0]], tuple(order), tuple(f for f in order if f not in shown))


def _check_chunk(chunk: np.ndarray, n_channels: int) -> np.ndarray:
    x = np.asarray(chunk, dtype=np.float64)
    if x.ndim == 1:
        x = x[:, None]
    if x.ndim != 2 or x.shape[1] != n_channels:
        raise InputError(f"EMG must be shaped (n_samples, {n_channels})", field="emg", value=x.shape)
    if not np.all(np.isfinite(x)):
        raise InputError("EMG holds non-finite samples", field="emg", value=int(np.sum(~np.isfinite(x))))
    return x


class ElectrodeQualityMonitor:
    """Streaming quality of ``n_channels`` electrodes. ``process(chunk)`` takes raw EMG ``(n_samples, n_channels)`` in
    volts (any ``n_samples``, also 0) and returns the verdicts of the windows completed by it, oldest first.

    State: the last ``window_samples - 1`` samples, the sample count and the detectors' hysteresis."""

    def __init__(self, config: QualityConfig, n_channels: int) -> None:
        if n_channels < 1:
            raise ConfigError("need at least one channel", field="n_channels", value=n_channels)
        self.config = config
        self.n_channels = n_channels
        self.reset()

    def reset(self) -> None:
        """Back to the start: no samples seen, every electrode unknown."""
        self.samples_seen = 0
        self._tail = np.zeros((0, self.n_channels))
        self._decisions = _Hysteresis(self.n_channels)
        self.latest: QualityVerdict | None = None

    @property
    def states(self) -> tuple[ElectrodeState, ...]:
        """Current state per electrode (``unknown`` before the first window)."""
        if self.latest is None:
            return (ElectrodeState.UNKNOWN,) * self.n_channels
        return self.latest.states

    def process(self, chunk: np.ndarray) -> list[QualityVerdict]:
        x = _check_chunk(chunk, self.n_channels)
        cfg = self.config
        w = cfg.window_samples
        first = self.samples_seen - self._tail.shape[0]  # sample index of the buffer's first row
        buffer = np.vstack([self._tail, x]) if self._tail.shape[0] else x
        self.samples_seen += x.shape[0]
        ends = _window_ends(first + w, self.samples_seen, cfg)  # window ends inside [first + w, samples_seen]
        verdicts = []
        if ends.size:
            windows = np.stack([buffer[e - first - w : e - first].T for e in ends])
            verdicts = _decide(ends, window_metrics(windows, cfg), self._decisions, cfg)
            self.latest = verdicts[-1]
        keep = min(w - 1, buffer.shape[0])
        self._tail = buffer[buffer.shape[0] - keep :].copy()
        return verdicts


def _window_ends(lowest: int, highest: int, config: QualityConfig) -> np.ndarray:
    """Ends (exclusive sample indices) of the analysed windows in ``[lowest, highest]``: ``w, w + h, w + 2h, ...``."""
    w, h = config.window_samples, config.hop_samples
    start = max(0, -(-(lowest - w) // h))
    stop = (highest - w) // h if highest >= w else -1
    return w + h * np.arange(start, stop + 1, dtype=np.int64)


def _decide(
    ends: np.ndarray, metrics: WindowMetrics, decisions: _Hysteresis, config: QualityConfig
) -> list[QualityVerdict]:
    verdicts = []
    for k, end in enumerate(ends):
        row = metrics.row(k)
        verdicts.append(QualityVerdict(int(end), decisions.step(row), row, config.range_v))
    return verdicts


def assess_quality(emg: np.ndarray, config: QualityConfig, *, block_windows: int = 256) -> list[QualityVerdict]:
    """Verdicts of a whole recording ``(n_samples, n_channels)``: what :class:`ElectrodeQualityMonitor` returns fed
    the same samples in any chunks. Windows are measured ``block_windows`` at a time (memory)."""
    x = _check_chunk(emg, np.shape(emg)[1] if np.ndim(emg) == 2 else 1)
    w = config.window_samples
    ends = _window_ends(w, x.shape[0], config)
    decisions = _Hysteresis(x.shape[1])
    views = sliding_window_view(x, w, axis=0)  # (n_samples - w + 1, n_channels, w)
    verdicts: list[QualityVerdict] = []
    for i in range(0, ends.size, block_windows):
        block = ends[i : i + block_windows]
        verdicts += _decide(block, window_metrics(views[block - w], config), decisions, config)
    return verdicts
