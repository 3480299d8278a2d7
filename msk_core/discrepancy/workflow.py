"""The whole discrepancy workflow on loaded trials: gaps, where they concentrate, the candidate search, the profile with
the named effects, and the gaps on the held-out trials before and after (torque and activation)."""

from __future__ import annotations

import copy
import datetime as _dt
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from msk_core.discrepancy.data import MAX_DELAY_S, SessionArrays, TrialArrays, check_inputs, session_arrays
from msk_core.discrepancy.model import Fit, crossed_coordinates, design, gaps, on
from msk_core.discrepancy.recalibrate import Recalibrator
from msk_core.discrepancy.select import BIC_MARGIN, MIN_REDUCTION, Selection, select_effects
from msk_core.estimate.effects import EFFECTS_FORMAT_VERSION, CoefKey, Effect, Nuisance, fibre_length
from msk_core.estimate.pack import PackLike
from msk_core.estimate.profile import SubjectProfile
from msk_core.estimate.trial import TrialData
from msk_core.progress import Progress
from msk_core.signal.reps import in_rep

N_BINS = 12
XCORR_MAX_LAG_S = 0.2


def effects_section(data: SessionArrays, f: Fit, evidence: dict) -> dict:
    """The profile's ``effects`` section for a fitted model (the per-coordinate offsets are nuisance, left out)."""
    coef = dict(zip(f.names, f.coef.tolist()))
    arm_groups = {k.group for k in coef if k.term is Effect.MOMENT_ARM_SCALE}
    # the re-fitted strengths, within the bounds the fit kept them in (the clip only removes round-off)
    bounds = {n: (lo, hi) for n, lo, hi in zip(f.names, f.lower, f.upper)}
    gain = {
        g: 1.0 if g in arm_groups else 1.0 + float(np.clip(coef[gain_key(g)], *bounds[gain_key(g)]))
        for g in data.emg_groups
    }
    effects = [
        {"name": name.value, "parameters": effect_parameters(data, name, setting, coef)}
        for name, setting in f.model.items()
    ]
    return {
        "format_version": EFFECTS_FORMAT_VERSION,
        "effects": effects,
        "strength_gain": {g: round(k, 6) for g, k in gain.items()},
        "evidence": evidence,
    }


def gain_key(group: str) -> CoefKey:
    """The key of a measured group's strength re-fit."""
    return CoefKey(Nuisance.GAIN, group=group)


def effect_parameters(data: SessionArrays, name: Effect, setting: dict, coef: dict[CoefKey, float]) -> dict:
    """One effect's ``parameters`` in the profile: its grid setting and its fitted coefficients, by name."""
    if name is Effect.EMD:
        extra = setting["delay_total_s"] - data.base_delay_s
        return {
            "delay_s": round(max(extra, 0.0), 6),
            "delay_total_s": round(setting["delay_total_s"], 6),
            "frame_interval_s": round(min(t.frame_interval_s for t in data.trials), 9),
        }
    if name is Effect.CROSSTALK:
        return {"fraction": setting["fraction"], "electrode_order": list(data.electrode_order)}
    if name in (Effect.FL_ACTIVE, Effect.FV, Effect.LOAD_MISREPORT):  # grid settings only
        return dict(setting)
    if name is Effect.FL_PASSIVE:
        return {"strain": setting["strain"], "scale": coef[CoefKey(name, "scale")]}
    if name is Effect.PASSIVE_JOINT:
        return {
            "decay_rad": setting["decay_rad"],
            "k_lower_nm": [coef[CoefKey(name, "k_lower", coordinate=c)] for c in data.coordinates],
            "k_upper_nm": [coef[CoefKey(name, "k_upper", coordinate=c)] for c in data.coordinates],
        }
    if name is Effect.DAMPING:
        return {"b_nms_per_rad": [coef[CoefKey(name, "b", coordinate=c)] for c in data.coordinates]}
    if name is Effect.MOMENT_ARM_SCALE:
        scales: dict[str, dict[str, float]] = {}
        for key, value in coef.items():
            if key.term is name:
                scales.setdefault(key.group, {})[key.coordinate] = 1.0 + value
        return {"scales": scales}
    raise ValueError(f"no profile parameters for effect {name!r}")  # pragma: no cover - the library is kept in step


