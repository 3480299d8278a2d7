"""What a trial's frames give at a pack's reference strengths, computed once per trial: the moment arms (with the
muscle-tendon lengths, when the pack gives them; one model evaluation per frame, under the one clamp rule of
:func:`msk_core.estimate.pack.clamp_to_ranges`) and static optimisation's activations of the frames' torques.

Calibration's delay estimate, its prior and minimal-effort error, its training frames, and the discrepancy analysis
all read them from here (``TrialData.mechanics(pack)``), so no trial's moment arms or static optimisation are
computed twice. The static optimisation is solved on first use only (a calibration with EMG on every group never
needs it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from msk_core.estimate.frame import FrameEstimator, FrameStatus, Method
from msk_core.estimate.pack import MusclePackLike, PackLike, clamp_to_ranges, fitted_ranges


@dataclass(frozen=True, eq=False)
class TrialMechanics:
    """Per frame of one trial, for one pack object. ``q`` and ``torques`` are the trial's own arrays (the same
    objects), so a trial copy with other coordinates or torques is never served these."""

    pack: PackLike
    q: np.ndarray  # (T, n_c) the trial's coordinates, rad
    torques: np.ndarray  # (T, n_c) the trial's torques, N·m
    q_clamped: np.ndarray  # (T, n_c) clamped into the pack's fitted ranges
    usable: np.ndarray  # (T,) the pose is within the clamp rule (else its moment arms and lengths are NaN)
    moment_arms: np.ndarray  # (T, n_c, G) m
    lengths: np.ndarray | None  # (T, G) m; None when the pack gives no lengths
    _min_effort: list[np.ndarray] = field(default_factory=list, repr=False)

    def serves(self, pack: PackLike, q: np.ndarray, torques: np.ndarray) -> bool:
        return self.pack is pack and self.q is q and self.torques is torques

    @property
    def min_effort(self) -> np.ndarray:
        """(T, G) static-optimisation activations at the reference F_max; NaN where not solved (frames outside the
        model, and ``reserve`` frames: the torque deficit must not become a prior). Solved on first use."""
        if not self._min_effort:
            self._min_effort.append(min_effort_of(self.pack, self.moment_arms, self.torques))
        return self._min_effort[0]


def mechanics_of(pack: PackLike, q: np.ndarray, torques: np.ndarray) -> TrialMechanics:
    """Moment arms and lengths of every frame of ``q`` (T, n_c): one model evaluation per usable pose."""
    q_clamped, usable = clamp_to_ranges(q, fitted_ranges(pack))
    n, n_c, g = q.shape[0], len(pack.coordinates), len(pack.groups)
    arms = np.full((n, n_c, g), np.nan)
    if not isinstance(pack, MusclePackLike):
        for i in np.flatnonzero(usable):
            arms[i] = pack.moment_arms(q_clamped[i])
        return TrialMechanics(pack, q, torques, q_clamped, usable, arms, None)
    lengths = np.full((n, g), np.nan)
    for i in np.flatnonzero(usable):
        lengths[i], arms[i] = pack.lengths_and_moment_arms(q_clamped[i])
    return TrialMechanics(pack, q, torques, q_clamped, usable, arms, lengths)


def min_effort_of(
    pack: PackLike, moment_arms: np.ndarray, torques: np.ndarray, f_max: np.ndarray | None = None
) -> np.ndarray:
    """(T, G) static optimisation (``so``, at ``f_max``; default the reference F_max) of each frame's torques with
    its moment arms; NaN where not solved."""
    est = FrameEstimator(pack, None, Method.SO, f_max=f_max)
    out = np.full((torques.shape[0], len(est.groups)), np.nan)
    for i in range(torques.shape[0]):
        res = est.solve(moment_arms[i], np.asarray(torques[i], dtype=float))
        if res.status is FrameStatus.SOLVED:  # reserve frames would put the torque deficit on the prior
            out[i] = res.activations
    return out
