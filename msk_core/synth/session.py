"""Assemble synthetic trials and sessions: kinematics -> inverse dynamics -> true recruitment -> EMG and IMU."""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np

from msk_core.model import load_pack
from msk_core.progress import Progress, counted
from msk_core.synth.effects import Effects, muscle_factors
from msk_core.synth.emg import MVC_BLOCK_S, mvc_drive, raw_emg, spectral_scale
from msk_core.synth.exercises import SPECS, Exercise, ExerciseSpec
from msk_core.synth.imu import ElectrodeAccStream, ImuStream, Motion, simulate_electrode_acc, simulate_imu
from msk_core.synth.kinematics import RepPlan, Tempo, evaluate, plan_reps
from msk_core.synth.recruitment import TONE, Recruitment, recruit
from msk_core.synth.rng import stream
from msk_core.synth.subject import Subject, make_subject
from msk_core.units import GRAVITY


@dataclass(frozen=True)
class SynthConfig:
    subject_seed: int = 7
    n_reps: int = 8
    kinematics_rate_hz: float = 100.0
    emg_rate_hz: float = 2000.0
    imu_rate_hz: float = 60.0  # Xsens Awinda: 60 Hz holds for up to 20 trackers
    emg_acc_rate_hz: float = 2 / 0.0135  # Trigno Avanti ACC on the AUX port: 2 samples per 13.5 ms frame (148.1 Hz)
    effects: Effects = Effects()
    tempo: Tempo = Tempo()
    loads_kg: dict[Exercise, tuple[float, ...]] | None = None  # None: the exercise defaults


@dataclass
class Trial:
    name: str
    exercise: Exercise
    pack_name: str
    load_kg: float  # true barbell mass
    reported_load_kg: float  # what the log / trial file says (differs under load_misreport)
    coordinates: list[str]
    groups: list[str]
    channels: list[str]
    time: np.ndarray  # (T,) kinematics time base
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    phase: np.ndarray
    rep: np.ndarray
    torque_id: np.ndarray  # inverse dynamics with the true load (net joint torque)
    torque_reported: np.ndarray  # inverse dynamics with the reported load (what a lab computes)
    torque_muscle: np.ndarray  # what the muscles produce (ID + joint damping, when on)
    activation: np.ndarray  # (T, G) truth
    force: np.ndarray  # (T, G) N, truth (active + passive)
    residual: np.ndarray  # muscle torque − required torque (non-zero only beyond capacity)
    fallback_frames: int
    emg_time: np.ndarray  # (E,)
    emg: np.ndarray  # (E, C) raw volts
    imu: list[ImuStream] = field(default_factory=list)
    emg_acc: ElectrodeAccStream | None = None  # the EMG sensors' accelerometers (Trigno AUX port)
    rep_starts: np.ndarray = field(default_factory=lambda: np.zeros(0))
    rep_ends: np.ndarray = field(default_factory=lambda: np.zeros(0))


@dataclass
class MvcTrial:
    """The MVC session: one isometric maximal contraction per electrode site, in that muscle's test position, against
    a dynamometer that measures the joint torques (the usual way to both normalise EMG and measure strength)."""

    exercise: Exercise
    channels: list[str]
    time: np.ndarray  # (E,) EMG time base, all blocks one after another
    drive: np.ndarray  # (E, C) neural drive of each site
    emg: np.ndarray  # (E, C) raw volts
    block_s: float = MVC_BLOCK_S
    coordinates: list[str] = field(default_factory=list)  # the pack's, when poses/torque are simulated
    poses: np.ndarray | None = None  # (C, n_c) test position of each channel's block, rad
    activation: np.ndarray | None = None  # (E, G) every group's activation (drive delayed by the EMD)
    torque: np.ndarray | None = None  # (E, n_c) joint torques the dynamometer measures, N·m

    def block(self, k: int) -> slice:
        """EMG samples of channel k's contraction."""
        n = int(round(self.block_s / float(self.time[1] - self.time[0])))
        return slice(k * n, (k + 1) * n)


@dataclass
class ExerciseSession:
    spec: ExerciseSpec
    pack_name: str
    subject: Subject
    f_max: np.ndarray  # subject's F_max per group (N)
    mvc: MvcTrial
    trials: list[Trial]


