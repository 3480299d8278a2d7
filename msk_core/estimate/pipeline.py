"""Offline workflows over whole trials: priors, calibration of a subject, estimation of a trial."""

from __future__ import annotations

import datetime as _dt
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from enum import Enum
from pathlib import Path

import numpy as np

from msk_core.errors import EstimationError
from msk_core.estimate.calibrate import CalibrationFrames, CalibrationResult, CalibrationSettings, calibrate
from msk_core.estimate.emd import estimate_emd, shift_emg
from msk_core.estimate.frame import FrameEstimator, Method
from msk_core.estimate.mechanics import min_effort_of
from msk_core.estimate.pack import PackLike
from msk_core.estimate.phase import LivePhase, PhaseModel, learn_phase_model
from msk_core.estimate.prior import PhasePrior, fill_empty_bins, fit_phase_prior, phase_bins
from msk_core.estimate.profile import SubjectProfile
from msk_core.estimate.trial import TrialData
from msk_core.progress import Progress, counted


class NoEmgPrior(str, Enum):
    """Prior of a group without EMG (see docs/estimation.md, "Groups without EMG")."""

    MIN_EFFORT = "min_effort"  # static optimisation's share of the calibration torques, binned like EMG (default)
    SYNERGIST = "synergist"  # the prior of the measured group with the most similar moment arms; else min effort
    WIDE = "wide"  # N(0, 0.5^2): nearly free (the first version; lets unmeasured groups soak up the torque)


class NoEmgStrength(str, Enum):
    """Strength of a group without EMG in the profile (see docs/estimation.md, "Groups without EMG")."""

    REFERENCE = "reference"  # the pack's reference F_max (default)
    # the measured groups' common calibrated factor (geometric median): the envelopes of one recording share their
    # normalisation, which the calibrated factors carry; the minimal-effort prior re-derived at those strengths
    MEASURED = "measured"
    # the calibrated factor of the measured group with the most similar moment arms (cosine >= SYNERGIST_MIN_COSINE,
    # :func:`pick_synergists`: a muscle of the same function at the same joints, recorded with the same electrodes and
    # normalisation), else the measured groups' common factor; the minimal-effort prior re-derived at those strengths
    SYNERGIST = "synergist"


#: phase bins of the prior per movement cycle, by default
PRIOR_BINS = 20


@dataclass(frozen=True)
class PriorSettings:
    """How :func:`build_prior` learns the N(mu, sigma^2) prior: ``n_bins`` phase bins per movement cycle; the prior of
    groups without EMG, first from ``synergists`` (unmeasured group -> the measured group whose prior it takes), then
    by ``no_emg``. Checked when made; ``no_emg`` may be given by its value ("wide")."""

    n_bins: int = PRIOR_BINS
    no_emg: NoEmgPrior = NoEmgPrior.MIN_EFFORT
    # a copy of the mapping given (a plain dict: the settings pickle and copy; their hash leaves it out)
    synergists: Mapping[str, str] = field(default_factory=dict, hash=False)

    def __post_init__(self) -> None:
        if isinstance(self.n_bins, bool) or not isinstance(self.n_bins, int) or self.n_bins < 2:
            raise EstimationError(
                f"the prior needs a whole number of at least 2 phase bins, got n_bins={self.n_bins!r}"
            )
        try:
            object.__setattr__(self, "no_emg", NoEmgPrior(self.no_emg))
        except ValueError:
            known = ", ".join(p.value for p in NoEmgPrior)
            raise EstimationError(f"no_emg must be one of {known}, got {self.no_emg!r}") from None
        object.__setattr__(self, "synergists", {str(u): str(m) for u, m in dict(self.synergists).items()})

    def __str__(self) -> str:
        """As a reader names it, e.g. ``prior synergist`` (``, 10 bins``, ``, synergists g3=g0`` when not the
        default)."""
        text = f"prior {self.no_emg.value}" + (f", {self.n_bins} bins" if self.n_bins != PRIOR_BINS else "")
        return text + (
            ", synergists " + " ".join(f"{u}={m}" for u, m in self.synergists.items()) if self.synergists else ""
        )


SYNERGIST_MIN_COSINE = 0.9  # moment-arm similarity a measured group needs to stand in for an unmeasured one


