"""Personalised calibration and per-frame muscle-activation estimation (the seed method) with its baselines.

The names below are imported on first use (PEP 562), so that a light submodule (``flags``, ``fatigue_verdict``) does
not bring the estimator's imports (scipy.stats, the QP solvers) into a process that only reads its results."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from msk_core.estimate.frame import FrameEstimator, FrameResult, FrameStatus, Method
    from msk_core.estimate.pack import PackLike
    from msk_core.estimate.phase import LivePhase, PhaseModel
    from msk_core.estimate.prior import PhasePrior, fit_phase_prior
    from msk_core.estimate.profile import SubjectProfile
    from msk_core.signal.reps import REST_PHASE

_WHERE = {
    "FrameEstimator": "msk_core.estimate.frame",
    "FrameResult": "msk_core.estimate.frame",
    "FrameStatus": "msk_core.estimate.frame",
    "Method": "msk_core.estimate.frame",
    "PackLike": "msk_core.estimate.pack",
    "LivePhase": "msk_core.estimate.phase",
    "PhaseModel": "msk_core.estimate.phase",
    "PhasePrior": "msk_core.estimate.prior",
    "fit_phase_prior": "msk_core.estimate.prior",
    "SubjectProfile": "msk_core.estimate.profile",
    "REST_PHASE": "msk_core.signal.reps",
}

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


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(_WHERE[name]), name)
    globals()[name] = value
    return value