@dataclass
class Session:
    config: SynthConfig
    exercises: list[ExerciseSession]


def _resolve_pack(spec: ExerciseSpec, pack):
    return load_pack(spec.pack) if pack is None else (load_pack(pack) if isinstance(pack, str) else pack)


def _shift(time: np.ndarray, x: np.ndarray, lead_s: float) -> np.ndarray:
    """x evaluated at time + lead_s (held at the ends)."""
    if lead_s == 0:
        return x
    return np.column_stack([np.interp(time + lead_s, time, x[:, k]) for k in range(x.shape[1])])


def _torques_and_geometry(
    pack, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, load_kg: float, reported: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per frame: inverse-dynamics torques for the true and the reported load, moment arms and muscle lengths."""
    n, n_c, n_g = q.shape[0], len(pack.coordinates), len(pack.groups)
    tau_id = np.empty((n, n_c))
    tau_rep = np.empty((n, n_c))
    arms = np.empty((n, n_c, n_g))
    lengths = np.empty((n, n_g))
    for k in range(n):
        tau_id[k] = pack.inverse_dynamics(q[k], qd[k], qdd[k], load_kg * GRAVITY)
        tau_rep[k] = (
            tau_id[k] if reported == load_kg else pack.inverse_dynamics(q[k], qd[k], qdd[k], reported * GRAVITY)
        )
        lengths[k], arms[k] = pack.lengths_and_moment_arms(q[k])
    return tau_id, tau_rep, arms, lengths


def _recruit_muscles(
    pack,
    subject: Subject,
    config: SynthConfig,
    arms: np.ndarray,
    lengths: np.ndarray,
    qd: np.ndarray,
    tau_muscle: np.ndarray,
    key: tuple[str, float],
) -> tuple[Recruitment, np.ndarray]:
    """The recruitment that produces ``tau_muscle`` (with the muscle-state effects when configured) and the forces."""
    eff = config.effects
    f_max = pack.f_max_ref * subject.f_max_factor
    active = passive = None
    if eff.needs_muscle_state:
        velocity = -np.einsum("tng,tn->tg", arms, qd)  # dl/dt = −r·qd
        active, passive, _ = muscle_factors(
            eff, lengths, velocity, pack.optimal_fiber_lengths, pack.tendon_slack_lengths
        )
    rec = recruit(
        arms,
        tau_muscle,
        f_max,
        subject.effort_weight,
        subject.cocontraction,
        rate_hz=config.kinematics_rate_hz,
        seed=subject.seed,
        key=key,
        active_factor=active,
        passive_factor=passive,
    )
    force = f_max * rec.activation * (1.0 if active is None else active) + (0.0 if passive is None else f_max * passive)
    return rec, force


def _trial_emg(
    plan: RepPlan,
    pack,
    subject: Subject,
    config: SynthConfig,
    channels: list[str],
    time: np.ndarray,
    activation: np.ndarray,
    key: tuple[str, float],
) -> tuple[np.ndarray, np.ndarray]:
    """EMG time and raw EMG of ``channels``: it follows the neural drive, which leads the force by the
    electromechanical delay."""
    eff = config.effects
    emg_time = np.arange(0.0, plan.duration, 1.0 / config.emg_rate_hz)
    index = [pack.groups.index(ch) for ch in channels]
    drive_k = _shift(time, activation[:, index], eff.emd)
    drive = np.column_stack([np.interp(emg_time, time, drive_k[:, j]) for j in range(len(channels))])
    touches = np.asarray([m.t0 for m in plan.moves if m.kind == "bottom"])
    emg = raw_emg(
        emg_time,
        drive,
        channels,
        subject.emg_gain_uv,
        subject.noise_floor_uv,
        rate_hz=config.emg_rate_hz,
        seed=subject.seed,
        key=key,
        crosstalk=eff.crosstalk,
        artefact_times=touches,
        spectral_scale=spectral_scale(emg_time, plan.rep_starts, eff.fatigue) if eff.fatigue else None,
    )
    return emg_time, emg


def _motion(plan: RepPlan, rate_hz: float) -> Motion:
    """The plan's motion sampled at ``rate_hz`` over its duration."""
    time = np.arange(0.0, plan.duration, 1.0 / rate_hz)
    q, qd, qdd, _, _ = evaluate(plan, time)
    return Motion(time, q, qd, qdd)


def _trial_motion_sensors(
    plan: RepPlan,
    spec: ExerciseSpec,
    pack,
    config: SynthConfig,
    channels: list[str],
    seed: int,
    key: tuple[str, float],
) -> tuple[list[ImuStream], ElectrodeAccStream]:
    """The IMU segments' and the EMG electrodes' accelerometers, each at its own rate."""
    imu = simulate_imu(pack, spec.segments, _motion(plan, config.imu_rate_hz), seed=seed, key=key)
    acc_motion = _motion(plan, config.emg_acc_rate_hz)
    emg_acc = simulate_electrode_acc(pack, spec.electrode_sites, channels, acc_motion, seed=seed, key=key)
    return imu, emg_acc


def generate_trial(
    spec: ExerciseSpec,
    pack,
    subject: Subject,
    load_kg: float,
    config: SynthConfig,
    channels: list[str],
) -> Trial:
    """One trial: ``config.n_reps`` repetitions at ``load_kg``."""
    seed = subject.seed
    key = (spec.exercise.value, float(load_kg))
    eff = config.effects
    top, bottom, warp = spec.poses(pack.coordinates, pack.reference_pose, pack.coordinate_ranges)
    plan = plan_reps(
        top,
        bottom,
        config.n_reps,
        seed=seed,
        key=key,
        tempo=config.tempo,
        warp=warp,
        lo=pack.coordinate_ranges[:, 0],
        hi=pack.coordinate_ranges[:, 1],
    )
    time = np.arange(0.0, plan.duration, 1.0 / config.kinematics_rate_hz)
    q, qd, qdd, phase, rep = evaluate(plan, time)
    reported = round(load_kg * eff.load_misreport, 3)
    tau_id, tau_rep, arms, lengths = _torques_and_geometry(pack, q, qd, qdd, load_kg, reported)
    tau_muscle = tau_id + eff.damping * qd  # muscles also overcome the joint damping (absent from ID)
    rec, force = _recruit_muscles(pack, subject, config, arms, lengths, qd, tau_muscle, key)
    emg_time, emg = _trial_emg(plan, pack, subject, config, channels, time, rec.activation, key)
    imu, emg_acc = _trial_motion_sensors(plan, spec, pack, config, channels, seed, key)
    return Trial(
        name=f"{spec.exercise.value}_{load_kg:g}kg",
        exercise=spec.exercise,
        pack_name=pack.name,
        load_kg=float(load_kg),
        reported_load_kg=float(reported),
        coordinates=list(pack.coordinates),
        groups=list(pack.groups),
        channels=list(channels),
        time=time,
        q=q,
        qd=qd,
        qdd=qdd,
        phase=phase,
        rep=rep,
        torque_id=tau_id,
        torque_reported=tau_rep,
        torque_muscle=tau_muscle,
        activation=rec.activation,
        force=force,
        residual=rec.residual,
        fallback_frames=rec.fallback_frames,
        emg_time=emg_time,
        emg=emg,
        imu=imu,
        rep_starts=plan.rep_starts,
        rep_ends=plan.rep_ends,
        emg_acc=emg_acc,
    )


def muscle_test_positions(pack, groups: list[int], *, points: int = 5) -> np.ndarray:
    """Per group in ``groups``, the pose (within the inner 80 % of the pack's fitted ranges, ``points`` per coordinate)
    where it has the largest share of the reference torque capacity of any coordinate it crosses: where a maximal
    contraction of it against a dynamometer is least masked by its synergists (manual-muscle-test positions follow the
    same idea). The grid's moment arms are evaluated once for all groups. Returns (len(groups), n_c)."""
    ranges = np.asarray(pack.coordinate_ranges, dtype=float)
    grid = [
        np.asarray(p)
        for p in itertools.product(
            *[np.linspace(lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo), points) for lo, hi in ranges]
        )
    ]
    f_ref = np.asarray(pack.f_max_ref, dtype=float)
    shares = []  # (poses, G): each group's largest capacity share at each pose
    for pose in grid:
        arms = np.abs(np.asarray(pack.moment_arms(pose), dtype=float)) * f_ref[None, :]  # (n_c, G) N·m
        shares.append(np.max(arms / np.maximum(arms.sum(axis=1, keepdims=True), 1e-12), axis=0))
    out = np.empty((len(groups), len(ranges)))
    for k, group in enumerate(groups):
        best, best_share = None, -1.0
        for pose, share in zip(grid, shares):  # first pose that is better by more than round-off
            if share[group] > best_share + 1e-12:
                best, best_share = pose, float(share[group])
        out[k] = best
    return out


