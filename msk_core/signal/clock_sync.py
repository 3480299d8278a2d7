"""The offset between two device clocks, measured from the accelerations both devices sense of one movement.

A Trigno Avanti sensor's accelerometer (AUX port, in g) runs on the EMG clock; an Xsens MTi measures acceleration
(m/s², gravity included) on its own clock. When an EMG sensor and a tracker sit on one body segment they sense one
motion, so the lag that best superimposes their accelerations is the offset between the two clocks:
``tracker device time = EMG device time + offset_ns`` for one instant.

:class:`ClockSync` is a streaming estimator with explicit state and no I/O (it never reads a clock): feed it blocks of
(device times, 3-axis accelerations) of every sensor on the EMG clock (:meth:`ClockSync.add_emg_sensor`) and of one
tracker (:meth:`ClockSync.add_tracker`) as they arrive, call :meth:`ClockSync.update`, and it answers a
:class:`ClockOffset`: the offset with its confidence, or, explicitly, why it cannot give one yet so that the caller
keeps the arrival-time mapping. One estimator per tracker: each MTi has its own clock.

The method, per window of ``window_s`` seconds on the EMG clock, a new window every ``step_s`` (so a drifting offset
is tracked):

* Feature: the magnitude of the measured acceleration minus gravity. A magnitude does not depend on how the sensor is
  oriented on the segment (an electrode follows its muscle's fibres, a tracker is strapped on anyhow), so the two
  devices need no common frame. (The two points of one segment still move differently where the segment rotates; the
  correlation threshold allows for it.)
* Both streams are linearly interpolated onto one grid (``grid_hz``) in EMG clock time, the tracker's through the
  current offset (the caller's prior, then the latest estimate), and low-passed alike (zero phase, ``lowpass_hz``):
  the movement's band, below both devices' Nyquist rates. Equal treatment of both streams keeps any filter delay out
  of the offset.
* Rest is skipped: a window where either feature varies less than ``min_motion_m_s2`` (RMS) holds sensor noise only,
  whose cross-correlation peaks at a random lag. Lifting sets begin with a static pose, so the first windows are rest.
* The normalised cross-correlation (Pearson r at each lag within ±``max_lag_s`` of the current offset) of each EMG
  sensor that moved with the tracker's feature; the sensor with the highest peak wins the window (the one on the
  tracker's segment). The peak is refined to sub-sample precision by a parabola through its three grid lags. A window
  is accepted when its peak r reaches ``min_correlation`` and lies inside the search range (a peak on its edge means
  the offset is outside it).
* The offset is the median of the accepted windows of the last ``history_s`` seconds, or, once they span
  ``drift_span_s``, the value at the newest window of a straight line fitted through them (clock drift). Its spread
  is the robust standard deviation (1.4826 x median absolute deviation) of the windows around it; overlapping
  windows (``window_s`` > ``step_s``) share data, so the spread is a lower bound of the error.

Docs: docs/devices.md ("Alignment from accelerations").
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy import signal

from msk_core.errors import ConfigError, InputError

#: One g in m/s² (standard gravity): the unit of the Trigno SDK's ACC channels.
STANDARD_GRAVITY = 9.80665


class AccUnit(enum.Enum):
    """Units of the accelerations fed in."""

    G = "g"  # Trigno Avanti ACC (AUX port 50044, legacy ACC port 50042)
    M_PER_S2 = "m/s2"  # Xsens MTi acceleration (MTData2 0x4020)

    @property
    def to_m_per_s2(self) -> float:
        return STANDARD_GRAVITY if self is AccUnit.G else 1.0


class SyncStatus(enum.Enum):
    LOCKED = "locked"  # an offset measured from accepted windows
    WAITING = "waiting"  # not yet a full window of both streams
    NO_MOVEMENT = "no_movement"  # every window so far was rest on the EMG sensors' side or the tracker's
    NOT_TOGETHER = "not_together"  # movement, but no EMG sensor moved with the tracker (peak r below the threshold)


@dataclass(frozen=True)
class ClockSyncConfig:
    grid_hz: float = 200.0  # common rate both streams are resampled to (sub-sample refinement goes finer)
    lowpass_hz: float = 8.0  # zero-phase Butterworth low-pass on the grid: lifting moves are slower than this
    lowpass_order: int = 4
    window_s: float = 6.0  # one estimate per window
    step_s: float = 2.0  # a new window this often
    max_lag_s: float = 0.5  # search half-width around the current offset (the arrival-time prior is off by latencies)
    min_motion_m_s2: float = 0.05  # RMS of a feature in a window below this: rest (sensor noise ~0.01 after low-pass)
    min_correlation: float = 0.8  # a window's peak Pearson r below this: that sensor did not move with the tracker
    pad_s: float = 1.0  # filtered beyond the window on each side and cut off, so filter edges never reach it
    history_s: float = 120.0  # accepted windows kept for the offset, its drift and its spread
    drift_span_s: float = 30.0  # fit a drift once the accepted windows span this long

    def __post_init__(self) -> None:
        positive = ("grid_hz", "lowpass_hz", "window_s", "step_s", "max_lag_s", "pad_s", "history_s", "drift_span_s")
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError("must be a positive number", field=name, value=value)
        if self.lowpass_hz >= self.grid_hz / 2:
            raise ConfigError(
                "the low-pass must lie below the grid's Nyquist frequency",
                field="lowpass_hz",
                value=(self.lowpass_hz, self.grid_hz),
            )
        if not 0 < self.min_correlation < 1:
            raise ConfigError("must lie in (0, 1)", field="min_correlation", value=self.min_correlation)
        if not self.min_motion_m_s2 >= 0:
            raise ConfigError("must be >= 0", field="min_motion_m_s2", value=self.min_motion_m_s2)
        if self.lowpass_order < 1:
            raise ConfigError("must be >= 1", field="lowpass_order", value=self.lowpass_order)


@dataclass(frozen=True)
class WindowEstimate:
    """One window's outcome (EMG clock times in ns)."""

    start_ns: int
    end_ns: int
    status: SyncStatus  # LOCKED: accepted
    offset_ns: int | None  # best lag's offset (also for a rejected window with movement)
    peak_correlation: float | None  # of the best sensor; None for rest
    peak_width_ms: float | None  # w of r(lag) ~ r_peak (1 - lag^2 / 2w^2) around the peak: the lobe's sharpness
    sensor: str | None  # the EMG-clock sensor that moved most like the tracker
    reason: str