def build_prior(pack: PackLike, trials: list[TrialData], prior_settings: PriorSettings | None = None) -> PhasePrior:
    """N(mu, sigma^2) per group and phase bin across all reps of all trials (:class:`PriorSettings`; default ones
    when None).

    Groups with EMG: from their normalised envelopes. Groups without: the settings' ``synergists`` (unmeasured ->
    measured group) first, then ``no_emg``: the minimal-effort (``so``) activation over the same reps, a measured
    synergist, or the wide default. Isometric trials are left out: they have no phase, and their contractions are
    not the rest between reps either.
    """
    isometric = [t.name for t in trials if t.isometric]
    trials = [t for t in trials if not t.isometric]
    groups = list(pack.groups)
    ps = prior_settings or PriorSettings()
    n_bins, no_emg = ps.n_bins, ps.no_emg
    emg_groups = _prior_emg_groups(trials, isometric)
    synergists, missing = _prior_synergists(pack, trials, emg_groups, ps.synergists, no_emg)
    effort = missing if no_emg is not NoEmgPrior.WIDE else []
    emg, phases, reps = _prior_samples(pack, trials, emg_groups, effort)
    prior = fit_phase_prior(groups, emg, phases, reps, n_bins=n_bins)
    mean, std = prior.mean.copy(), prior.std.copy()
    rest_mean = None if prior.rest_mean is None else prior.rest_mean.copy()
    rest_std = None if prior.rest_std is None else prior.rest_std.copy()
    sources = []
    for j, g in enumerate(groups):
        if g in emg_groups:
            sources.append("emg")
        elif g in synergists:
            k = groups.index(synergists[g])
            mean[:, j], std[:, j] = mean[:, k], std[:, k]
            if rest_mean is not None and rest_std is not None:  # both or neither
                rest_mean[j], rest_std[j] = rest_mean[k], rest_std[k]
            sources.append(f"synergist:{synergists[g]}")
        else:
            sources.append("min_effort" if g in effort else "default")
    torque, load_newton = training_torque(trials, n_bins)
    return PhasePrior(
        groups=tuple(groups),
        mean=mean,
        std=std,
        has_emg=np.array([g in emg_groups for g in groups]),
        rest_mean=rest_mean,
        rest_std=rest_std,
        sources=tuple(sources),
        torque=torque,
        load_newton=load_newton,
    )


def training_torque(trials: list[TrialData], n_bins: int) -> tuple[np.ndarray | None, float | None]:
    """(mean |torque| per phase bin and coordinate over the reps of ``trials``, their mean hand load in N) that the
    prior was learned at (:class:`msk_core.estimate.prior.LoadScale`); (None, None) without a rep. The bins are the
    prior's; a bin no rep reached takes its neighbours' value."""
    in_reps = [(t, t.rep_index >= 0) for t in trials]
    frames = sum(int(m.sum()) for _, m in in_reps)
    if not frames:
        return None, None
    tau = np.concatenate([np.abs(t.torques[m]) for t, m in in_reps])
    phase = np.concatenate([t.phase[m] for t, m in in_reps])
    bins = phase_bins(phase, n_bins)
    count = np.bincount(bins, minlength=n_bins).astype(float)
    torque = np.full((n_bins, tau.shape[1]), np.nan)
    filled = count > 0
    for n in range(tau.shape[1]):
        torque[filled, n] = np.bincount(bins, weights=tau[:, n], minlength=n_bins)[filled] / count[filled]
        torque[:, n] = fill_empty_bins(torque[:, n])
    load = sum(t.hand_load_newton * int(m.sum()) for t, m in in_reps) / frames
    return torque, float(load)


def _prior_emg_groups(trials: list[TrialData], isometric: list[str]) -> list[str]:
    """The groups with EMG in the trials with reps (sorted); refused when there are none or no trial has a rep."""
    emg_groups = sorted({g for t in trials for g in t.emg})
    if not emg_groups:
        raise EstimationError(
            f"the trials ({', '.join(t.name for t in trials) or 'none'}) have no EMG: the prior needs EMG of at least "
            "one group in a trial with reps"
            + (f" (isometric trials have no phase: {', '.join(isometric)})" if isometric else "")
        )
    if not any(np.any(t.rep_index >= 0) for t in trials):
        raise EstimationError(
            "no trial has a complete repetition: the prior is learned per phase of the reps ("
            + "; ".join(f"{t.name}: {t.extra.get('no_reps', 'no reps')}" for t in trials)
            + ")"
        )
    return emg_groups


def _prior_synergists(
    pack: PackLike,
    trials: list[TrialData],
    emg_groups: list[str],
    synergists: Mapping[str, str],
    no_emg: NoEmgPrior,
) -> tuple[dict[str, str], list[str]]:
    """(unmeasured -> measured group: the given ones checked, then picked ones for ``no_emg=synergist``; the groups
    still without EMG or synergist)."""
    groups = list(pack.groups)
    synergists = dict(synergists)
    for g, h in synergists.items():
        if g not in groups or h not in emg_groups:
            raise EstimationError(
                f"synergist {g!r} -> {h!r}: the first must be a pack group, the second a group with EMG "
                f"(groups with EMG: {emg_groups})"
            )
    missing = [g for g in groups if g not in emg_groups and g not in synergists]
    if no_emg is NoEmgPrior.SYNERGIST and missing:
        synergists.update(pick_synergists(pack, trials, missing, emg_groups))
        missing = [g for g in missing if g not in synergists]
    return synergists, missing


