"""Scoring a live run against the generator's truth: the activation frames an MCAP recording holds, cut into trials
by its load events and compared with each trial's true activations (RMSE per method and group, torque residual,
solver time, end-to-end latency), as a markdown table and plots. ``msk demo`` uses it; any recording of a synthetic
session (``msk synth``) can be scored the same way. Beside it, :mod:`msk_core.estimate.scores` scores trials offline.

A ``msk live --sim`` run (:func:`score_live_run`) has no load events on the trial's clock: its simulators play the
held-out trial in a loop on one trial clock, whose origin ``summary.json`` states (``trial_clock``), so each frame's
host time says its trial instant (:class:`SimWorld`). The mapping is checked against the content (the live joint
angles against the trial's, :func:`peak_lag`), then every method is scored per group against the truth, the groups
with an electrode and those without apart.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from msk_core.errors import InputError
from msk_core.estimate.metrics import pearson_r, rmse
from msk_core.io import Storage, read_sto
from services.transport import messages
from services.transport.mcap_io import read_messages

METHODS = ("proposed", "so", "hybrid")


@dataclass
class TrialWindow:
    exercise: str
    load_kg: float
    start_s: float
    end_s: float

    @property
    def name(self) -> str:
        return f"{self.exercise}_{self.load_kg:g}kg"


@dataclass
class MethodScore:
    exercise: str
    trial: str
    role: str  # "calibration" or "held out"
    method: str
    frames: int
    activation_rmse: float
    torque_rmse_nm: float
    flagged: int
    solve_us_median: float
    solve_us_p99: float
    latency_ms_median: float
    latency_ms_p99: float
    per_group_rmse: dict[str, float] = field(default_factory=dict)


def _trial_folders(recordings: Path, exercise: str) -> list[Path]:
    folders = sorted(p for p in (recordings / "demo" / exercise).iterdir() if (p / "trial.toml").is_file())
    if len(folders) < 2:
        raise InputError(
            "the demo needs two trials per exercise (calibration + held out)", path=recordings / "demo" / exercise
        )
    return sorted(folders, key=lambda p: float(p.name.rsplit("_", 1)[1].removesuffix("kg")))


def trial_windows(load_events: list) -> list[TrialWindow]:
    """Trials as the load events delimit them: a non-zero mass opens one, the next zero closes it."""
    windows, open_window = [], None
    for event in load_events:
        t = event.device_time_ns / 1e9
        if event.barbell_mass_kg > 0:
            open_window = TrialWindow(event.exercise, event.barbell_mass_kg, t, float("inf"))
        elif open_window is not None:
            open_window.end_s = t
            windows.append(open_window)
            open_window = None
    return windows


def score(recorded_mcap: Path, recordings: Path) -> tuple[list[MethodScore], dict]:
    frames: dict[str, list] = {m: [] for m in METHODS}
    load_events = []
    for recorded in read_messages(recorded_mcap):  # one pass over the recording for frames and load events
        if recorded.type_name == "msk.ActivationFrame":
            frame = recorded.decode(messages.ActivationFrame)
            frames[frame.method].append(frame)
        elif recorded.type_name == "msk.LoadEvent":
            load_events.append(recorded.decode(messages.LoadEvent))
    scores, curves = [], {}
    for window in trial_windows(load_events):
        folders = _trial_folders(recordings, window.exercise)
        folder = next((f for f in folders if f.name == window.name), None)
        if folder is None:
            continue
        role = "calibration" if folder == folders[0] else "held out"
        truth = read_sto(folder / "truth_activations.sto")
        for method in METHODS:
            inside = [
                f
                for f in frames[method]
                if window.start_s - 1e-6 <= f.time_s <= window.end_s + 1e-6 and set(f.groups) == set(truth.columns)
            ]
            if not inside:
                continue
            groups = list(inside[0].groups)
            t = np.array([f.time_s - window.start_s for f in inside])
            estimated = np.array([f.activations for f in inside])
            true = np.column_stack([np.interp(t, truth.time, truth.column(g)) for g in groups])
            ok = np.all(np.isfinite(estimated), axis=1)
            residual = np.array([[c.residual_nm for c in f.torques] for f in inside])
            solve = np.array([f.solve_time_s for f in inside]) * 1e6
            latency = np.array([(f.publish_ns - f.input_arrival_ns) / 1e6 for f in inside])
            per_group = {
                g: float(np.sqrt(np.mean((estimated[ok, i] - true[ok, i]) ** 2))) for i, g in enumerate(groups)
            }
            scores.append(
                MethodScore(
                    exercise=window.exercise,
                    trial=window.name,
                    role=role,
                    method=method,
                    frames=len(inside),
                    activation_rmse=float(np.sqrt(np.mean((estimated[ok] - true[ok]) ** 2))),
                    torque_rmse_nm=float(np.sqrt(np.mean(residual[ok] ** 2))),
                    flagged=int(sum(1 for f in inside if f.flags)),
                    solve_us_median=float(np.median(solve)),
                    solve_us_p99=float(np.percentile(solve, 99)),
                    latency_ms_median=float(np.median(latency)),
                    latency_ms_p99=float(np.percentile(latency, 99)),
                    per_group_rmse=per_group,
                )
            )
            curves[(window.name, method)] = (t, estimated, true, groups)
    return scores, curves


def markdown(scores: list[MethodScore]) -> str:
    lines = [
        "| trial | role | method | frames | activation RMSE (0 to 1) | torque residual RMS (N·m) | flagged | solve µs (median / p99) | latency ms (median / p99) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for s in scores:
        lines.append(
            f"| {s.trial} | {s.role} | {s.method} | {s.frames} | {s.activation_rmse:.3f} | {s.torque_rmse_nm:.2f} | {s.flagged} | "
            f"{s.solve_us_median:.0f} / {s.solve_us_p99:.0f} | {s.latency_ms_median:.2f} / {s.latency_ms_p99:.2f} |"
        )
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------ msk live --sim

#: frames of a live run's first seconds are not scored: the host clock mappings' minimums, the EMG filters, the
#: acceleration alignment of the EMG clock and the phase tracker settle
WARMUP_S = 5.0
MAX_LAG_S = 0.5
LAG_STEP_S = 0.001


@dataclass(frozen=True)
class SimWorld:
    """The trial clock of a ``msk live --sim`` run as ``summary.json`` states it (``trial_clock``, written by
    :meth:`services.sessions.live.Simulators.world`): the trial's sample 0 was measured at host time ``origin_ns``, and the
    trial loops every ``loop_s``; with sets (``msk live --sim`` plays sets with rests, services.sessions.sim_sets) a cycle of
    ``cycle_s`` repeats instead, ``schedule`` its (trial start, duration) segments."""

    exercise: str
    trial: str
    origin_ns: int
    loop_s: float
    speed: float = 1.0
    schedule: tuple[tuple[float, float], ...] = ()
    cycle_s: float = 0.0

    @classmethod
    def from_summary(cls, summary: dict, path: Path | None = None) -> SimWorld:
        world = summary.get("trial_clock")
        if not world:
            raise InputError(
                "no trial clock: not the summary of a `msk live --sim` run", path=path, field="trial_clock"
            )
        try:
            made = cls(
                str(world["exercise"]),
                str(world["trial"]),
                int(world["origin_ns"]),
                float(world["loop_s"]),
                float(world.get("speed", 1.0)),
                tuple((float(a), float(d)) for a, d in world.get("schedule", ())),
                float(world.get("cycle_s", 0.0)),
            )
        except (KeyError, TypeError, ValueError) as error:
            raise InputError(f"malformed trial clock ({error})", path=path, field="trial_clock", value=world) from None
        if not (made.loop_s > 0 and made.speed > 0):
            raise InputError("loop and speed must be positive", path=path, field="trial_clock", value=world)
        if made.schedule and abs(sum(d for _, d in made.schedule) - made.cycle_s) > 1e-6:
            raise InputError("the schedule's segments do not fill the cycle", path=path, field="trial_clock")
        return made

    def trial_s(self, host_ns) -> np.ndarray:
        """Trial time (s, within one loop) of each host time (ns since the epoch, as the session maps every device
        clock): (host - origin) x speed, modulo the loop. The devices' stated latencies are already off (the clock
        mappings take them off), so nothing else is subtracted."""
        elapsed_ns = np.asarray(host_ns, dtype=np.int64) - np.int64(self.origin_ns)
        if not self.schedule:
            return np.mod(elapsed_ns / 1e9 * self.speed, self.loop_s)
        # sets: the moment of the cycle, then the trial instant its segment plays
        moment = np.mod(elapsed_ns / 1e9 * self.speed, self.cycle_s)
        starts = np.cumsum([0.0] + [d for _, d in self.schedule[:-1]])
        k = np.clip(np.searchsorted(starts, moment, side="right") - 1, 0, len(self.schedule) - 1)
        trial_starts = np.array([a for a, _ in self.schedule])
        return np.mod(trial_starts[k] + (moment - starts[k]), self.loop_s)


def looped(truth: Storage, columns: list[str], trial_s: np.ndarray, loop_s: float) -> np.ndarray:
    """(n, columns) of ``truth`` at the instants ``trial_s`` of a trial played in a loop every ``loop_s`` (its rows
    from ``loop_s`` on are not played: the loop starts over there), linear between rows and across the seam."""
    keep = truth.time < loop_s
    return np.column_stack(
        [np.interp(trial_s, truth.time[keep], truth.column(c)[keep], period=loop_s) for c in columns]
    )


def peak_lag(
    trial_s: np.ndarray, measured: np.ndarray, truth: Storage, columns: list[str], loop_s: float
) -> tuple[float, float]:
    """(lag in s, correlation): the lag maximising the correlation, averaged over ``columns``, of ``measured`` (n,
    columns) with the looped truth at ``trial_s`` + lag, within ±:data:`MAX_LAG_S`. 0: the trial instants are the
    truth's; +: the measurement shows the truth of a later instant."""
    lags = np.arange(-MAX_LAG_S, MAX_LAG_S + LAG_STEP_S / 2, LAG_STEP_S)
    total = np.zeros(len(lags))
    for j, column in enumerate(columns):
        shifted = looped(truth, [column], (trial_s[:, None] + lags[None, :]).ravel(), loop_s).reshape(len(trial_s), -1)
        a = (measured[:, j] - measured[:, j].mean()) / measured[:, j].std()
        b = (shifted - shifted.mean(axis=0)) / shifted.std(axis=0)
        total += (a[:, None] * b).mean(axis=0)
    best = int(np.argmax(total))
    return float(lags[best]), float(total[best] / len(columns))


