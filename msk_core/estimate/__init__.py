"""Personalised calibration and per-frame muscle-activation estimation (the seed method) with its baselines."""

from msk_core.estimate.frame import FrameEstimator, FrameResult, FrameStatus, Method
from msk_core.estimate.pack import PackLike
from msk_core.estimate.phase import LivePhase, PhaseModel
from msk_core.estimate.prior import REST_PHASE, PhasePrior, prior_from_reps
from msk_core.estimate.profile import SubjectProfile

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
    "prior_from_reps",
]