def _prior_samples(
    pack: PackLike, trials: list[TrialData], emg_groups: list[str], effort: list[str]
) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """(group -> activation samples over all trials' frames: EMG (NaN where a trial lacks it), or the minimal-effort
    activation for the ``effort`` groups; phases; rep numbers made distinct across trials, -1 between reps)."""
    groups = list(pack.groups)
    phases: list[np.ndarray] = []
    reps: list[np.ndarray] = []
    emg: dict[str, list[np.ndarray]] = {g: [] for g in emg_groups + effort}
    offset = 0
    for t in trials:
        phases.append(t.phase)
        reps.append(np.where(t.rep_index >= 0, t.rep_index + offset, -1))
        offset += int(t.rep_index.max()) + 1
        for g in emg_groups:
            emg[g].append(t.emg.get(g, np.full(t.n_frames, np.nan)))
        if effort:
            so = t.mechanics(pack).min_effort
            for g in effort:
                emg[g].append(so[:, groups.index(g)])
    return {g: np.concatenate(v) for g, v in emg.items()}, np.concatenate(phases), np.concatenate(reps)


def pick_synergists(
    pack: PackLike, trials: list[TrialData], unmeasured: list[str], measured: list[str]
) -> dict[str, str]:
    """Unmeasured group -> the measured group whose moment arms over the trials' frames are the most similar
    (cosine of the stacked (frames x coordinates) columns, at least ``SYNERGIST_MIN_COSINE``); ties go to the first."""
    return _most_similar(moment_arm_cosines(pack, trials), list(pack.groups), unmeasured, measured)


def _most_similar(cos: np.ndarray, groups: list[str], unmeasured: list[str], measured: list[str]) -> dict[str, str]:
    """:func:`pick_synergists` from the groups' moment-arm cosines (:func:`moment_arm_cosines`)."""
    picked = {}
    for g in unmeasured:
        row = [float(cos[groups.index(g), groups.index(h)]) for h in measured]
        best = int(np.argmax(row))  # first of equals
        if row[best] >= SYNERGIST_MIN_COSINE:
            picked[g] = measured[best]
    return picked


def moment_arm_cosines(pack: PackLike, trials: list[TrialData]) -> np.ndarray:
    """(G, G) cosines between the groups' moment arms stacked over the trials' frames and coordinates (frames with a
    non-finite moment arm left out)."""
    arms = np.concatenate([t.mechanics(pack).moment_arms for t in trials])
    r = arms[np.all(np.isfinite(arms), axis=(1, 2))]  # (T, n_c, G)
    cols = r.transpose(2, 0, 1).reshape(len(pack.groups), -1)
    norm = np.linalg.norm(cols, axis=1)
    return (cols @ cols.T) / np.maximum(np.outer(norm, norm), 1e-300)


def profile_synergists(pack: PackLike, trials: list[TrialData], prior: PhasePrior) -> dict[str, str]:
    """Group without EMG -> its measured synergist (:func:`pick_synergists` over the trials with reps), stored in the
    profile: ``assisted`` lets such a group follow its synergist's live envelope (docs/estimation.md, "Live EMG and
    `assisted`")."""
    groups = list(pack.groups)
    moving = [t for t in trials if not t.isometric]
    measured = [g for g, m in zip(groups, prior.has_emg) if m]
    unmeasured = [g for g, m in zip(groups, prior.has_emg) if not m]
    if not moving or not measured or not unmeasured:
        return {}
    return pick_synergists(pack, moving, unmeasured, measured)


def synergist_error(pack: PackLike, trials: list[TrialData]) -> float:
    """RMS of (EMG - gain x the envelope of its measured synergist) over the measured groups that have one among the
    other measured groups (:func:`pick_synergists`) and the frames inside reps; gain: the ratio of the two envelopes'
    means there. How far "a muscle of the same action has the same drive, at its own level" is from the envelopes
    where it can be checked, as :func:`min_effort_error` is for minimal effort (NaN without a measured pair)."""
    moving = [t for t in trials if not t.isometric and t.emg]
    measured = sorted({g for t in moving for g in t.emg})
    if len(measured) < 2:
        return float("nan")
    groups, cos = list(pack.groups), moment_arm_cosines(pack, moving)  # once for every measured group
    diffs = []
    for g in measured:
        picked = _most_similar(cos, groups, [g], [h for h in measured if h != g])
        if g not in picked:
            continue
        diffs.append(_scaled_difference(moving, g, picked[g]))
    d = np.concatenate(diffs) if diffs else np.zeros(0)
    return float(np.sqrt(np.mean(d**2))) if d.size else float("nan")


