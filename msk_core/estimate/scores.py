"""``msk evaluate`` scores: per trial and method, activation RMSE against measured EMG and torque tracking, and the
prior band the report plots. The report files and plots: :mod:`services.surfaces.reports.evaluation`."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from msk_core.errors import EstimationError
from msk_core.estimate.emd import calibrated_delay, shift_emg
from msk_core.estimate.metrics import activation_rmse, torque_tracking
from msk_core.estimate.pack import PackLike
from msk_core.estimate.pipeline import TrialEstimate, estimate_trial, trial_phase
from msk_core.estimate.profile import SubjectProfile
from msk_core.estimate.trial import TrialData
from msk_core.progress import Progress

METHODS = ("proposed", "so", "hybrid", "prior")
# Published EMG-driven range for such lifts (the reference: R 0.88-0.94, RMSE 0.21-0.38 N·m/kg).
PUBLISHED_EMG_DRIVEN = {"r": (0.88, 0.94), "rmse_nm_per_kg": (0.21, 0.38)}


@dataclass
class MethodScore:
    trial: str
    method: str
    activation_rmse: dict[str, float]
    torque: dict[str, dict[str, float]]
    flag_counts: dict[str, int]
    frames: int
    # against the envelopes delayed by the subject's calibrated electromechanical delay (a(t) = e(t - d), the
    # calibration's model of activation; docs/estimation.md "Leave one electrode out")
    activation_rmse_aligned: dict[str, float] = field(default_factory=dict)


def evaluate(
    pack: PackLike,
    subject: SubjectProfile,
    trials: list[TrialData],
    *,
    methods=METHODS,
    progress: Progress | None = None,
    **options,
) -> tuple[list[MethodScore], dict[tuple[str, str], TrialEstimate]]:
    """Every method over every trial; ``options`` go to each :class:`FrameEstimator` (solver, activation bounds)."""
    scores, runs = [], {}
    delay_s = calibrated_delay(subject)
    for trial in trials:
        aligned = shift_emg(trial, delay_s, hold_first=False).emg
        for method in methods:
            run = estimate_trial(pack, trial, method, subject=subject, progress=progress, **options)
            runs[(trial.name, method)] = run
            scores.append(
                MethodScore(
                    trial=trial.name,
                    method=method,
                    activation_rmse=activation_rmse(run.activations, run.groups, trial.emg),
                    torque=torque_tracking(run.model_torques, run.torques, run.coordinates, trial.body_mass_kg),
                    flag_counts=run.flag_counts,
                    frames=trial.n_frames,
                    activation_rmse_aligned=activation_rmse(run.activations, run.groups, aligned),
                )
            )
    return scores, runs


def prior_band(trial: TrialData, subject: SubjectProfile) -> tuple[np.ndarray, np.ndarray]:
    """(T, G) mean and standard deviation of the subject's phase prior at each frame of the trial (groups in the
    profile's order): what the ``prior`` method assumes before any torque."""
    prior = subject.prior
    if prior is None:
        raise EstimationError("the subject profile has no phase prior (a profile written by a calibration has one)")
    at = [prior.at(trial_phase(trial, i)) for i in range(trial.n_frames)]
    return np.array([mean for mean, _ in at]), np.array([std for _, std in at])
