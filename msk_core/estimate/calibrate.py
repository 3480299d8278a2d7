"""Calibration (the paper's first optimisation): per-group strength and per-frame activations over training trials.

Variables: strength factors k_g in [alpha, beta] (F_max,g = k_g F_ref,g; defaults [0.5, 2.5], the range of CEINMS'
calibrated strength coefficients) and activations a_tg in [a_min, 1] for every training frame t. Objective, each term
half a squared, normalised error so that J reads as a negative log-likelihood:

    J = 1/2 sum_t,n ((sum_g R_tng F_ref,g k_g a_tg - tau_tn) / (eps c_tn))^2            torque, eps = torque_tolerance
      + 1/2 w_prior sum_t,g w_tg ((a_tg - mu_g(phase_t)) / sigma_g(phase_t))^2             N(mu, sigma^2) across reps
      + 1/2 w_emg   sum_t,g in EMG ((a_tg - e_g(t)) / sigma_e)^2                            the trial's own EMG
      + 1/2 sum_g free ((k_g - 1) / strength_prior_std)^2                                 N(1, 0.3^2) strength prior

Optionally (``CalibrationFrames.torque_basis`` Z, (T, n_c, p)) the torque term carries + sum_j Z_tnj beta_j: torque
the muscles' activations do not produce (a passive moment, joint damping; :mod:`msk_core.discrepancy`), its
coefficients beta_j >= ``torque_basis_lower`` fitted jointly with k and a. Without it a calibration takes such a
moment into the strengths (a passive extension moment raises the extensors' k and lowers the flexors').

with sigma_e = sqrt(emg_std^2 + (emg_relative_std e_g(t))^2) (amplitude-estimate noise grows with the amplitude); under
``IdentifyMode.SHRINK`` the strength prior is weighed by the residuals' autocorrelation time tau (the data terms
then count T/tau independent frames).

w_tg = 1 for groups without EMG, ``emg_group_prior_weight`` (default 0) where the group's own EMG is known: the
prior is built from that same EMG, so both terms would count it twice (and its phase-averaged mean biases k).

Identifiability: the Laplace (Gauss-Newton) covariance of k with the activations and the held factors marginalised,
the data's curvature divided by the residuals' integrated autocorrelation time (frames are not independent), gives
each group a data-only std; ``StrengthStatus`` says identified / combination / unidentified / at_bound /
not_calibrated, and ``IdentifyMode`` what is done with unidentified directions (report only by default).

The strength prior (default s = 0.3, ``None`` = off) keeps the factors the data barely identify (groups that stay
near rest, nearly collinear force columns) at the reference; well-identified factors move freely (torque terms over
thousands of frames outweigh it).

with c_tn = sum_g |R_tng| F_ref,g the reference torque capacity of coordinate n (the same per-coordinate scaling as the
estimator, fixed so it does not depend on k). Groups without EMG have no EMG term, and by default
(``calibrate="emg"``) keep k = 1: nothing in the data identifies their strength separately from their activation.

The problem is smooth and bound-constrained (bilinear in k and a), so it is solved as such (:func:`calibrate`): by
default ("reduced") L-BFGS-B on the free strength factors, every frame's activations the exact optimum of its QP at
those strengths (and the torque basis' coefficients, if any); or ("joint") L-BFGS-B on all variables with the
analytic gradient.
:func:`calibrate_alternating` is an independent second method (block
coordinate descent: per-frame bounded QPs in a by PIQP, bounded least squares in k by scipy's ``lsq_linear``) used to
show both reach the same optimum. Convergence is reported (iterations, projected-gradient norm, objective terms).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from enum import Enum
from typing import Any

import numba
import numpy as np
import piqp
from scipy.optimize import Bounds, lsq_linear, minimize

from msk_core.errors import EstimationError
from msk_core.estimate.active_set import CERTIFIED, seed_state, solve_box_lsq


class IdentifyMode(str, Enum):
    """What the calibration does with strength directions the data do not determine."""

    SHRINK = "shrink"  # strength prior weighed by the residuals' autocorrelation time: MAP shrinks them to 1
    TRUNCATE = "truncate"  # directions with relative std > identify_max_std set to the reference, a re-solved
    REPORT = "report"  # plain MAP of the objective as written; identifiability only reported


COMBINATION_MIN_SHARE = 0.25  # a group with at least this share in identified directions is part of a known combination


class StrengthStatus(str, Enum):
    """What the calibration could say about a group's strength factor."""

    IDENTIFIED = "identified"  # free, data-only relative Laplace std <= identify_max_std, inside the bounds
    COMBINATION = "combination"  # alone unidentified, but >= COMBINATION_MIN_SHARE of it lies in identified
    # combinations (a left/right pair: their common factor is known, the split is not; each has share 1/2)
    UNIDENTIFIED = "unidentified"  # data-only std above the threshold, outside identified combinations: ~reference
    AT_BOUND = "at_bound"  # the data push it to alpha or beta: the model cannot fit them inside the range
    NOT_CALIBRATED = "not_calibrated"  # no EMG (calibrate="emg"): fixed at the reference by design