def synergist_errors(pack: PackLike, trials: list[TrialData]) -> dict[str, float]:
    """Per measured group h with measured synergists (the other measured groups whose moment arms have a cosine of at
    least ``SYNERGIST_MIN_COSINE`` with h's): the RMS of (their EMG - gain x h's envelope) inside reps, gain the ratio
    of the envelopes' means. How well h's envelope stands for the muscles of its action in these trials, the error
    ``assisted`` with live synergists gives h as the source of a group without EMG (else :func:`synergist_error`)."""
    moving = [t for t in trials if not t.isometric and t.emg]
    measured = sorted({g for t in moving for g in t.emg})
    if len(measured) < 2:
        return {}
    groups = list(pack.groups)
    cos = moment_arm_cosines(pack, moving)
    out = {}
    for h in measured:
        partners = [g for g in measured if g != h and cos[groups.index(g), groups.index(h)] >= SYNERGIST_MIN_COSINE]
        d = np.concatenate([_scaled_difference(moving, g, h) for g in partners]) if partners else np.zeros(0)
        if d.size:
            out[h] = float(np.sqrt(np.mean(d**2)))
    return out


def _scaled_difference(trials: list[TrialData], g: str, h: str) -> np.ndarray:
    """EMG of g - (mean g / mean h) x EMG of h over the frames inside reps where both are finite."""
    pairs = [(t.emg[g][t.rep_index >= 0], t.emg[h][t.rep_index >= 0]) for t in trials if g in t.emg and h in t.emg]
    if not pairs:
        return np.zeros(0)
    e_g, e_h = np.concatenate([p[0] for p in pairs]), np.concatenate([p[1] for p in pairs])
    ok = np.isfinite(e_g) & np.isfinite(e_h)
    if ok.sum() < 2 or not np.mean(e_h[ok]) > 0:
        return np.zeros(0)
    return e_g[ok] - np.mean(e_g[ok]) / np.mean(e_h[ok]) * e_h[ok]


def _none_if_nan(x: float) -> float | None:
    return None if not np.isfinite(x) else float(x)


def trial_phase(trial: TrialData, i: int) -> float:
    """Phase of frame i: in [0, 1) inside a rep, REST_PHASE between reps."""
    return float(trial.phase[i])


def min_effort_error(pack: PackLike, trials: list[TrialData]) -> float:
    """RMS of (EMG - static optimisation's activation) over the measured groups and the frames inside reps: how far
    the minimal-effort hypothesis is from activations where it can be checked (NaN without any such frame)."""
    groups = list(pack.groups)
    diffs = []
    for t in trials:
        if not t.emg or t.isometric:
            continue
        so = t.mechanics(pack).min_effort
        inside = t.rep_index >= 0
        for g, e in t.emg.items():
            d = (e - so[:, groups.index(g)])[inside]
            diffs.append(d[np.isfinite(d)])
    d = np.concatenate(diffs) if diffs else np.zeros(0)
    return float(np.sqrt(np.mean(d**2))) if d.size else float("nan")


