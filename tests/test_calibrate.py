"""Calibration NLP: L-BFGS-B joint solve vs an independent block-coordinate solve; recovery on synthetic data."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from msk_core.errors import EstimationError
from msk_core.estimate.calibrate import CalibrationFrames, CalibrationSettings, calibrate, calibrate_alternating


def _synthetic(seed=0, t=60, n_c=2, g=5, emg_groups=4, noise=0.0):
    rng = np.random.default_rng(seed)
    f_ref = rng.uniform(400, 1200, g)
    k_true = rng.uniform(0.7, 1.8, g)
    k_true[emg_groups:] = 1.0  # groups without EMG keep reference strength in the "emg" mode
    phase = np.linspace(0, 1, t)
    a_true = np.clip(0.3 + 0.25 * np.sin(2 * np.pi * (phase[:, None] + rng.uniform(0, 1, g))), 0, 1)
    r = rng.uniform(-0.05, 0.05, (t, n_c, g)) * 0.2 + rng.uniform(-0.05, 0.05, (1, n_c, g))
    tau = np.einsum("tng,tg->tn", r * f_ref, a_true * k_true)
    emg = a_true + noise * rng.normal(size=a_true.shape)
    emg[:, emg_groups:] = np.nan
    frames = CalibrationFrames(
        moment_arms=r,
        torques=tau,
        prior_mean=np.clip(a_true + 0.05 * rng.normal(size=a_true.shape), 0, 1),
        prior_std=np.full_like(a_true, 0.1),
        emg=emg,
    )
    return f_ref, k_true, a_true, frames


@pytest.mark.parametrize("precondition", [True, False])
@pytest.mark.parametrize("strength_prior_std,emg_relative_std", [(None, None), (0.3, None), (0.3, 0.1)])
def test_joint_lbfgsb_and_alternating_reach_the_same_optimum(strength_prior_std, emg_relative_std, precondition):
    f_ref, _, _, frames = _synthetic(seed=1, t=40, noise=0.03)
    s = CalibrationSettings(
        torque_tolerance=0.02,
        strength_prior_std=strength_prior_std,
        precondition=precondition,
        emg_relative_std=emg_relative_std,
        identify_max_std=None,
        solver="joint",
    )  # the NLP optimum itself
    joint = calibrate(f_ref, frames, s)
    alt = calibrate_alternating(f_ref, frames, s)
    assert joint.converged, joint.message
    assert joint.projected_gradient < 1e-4 and alt.projected_gradient < 1e-4
    np.testing.assert_allclose(joint.objective, alt.objective, rtol=1e-5)
    np.testing.assert_allclose(joint.scale, alt.scale, atol=2e-3)
    np.testing.assert_allclose(joint.activations, alt.activations, atol=2e-3)
    # groups without EMG stay at reference strength; others within the bounds
    assert joint.scale[4] == 1.0
    assert np.all((joint.scale >= 0.5) & (joint.scale <= 2.5))
    rep = joint.report()
    expected = {"torque", "prior", "emg"} | ({"strength"} if strength_prior_std else set())
    assert rep["converged"] and set(rep["terms"]) == expected
    if emg_relative_std is not None:  # the EMG term with sigma^2 = emg_std^2 + (rel * e)^2, evaluated independently
        e = np.where(np.isfinite(frames.emg), frames.emg, 0.0)
        var = s.emg_std**2 + (emg_relative_std * e) ** 2
        has = np.isfinite(frames.emg)
        expected_emg = 0.5 * np.sum(((joint.activations - e) ** 2 / var)[has])
        np.testing.assert_allclose(rep["terms"]["emg"], expected_emg, rtol=1e-10)


@pytest.mark.parametrize("strength_prior_std", [None, 0.3])
def test_reduced_solver_reaches_the_joint_optimum(strength_prior_std):
    """solver="reduced" (L-BFGS-B on the strengths, each frame's activations its exact box-QP optimum) and the joint
    L-BFGS-B reach the same strengths, activations and objective; with a group without EMG and frames outside reps
    (prior std inf: those activations only the torque sees, held by the tiny ridge)."""
    f_ref, _, _, frames = _synthetic(seed=3, t=50, noise=0.03)
    frames.prior_std[:10, 4] = np.inf  # "between reps": the group without EMG has no prior there
    base = {"torque_tolerance": 0.02, "strength_prior_std": strength_prior_std, "identify_max_std": None}
    joint = calibrate(f_ref, frames, CalibrationSettings(**base, solver="joint"))
    reduced = calibrate(f_ref, frames, CalibrationSettings(**base))  # the default
    assert joint.converged and reduced.converged, (joint.message, reduced.message)
    assert reduced.method.startswith("L-BFGS-B (strengths")
    np.testing.assert_allclose(reduced.objective, joint.objective, rtol=1e-6)
    np.testing.assert_allclose(reduced.scale, joint.scale, atol=1e-4)
    np.testing.assert_allclose(reduced.activations, joint.activations, atol=2e-3)
    # the ridge on activations only the torque sees leaves its own pull there: |dJ/da| <= reduced_ridge * a
    assert reduced.projected_gradient <= CalibrationSettings().reduced_ridge and reduced.scale[4] == 1.0
    with pytest.raises(EstimationError, match="solver"):
        CalibrationSettings(solver="newton")


@pytest.mark.parametrize("identify,max_std", [("report", None), ("truncate", 1e-6)])
def test_a_reduced_solve_that_does_not_converge_is_continued_by_the_joint_solve(monkeypatch, identify, max_std):
    """The reduced solve is the default; where it ends unconverged (here: its first solve made to stop after one
    L-BFGS-B iteration), the joint solve takes over from its end and reaches the joint optimum, the message says what
    happened and the result keeps the caller's settings. With truncation the second solve (every direction held)
    converges: the result is still the unconverged first solve's, so it is continued all the same."""
    from msk_core.estimate import calibrate as module

    f_ref, _, _, frames = _synthetic(seed=3, t=50, noise=0.03)
    settings = CalibrationSettings(torque_tolerance=0.02, identify=identify, identify_max_std=max_std)
    joint = calibrate(f_ref, frames, dataclasses.replace(settings, solver="joint"))
    solve, calls = module._ReducedSolve.solve, []

    def first_cut_short(self, z0):  # L-BFGS-B stopped away from a stationary point, the first time only
        calls.append(1)
        if len(calls) > 1:
            return solve(self, z0)
        self.max_iter = 1
        z, _, iterations, message = solve(self, z0)
        return z, False, iterations, message

    monkeypatch.setattr(module._ReducedSolve, "solve", first_cut_short)
    continued = calibrate(f_ref, frames, settings)
    assert len(calls) == (2 if identify == "truncate" else 1)
    assert continued.converged and continued.method == "L-BFGS-B (joint)", continued.message
    assert continued.message.startswith("the reduced solve did not converge"), continued.message
    assert continued.settings.solver == "reduced"
    np.testing.assert_allclose(continued.scale, joint.scale, atol=1e-4)
    np.testing.assert_allclose(continued.objective, joint.objective, rtol=1e-6)


def test_calibration_recovers_true_strength_from_clean_emg():
    f_ref, k_true, _, frames = _synthetic(seed=2, t=80, noise=0.01)
    res = calibrate(f_ref, frames)
    assert res.converged
    err = np.abs(res.scale[:4] - k_true[:4]) / k_true[:4]
    assert np.median(err) <= 0.10, (res.scale, k_true)
    np.testing.assert_allclose(res.f_max, res.scale * f_ref)


def _with_passive_moment(seed: int, t: int = 80):
    """Synthetic frames whose torques also carry a passive moment (an exponential of a pose signal, 2 coefficients:
    one per coordinate) that no activation produces."""
    f_ref, k_true, a_true, frames = _synthetic(seed=seed, t=t, noise=0.01)
    pose = np.linspace(0.0, 1.0, t)
    basis = np.zeros((t, 2, 2))
    basis[:, 0, 0] = np.exp(-pose / 0.3)  # rises toward one end of the motion
    basis[:, 1, 1] = -np.exp(-(1.0 - pose) / 0.3)  # ... and the other, opposite sign
    beta_true = np.array([0.6, 0.4]) * np.abs(frames.torques).max(axis=0)
    torques = frames.torques + np.einsum("tnp,p->tn", basis, beta_true)
    plain = CalibrationFrames(frames.moment_arms, torques, frames.prior_mean, frames.prior_std, frames.emg)
    with_basis = CalibrationFrames(
        frames.moment_arms,
        torques,
        frames.prior_mean,
        frames.prior_std,
        frames.emg,
        torque_basis=basis,
        torque_basis_lower=np.zeros(2),
        torque_basis_names=("passive:0", "passive:1"),
    )
    return f_ref, k_true, beta_true, plain, with_basis


@pytest.mark.parametrize("solver", ["reduced", "joint"])
def test_a_torque_basis_is_fitted_jointly_and_keeps_the_strengths_true(solver):
    """A moment the activations do not produce goes into the strengths of a plain calibration; with its basis the
    calibration fits its coefficients instead, and the solvers (reduced, joint, alternating) agree on that optimum."""
    f_ref, k_true, beta_true, plain, with_basis = _with_passive_moment(seed=6)
    s = CalibrationSettings(strength_prior_std=None, identify_max_std=None, solver=solver)
    absorbed = calibrate(f_ref, plain, s)
    fitted = calibrate(f_ref, with_basis, s)
    alt = calibrate_alternating(f_ref, with_basis, s)
    err = lambda k: float(np.median(np.abs(k[:4] - k_true[:4]) / k_true[:4]))  # noqa: E731
    assert err(fitted.scale) <= 0.05 < err(absorbed.scale), (fitted.scale, absorbed.scale, k_true)
    np.testing.assert_allclose(fitted.torque_coefficients, beta_true, rtol=0.15)
    assert absorbed.torque_coefficients is None and "torque_coefficients" not in absorbed.report()
    assert fitted.report()["torque_coefficients"] == pytest.approx(list(fitted.torque_coefficients))
    assert fitted.report()["torque_basis"] == pytest.approx(
        dict(zip(("passive:0", "passive:1"), fitted.torque_coefficients))
    )
    assert fitted.converged and fitted.method.startswith(
        "L-BFGS-B (strengths" if solver == "reduced" else "L-BFGS-B (j"
    )
    assert fitted.projected_gradient < 1e-4 and alt.projected_gradient < 1e-4
    np.testing.assert_allclose(fitted.objective, alt.objective, rtol=1e-5)
    np.testing.assert_allclose(fitted.torque_coefficients, alt.torque_coefficients, rtol=1e-3)
    np.testing.assert_allclose(fitted.scale, alt.scale, atol=2e-3)


def test_a_torque_basis_respects_its_lower_bound_and_is_checked():
    f_ref, _, beta_true, plain, with_basis = _with_passive_moment(seed=7)
    # plain's frames with another torque basis: the dataclass's own checks run again (replace calls __init__)
    flipped = dataclasses.replace(plain, torque_basis=-with_basis.torque_basis, torque_basis_lower=np.zeros(2))
    res = calibrate(f_ref, flipped, CalibrationSettings(identify_max_std=None))
    assert np.all(res.torque_coefficients >= 0.0) and np.any(res.torque_coefficients <= 1e-9)
    with pytest.raises(EstimationError, match=r"torque_basis must be \(80, 2, p\)"):
        dataclasses.replace(plain, torque_basis=np.zeros((79, 2, 1)))
    with pytest.raises(EstimationError, match="torque_basis_lower must be"):
        dataclasses.replace(plain, torque_basis=np.zeros((80, 2, 2)), torque_basis_lower=np.zeros(3))


def test_strength_std_marginalises_the_torque_basis_coefficients():
    """With a torque basis the strengths' Laplace std is the k-block of the inverse Gauss-Newton curvature over all of
    (k, a, beta): the activations and the coefficients marginalised (a dense inverse here, the per-frame Schur
    complement in the code). It is larger than with the coefficients held: a strength confounded with the moment is
    not known as well as that."""
    from msk_core.estimate.calibrate import _Problem

    f_ref, _, _, _, with_basis = _with_passive_moment(seed=6)
    s = CalibrationSettings(strength_prior_std=None, identify_max_std=None)
    res = calibrate(f_ref, with_basis, s)
    prob = _Problem(f_ref, with_basis, s)
    z = np.concatenate([res.scale, res.activations.ravel(), res.torque_coefficients])
    m, inv_s, basis = prob.m, prob.inv_s, prob.basis
    t, n_c, g = m.shape
    rows = []  # d(torque residual / s) / d(k, a, beta), one row per frame and coordinate
    for i in range(t):
        for n in range(n_c):
            d_a = np.zeros((t, g))
            d_a[i] = m[i, n] * res.scale * inv_s[i, n]
            rows.append(
                np.concatenate([m[i, n] * res.activations[i] * inv_s[i, n], d_a.ravel(), basis[i, n] * inv_s[i, n]])
            )
    jac = np.array(rows)
    hess = jac.T @ jac + np.diag(np.concatenate([np.zeros(g), (prob.w_p + prob.w_e).ravel(), np.zeros(basis.shape[2])]))
    a = res.activations.ravel()
    free_k = np.array([lo < hi for lo, hi in prob.k_bounds])
    keep = np.concatenate([free_k, (a > prob.a_min + 1e-9) & (a < 1.0 - 1e-9), res.torque_coefficients > 1e-9])
    cov = np.linalg.inv(hess[np.ix_(keep, keep)])
    tau = prob.correlation_frames(z)
    dense = np.sqrt(tau * np.diag(cov)[: int(free_k.sum())])
    np.testing.assert_allclose(res.strength_std_data[free_k], dense, rtol=1e-4)
    keep[g + a.size :] = False  # the coefficients held
    held = np.sqrt(tau * np.diag(np.linalg.inv(hess[np.ix_(keep, keep)]))[: int(free_k.sum())])
    assert np.all(dense >= held * (1 - 1e-9)) and np.max(dense / held) > 1.1, (dense, held)  # 1.15 here


def test_strength_bounds_are_respected_and_validated():
    f_ref, _, _, frames = _synthetic(seed=3)
    frames.torques *= 10.0  # far stronger than any activation pattern can make with k <= 1.2
    res = calibrate(f_ref, frames, CalibrationSettings(strength_bounds=(0.8, 1.2)))
    assert np.all(res.scale[:4] <= 1.2 + 1e-12) and np.any(np.isclose(res.scale[:4], 1.2))
    with pytest.raises(EstimationError, match="strength bounds"):
        calibrate(f_ref, frames, CalibrationSettings(strength_bounds=(1.5, 2.5)))
    frames.torques[3, 0] = np.nan
    with pytest.raises(EstimationError, match="NaN"):
        CalibrationFrames(frames.moment_arms, frames.torques, frames.prior_mean, frames.prior_std, frames.emg)


def test_prior_on_emg_groups_counts_their_emg_twice_and_biases_strength():
    """With exact EMG and torques the strength is the truth; a smoothed across-rep prior on the same groups (built
    from that EMG) pulls activations off it and k absorbs the difference — hence weight 0 by default."""
    f_ref, k_true, a_true, frames = _synthetic(seed=4, t=80, emg_groups=5)
    frames.prior_mean[:] = 0.8 * a_true + 0.05  # a phase-averaged, flattened version of the activations
    frames.prior_std[:] = 0.03
    base = CalibrationSettings(strength_prior_std=None, identify_max_std=None)
    default = calibrate(f_ref, frames, base)
    np.testing.assert_allclose(default.scale, k_true, rtol=2e-3)
    doubled = calibrate(
        f_ref, frames, CalibrationSettings(strength_prior_std=None, identify_max_std=None, emg_group_prior_weight=1.0)
    )
    assert np.median(np.abs(doubled.scale / k_true - 1.0)) > 0.05


@pytest.mark.parametrize("mode", ["shrink", "truncate"])
def test_identifiability_flags_a_group_the_data_cannot_see_and_keeps_it_at_reference(mode):
    f_ref, k_true, a_true, frames = _synthetic(seed=5, t=120, emg_groups=5, noise=0.01)
    frames.moment_arms[:, :, 2] *= 1e-4  # group 2 barely acts on any coordinate: its strength is invisible
    frames.torques = np.einsum("tng,tg->tn", frames.moment_arms * f_ref, a_true * k_true)
    res = calibrate(f_ref, frames, CalibrationSettings(identify_max_std=0.15, identify=mode))
    assert res.status[2] == "unidentified" and abs(res.scale[2] - 1.0) < 1e-3 and res.identified_share[2] < 0.01
    assert res.strength_std_data[2] > 0.15
    if mode == "shrink":  # posterior std of an unseen factor = the strength prior's
        assert abs(res.strength_std[2] - 0.3) < 1e-3
    else:
        assert np.isnan(res.strength_std[2])
    ok = [j for j in range(5) if j != 2]
    assert all(res.status[j] == "identified" for j in ok), res.status
    assert np.all(res.strength_std_data[ok] / res.scale[ok] <= 0.15)
    assert np.all(res.strength_std[ok] <= res.strength_std_data[ok] + 1e-12)
    assert np.median(np.abs(res.scale[ok] / k_true[ok] - 1.0)) <= 0.05
    assert res.converged and res.projected_gradient < 1e-4
    rep = res.report(["g0", "g1", "g2", "g3", "g4"])
    assert rep["strength"]["g2"]["status"] == "unidentified" and rep["strength"]["g0"]["std_data"] is not None
    assert res.identified.tolist() == [True, True, False, True, True]


def test_laplace_strength_std_matches_the_spread_of_repeated_calibrations():
    """The curvature-based std of k (activations marginalised, residual autocorrelation accounted for) agrees with
    the empirical spread of k over independent EMG noise draws (white noise: tau_int ~ 1)."""
    f_ref, k_true, a_true, frames = _synthetic(seed=6, t=60, emg_groups=5)
    s = CalibrationSettings(strength_prior_std=None, identify_max_std=None, emg_std=0.05, torque_tolerance=0.02)
    rng = np.random.default_rng(0)
    draws, stds = [], []
    for _ in range(30):
        f = CalibrationFrames(
            frames.moment_arms,
            frames.torques,
            frames.prior_mean,
            np.full_like(a_true, np.inf),
            np.clip(a_true + 0.05 * rng.normal(size=a_true.shape), 0, 1),
        )
        r = calibrate(f_ref, f, s)
        draws.append(r.scale)
        stds.append(r.strength_std_data)
    empirical = np.std(draws, axis=0)
    predicted = np.median(stds, axis=0)
    ratio = predicted / empirical
    assert np.all((ratio > 0.5) & (ratio < 2.0)), (predicted, empirical)