@dataclass(frozen=True)
class ClockOffset:
    """The estimator's answer. ``offset_ns``: tracker device time minus EMG device time of one instant, None unless
    ``status`` is LOCKED; ``reason`` says in words what was found (and, when not locked, why the caller must keep the
    arrival-time mapping)."""

    status: SyncStatus
    reason: str
    offset_ns: int | None = None
    spread_ns: int | None = None  # robust spread of the accepted windows; None with a single window
    drift_ppm: float | None = None  # fitted drift of the tracker clock against the EMG clock; None until fitted
    windows: int = 0  # accepted windows the offset comes from
    peak_correlation: float | None = None  # newest accepted window's
    peak_width_ms: float | None = None
    sensor: str | None = None  # newest accepted window's EMG-clock sensor
    windows_seen: int = 0  # every window evaluated so far, accepted or not

    @property
    def locked(self) -> bool:
        return self.status is SyncStatus.LOCKED

    def emg_host_offset_ns(self, tracker_host_offset_ns: int) -> int:
        """The EMG clock's host mapping (host time - EMG device time) implied by the tracker's (host time - tracker
        device time): the EMG then lands on the host clock where the tracker's samples of the same instant do."""
        if self.offset_ns is None:
            raise InputError(
                "no offset measured yet: keep the arrival-time mapping", field="status", value=self.status.value
            )
        return int(tracker_host_offset_ns + self.offset_ns)