def unmeasured_from_measured(
    pack: PackLike,
    trials: list[TrialData],
    prior: PhasePrior,
    result: CalibrationResult,
    mode: NoEmgStrength | str = NoEmgStrength.MEASURED,
) -> tuple[np.ndarray, PhasePrior]:
    """(F_max, prior) of the profile with ``NoEmgStrength.MEASURED``: every group without EMG gets the measured
    groups' common calibrated factor (geometric median of their scale factors) and the groups whose prior is the
    minimal-effort share get it re-derived by static optimisation at these strengths (binned as before). The envelopes
    of one recording are normalised alike and the calibrated factors carry that normalisation (docs/estimation.md:
    envelopes peaking near 0.35 of the recording's maximum give extensor factors at 2.5); a group without EMG at the
    reference strength is then estimated on another scale than the envelopes it is compared with. ``mode``
    ``NoEmgStrength.SYNERGIST``: a group with a measured synergist (:func:`pick_synergists`) takes that group's factor
    instead of the common one."""
    f_ref = np.asarray(pack.f_max_ref, dtype=float)
    measured = np.asarray(prior.has_emg, dtype=bool)
    f_max = np.asarray(result.f_max, dtype=float).copy()
    if not np.any(measured) or np.all(measured):
        return f_max, prior
    common = float(np.exp(np.median(np.log(result.scale[measured]))))
    f_max[~measured] = common * f_ref[~measured]
    groups = list(pack.groups)
    if NoEmgStrength(mode) is NoEmgStrength.SYNERGIST:
        unmeasured = [g for g, m in zip(groups, measured) if not m]
        picked = pick_synergists(pack, trials, unmeasured, [g for g, m in zip(groups, measured) if m])
        for g, h in picked.items():
            f_max[groups.index(g)] = result.scale[groups.index(h)] * f_ref[groups.index(g)]
    effort = [g for g, src in zip(groups, prior.sources or ()) if src == "min_effort"]
    if not effort:
        return f_max, prior
    series: dict[str, list[np.ndarray]] = {g: [] for g in effort}
    phases, reps, offset = [], [], 0
    for t in trials:
        if t.isometric:
            continue
        so = min_effort_of(pack, t.mechanics(pack).moment_arms, t.torques, f_max=f_max)
        for g in effort:
            series[g].append(so[:, groups.index(g)])
        phases.append(t.phase)
        reps.append(np.where(t.rep_index >= 0, t.rep_index + offset, -1))
        offset += int(t.rep_index.max()) + 1
    refit = fit_phase_prior(
        groups,
        {g: np.concatenate(v) for g, v in series.items()},
        np.concatenate(phases),
        np.concatenate(reps),
        n_bins=prior.n_bins,
    )
    cols = [groups.index(g) for g in effort]
    mean, std = prior.mean.copy(), prior.std.copy()
    mean[:, cols], std[:, cols] = refit.mean[:, cols], refit.std[:, cols]
    rest_mean, rest_std = prior.rest_mean, prior.rest_std
    if rest_mean is not None and rest_std is not None and refit.rest_mean is not None and refit.rest_std is not None:
        rest_mean, rest_std = rest_mean.copy(), rest_std.copy()
        rest_mean[cols], rest_std[cols] = refit.rest_mean[cols], refit.rest_std[cols]
    return f_max, replace(prior, mean=mean, std=std, rest_mean=rest_mean, rest_std=rest_std)


def calibration_frames(
    pack: PackLike,
    trials: list[TrialData],
    prior: PhasePrior,
    *,
    min_effort_std: float = 0.0,
    torque_basis: TorqueBasis | None = None,
    force_scale: Callable[[TrialData], np.ndarray] | None = None,
) -> CalibrationFrames:
    """Stacked training frames; frames outside any rep carry no prior term (std = inf). ``min_effort_std`` widens
    the prior of groups whose prior is the minimal-effort share (their activation nobody measured) by the error
    that hypothesis shows on the measured groups (:func:`min_effort_error`), added in quadrature: the across-rep
    spread of a deterministic static-optimisation solution says nothing about how wrong it is, and an overconfident
    prior on them makes the calibration credit the measured groups' strength with information it does not have."""
    groups = list(pack.groups)
    widen = np.array([s == "min_effort" for s in (prior.sources or ("",) * len(groups))]) * (min_effort_std or 0.0)
    r, tau, mu, sd, emg, basis = [], [], [], [], [], []
    for t in trials:
        target = isometric_target(t) if t.isometric else None
        z = None if torque_basis is None else torque_basis.columns(t)
        phi = None if force_scale is None else force_scale(t)
        arms = t.mechanics(pack).moment_arms
        for i in range(t.n_frames):
            m = arms[i]
            if not (np.all(np.isfinite(m)) and np.all(np.isfinite(t.torques[i]))):
                continue  # frames the model cannot represent do not enter the fit
            if phi is not None:
                m = m * phi[i]
            if z is not None:
                basis.append(z[i])
            if t.isometric:
                a, b = isometric_cocontraction_prior(t, i, groups, m, target)
            elif t.rep_index[i] >= 0:
                a, b = prior.at(float(t.phase[i]))
                b = np.sqrt(b**2 + widen**2)
            else:  # the prior is a distribution across reps: between reps only torque and the trial's EMG count
                a, b = np.zeros(len(groups)), np.full(len(groups), np.inf)
            r.append(m)
            tau.append(t.torques[i])
            mu.append(a)
            sd.append(b)
            emg.append([t.emg[g][i] if g in t.emg else np.nan for g in groups])
    if not r:
        raise EstimationError("no usable calibration frame")
    stacked = (np.array(r), np.array(tau), np.array(mu), np.array(sd), np.array(emg, dtype=float))
    if torque_basis is None:
        return CalibrationFrames(*stacked)
    return CalibrationFrames(
        *stacked,
        torque_basis=np.array(basis),
        torque_basis_lower=torque_basis.lower,
        torque_basis_names=tuple(torque_basis.names),
    )


