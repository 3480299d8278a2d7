"""Personalised calibration and per-frame muscle-activation estimation (the seed method) with its baselines."""

from msk_core.estimate.frame import FrameEstimator, FrameResult, FrameStatus, Method
from msk_core.estimate.pack import PackLike
from msk_core.estimate.phase import LivePhase, PhaseModel
from msk_core.estimate.prior import PhasePrior, fit_phase_prior
from msk_core.estimate.profile import SubjectProfile
from msk_core.signal.reps import REST_PHASE

__all__ = [
    "FrameEstimator",
    "FrameResult",
    "FrameStatus",
    "LivePhase",
    "Method",
    "PackLike",
    "PhaseModel",
    "PhasePrior",
    "REST_PHASE",
    "SubjectProfile",
    "fit_phase_prior",
]
