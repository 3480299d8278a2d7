"""The EMG-driven torque model, its candidate effects, and their fit on training trials / score on held-out trials.

Every sample is one frame t and coordinate n, in capacity-scaled units (torque / c_tn, c = sum_g |R_ng| F_max,g):

    y_tn = tau_tn / c_tn                                        (inverse-dynamics torque)
    m_tn = sum_{g with EMG} A_tng (1 + d_g) phi_tg x_tg         (EMG-implied; d_g: strength re-fit, ridge to 0)
         + sum_{g without EMG} A_tng phi_tg mu_tg               (the prior's mean at the phase, as estimated today)
         + b_n / c_tn                                           (per-coordinate offset: the unmeasured groups' bias)
         + sum_j beta_j Z_tnj                                   (the effect's linear terms)
    gap_tn = y_tn - m_tn,   A_tng = R_tng F_max,g / c_tn

x = EMG envelope (delayed by the profile's calibrated EMD), phi = 1 without a muscle-state effect. The "none" model
has the strength re-fit and the offsets only; each candidate adds its term (a 1-D/2-D grid for its nonlinear
parameter, least squares for the linear ones, bounded where physics or the profile bound them: 1 + d_g times the
group's typical force factor in STRENGTH_GAIN_RANGE, the passive and damping terms >= 0). Fitted on the training
trials, scored on the held-out trials.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import lsq_linear

from msk_core.discrepancy.data import MAX_DELAY_S, SessionArrays, TrialArrays
from msk_core.estimate.effects import (
    CoefKey,
    Effect,
    Nuisance,
    force_factor,
    torque_term_columns,
    torque_term_names,
    unmix_envelopes,
)
from msk_core.signal.reps import in_rep

GAIN_RIDGE = 0.05  # ridge on the unmeasured groups' re-fit, relative to each column's own sum of squares
GAIN_RIDGE_ABS = 0.1  # ... plus this much absolute (scaled-torque units): pins directions the data leave open
# The measured groups' strength re-fit is held more loosely: their EMG fixes the shape, so only the scale is free,
# and a tight ridge there leaves part of a missing effect's training gap unexplained, which hides it (cross-talk)
# or keeps it from being fitted fully (docs/discrepancy.md, "Ridge").
MEASURED_RIDGE = 0.01
MEASURED_RIDGE_ABS = 0.02
TINY_RIDGE = 1e-9
# The range the measured groups' strength re-fit 1 + d (and a moment-arm scale) may take: the range the profile's
# ``strength_gain`` is written in, so that the model scored is the model the profile carries. Unbounded, noisy EMG
# let the re-fit switch electrodes off (1 + d near 0: the fit moved the torque onto noise-free nuisance columns),
# which held-out trials at another load then showed as a pose-following gap that any candidate could "explain"
# (docs/discrepancy.md, "Noisy EMG").
STRENGTH_GAIN_RANGE = (0.5, 2.0)
# true / reported bar load searched by ``load_misreport`` (a grid point, not a linear coefficient: fitted by least
# squares the ratio only follows the strengths down to their bound - shrinking the target shrinks every gap - and came
# out at 0.54 on effect-free sessions as on sessions whose load was over-reported by 1.8; docs/discrepancy.md, Limits)
LOAD_RATIOS = (0.5, 0.6, 0.7, 0.8, 0.9, 1.1, 1.25, 1.4, 1.6, 1.8, 2.0)


@dataclass(frozen=True)
class Candidate:
    name: Effect
    grid: tuple[dict, ...]  # settings of the nonlinear parameters ({} when there are none)
    formula: str
    # re-mixes the EMG channels (cross-talk unmixing adds the neighbours' envelope noise to each channel): its
    # residuals are rougher than the base model's whether or not it explains anything (select.py, tau_int)
    remixes_emg: bool = False


def candidate_library(data: SessionArrays, train: list[TrialArrays]) -> list[Candidate]:
    """The candidates that apply to this pack and session (muscle-state ones need fibre lengths, load needs load)."""
    dt = min(t.frame_interval_s for t in data.trials)
    delays = np.arange(0, int(round(MAX_DELAY_S / dt)) + 1) * dt
    out = [
        Candidate(
            Effect.EMD,
            tuple({"delay_total_s": float(d)} for d in delays),
            "x_g(t) = e_g(t - d): EMG leads the force by the electromechanical delay d",
        ),
    ]
    if len(data.emg_groups) >= 2:
        out.append(
            Candidate(
                Effect.CROSSTALK,
                tuple({"fraction": c} for c in (0.05, 0.1, 0.15, 0.2, 0.3, 0.4)),
                "x^2 = (M o M)^-1 e^2: electrode k holds (1 - c) of its muscle's signal and c/2 of each neighbour's",
                remixes_emg=True,
            )
        )
    if data.optimal is not None and data.trials[0].lengths is not None:
        out += [
            Candidate(
                Effect.FL_ACTIVE,
                tuple({"width": w} for w in (0.25, 0.35, 0.45, 0.6, 0.8)),
                "phi_g = exp(-((l_g - 1)/w)^2), l_g normalised fibre length",
            ),
            Candidate(
                Effect.FL_PASSIVE,
                tuple({"strain": s} for s in (0.3, 0.45, 0.6, 0.8, 1.0)),
                "Z = sum_g A_g (exp(4 (l_g - 1)/s) - 1)/(e^4 - 1) for l_g > 1, one scale",
            ),
            Candidate(
                Effect.FV,
                tuple({"v_max": v, "eccentric": e} for v in (5.0, 10.0, 15.0, 20.0) for e in (1.4, 1.8)),
                "phi_g = Hill force-velocity(shortening speed / v_max l_opt), eccentric plateau",
            ),
        ]
    if data.lo is not None:
        out.append(
            Candidate(
                Effect.PASSIVE_JOINT,
                tuple({"decay_rad": d} for d in (0.05, 0.1, 0.2, 0.35)),
                "Z_n = k_lo,n exp((lo_n - q_n)/d) - k_hi,n exp((q_n - hi_n)/d) / c_n",
            )
        )
    out.append(Candidate(Effect.DAMPING, ({},), "Z_n = -b_n qd_n / c_n (muscles also overcome joint damping)"))
    if len({t.load_kg for t in train}) >= 2:  # with one load a load scale is a strength scale (not separable)
        out.append(
            Candidate(
                Effect.LOAD_MISREPORT,
                tuple({"true_over_reported": r} for r in LOAD_RATIOS),
                "y = (tau - (1 - r) tau_load) / c: the bar's true load is r x the reported one",
            )
        )
    multi = [g for g in data.emg_groups if _crosses(data, g) > 1]
    if multi:
        out.append(
            Candidate(
                Effect.MOMENT_ARM_SCALE,
                ({},),
                "per (group, coordinate) scale of R_ng for groups with EMG crossing several coordinates",
            )
        )
    return out


def crossed_coordinates(data: SessionArrays, group: str) -> list[str]:
    """The coordinates a group has a moment arm about (> 0.1 mm anywhere in the first trial)."""
    j = data.groups.index(group)
    arms = data.trials[0].arms[:, :, j]
    return [c for n, c in enumerate(data.coordinates) if np.any(np.abs(arms[:, n]) > 1e-4)]


def _crosses(data: SessionArrays, group: str) -> int:
    return len(crossed_coordinates(data, group))


UNMEASURED_PHASE_BINS = 6  # free phase profile of each unmeasured group's demand share (nuisance)


def phase_basis(phase: np.ndarray, n: int = UNMEASURED_PHASE_BINS) -> list[np.ndarray]:
    """Periodic hat functions over the rep phase (n, summing to 1 inside reps) and an indicator of rest."""
    inside = in_rep(phase)
    p = np.where(inside, phase, 0.0) * n
    out = []
    for k in range(n):
        d = np.abs(((p - k + n / 2) % n) - n / 2)
        out.append(np.where(inside, np.clip(1.0 - d, 0.0, None), 0.0))
    out.append((~inside).astype(float))
    return out


@dataclass
class Design:
    y: np.ndarray  # (N,)
    fixed: np.ndarray  # (N,) the model with every linear coefficient at 0
    columns: np.ndarray  # (N, p)
    names: list[CoefKey]
    ridge: np.ndarray  # (p,) relative ridge
    ridge_abs: np.ndarray  # (p,) absolute ridge
    n_frames: int
    n_coordinates: int
    emg_sum: np.ndarray  # (G_E,) sum over the frames of each measured group's effective EMG x
    phi_emg_sum: np.ndarray  # (G_E,) ... of phi x (typical_force_factor)


def effective_emg(data: SessionArrays, trial: TrialArrays, model: dict[Effect, dict]) -> np.ndarray:
    """(T, G_E) activations the EMG stands for under the model: delayed, unmixed."""
    delay = model.get(Effect.EMD, {}).get("delay_total_s", data.base_delay_s)
    x = trial.emg
    if delay > 0:
        x = np.column_stack([np.interp(trial.time - delay, trial.time, x[:, k]) for k in range(x.shape[1])])
    if Effect.CROSSTALK in model:
        idx = [data.emg_groups.index(g) for g in data.electrode_order]
        x = x.copy()
        x[:, idx] = unmix_envelopes(x[:, idx], model[Effect.CROSSTALK]["fraction"])
    return x


def design(data: SessionArrays, trial: TrialArrays, model: dict[Effect, dict]) -> Design:
    n, n_c = trial.n, len(data.coordinates)
    e_idx, o_idx = data.emg_index, data.other_index
    a = trial.arms * data.f_max / trial.scale[:, :, None]  # (T, n_c, G)
    x = effective_emg(data, trial, model)
    phi = force_factor(trial.lengths, trial.arms, trial.qd, data.optimal, data.slack, model)
    contrib = a[:, :, e_idx] * (phi[:, e_idx] * x)[:, None, :]  # (T, n_c, G_E)
    fixed = contrib.sum(axis=2)
    if o_idx.size:
        fixed = fixed + (a[:, :, o_idx] * (phi[:, o_idx] * trial.prior_mean[:, o_idx])[:, None, :]).sum(axis=2)
    cols, names, ridge, ridge_abs = [], [], [], []

    def add(column: np.ndarray, name: CoefKey, rel: float = TINY_RIDGE, absolute: float = 0.0) -> None:
        cols.append(column.ravel())
        names.append(name)
        ridge.append(rel)
        ridge_abs.append(absolute)

    onehot = np.eye(n_c)
    # The columns are the same for every trial of the session (a fit on the training trials is applied to the held-out
    # ones): a column that is zero in one trial (a group that static optimisation leaves off in one phase) stays, and
    # its absolute ridge holds its coefficient at 0 where the data say nothing.
    # Strength re-fit per measured group (ridge toward the calibrated strength); with moment_arm_scale one per group
    # and coordinate crossed, for the groups crossing several coordinates
    multi = set()
    if Effect.MOMENT_ARM_SCALE in model:
        for k, g in enumerate(data.emg_groups):
            crossed = crossed_coordinates(data, g)
            if len(crossed) > 1:
                multi.add(k)
                for coordinate in crossed:
                    add(
                        contrib[:, :, k] * onehot[data.coordinates.index(coordinate)],
                        CoefKey(Effect.MOMENT_ARM_SCALE, "scale", group=g, coordinate=coordinate),
                        MEASURED_RIDGE,
                        MEASURED_RIDGE_ABS,
                    )
    for k, g in enumerate(data.emg_groups):
        if k not in multi:
            add(contrib[:, :, k], CoefKey(Nuisance.GAIN, group=g), MEASURED_RIDGE, MEASURED_RIDGE_ABS)
    for j in o_idx:  # the unmeasured groups' prior-mean contribution, re-scaled like the measured groups' strength
        add(
            a[:, :, j] * (phi[:, j] * trial.prior_mean[:, j])[:, None],
            CoefKey(Nuisance.PRIOR, group=data.groups[j]),
            GAIN_RIDGE,
            GAIN_RIDGE_ABS,
        )
        base = a[:, :, j] * (phi[:, j] * trial.min_effort[:, j])[:, None]  # follows the frame's demand (load)
        for k, w in enumerate(phase_basis(trial.phase)):  # ... with a free share per phase of the rep
            add(
                base * w[:, None],
                CoefKey(Nuisance.DEMAND, group=data.groups[j], phase_bin=k),
                GAIN_RIDGE,
                GAIN_RIDGE_ABS,
            )
    inv_c = 1.0 / trial.scale
    for c in range(n_c):
        add(inv_c * onehot[c], CoefKey(Nuisance.OFFSET, coordinate=data.coordinates[c]))
    terms = torque_term_columns(
        model, trial.q, trial.qd, trial.lengths, trial.arms, data.f_max, data.optimal, data.slack, data.lo, data.hi
    )  # (T, n_c, p) N·m per unit coefficient
    for j, name in enumerate(torque_term_names(model, data.coordinates)):
        add(terms[:, :, j] * inv_c, name)
    return Design(
        y=(target_torque(trial, model) * inv_c).ravel(),
        fixed=fixed.ravel(),
        columns=np.column_stack(cols),
        names=names,
        ridge=np.asarray(ridge),
        ridge_abs=np.asarray(ridge_abs),
        n_frames=n,
        n_coordinates=n_c,
        emg_sum=x.sum(axis=0),
        phi_emg_sum=(phi[:, e_idx] * x).sum(axis=0),
    )


def typical_force_factor(designs: list[Design]) -> np.ndarray:
    """(G_E,) each measured group's force factor phi (force-length x force-velocity; 1 without them) averaged over the
    designs' frames (the training trials), weighted by its EMG: what the factor does to the group's force where it
    works. A muscle-state factor (<= 1 concentric) is a shape *and* a strength change; the strength bound applies to
    the product."""
    num = sum(d.phi_emg_sum for d in designs)
    den = sum(d.emg_sum for d in designs)
    return np.where(den > 0, num / np.maximum(den, 1e-12), 1.0)


# passive force is tensile, an elastic joint moment pushes away from its limit, damping dissipates: these
# (effect, parameter) coefficients are >= 0
NON_NEGATIVE = frozenset(
    {
        (Effect.FL_PASSIVE, "scale"),
        (Effect.PASSIVE_JOINT, "k_lower"),
        (Effect.PASSIVE_JOINT, "k_upper"),
        (Effect.DAMPING, "b"),
    }
)
STRENGTH_TERMS = (Nuisance.GAIN, Effect.MOMENT_ARM_SCALE)  # scales of a measured group's strength (per coordinate)


def coefficient_bounds(
    data: SessionArrays, names: list[CoefKey], phi_typical: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Bounds on the coefficients: the strength (and moment-arm) scales of the measured groups, times their typical
    force factor, in STRENGTH_GAIN_RANGE; the passive and damping terms >= 0 (NON_NEGATIVE: free in sign, they fitted
    unphysical negative moments - a negative passive force for an active force-length effect, a joint moment pulling
    toward its limit for a passive force - and were named for them); the other coefficients free."""
    lower, upper = np.full(len(names), -np.inf), np.full(len(names), np.inf)
    for j, key in enumerate(names):
        if key.term in STRENGTH_TERMS:
            phi = max(float(phi_typical[data.emg_groups.index(key.group)]), 1e-3)
            lower[j], upper[j] = STRENGTH_GAIN_RANGE[0] / phi - 1.0, STRENGTH_GAIN_RANGE[1] / phi - 1.0
        elif (key.term, key.parameter) in NON_NEGATIVE:
            lower[j] = 0.0
    return lower, upper