@dataclass
class CalibrationFrames:
    """Training data, all frames of all trials stacked. emg is NaN for groups/frames without EMG."""

    moment_arms: np.ndarray  # (T, n_c, G) metres
    torques: np.ndarray  # (T, n_c) N·m
    prior_mean: np.ndarray  # (T, G)
    prior_std: np.ndarray  # (T, G)
    emg: np.ndarray  # (T, G)
    # torque not produced by the activations, known up to linear coefficients fitted with k and a (None: none)
    torque_basis: np.ndarray | None = None  # (T, n_c, p) N·m per unit coefficient
    torque_basis_lower: np.ndarray | None = None  # (p,) lower bounds of the coefficients (None: free)
    torque_basis_names: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        t, n_c, g = self.moment_arms.shape
        if self.torque_basis is not None:
            z = self.torque_basis
            if z.ndim != 3 or z.shape[:2] != (t, n_c):
                raise EstimationError(f"calibration torque_basis must be ({t}, {n_c}, p), got {z.shape}")
            if not np.all(np.isfinite(z)):
                raise EstimationError("calibration torque_basis has non-finite values")
            if self.torque_basis_lower is not None and np.shape(self.torque_basis_lower) != (z.shape[2],):
                raise EstimationError(
                    f"calibration torque_basis_lower must be ({z.shape[2]},), got {np.shape(self.torque_basis_lower)}"
                )
            if self.torque_basis_names and len(self.torque_basis_names) != z.shape[2]:
                raise EstimationError(
                    f"calibration torque_basis_names: {len(self.torque_basis_names)} names for {z.shape[2]} columns"
                )
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
    # signal-dependent EMG noise: sigma_tg = sqrt(emg_std^2 + (emg_relative_std * e_tg)^2) (an sEMG amplitude
    # estimate's error grows with the amplitude; docs/estimation.md); None: constant emg_std
    emg_relative_std: float | None = 0.1
    prior_weight: float = 1.0
    # weight of the across-rep prior on a group in the frames where that group's own EMG is known. The prior is built
    # from the same EMG (phase-binned across reps), so with the EMG term it counts that evidence twice, and its
    # smoothed mean fights the frame's EMG: with the true activations as EMG the strength is then recovered with a
    # 25 % (bench) / 12 % (deadlift) median error instead of 0 (docs/estimation.md). 0 = the EMG decides.
    emg_group_prior_weight: float = 0.0
    emg_weight: float = 1.0
    strength_prior_std: float | None = 0.3  # N(1, s^2) on each free strength factor (None: off)
    calibrate: str = "emg"  # "emg": only groups with EMG; "all": every group
    # identifiability: a strength direction (eigenvector of the data-only Laplace covariance of log k, activations
    # and held factors marginalised) whose relative std exceeds this is unidentified and held at the reference;
    # a group is "identified" when its own relative std is within it. 0.15 = half the strength prior's std (the data
    # then carry >= 4/5 of the precision). None: keep every factor free, report only
    identify_max_std: float | None = 0.15
    identify: IdentifyMode | str = IdentifyMode.REPORT  # what happens to unidentified directions (docs/estimation.md)

    def __post_init__(self) -> None:
        self.identify = IdentifyMode(self.identify)
        if self.solver not in ("joint", "reduced"):
            raise EstimationError(f"calibration solver must be 'joint' or 'reduced', got {self.solver!r}")

    a_min: float = 0.0
    max_iter: int = 20000
    gtol: float = 1e-7
    precondition: bool = True  # Jacobi-scaled variables in the joint solve (False: as written; msk bench calibrate)
    # "joint": L-BFGS-B on (k, a, beta) together; "reduced": L-BFGS-B on the free strengths only, every frame's
    # activations the exact optimum of its box QP at those strengths (compiled active set, warm from the last
    # evaluation), the gradient in k by the envelope theorem (:func:`calibrate`; same optimum, ~15x less CPU on the
    # walk; the default since 28 Nov; with a torque basis its coefficients are variables beside the strengths)
    solver: str = "reduced"
    # "reduced": activations that no term but the torque pins down (groups without EMG between reps) get this tiny
    # pull to 0 (the joint solve's start), so that each frame's QP has one optimum
    reduced_ridge: float = 1e-3
    ftol: float = 1e-15  # L-BFGS-B stops when an iteration lowers the objective by less than ftol (relative)


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
    # per group: Laplace std of k from the curvature of J (activations marginalised), with the strength prior and
    # from the data alone (NaN: not a calibrated factor), and the group's status (see StrengthStatus; empty until the
    # identifiability pass, which every calibration ends with)
    strength_std: np.ndarray | None = None
    strength_std_data: np.ndarray | None = None
    #: the data-only std relative to the factor found before any truncation: what the status is judged on
    strength_rel_std_data: np.ndarray | None = None
    status: list[str] = field(default_factory=list)
    identified_share: np.ndarray | None = None  # diag of the projector on the identified directions
    torque_coefficients: np.ndarray | None = None  # (p,) the torque basis' fitted coefficients (None: no basis)
    torque_basis_names: tuple[str, ...] = ()  # their names (CalibrationFrames.torque_basis_names; may be empty)

    @property
    def identified(self) -> np.ndarray:
        """Groups whose strength the data determined (free, data std within the threshold, not at a bound)."""
        return np.array([s == StrengthStatus.IDENTIFIED.value for s in self.status], dtype=bool)

    def identifiability(self, groups: list[str] | tuple[str, ...]) -> dict[str, dict]:
        """Per group: scale, Laplace std (posterior and data only) and status, JSON-ready."""
        out = {}
        for j, g in enumerate(groups):
            std = None if self.strength_std is None else self.strength_std[j]
            std_d = None if self.strength_std_data is None else self.strength_std_data[j]
            rel_d = None if self.strength_rel_std_data is None else self.strength_rel_std_data[j]
            out[g] = {
                "scale": float(self.scale[j]),
                "std": None if std is None or not np.isfinite(std) else float(std),
                "std_data": None if std_d is None or not np.isfinite(std_d) else float(std_d),
                "rel_std_data": None if rel_d is None or not np.isfinite(rel_d) else float(rel_d),
                "status": self.status[j] if self.status else None,
                "identified_share": None
                if self.identified_share is None or not np.isfinite(self.identified_share[j])
                else float(self.identified_share[j]),
            }
        return out

    def report(self, groups: list[str] | tuple[str, ...] | None = None) -> dict:
        """JSON-ready convergence report (stored in the subject profile); with ``groups`` also the per-group
        identifiability (``strength``)."""
        extra = {} if groups is None or not self.status else {"strength": self.identifiability(groups)}
        return {**self._convergence(), **extra}

    def _convergence(self) -> dict:
        out: dict[str, object] = {
            "method": self.method,
            "converged": bool(self.converged),
            "iterations": int(self.iterations),
            "objective": float(self.objective),
            "terms": {k: float(v) for k, v in self.terms.items()},
            "projected_gradient_inf_norm": float(self.projected_gradient),
            "message": self.message,
            "settings": asdict(self.settings),
        }
        if self.torque_coefficients is not None:
            coefficients = [float(x) for x in self.torque_coefficients]
            out["torque_coefficients"] = coefficients
            if self.torque_basis_names:  # by name as well, for whoever reads the report
                out["torque_basis"] = dict(zip(self.torque_basis_names, coefficients))
        return out


