"""EMG processing chain: band-pass -> full-wave rectification -> low-pass envelope -> MVC normalisation -> delay.

Three ways to run the same chain:

* :class:`EmgEnvelopeFilter` — streaming, causal, explicit state; feed chunks ``(n_samples, n_channels)`` of any size.
* :func:`envelope_causal` — batch, causal (scipy ``sosfilt`` from rest). The streaming filter equals it to rounding
  (relative 1e-12) whatever the chunking.
* :func:`envelope_zero_phase_noncausal` — offline, zero-phase (``sosfiltfilt``), for calibration trials only: it uses
  future samples and must never feed the live loop.

:class:`StreamingEmgChain` chains the live envelope, :class:`NormalisationReference` and the electromechanical delay.

The streaming filter keeps each stage's state in scipy's own ``zi`` coordinates (second-order sections, transposed
direct form II). Small chunks (a Trigno frame is 27 samples) are run as one block product per stage — the exact linear
map ``[y; z'] = [[D, C], [B, A]] [u; z]`` over the chunk, derived from ``sosfilt`` itself — because calling ``sosfilt``
twice per 27-sample chunk costs more in call overhead than the filtering (benchmark: services/bench/emg.py).
Larger chunks go through ``sosfilt`` with the carried ``zi``.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
from scipy import signal

from msk_core.errors import ConfigError, InputError

# Chunks up to this size use cached block matrices; larger ones call sosfilt (same state coordinates).
_BLOCK_MAX = 64


@dataclass(frozen=True)
class EmgFilterConfig:
    """Configuration of the envelope chain. Frequencies in Hz; orders are scipy ``butter`` orders."""

    rate_hz: float
    bandpass_hz: tuple[float, float] | None = (20.0, 450.0)
    bandpass_order: int = 2  # butter(N) band-pass: 2N poles
    lowpass_hz: float = 6.0
    lowpass_order: int = 3

    def __post_init__(self) -> None:
        nyquist = self.rate_hz / 2.0
        if not (np.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise ConfigError("sample rate must be positive", field="rate_hz", value=self.rate_hz)
        if not 0 < self.lowpass_hz < nyquist:
            raise ConfigError(
                f"low-pass cut-off must be in (0, {nyquist}) Hz", field="lowpass_hz", value=self.lowpass_hz
            )
        if self.lowpass_order < 1:
            raise ConfigError("order must be >= 1", field="lowpass_order", value=self.lowpass_order)
        if self.bandpass_hz is not None:
            lo, hi = self.bandpass_hz
            if not 0 < lo < hi < nyquist:
                raise ConfigError(
                    f"band-pass edges must satisfy 0 < low < high < {nyquist} Hz (Nyquist)",
                    field="bandpass_hz",
                    value=self.bandpass_hz,
                )
            if self.bandpass_order < 1:
                raise ConfigError("order must be >= 1", field="bandpass_order", value=self.bandpass_order)

    def bandpass_sos(self) -> np.ndarray | None:
        if self.bandpass_hz is None:
            return None
        return signal.butter(self.bandpass_order, self.bandpass_hz, btype="bandpass", fs=self.rate_hz, output="sos")

    def lowpass_sos(self) -> np.ndarray:
        return signal.butter(self.lowpass_order, self.lowpass_hz, btype="lowpass", fs=self.rate_hz, output="sos")


def _as_samples(x: np.ndarray, n_channels: int | None = None) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2:
        raise InputError("EMG must be shaped (n_samples, n_channels)", field="emg", value=a.shape)
    if n_channels is not None and a.shape[1] != n_channels:
        raise InputError(f"expected {n_channels} channels", field="emg", value=a.shape)
    return a


def envelope_causal(emg: np.ndarray, config: EmgFilterConfig) -> np.ndarray:
    """Causal envelope of ``emg`` ``(n_samples, n_channels)``, all filters starting from rest."""
    x = _as_samples(emg)
    bp = config.bandpass_sos()
    if bp is not None:
        x = signal.sosfilt(bp, x, axis=0)
    return signal.sosfilt(config.lowpass_sos(), np.abs(x), axis=0)


def envelope_zero_phase_noncausal(emg: np.ndarray, config: EmgFilterConfig) -> np.ndarray:
    """NON-CAUSAL zero-phase envelope (forward-backward filtering) for offline calibration trials only.

    Each stage is applied forwards and backwards, so its magnitude response is squared and the delay is zero.
    """
    x = _as_samples(emg)
    bp = config.bandpass_sos()
    if bp is not None:
        x = signal.sosfiltfilt(bp, x, axis=0)
    return signal.sosfiltfilt(config.lowpass_sos(), np.abs(x), axis=0)


def envelope_group_delay_s(config: EmgFilterConfig, modulation_hz: float = 1.0) -> float:
    """Group delay (s) of the causal low-pass stage at ``modulation_hz``: the lag of the envelope behind the
    muscle's activity modulation. (The band-pass delays the carrier, which rectification discards.)"""
    b, a = signal.sos2tf(config.lowpass_sos())
    _, gd = signal.group_delay((b, a), w=[modulation_hz], fs=config.rate_hz)
    return float(gd[0]) / config.rate_hz


