"""Repetitions and their phase from one kinematic signal (elbow angle for bench press, hip or pelvis angle for lifts).

Offline (:func:`detect_reps`, :func:`rep_phase`) sees the whole trial. Live (:class:`PhaseTracker`) is causal: it
maps the progress of the signal through the current rep onto a :class:`RepTemplate` learned at calibration.

Progress is the signal normalised to the rep range: ``p = (s * sign - rest) / depth`` (0 at rest, 1 at a full rep),
``sign`` set by :class:`Excursion`. Phase is in [0, 1) inside a rep and :data:`REST_PHASE` between reps, everywhere in
the project (offline arrays, the live tracker, the wire); NaN means the phase is unknown (no rep template, no phase
signal). :func:`in_rep` tells the two apart.

Counting reps of a phase stream (the dashboards live, the report offline): :class:`PhaseRepCounter`,
:func:`phase_rep_spans`.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from msk_core.errors import ConfigError, InputError

# Phase of a sample between repetitions (the subject rests). Any negative phase reads as rest; NaN is "unknown".
REST_PHASE = -1.0


def in_rep(phase: np.ndarray | float) -> np.ndarray:
    """True where ``phase`` is inside a repetition ([0, 1)); False at rest (:data:`REST_PHASE`) and where unknown."""
    with np.errstate(invalid="ignore"):
        return np.asarray(phase, dtype=float) >= 0.0


class Excursion(enum.Enum):
    """Direction the signal moves away from rest during a rep."""

    INCREASE = "increase"  # e.g. elbow flexion while lowering the bar in a bench press
    DECREASE = "decrease"  # e.g. pelvis tilt (trunk flexes forward) or pelvis height in a lift

    @property
    def sign(self) -> float:
        return 1.0 if self is Excursion.INCREASE else -1.0


class PhaseMode(enum.Enum):
    """How time inside a rep maps to phase."""

    TIME = "time"  # linear in time from rep start to rep end
    TURNING_POINT = "turning_point"  # start..turn -> [0, 0.5), turn..end -> [0.5, 1): aligns the bottoms of reps


@dataclass(frozen=True)
class RepDetectionConfig:
    excursion: Excursion = Excursion.INCREASE
    start_fraction: float = 0.2  # progress above which a rep is under way
    min_depth_fraction: float = 0.5  # a rep must reach this progress
    min_duration_s: float = 0.4
    rest_percentile: float = 5.0  # robust rest level of the trial
    peak_percentile: float = 98.0  # robust full-rep level of the trial
    settle_tolerance: float = 0.03  # start/end = last/first sample within this progress of the local minimum

    def __post_init__(self) -> None:
        if not 0.0 < self.start_fraction < self.min_depth_fraction <= 1.0:
            raise ConfigError(
                "need 0 < start_fraction < min_depth_fraction <= 1",
                field="start_fraction",
                value=(self.start_fraction, self.min_depth_fraction),
            )
        if not 0.0 <= self.rest_percentile < self.peak_percentile <= 100.0:
            raise ConfigError(
                "need rest_percentile < peak_percentile",
                field="rest_percentile",
                value=(self.rest_percentile, self.peak_percentile),
            )


@dataclass(frozen=True)
class Rep:
    """One repetition: sample indices ``start <= turn < end`` (``end`` exclusive) and their times."""

    start: int
    turn: int
    end: int
    t_start: float
    t_turn: float
    t_end: float

    @property
    def duration(self) -> float:
        return self.t_end - self.t_start


def _check_series(time: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(time, dtype=float).reshape(-1)
    v = np.asarray(values, dtype=float).reshape(-1)
    if t.shape != v.shape:
        raise InputError("time and signal lengths differ", field="signal", value=(t.shape[0], v.shape[0]))
    if t.shape[0] < 3 or np.any(np.diff(t) <= 0):
        raise InputError("time must be strictly increasing with at least 3 samples", field="time")
    if not np.all(np.isfinite(v)):
        raise InputError("signal has non-finite values", field="signal")
    return t, v


def progress_scale(values: np.ndarray, config: RepDetectionConfig) -> tuple[float, float]:
    """``(rest, depth)`` of a trial, in signed signal units: ``p = (sign * s - rest) / depth``."""
    e = config.excursion.sign * np.asarray(values, dtype=float)
    rest = float(np.percentile(e, config.rest_percentile))
    depth = float(np.percentile(e, config.peak_percentile)) - rest
    if not depth > 0:
        raise InputError("signal does not move: no repetitions to find", field="signal", value=depth)
    return rest, depth


def _settle(p: np.ndarray, i: int, limit: int, step: int, tol: float) -> int:
    """From ``i`` walk (``step`` = -1 back, +1 forward, not past ``limit``) down the progress valley while it does
    not climb more than ``2 * tol`` above its running minimum; return the sample nearest ``i`` within ``tol`` of
    that minimum: where the movement leaves (or reaches) rest."""
    k, low, k_low = i, p[i], i
    while k != limit and p[k + step] <= low + 2 * tol:
        k += step
        if p[k] < low:
            low, k_low = p[k], k
    span = np.arange(k_low, i - step, -step)  # from the minimum towards i
    near = span[p[span] <= low + tol]
    return int(near[-1])


def detect_reps(time: np.ndarray, values: np.ndarray, config: RepDetectionConfig) -> list[Rep]:
    """Complete reps of a whole trial (offline). A rep is a run of progress above ``start_fraction`` that reaches
    ``min_depth_fraction``, widened to the surrounding rest points (last/first samples near the local minima).
    A rep already under way at the first sample, or not finished at the last, is left out."""
    t, v = _check_series(time, values)
    rest, depth = progress_scale(v, config)
    p = (config.excursion.sign * v - rest) / depth
    above = p > config.start_fraction
    edges = np.diff(above.astype(np.int8))
    rises = [int(i) for i in np.flatnonzero(edges == 1) + 1]
    falls = [int(i) for i in np.flatnonzero(edges == -1) + 1]
    if above[0]:
        rises.insert(0, 0)
    runs = [(r, f) for r, f in zip(rises, falls) if f > r]  # an unfinished last run has no fall: dropped
    runs = [(r, f) for r, f in runs if p[r:f].max() >= config.min_depth_fraction and r > 0]

    reps: list[Rep] = []
    prev_end = 0
    for k, (r, f) in enumerate(runs):
        nxt = runs[k + 1][0] if k + 1 < len(runs) else len(p) - 1
        start = _settle(p, r, prev_end, -1, config.settle_tolerance)
        end = _settle(p, f, nxt, +1, config.settle_tolerance)
        turn = start + int(np.argmax(p[start:end]))
        if end <= turn or t[end] - t[start] < config.min_duration_s:
            continue
        reps.append(Rep(start, turn, end, float(t[start]), float(t[turn]), float(t[end])))
        prev_end = end
    return reps


def rep_phase(
    time: np.ndarray, reps: list[Rep], mode: PhaseMode = PhaseMode.TURNING_POINT
) -> tuple[np.ndarray, np.ndarray]:
    """Phase in [0, 1) of every sample inside a rep (:data:`REST_PHASE` outside) and the rep index (-1 outside)."""
    t = np.asarray(time, dtype=float).reshape(-1)
    phase = np.full(t.shape, REST_PHASE)
    index = np.full(t.shape, -1, dtype=int)
    for k, rep in enumerate(reps):
        sl = slice(rep.start, rep.end)
        ts = t[sl]
        if mode is PhaseMode.TIME:
            ph = (ts - rep.t_start) / (rep.t_end - rep.t_start)
        else:
            down = (ts - rep.t_start) / max(rep.t_turn - rep.t_start, 1e-12)
            up = (ts - rep.t_turn) / (rep.t_end - rep.t_turn)
            ph = np.where(ts < rep.t_turn, 0.5 * down, 0.5 + 0.5 * up)
        phase[sl] = np.clip(ph, 0.0, np.nextafter(1.0, 0.0))
        index[sl] = k
    return phase, index


def _number(d: dict[str, object], key: str) -> float:
    """``d[key]`` of a JSON document, which must be a number (KeyError when missing, as ``d[key]``)."""
    value = d[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError("must be a number", field=key, value=value)
    return float(value)


@dataclass(frozen=True)
class RepTemplate:
    """Mean progress curve of calibration reps, ``progress[i]`` at ``phase_grid[i]``, with the scale it used."""

    excursion: Excursion
    mode: PhaseMode
    rest: float
    depth: float
    start_fraction: float
    min_depth_fraction: float
    phase_grid: np.ndarray
    progress: np.ndarray
    progress_std: np.ndarray
    mean_duration_s: float
    n_reps: int

    @property
    def turn_phase(self) -> float:
        return float(self.phase_grid[int(np.argmax(self.progress))])

    def to_dict(self) -> dict[str, object]:
        return {
            "excursion": self.excursion.value,
            "mode": self.mode.value,
            "rest": self.rest,
            "depth": self.depth,
            "start_fraction": self.start_fraction,
            "min_depth_fraction": self.min_depth_fraction,
            "phase_grid": self.phase_grid.tolist(),
            "progress": self.progress.tolist(),
            "progress_std": self.progress_std.tolist(),
            "mean_duration_s": self.mean_duration_s,
            "n_reps": self.n_reps,
        }

    @classmethod
    def from_dict(cls, d: dict[str, object]) -> RepTemplate:
        """The template :meth:`to_dict` wrote; ConfigError naming the field that is missing or not a number."""
        try:
            return cls(
                excursion=Excursion(d["excursion"]),
                mode=PhaseMode(d["mode"]),
                rest=_number(d, "rest"),
                depth=_number(d, "depth"),
                start_fraction=_number(d, "start_fraction"),
                min_depth_fraction=_number(d, "min_depth_fraction"),
                phase_grid=np.asarray(d["phase_grid"], dtype=float),
                progress=np.asarray(d["progress"], dtype=float),
                progress_std=np.asarray(d["progress_std"], dtype=float),
                mean_duration_s=_number(d, "mean_duration_s"),
                n_reps=int(_number(d, "n_reps")),
            )
        except KeyError as exc:
            raise ConfigError("rep template misses a field", field=str(exc.args[0])) from None
        except (ValueError, TypeError) as exc:
            raise ConfigError(f"invalid rep template: {exc}", field="rep_template") from exc


def learn_template(
    time: np.ndarray,
    values: np.ndarray,
    config: RepDetectionConfig,
    *,
    mode: PhaseMode = PhaseMode.TURNING_POINT,
    n_grid: int = 101,
) -> RepTemplate:
    """Detect the calibration reps and average their progress curves over phase."""
    t, v = _check_series(time, values)
    reps = detect_reps(t, v, config)
    if not reps:
        raise InputError("no complete repetition found in the calibration signal", field="signal")
    rest, depth = progress_scale(v, config)
    p = (config.excursion.sign * v - rest) / depth
    phase, index = rep_phase(t, reps, mode)
    grid = np.linspace(0.0, 1.0, n_grid)
    curves = []
    for k in range(len(reps)):
        m = index == k
        ph = np.append(phase[m], 1.0)  # close the rep at its end sample
        pk = np.append(p[m], p[reps[k].end])
        curves.append(np.interp(grid, ph, pk))
    c = np.vstack(curves)
    return RepTemplate(
        excursion=config.excursion,
        mode=mode,
        rest=rest,
        depth=depth,
        start_fraction=config.start_fraction,
        min_depth_fraction=config.min_depth_fraction,
        phase_grid=grid,
        progress=c.mean(axis=0),
        progress_std=c.std(axis=0),
        mean_duration_s=float(np.mean([r.duration for r in reps])),
        n_reps=len(reps),
    )


class PhaseTracker:
    """Causal phase of the current rep from progress along the template. Explicit state; ``update`` per sample.

    Before the turning point phase follows the template's rising branch, after it the falling branch; phase never
    goes backwards within a rep. A rise that never reaches ``min_depth_fraction`` is abandoned as a false start.
    """

    def __init__(self, template: RepTemplate, *, turn_hysteresis: float = 0.03) -> None:
        self.template = template
        self.turn_hysteresis = turn_hysteresis
        g, pr = template.phase_grid, template.progress
        k = int(np.argmax(pr))
        # monotone branches so that progress -> phase is a function
        rise_p = np.maximum.accumulate(pr[: k + 1])
        fall_p = np.minimum.accumulate(pr[k:])
        self._rise = (rise_p + np.arange(k + 1) * 1e-12, g[: k + 1])
        self._fall = ((fall_p - np.arange(fall_p.shape[0]) * 1e-12)[::-1], g[k:][::-1])
        self._turn_phase = float(g[k])
        self._peak_progress = float(pr[k])
        self._end_phase = float(g[-1] - 2 * (g[1] - g[0]))
        self.reset()

    def reset(self) -> None:
        self.in_rep = False
        self.passed_turn = False
        self.phase = REST_PHASE
        self.peak = 0.0
        self.trough = float("inf")
        self.t_start = float("nan")
        self.rep_count = 0

    def progress(self, value: float) -> float:
        tpl = self.template
        return (tpl.excursion.sign * value - tpl.rest) / tpl.depth

    def update(self, t: float, value: float) -> float:
        """Phase in [0, 1) of the sample at time ``t`` (:data:`REST_PHASE` when no rep is under way)."""
        tpl = self.template
        p = self.progress(value)
        if not self.in_rep:
            if p > tpl.start_fraction:
                self.in_rep, self.passed_turn = True, False
                self.peak, self.trough, self.t_start = p, float("inf"), t
                self.phase = float(np.interp(p, *self._rise))
                self.rep_count += 1
                return self.phase
            return REST_PHASE
        if not self.passed_turn:
            self.peak = max(self.peak, p)
            if p < tpl.start_fraction and self.peak < tpl.min_depth_fraction:
                self.in_rep, self.phase = False, REST_PHASE  # false start
                self.rep_count -= 1
                return self.phase
            if self.peak >= tpl.min_depth_fraction and p < self.peak - self.turn_hysteresis:
                self.passed_turn = True
            else:
                cand = min(float(np.interp(p, *self._rise)), np.nextafter(self._turn_phase, 0.0))
                self.phase = max(self.phase, cand)
                return self.phase
        # after the turning point: falling branch until the signal settles or starts the next rep
        self.trough = min(self.trough, p)
        settled = p > self.trough + self.turn_hysteresis and p < tpl.start_fraction
        # touch-and-go: the rep is nearly done and progress rises again without resting in between
        restarted = p > self.trough + 2 * self.turn_hysteresis and self.phase > 0.75
        overdue = t - self.t_start > 2.0 * tpl.mean_duration_s
        if settled or restarted or overdue:
            self.in_rep, self.phase = False, REST_PHASE
            return self.update(t, value) if p > tpl.start_fraction else self.phase
        # this rep's own depth replaces the template's on the way back (reps differ in depth)
        cand = float(np.interp(p * self._peak_progress / self.peak, *self._fall))
        self.phase = min(max(self.phase, cand, self._turn_phase), float(np.nextafter(1.0, 0.0)))
        phase = self.phase
        if cand >= self._end_phase:  # back at the template's resting level: this rep is over
            self.in_rep, self.phase = False, REST_PHASE
        return phase

    def process(self, time: np.ndarray, values: np.ndarray) -> np.ndarray:
        """``update`` over a series; returns the phases."""
        return np.array([self.update(float(a), float(b)) for a, b in zip(time, values)])


# -- reps of a phase stream: the live rep count of the dashboards and the report's reps --------------------------------

#: joint power (W) below which a rep is turning (or held), neither lifting nor lowering
MOVEMENT_POWER_W = 5.0


def movement(torques_nm: dict[str, float], velocities: dict[str, float], threshold_w: float = MOVEMENT_POWER_W) -> str:
    """``"lifting"`` when the net joint power of the inverse-dynamics torques is positive (the muscles do work: the
    load rises, concentric), ``"lowering"`` when negative (eccentric), ``"turning"`` near zero. Any exercise, any
    start: a deadlift from the floor lifts first, a bench press lowers first (the phase's halves cannot say which).
    ``velocities`` in rad/s (or m/s) per coordinate, as the torques are named."""
    power = sum(tau * velocities[name] for name, tau in torques_nm.items() if name in velocities)
    if power > threshold_w:
        return "lifting"
    if power < -threshold_w:
        return "lowering"
    return "turning"


def joint_movement(torques_nm: dict[str, float], coordinates, velocities) -> str | None:
    """:func:`movement` of the newest torques and a joint-angle message's ``coordinates`` and ``velocities``; None
    (no word rather than a stale one) without torques or without a velocity per coordinate."""
    if not torques_nm or len(velocities) != len(coordinates):
        return None
    return movement(torques_nm, dict(zip(coordinates, velocities)))


# A run of in-rep phase shorter than this is no repetition (a tracker that flickers into a rep and out again).
MIN_REP_S = 0.3
#: A rep under way when the data end counts only if its phase got this far (the phase runs 0-1 over a rep).
MIN_FINISHED_PHASE = 0.9
# Samples further apart than this do not belong to one rep (the stream had a gap: the rep is closed at its last sample).
MAX_SAMPLE_GAP_S = 0.5


class PhaseRepCounter:
    """Repetitions of a phase stream (:data:`REST_PHASE` between reps, NaN unknown), one sample at a time.

    A rep is a run of samples inside a rep. It ends at the first sample at rest or of unknown phase, where the phase
    wraps (falls by more than 0.5: the next rep began without rest, which starts at that sample), or before a sample
    more than ``MAX_SAMPLE_GAP_S`` after the previous one; it counts when its samples span at least ``MIN_REP_S``.
    Explicit state; ``update`` per sample, ``finish`` at the end of the data.
    """

    def __init__(self) -> None:
        self.count = 0  # reps completed
        self._start: float | None = None  # time of the first sample of the rep under way
        self._last: tuple[float, float] | None = None  # (time, phase) of its newest sample

    @property
    def in_rep(self) -> bool:
        """A rep is under way (not yet counted)."""
        return self._start is not None

    @property
    def rep_start_s(self) -> float | None:
        """Time of the first sample of the rep under way (None between reps)."""
        return self._start

    def began_at(self, t: float) -> None:
        """The rep under way began at ``t``, before this counter's first sample of it (another counter saw its
        start: a page that joined during the rep)."""
        if self._start is not None and t < self._start:
            self._start = t

    def update(self, t: float, phase: float | None) -> tuple[float, float] | None:
        """The sample at time ``t`` (s); returns the (first, last sample time) of the rep it completed, if any."""
        p = float("nan") if phase is None else float(phase)
        inside = p >= 0.0  # NaN (unknown) compares False
        done = None
        last = self._last
        if last is not None and (not inside or p < last[1] - 0.5 or t - last[0] > MAX_SAMPLE_GAP_S):
            done = self._close()
        if inside:
            if self._start is None:
                self._start = t
            self._last = (t, p)
        return done

    def finish(self) -> tuple[float, float] | None:
        """The end of the data: close the rep under way; returns its span when it counts, which it does only when its
        phase reached ``MIN_FINISHED_PHASE`` (a rep the data cut in the middle, e.g. the session stopped during it,
        was not done: it must not add a rep and its time under tension)."""
        if self._last is not None and self._last[1] < MIN_FINISHED_PHASE:
            self._start = self._last = None
            return None
        return self._close()

    def _close(self) -> tuple[float, float] | None:
        """Close the rep under way (rest, the next rep, a gap in the stream); returns its span when it counts."""
        start, last = self._start, self._last
        self._start = self._last = None
        if start is None or last is None or last[0] - start < MIN_REP_S:
            return None
        self.count += 1
        return start, last[0]


def phase_rep_spans(time: np.ndarray, phase: np.ndarray) -> list[tuple[float, float]]:
    """(first, last sample time) of each rep of a recorded phase series, as :class:`PhaseRepCounter` counts them."""
    counter = PhaseRepCounter()
    spans = [span for t, p in zip(time, phase) if (span := counter.update(float(t), float(p))) is not None]
    last = counter.finish()
    return spans + ([last] if last is not None else [])