def integrated_autocorrelation(x: np.ndarray, *, cutoff: float = 0.05) -> float:
    """1 + 2 sum_L rho(L), summed until the autocorrelation first drops below ``cutoff`` (>= 1)."""
    x = np.asarray(x, dtype=float) - np.mean(x)
    var = float(np.dot(x, x))
    if var <= 0.0 or x.size < 3:
        return 1.0
    spectrum = np.fft.rfft(x, 2 * x.size)
    acf = np.fft.irfft(spectrum * np.conj(spectrum))[: x.size] / var
    below = np.flatnonzero(acf[1:] < cutoff)
    stop = int(below[0]) + 1 if below.size else x.size
    return max(1.0, 1.0 + 2.0 * float(np.sum(acf[1:stop])))


class _Problem:
    """Objective pieces shared by both solvers."""

    def __init__(self, f_ref: np.ndarray, frames: CalibrationFrames, s: CalibrationSettings) -> None:
        self.m = frames.moment_arms * f_ref[None, None, :]  # (T, n_c, G)
        cap = np.maximum(np.abs(self.m).sum(axis=2), 1.0)  # (T, n_c)
        self.inv_s = 1.0 / (s.torque_tolerance * cap)
        self.tau = frames.torques
        self.mu = frames.prior_mean
        has = np.isfinite(frames.emg)
        self.w_p = np.where(has, s.emg_group_prior_weight, 1.0) * s.prior_weight / frames.prior_std**2
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
        self.free = free.copy()  # calibrated factors (others fixed at the reference)
        self.k_bounds = [(lo, hi) if f else (1.0, 1.0) for f in free]
        self.w_k = 0.0 if s.strength_prior_std is None else 1.0 / s.strength_prior_std**2
        self.w_k_obj = self.w_k  # the strength prior's weight in the objective (x tau_int in IdentifyMode.SHRINK)
        self.a_min = s.a_min
        # the torque basis' coefficients beta, the last p variables: z = (k, a, beta)
        self.basis = (
            np.zeros((self.t, self.m.shape[1], 0))
            if frames.torque_basis is None
            else np.asarray(frames.torque_basis, dtype=float)
        )
        self.p = self.basis.shape[2]
        self.basis_names = tuple(frames.torque_basis_names or ())
        lower = frames.torque_basis_lower
        self.beta_lower = np.full(self.p, -np.inf) if lower is None else np.asarray(lower, dtype=float)

    def split(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(k, a, beta) of a variable vector."""
        n = self.g + self.t * self.g
        return z[: self.g], z[self.g : n].reshape(self.t, self.g), z[n:]

    def offset(self, beta: np.ndarray) -> np.ndarray | float:
        """(T, n) torque of the basis at coefficients ``beta``; 0.0 without a basis."""
        return np.einsum("tnp,p->tn", self.basis, beta) if self.p else 0.0

    def terms(self, k: np.ndarray, a: np.ndarray, beta: np.ndarray) -> tuple[dict[str, float], np.ndarray]:
        rho = (np.einsum("tng,tg->tn", self.m, a * k) + self.offset(beta) - self.tau) * self.inv_s
        terms = {
            "torque": 0.5 * float(np.sum(rho**2)),
            "prior": 0.5 * float(np.sum(self.w_p * (a - self.mu) ** 2)),
            "emg": 0.5 * float(np.sum(self.w_e * (a - self.e) ** 2)),
        }
        if self.w_k:
            terms["strength"] = 0.5 * self.w_k_obj * float(np.sum((k - 1.0) ** 2))
        return terms, rho

    def value_grad(self, z: np.ndarray) -> tuple[float, np.ndarray]:
        """J and its gradient in all variables (k, a, beta)."""
        k, a, beta = self.split(z)
        terms, rho = self.terms(k, a, beta)
        back = np.einsum("tn,tng->tg", rho * self.inv_s, self.m)  # d(torque)/d(a_tg k_g)
        grad_a = back * k + self.w_p * (a - self.mu) + self.w_e * (a - self.e)
        grad_k = np.sum(back * a, axis=0) + self.w_k_obj * (k - 1.0)
        grad_beta = np.einsum("tn,tnp->p", rho * self.inv_s, self.basis)
        return sum(terms.values()), np.concatenate([grad_k, grad_a.ravel(), grad_beta])

    def diagonal_curvature(self, z: np.ndarray) -> np.ndarray:
        """Diagonal of the Gauss-Newton Hessian of J at z (the Jacobi preconditioner of the joint solve)."""
        k, a, _ = self.split(z)
        b2 = (self.m * self.inv_s[:, :, None]) ** 2  # (T, n_c, G)
        col = b2.sum(axis=1)  # (T, G): sum_n (m_tng / s_tn)^2
        h_a = col * k**2 + self.w_p + self.w_e
        h_k = np.sum(col * a**2, axis=0) + self.w_k_obj
        h_beta = np.einsum("tnp,tn->p", self.basis**2, self.inv_s**2)
        return np.concatenate([h_k, h_a.ravel(), h_beta])

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) of every variable (k, a, beta)."""
        k_lo, k_hi = np.array(self.k_bounds, dtype=float).reshape(self.g, 2).T
        n_a = self.t * self.g
        return (
            np.concatenate([k_lo, np.full(n_a, self.a_min), self.beta_lower]),
            np.concatenate([k_hi, np.ones(n_a), np.full(self.p, np.inf)]),
        )

    def strength_std(self, z: np.ndarray, *, with_prior: bool, return_cov: bool = False):
        """Laplace std of each free k: the inverse of the Gauss-Newton curvature of J in k after marginalising the
        activations (Schur complement of the per-frame activation blocks; activations at a bound are held, as in
        the estimator's Laplace std) and the torque basis' coefficients (those at their lower bound held). NaN for
        factors that are not free; inf when the data carry no information."""
        k, a, beta = self.split(z)
        free_k = np.array([lo < hi for lo, hi in self.k_bounds])
        out = np.full(self.g, np.nan)
        if not np.any(free_k):
            return (out, np.zeros((0, 0))) if return_cov else out
        b = self.m * self.inv_s[:, :, None]  # (T, n_c, G): torque residual rows
        btb = np.einsum("tng,tnh->tgh", b, b)
        h_kk = np.einsum("tg,tgh,th->gh", a, btb, a)
        h_ka = a[:, :, None] * btb * k[None, None, :]  # (T, G_k, G_a)
        h_aa = k[None, :, None] * btb * k[None, None, :]
        diag = self.w_p + self.w_e
        h_aa[:, np.arange(self.g), np.arange(self.g)] += diag
        held = (a <= self.a_min + 1e-9) | (a >= 1.0 - 1e-9)  # activations at a bound carry no curvature
        h_ka = np.where(held[:, None, :], 0.0, h_ka)
        h_aa = np.where(held[:, :, None] | held[:, None, :], 0.0, h_aa)
        eye = np.eye(self.g)[None]
        # tiny ridge: an activation that only the torque sees, collinear with another, has a flat direction
        h_aa = h_aa + eye * np.where(held[:, :, None], 1.0, 1e-9 * (1.0 + np.abs(h_aa).max(axis=(1, 2)))[:, None, None])
        schur = h_kk - np.einsum("tga,tab->gb", h_ka, np.linalg.solve(h_aa, h_ka.transpose(0, 2, 1)))
        free_beta = beta > self.beta_lower + 1e-9 * (1.0 + np.abs(beta))  # at the bound: held, like activations
        if np.any(free_beta):
            # the coefficients couple every frame: the Schur complement over the activations of the (k, beta) block,
            # then beta marginalised (a strength confounded with a passive moment is not known better than that)
            zb = self.basis[:, :, free_beta] * self.inv_s[:, :, None]  # (T, n_c, p_free)
            btz = np.einsum("tng,tnp->tgp", b, zb)
            h_kb = np.einsum("tg,tgp->gp", a, btz)
            h_ab = np.where(held[:, :, None], 0.0, k[None, :, None] * btz)  # (T, G_a, p)
            h_bb = np.einsum("tnp,tnq->pq", zb, zb)
            solved = np.linalg.solve(h_aa, h_ab)  # (T, G_a, p)
            s_kb = h_kb - np.einsum("tga,tap->gp", h_ka, solved)
            s_bb = h_bb - np.einsum("tap,taq->pq", h_ab, solved)
            s_bb = 0.5 * (s_bb + s_bb.T) + np.eye(s_bb.shape[0]) * 1e-12 * max(float(np.abs(s_bb).max()), 1e-300)
            schur = schur - s_kb @ np.linalg.solve(s_bb, s_kb.T)
        # the factors held at the reference are not known either: with a strength prior they are nuisance
        # variables N(1, s^2) and marginalised too, so a free factor confounded with one of them is not credited
        # with information it does not have; the free factors' own prior only enters the posterior std
        nuisance = ~free_k & (self.w_k > 0)
        keep = free_k | nuisance
        prec = np.where(nuisance | (free_k & with_prior), self.w_k, 0.0)
        # the curvature counts every frame as independent evidence; the residuals are correlated over ~0.1 s
        # (6 Hz envelopes, smooth activations), so the data carry the information of T / tau_int frames
        s_ff = schur[np.ix_(keep, keep)] / self.correlation_frames(z) + np.diag(prec[keep])
        s_ff = 0.5 * (s_ff + s_ff.T)
        evals, evecs = np.linalg.eigh(s_ff)
        floor = 1e-12 * max(float(evals.max()), 1e-300)  # a flat direction reads as a huge (not NaN) std
        cov = (evecs / np.maximum(evals, floor)) @ evecs.T
        sub = free_k[keep]
        out[free_k] = np.sqrt(np.diag(cov)[sub])
        return (out, cov[np.ix_(sub, sub)]) if return_cov else out

    def correlation_frames(self, z: np.ndarray) -> float:
        """Integrated autocorrelation time (frames) of the fitted residuals: median over the EMG residual series
        a_g - e_g of each group with EMG and the torque residual of each coordinate (>= 1)."""
        k, a, beta = self.split(z)
        _, rho = self.terms(k, a, beta)
        series = [rho[:, n] for n in range(rho.shape[1])]
        series += [(a - self.e)[:, j] for j in range(self.g) if np.all(self.w_e[:, j] > 0)]
        return max(1.0, float(np.median([integrated_autocorrelation(x) for x in series])))

    def projected_gradient(self, z: np.ndarray, *, strengths_only: bool = False) -> float:
        """Infinity norm of the projected gradient of J at z; ``strengths_only``: over the strength factors (and the
        torque basis' coefficients) alone, as the "reduced" solve sees them: its activations are each frame's exact
        optimum, with its ridge, so J's gradient in them is that ridge's pull, not a distance from the optimum."""
        _, grad = self.value_grad(z)
        lower, upper = self.bounds()
        pg = np.clip(z - grad, lower, upper) - z
        if strengths_only:
            pg = np.concatenate([pg[: self.g], pg[self.g + self.t * self.g :]])
        return float(np.max(np.abs(pg))) if pg.size else 0.0

    def start(self) -> np.ndarray:
        a0 = np.clip(np.where(self.w_e > 0, self.e, self.mu), self.a_min, 1.0)
        return np.concatenate([np.ones(self.g), a0.ravel(), np.clip(np.zeros(self.p), self.beta_lower, None)])

    def result(self, z, method, converged, iterations, message, settings, f_ref) -> CalibrationResult:
        k, a, beta = self.split(z)
        k, a = k.copy(), a.copy()
        terms, _ = self.terms(k, a, beta)
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
            torque_coefficients=beta.copy() if self.p else None,
            torque_basis_names=self.basis_names if self.p else (),
        )