@dataclass(frozen=True)
class GroupScore:
    rmse: float
    r: float


def score_against_truth(
    trial_s: np.ndarray, estimated: np.ndarray, groups: list[str], truth: Storage, loop_s: float
) -> dict[str, GroupScore]:
    """Per group, RMSE and Pearson r of ``estimated`` (n, groups) against the looped truth at ``trial_s``."""
    true = looped(truth, groups, trial_s, loop_s)
    return {
        g: GroupScore(rmse(estimated[:, j], true[:, j]), pearson_r(estimated[:, j], true[:, j]))
        for j, g in enumerate(groups)
    }


def pooled_rmse(
    trial_s: np.ndarray, estimated: np.ndarray, groups: list[str], truth: Storage, loop_s: float, chosen: list[str]
) -> float:
    """One RMSE over the ``chosen`` groups together (as the offline figure of docs/estimation.md pools them)."""
    columns = [groups.index(g) for g in chosen]
    return rmse(estimated[:, columns], looped(truth, chosen, trial_s, loop_s))


@dataclass
class LiveTruthScore:
    """A ``msk live --sim`` run scored against the generator's truth (:func:`score_live_run`)."""

    world: SimWorld
    frames: int  # joint frames scored (after the warm-up), each estimated by every method
    frame_s: float  # the joint frames' median period
    angle_lag_s: float  # the mapping's check: live joint angles against the trial's (0: the mapping is right)
    angle_r: float
    electrode_groups: list[str]
    no_electrode_groups: list[str]
    per_group: dict[str, dict[str, GroupScore]]  # method -> group -> score
    pooled: dict[str, dict[str, float]]  # method -> {"no_electrode", "electrode", "all"}: one RMSE over the groups

    def median_rmse(self, method: str, groups: list[str]) -> float:
        return float(np.median([self.per_group[method][g].rmse for g in groups]))


