"""Candidate scoring and greedy forward selection (docs/discrepancy.md, "Criterion").

A candidate is named when, against the current model (at first: "none" = strength re-fit + offsets):

1. its held-out mean-squared torque gap is at least ``MIN_REDUCTION`` (15 %) smaller (minimum effect size, set above
   the largest improvement on the effect-free synthetic sessions when it was chosen, 12.7 %; the closest calls now
   are in docs/discrepancy.md, Criterion),
2. the Bayesian information criterion prefers it by more than ``BIC_MARGIN`` (10: "very strong" on the Kass-Raftery
   scale) on the training trials, where its parameters were fitted, with Gaussian errors:
   dBIC = N_eff ln(MSE_cand / MSE_base) + dp ln(N_eff), dp its extra parameters (linear and grid), and
3. the held-out trials, where nothing was fitted, favour it by a log-likelihood ratio of more than ``BIC_MARGIN``
   on the same scale: -2 ln LR = N_eff ln(MSE_cand / MSE_base) < -10 (no parameter penalty: a candidate that overfits
   the training trials pays for it here as a worse held-out fit, so a penalty would count the parameters twice), and
4. with several training trials, none of them, left out of the fit, favours the base model by -2 ln LR > ``BIC_MARGIN``
   (``_left_out_reductions``: an effect of the body holds on every trial).

N_eff = N / tau_int discounts the gaps' autocorrelation (consecutive frames are not independent samples). tau_int is
measured on the residuals of the candidate, the larger model of the pair: the base model's residuals still carry the
very effect being tested, whose smooth signature would inflate tau_int and so penalise exactly the effects that are
there (the usual choice of a nested test, whose noise is estimated from the fuller model). The exception is a
candidate that re-mixes the EMG channels (cross-talk unmixing subtracts the neighbours' envelopes and so adds their
noise): its residuals are rougher whether or not it explains anything (tau_int halved on sessions without cross-talk,
docs/discrepancy.md), which would inflate N_eff; for it the larger of the two tau_int is used.

Among the candidates that pass, the one with the lowest held-out BIC, -2 ln LR + dp ln(N_eff) on the held-out trials,
is named: two candidates that both explain the gap are often two descriptions of one effect (a muscle's passive force
and the joint's passive moment), and the held-out fit alone prefers the one with more parameters (a predictive score
is not consistent: it keeps a larger model that is no truer), while BIC takes the extra parameters' fit as evidence
only where it pays for them. With ``max_effects`` > 1 it
joins the model, the others are refitted on top of it, and the search repeats.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from msk_core.discrepancy.data import SessionArrays, TrialArrays
from msk_core.discrepancy.model import (
    Candidate,
    Fit,
    Score,
    candidate_library,
    fit,
    gaps,
    integrated_autocorrelation,
    mean_square,
    mse,
    on,
    target_ms,
    target_torque,
)
from msk_core.discrepancy.recalibrate import HONOURED, Recalibrator
from msk_core.errors import EstimationError
from msk_core.estimate.effects import Effect
from msk_core.progress import Progress, counted

MIN_REDUCTION = 0.15
BIC_MARGIN = 10.0


def _n_eff(data: SessionArrays, trials: list[TrialArrays], f: Fit) -> tuple[float, float]:
    return _n_eff_of([gaps(data, t, f) for t in trials])


def _n_eff_of(res: list[np.ndarray]) -> tuple[float, float]:
    """(N_eff, tau_int) of residuals already computed ((T, n_c) per trial)."""
    n = sum(r.size for r in res)
    tau = integrated_autocorrelation([r[:, c] for r in res for c in range(r.shape[1])])
    return n / tau, tau


def _unexplained(data: SessionArrays, trials: list[TrialArrays], f: Fit, ms: float | None = None) -> float:
    """MSE / mean square of the target (model.target_ms: the MSE ratio unless a candidate changes its own target)."""
    return (mse(data, trials, f) if ms is None else ms) / target_ms(data, trials, f)


@dataclass(frozen=True)
class LeftOut:
    """One training trial left out of the fit: the base model fitted on the others, once per greedy step."""

    trial: TrialArrays
    rest: list[TrialArrays]
    base_fit: Fit
    base_unexplained: float  # on the left-out trial
    offered: frozenset[Effect]  # the candidates the other trials still define (a load scale needs two loads)


def left_out_bases(data: SessionArrays, train: list[TrialArrays], base: Fit) -> list[LeftOut]:
    """With several training trials, each left out in turn (none with one training trial)."""
    if len(train) < 2:
        return []
    out = []
    for k, trial in enumerate(train):
        rest = train[:k] + train[k + 1 :]
        b = fit(data, rest, base.model)
        out.append(
            LeftOut(
                trial, rest, b, _unexplained(data, [trial], b), frozenset(c.name for c in candidate_library(data, rest))
            )
        )
    return out


@dataclass
class Base:
    """The model a candidate is compared with in one greedy step: its fit, its held-out gaps and its left-out fits."""

    fit: Fit
    hold_gaps: list[np.ndarray]
    left_out: list[LeftOut]


def base_state(data: SessionArrays, train: list[TrialArrays], holdout: list[TrialArrays], f: Fit) -> Base:
    return Base(f, [gaps(data, t, f) for t in holdout], left_out_bases(on(data, f), train, f))


def score_candidate(
    data, train, holdout, current: Base, cand: Candidate, recalibrated: tuple[Recalibrator, Base] | None = None
) -> Score:
    """``current``: the model of this greedy step (the same for every candidate of the step). ``recalibrated``: for a
    muscle- or joint-state candidate, the re-calibrator and the current model re-calibrated the same way; the
    candidate is then fitted with the strengths of a calibration that has it in it, and compared with that
    (recalibrate.py)."""
    base, base_hold_gaps, left_out = current.fit, current.hold_gaps, current.left_out
    data = on(data, base)  # the strengths the base model was fitted with (a re-calibration's, after a torque term)
    best, best_fraction = None, np.inf
    for setting in cand.grid:  # nonlinear parameters: the grid point with the lowest training unexplained fraction
        f = fit(data, train, {**base.model, cand.name: dict(setting)})  # (the MSE, unless it changes its target)
        fraction = _unexplained(data, train, f, f.train_mse)
        if best is None or fraction < best_fraction:
            best, best_fraction = f, fraction
    if best is None:
        raise EstimationError(f"discrepancy candidate {cand.name!r} has no parameter setting to fit (an empty grid)")
    if recalibrated is not None:
        recal, rbase = recalibrated
        best = fit(replace(data, f_max=recal.f_max(best.model)), train, best.model)
        best_fraction = _unexplained(data, train, best, best.train_mse)
        base, base_hold_gaps, left_out = rbase.fit, rbase.hold_gaps, rbase.left_out
    hold_gaps = [gaps(data, t, best) for t in holdout]  # once: the held-out MSE, N_eff and the per-rep reductions
    hold = mean_square(hold_gaps)
    base_hold_mse = mean_square(base_hold_gaps)
    n_eff_train, tau_train = _n_eff(data, train, best)
    n_eff_hold, tau_hold = _n_eff_of(hold_gaps)
    if cand.remixes_emg:
        n_eff_train, tau_train = min((n_eff_train, tau_train), _n_eff(data, train, base))
        n_eff_hold, tau_hold = min((n_eff_hold, tau_hold), _n_eff_of(base_hold_gaps))
    dp = best.n_params - base.n_params
    ratio_train = best_fraction / _unexplained(data, train, base, base.train_mse)
    ratio_hold = _unexplained(data, holdout, best, hold) / _unexplained(data, holdout, base, base_hold_mse)
    dbic_train = n_eff_train * float(np.log(ratio_train)) + dp * float(np.log(n_eff_train))
    lr_hold = n_eff_hold * float(np.log(ratio_hold))  # -2 ln LR on data the fit never saw
    bic_hold = lr_hold + dp * float(np.log(n_eff_hold))  # ranks the candidates (select_effects)
    reduction = 1.0 - ratio_hold
    left_out_scores = _left_out_reductions(on(data, best), left_out, base, cand, best.model[cand.name])
    reasons = []
    if reduction < MIN_REDUCTION:
        reasons.append(f"held-out reduction {reduction:.1%} < {MIN_REDUCTION:.0%}")
    for label, (r, lr) in left_out_scores.items():
        if lr > BIC_MARGIN:
            reasons.append(
                f"training trial {label}, left out of the fit, contradicts it ({r:+.1%}, -2 ln LR {lr:+.1f} "
                f"> {BIC_MARGIN:g})"
            )
    if dbic_train > -BIC_MARGIN:
        reasons.append(f"training dBIC {dbic_train:.1f} > -{BIC_MARGIN:g}")
    if lr_hold > -BIC_MARGIN:
        reasons.append(f"held-out -2 ln LR {lr_hold:.1f} > -{BIC_MARGIN:g}")
    per_rep = rep_reductions(data, holdout, best, base, hold_gaps, base_hold_gaps)
    return Score(
        name=cand.name,
        parameters=dict(best.model[cand.name]),
        fit=best,
        holdout_mse=hold,
        reduction=reduction,
        delta_bic_train=dbic_train,
        minus2_ln_lr_holdout=lr_hold,
        holdout_bic=bic_hold,
        accepted=not reasons,
        reason="; ".join(reasons) or "passes",
        extra={"tau_train_frames": tau_train, "tau_holdout_frames": tau_hold, "recalibrated": recalibrated is not None},
        left_out_reductions=left_out_scores,
        rep_reductions=per_rep,
    )


def rep_reductions(
    data: SessionArrays,
    holdout: list[TrialArrays],
    cand: Fit,
    base: Fit,
    cand_gaps: list[np.ndarray] | None = None,
    base_gaps: list[np.ndarray] | None = None,
) -> list[tuple[str, int, float]]:
    """Each held-out rep's reduction of the unexplained fraction by the candidate (how sure: an effect of the body
    helps rep after rep; one that wins on the pooled gap through a rep or two does not), and the frames between reps
    as rep -1 (set-up and rests: a passive moment can show there alone). [(trial, rep, reduction)]. The models' gaps
    on ``holdout`` are computed unless given."""
    cand_gaps = cand_gaps if cand_gaps is not None else [gaps(data, t, cand) for t in holdout]
    base_gaps = base_gaps if base_gaps is not None else [gaps(data, t, base) for t in holdout]
    out = []
    for t, g_c, g_b in zip(holdout, cand_gaps, base_gaps):
        y_c = target_torque(t, cand.model) / t.scale
        y_b = target_torque(t, base.model) / t.scale
        reps = np.unique(t.rep_index)
        for r in ([-1] if reps[0] < 0 else []) + [int(x) for x in reps[reps >= 0]]:
            m = (t.rep_index < 0) if r < 0 else (t.rep_index == r)
            frac_c = float(np.mean(g_c[m] ** 2)) / max(float(np.mean(y_c[m] ** 2)), 1e-300)
            frac_b = float(np.mean(g_b[m] ** 2)) / max(float(np.mean(y_b[m] ** 2)), 1e-300)
            out.append((t.name, int(r), 1.0 - frac_c / max(frac_b, 1e-300)))
    return out


def _left_out_reductions(
    data: SessionArrays, left_out: list[LeftOut], base: Fit, cand: Candidate, setting: dict
) -> dict[str, tuple[float, float]]:
    """With several training trials: for each one, the candidate (at its chosen setting) and the base model fitted on
    the *other* training trials; returns the candidate's reduction of that trial's unexplained fraction and its
    -2 ln LR there (N_eff ln ratio, > 0 when the trial favours the base model). An effect of the body holds on every
    trial; a term that only bends the fit between the training loads does not (effect-free bench-press seed 8 with two
    training loads: the passive force took 23 % off the held-out gap, but fitted on one training load it made the
    other 14-16 % worse; docs/discrepancy.md, Criterion). Skipped for a trial whose absence leaves the candidate
    undefined (a load scale needs two loads)."""
    out: dict[str, tuple[float, float]] = {}
    for lo in left_out:
        if cand.name not in lo.offered:
            continue
        c = fit(data, lo.rest, {**base.model, cand.name: dict(setting)})
        ratio = _unexplained(data, [lo.trial], c) / lo.base_unexplained
        n_eff, _ = _n_eff(data, [lo.trial], c)
        out[lo.trial.name] = (1.0 - ratio, n_eff * float(np.log(ratio)))
    return out


@dataclass
class Selection:
    none_fit: Fit
    final_fit: Fit
    named: list[Effect]
    steps: list[list[Score]]  # per greedy step, the candidates ranked by held-out BIC
    gap_before_mse: float
    gap_after_mse: float
    autocorrelation_frames: float


def select_effects(
    data: SessionArrays,
    train: list[TrialArrays],
    holdout: list[TrialArrays],
    *,
    max_effects: int = 1,
    progress: Progress | None = None,
    recalibrator: Recalibrator | None = None,
) -> Selection:
    """Greedy forward selection. With a ``recalibrator``, the muscle- and joint-state candidates and the delay
    (recalibrate.HONOURED) are fitted with a calibration that has them in it, against the base model calibrated the
    same way."""
    library = candidate_library(data, train)
    none = fit(data, train, {})
    base, base_hold = none, mse(data, holdout, none)
    before = base_hold
    named: list[Effect] = []
    steps: list[list[Score]] = []
    tau = 1.0
    for step in range(max_effects):
        _, tau = _n_eff(data, train, base)
        remaining = [c for c in library if c.name not in base.model]
        if not remaining:
            break
        plain = base_state(data, train, holdout, base)
        rbase = None

        def recalibrated(c: Candidate, base: Fit = base) -> tuple[Recalibrator, Base] | None:  # this step's base
            nonlocal rbase
            if (
                recalibrator is None
                or c.name not in HONOURED  # the delay too: calibrated again with the EMG shifted by it
                or not recalibrator.supports({**base.model, c.name: {}})
            ):
                return None
            if rbase is None:  # the base model re-calibrated with its own torque terms (none at the first step)
                rbase = base_state(
                    data, train, holdout, fit(replace(data, f_max=recalibrator.f_max(base.model)), train, base.model)
                )
            return recalibrator, rbase

        scores = [
            score_candidate(data, train, holdout, plain, c, recalibrated(c))
            for c in counted(remaining, progress, f"discrepancy step {step + 1} (candidates)")
        ]
        scores.sort(key=lambda s: s.holdout_bic)
        steps.append(scores)
        winner = next((s for s in scores if s.accepted), None)
        if winner is None:
            break
        named.append(winner.name)
        base, base_hold = winner.fit, winner.holdout_mse
    return Selection(
        none_fit=none,
        final_fit=base,
        named=named,
        steps=steps,
        gap_before_mse=before,
        gap_after_mse=base_hold,
        autocorrelation_frames=tau,
    )