def calibrate(
    f_max_ref: np.ndarray,
    frames: CalibrationFrames,
    settings: CalibrationSettings | None = None,
    *,
    start: CalibrationResult | None = None,
) -> CalibrationResult:
    """Bound-constrained solve of the calibration problem (``settings.solver``: "reduced" by default, or "joint"),
    with the identifiability pass (unidentified factors held at the reference, then
    re-solved). A reduced solve that does not converge (a frame's QP not certified, L-BFGS-B stopped away from a
    stationary point) is continued by the joint solve from where it ended, and its message says so. ``start``: a
    calibration of the same frames to start from (its strengths and activations; the torque basis' coefficients
    from 0), which a re-calibration with a torque basis reaches in fewer iterations."""
    s = settings or CalibrationSettings()
    f_ref = np.asarray(f_max_ref, dtype=float)
    prob = _Problem(f_ref, frames, s)

    def solve(z0: np.ndarray) -> tuple[np.ndarray, bool, int, str]:
        # Jacobi preconditioning (z = d y, d = curvature^-1/2 at the start): one strength factor collects the
        # curvature of thousands of frames, one activation that of one frame; unscaled, L-BFGS-B spends most of its
        # iterations on that spread (bench press demo with its isometric trials: 2203 -> 170 iterations, same optimum)
        d = _jacobi_scale(prob.diagonal_curvature(z0)) if s.precondition else np.ones_like(z0)
        lower, upper = prob.bounds()
        options = {"maxiter": s.max_iter, "maxfun": 2 * s.max_iter, "gtol": s.gtol, "ftol": s.ftol, "maxcor": 10}
        z, res = _scaled_lbfgsb(prob.value_grad, z0, lower, upper, d, options)
        return z, bool(res.success), int(res.nit), str(res.message)

    if s.solver == "reduced":
        reduced = _ReducedSolve(prob, s)
        result = _solve_identified(
            prob, s, f_ref, reduced.solve, "L-BFGS-B (strengths, exact activations)", start=start
        )
        z = np.concatenate([result.scale, result.activations.ravel(), _coefficients(result)])
        result.projected_gradient = prob.projected_gradient(z, strengths_only=True)
        if result.converged:
            return result
        joint = calibrate(f_ref, frames, replace(s, solver="joint"), start=result)
        joint.message = (
            f"the reduced solve did not converge ({result.message}); joint solve from its end: {joint.message}"
        )
        joint.iterations += result.iterations
        joint.settings = s  # what the caller asked for (a re-calibration of the profile starts reduced again)
        return joint
    return _solve_identified(prob, s, f_ref, solve, "L-BFGS-B (joint)", start=start)


