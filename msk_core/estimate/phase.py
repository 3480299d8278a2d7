"""Repetition phase for estimation: the minimal offline detector (torque signals) and the kinematic phase shared by
calibration and the live node (:func:`kinematic_phase`, :class:`PhaseModel`, :class:`LivePhase`).

A repetition is an excursion of a kinematic signal (e.g. trunk tilt in a lift, elbow angle on the bench) away from its
rest level. Rest = median of the signal's first and last 0.5 s; the excursion direction is that of the largest
deviation. A rep is where the deviation exceeds ``enter`` x the 98th-percentile deviation, widened to where it falls
back below ``leave`` x that; reps shorter than ``min_duration_s`` are dropped. Phase = time through the rep in [0, 1].
This is offline (it looks at the whole trial); it is used for ``torque:<coordinate>`` phase signals.

On a kinematic phase coordinate the phase is msk_core.signal.reps's (``detect_reps`` + ``rep_phase``, turning-point mode);
calibration learns a rep template on it and :class:`LivePhase` tracks the same phase causally from the template.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from msk_core.errors import EstimationError, InputError
from msk_core.estimate.prior import REST_PHASE
from msk_core.signal.reps import (
    Excursion,
    PhaseMode,
    PhaseTracker,
    RepDetectionConfig,
    RepTemplate,
    learn_template,
    rep_phase,
)
from msk_core.signal.reps import detect_reps as detect_kinematic_reps


def detect_reps(
    time: np.ndarray,
    signal: np.ndarray,
    *,
    enter: float = 0.5,
    leave: float = 0.15,
    min_duration_s: float = 0.5,
    rest_window_s: float = 0.5,
) -> tuple[np.ndarray, np.ndarray]:
    """(phase, rep_index) per sample; samples outside any rep get phase NaN and rep_index -1."""
    time = np.asarray(time, dtype=float)
    x = np.asarray(signal, dtype=float)
    if time.shape != x.shape or x.size < 3 or not np.all(np.isfinite(x)):
        raise EstimationError("rep detection needs a finite signal with at least 3 samples, aligned with time")
    edge = (time - time[0] <= rest_window_s) | (time[-1] - time <= rest_window_s)
    direction = np.sign(np.median(x) - np.median(x[edge])) or 1.0
    dev = direction * x
    dev = dev - np.percentile(dev, 2)  # rest level = the most rest-like values (robust minimum)
    scale = float(np.percentile(dev, 98))
    if scale <= 0:
        raise EstimationError("signal never leaves its rest level: no repetition to detect")
    runs = _runs(dev > enter * scale)
    quiet = dev <= leave * scale
    phase = np.full(x.shape, np.nan)
    rep_index = np.full(x.shape, -1, dtype=int)
    k = 0
    prev_end = 0
    for j, (r0, r1) in enumerate(runs):
        nxt = runs[j + 1][0] if j + 1 < len(runs) else x.size
        q_before = np.flatnonzero(quiet[prev_end:r0])
        start = prev_end + q_before[-1] if q_before.size else prev_end + int(np.argmin(dev[prev_end : r0 + 1]))
        q_after = np.flatnonzero(quiet[r1:nxt])
        if q_after.size:
            end = r1 + int(q_after[0])
        elif r1 < nxt:
            end = r1 + int(np.argmin(dev[r1:nxt]))
        else:  # the excursion lasts to the end of the recording
            end = x.size - 1
        prev_end = end
        if time[end] - time[start] < min_duration_s:
            continue
        phase[start : end + 1] = (time[start : end + 1] - time[start]) / (time[end] - time[start])
        rep_index[start : end + 1] = k
        k += 1
    if k == 0:
        raise EstimationError("no repetition found in the phase signal")
    return phase, rep_index


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) index pairs of the True runs of a boolean array."""
    d = np.diff(np.r_[0, mask.astype(np.int8), 0])
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))


# -- kinematic phase: the project's msk_core.signal.reps, shared by calibration (offline) and the live node ------------------

# The offline phase of a rep and the live tracker's phase must mean the same thing, or the prior learnt per phase bin
# is read at the wrong bins live: both use msk_core.signal.reps's turning-point phase (start..bottom -> [0, 0.5),
# bottom..end -> [0.5, 1)) on the same coordinate, and the live tracker follows the template learnt at calibration.
PHASE_MODE = PhaseMode.TURNING_POINT
# Per pack, the coordinate whose excursion defines a rep (issue 4: elbow angle on the bench, hip angle in a deadlift).
DEFAULT_PHASE_COORDINATES = {"bench_press": "elbow_flex_r", "deadlift": "hip_flexion_r"}


