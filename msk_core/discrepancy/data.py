"""Per-sample arrays of a session for the discrepancy analysis: kinematics, torques, moment arms, muscle state, EMG and
the prior, all on the trials' frames, and the capacity scale c_tn = sum_g |R_tng| F_max,g (N·m, floored at 1) that
makes a torque gap a fraction of what the muscles can produce at that pose (the estimator's own residual scale)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msk_core.errors import EstimationError, InputError
from msk_core.estimate.emd import calibrated_delay
from msk_core.estimate.frame import MIN_TORQUE_SCALE
from msk_core.estimate.pack import PackLike, fibre_lengths, fitted_ranges
from msk_core.estimate.profile import SubjectProfile
from msk_core.estimate.trial import TrialData

CAPACITY_MARGIN = 0.95  # frames needing more than this share of a coordinate's capacity are left out
MIN_FRAMES = 20  # a trial with fewer frames left for the analysis is refused (nothing to fit or score)
MAX_DELAY_S = 0.2  # longest electromechanical delay searched (physiological 30-100 ms; the generator allows 200)


@dataclass
class TrialArrays:
    name: str
    path: str
    time: np.ndarray  # (T,)
    q: np.ndarray  # (T, n_c)
    qd: np.ndarray
    tau: np.ndarray  # (T, n_c) inverse-dynamics torque, N·m
    arms: np.ndarray  # (T, n_c, G) m
    lengths: np.ndarray | None  # (T, G) MTU length, m
    scale: np.ndarray  # (T, n_c) capacity c, N·m
    emg: np.ndarray  # (T, G_E) envelopes of the groups with EMG (as recorded, not yet delayed)
    prior_mean: np.ndarray  # (T, G) prior mean at each frame's phase (used for groups without EMG)
    min_effort: np.ndarray  # (T, G) static optimisation's activations of the frame's torque (demand-following share)
    tau_load: np.ndarray  # (T, n_c) the external load's part of the ID torque (ID(L) - ID(0)), N·m
    phase: np.ndarray  # (T,) REST_PHASE outside reps
    rep_index: np.ndarray  # (T,) the rep each frame belongs to, -1 outside reps
    load_kg: float
    left_out: dict[str, int]  # frames left out of the analysis, by reason (the first reason that applies)

    @property
    def n(self) -> int:
        return int(self.time.size)

    @property
    def frame_interval_s(self) -> float:
        return float(np.median(np.diff(self.time)))


@dataclass
class SessionArrays:
    groups: list[str]
    coordinates: list[str]
    emg_groups: list[str]  # groups with EMG in every trial (the others use the prior, as the estimator does)
    electrode_order: list[str]  # EMG groups in the order of the first trial's emg_map (neighbours for cross-talk)
    f_max: np.ndarray
    base_delay_s: float  # the profile's calibrated electromechanical delay (already part of the model)
    optimal: np.ndarray | None
    slack: np.ndarray | None
    lo: np.ndarray | None
    hi: np.ndarray | None
    trials: list[TrialArrays]

    @property
    def emg_index(self) -> np.ndarray:
        return np.array([self.groups.index(g) for g in self.emg_groups], dtype=int)

    @property
    def other_index(self) -> np.ndarray:
        return np.array([j for j, g in enumerate(self.groups) if g not in self.emg_groups], dtype=int)


def describe_left_out(left_out: dict[str, int]) -> str:
    """``"12 (reason), 3 (reason)"``: the frames left out of a trial, by reason (reasons with none left out skipped)."""
    return ", ".join(f"{n} ({reason})" for reason, n in left_out.items() if n)


def check_inputs(train: list[TrialData], holdout: list[TrialData], max_delay_s: float = MAX_DELAY_S) -> None:
    """The precise input errors of ``msk discrepancy`` (file and field named)."""
    if not train:
        raise EstimationError("discrepancy needs at least one training trial")
    if not holdout:
        raise EstimationError("discrepancy needs at least one held-out trial (the candidates are scored on them)")
    seen = {str(t.path.resolve()) if t.path else t.name: t for t in train}
    for t in holdout:
        key = str(t.path.resolve()) if t.path else t.name
        twin = seen.get(key) or next((u for u in train if _same_data(t, u)), None)
        if twin is not None:
            raise InputError(
                "a held-out trial must not also be a training trial (the score would not be held out)"
                + (f": it holds the same frames as {twin.path}" if twin.path != t.path else ""),
                path=t.path,
                field="--holdout",
                value=str(t.path),
            )
    for label, trials in (("--trial", train), ("--holdout", holdout)):
        if all(t.isometric for t in trials):
            raise InputError(
                "every trial here is isometric (`isometric = true`); the effects are searched in movement, "
                "so at least one trial with reps is needed",
                path=trials[0].path,
                field=label,
                value=", ".join(t.name for t in trials),
            )
    for t in holdout:
        if t.torque_source != "file":
            raise InputError(
                "a held-out trial needs measured torques (`torques = ...`, an inverse-dynamics file): the "
                "gap is measured against them",
                path=t.path,
                field="torques",
            )
    if not any(t.emg for t in train + holdout):
        raise InputError(
            "no trial has EMG (`emg = ...` with an [emg_map]): the gap between what the EMG implies and "
            "the torques needs it",
            path=train[0].path,
            field="emg",
        )
    for t in train + holdout:
        if t.isometric:
            continue
        span = float(t.time[-1] - t.time[0])
        if span <= 2 * max_delay_s:
            raise InputError(
                f"trial lasts {span:.3f} s, not longer than twice the longest delay searched ({max_delay_s:g} s)",
                path=t.path,
                field="kinematics",
                value=round(span, 3),
            )


def _same_data(a: TrialData, b: TrialData) -> bool:
    """Whether two trials hold the same frames (a copy of a trial file under another name)."""
    return (
        a.n_frames == b.n_frames
        and np.array_equal(a.time, b.time)
        and np.array_equal(a.q, b.q, equal_nan=True)
        and np.array_equal(a.torques, b.torques, equal_nan=True)
    )


def _too_few_frames(trial: TrialData, kept: int, left_out: dict[str, int]) -> InputError:
    """The error for a trial with fewer than ``MIN_FRAMES`` usable frames: what was left out and why, or that the
    trial itself is that short."""
    capacity = left_out.get(f"torque beyond {CAPACITY_MARGIN:.0%} of the muscles' capacity")
    return InputError(
        (
            f"only {kept} of {trial.n_frames} frames are left for the discrepancy analysis "
            f"(at least {MIN_FRAMES} needed); left out: {describe_left_out(left_out)}"
            if any(left_out.values())
            else f"the trial has only {trial.n_frames} frames; the discrepancy analysis needs at least {MIN_FRAMES}"
        )
        + (" - for torques beyond the capacity, check the load and the profile's strengths" if capacity else ""),
        path=trial.path,
        field="torques" if trial.torque_source == "file" else "kinematics",
    )


def _arrays(pack: PackLike, profile: SubjectProfile, trial: TrialData, emg_groups: list[str]) -> TrialArrays:
    groups = list(pack.groups)
    n_c, g = len(pack.coordinates), len(groups)
    mech = trial.mechanics(pack)  # moment arms and static optimisation, as calibration reads them
    q = mech.q_clamped
    keep = np.all(np.isfinite(trial.q), axis=1) & np.all(np.isfinite(trial.torques), axis=1)
    left_out = {
        # what loading the trial left out already (msk_core.estimate.trial): counted here too, by its reason
        "outside the torque file's time span": int(trial.extra.get("torque_frames_outside", 0)),
        "torque file not finite": int((trial.extra.get("torque_frames_not_finite") or (0,))[0]),
        "non-finite kinematics or torques": int((~keep).sum()),
    }

    def drop(reason: str, ok: np.ndarray) -> None:
        nonlocal keep
        left_out[reason] = int((keep & ~ok).sum())
        keep &= ok

    drop("outside the pack's coordinate ranges", mech.usable)
    lengths, arms = mech.lengths, mech.moment_arms
    scale = np.maximum(np.abs(arms * profile.f_max).sum(axis=2), MIN_TORQUE_SCALE)
    # frames beyond the muscles' capacity (a torque outside [sum of negative, sum of positive] moment capacities at
    # some coordinate): no activation explains them (the estimator flags them `reserve`); they stay out of the fit
    a = arms * profile.f_max
    reach_hi, reach_lo = np.clip(a, 0, None).sum(axis=2), np.clip(a, None, 0).sum(axis=2)
    tau0 = np.nan_to_num(trial.torques)
    drop(
        f"torque beyond {CAPACITY_MARGIN:.0%} of the muscles' capacity",
        np.all((tau0 <= CAPACITY_MARGIN * reach_hi) & (tau0 >= CAPACITY_MARGIN * reach_lo), axis=1),
    )
    prior = profile.prior
    if prior is not None:
        mean = np.array([prior.mean_precision(float(p))[0] for p in trial.phase])
    else:
        mean = np.zeros((trial.n_frames, g))
    emg = np.column_stack([trial.emg[x] for x in emg_groups]) if emg_groups else np.zeros((trial.n_frames, 0))
    drop("non-finite EMG", np.all(np.isfinite(emg), axis=1))
    if keep.sum() < MIN_FRAMES:
        raise _too_few_frames(trial, int(keep.sum()), left_out)
    hand = trial.hand_load_newton
    if hand > 0:
        tau_load = np.array(
            [
                np.asarray(pack.inverse_dynamics(a, b, c, hand)) - np.asarray(pack.inverse_dynamics(a, b, c, 0.0))
                for a, b, c in zip(q, trial.qd, trial.qdd)
            ]
        )
    else:
        tau_load = np.zeros((trial.n_frames, n_c))
    so = np.nan_to_num(mech.min_effort) if len(emg_groups) < g else np.zeros((trial.n_frames, g))
    sel = keep
    return TrialArrays(
        name=trial.name,
        path=str(trial.path),
        time=trial.time[sel],
        q=q[sel],
        qd=trial.qd[sel],
        tau=trial.torques[sel],
        arms=arms[sel],
        lengths=None if lengths is None else lengths[sel],
        scale=scale[sel],
        emg=emg[sel],
        prior_mean=mean[sel],
        min_effort=so[sel],
        tau_load=tau_load[sel],
        phase=trial.phase[sel],
        rep_index=np.asarray(trial.rep_index)[sel],
        load_kg=trial.load_kg,
        left_out={k: v for k, v in left_out.items() if v},
    )


def session_arrays(pack: PackLike, profile: SubjectProfile, trials: list[TrialData]) -> SessionArrays:
    """Arrays of the trials (isometric trials left out: no phase, and the effects searched here need movement)."""
    profile.check_pack(pack)
    trials = [t for t in trials if not t.isometric]
    groups = list(pack.groups)
    emg_groups = [g for g in groups if all(g in t.emg for t in trials)]
    if not emg_groups:
        raise InputError(
            "no group has EMG in every trial; the EMG-implied torque needs the same electrodes throughout",
            path=trials[0].path if trials else None,
            field="emg_map",
        )
    first = trials[0]
    order = [first.emg_channels[ch] for ch in first.emg_channels if first.emg_channels[ch] in emg_groups]
    order = list(dict.fromkeys(order))
    lo, hi = fitted_ranges(pack) or (None, None)
    optimal, slack = fibre_lengths(pack)
    return SessionArrays(
        groups=groups,
        coordinates=list(pack.coordinates),
        emg_groups=emg_groups,
        electrode_order=order,
        f_max=np.asarray(profile.f_max, dtype=float),
        base_delay_s=calibrated_delay(profile),
        optimal=optimal,
        slack=slack,
        lo=lo,
        hi=hi,
        trials=[_arrays(pack, profile, t, emg_groups) for t in trials],
    )