def _jit(fn):  # type: ignore[no-untyped-def]
    try:
        return numba.njit(cache=True)(fn)
    except RuntimeError:  # no writable cache location: compile in memory at first call
        return numba.njit(fn)


@_jit
def _frames_box_lsq(r, k, tau, w, mean, prec, lb, ub, scale, x, state, max_iter):  # type: ignore[no-untyped-def]
    """Every frame's activation QP at strengths k (:func:`msk_core.estimate.active_set.solve_box_lsq`, warm from x and
    state, both (T, G), updated in place); returns each frame's result code."""
    codes = np.empty(r.shape[0], dtype=np.int64)
    for t in range(r.shape[0]):
        code, _, _, _ = solve_box_lsq(
            r[t], k, tau[t], w, mean, prec, t, t, 0.0, lb, ub, scale, x[t], state[t], max_iter, False
        )
        codes[t] = code
    return codes


class _ReducedSolve:
    """The calibration as a problem in the free strength factors (and the torque basis' coefficients beta) alone:
    J(k, beta) = min_a J(k, a, beta) (+ the strength prior). At fixed (k, beta) the frames decouple into
    box-constrained least squares in their activations,

        1/2 |diag(inv_s) (m diag(k) a + Z beta - tau)|^2 + 1/2 sum_g d_g (a_g - nu_g)^2,   d = w_p + w_e,
        nu = (w_p mu + w_e e) / d,   a_min <= a <= 1,

    strictly convex (d > 0: activations only the torque sees get ``reduced_ridge``), solved exactly and certified by
    the compiled active-set kernel, each from its last working set. By the envelope theorem dJ/dk and dJ/dbeta are
    the partial derivatives at the optimal activations, so L-BFGS-B on <= G + p variables sees the exact value and
    gradient of what it minimises (J plus the ridge's pull). The
    kernel scales each torque row by c_n = max(sum_g |A_ng|, min_scale); a min_scale above every row sum (the rows
    are divided by eps c_tn beforehand, so sum_g |A_ng| <= max k / eps) makes c constant, and w = min_scale^2
    restores the calibration's weighting."""

    def __init__(self, prob: _Problem, s: CalibrationSettings) -> None:
        self.prob = prob
        self.rows = np.ascontiguousarray(prob.m * prob.inv_s[:, :, None])  # (T, n_c, G): m / (eps c)
        self.target = np.ascontiguousarray(prob.tau * prob.inv_s)
        d = prob.w_p + prob.w_e
        self.mean = np.ascontiguousarray(
            np.where(d > 0, (prob.w_p * prob.mu + prob.w_e * prob.e) / np.where(d > 0, d, 1.0), 0.0)
        )
        self.prec = np.ascontiguousarray(np.where(d > 0, d, 0.0) + s.reduced_ridge)
        self.ridge = s.reduced_ridge
        self.ftol = s.ftol
        self.lb = np.full(prob.g, prob.a_min)
        self.ub = np.ones(prob.g)
        self.scale = 1.01 * max(s.strength_bounds[1], 1.0) / s.torque_tolerance
        self.x = np.zeros((prob.t, prob.g))
        self.state = np.zeros((prob.t, prob.g), dtype=np.int8)
        self.failed = 0
        self.max_iter = s.max_iter

    def activations(self, k: np.ndarray, beta: np.ndarray) -> np.ndarray:
        """The frames' optimal activations at strengths k and basis coefficients beta (warm from the last call; a
        frame whose active set does not certify within its budget starts again from everything free, with a larger
        budget)."""
        prob = self.prob
        target = np.ascontiguousarray((prob.tau - prob.offset(beta)) * prob.inv_s) if prob.p else self.target
        args = (self.rows, k, target, self.scale**2, self.mean, self.prec, self.lb, self.ub, self.scale)
        codes = _frames_box_lsq(*args, self.x, self.state, 4 * self.prob.g)
        bad = np.flatnonzero(codes != CERTIFIED)
        if bad.size:
            x, state = self.x[bad].copy(), np.zeros((bad.size, self.prob.g), dtype=np.int8)
            x[:] = np.clip(self.mean[bad], self.lb, self.ub)
            sub = (self.rows[bad], k, target[bad], self.scale**2, self.mean[bad], self.prec[bad])
            again = _frames_box_lsq(*sub, self.lb, self.ub, self.scale, x, state, 40 * self.prob.g)
            self.x[bad], self.state[bad] = x, state
            self.failed += int(np.sum(again != CERTIFIED))
        return self.x

    def solve(self, z0: np.ndarray) -> tuple[np.ndarray, bool, int, str]:
        prob = self.prob
        k0, a0, beta0 = prob.split(z0)
        self.x[:] = np.clip(a0, self.lb, self.ub)
        for t in range(prob.t):
            seed_state(self.x[t], self.lb, self.ub, 1e-12, self.state[t])
        lo, hi = np.array(prob.k_bounds, dtype=float).T
        free = lo < hi
        n_free = int(free.sum())
        k, beta = np.clip(k0, lo, hi), np.maximum(beta0, prob.beta_lower)
        # the variables: the free strengths, then the torque basis' coefficients (none without a basis)
        lower = np.concatenate([lo[free], prob.beta_lower])
        upper = np.concatenate([hi[free], np.full(prob.p, np.inf)])
        self.failed = 0

        def value_grad(v: np.ndarray) -> tuple[float, np.ndarray]:
            k[free], beta[:] = v[:n_free], v[n_free:]
            a = self.activations(k, beta)
            terms, rho = prob.terms(k, a, beta)
            back = np.einsum("tn,tng->tg", rho * prob.inv_s, prob.m)
            grad_k = np.sum(back * a, axis=0) + prob.w_k_obj * (k - 1.0)
            grad_beta = np.einsum("tn,tnp->p", rho * prob.inv_s, prob.basis)
            # the value of what is minimised, min_a (J + the ridge's pull), whose gradient in (k, beta) this is
            pull = 0.5 * self.ridge * float(np.sum((a - self.mean) ** 2))
            return sum(terms.values()) + pull, np.concatenate([grad_k[free], grad_beta])

        def curvature() -> np.ndarray:  # the Gauss-Newton curvature of each variable, at the current point
            c = prob.diagonal_curvature(np.concatenate([k, self.x.ravel(), beta]))
            return np.concatenate([c[: prob.g][free], c[prob.g * (1 + prob.t) :]])

        if lower.size == 0:
            value_grad(lower)
            z = np.concatenate([k, self.x.ravel(), beta])
            return z, self.failed == 0, 0, "no free strength: activations solved at the held ones"
        # with a basis, Jacobi-scaled variables (as the joint solve's): a coefficient's curvature is the whole torque
        # term's, a strength's that of its group, and unscaled L-BFGS-B ran out of evaluations between them
        d = _jacobi_scale(curvature()) if prob.p else np.ones(lower.size)
        # gtol on the unscaled variables (the joint solve's gtol is for its preconditioned ones)
        options = {"maxiter": self.max_iter, "gtol": 1e-10, "ftol": self.ftol, "maxcor": 10}
        x, res = _scaled_lbfgsb(value_grad, np.concatenate([k[free], beta]), lower, upper, d, options)
        _, grad = value_grad(x)  # the activations at the returned strengths
        # L-BFGS-B may end its line search at the precision of J (ABNORMAL) at a stationary point: converged when
        # the step the projected gradient implies (over the Gauss-Newton curvature of each variable) is below 1e-6
        pg = np.clip(x - grad, lower, upper) - x
        step = np.abs(pg) / curvature()
        converged = self.failed == 0 and (bool(res.success) or float(np.max(step)) < 1e-6)
        message = str(res.message) + (f"; {self.failed} frame QPs not certified" if self.failed else "")
        return np.concatenate([k, self.x.ravel(), beta]), converged, int(res.nit), message