def calibration_at_bounds(data: SessionArrays, profile: SubjectProfile) -> list[dict]:
    """The groups whose calibrated strength sits at the calibration's bounds (status ``at_bound``), with the side and
    the coordinates they cross. A strength pinned at a bound absorbed torque the calibration could not explain with
    activations: a missing effect often shows here first (a passive extension moment in a deadlift drives the back
    extensors to the upper bound and the abdominals to the lower one)."""
    strength = (profile.calibration or {}).get("strength") or {}
    if not isinstance(strength, dict):
        return []
    out = []
    for g, info in strength.items():
        if not isinstance(info, dict) or info.get("status") != "at_bound" or g not in data.groups:
            continue
        j = data.groups.index(g)
        scale = float(info.get("scale", profile.f_max[j] / profile.f_max_ref[j]))
        out.append(
            {
                "group": g,
                "scale": round(scale, 4),
                "side": "upper" if scale >= 1.0 else "lower",
                "coordinates": crossed_coordinates(data, g),
            }
        )
    return out


def _binned(x: np.ndarray, y: np.ndarray, bins: int = N_BINS) -> tuple[list[float], list[float]]:
    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < bins:
        return [], []
    edges = np.quantile(x[ok], np.linspace(0, 1, bins + 1))
    idx = np.clip(np.searchsorted(edges, x[ok], side="right") - 1, 0, bins - 1)
    centres = [float(np.mean(x[ok][idx == k])) if np.any(idx == k) else float("nan") for k in range(bins)]
    means = [float(np.mean(y[ok][idx == k])) if np.any(idx == k) else float("nan") for k in range(bins)]
    return centres, means


def _corr(x: np.ndarray, y: np.ndarray, undefined: float = 0.0) -> float:
    """Pearson r of the finite pairs; ``undefined`` when it is not defined (a constant series, e.g. one held-out
    load: NaN in the tables, "n/a" in the report; 0 where r is summed over lags)."""
    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 3 or np.std(x[ok]) == 0 or np.std(y[ok]) == 0:
        return undefined
    return float(np.corrcoef(x[ok], y[ok])[0, 1])


def relations(data: SessionArrays, trials, f: Fit) -> dict:
    """Where the gaps of model ``f`` concentrate on ``trials``: binned means and correlations against joint angle and
    velocity (per coordinate), phase, load; per EMG group the gap seen along its moment arms against its fibre length
    and lengthening velocity; and the correlation of torque with the EMG-implied torque against the lag."""
    g = np.vstack([gaps(data, t, f) for t in trials])
    q = np.vstack([t.q for t in trials])
    qd = np.vstack([t.qd for t in trials])
    phase = np.concatenate([t.phase for t in trials])
    inside = in_rep(phase)  # frames between reps have no phase of the rep to bin
    load = np.concatenate([np.full(t.n, t.load_kg) for t in trials])
    out: dict = {"coordinates": {}, "groups": {}}
    for n, c in enumerate(data.coordinates):
        out["coordinates"][c] = {
            "angle": dict(zip(("x", "gap"), _binned(q[:, n], g[:, n]))),
            "velocity": dict(zip(("x", "gap"), _binned(qd[:, n], g[:, n]))),
            "phase": dict(zip(("x", "gap"), _binned(phase[inside], g[inside, n]))),
            "corr_angle": _corr(q[:, n], g[:, n], np.nan),
            "corr_velocity": _corr(qd[:, n], g[:, n], np.nan),
            "corr_load": _corr(load, g[:, n], np.nan),
        }
    if data.optimal is not None and data.slack is not None and trials[0].lengths is not None:
        arms = np.vstack([t.arms * on(data, f).f_max / t.scale[:, :, None] for t in trials])
        lengths = np.vstack([fibre_length(t.lengths, data.optimal, data.slack) for t in trials])
        vel = -np.einsum("tng,tn->tg", np.vstack([t.arms for t in trials]), qd)
        for j in data.emg_index:
            a = arms[:, :, j]
            along = (a * g).sum(axis=1) / np.maximum((a * a).sum(axis=1), 1e-12)
            out["groups"][data.groups[j]] = {
                "corr_fibre_length": _corr(lengths[:, j], along, np.nan),
                "corr_lengthening_velocity": _corr(vel[:, j], along, np.nan),
            }
    dt = min(t.frame_interval_s for t in trials)
    lags = np.arange(-int(round(XCORR_MAX_LAG_S / dt)), int(round(XCORR_MAX_LAG_S / dt)) + 1)
    xc = np.zeros((lags.size, len(data.coordinates)))
    for t in trials:
        d = design(data, t, {Effect.EMD: {"delay_total_s": 0.0}})
        y = d.y.reshape(t.n, -1)
        m = d.fixed.reshape(t.n, -1)
        for k, lag in enumerate(lags):  # torque at t against the EMG-implied torque at t - lag
            a, b = (y[lag:], m[: t.n - lag]) if lag >= 0 else (y[: t.n + lag], m[-lag:])
            for n in range(y.shape[1]):
                xc[k, n] += _corr(a[:, n], b[:, n]) / len(trials)
    out["xcorr"] = {
        "lag_s": (lags * dt).tolist(),
        "corr": xc.T.tolist(),
        "peak_lag_s": [float(lags[int(np.argmax(xc[:, n]))] * dt) for n in range(xc.shape[1])],
    }
    return out


