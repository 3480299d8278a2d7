"""``assisted`` with ``live_synergists``: a group without EMG follows the live envelope of its measured synergist,
at its own prior level, weighed against its phase prior by the errors the profile measured for the two hypotheses
(docs/estimation.md, "Live EMG and `assisted`"). On a hand-built pack, with a torque term too weak to matter, the
estimate is the prior mean the method builds, so the rule is checked exactly."""

from __future__ import annotations

import numpy as np
import pytest

from msk_core.estimate import FrameEstimator, PhasePrior
from msk_core.estimate.profile import SubjectProfile

GROUPS = ["measured", "effort", "copied", "alone"]
PHASE = 0.3


class TinyPack:
    name = "tiny"
    version = "1"
    coordinates = ["c0"]
    groups = GROUPS
    f_max_ref = np.array([500.0, 400.0, 300.0, 200.0])

    def moment_arms(self, q):
        return np.array([[0.03, 0.02, 0.01, -0.02]])

    def inverse_dynamics(self, q, qd, qdd, hand_load_newton):
        return np.zeros(1)


def _profile(calibration: dict) -> SubjectProfile:
    n_bins = 4
    mean = np.tile([0.30, 0.10, 0.30, 0.05], (n_bins, 1))
    std = np.full((n_bins, len(GROUPS)), 0.05)
    prior = PhasePrior(
        tuple(GROUPS),
        mean,
        std,
        np.array([True, False, False, False]),
        sources=("emg", "min_effort", "synergist:measured", "min_effort"),
    )
    pack = TinyPack()
    return SubjectProfile(
        pack.name, pack.version, GROUPS, pack.f_max_ref.copy(), pack.f_max_ref.copy(), prior, calibration=calibration
    )


def _assisted(profile: SubjectProfile, live: bool, envelope: float) -> np.ndarray:
    pack = TinyPack()
    est = FrameEstimator(pack, profile, "assisted", torque_tolerance=1e4, live_synergists=live, hot_start=False)
    emg = np.array([envelope, np.nan, np.nan, np.nan])
    return est.solve(pack.moment_arms(None), np.zeros(1), PHASE, emg).activations


def test_live_synergists_weigh_the_measured_synergists_envelope_into_the_prior_mean():
    me_err, syn_err = 0.10, 0.05
    profile = _profile(
        {"synergists": {"effort": "measured"}, "synergist_error_rms": syn_err, "min_effort_error_rms": me_err}
    )
    envelope = 0.6
    off = _assisted(profile, False, envelope)
    on = _assisted(profile, True, envelope)
    assert off == pytest.approx([0.6, 0.10, 0.30, 0.05], abs=1e-4)  # the phase prior, the EMG for the measured
    w = me_err**2 / (me_err**2 + syn_err**2)  # 0.8: the synergist hypothesis erred less on the measured groups
    gain = 0.10 / 0.30  # the envelope brought to the group's own (pooled) prior level
    assert on[1] == pytest.approx(w * gain * envelope + (1 - w) * 0.10, abs=1e-4)
    assert on[2] == pytest.approx(envelope, abs=1e-4)  # its prior is the synergist's: it takes the envelope
    assert on[3] == pytest.approx(0.05, abs=1e-4)  # no synergist: unchanged
    # without the envelope of the synergist the groups keep their phase prior
    nan = _assisted(profile, True, np.nan)
    assert nan[1:] == pytest.approx([0.10, 0.30, 0.05], abs=1e-4)


def test_without_a_measured_synergist_error_only_the_copied_prior_follows():
    """No measured pair to check "same drive, own level" on: the moment-arm synergist is not used; a group whose
    prior is its synergist's still follows that synergist (the hypothesis its prior already made)."""
    profile = _profile({"synergists": {"effort": "measured"}, "min_effort_error_rms": 0.1})
    on = _assisted(profile, True, 0.6)
    assert on[1:] == pytest.approx([0.10, 0.6, 0.05], abs=1e-4)


def test_the_sources_own_synergist_error_outweighs_the_pooled_one():
    """``synergist_error_by_source``: how well the source stood for its own measured synergists; a source that stood
    badly (error 0.2 against the minimal-effort error 0.1) moves the group less than the pooled error would."""
    calibration = {"synergists": {"effort": "measured"}, "synergist_error_rms": 0.05, "min_effort_error_rms": 0.1}
    pooled = _assisted(_profile(calibration), True, 0.6)
    own = _assisted(_profile(calibration | {"synergist_error_by_source": {"measured": 0.2}}), True, 0.6)
    w = 0.1**2 / (0.1**2 + 0.2**2)
    assert own[1] == pytest.approx(w * (0.10 / 0.30) * 0.6 + (1 - w) * 0.10, abs=1e-4)
    assert abs(own[1] - 0.10) < abs(pooled[1] - 0.10)