def _jacobi_scale(curvature: np.ndarray) -> np.ndarray:
    """The variables' Jacobi scales d = curvature^-1/2 (the solves run on y = z / d)."""
    return 1.0 / np.sqrt(np.maximum(curvature, 1e-12))


def _scaled_lbfgsb(value_grad, x0: np.ndarray, lower: np.ndarray, upper: np.ndarray, d: np.ndarray, options: Any):
    """L-BFGS-B on ``value_grad`` (value and gradient of x) in the scaled variables y = x / d, within [lower,
    upper]; returns (x at the end, clipped to the bounds; scipy's result)."""

    def scaled(y: np.ndarray) -> tuple[float, np.ndarray]:
        value, grad = value_grad(d * y)
        return value, grad * d

    res = minimize(scaled, x0 / d, jac=True, method="L-BFGS-B", bounds=Bounds(lower / d, upper / d), options=options)
    return np.clip(res.x * d, lower, upper), res


def _coefficients(result: CalibrationResult) -> np.ndarray:
    """The torque basis' fitted coefficients of ``result`` (none without a basis)."""
    return result.torque_coefficients if result.torque_coefficients is not None else np.zeros(0)


def _start_vector(prob: _Problem, start: CalibrationResult | None) -> np.ndarray:
    """The solve's start: the problem's own, or the strengths and activations of ``start`` (same frames)."""
    z0 = prob.start()
    if start is not None:
        if start.activations.shape != (prob.t, prob.g):
            raise EstimationError(
                f"calibration start: activations {start.activations.shape} for {(prob.t, prob.g)} frames x groups"
            )
        lo, hi = np.array(prob.k_bounds).T
        z0[: prob.g] = np.clip(start.scale, lo, hi)
        z0[prob.g : prob.g * (1 + prob.t)] = np.clip(start.activations, prob.a_min, 1.0).ravel()
    return z0


