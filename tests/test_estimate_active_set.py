"""The hot-started active-set solve: the same optimum as PIQP and an independent bounded least-squares solve, a
KKT certificate checked here in numpy, PIQP taking over when the working set is not found in time."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import lsq_linear

from msk_core.estimate import FrameEstimator, PhasePrior, active_set
from msk_core.estimate.frame import BOUND_TOL, MIN_TORQUE_SCALE, FrameResult
from msk_core.estimate.laplace import laplace_std
from msk_core.signal.reps import REST_PHASE


def _random_problem(rng, m, g):
    r = rng.uniform(-0.05, 0.05, (m, g)) * (rng.random((m, g)) < 0.6)
    f_max = rng.uniform(100.0, 3000.0, g)
    capacity = np.abs(r * f_max).sum(axis=1)
    tau = capacity * rng.uniform(-0.8, 0.8, m)  # some beyond what a subset can do: active bounds at 0 and 1
    w = 10.0 ** rng.uniform(0, 5)
    mean = rng.uniform(-0.2, 1.2, (1, g))  # priors outside [0, 1] push variables onto both bounds
    prec = 10.0 ** rng.uniform(-1, 3.5, (1, g))
    return r, f_max, tau, w, mean, prec


def _scaled(r, f_max, tau):
    a = r * f_max
    c = np.maximum(np.abs(a).sum(axis=1), MIN_TORQUE_SCALE)
    return a / c[:, None], tau / c


def _kkt_violation(at, tt, w, d, mu, x):
    """Largest violation of the box-QP optimality conditions, relative to the gradient's scale."""
    grad = w * at.T @ (at @ x - tt) + d * (x - mu)
    lower, upper = x <= 0.0, x >= 1.0
    free = ~(lower | upper)
    worst = max(np.abs(grad[free]).max(initial=0.0), (-grad[lower]).max(initial=0.0), grad[upper].max(initial=0.0))
    scale = np.max(w * np.abs(at).T @ (np.abs(tt) + 1.0) + d * (1.0 + np.abs(mu)))
    return worst / scale