def _rms(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x**2))) if x.size else float("nan")


def activation_gaps(
    pack: PackLike,
    profile: SubjectProfile,
    trials: list[TrialData],
    groups: list[str],
    delay_s: float,
    progress: Progress | None = None,
) -> dict:
    """RMS of (estimated activation (``proposed``) - EMG envelope delayed by ``delay_s``) per EMG group, pooled over
    the trials, plus the activations themselves for plots."""
    from msk_core.estimate.pipeline import estimate_trial

    diffs: dict[str, list[np.ndarray]] = {g: [] for g in groups}
    for t in trials:
        est = estimate_trial(pack, t, "proposed", subject=profile, progress=progress)
        for g in groups:
            e = np.interp(t.time - delay_s, t.time, t.emg[g])
            diffs[g].append(est.activations[:, list(pack.groups).index(g)] - e)
    per = {g: _rms(np.concatenate(v)) for g, v in diffs.items()}
    return {"per_group": per, "rms": _rms(np.concatenate([np.concatenate(v) for v in diffs.values()]))}


@dataclass
class DiscrepancyResult:
    data: SessionArrays
    selection: Selection
    profile_with_effects: SubjectProfile | None
    summary: dict
    relations_before: dict
    relations_after: dict
    extra: dict = field(default_factory=dict)


def _score_dict(s) -> dict:
    return {
        "effect": s.name.value,
        "parameters": s.parameters,
        "holdout_mse_reduction": round(s.reduction, 5),
        "holdout_gap_rms": round(float(np.sqrt(s.holdout_mse)), 6),
        "delta_bic_train": round(s.delta_bic_train, 2),
        "minus2_ln_lr_holdout": round(s.minus2_ln_lr_holdout, 2),
        "holdout_bic": round(s.holdout_bic, 2),
        "n_params": s.fit.n_params,
        "accepted": s.accepted,
        "reason": s.reason,
        "tau_frames": {k: round(v, 2) for k, v in s.extra.items() if k.startswith("tau_")},
        "recalibrated": bool(s.extra.get("recalibrated", False)),
        "left_out_training_trials": {
            k: {"reduction": round(r, 5), "minus2_ln_lr": round(lr, 2)} for k, (r, lr) in s.left_out_reductions.items()
        },
        "holdout_reps": _rep_summary(s.rep_reductions),
    }


def _rep_summary(per_rep: list[tuple[str, int, float]]) -> dict:
    """How consistently a candidate helps: of the held-out reps, how many it improves (unexplained fraction of the
    rep's frames lower than the base model's), the median and lowest reduction, the frames between reps (pooled over
    the trials' set-up and rests), and each rep's (rep -1: between reps)."""
    red = np.array([x for _, r, x in per_rep if r >= 0])
    between = [x for _, r, x in per_rep if r < 0]
    return {
        "reps": int(red.size),
        "improved": int(np.sum(red > 0)),
        "median_reduction": round(float(np.median(red)), 5) if red.size else None,
        "min_reduction": round(float(red.min()), 5) if red.size else None,
        "between_reps_reduction": round(float(np.median(between)), 5) if between else None,
        "per_rep": [{"trial": t, "rep": r, "reduction": round(x, 5)} for t, r, x in per_rep],
    }


