"""Shared by the tests that need a subject profile without calibrating one: the pack's reference strengths and a prior
that tells the phases apart."""

from __future__ import annotations

from typing import Any

import numpy as np

from msk_core.estimate import PhasePrior, SubjectProfile
from msk_core.model.pack import ModelPack

PRIOR_BINS = 10


def phased_profile(pack: ModelPack, **fields: Any) -> SubjectProfile:
    """A profile of ``pack`` at its reference strengths whose prior differs per phase bin and at rest, so a wrong phase
    gives other activations; ``fields``: more of the profile's (``effects``, ``phase_model``)."""
    groups = list(pack.groups)
    f_ref = np.asarray(pack.f_max_ref, dtype=float)
    prior = PhasePrior(
        tuple(groups),
        np.linspace(0.05, 0.5, PRIOR_BINS)[:, None] * np.ones((1, len(groups))),
        np.full((PRIOR_BINS, len(groups)), 0.05),
        np.ones(len(groups), dtype=bool),
        rest_mean=np.full(len(groups), 0.01),
        rest_std=np.full(len(groups), 0.02),
    )
    return SubjectProfile(pack.name, str(pack.version), groups, f_ref.copy(), f_ref.copy(), prior, **fields)


def reference_profile(pack: ModelPack, electrodes: dict[str, str]) -> SubjectProfile:
    """A subject at the pack's reference strengths whose electrodes (channel -> group) have MVC divisor 1."""
    normalisation = {channel: {"group": group, "divisor": 1.0} for channel, group in electrodes.items()}
    f_ref = np.asarray(pack.f_max_ref, dtype=float)
    return SubjectProfile(
        pack.name, str(pack.version), list(pack.groups), f_ref.copy(), f_ref.copy(), emg_normalisation=normalisation
    )