@dataclass
class _Stream:
    """Raw feature samples of one sensor: device time (ns, increasing) and |a| - g (m/s²)."""

    time_ns: list[np.ndarray] = field(default_factory=list)
    feature: list[np.ndarray] = field(default_factory=list)
    last_ns: int | None = None

    def add(self, time_ns: np.ndarray, feature: np.ndarray, name: str, *, increasing: bool = False) -> None:
        """``increasing``: the caller checked that ``time_ns`` increase (one check for the sensors of a block)."""
        if time_ns.size == 0:
            return
        if (not increasing and np.any(np.diff(time_ns) <= 0)) or (
            self.last_ns is not None and time_ns[0] <= self.last_ns
        ):
            raise InputError(
                "device times must increase from sample to sample and block to block",
                field=name,
                value=(self.last_ns, int(time_ns[0])),
            )
        self.time_ns.append(time_ns)
        self.feature.append(feature)
        self.last_ns = int(time_ns[-1])

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        if len(self.time_ns) > 1:
            self.time_ns, self.feature = [np.concatenate(self.time_ns)], [np.concatenate(self.feature)]
        return (self.time_ns[0], self.feature[0]) if self.time_ns else (np.empty(0, np.int64), np.empty(0))

    @property
    def first_ns(self) -> int | None:
        return int(self.time_ns[0][0]) if self.time_ns else None

    def drop_before(self, time_ns: int) -> None:
        """Forget the samples before ``time_ns`` but the last one (for interpolation). Whole blocks go without
        joining the others (this runs after every block: joining re-copied the retained window each time)."""
        while len(self.time_ns) > 1 and self.time_ns[1][0] < time_ns:  # a later block holds the one kept before
            del self.time_ns[0], self.feature[0]
        if self.time_ns:
            keep = max(0, int(np.searchsorted(self.time_ns[0], time_ns)) - 1)
            if keep:
                self.time_ns[0], self.feature[0] = self.time_ns[0][keep:], self.feature[0][keep:]


def _feature(acc: np.ndarray, unit: AccUnit, name: str, *, sensors: int | None = None) -> np.ndarray:
    """|a| - g (m/s²) of accelerations (n, 3), or (n, ``sensors``, 3) of several sensors at once (n, sensors)."""
    acc = np.asarray(acc, dtype=float)
    shape = (3,) if sensors is None else (sensors, 3)
    if acc.ndim != 1 + len(shape) or acc.shape[1:] != shape:
        raise InputError(f"accelerations must be (n, {', '.join(map(str, shape))})", field=name, value=acc.shape)
    if not np.all(np.isfinite(acc)):
        raise InputError("accelerations hold NaN or infinite values", field=name)
    return np.linalg.norm(acc, axis=-1) * unit.to_m_per_s2 - STANDARD_GRAVITY


def _times(device_time_ns, n: int, name: str) -> np.ndarray:
    t = np.atleast_1d(np.asarray(device_time_ns)).astype(np.int64)
    if t.shape != (n,):
        raise InputError("one device time per acceleration sample", field=name, value=(t.shape, n))
    return t


def _refined_peak(r: np.ndarray, k: int, grid_hz: float) -> tuple[float, float | None, float]:
    """(peak r, lobe width in ms or None, lag index) of the correlation r's maximum at index k, refined by the
    parabola through its three grid lags (at the edge of the range: the grid value)."""
    peak, width, refined = float(r[k]), None, float(k)
    if 0 < k < len(r) - 1:
        left, right = float(r[k - 1]), float(r[k + 1])
        curvature = left - 2 * peak + right  # < 0 at a maximum
        delta = 0.5 * (left - right) / curvature if curvature < 0 else 0.0
        refined = k + delta
        peak = peak - 0.25 * (left - right) * delta
        if curvature < 0:
            width = 1e3 * math.sqrt(peak / (-curvature * grid_hz**2)) if peak > 0 else None
    return peak, width, refined