def _evidence(sel: Selection, tr: list[TrialArrays], ho: list[TrialArrays]) -> dict[str, Any]:
    """The profile's record (JSON) of how the effects were found: trials, criterion, gaps and the greedy steps."""
    return {
        "created_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "training_trials": [t.path for t in tr],
        "holdout_trials": [t.path for t in ho],
        "criterion": {
            "min_holdout_mse_reduction": MIN_REDUCTION,
            "bic_margin": BIC_MARGIN,
            "minus2_ln_lr_holdout": "-2 ln LR on the held-out trials (no parameter penalty), < -bic_margin",
            "left_out_training_trials": "with several training trials, none left out of the fit may "
            "favour the base model by -2 ln LR > bic_margin",
            "rank": "of those that pass, the lowest held-out BIC (-2 ln LR + extra parameters x ln N_eff)",
        },
        "gap_before_rms": float(np.sqrt(sel.gap_before_mse)),
        "gap_after_rms": float(np.sqrt(sel.gap_after_mse)),
        "steps": [[_score_dict(s) for s in step[:3]] for step in sel.steps],
    }


def _profile_with_effects(
    profile: SubjectProfile,
    data: SessionArrays,
    after_fit: Fit,
    recalibrator: Recalibrator | None,
    evidence: dict[str, Any],
    recalibrated: bool,
) -> tuple[SubjectProfile, dict]:
    """A copy of ``profile`` with the named effects (and, when ``recalibrated``, the strengths of the calibration with
    the named torque terms in it, recorded in ``evidence``), and its effects section."""
    profile_out = copy.deepcopy(profile)
    if recalibrated:
        evidence["recalibrated"] = {
            "f_max_before": [round(float(x), 4) for x in data.f_max],
            "calibration": recalibrator.report(after_fit.model) if recalibrator else None,
        }
        profile_out.f_max = np.asarray(after_fit.f_max, dtype=float).copy()
    effects = effects_section(data, after_fit, evidence)
    profile_out.effects = effects
    return profile_out, effects


def _torque_summary(
    data: SessionArrays,
    profile: SubjectProfile,
    sel: Selection,
    named: list[str],
    effects: dict,
    evidence: dict[str, Any],
    tr: list[TrialArrays],
    ho: list[TrialArrays],
) -> dict:
    """The summary of the torque side: the named effect(s) and parameters, the held-out gaps before and after (in
    total and per coordinate), the candidates and greedy steps, and what the session held."""
    per_c_before = np.sqrt(np.mean(np.vstack([gaps(data, t, sel.none_fit) for t in ho]) ** 2, axis=0))
    per_c_after = np.sqrt(np.mean(np.vstack([gaps(data, t, sel.final_fit) for t in ho]) ** 2, axis=0))
    return {
        "effect": "none" if not named else (named[0] if len(named) == 1 else named),
        "parameters": {}
        if not named
        else (
            effects["effects"][0]["parameters"]
            if len(named) == 1
            else {e["name"]: e["parameters"] for e in effects["effects"]}
        ),
        "gap_before": float(np.sqrt(sel.gap_before_mse)),
        "gap_after": float(np.sqrt(sel.gap_after_mse)),
        "gap_units": "RMS held-out torque gap, fraction of each coordinate's muscle torque capacity at the pose",
        "gap_per_coordinate": {
            c: {"before": float(b), "after": float(a)} for c, b, a in zip(data.coordinates, per_c_before, per_c_after)
        },
        "candidates": [_score_dict(s) for s in sel.steps[0]] if sel.steps else [],
        "greedy_steps": [[_score_dict(s) for s in step] for step in sel.steps],
        "criterion": evidence["criterion"],
        "autocorrelation_frames": sel.autocorrelation_frames,
        "training_trials": evidence["training_trials"],
        "holdout_trials": evidence["holdout_trials"],
        "emg_groups": data.emg_groups,
        "calibration_at_bounds": calibration_at_bounds(data, profile),
        "frames": {"training": int(sum(t.n for t in tr)), "holdout": int(sum(t.n for t in ho))},
        "frames_left_out": {t.name: t.left_out for t in tr + ho if t.left_out},
    }