def excursion_of(time: np.ndarray, values: np.ndarray, *, rest_window_s: float = 0.5) -> Excursion:
    """Direction of a rep: away from the level at the trial's first and last ``rest_window_s`` (rest)."""
    t = np.asarray(time, dtype=float)
    x = np.asarray(values, dtype=float)
    edge = (t - t[0] <= rest_window_s) | (t[-1] - t <= rest_window_s)
    return Excursion.DECREASE if np.median(x) < np.median(x[edge]) else Excursion.INCREASE


def rep_config(time: np.ndarray, values: np.ndarray) -> RepDetectionConfig:
    """msk_core.signal.reps's default detection settings with the excursion direction of this signal."""
    return RepDetectionConfig(excursion=excursion_of(time, values))


def kinematic_phase(time: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(phase, rep_index) of a whole trial from one coordinate (offline; NaN / -1 outside reps)."""
    try:
        reps = detect_kinematic_reps(time, values, rep_config(time, values))
    except InputError as exc:
        raise EstimationError(f"rep detection on the phase coordinate failed: {exc}") from None
    if not reps:
        raise EstimationError("no complete repetition found on the phase coordinate")
    return rep_phase(time, reps, PHASE_MODE)


@dataclass(frozen=True)
class PhaseModel:
    """What the live node needs to track the phase: the coordinate and the rep template learnt at calibration."""

    coordinate: str
    template: RepTemplate

    def to_dict(self) -> dict:
        return {"coordinate": self.coordinate, "template": self.template.to_dict()}

    @classmethod
    def from_dict(cls, data: dict) -> "PhaseModel":
        return cls(coordinate=str(data["coordinate"]), template=RepTemplate.from_dict(data["template"]))


def learn_phase_model(coordinate: str, series: list[tuple[np.ndarray, np.ndarray]]) -> PhaseModel:
    """Rep template of ``coordinate`` over one or more trials' (time, values), laid end to end."""
    if not series:
        raise EstimationError("no trial to learn a rep template from")
    times, values, offset = [], [], 0.0
    for t, v in series:
        t = np.asarray(t, dtype=float)
        dt = float(np.median(np.diff(t))) if t.size > 1 else 0.01
        times.append(t - t[0] + offset)
        values.append(np.asarray(v, dtype=float))
        offset = times[-1][-1] + dt
    t, v = np.concatenate(times), np.concatenate(values)
    try:
        template = learn_template(t, v, rep_config(t, v), mode=PHASE_MODE)
    except InputError as exc:
        raise EstimationError(f"cannot learn a rep template on {coordinate!r}: {exc}") from None
    return PhaseModel(coordinate, template)


class LivePhase:
    """Causal phase of the current frame from the profile's rep template. Explicit state; ``update`` per frame.

    Returns a phase in [0, 1) inside a rep and ``REST_PHASE`` between reps (the estimator's rest prior), the same
    convention as :meth:`msk_core.estimate.PhasePrior.at`.
    """

    def __init__(self, model: PhaseModel, coordinates: Sequence[str]) -> None:
        if model.coordinate not in coordinates:
            raise EstimationError(f"phase coordinate {model.coordinate!r} is not among {list(coordinates)}")
        self.model = model
        self.index = list(coordinates).index(model.coordinate)
        self.tracker = PhaseTracker(model.template)

    @classmethod
    def from_profile(cls, profile, coordinates: Sequence[str]) -> "LivePhase | None":
        """The profile's live phase, or ``None`` when it was calibrated without a kinematic phase coordinate."""
        model = getattr(profile, "phase_model", None)
        return None if model is None else cls(model, coordinates)

    def reset(self) -> None:
        self.tracker.reset()

    def update(self, t: float, q: np.ndarray) -> float:
        """Phase of the frame at time ``t`` (s) with pack coordinates ``q`` (rad)."""
        value = float(q[self.index])
        if not math.isfinite(value) or not math.isfinite(t):
            return REST_PHASE if not self.tracker.in_rep else self.tracker.phase
        phase = self.tracker.update(t, value)
        return REST_PHASE if math.isnan(phase) else phase

    def process(self, time: np.ndarray, q: np.ndarray) -> np.ndarray:
        """``update`` over a trial's frames; returns the phases."""
        return np.array([self.update(float(t), qi) for t, qi in zip(time, q)])