def _solve_identified(
    prob: _Problem,
    s: CalibrationSettings,
    f_ref: np.ndarray,
    solve,
    method: str,
    *,
    start: CalibrationResult | None = None,
) -> CalibrationResult:
    """Solve with every factor free, then per ``s.identify``: REPORT keeps that optimum; SHRINK re-solves with the
    strength prior weighed by the residuals' autocorrelation time; TRUNCATE sets the eigen-directions of the
    data-only covariance of log k whose std exceeds ``identify_max_std`` back to the reference (log k = P log k_hat,
    P the projector on the identified directions) and re-solves the activations with k held there. Then the
    per-group stds and statuses: a group alone unidentified is a ``combination`` when a large enough share of it lies
    in identified directions (left/right pairs, muscles with the same moment arms: only their common factor is
    known)."""
    z, converged, iterations, message = solve(_start_vector(prob, start))
    tau = prob.correlation_frames(z)
    if s.identify is IdentifyMode.SHRINK and prob.w_k and tau > 1.0:
        # the data terms count T frames, but carry the information of T / tau_int: weigh the strength prior up by
        # tau_int so that the MAP shrinks what the data cannot determine towards the reference, and re-solve
        prob.w_k_obj = prob.w_k * tau
        z, again, more, message = solve(z)
        converged, iterations = converged and again, iterations + more  # both solves must have converged
        message += f"; strength prior weighed by tau_int = {tau:.1f} frames"
    std_data, cov = prob.strength_std(z, with_prior=False, return_cov=True)
    std_post = prob.strength_std(z, with_prior=True)
    free = np.array([lo < hi for lo, hi in prob.k_bounds])
    share = np.where(free, 1.0, np.nan)  # fraction of each factor inside the identified directions
    lo_b, hi_b = s.strength_bounds
    k_hat = z[: prob.g].copy()
    rel_std = std_data / k_hat  # strength is a scale: its precision is relative (F_max error is relative)
    if s.identify is IdentifyMode.TRUNCATE and s.identify_max_std is not None and np.any(free):
        rel_cov = cov / np.outer(k_hat[free], k_hat[free])  # covariance of log k
        var, vec = np.linalg.eigh(0.5 * (rel_cov + rel_cov.T))
        known = vec[:, var <= s.identify_max_std**2]
        proj = known @ known.T
        if known.shape[1] < int(free.sum()):
            k = k_hat.copy()
            k[free] = np.clip(np.exp(proj @ np.log(k_hat[free])), lo_b, hi_b)
            for j in np.flatnonzero(free).tolist():
                prob.k_bounds[j] = (float(k[j]), float(k[j]))
            z[: prob.g] = k
            z, again, more, message = solve(z)  # the directions held come from the first solve: it must have converged
            converged, iterations = converged and again, iterations + more
            message += "; unidentified directions held at the reference"
    if s.identify_max_std is not None and np.any(free):  # share of each factor in the identified directions
        rel_cov = cov / np.outer(k_hat[free], k_hat[free])
        var, vec = np.linalg.eigh(0.5 * (rel_cov + rel_cov.T))
        known = vec[:, var <= s.identify_max_std**2]
        share[free] = np.clip(np.sum(known**2, axis=1), 0.0, 1.0)
    if s.identify is IdentifyMode.TRUNCATE and s.identify_max_std is not None:
        std_post = np.where(free & (rel_std <= s.identify_max_std), std_post, np.nan)  # of the free estimate
    k = z[: prob.g]
    status = []
    for j in range(prob.g):
        if not free[j]:
            status.append(StrengthStatus.NOT_CALIBRATED.value)
        elif min(k[j] - lo_b, hi_b - k[j]) <= 1e-6 * hi_b:
            status.append(StrengthStatus.AT_BOUND.value)
        elif s.identify_max_std is None or rel_std[j] <= s.identify_max_std:
            status.append(StrengthStatus.IDENTIFIED.value)
        elif share[j] >= COMBINATION_MIN_SHARE:
            status.append(StrengthStatus.COMBINATION.value)
        else:
            status.append(StrengthStatus.UNIDENTIFIED.value)
    result = prob.result(z, method, converged, iterations, message, s, f_ref)
    result.strength_std, result.strength_std_data, result.status = std_post, std_data, status
    result.strength_rel_std_data = rel_std
    result.identified_share = share
    return result