def _recalibrated_summary(data: SessionArrays, profile_out: SubjectProfile, evidence: dict[str, Any]) -> dict:
    """The groups whose calibrated strength moved by more than 1 %, and the torque terms that calibration fitted
    alongside the strengths (N·m per unit of each term)."""
    out: dict[str, Any] = {
        "recalibrated_strengths": {
            g: {"before": float(b), "after": float(a)}
            for g, b, a in zip(data.groups, data.f_max, profile_out.f_max)
            if abs(a / b - 1.0) > 0.01
        }
    }
    terms = ((evidence["recalibrated"].get("calibration") or {}).get("torque_basis")) or {}
    if terms:
        out["recalibrated_torque_terms"] = {k: float(v) for k, v in terms.items()}
    return out


def _activation_summary(
    pack: PackLike,
    profile: SubjectProfile,
    profile_out: SubjectProfile | None,
    holdout: list[TrialData],
    data: SessionArrays,
    after_fit: Fit,
    progress: Progress | None,
) -> dict:
    """The held-out activation gaps (RMS and per EMG group) before and after, with each model's delay."""
    held = [t for t in holdout if not t.isometric]
    d0 = data.base_delay_s
    d1 = after_fit.model.get(Effect.EMD, {}).get("delay_total_s", d0)
    before = activation_gaps(pack, profile, held, data.emg_groups, d0, progress)
    after = activation_gaps(pack, profile_out, held, data.emg_groups, d1, progress) if profile_out else before
    return {
        "activation_gap_before": before["rms"],
        "activation_gap_after": after["rms"],
        "activation_gap_per_group": {
            g: {"before": before["per_group"][g], "after": after["per_group"][g]} for g in data.emg_groups
        },
    }


def run_discrepancy(
    pack: PackLike,
    profile: SubjectProfile,
    train: list[TrialData],
    holdout: list[TrialData],
    *,
    max_effects: int = 1,
    activation: bool = True,
    progress: Progress | None = None,
    recalibrate: bool = False,
) -> DiscrepancyResult:
    """``recalibrate``: fit the torque-term candidates with a calibration of the training trials that has their torque
    in it (recalibrate.py); False: every candidate with the profile's strengths."""
    check_inputs(train, holdout, MAX_DELAY_S)
    data = session_arrays(pack, profile, train + holdout)
    n_train = len([t for t in train if not t.isometric])
    tr, ho = data.trials[:n_train], data.trials[n_train:]
    recalibrator = Recalibrator(pack, profile, train, data.base_delay_s) if recalibrate else None
    sel = select_effects(data, tr, ho, max_effects=max_effects, progress=progress, recalibrator=recalibrator)
    before_fit, after_fit = sel.none_fit, sel.final_fit
    named = [e.value for e in sel.named]
    evidence = _evidence(sel, tr, ho)
    profile_out = None
    effects: dict = {}  # the profile's effects section, when an effect is named
    recalibrated = after_fit.f_max is not None and not np.array_equal(after_fit.f_max, data.f_max)
    if named:
        profile_out, effects = _profile_with_effects(profile, data, after_fit, recalibrator, evidence, recalibrated)
    summary = _torque_summary(data, profile, sel, named, effects, evidence, tr, ho)
    summary["recalibrate"] = bool(recalibrate)
    if profile_out is not None:
        summary["strength_gain"] = effects["strength_gain"]
        if recalibrated:
            summary.update(_recalibrated_summary(data, profile_out, evidence))
    if activation:
        summary.update(_activation_summary(pack, profile, profile_out, holdout, data, after_fit, progress))
    return DiscrepancyResult(
        data=data,
        selection=sel,
        profile_with_effects=profile_out,
        summary=summary,
        relations_before=relations(data, ho, before_fit),
        relations_after=relations(data, ho, after_fit),
    )