class ClockSync:
    """Streaming estimate of one tracker's clock against the EMG clock (module docstring). ``prior_offset_ns``: the
    offset the arrival-time mappings imply (EMG host offset - tracker host offset, each the smallest arrival minus
    device time); the first search spans ±``max_lag_s`` around it."""

    def __init__(self, prior_offset_ns: int, config: ClockSyncConfig | None = None) -> None:
        self.config = config or ClockSyncConfig()
        self.prior_offset_ns = int(prior_offset_ns)
        self._center_ns = int(prior_offset_ns)  # offset the tracker is resampled through
        self._emg: dict[str, _Stream] = {}
        self._tracker = _Stream()
        self._next_end_ns: int | None = None
        self.windows: list[WindowEstimate] = []  # every window evaluated, oldest first (pruned to history_s)
        self._windows_seen = 0
        cfg = self.config
        self._sos = signal.butter(cfg.lowpass_order, cfg.lowpass_hz, fs=cfg.grid_hz, output="sos")

    # ------------------------------------------------------------------------------------------ input
    def add_emg_sensor(self, sensor: str, device_time_ns, acc, unit: AccUnit = AccUnit.G) -> None:
        """Accelerations (n, 3) of one sensor on the EMG clock at its device times (n,) ns."""
        feature = _feature(acc, unit, sensor)
        self._emg.setdefault(sensor, _Stream()).add(_times(device_time_ns, len(feature), sensor), feature, sensor)

    def add_emg_sensors(self, sensors: Sequence[str], device_time_ns, acc, unit: AccUnit = AccUnit.G) -> None:
        """Accelerations (n, sensors, 3) of several sensors sampled together on the EMG clock at device times (n,) ns:
        :meth:`add_emg_sensor` of each, with the feature and the checks computed once for the block."""
        name = f"acc/{','.join(sensors)}"
        feature = _feature(acc, unit, name, sensors=len(sensors))
        times = _times(device_time_ns, len(feature), name)
        increasing = not np.any(np.diff(times) <= 0)
        for k, sensor in enumerate(sensors):
            self._emg.setdefault(sensor, _Stream()).add(times, feature[:, k], sensor, increasing=increasing)

    def add_tracker(self, device_time_ns, acc, unit: AccUnit = AccUnit.M_PER_S2) -> None:
        """Accelerations (n, 3) of the tracker at its device times (n,) ns."""
        feature = _feature(acc, unit, "tracker")
        self._tracker.add(_times(device_time_ns, len(feature), "tracker"), feature, "tracker")

    # ------------------------------------------------------------------------------------------ estimate
    def update(self) -> ClockOffset:
        """Evaluate every window the data now cover and answer the current offset (or why there is none)."""
        cfg = self.config
        if not self._emg or self._tracker.last_ns is None:
            return self._answer()
        window_ns, step_ns = int(round(cfg.window_s * 1e9)), int(round(cfg.step_s * 1e9))
        while True:
            covered = self._covered_ns()
            if covered is None:
                break
            first, last = covered
            if self._next_end_ns is None or self._next_end_ns - window_ns < first:
                self._next_end_ns = first + window_ns  # the first window, or the data restart later (pruned)
            if self._next_end_ns > last:
                break
            self._evaluate(self._next_end_ns - window_ns, self._next_end_ns)
            self._next_end_ns += step_ns
        self._prune()
        return self._answer()

    def _covered_ns(self) -> tuple[int, int] | None:
        """EMG clock interval where a window and its margins (filter pad; for the tracker also the search range) have
        data of the tracker and of at least one EMG sensor."""
        cfg = self.config
        pad_ns, lag_ns = int(round(cfg.pad_s * 1e9)), int(round(cfg.max_lag_s * 1e9))
        spans = [
            (s.first_ns, s.last_ns) for s in self._emg.values() if s.first_ns is not None and s.last_ns is not None
        ]
        tracker_first, tracker_last = self._tracker.first_ns, self._tracker.last_ns
        if not spans or tracker_first is None or tracker_last is None:
            return None
        first = max(min(a for a, _ in spans) + pad_ns, tracker_first - self._center_ns + lag_ns + pad_ns)
        last = min(max(b for _, b in spans) - pad_ns, tracker_last - self._center_ns - lag_ns - pad_ns)
        return (first, last) if last > first else None

    def _grid_feature(self, stream: _Stream, shift_ns: int, t0_ns: int, n: int) -> np.ndarray | None:
        """The stream's feature on ``n`` grid points from ``t0_ns`` (EMG clock), its device times shifted by
        ``-shift_ns``, low-passed; None where the stream does not cover the padded span."""
        cfg = self.config
        pad = int(round(cfg.pad_s * cfg.grid_hz))
        t, f = stream.arrays()
        if t.size < 2:
            return None
        grid_s = np.arange(-pad, n + pad) / cfg.grid_hz
        local_s = (t - shift_ns - t0_ns) / 1e9
        if local_s[0] > grid_s[0] or local_s[-1] < grid_s[-1]:
            return None
        resampled = np.interp(grid_s, local_s, f)
        return signal.sosfiltfilt(self._sos, resampled)[pad : pad + n]

    def _evaluate(self, start_ns: int, end_ns: int) -> None:
        """One window: the best EMG-clock sensor's correlation peak with the tracker gives its offset, recorded with
        whether it is accepted (or why not); an accepted window moves the search centre."""
        cfg = self.config
        self._windows_seen += 1
        n = int(round((end_ns - start_ns) * 1e-9 * cfg.grid_hz))
        lags = int(round(cfg.max_lag_s * cfg.grid_hz))
        lag_ns = int(round(lags * 1e9 / cfg.grid_hz))
        tracker = self._grid_feature(self._tracker, self._center_ns, start_ns - lag_ns, n + 2 * lags)
        if tracker is None:
            reason = "the tracker does not cover the window"
            self.windows.append(WindowEstimate(start_ns, end_ns, SyncStatus.WAITING, None, None, None, None, reason))
            return
        tracker_rms = float(np.std(tracker[lags : lags + n]))
        best, moving_emg = self._best_sensor(tracker, tracker_rms, start_ns, n)
        if best is None:  # rest on one side at least
            rest = [] if moving_emg else ["no EMG-clock sensor moved"]
            if tracker_rms < cfg.min_motion_m_s2:
                rest.append("the tracker did not move")
            reason = " and ".join(rest) + f" (feature RMS below {cfg.min_motion_m_s2:g} m/s²)"
            self.windows.append(
                WindowEstimate(start_ns, end_ns, SyncStatus.NO_MOVEMENT, None, None, None, None, reason)
            )
            return
        k, r, sensor = best
        peak, width, refined = _refined_peak(r, k, cfg.grid_hz)
        offset_ns = self._center_ns + int(round((refined - lags) * 1e9 / cfg.grid_hz))
        status, reason = self._verdict(k, len(r), peak, sensor)
        self.windows.append(WindowEstimate(start_ns, end_ns, status, offset_ns, peak, width, sensor, reason))
        if status is SyncStatus.LOCKED:
            self._center_ns = self._combined()[0]

    def _best_sensor(
        self, tracker: np.ndarray, tracker_rms: float, start_ns: int, n: int
    ) -> tuple[tuple[int, np.ndarray, str] | None, int]:
        """((best lag index, r at every lag, sensor) of the EMG-clock sensor whose correlation with the tracker
        peaks highest, None when no sensor or the tracker moved; how many EMG-clock sensors moved)."""
        cfg = self.config
        rows = sliding_window_view(tracker, n)  # (2 lags + 1, n): the tracker at each lag
        centred = rows - rows.mean(axis=1, keepdims=True)
        centred_norm = np.linalg.norm(centred, axis=1)
        moving_emg = 0
        best: tuple[int, np.ndarray, str] | None = None
        for sensor, stream in self._emg.items():
            x = self._grid_feature(stream, 0, start_ns, n)
            if x is None:
                continue
            x = x - x.mean()
            x_rms = float(np.sqrt(np.mean(x * x)))
            if x_rms < cfg.min_motion_m_s2:
                continue
            moving_emg += 1
            if tracker_rms < cfg.min_motion_m_s2:
                continue
            r = centred @ x / (centred_norm * np.linalg.norm(x))
            k = int(np.argmax(r))
            if best is None or r[k] > best[1][best[0]]:
                best = (k, r, sensor)
        return best, moving_emg

    def _verdict(self, k: int, n_lags: int, peak: float, sensor: str) -> tuple[SyncStatus, str]:
        """A window's status and reason from its correlation peak at lag index k of n_lags."""
        cfg = self.config
        if k in (0, n_lags - 1):
            return SyncStatus.NOT_TOGETHER, (
                f"the best correlation (r = {peak:.2f}, {sensor}) lies on the edge of the search range "
                f"(±{cfg.max_lag_s:g} s around {self._center_ns / 1e6:.1f} ms): the offset is outside it or no sensor "
                "moved with the tracker"
            )
        if peak < cfg.min_correlation:
            return SyncStatus.NOT_TOGETHER, (
                f"no EMG-clock sensor moved with the tracker: best peak r = {peak:.2f} ({sensor}) is below "
                f"{cfg.min_correlation:g}"
            )
        return SyncStatus.LOCKED, f"r = {peak:.3f} ({sensor})"

    def _accepted(self) -> list[WindowEstimate]:
        return [w for w in self.windows if w.status is SyncStatus.LOCKED]

    def _combined(self) -> tuple[int, int | None, float | None]:
        """(offset, spread, drift ppm) from the accepted windows kept."""
        cfg = self.config
        accepted = self._accepted()
        centre_s = np.array([(w.start_ns + w.end_ns) / 2e9 for w in accepted])
        offsets = np.array([w.offset_ns for w in accepted], dtype=float)
        drift = None
        if centre_s[-1] - centre_s[0] >= cfg.drift_span_s and len(accepted) >= 3:
            slope, intercept = np.polyfit(centre_s - centre_s[-1], offsets, 1)
            residual = offsets - (intercept + slope * (centre_s - centre_s[-1]))
            value, drift = intercept, slope / 1e3  # ns per s -> ppm
        else:
            value = float(np.median(offsets))
            residual = offsets - value
        spread = int(round(1.4826 * float(np.median(np.abs(residual))))) if len(accepted) >= 2 else None
        return int(round(value)), spread, drift

    def _prune(self) -> None:
        """Forget windows older than ``history_s`` and raw samples no future window needs."""
        cfg = self.config
        if self.windows:
            newest = self.windows[-1].end_ns
            self.windows = [w for w in self.windows if newest - w.end_ns <= cfg.history_s * 1e9]
        if self._next_end_ns is None:
            return
        keep_from = self._next_end_ns - int(round((cfg.window_s + 2 * cfg.max_lag_s + 2 * cfg.pad_s) * 1e9))
        for stream in self._emg.values():
            stream.drop_before(keep_from)
        self._tracker.drop_before(keep_from + self._center_ns - int(round(cfg.max_lag_s * 1e9)))

    def _answer(self) -> ClockOffset:
        cfg = self.config
        seen = self._windows_seen
        accepted = self._accepted()
        if accepted:
            offset, spread, drift = self._combined()
            last = accepted[-1]
            return ClockOffset(
                SyncStatus.LOCKED,
                f"{len(accepted)} window(s) agree; newest {last.reason}",
                offset,
                spread,
                drift,
                len(accepted),
                last.peak_correlation,
                last.peak_width_ms,
                last.sensor,
                seen,
            )
        if not self._emg or self._tracker.last_ns is None:
            missing = "EMG-clock accelerations" if not self._emg else "tracker accelerations"
            return ClockOffset(SyncStatus.WAITING, f"no {missing} yet", windows_seen=seen)
        evaluated = [w for w in self.windows if w.status is not SyncStatus.WAITING]
        if not evaluated:
            return ClockOffset(
                SyncStatus.WAITING,
                f"not yet a {cfg.window_s:g} s window of both streams (plus "
                f"±{cfg.max_lag_s:g} s search and {cfg.pad_s:g} s filter margins)",
                windows_seen=seen,
            )
        together = [w for w in evaluated if w.status is SyncStatus.NOT_TOGETHER]
        if together:
            # a window with movement has a peak correlation (None is for rest only)
            best = max(together, key=lambda w: -math.inf if w.peak_correlation is None else w.peak_correlation)
            return ClockOffset(
                SyncStatus.NOT_TOGETHER,
                f"{len(together)} window(s) with movement, none accepted: {best.reason}",
                peak_correlation=best.peak_correlation,
                sensor=best.sensor,
                windows_seen=seen,
            )
        return ClockOffset(
            SyncStatus.NO_MOVEMENT, f"{len(evaluated)} window(s), all rest: {evaluated[-1].reason}", windows_seen=seen
        )