@pytest.mark.parametrize("m,g", [(1, 3), (2, 6), (4, 19), (6, 60), (10, 8)])
def test_cold_solve_is_certified_and_matches_bounded_least_squares(m, g):
    rng = np.random.default_rng(m * 100 + g)
    lb, ub = np.zeros(g), np.ones(g)
    for _ in range(40):
        r, f_max, tau, w, mean, prec = _random_problem(rng, m, g)
        x, state = active_set.new_state(g)
        code, changes, out, torques = active_set.solve_box_lsq(
            r, f_max, tau, w, mean, prec, 0, 0, 0.0, lb, ub, MIN_TORQUE_SCALE, x, state, 4 * g + 10, True
        )
        assert code == active_set.CERTIFIED
        at, tt = _scaled(r, f_max, tau)
        np.testing.assert_allclose(out[m + 3], _general_std(at, w, prec[0], False, x), rtol=1e-9, atol=1e-7)
        np.testing.assert_allclose(out[:m], at, rtol=1e-14)
        np.testing.assert_array_equal(out[m], x)
        assert np.all((x >= 0.0) & (x <= 1.0))
        assert _kkt_violation(at, tt, w, prec[0], mean[0], x) < 1e-9
        sd = 1.0 / np.sqrt(prec[0])
        ref = lsq_linear(
            np.vstack([np.sqrt(w) * at, np.diag(1.0 / sd)]),
            np.r_[np.sqrt(w) * tt, mean[0] / sd],
            bounds=(0, 1),
            tol=1e-13,
            lsq_solver="exact",
        )
        np.testing.assert_allclose(x, ref.x, atol=1e-6)
        np.testing.assert_allclose(torques[0], r @ (f_max * x), rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(torques[1], torques[0] - tau, rtol=1e-12, atol=1e-9)


def test_hot_start_reuses_the_working_set_and_cannot_be_fooled_by_a_stale_one():
    rng = np.random.default_rng(5)
    m, g = 4, 19
    r, f_max, tau, w, mean, prec = _random_problem(rng, m, g)
    lb, ub = np.zeros(g), np.ones(g)
    x, state = active_set.new_state(g)
    args = (lb, ub, MIN_TORQUE_SCALE)
    cold = active_set.solve_box_lsq(r, f_max, tau, w, mean, prec, 0, 0, 0.0, *args, x, state, 100, False)
    assert cold[0] == active_set.CERTIFIED
    again = active_set.solve_box_lsq(r, f_max, tau, w, mean, prec, 0, 0, 0.0, *args, x, state, 100, False)
    assert again[0] == active_set.CERTIFIED and again[1] == 0  # same frame: one solve, no working-set change
    # a working set that is wrong everywhere: still the same optimum, after changes
    wrong = np.where(state == active_set.FREE, active_set.UPPER, active_set.FREE).astype(np.int8)
    x2 = np.full(g, 0.5)
    flipped = active_set.solve_box_lsq(r, f_max, tau, w, mean, prec, 0, 0, 0.0, *args, x2, wrong, 200, False)
    assert flipped[0] == active_set.CERTIFIED and flipped[1] > 0
    np.testing.assert_allclose(x2, x, atol=1e-10)
    # too few changes allowed: no certificate (the caller then asks PIQP)
    wrong = np.where(state == active_set.FREE, active_set.UPPER, active_set.FREE).astype(np.int8)
    short = active_set.solve_box_lsq(r, f_max, tau, w, mean, prec, 0, 0, 0.0, *args, np.full(g, 0.5), wrong, 0, False)
    assert short[0] == active_set.NOT_CONVERGED


class SmoothPack:
    """Moment arms r(q) = r0 + q r1 and a torque that sweeps beyond the muscles' reach and back."""

    name, version = "smooth", "1"

    def __init__(self, m=4, g=19, seed=0):
        rng = np.random.default_rng(seed)
        self.coordinates = [f"c{i}" for i in range(m)]
        self.groups = [f"g{i}" for i in range(g)]
        self.f_max_ref = rng.uniform(200.0, 2500.0, g)
        self.r0 = rng.uniform(-0.05, 0.05, (m, g)) * (rng.random((m, g)) < 0.6)
        self.r1 = rng.uniform(-0.02, 0.02, (m, g)) * (self.r0 != 0)

    def moment_arms(self, q):
        return self.r0 + np.asarray(q)[:, None] * self.r1

    def inverse_dynamics(self, q, qd, qdd, hand_load_newton):
        return 150.0 * np.sin(3.0 * np.asarray(q)) + 2.0 * np.asarray(qdd)


def _prior(groups, rng):
    n_bins = 20
    mean = rng.uniform(0.0, 0.5, (n_bins, len(groups)))
    std = rng.uniform(0.03, 0.3, (n_bins, len(groups)))
    return PhasePrior(
        tuple(groups),
        mean,
        std,
        np.ones(len(groups), dtype=bool),
        rest_mean=np.full(len(groups), 0.02),
        rest_std=np.full(len(groups), 0.05),
    )


def _envelopes(n_frames: int, n_groups: int) -> list[np.ndarray | None]:
    """``assisted``'s live EMG: two measured groups (one of them switching off and on), none every 50th frame."""
    out: list[np.ndarray | None] = []
    for i in range(n_frames):
        e = np.full(n_groups, np.nan)
        e[0] = 0.3 + 0.25 * np.sin(i / 20.0)
        if (i // 80) % 2 == 0:
            e[2] = 0.05 + 0.04 * np.cos(i / 13.0)
        out.append(None if i % 50 == 0 else e)
    return out


@pytest.mark.parametrize("method", ["proposed", "hybrid", "assisted"])
def test_estimator_hot_start_gives_piqps_optimum_frame_by_frame(method):
    pack = SmoothPack()
    prior = _prior(pack.groups, np.random.default_rng(1)) if method != "hybrid" else None
    emg = _envelopes(600, len(pack.groups)) if method == "assisted" else [None] * 600
    hot = FrameEstimator(pack, method=method, prior=prior)
    piqp_only = FrameEstimator(pack, method=method, prior=prior, hot_start=False)
    limited = FrameEstimator(pack, method=method, prior=prior, hot_start_max_changes=1)
    t = np.arange(600) / 100.0
    q = 0.6 * np.sin(np.outer(t, [1.0, 1.3, 0.7, 2.1]))
    qdd = -0.6 * np.sin(np.outer(t, [1.0, 1.3, 0.7, 2.1])) * np.array([1.0, 1.69, 0.49, 4.41])
    phases = [None if i % 97 == 0 else (REST_PHASE if (i // 150) % 2 else (i % 150) / 150) for i in range(600)]
    sources = {"active_set": 0, "piqp": 0}
    bound_disagreements = kernel_std = reserve = 0
    for i in range(600):
        a = hot.step(q[i], None, qdd[i], phase=phases[i], emg=emg[i])
        b = piqp_only.step(q[i], None, qdd[i], phase=phases[i], emg=emg[i])
        c = limited.step(q[i], None, qdd[i], phase=phases[i], emg=emg[i])
        # "reserve": the toy pack's torque beyond its muscles' capacity at some poses (the same flag for all three)
        assert a.status.value == b.status.value == c.status.value in ("solved", "reserve")
        reserve += a.status.value == "reserve"
        kernel_std += _kernel_std_is_laplace_std(a)
        np.testing.assert_allclose(a.activations, b.activations, atol=2e-4)
        np.testing.assert_allclose(c.activations, a.activations, atol=2e-4)
        np.testing.assert_allclose(a.model_torques, b.model_torques, rtol=1e-3, atol=0.05)
        # the std is 0 at a bound: PIQP's interior iterate may stop just above a bound the active set pins exactly
        # (and then the free block, hence every free std, differs too)
        same = a.at_bound == b.at_bound
        if same.all():
            np.testing.assert_allclose(a.activation_std, b.activation_std, atol=1e-3)
        else:
            assert np.all(np.minimum(b.activations[~same], 1.0 - b.activations[~same]) < 2e-4)
            bound_disagreements += 1
        sources[c.solver] += 1
    if method != "hybrid":  # hybrid sends many groups to 0, where PIQP stops ~1e-5 above it in most frames
        assert bound_disagreements < 60  # measured 33 of 600 (PIQP eps 1e-8)
    assert hot.solver_counts == {"active_set": 600, "piqp": 0} and kernel_std == 600
    assert hot.flag_counts == piqp_only.flag_counts == limited.flag_counts == ({"reserve": reserve} if reserve else {})
    assert piqp_only.solver_counts == {"active_set": 0, "piqp": 600}
    # one change allowed: frames needing more go to PIQP, which then seeds the next frame's working set
    assert limited.solver_counts == sources and sources["piqp"] > 0 and sources["active_set"] > 300


def test_prior_rows_interpolate_exactly_like_the_prior():
    prior = _prior([f"g{i}" for i in range(5)], np.random.default_rng(3))
    mean_t, prec_t = prior.table()
    phases = [None, math.nan, REST_PHASE, -0.3, 0.0, 1e-9, 0.024, 0.025, 0.026, 0.5, 0.731, 0.975, 0.99, 1.0, 1.5]
    for phase in phases:
        i0, i1, frac = prior.rows(phase)
        mu, prec = prior.mean_precision(phase)
        np.testing.assert_allclose(mean_t[i0] + frac * (mean_t[i1] - mean_t[i0]), mu, rtol=1e-14, atol=1e-15)
        np.testing.assert_allclose(prec_t[i0] + frac * (prec_t[i1] - prec_t[i0]), prec, rtol=1e-14)
    # the rows themselves: bins, pooled prior (law of total variance), rest prior
    n = prior.n_bins
    np.testing.assert_array_equal(mean_t[:n], prior.mean)
    np.testing.assert_allclose(mean_t[n], prior.mean.mean(axis=0))
    np.testing.assert_allclose(1.0 / prec_t[n], (prior.std**2).mean(axis=0) + prior.mean.var(axis=0))
    np.testing.assert_array_equal(mean_t[n + 1], prior.rest_mean)
    np.testing.assert_allclose(prec_t[n + 1], 1.0 / prior.rest_std**2)
    assert prior.rows(0.5) == (9, 10, pytest.approx(0.5))  # 20 bins: phase 0.5 lies between bin centres 9 and 10


def test_warm_up_leaves_a_fresh_estimator():
    pack = SmoothPack()
    prior = _prior(pack.groups, np.random.default_rng(2))
    warmed, fresh = (FrameEstimator(pack, method="proposed", prior=prior) for _ in range(2))
    warmed.warm_up()
    assert warmed.frames == 0 and warmed.flag_counts == {} and warmed.solver_counts == {"active_set": 0, "piqp": 0}
    q = np.array([0.1, -0.2, 0.3, 0.0])
    tau = np.array([20.0, -10.0, 5.0, 0.0])
    a, b = warmed.step(q, torques=tau), fresh.step(q, torques=tau)
    np.testing.assert_array_equal(a.activations, b.activations)
    assert a.iterations == b.iterations


# -- so: the equality-constrained kernel ------------------------------------------------------------------------------


def _so_kkt_violation(at, tt, x, lb, ub):
    """Largest violation of so's optimality conditions at x, found here in numpy (not from the kernel's state): the
    multipliers lam from the free groups' stationarity 2 a_F + A_F' lam = 0 (least squares), then the equality's
    residual, the free groups' stationarity and the held groups' signs (2 a + A' lam >= 0 at lb, <= 0 at ub)."""
    lower, upper = x <= lb, x >= ub
    free = ~(lower | upper)
    lam = np.linalg.lstsq(at[:, free].T, -2.0 * x[free], rcond=None)[0]
    grad = 2.0 * x + at.T @ lam
    return max(
        np.abs(at @ x - tt).max(),
        np.abs(grad[free]).max(initial=0.0),
        (-grad[lower]).max(initial=0.0),
        grad[upper].max(initial=0.0),
    )


@pytest.mark.parametrize("m,g", [(1, 3), (2, 6), (4, 19), (6, 40)])
def test_so_kernel_cold_and_hot_is_certified_on_feasible_frames(m, g):
    """Torques some activations in [0, 1] produce: the cold start certifies (nearly) all, each with so's KKT
    conditions holding in numpy, and the same frame again is one solve with no working-set change."""
    rng = np.random.default_rng(7 * m + g)
    lb, ub = np.zeros(g), np.ones(g)
    certified = 0
    for _ in range(40):
        r, f_max, _, _, _, _ = _random_problem(rng, m, g)
        r[:, : min(m, g)] += 0.01 * np.eye(m, min(m, g))  # every coordinate crossed by some group
        tau = (r * f_max) @ np.clip(rng.uniform(-0.3, 1.0, g), 0.0, 1.0)
        x, state = active_set.new_state(g)
        code, changes, out, torques = active_set.solve_min_norm_eq(r, f_max, tau, lb, ub, 1.0, x, state, 4 * g + 10)
        if code != active_set.CERTIFIED:
            continue
        certified += 1
        at, tt = _scaled(r, f_max, tau)
        np.testing.assert_array_equal(out[m], x)
        np.testing.assert_array_equal(out[m + 2], 2.0)
        assert np.all((x >= lb) & (x <= ub))
        assert _so_kkt_violation(at, tt, x, lb, ub) < 1e-9
        np.testing.assert_allclose(torques[0], tau, rtol=1e-9, atol=1e-9)
        again = active_set.solve_min_norm_eq(r, f_max, tau, lb, ub, 1.0, x, state, 4 * g + 10)
        assert again[0] == active_set.CERTIFIED and again[1] == 0
    assert certified >= 36, f"{certified} of 40 feasible frames certified from a cold start"


def test_so_kernel_degenerate_working_sets_hand_the_frame_over():
    """Every group held: A_F A_F' is empty (singular). With no torque every bound is weakly active (a = 0, all
    multipliers 0) and the penalty problem's working set is again all held: the kernel says so instead of answering.
    At exactly full capacity (the only feasible point has every group at its upper bound) no working set with a free
    group solves the equality: not certified either; no changes allowed: not converged. The estimator then answers
    with PIQP, and the hot start resumes on the next ordinary frame."""
    rng = np.random.default_rng(3)
    m, g = 3, 8
    r = rng.uniform(0.01, 0.05, (m, g))  # every group pulls every coordinate the same way
    f_max = rng.uniform(200.0, 2000.0, g)
    lb, ub = np.zeros(g), np.ones(g)
    x, state = np.zeros(g), np.full(g, active_set.LOWER, dtype=np.int8)
    code, _, _, _ = active_set.solve_min_norm_eq(r, f_max, np.zeros(m), lb, ub, 1.0, x, state, 20)
    assert code == active_set.FACTORISATION_FAILED
    full = (r * f_max).sum(axis=1)
    for start in (active_set.FREE, active_set.UPPER):
        x, state = np.full(g, 0.5), np.full(g, start, dtype=np.int8)
        code, _, _, _ = active_set.solve_min_norm_eq(r, f_max, full, lb, ub, 1.0, x, state, 50)
        assert code == active_set.FACTORISATION_FAILED
    x, state = np.full(g, 0.5), np.full(g, active_set.FREE, dtype=np.int8)
    assert active_set.solve_min_norm_eq(r, f_max, full, lb, ub, 1.0, x, state, 0)[0] == active_set.NOT_CONVERGED
    # the estimator hands that frame to PIQP: a finite answer at (or flagged beside) full activation, never raised
    pack = SmoothPack(m, g)
    pack.r0, pack.r1, pack.f_max_ref = r, np.zeros_like(r), f_max
    est = FrameEstimator(pack, method="so")
    result = est.step(np.zeros(m), torques=full)
    assert result.solver == "piqp" and est.solver_counts == {"active_set": 0, "piqp": 1}
    assert result.status.value in ("solved", "reserve") and np.all(result.activations > 0.99)
    rest = est.step(np.zeros(m), torques=np.zeros(m))
    assert rest.solver == "piqp" and np.abs(rest.activations).max() < 1e-6
    half = est.step(np.zeros(m), torques=0.5 * full)
    assert half.solver == "active_set" and half.status.value == "solved"
    np.testing.assert_allclose(half.model_torques, 0.5 * full, rtol=1e-9)


def _kernel_std_is_laplace_std(result: FrameResult) -> bool:
    """The Laplace std the compiled kernel computed with a hot-started frame equals laplace_std of the frame's Hessian
    (1e-9 relative + 1e-7: a variance that rounding leaves at ~1e-16 instead of 0 has a std of ~1e-8); False when the kernel left it to be computed when read (its m x m system singular)."""
    if result._std is None:
        return False
    general = laplace_std(result.hessian, ~result.at_bound, result._equality)
    np.testing.assert_allclose(result._std, general, rtol=1e-9, atol=1e-7)
    return True


#: |a_hot - a_piqp| bound on every frame the hot start answers. PIQP (interior point, eps 1e-8) stops short of a bound
#: whose multiplier is ~0 by up to ~sqrt of its tolerance: measured max 1.8e-5 on deadlift_75kg, where the active set
#: sits exactly on the bound with an objective never above PIQP's; 98 % of the frames agree within 1e-6.
SO_AGREEMENT_ATOL = 5e-5


def test_so_hot_start_equals_piqp_every_frame_on_the_held_out_deadlift(repo_root):
    """The held-out deadlift (75 kg, measured torques), so hot-started beside so with PIQP every frame: the same
    status on every frame, the same activations within SO_AGREEMENT_ATOL (1e-6 on >= 95 % of the frames), a
    certified optimum (numpy KKT check) no worse than PIQP's; the frames beyond the muscles' capacity still RESERVE,
    answered by PIQP's fallback; a frame pushed to 3x the torque too, after which the hot start resumes."""
    from msk_core.estimate.trial import load_trial
    from msk_core.model import load_pack

    pack = load_pack("deadlift")
    trial = load_trial(repo_root / "recordings/demo/deadlift/deadlift_75kg/trial.toml", pack)
    hot, piqp_only = FrameEstimator(pack, method="so"), FrameEstimator(pack, method="so", hot_start=False)
    lb, ub = np.zeros(len(pack.groups)), np.ones(len(pack.groups))
    close, by_status, kernel_std = 0, {}, 0
    for i in range(trial.n_frames):
        args = (trial.q[i], trial.qd[i], trial.qdd[i])
        a = hot.step(*args, torques=trial.torques[i])
        b = piqp_only.step(*args, torques=trial.torques[i])
        assert a.status is b.status, f"frame {i}: {a.status.value} hot, {b.status.value} PIQP every frame"
        by_status[(a.status.value, a.solver)] = by_status.get((a.status.value, a.solver), 0) + 1
        err = np.abs(a.activations - b.activations).max()
        assert err <= SO_AGREEMENT_ATOL, f"frame {i}: |a_hot - a_piqp| = {err:.2e} ({a.solver})"
        close += err <= 1e-6
        if a.solver == "active_set":
            kernel_std += _kernel_std_is_laplace_std(a)
            at, tt = _scaled(np.asarray(pack.moment_arms(trial.q[i])), hot.f_max, trial.torques[i])
            np.testing.assert_allclose(a._hess_parts[0], at, rtol=1e-12, atol=1e-15)  # the kernel's A~
            assert _so_kkt_violation(at, tt, a.activations, lb, ub) < 1e-9, f"frame {i}"
            assert a.activations @ a.activations <= b.activations @ b.activations + 1e-12, f"frame {i}"
    n = trial.n_frames
    certified = by_status.get(("solved", "active_set"), 0)
    reserve = by_status.get(("reserve", "piqp"), 0)
    assert set(by_status) <= {("solved", "active_set"), ("solved", "piqp"), ("reserve", "piqp")}, by_status
    assert reserve > 0 and hot.flag_counts == piqp_only.flag_counts == {"reserve": reserve}
    # measured: every one of the 1366 feasible frames certified
    assert certified >= 0.99 * (n - reserve), f"{certified} of {n - reserve} feasible frames certified: {by_status}"
    assert close >= 0.95 * n, f"{close} of {n} frames within 1e-6"
    assert kernel_std >= 0.99 * certified, f"the kernel's std on {kernel_std} of {certified} certified frames"
    assert hot.solver_counts == {"active_set": certified, "piqp": n - certified}
    assert piqp_only.solver_counts == {"active_set": 0, "piqp": n}
    i = int(np.argmax(np.abs(trial.torques).sum(axis=1) > 0))  # a frame far beyond capacity, then a normal one
    beyond = hot.step(trial.q[i], trial.qd[i], trial.qdd[i], torques=3.0 * trial.torques[i] + 5e3)
    assert beyond.status.value == "reserve" and beyond.solver == "piqp"
    certified_before = hot.solver_counts["active_set"]
    for k in range(n - 20, n):
        hot.step(trial.q[k], trial.qd[k], trial.qdd[k], torques=trial.torques[k])
    assert hot.solver_counts["active_set"] >= certified_before + 15


def _general_std(at: np.ndarray, w: float, d: np.ndarray, equality: bool, x: np.ndarray) -> np.ndarray:
    free = (x > BOUND_TOL) & (x < 1.0 - BOUND_TOL)
    return laplace_std(w * at.T @ at + np.diag(d), free, at if equality else None)


def _kernel_std(at: np.ndarray, w: float, d: np.ndarray, equality: bool, x: np.ndarray) -> np.ndarray:
    std = np.empty(at.shape[1])
    active_set._laplace_std(at, w, d, equality, x, np.zeros(at.shape[1]), np.ones(at.shape[1]), std)
    return std


@pytest.mark.parametrize("equality", [False, True])
def test_kernel_std_equals_laplace_std_or_leaves_it_to_it(equality: bool) -> None:
    """The kernel's Laplace std against laplace_std (SVD null space, Cholesky) on random frames: equal where the m x m
    system is well conditioned; exactly 0 when the equality leaves no free direction (as many free groups as rows:
    the cancelling expression would say ~1e-4); NaN, i.e. computed the general way, for nearly parallel rows."""
    rng = np.random.default_rng(11)
    m, g = 3, 9
    d = 2.0 * np.ones(g) if equality else rng.uniform(0.5, 50.0, g)
    w = 0.0 if equality else 1e3
    for _ in range(200):
        at = rng.normal(size=(m, g))
        x = np.where(rng.random(g) < 0.3, 0.0, rng.uniform(0.05, 0.95, g))
        general, kernel = _general_std(at, w, d, equality, x), _kernel_std(at, w, d, equality, x)
        if np.isnan(kernel).all():
            assert equality and np.sum(x > 0) < m  # too few free groups for a full-rank A~_F
            continue
        np.testing.assert_allclose(kernel, general, rtol=1e-9, atol=1e-7)
    at = rng.normal(size=(m, g))
    exactly_m_free = np.r_[np.full(m, 0.5), np.zeros(g - m)]
    kernel = _kernel_std(at, w, d, equality, exactly_m_free)
    assert np.all(kernel[m:] == 0.0)
    if equality:
        assert np.all(kernel == 0.0) and np.all(_general_std(at, w, d, equality, exactly_m_free) == 0.0)
        nearly_parallel = np.vstack([at[0], at[0] + 1e-5 * rng.normal(size=g), at[2]])
        x = np.full(g, 0.5)
        kernel = _kernel_std(nearly_parallel, w, d, equality, x)
        assert np.isnan(kernel).all()  # the general way: the SVD finds the rank
    nothing_free = _kernel_std(at, w, d, equality, np.zeros(g))
    assert np.isnan(nothing_free).all() if equality else np.all(nothing_free == 0.0)