def calibrate_alternating(
    f_max_ref: np.ndarray,
    frames: CalibrationFrames,
    settings: CalibrationSettings | None = None,
    *,
    max_sweeps: int = 2000,
    tol: float = 1e-12,
) -> CalibrationResult:
    """Independent check: exact block minimisation, a-step by PIQP per frame, k-step by bounded least squares
    (same identifiability passes as :func:`calibrate`)."""
    s = settings or CalibrationSettings()
    f_ref = np.asarray(f_max_ref, dtype=float)
    prob = _Problem(f_ref, frames, s)
    g = prob.g
    solver = piqp.DenseSolver()
    solver.settings.eps_abs = 1e-10
    solver.settings.eps_rel = 1e-10
    ready = False

    def solve(z: np.ndarray) -> tuple[np.ndarray, bool, int, str]:
        nonlocal ready
        lo = np.array([b[0] for b in prob.k_bounds])
        hi = np.array([b[1] for b in prob.k_bounds])
        previous = np.inf
        sweeps = 0
        for sweeps in range(1, max_sweeps + 1):  # noqa: B007 - the count of sweeps done is returned after the loop
            k, a, beta = prob.split(z)
            a = a.copy()
            tau = prob.tau - prob.offset(beta)  # the torque the activations must produce
            for t in range(prob.t):
                at = prob.m[t] * k[None, :] * prob.inv_s[t][:, None]
                hess = at.T @ at + np.diag(prob.w_p[t] + prob.w_e[t])
                c = -(at.T @ (tau[t] * prob.inv_s[t]) + prob.w_p[t] * prob.mu[t] + prob.w_e[t] * prob.e[t])
                if not ready:
                    solver.setup(np.asfortranarray(hess), c, x_l=np.full(g, s.a_min), x_u=np.ones(g))
                    ready = True
                else:
                    solver.update(P=np.asfortranarray(hess), c=c)
                solver.solve()
                a[t] = np.clip(solver.result.x, s.a_min, 1.0)
            # (k, beta)-step: torque residuals are linear in k and beta -> stacked bounded least squares
            rows = (prob.m * a[:, None, :] * prob.inv_s[:, :, None]).reshape(-1, g)
            basis_rows = (prob.basis * prob.inv_s[:, :, None]).reshape(rows.shape[0], prob.p)
            target = (prob.tau * prob.inv_s).ravel()
            fixed = lo == hi
            kk = np.where(fixed, lo, k)
            n_free = int((~fixed).sum())
            if n_free or prob.p:
                rhs = target - rows[:, fixed] @ lo[fixed]
                mat = np.hstack([rows[:, ~fixed], basis_rows])
                if prob.w_k_obj and n_free:  # the strength prior as extra least-squares rows sqrt(w_k) (k - 1)
                    prior_rows = np.hstack([np.sqrt(prob.w_k_obj) * np.eye(n_free), np.zeros((n_free, prob.p))])
                    mat = np.vstack([mat, prior_rows])
                    rhs = np.concatenate([rhs, np.full(n_free, np.sqrt(prob.w_k_obj))])
                sol = lsq_linear(
                    mat,
                    rhs,
                    bounds=(np.r_[lo[~fixed], prob.beta_lower], np.r_[hi[~fixed], np.full(prob.p, np.inf)]),
                    tol=1e-14,
                ).x
                kk[~fixed], beta = sol[:n_free], sol[n_free:]
            z = np.concatenate([kk, a.ravel(), beta])
            value, _ = prob.value_grad(z)
            if previous - value <= tol * max(1.0, abs(value)):
                break
            previous = value
        return z, prob.projected_gradient(z) < 1e-4, sweeps, f"{sweeps} sweeps"

    return _solve_identified(prob, s, f_ref, solve, "alternating (PIQP + lsq_linear)")