@dataclass(frozen=True)
class TorqueBasis:
    """Torque the muscles' activations do not produce, linear in coefficients the calibration fits: ``columns(trial)``
    gives (T, n_c, p) N·m per unit coefficient on every frame of a trial, ``lower`` the coefficients' lower bounds."""

    columns: Callable[[TrialData], np.ndarray]
    lower: np.ndarray
    names: tuple[str, ...]


ISOMETRIC_COCONTRACTION_STD = (
    0.05  # added in quadrature to the measured groups' spread (an unmeasured group is not one of them)
)
ISOMETRIC_MIN_SITES = 3  # non-target sites with EMG needed to say how the others co-contract


def isometric_target(trial: TrialData) -> str | None:
    """The group an isometric trial contracts maximally: the one whose EMG peaks highest (None without EMG)."""
    peaks = {g: float(np.nanmax(e)) for g, e in trial.emg.items() if np.any(np.isfinite(e))}
    return max(peaks, key=peaks.__getitem__) if peaks else None


def isometric_cocontraction_prior(
    trial: TrialData, i: int, groups: list[str], moment_arms: np.ndarray | None = None, target: str | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Prior of frame i of an isometric trial for the groups without EMG in it: N(median, s^2) of the other sites'
    EMG in that frame (the target, ``isometric_target``, left out), s^2 = (1.4826 MAD)^2 + ISOMETRIC_COCONTRACTION_STD^2:
    they co-contract like the measured non-target sites. None (std = inf) for groups with EMG (their EMG decides);
    for a synergist of the target (moment arms at the pose, ``moment_arms`` (n_c, G), with cosine >=
    ``SYNERGIST_MIN_COSINE``: another head of the same muscle may push maximally with it, so its activation is not
    known); and for everyone when fewer than ``ISOMETRIC_MIN_SITES`` non-target sites are recorded (nothing to say
    how the others co-contract). Without a prior a free unmeasured group soaks up torque and the target's strength
    is then reported as not identified rather than confidently wrong."""
    target = isometric_target(trial) if target is None else target
    e = np.array([trial.emg[g][i] for g in trial.emg if g != target], dtype=float)
    e = e[np.isfinite(e)]
    mean = np.zeros(len(groups))
    std = np.full(len(groups), np.inf)
    if e.size < ISOMETRIC_MIN_SITES:
        return mean, std
    centre = float(np.median(e))
    spread = 1.4826 * float(np.median(np.abs(e - centre)))
    t = groups.index(target) if target in groups else None
    for j, g in enumerate(groups):
        if g in trial.emg:
            continue
        if moment_arms is not None and t is not None:
            a, b = moment_arms[:, j], moment_arms[:, t]
            if float(a @ b) >= SYNERGIST_MIN_COSINE * max(float(np.linalg.norm(a) * np.linalg.norm(b)), 1e-300):
                continue
        mean[j], std[j] = max(centre, 0.0), float(np.hypot(spread, ISOMETRIC_COCONTRACTION_STD))
    return mean, std


@dataclass(frozen=True)
class CalibrationInputs:
    """What a calibration of a set of trials needs before its NLP, and does not change with a torque basis or a
    force scale: the trials with their EMG shifted by the delay, the prior learned from them, and the minimal-effort
    error (:func:`calibration_inputs`). A re-calibration of the same trials with other terms reuses it."""

    trials: list[TrialData]
    prior: PhasePrior
    min_effort_error: float  # NaN when no group's prior is the minimal-effort share
    emd: dict


def calibration_inputs(
    pack: PackLike,
    trials: list[TrialData],
    *,
    prior_settings: PriorSettings | None = None,
    emd_s: float | str | None = "auto",
) -> CalibrationInputs:
    """The delay (``emd_s``, as in :func:`calibrate_subject`) applied to the trials' EMG, then the prior and the
    minimal-effort error."""
    if not trials:
        raise EstimationError("calibration needs at least one trial")
    if all(t.isometric for t in trials):
        raise EstimationError(
            "calibration needs at least one trial with reps besides the isometric ones: the N(mu, sigma^2) prior per "
            f"phase of the movement is learned from reps (trials: {', '.join(t.name for t in trials)})"
        )
    if not any(t.emg for t in trials):  # said before the delay, which needs EMG too
        raise EstimationError(
            f"calibration needs EMG, and no trial has any ({', '.join(t.name for t in trials)}): give the trials an "
            "`emg` file and an [emg_map] (docs/estimation.md, 'Trial description'); static optimisation needs no EMG "
            "and no calibration: msk estimate --method so"
        )
    if emd_s == "auto":
        emd = estimate_emd(pack, trials).to_dict() | {"source": "estimated"}
    elif emd_s is None or isinstance(emd_s, (int, float)):
        if emd_s is not None and not 0 <= float(emd_s) <= 0.5:
            raise EstimationError(f"electromechanical delay must be in [0, 0.5] s, got {emd_s}")
        emd = {"delay_s": float(emd_s or 0.0), "source": "given"}
    else:
        raise EstimationError(f"emd_s must be 'auto', a delay in seconds or None, got {emd_s!r}")
    trials = [shift_emg(t, emd["delay_s"]) for t in trials]
    prior = build_prior(pack, trials, prior_settings)
    me_error = min_effort_error(pack, trials) if "min_effort" in (prior.sources or ()) else float("nan")
    return CalibrationInputs(trials=trials, prior=prior, min_effort_error=me_error, emd=emd)


def calibrate_subject(
    pack: PackLike,
    trials: list[TrialData],
    *,
    settings: CalibrationSettings | None = None,
    prior_settings: PriorSettings | None = None,
    emd_s: float | str | None = "auto",
    torque_basis: TorqueBasis | None = None,
    force_scale: Callable[[TrialData], np.ndarray] | None = None,
    start: CalibrationResult | None = None,
    no_emg_strength: NoEmgStrength | str = NoEmgStrength.REFERENCE,
) -> tuple[SubjectProfile, CalibrationResult]:
    """Prior from the trials' EMG, then the calibration NLP; returns the profile (not yet saved) and the result.

    ``emd_s``: electromechanical delay applied to the EMG before both ("auto": estimated from the trials,
    :mod:`msk_core.estimate.emd`; a number: given, seconds; None or 0: none). ``torque_basis``: torque the
    activations do not produce, its coefficients fitted with the strengths (:class:`TorqueBasis`); ``force_scale``:
    a per-frame factor on each group's active force (:func:`calibration_frames`); ``start``: a
    calibration of the same trials to start the solve from (:func:`msk_core.estimate.calibrate.calibrate`)."""
    inputs = calibration_inputs(pack, trials, prior_settings=prior_settings, emd_s=emd_s)
    return calibrate_inputs(
        pack,
        inputs,
        settings=settings,
        torque_basis=torque_basis,
        force_scale=force_scale,
        start=start,
        no_emg_strength=no_emg_strength,
    )


def calibrate_inputs(
    pack: PackLike,
    inputs: CalibrationInputs,
    *,
    settings: CalibrationSettings | None = None,
    torque_basis: TorqueBasis | None = None,
    force_scale: Callable[[TrialData], np.ndarray] | None = None,
    start: CalibrationResult | None = None,
    no_emg_strength: NoEmgStrength | str = NoEmgStrength.REFERENCE,
) -> tuple[SubjectProfile, CalibrationResult]:
    """The calibration NLP on prepared inputs (:func:`calibration_inputs`); the rest as :func:`calibrate_subject`.
    ``no_emg_strength``: F_max (and minimal-effort prior) of the groups without EMG in the profile
    (:class:`NoEmgStrength`, :func:`unmeasured_from_measured`); the NLP is the same either way."""
    trials, prior, me_error, emd = inputs.trials, inputs.prior, inputs.min_effort_error, inputs.emd
    frames = calibration_frames(
        pack,
        trials,
        prior,
        min_effort_std=0.0 if np.isnan(me_error) else me_error,
        torque_basis=torque_basis,
        force_scale=force_scale,
    )
    result = calibrate(pack.f_max_ref, frames, settings, start=start)
    f_max, profile_prior = np.asarray(result.f_max, dtype=float), prior
    if NoEmgStrength(no_emg_strength) is not NoEmgStrength.REFERENCE:
        f_max, profile_prior = unmeasured_from_measured(pack, trials, prior, result, no_emg_strength)
    phase_model = learn_trials_phase_model(pack, trials)
    norm: dict[str, dict] = {}  # per EMG channel: its normalisation and the trials it was measured in
    for t in trials:
        for ch, info in t.emg_normalisation.items():
            norm.setdefault(ch, {**info, "trials": []})["trials"].append(t.name)
    import msk_core

    profile = SubjectProfile(
        pack_name=pack.name,
        pack_version=str(pack.version),
        groups=list(pack.groups),
        f_max=f_max,
        f_max_ref=np.asarray(pack.f_max_ref, dtype=float),
        prior=profile_prior,
        emg_normalisation=norm,
        calibration={
            **result.report(list(pack.groups)),
            "frames": int(frames.torques.shape[0]),
            "min_effort_error_rms": None if np.isnan(me_error) else me_error,
            "emd": emd,
            "isometric_trials": [t.name for t in trials if t.isometric],
            "no_emg_strength": NoEmgStrength(no_emg_strength).value,
            "synergists": profile_synergists(pack, trials, profile_prior),
            "synergist_error_rms": _none_if_nan(synergist_error(pack, trials)),
            "synergist_error_by_source": synergist_errors(pack, trials),
        },
        provenance={
            "created_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "trials": [str(Path(t.path).resolve()) for t in trials],
            "software": f"msk-live {getattr(msk_core, '__version__', 'dev')}",
            "phase_signals": sorted({t.phase_signal for t in trials}),
        },
        phase_model=phase_model,
    )
    return profile, result


def learn_trials_phase_model(pack: PackLike, trials: list[TrialData]) -> PhaseModel | None:
    """Rep template on the trials' phase coordinate (None when their phase is not kinematic: nothing to track live).
    Isometric trials have no reps and are left out."""
    trials = [t for t in trials if not t.isometric]
    found = {t.phase_coordinate for t in trials}
    coordinates = {c for c in found if c is not None}
    if len(coordinates) < len(found):  # a trial whose phase is not a coordinate
        return None
    if len(coordinates) > 1:
        raise EstimationError(
            f"calibration trials define the phase on different coordinates {sorted(coordinates)}; set one "
            "phase_signal in all trial files"
        )
    (coordinate,) = coordinates
    j = list(pack.coordinates).index(coordinate)
    return learn_phase_model(coordinate, [(t.time, t.q[:, j]) for t in trials])


@dataclass
class TrialEstimate:
    method: str
    groups: list[str]
    coordinates: list[str]
    time: np.ndarray
    phase: np.ndarray
    activations: np.ndarray  # (T, G)
    activation_std: np.ndarray  # (T, G)
    model_torques: np.ndarray  # (T, n_c)
    torques: np.ndarray
    residual: np.ndarray
    status: list[str]
    iterations: np.ndarray
    solve_time_s: np.ndarray
    flag_counts: dict[str, int] = field(default_factory=dict)
    load_scale: dict | None = None  # the prior scaled to the trial's load (FrameEstimator.load_scale); None: not


def estimate_trial(
    pack: PackLike,
    trial: TrialData,
    method: Method | str,
    *,
    subject: SubjectProfile | None = None,
    progress: Progress | None = None,
    live_phase: bool = False,
    **options,
) -> TrialEstimate:
    """Run the per-frame estimator over a trial (torques from the trial). Phase: the trial's offline rep detection,
    or with ``live_phase`` the causal tracker of the subject's rep template, frame by frame as the live node does."""
    est = FrameEstimator(pack, subject, method, **options)
    tracker = LivePhase.from_profile(subject, est.coordinates) if live_phase else None
    if live_phase and tracker is None:
        raise EstimationError("live_phase needs a subject profile calibrated with a kinematic phase coordinate")
    phases = tracker.process(trial.time, trial.q) if tracker is not None else None
    g, n_c, n = len(est.groups), len(est.coordinates), trial.n_frames
    out = TrialEstimate(
        method=est.method.value,
        groups=list(est.groups),
        coordinates=list(est.coordinates),
        time=trial.time,
        phase=trial.phase if phases is None else phases,
        activations=np.zeros((n, g)),
        activation_std=np.zeros((n, g)),
        model_torques=np.zeros((n, n_c)),
        torques=np.zeros((n, n_c)),
        residual=np.zeros((n, n_c)),
        status=[],
        iterations=np.zeros(n, dtype=int),
        solve_time_s=np.zeros(n),
    )
    for i in counted(range(n), progress, f"{trial.name} [{est.method.value}] (frames)"):
        phase = float(trial.phase[i] if phases is None else phases[i])
        # with torques given no inverse dynamics runs: qd and qdd matter to a profile's effects, the load to them and
        # to the prior's load scale
        res = est.step(
            trial.q[i], trial.qd[i], trial.qdd[i], trial.hand_load_newton, torques=trial.torques[i], phase=phase
        )
        out.activations[i] = res.activations
        out.activation_std[i] = res.activation_std
        out.model_torques[i] = res.model_torques
        out.torques[i] = res.torques
        out.residual[i] = res.residual
        out.status.append(res.status.value)
        out.iterations[i] = res.iterations
        out.solve_time_s[i] = res.solve_time_s
    out.flag_counts = dict(est.flag_counts)
    out.load_scale = est.load_scale
    return out