def _run_messages(recordings: list[Path]) -> tuple[dict[str, list], list]:
    """Activation frames per method and joint frames of a run's recording parts."""
    frames: dict[str, list] = {}
    joints = []
    for part in recordings:
        for recorded in read_messages(part):
            if recorded.type_name == "msk.ActivationFrame":
                frame = recorded.decode(messages.ActivationFrame)
                frames.setdefault(frame.method, []).append(frame)
            elif recorded.type_name == "msk.JointAngles":
                joints.append(recorded.decode(messages.JointAngles))
    return frames, joints


def score_live_run(out: Path, recordings: Path, warmup_s: float = WARMUP_S) -> LiveTruthScore:
    """Score the ``msk live --sim`` run whose output folder is ``out`` (its ``summary.json``, recording parts and
    ``subject_session.json``, the profile keyed by the session's electrode map) against the truth of the bundled
    trial it played (``recordings``/demo/<exercise>/<trial>: ``truth_activations.sto``, ``ik.sto``), over the joint
    frames from ``warmup_s`` after the first on."""
    from msk_core.estimate.live_emg import EmgSetup
    from msk_core.estimate.profile import SubjectProfile

    summary_path = out / "summary.json"
    if not summary_path.is_file():
        raise InputError("no summary.json: not the output folder of a finished `msk live` run", path=out)
    summary = json.loads(summary_path.read_text())
    world = SimWorld.from_summary(summary, summary_path)
    folder = recordings / "demo" / world.exercise / world.trial
    truth, kinematics = read_sto(folder / "truth_activations.sto"), read_sto(folder / "ik.sto")
    frames, joints = _run_messages([Path(p) for p in summary.get("recordings", [])])
    if not joints or not frames:
        raise InputError("the run recorded no joint or activation frames", path=out, value=summary.get("recordings"))
    joint_ns = np.array([j.device_time_ns for j in joints], dtype=np.int64)
    start_ns = int(joint_ns.min() + warmup_s * 1e9)
    kept = joint_ns >= start_ns
    coordinates = [c for c in joints[0].coordinates if kinematics.has_column(c)]
    q = np.array([[j.q[list(j.coordinates).index(c)] for c in coordinates] for j in joints])[kept]
    angle_lag_s, angle_r = peak_lag(world.trial_s(joint_ns[kept]), q, kinematics, coordinates, world.loop_s)
    setup = EmgSetup.from_profile(SubjectProfile.load(out / "subject_session.json"))
    groups = list(next(iter(frames.values()))[0].groups)
    electrode = [g for g in groups if g in set(setup.channel_group.values())]
    no_electrode = [g for g in groups if g not in electrode]
    per_group, pooled, counts = {}, {}, {}
    for method, method_frames in frames.items():
        inside = [f for f in method_frames if round(f.time_s * 1e9) >= start_ns and list(f.groups) == groups]
        trial_s = world.trial_s(np.array([round(f.time_s * 1e9) for f in inside], dtype=np.int64))
        estimated = np.array([f.activations for f in inside], dtype=float)
        per_group[method] = score_against_truth(trial_s, estimated, groups, truth, world.loop_s)
        pooled[method] = {
            name: pooled_rmse(trial_s, estimated, groups, truth, world.loop_s, chosen)
            for name, chosen in (("no_electrode", no_electrode), ("electrode", electrode), ("all", groups))
            if chosen
        }
        counts[method] = len(inside)
    return LiveTruthScore(
        world,
        min(counts.values()),
        float(np.median(np.diff(np.sort(joint_ns)))) / 1e9,
        angle_lag_s,
        angle_r,
        electrode,
        no_electrode,
        per_group,
        pooled,
    )


