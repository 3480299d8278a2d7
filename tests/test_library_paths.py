"""The two numerical cores written here beside the libraries that do the same job, checked against those libraries on
the demo sessions on every run (docs/estimation.md, "Solvers and dynamics"):

* the numba recursive Newton-Euler kernel (``Evaluator.COMPILED``) against pinocchio (``Evaluator.NUMPY``);
* the hot-started active-set solve against the warm PIQP on every frame (``hot_start=False``, ``--solver piqp``).
"""

from __future__ import annotations

import numpy as np
import pytest

from msk_core.estimate import FrameEstimator
from msk_core.estimate.pipeline import build_prior, trial_phase
from msk_core.estimate.trial import load_trial
from msk_core.model import Evaluator, load_pack

TORQUE_RTOL = 1e-9  # of the trial's largest torque
# PIQP stops at its tolerance (eps = 1e-8 on the scaled problem), the certified active set is exact to rounding: the
# difference is PIQP's (measured on the demo: max 1.7e-4, docs/estimation.md)
ACTIVATION_MAX_DIFF = 1e-3
ACTIVATION_RMS_DIFF = 1e-4


def _heavier_trial(repo_root, exercise):
    folders = sorted(
        (repo_root / "recordings" / "demo" / exercise).glob(f"{exercise}_*kg"),
        key=lambda p: float(p.name.rsplit("_", 1)[1].removesuffix("kg")),
    )
    return folders[-1] / "trial.toml"


@pytest.fixture(scope="module", params=["bench_press", "deadlift"])
def demo(request, repo_root):
    pack = load_pack(request.param)
    return pack, load_trial(_heavier_trial(repo_root, request.param), pack)


def test_compiled_dynamics_equal_pinocchio_on_the_demo_session(demo):
    pack, trial = demo
    compiled = load_pack(pack.name, evaluator=Evaluator.COMPILED)
    hand = trial.hand_load_newton
    tau_pin = np.array([pack.inverse_dynamics(q, qd, qdd, hand) for q, qd, qdd in zip(trial.q, trial.qd, trial.qdd)])
    tau_numba = np.array(
        [compiled.inverse_dynamics(q, qd, qdd, hand) for q, qd, qdd in zip(trial.q, trial.qd, trial.qdd)]
    )
    scale = np.abs(tau_pin).max()
    assert scale > 10.0  # a real lift, not a resting pose
    assert np.abs(tau_numba - tau_pin).max() <= TORQUE_RTOL * scale
    r_pin = np.array([pack.moment_arms(q) for q in trial.q[::10]])
    r_numba = np.array([compiled.moment_arms(q) for q in trial.q[::10]])
    np.testing.assert_allclose(r_numba, r_pin, rtol=0, atol=1e-12)


def _run(pack, trial, method, prior, hot_start):
    est = FrameEstimator(pack, method=method, prior=prior, hot_start=hot_start)
    results = [
        est.step(trial.q[i], torques=trial.torques[i], phase=trial_phase(trial, i)) for i in range(trial.n_frames)
    ]
    return np.array([r.activations for r in results]), [r.status for r in results], est.solver_counts


@pytest.mark.parametrize("method", ["hybrid", "proposed"])
def test_active_set_hot_start_equals_piqp_every_frame_on_the_demo_session(demo, method):
    pack, trial = demo
    prior = build_prior(pack, [trial]) if method == "proposed" else None
    hot, hot_status, counts = _run(pack, trial, method, prior, True)
    piqp, piqp_status, piqp_counts = _run(pack, trial, method, prior, False)
    assert hot_status == piqp_status
    assert piqp_counts["active_set"] == 0
    # the hot start really answered most frames (else this compares PIQP with itself)
    assert counts["active_set"] > 0.9 * trial.n_frames, counts
    diff = np.abs(hot - piqp)
    print(f"{pack.name} {method}: max |hot start - PIQP| {diff.max():.2e}, RMS {np.sqrt(np.mean(diff**2)):.2e}")
    assert diff.max() <= ACTIVATION_MAX_DIFF
    assert np.sqrt(np.mean(diff**2)) <= ACTIVATION_RMS_DIFF
