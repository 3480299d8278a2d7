"""Repetition phase for estimation: the offline phase of a trial (:func:`kinematic_phase`, :func:`torque_phase`) and
the live phase of the node (:class:`PhaseModel`, :class:`LivePhase`), both msk_core.signal.reps's.

Offline, the reps of the trial's phase signal come from ``msk_core.signal.reps.detect_reps`` (complete reps: rest ->
excursion -> rest, direction from the trial's rest level) and their phase from ``rep_phase`` in turning-point mode;
calibration learns a rep template on a kinematic phase coordinate and :class:`LivePhase` tracks the same phase causally
from it. Between reps the phase is ``REST_PHASE``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from msk_core.errors import EstimationError, InputError
from msk_core.signal.reps import (
    Excursion,
    PhaseMode,
    PhaseTracker,
    RepDetectionConfig,
    RepTemplate,
    detect_reps,
    learn_template,
    rep_phase,
)

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


# A joint torque need not come back to rest between the movements of a set (the lumbar moment of a box lift stays above
# a fifth of its range while the box is put down and lifted again): on a torque, a rep starts above 0.3 of its range.
TORQUE_START_FRACTION = 0.3


def rep_config(time: np.ndarray, values: np.ndarray, *, torque: bool = False) -> RepDetectionConfig:
    """msk_core.signal.reps's default detection settings with the excursion direction of this signal (and on a joint
    torque, ``TORQUE_START_FRACTION``)."""
    config = RepDetectionConfig(excursion=excursion_of(time, values))
    return replace(config, start_fraction=TORQUE_START_FRACTION) if torque else config


def kinematic_phase(time: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(phase, rep_index) of a whole trial from one coordinate (offline; ``REST_PHASE`` / -1 outside reps)."""
    return _offline_phase(time, values, rep_config(time, values), "phase coordinate")


def torque_phase(time: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(phase, rep_index) of a whole trial from one joint torque (``phase_signal = "torque:<coordinate>"``)."""
    return _offline_phase(time, values, rep_config(time, values, torque=True), "phase torque")


def _offline_phase(
    time: np.ndarray, values: np.ndarray, config: RepDetectionConfig, what: str
) -> tuple[np.ndarray, np.ndarray]:
    try:
        reps = detect_reps(time, values, config)
    except InputError as exc:
        raise EstimationError(f"rep detection on the {what} failed: {exc}") from None
    if not reps:
        raise EstimationError(f"no complete repetition found on the {what}")
    return rep_phase(time, reps, PHASE_MODE)


@dataclass(frozen=True)
class PhaseModel:
    """What the live node needs to track the phase: the coordinate and the rep template learnt at calibration."""

    coordinate: str
    template: RepTemplate

    def to_dict(self) -> dict:
        return {"coordinate": self.coordinate, "template": self.template.to_dict()}

    @classmethod
    def from_dict(cls, data: dict) -> PhaseModel:
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

    Returns a phase in [0, 1) inside a rep and ``REST_PHASE`` between reps (the estimator's rest prior).
    """

    def __init__(self, model: PhaseModel, coordinates: Sequence[str]) -> None:
        if model.coordinate not in coordinates:
            raise EstimationError(f"phase coordinate {model.coordinate!r} is not among {list(coordinates)}")
        self.model = model
        self.index = list(coordinates).index(model.coordinate)
        self.tracker = PhaseTracker(model.template)

    @classmethod
    def from_profile(cls, profile, coordinates: Sequence[str]) -> LivePhase | None:
        """The profile's live phase, or ``None`` when it was calibrated without a kinematic phase coordinate."""
        model = getattr(profile, "phase_model", None)
        return None if model is None else cls(model, coordinates)

    def reset(self) -> None:
        self.tracker.reset()

    def update(self, t: float, q: np.ndarray) -> float:
        """Phase of the frame at time ``t`` (s) with pack coordinates ``q`` (rad)."""
        value = float(q[self.index])
        if not math.isfinite(value) or not math.isfinite(t):
            return self.tracker.phase  # a frame without a pose: the rep (or rest) goes on
        return self.tracker.update(t, value)

    def process(self, time: np.ndarray, q: np.ndarray) -> np.ndarray:
        """``update`` over a trial's frames; returns the phases."""
        return np.array([self.update(float(t), qi) for t, qi in zip(time, q)])
