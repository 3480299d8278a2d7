"""Calibration (the paper's first optimisation): per-group strength and per-frame activations over training trials.

Variables: strength factors k_g in [alpha, beta] (F_max,g = k_g F_ref,g; defaults [0.5, 2.5], the range of CEINMS'
calibrated strength coefficients) and activations a_tg in [a_min, 1] for every training frame t. Objective, each term
half a squared, normalised error so that J reads as a negative log-likelihood:

    J = 1/2 sum_t,n ((sum_g R_tng F_ref,g k_g a_tg - tau_tn) / (eps c_tn))^2            torque, eps = torque_tolerance
      + 1/2 w_prior sum_t,g ((a_tg - mu_g(phase_t)) / sigma_g(phase_t))^2                  N(mu, sigma^2) across reps
      + 1/2 w_emg   sum_t,g in EMG ((a_tg - e_g(t)) / emg_std)^2                            the trial's own EMG
      + 1/2 sum_g free ((k_g - 1) / strength_prior_std)^2                                 N(1, 0.3^2) strength prior

The strength prior (default s = 0.3, ``None`` = off) keeps the factors the data barely identify (groups that stay
near rest, nearly collinear force columns) at the reference; well-identified factors move freely (torque terms over
thousands of frames outweigh it).

with c_tn = sum_g |R_tng| F_ref,g the reference torque capacity of coordinate n (the same per-coordinate scaling as the
estimator, fixed so it does not depend on k). Groups without EMG have no EMG term, and by default
(``calibrate="emg"``) keep k = 1: nothing in the data identifies their strength separately from their activation.

The problem is smooth and bound-constrained (bilinear in k and a), so it is solved as such: L-BFGS-B on all variables
with the analytic gradient (:func:`calibrate`). :func:`calibrate_alternating` is an independent second method (block
coordinate descent: per-frame bounded QPs in a by PIQP, bounded least squares in k by scipy's ``lsq_linear``) used to
show both reach the same optimum. Convergence is reported (iterations, projected-gradient norm, objective terms).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
import piqp
from scipy.optimize import lsq_linear, minimize

from msk_core.errors import EstimationError


@dataclass
class CalibrationFrames:
    """Training data, all frames of all trials stacked. emg is NaN for groups/frames without EMG."""

    moment_arms: np.ndarray  # (T, n_c, G) metres
    torques: np.ndarray  # (T, n_c) N·m
    prior_mean: np.ndarray  # (T, G)
    prior_std: np.ndarray  # (T, G)
    emg: np.ndarray  # (T, G)

    def __post_init__(self) -> None:
        t, n_c, g = self.moment_arms.shape
        for name, arr, shape in (
            ("torques", self.torques, (t, n_c)),
            ("prior_mean", self.prior_mean, (t, g)),
            ("prior_std", self.prior_std, (t, g)),
            ("emg", self.emg, (t, g)),
        ):
            if arr.shape != shape:
                raise EstimationError(f"calibration {name} must be {shape}, got {arr.shape}")
        ok = np.all(np.isfinite(self.moment_arms), axis=(1, 2)) & np.all(np.isfinite(self.torques), axis=1)
        if not np.all(ok):
            raise EstimationError(f"{int((~ok).sum())} calibration frames have NaN moment arms or torques; drop them")


@dataclass
class CalibrationSettings:
    strength_bounds: tuple[float, float] = (0.5, 2.5)
    torque_tolerance: float = 0.01
    emg_std: float = 0.05
    # optional signal-dependent EMG noise: sigma_tg = sqrt(emg_std^2 + (emg_relative_std * e_tg)^2) (sEMG amplitude
    # noise grows with the amplitude); None: constant emg_std
    emg_relative_std: float | None = None
    prior_weight: float = 1.0
    emg_weight: float = 1.0
    strength_prior_std: float | None = 0.3  # N(1, s^2) on each free strength factor (None: off)
    calibrate: str = "emg"  # "emg": only groups with EMG; "all": every group
    a_min: float = 0.0
    max_iter: int = 20000
    gtol: float = 1e-7


@dataclass
class CalibrationResult:
    scale: np.ndarray
    f_max: np.ndarray
    activations: np.ndarray
    objective: float
    terms: dict[str, float]
    converged: bool
    iterations: int
    projected_gradient: float
    message: str
    method: str
    settings: CalibrationSettings = field(default_factory=CalibrationSettings)

    def report(self) -> dict:
        """JSON-ready convergence report (stored in the subject profile)."""
        return {
            "method": self.method,
            "converged": bool(self.converged),
            "iterations": int(self.iterations),
            "objective": float(self.objective),
            "terms": {k: float(v) for k, v in self.terms.items()},
            "projected_gradient_inf_norm": float(self.projected_gradient),
            "message": self.message,
            "settings": asdict(self.settings),
        }


class _Problem:
    """Objective pieces shared by both solvers."""

    def __init__(self, f_ref: np.ndarray, frames: CalibrationFrames, s: CalibrationSettings) -> None:
        self.m = frames.moment_arms * f_ref[None, None, :]  # (T, n_c, G)
        cap = np.maximum(np.abs(self.m).sum(axis=2), 1.0)  # (T, n_c)
        self.inv_s = 1.0 / (s.torque_tolerance * cap)
        self.tau = frames.torques
        self.mu = frames.prior_mean
        self.w_p = s.prior_weight / frames.prior_std**2
        has = np.isfinite(frames.emg)
        self.e = np.where(has, frames.emg, 0.0)
        var_e = s.emg_std**2 + (0.0 if s.emg_relative_std is None else (s.emg_relative_std * self.e) ** 2)
        self.w_e = np.where(has, s.emg_weight / var_e, 0.0)
        self.t, _, self.g = self.m.shape
        lo, hi = s.strength_bounds
        if not 0 < lo <= 1.0 <= hi:
            raise EstimationError(f"strength bounds must satisfy 0 < alpha <= 1 <= beta, got {s.strength_bounds}")
        free = np.ones(self.g, dtype=bool) if s.calibrate == "all" else np.any(has, axis=0)
        if s.calibrate not in ("all", "emg"):
            raise EstimationError(f"calibrate must be 'emg' or 'all', got {s.calibrate!r}")
        self.k_bounds = [(lo, hi) if f else (1.0, 1.0) for f in free]
        self.w_k = 0.0 if s.strength_prior_std is None else 1.0 / s.strength_prior_std**2
        self.a_min = s.a_min

    def terms(self, k: np.ndarray, a: np.ndarray) -> tuple[dict[str, float], np.ndarray]:
        rho = (np.einsum("tng,tg->tn", self.m, a * k) - self.tau) * self.inv_s
        terms = {
            "torque": 0.5 * float(np.sum(rho**2)),
            "prior": 0.5 * float(np.sum(self.w_p * (a - self.mu) ** 2)),
            "emg": 0.5 * float(np.sum(self.w_e * (a - self.e) ** 2)),
        }
        if self.w_k:
            terms["strength"] = 0.5 * self.w_k * float(np.sum((k - 1.0) ** 2))
        return terms, rho

    def value_grad(self, z: np.ndarray) -> tuple[float, np.ndarray]:
        k, a = z[: self.g], z[self.g :].reshape(self.t, self.g)
        terms, rho = self.terms(k, a)
        back = np.einsum("tn,tng->tg", rho * self.inv_s, self.m)  # d(torque)/d(a_tg k_g)
        grad_a = back * k + self.w_p * (a - self.mu) + self.w_e * (a - self.e)
        grad_k = np.sum(back * a, axis=0) + self.w_k * (k - 1.0)
        return sum(terms.values()), np.concatenate([grad_k, grad_a.ravel()])

    def bounds(self) -> list[tuple[float, float]]:
        return self.k_bounds + [(self.a_min, 1.0)] * (self.t * self.g)

    def projected_gradient(self, z: np.ndarray) -> float:
        _, grad = self.value_grad(z)
        b = np.array(self.bounds())
        pg = np.clip(z - grad, b[:, 0], b[:, 1]) - z
        return float(np.max(np.abs(pg)))

    def start(self) -> np.ndarray:
        a0 = np.clip(np.where(self.w_e > 0, self.e, self.mu), self.a_min, 1.0)
        return np.concatenate([np.ones(self.g), a0.ravel()])

    def result(self, z, method, converged, iterations, message, settings, f_ref) -> CalibrationResult:
        k, a = z[: self.g].copy(), z[self.g :].reshape(self.t, self.g).copy()
        terms, _ = self.terms(k, a)
        return CalibrationResult(
            scale=k,
            f_max=k * f_ref,
            activations=a,
            objective=sum(terms.values()),
            terms=terms,
            converged=converged,
            iterations=iterations,
            projected_gradient=self.projected_gradient(z),
            message=message,
            method=method,
            settings=settings,
        )


def calibrate(
    f_max_ref: np.ndarray, frames: CalibrationFrames, settings: CalibrationSettings | None = None
) -> CalibrationResult:
    """Joint bound-constrained solve (L-BFGS-B, analytic gradient) of the calibration problem."""
    s = settings or CalibrationSettings()
    f_ref = np.asarray(f_max_ref, dtype=float)
    prob = _Problem(f_ref, frames, s)
    res = minimize(
        prob.value_grad,
        prob.start(),
        jac=True,
        method="L-BFGS-B",
        bounds=prob.bounds(),
        options={"maxiter": s.max_iter, "maxfun": 2 * s.max_iter, "gtol": s.gtol, "ftol": 1e-15, "maxcor": 10},
    )
    return prob.result(res.x, "L-BFGS-B (joint)", bool(res.success), int(res.nit), str(res.message), s, f_ref)


def calibrate_alternating(
    f_max_ref: np.ndarray,
    frames: CalibrationFrames,
    settings: CalibrationSettings | None = None,
    *,
    max_sweeps: int = 2000,
    tol: float = 1e-12,
) -> CalibrationResult:
    """Independent check: exact block minimisation, a-step by PIQP per frame, k-step by bounded least squares."""
    s = settings or CalibrationSettings()
    f_ref = np.asarray(f_max_ref, dtype=float)
    prob = _Problem(f_ref, frames, s)
    z = prob.start()
    g = prob.g
    lo = np.array([b[0] for b in prob.k_bounds])
    hi = np.array([b[1] for b in prob.k_bounds])
    solver = piqp.DenseSolver()
    solver.settings.eps_abs = 1e-10
    solver.settings.eps_rel = 1e-10
    ready = False
    previous = np.inf
    sweeps = 0
    for sweeps in range(1, max_sweeps + 1):
        k = z[:g]
        a = z[g:].reshape(prob.t, g)
        for t in range(prob.t):
            at = prob.m[t] * k[None, :] * prob.inv_s[t][:, None]
            hess = at.T @ at + np.diag(prob.w_p[t] + prob.w_e[t])
            c = -(at.T @ (prob.tau[t] * prob.inv_s[t]) + prob.w_p[t] * prob.mu[t] + prob.w_e[t] * prob.e[t])
            if not ready:
                solver.setup(np.asfortranarray(hess), c, x_l=np.full(g, s.a_min), x_u=np.ones(g))
                ready = True
            else:
                solver.update(P=np.asfortranarray(hess), c=c)
            solver.solve()
            a[t] = np.clip(solver.result.x, s.a_min, 1.0)
        # k-step: torque residuals are linear in k -> stacked bounded least squares
        rows = (prob.m * a[:, None, :] * prob.inv_s[:, :, None]).reshape(-1, g)
        target = (prob.tau * prob.inv_s).ravel()
        fixed = lo == hi
        kk = np.where(fixed, lo, k)
        if np.any(~fixed):
            rhs = target - rows[:, fixed] @ lo[fixed]
            mat = rows[:, ~fixed]
            if prob.w_k:  # the strength prior as extra least-squares rows sqrt(w_k) (k - 1)
                n_free = int((~fixed).sum())
                mat = np.vstack([mat, np.sqrt(prob.w_k) * np.eye(n_free)])
                rhs = np.concatenate([rhs, np.full(n_free, np.sqrt(prob.w_k))])
            kk[~fixed] = lsq_linear(mat, rhs, bounds=(lo[~fixed], hi[~fixed]), tol=1e-14).x
        z = np.concatenate([kk, a.ravel()])
        value, _ = prob.value_grad(z)
        if previous - value <= tol * max(1.0, abs(value)):
            break
        previous = value
    pg = prob.projected_gradient(z)
    return prob.result(z, "alternating (PIQP + lsq_linear)", pg < 1e-4, sweeps, f"{sweeps} sweeps", s, f_ref)