def _bounded_quadratic_minimum(g: np.ndarray, h: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """argmin 1/2 c'Gc - h'c within [lower, upper], as the least-squares problem ||S c - S^-T h|| with G = S'S
    (Cholesky; a near-singular G through its eigen-decomposition, eigenvalues floored)."""
    try:
        chol = np.linalg.cholesky(g)
        a, b = chol.T, np.linalg.solve(chol, h)
    except np.linalg.LinAlgError:
        w, v = np.linalg.eigh(0.5 * (g + g.T))
        w = np.maximum(w, 1e-12 * max(float(w.max()), 1e-300))
        a, b = np.sqrt(w)[:, None] * v.T, (v.T @ h) / np.sqrt(w)
    return lsq_linear(a, b, bounds=(lower, upper), method="bvls").x


@dataclass
class Fit:
    model: dict[Effect, dict]
    names: list[CoefKey]
    coef: np.ndarray
    train_mse: float
    n_params: int  # linear coefficients + nonlinear parameters
    phi_typical: np.ndarray  # (G_E,) typical_force_factor on the training trials
    lower: np.ndarray  # (p,) the coefficients' bounds (coefficient_bounds; -inf / inf where free)
    upper: np.ndarray
    # the calibrated strengths the fit was made with: the session's, or a re-calibration's with the candidate's torque
    # in the calibration (recalibrate.py); ``gaps`` and the other users of a fit evaluate it with these
    f_max: np.ndarray | None = None


def on(data: SessionArrays, f: Fit) -> SessionArrays:
    """The session arrays with the strengths ``f`` was fitted with (the same frames and capacity scale)."""
    if f.f_max is None or f.f_max is data.f_max or np.array_equal(f.f_max, data.f_max):
        return data
    return replace(data, f_max=f.f_max)


def fit(data: SessionArrays, trials: list[TrialArrays], model: dict[Effect, dict]) -> Fit:
    """Least squares (normal equations, relative ridge) of the linear coefficients over the trials."""
    designs = [design(data, t, model) for t in trials]
    x = np.vstack([d.columns for d in designs])
    r = np.concatenate([d.y - d.fixed for d in designs])
    g = x.T @ x
    diag = np.diag(g).copy()
    ridge = designs[0].ridge
    g[np.diag_indices_from(g)] += ridge * np.maximum(diag, 1e-12) + designs[0].ridge_abs
    coef = np.linalg.solve(g, x.T @ r)
    phi_typical = typical_force_factor(designs)
    lower, upper = coefficient_bounds(data, designs[0].names, phi_typical)
    if np.any(coef < lower) or np.any(coef > upper):  # the same quadratic, minimised inside the bounds
        coef = _bounded_quadratic_minimum(g, x.T @ r, lower, upper)
    res = r - x @ coef
    n_nonlinear = sum(len(p) for p in model.values())
    return Fit(
        model=model,
        names=designs[0].names,
        coef=coef,
        train_mse=float(np.mean(res**2)),
        n_params=len(coef) + n_nonlinear,
        phi_typical=phi_typical,
        lower=lower,
        upper=upper,
        f_max=data.f_max,
    )


def gaps(data: SessionArrays, trial: TrialArrays, f: Fit) -> np.ndarray:
    """(T, n_c) torque gap y - m in capacity-scaled units under a fitted model, with the strengths it was fitted at."""
    d = design(on(data, f), trial, f.model)
    return (d.y - d.fixed - d.columns @ f.coef).reshape(d.n_frames, d.n_coordinates)


def integrated_autocorrelation(res: list[np.ndarray], max_lag: int = 400) -> float:
    """tau_int = 1 + 2 sum_k rho_k (up to the first lag where rho < 0.05) of the residual series, averaged over series:
    how many consecutive samples carry one sample's worth of information."""
    taus = []
    for s in res:
        s = s - s.mean()
        v = float(s @ s)
        if v <= 0 or s.size < 10:
            continue
        tau = 1.0
        for k in range(1, min(max_lag, s.size // 2)):
            rho = float(s[:-k] @ s[k:]) / v
            if rho < 0.05:
                break
            tau += 2.0 * rho
        taus.append(tau)
    return float(np.mean(taus)) if taus else 1.0


@dataclass
class Score:
    name: Effect
    parameters: dict
    fit: Fit
    holdout_mse: float
    reduction: float  # 1 - holdout MSE / holdout MSE of the base model
    delta_bic_train: float
    minus2_ln_lr_holdout: float  # -2 ln (likelihood ratio) on the held-out trials, N_eff ln(MSE_cand / MSE_base)
    holdout_bic: float  # the same plus dp ln N_eff (its extra parameters): the rank among candidates that pass
    accepted: bool
    reason: str
    extra: dict = field(default_factory=dict)
    left_out_reductions: dict = field(default_factory=dict)  # training trial -> reduction when left out of the fit
    rep_reductions: list = field(default_factory=list)  # [(held-out trial, rep, reduction)] (select.rep_reductions)


def mse(data: SessionArrays, trials: list[TrialArrays], f: Fit) -> float:
    return mean_square([gaps(data, t, f) for t in trials])


def mean_square(res: list[np.ndarray]) -> float:
    """The mean square of gaps already computed, pooled over trials and coordinates."""
    return float(np.mean(np.concatenate([r.ravel() for r in res]) ** 2))


def target_torque(trial: TrialArrays, model: dict[Effect, dict]) -> np.ndarray:
    """(T, n_c) the torque the muscles must explain: the inverse-dynamics torque, with ``load_misreport`` corrected to
    the true load, tau - (1 - r) tau_load (tau_load: the reported load's share, r = true / reported)."""
    if Effect.LOAD_MISREPORT not in model:
        return trial.tau
    return trial.tau - (1.0 - model[Effect.LOAD_MISREPORT]["true_over_reported"]) * trial.tau_load


def target_ms(data: SessionArrays, trials: list[TrialArrays], f: Fit) -> float:
    """Mean square of the (capacity-scaled) torque the model must explain, target_torque / c. A load scale changes its
    own target: shrinking the target and, through the strengths, the EMG-implied torque with it shrinks every gap -
    EMG noise included - without explaining anything (in a bench press, where the bar is nearly all of the torque, it
    is the same as a strength scale). Scores compare MSE / target_ms (the unexplained fraction); for the models that
    keep the target it is the MSE ratio."""
    ys = np.concatenate([(target_torque(t, f.model) / t.scale).ravel() for t in trials])
    return float(np.mean(ys**2))