def live_markdown(scored: LiveTruthScore) -> str:
    """Per group (electrode or not) each method's RMSE (r) against the truth, then per set of groups (without an
    electrode, with one) the median of their RMSEs and their pooled RMSE."""
    methods = list(scored.per_group)
    lines = [
        "| group | electrode | " + " | ".join(f"{m} RMSE (r)" for m in methods) + " |",
        "|---|---|" + "---|" * len(methods),
    ]
    for group in scored.electrode_groups + scored.no_electrode_groups:
        cells = [f"{scored.per_group[m][group].rmse:.4f} ({scored.per_group[m][group].r:.2f})" for m in methods]
        lines.append(f"| {group} | {'yes' if group in scored.electrode_groups else 'no'} | " + " | ".join(cells) + " |")
    for name, chosen in (("no electrode", scored.no_electrode_groups), ("electrode", scored.electrode_groups)):
        if chosen:
            lines.append(
                f"| median, {name} | | " + " | ".join(f"{scored.median_rmse(m, chosen):.4f}" for m in methods) + " |"
            )
    for name, key in (("no electrode", "no_electrode"), ("electrode", "electrode")):
        if all(key in scored.pooled[m] for m in methods):
            lines.append(f"| pooled, {name} | | " + " | ".join(f"{scored.pooled[m][key]:.4f}" for m in methods) + " |")
    return "\n".join(lines)