class _SosStage:
    """One linear stage; its state is scipy's ``zi`` flattened to ``(2 * n_sections, n_channels)``.

    For a chunk of ``n <= _BLOCK_MAX`` samples the stage is the exact linear map ``[y; z'] = M_n @ [u; z]``, with
    ``M_n`` measured by running ``sosfilt`` on unit impulses and unit states. The state lives in the tail of the
    current block's input buffer, so a run of equal chunk sizes moves it with one copy per chunk.
    """

    def __init__(self, sos: np.ndarray, n_channels: int) -> None:
        self.sos = sos
        self.n_channels = n_channels
        self.n_states = sos.shape[0] * 2
        self.zi = np.zeros((self.n_states, n_channels))  # always a view of the current state storage
        self._blocks: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
        self._current = 0

    def _build(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        s, n_sec = self.n_states, self.sos.shape[0]
        # Response to unit impulses at each sample from rest: columns of D (output) and B (final state).
        y_u, z_u = signal.sosfilt(self.sos, np.eye(n), axis=0, zi=np.zeros((n_sec, 2, n)))
        # Response to each unit initial state with zero input: columns of C and A.
        y_z, z_z = signal.sosfilt(self.sos, np.zeros((n, s)), axis=0, zi=np.eye(s).reshape(n_sec, 2, s))
        m = np.block([[y_u, y_z], [z_u.reshape(s, n), z_z.reshape(s, s)]])
        buf_in = np.zeros((n + s, self.n_channels))
        return m, buf_in, buf_in[:n], buf_in[n:], np.empty((n + s, self.n_channels))

    def enter_block(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Make block ``n`` current (moving the state into its buffer) and return it."""
        block = self._blocks.get(n)
        if block is None:
            block = self._blocks[n] = self._build(n)
        if self._current != n:
            np.copyto(block[3], self.zi)
            self.zi = block[3]
            self._current = n
        return block

    def process_sosfilt(self, u: np.ndarray) -> np.ndarray:
        y, zf = signal.sosfilt(self.sos, u, axis=0, zi=self.zi.reshape(-1, 2, self.n_channels))
        np.copyto(self.zi, zf.reshape(self.n_states, self.n_channels))
        return y

    def reset(self) -> None:
        self.zi[:] = 0.0


class EmgEnvelopeFilter:
    """Streaming causal envelope of ``n_channels`` EMG channels. State: the two filter stages' ``zi``.

    ``process(chunk)`` takes ``(n_samples, n_channels)`` (any ``n_samples``, also 0) and returns the envelope of
    those samples; the concatenated outputs equal :func:`envelope_causal` of the concatenated inputs.
    """

    def __init__(self, config: EmgFilterConfig, n_channels: int) -> None:
        if n_channels < 1:
            raise ConfigError("need at least one channel", field="n_channels", value=n_channels)
        self.config = config
        self.n_channels = n_channels
        bp = config.bandpass_sos()
        self._bandpass = _SosStage(bp, n_channels) if bp is not None else None
        self._lowpass = _SosStage(config.lowpass_sos(), n_channels)
        self.samples_seen = 0
        self._fast_n = -1
        self._fast: tuple = ()

    def _enter(self, n: int) -> tuple:
        lp = self._lowpass.enter_block(n)
        fast: tuple  # the seven band-pass buffers (None without a band-pass), then the four low-pass ones
        if self._bandpass is None:
            fast = (None, None, None, None, None, None, None, lp[0], lp[1], lp[2], lp[3])
        else:
            bp = self._bandpass.enter_block(n)
            # views made once per chunk size: slicing costs as much as a small copy on the hot path
            fast = (bp[0], bp[1], bp[2], bp[3], bp[4], bp[4][:n], bp[4][n:], lp[0], lp[1], lp[2], lp[3])
        self._fast_n, self._fast = n, fast
        return fast

    def process(self, chunk: np.ndarray) -> np.ndarray:
        """Envelope of the next ``chunk`` ``(n_samples, n_channels)`` (a 1-D chunk is one channel)."""
        x = chunk
        if not (type(x) is np.ndarray and x.dtype == np.float64 and x.ndim == 2):
            x = _as_samples(x)
        n, c = x.shape
        if c != self.n_channels:
            raise InputError(f"expected {self.n_channels} channels", field="emg", value=x.shape)
        self.samples_seen += n
        if 0 < n <= _BLOCK_MAX:
            # Hot path (one Trigno frame): one matmul per stage into preallocated buffers, no allocation but the result.
            fast = self._fast if n == self._fast_n else self._enter(n)
            mb, bin_b, bin_b_u, bin_b_z, bout_b, bout_b_y, bout_b_z, ml, bin_l, bin_l_u, bin_l_z = fast
            if mb is None:
                np.abs(x, out=bin_l_u)
            else:
                np.copyto(bin_b_u, x)
                np.dot(mb, bin_b, out=bout_b)  # np.dot: less dispatch overhead than matmul on small matrices
                np.copyto(bin_b_z, bout_b_z)
                np.abs(bout_b_y, out=bin_l_u)
            out = np.dot(ml, bin_l)
            np.copyto(bin_l_z, out[n:])
            return out[:n]
        if n == 0:
            return np.empty((0, c))
        if self._bandpass is not None:
            x = self._bandpass.process_sosfilt(x)
            np.abs(x, out=x)
        else:
            x = np.abs(x)
        return self._lowpass.process_sosfilt(x)

    def reset(self) -> None:
        """Back to rest (as if no sample had been seen)."""
        if self._bandpass is not None:
            self._bandpass.reset()
        self._lowpass.reset()
        self.samples_seen = 0


# --- normalisation ---------------------------------------------------------------------------------------------------


class NormalisationMode(enum.Enum):
    """Where the per-channel scale comes from."""

    MVC = "mvc"  # peak envelope of the MVC trials
    MAX_ALL_TRIALS = "max_all_trials"  # max over MVC and task trials (heavy lifts often exceed the "MVC")


@dataclass(frozen=True)
class NormalisationReference:
    """Per-channel divisor of envelopes. Serialisable for the subject profile."""

    scale: np.ndarray
    mode: NormalisationMode
    channels: tuple[str, ...] = ()

    def normalise(self, envelope: np.ndarray) -> np.ndarray:
        """``envelope / scale``. Never clipped: values above 1 mean activity beyond the reference."""
        env = np.asarray(envelope, dtype=float)
        if env.shape[-1] != self.scale.shape[0]:
            raise InputError(f"expected {self.scale.shape[0]} channels", field="envelope", value=env.shape)
        return env / self.scale

    def to_dict(self) -> dict[str, object]:
        return {"scale": self.scale.tolist(), "mode": self.mode.value, "channels": list(self.channels)}

    @classmethod
    def from_dict(cls, d: dict[str, object]) -> NormalisationReference:
        try:
            mode = NormalisationMode(d.get("mode"))
        except ValueError:
            raise ConfigError(
                f"unknown normalisation mode; expected one of {[m.value for m in NormalisationMode]}",
                field="mode",
                value=d.get("mode"),
            ) from None
        try:
            scale = np.asarray(d["scale"], dtype=float).reshape(-1)
        except (KeyError, ValueError, TypeError) as exc:
            raise ConfigError(f"invalid normalisation scale: {exc}", field="scale") from exc
        channels = d.get("channels", ())
        if not isinstance(channels, (list, tuple)) or not all(isinstance(c, str) for c in channels):
            raise ConfigError("must be a list of channel labels", field="channels", value=channels)
        return cls(scale=_check_scale(scale), mode=mode, channels=tuple(channels))


def _check_scale(scale: np.ndarray) -> np.ndarray:
    bad = np.flatnonzero(~(np.isfinite(scale) & (scale > 0)))
    if bad.size:
        raise InputError(
            f"channel {int(bad[0])} has no usable reference amplitude (flat or missing EMG)",
            field="scale",
            value=float(scale[bad[0]]),
        )
    return scale


#: The MVC amplitude convention: the highest 0.5 s mean of the envelope (:func:`windowed_peak`).
MVC_WINDOW_S = 0.5


def mvc_window_samples(rate_hz: float) -> int:
    """:data:`MVC_WINDOW_S` in samples of an envelope at ``rate_hz`` (at least 1)."""
    return max(1, int(round(MVC_WINDOW_S * rate_hz)))


def windowed_peak(envelope: np.ndarray, window_samples: int = 1) -> np.ndarray:
    """Per channel, the highest mean of the envelope over ``window_samples`` consecutive samples.

    With 1 sample this is the plain peak. The peak of an EMG envelope sits on its ripple: on a sustained maximal
    contraction it exceeds the contraction's mean level by ~10-15 % (6 Hz low-pass of rectified noise), so MVC
    amplitudes are conventionally the highest 0.5-1 s mean (Konrad, *The ABC of EMG*, 2005; SENIAM) - otherwise every
    normalised envelope reads ~10-15 % low.
    """
    a = _as_samples(envelope)
    if not (isinstance(window_samples, (int, np.integer)) and 1 <= window_samples):
        raise ConfigError(
            "the MVC window must be a whole number of samples >= 1", field="window_samples", value=window_samples
        )
    if window_samples > a.shape[0]:
        raise InputError(
            f"the MVC trial ({a.shape[0]} samples) is shorter than the window",
            field="window_samples",
            value=window_samples,
        )
    if window_samples == 1:
        return a.max(axis=0)
    csum = np.vstack([np.zeros((1, a.shape[1])), np.cumsum(a, axis=0)])
    return ((csum[window_samples:] - csum[:-window_samples]) / window_samples).max(axis=0)


def normalisation_reference(
    mvc_envelopes: list[np.ndarray],
    *,
    task_envelopes: list[np.ndarray] | None = None,
    mode: NormalisationMode = NormalisationMode.MVC,
    channels: tuple[str, ...] = (),
    window_samples: int = 1,
) -> NormalisationReference:
    """Reference from envelopes ``(n_samples, n_channels)`` of MVC trials (and task trials for MAX_ALL_TRIALS).

    ``window_samples``: the amplitude is the highest mean over this many samples (see :func:`windowed_peak`; e.g.
    0.5 s worth); 1 = the plain envelope peak."""
    if not mvc_envelopes:
        raise InputError("at least one MVC trial is needed", field="mvc_envelopes")
    peaks = np.max(np.vstack([windowed_peak(e, window_samples) for e in mvc_envelopes]), axis=0)
    if mode is NormalisationMode.MAX_ALL_TRIALS:
        if not task_envelopes:
            raise InputError("MAX_ALL_TRIALS needs the task trials", field="task_envelopes")
        task = np.max(np.vstack([windowed_peak(e, window_samples) for e in task_envelopes]), axis=0)
        peaks = np.maximum(peaks, task)
    if channels and len(channels) != peaks.shape[0]:
        raise InputError(f"{len(channels)} channel names for {peaks.shape[0]} channels", field="channels")
    return NormalisationReference(scale=_check_scale(peaks), mode=mode, channels=tuple(channels))


# --- electromechanical delay -----------------------------------------------------------------------------------------


def delay_samples(delay_s: float, rate_hz: float) -> int:
    """Electromechanical delay in whole samples (rounded)."""
    if not (np.isfinite(delay_s) and delay_s >= 0):
        raise ConfigError("electromechanical delay must be >= 0 s", field="delay_s", value=delay_s)
    return int(round(delay_s * rate_hz))


def delay_batch(x: np.ndarray, n_delay: int, *, initial: float = 0.0) -> np.ndarray:
    """``y[t] = x[t - n_delay]`` (``initial`` before the start): activation lags the envelope."""
    a = _as_samples(x)
    if n_delay == 0:
        return a.copy()
    pad = np.full((min(n_delay, a.shape[0]), a.shape[1]), initial)
    return np.vstack([pad, a[: max(a.shape[0] - n_delay, 0)]])


class DelayLine:
    """Streaming ``n_delay``-sample delay with explicit state (the last ``n_delay`` inputs)."""

    def __init__(self, n_delay: int, n_channels: int, *, initial: float = 0.0) -> None:
        if n_delay < 0:
            raise ConfigError("delay must be >= 0 samples", field="n_delay", value=n_delay)
        self.n_delay = n_delay
        self.buffer = np.full((n_delay, n_channels), initial)

    def process(self, chunk: np.ndarray) -> np.ndarray:
        x = _as_samples(chunk, self.buffer.shape[1])
        if self.n_delay == 0:
            return x.copy()
        joined = np.vstack([self.buffer, x])
        self.buffer = joined[joined.shape[0] - self.n_delay :].copy()
        return joined[: x.shape[0]]


# --- the whole live chain --------------------------------------------------------------------------------------------


class StreamingEmgChain:
    """Live raw EMG -> envelope -> normalised -> delayed by the electromechanical delay. Explicit state: the
    envelope filter's and the delay line's. ``process(chunk)`` equals :func:`emg_chain_batch` on the concatenation."""

    def __init__(self, config: EmgFilterConfig, reference: NormalisationReference, *, delay_s: float = 0.0) -> None:
        n = int(reference.scale.shape[0])
        self.config = config
        self.reference = reference
        self.envelope = EmgEnvelopeFilter(config, n)
        self.delay = DelayLine(delay_samples(delay_s, config.rate_hz), n)

    def process(self, chunk: np.ndarray) -> np.ndarray:
        return self.delay.process(self.reference.normalise(self.envelope.process(chunk)))

    def reset(self) -> None:
        self.envelope.reset()
        self.delay = DelayLine(self.delay.n_delay, self.delay.buffer.shape[1])


def emg_chain_batch(
    emg: np.ndarray, config: EmgFilterConfig, reference: NormalisationReference, *, delay_s: float = 0.0
) -> np.ndarray:
    """Batch causal equivalent of :class:`StreamingEmgChain`."""
    env = reference.normalise(envelope_causal(emg, config))
    return delay_batch(env, delay_samples(delay_s, config.rate_hz))