def generate_mvc(spec: ExerciseSpec, subject: Subject, channels: list[str], config: SynthConfig, pack=None) -> MvcTrial:
    """MVC blocks (EMG of every site while one site contracts maximally); with ``pack`` also each block's test
    position and the joint torques a dynamometer measures: sum_g r_g(pose) F_g (f_g a_g + p_g), where groups without an
    electrode co-contract as the measured non-target sites do (5-15 % of the effort; an electrode does not change a
    muscle's activation), and the force follows the drive by the EMD."""
    time, drive = mvc_drive(channels, config.emg_rate_hz, seed=subject.seed, block_s=MVC_BLOCK_S)
    emg = raw_emg(
        time,
        drive,
        channels,
        subject.emg_gain_uv,
        subject.noise_floor_uv,
        rate_hz=config.emg_rate_hz,
        seed=subject.seed,
        key=(spec.exercise.value, "mvc"),
        crosstalk=config.effects.crosstalk,
    )
    mvc = MvcTrial(spec.exercise, list(channels), time, drive, emg)
    if pack is None:
        return mvc
    groups = list(pack.groups)
    f_max = np.asarray(pack.f_max_ref, dtype=float) * subject.f_max_factor
    eff = config.effects
    lagged = _shift(time, drive, -eff.emd)  # force follows the drive
    activation = np.empty((time.size, len(groups)))
    torque = np.empty((time.size, len(pack.coordinates)))
    poses = muscle_test_positions(pack, [groups.index(ch) for ch in channels])
    for k, ch in enumerate(channels):
        sl = mvc.block(k)
        effort = lagged[sl, k]
        for j, g in enumerate(groups):
            if g in channels:
                activation[sl, j] = lagged[sl, channels.index(g)]
            else:  # co-contracts like the sites with an electrode do (mvc_drive: 5-15 % of the effort)
                share = stream(subject.seed, "mvc", ch, "unmeasured", g).uniform(0.05, 0.15)
                activation[sl, j] = np.maximum(TONE, share * effort)
        lengths, arms = pack.lengths_and_moment_arms(poses[k])
        active, passive = np.ones(len(groups)), np.zeros(len(groups))
        if eff.needs_muscle_state:  # isometric: force-velocity at zero speed is 1
            active, passive, _ = muscle_factors(
                eff, lengths[None], np.zeros((1, len(groups))), pack.optimal_fiber_lengths, pack.tendon_slack_lengths
            )
            active, passive = active[0], passive[0]
        torque[sl] = (activation[sl] * active + passive) @ (np.asarray(arms) * f_max[None, :]).T
    mvc.coordinates, mvc.poses, mvc.activation, mvc.torque = list(pack.coordinates), poses, activation, torque
    return mvc


def generate_exercise(
    exercise: Exercise, config: SynthConfig, *, pack=None, progress: Progress | None = None
) -> ExerciseSession:
    """MVC block plus one trial per load for one exercise. ``pack``: a ModelPack or name (default: the exercise's)."""
    spec = SPECS[exercise]
    pack = _resolve_pack(spec, pack)
    channels = spec.channels(pack.groups)
    subject = make_subject(config.subject_seed, pack.groups, channels)
    loads = (config.loads_kg or {}).get(exercise, spec.loads_kg)
    mvc = generate_mvc(spec, subject, channels, config, pack)
    trials = []
    for load in counted(loads, progress, f"synth {exercise.value} (loads)"):
        trials.append(generate_trial(spec, pack, subject, float(load), config, channels))
    return ExerciseSession(spec, pack.name, subject, pack.f_max_ref * subject.f_max_factor, mvc, trials)


def generate_session(
    exercises: list[Exercise],
    config: SynthConfig,
    *,
    packs: dict[Exercise, object] | None = None,
    progress: Progress | None = None,
) -> Session:
    packs = packs or {}
    return Session(config, [generate_exercise(e, config, pack=packs.get(e), progress=progress) for e in exercises])
