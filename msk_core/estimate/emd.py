"""Electromechanical delay (EMD) for calibration: EMG leads the force it causes by some 30-100 ms.

Offline the envelope is zero-phase (no filter lag), so what is left between the EMG and the joint torque is the
physiological delay. Calibration compares activations with the EMG frame by frame; a lead of 50 ms at rep speeds of
~1 s per movement makes the EMG-implied torque early, and the strength factors absorb the mismatch. The delay is
estimated as the shift that lets the EMG, through the pack's moment arms, explain the inverse-dynamics torque best:
for each candidate delay d, least squares of the (capacity-scaled) torque on the columns R_ng F_ref,g e_g(t - d) of
the groups with EMG plus an intercept per coordinate (the unmeasured groups' share), free factors; the delay with the
smallest residual wins (parabolic refinement between frames). The strength factors of this fit are not used.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from msk_core.errors import EstimationError
from msk_core.estimate.pack import PackLike
from msk_core.estimate.trial import TrialData

if TYPE_CHECKING:
    from msk_core.estimate.profile import SubjectProfile

MAX_DELAY_S = 0.15  # beyond the physiological range (Cavanagh & Komi 1979: 30-100 ms)


@dataclass(frozen=True)
class EmdEstimate:
    delay_s: float
    candidates_s: np.ndarray  # delays tried
    residual: np.ndarray  # relative residual sum of squares per candidate (1 = nothing explained)

    def to_dict(self) -> dict:
        return {
            "delay_s": float(self.delay_s),
            "candidates_s": [round(float(x), 6) for x in self.candidates_s],
            "relative_residual": [round(float(x), 6) for x in self.residual],
        }


def calibrated_delay(profile: SubjectProfile) -> float:
    """A subject profile's calibrated electromechanical delay in seconds (0 for a profile calibrated without one)."""
    return float(((profile.calibration or {}).get("emd") or {}).get("delay_s") or 0.0)


def shift_emg(trial: TrialData, delay_s: float, *, hold_first: bool = True) -> TrialData:
    """The trial with each EMG envelope delayed by ``delay_s`` (e(t - d): aligned with the force it causes); the
    first ``d`` of the trial holds the first sample, or (``hold_first`` False, for scoring) is NaN: not measured."""
    if delay_s == 0 or not trial.emg:
        return trial
    before = None if hold_first else np.nan
    emg = {g: np.interp(trial.time - delay_s, trial.time, e, left=before) for g, e in trial.emg.items()}
    return replace(trial, emg=emg, extra={**trial.extra, "emg_delay_s": float(delay_s)})


def _envelopes(t: TrialData, emg_groups: list[str], delay_s: float) -> np.ndarray:
    """(T, len(emg_groups)) the trial's envelopes delayed by ``delay_s``; zeros for a group it has no EMG of (or
    none finite: an electrode that never worked)."""
    columns = []
    for g in emg_groups:
        e = t.emg.get(g)
        if e is not None and np.any(np.isfinite(e)):
            columns.append(np.interp(t.time - delay_s, t.time, e))
        else:
            columns.append(np.zeros(t.n_frames))
    return np.column_stack(columns)


def _design(
    pack: PackLike,
    trials: list[TrialData],
    emg_groups: list[str],
    envelopes: list[np.ndarray],
    moment_arms: list[np.ndarray],
    measured: list[np.ndarray],
):
    """Least-squares rows and target at one delay: ``envelopes`` per trial (:func:`_envelopes` at that delay),
    ``measured`` per trial the frames whose EMG is finite at every candidate delay."""
    groups = list(pack.groups)
    f_ref = np.asarray(pack.f_max_ref, dtype=float)
    cols = [groups.index(g) for g in emg_groups]
    rows, target = [], []
    n_c = len(pack.coordinates)
    for t, e, arms, valid in zip(trials, envelopes, moment_arms, measured):
        ok = np.all(np.isfinite(arms), axis=(1, 2)) & np.all(np.isfinite(t.torques), axis=1) & valid
        m = arms[ok] * f_ref[None, None, :]
        scale = 1.0 / np.maximum(np.abs(m).sum(axis=2), 1.0)  # per-coordinate capacity, as in the calibration
        x = m[:, :, cols] * e[ok][:, None, :] * scale[:, :, None]  # (T, n_c, G_emg)
        intercept = np.broadcast_to(np.eye(n_c)[None], (x.shape[0], n_c, n_c)) * scale[:, :, None]
        rows.append(np.concatenate([x, intercept], axis=2).reshape(-1, len(cols) + n_c))
        target.append((t.torques[ok] * scale).ravel())
    return np.vstack(rows), np.concatenate(target)


def estimate_emd(pack: PackLike, trials: list[TrialData], *, max_delay_s: float = MAX_DELAY_S) -> EmdEstimate:
    """Delay in [0, max_delay_s] that best explains the trials' torques by their EMG (see module docstring)."""
    if not any(t.emg for t in trials):
        raise EstimationError("EMD estimation needs EMG in at least one trial")
    # the finest frame interval (isometric trials are 50 Hz, lifts 100 Hz)
    dt = min(float(np.median(np.diff(t.time))) for t in trials if t.n_frames >= 2)
    candidates = np.arange(0, int(round(max_delay_s / dt)) + 1) * dt
    arms = [t.mechanics(pack).moment_arms for t in trials]
    emg_groups = sorted({g for t in trials for g in t.emg})
    shifted = [[_envelopes(t, emg_groups, d) for t in trials] for d in candidates]  # per candidate, per trial
    # one frame set for all candidates, so their residuals compare like with like: the frames whose EMG is finite at
    # every delay (a gap, NaN, or an EMG file that ends first, tells nothing)
    measured = [
        np.logical_and.reduce([np.all(np.isfinite(at_delay[k]), axis=1) for at_delay in shifted])
        for k in range(len(trials))
    ]
    if not any(m.any() for m in measured):
        raise EstimationError("EMD estimation found no frame with every envelope measured (all EMG NaN?)")
    residual = np.empty(candidates.size)
    for i, envelopes in enumerate(shifted):
        x, y = _design(pack, trials, emg_groups, envelopes, arms, measured)
        coef, *_ = np.linalg.lstsq(x, y, rcond=None)
        residual[i] = float(np.sum((y - x @ coef) ** 2) / max(float(np.sum((y - y.mean()) ** 2)), 1e-300))
    best = int(np.argmin(residual))
    delay = float(candidates[best])
    if 0 < best < candidates.size - 1:  # parabola through the minimum and its neighbours
        r0, r1, r2 = residual[best - 1 : best + 2]
        curv = r0 - 2 * r1 + r2
        if curv > 0:
            delay += dt * float(np.clip(0.5 * (r0 - r2) / curv, -0.5, 0.5))
    return EmdEstimate(delay_s=delay, candidates_s=candidates, residual=residual)
