"""The demo: the embedded synthetic gym session through the whole live graph, scored against its known truth.

1. Calibrate one subject profile per exercise (strength per muscle group + the N(mu, sigma^2) EMG prior) on the
   lighter-load trial of ``recordings/demo`` and the isometric MVC trials (one maximal contraction per electrode site
   against a dynamometer) - OpenSim storage files + trial TOMLs written by ``msk synth``.
2. Start, on a private loopback Zenoh endpoint, a recorder and per exercise pack a kinematics node (IMU -> joint
   angles) and an estimator node (methods ``proposed``, ``so`` and ``hybrid``), then replay
   ``recordings/demo_session.mcap`` (raw EMG, IMU and load events; its recorded joint angles are left out, so the
   joints come from the IMUs as on a real rig) through them. The heavier-load trial of each exercise is held out.
3. Read the recorded activation topics back from MCAP and score them against the true activations the generator
   used: RMSE per method and trial, torque tracking, solver time and end-to-end latency; plots in the output folder.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from msk_core.errors import InputError
from msk_core.estimate.pipeline import calibrate_subject
from msk_core.estimate.trial import load_trial
from msk_core.io import read_sto
from msk_core.model import load_pack
from services import estimator, kinematics_node, recorder, replayer
from services.mcap_io import read_messages
from services.graph import Graph, wait_for
from services.zenoh_session import ZenohOptions

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_RECORDINGS = REPO_ROOT / "recordings"
METHODS = ("proposed", "so", "hybrid")
SESSION = "demo"


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
        raise InputError("the demo needs two trials per exercise (calibration + held out)", path=recordings / "demo" / exercise)
    return sorted(folders, key=lambda p: float(p.name.rsplit("_", 1)[1].removesuffix("kg")))


def calibration_trial_files(recordings: Path, exercise: str) -> tuple[Path, list[Path]]:
    """The demo's calibration input for an exercise: the lighter lift's folder and the isometric MVC trial files."""
    return _trial_folders(recordings, exercise)[0], sorted((recordings / "demo" / exercise / "mvc").glob("*/trial.toml"))


def calibrate(recordings: Path, out: Path, exercise: str, log) -> tuple[Path, dict]:
    pack = load_pack(exercise)
    training, isometric = calibration_trial_files(recordings, exercise)
    log(f"[{exercise}] calibrating on {training.name}" + (f" + {len(isometric)} isometric MVC trials" if isometric else "")
        + " ...")
    started = time.perf_counter()
    trials = [load_trial(training / "trial.toml", pack)] + [load_trial(p, pack) for p in isometric]
    profile, result = calibrate_subject(pack, trials)
    path = out / f"subject_{exercise}.json"
    profile.save(path)
    truth = json.loads((recordings / "demo" / "truth.json").read_text())["exercises"][exercise]["f_max_n"]
    true_f = np.array([truth[g] for g in pack.groups])
    error = np.abs(profile.f_max / true_f - 1.0)
    measured = np.array([s != "not_calibrated" for s in result.status])
    identified = result.identified

    def median(mask: np.ndarray) -> float | None:
        return float(np.median(error[mask])) if np.any(mask) else None

    report = {
        "trials": {"lift": training.name, "isometric": len(isometric)},
        "groups": {
            g: {"f_max_n": float(f), "truth_n": float(t), "reference_n": float(r), "status": st}
            for g, f, t, r, st in zip(pack.groups, profile.f_max, true_f, pack.f_max_ref, result.status)
        },
        "seconds": time.perf_counter() - started,
        "converged": bool(result.report().get("converged", True)),
        "strength_error_median": float(np.median(error)),
        "strength_error_median_emg": median(measured),
        "strength_error_median_identified": median(identified),
        "identified_groups": [g for g, ok in zip(pack.groups, identified) if ok],
        "status": dict(zip(pack.groups, result.status)),
        "reference_error_median": float(np.median(np.abs(np.asarray(pack.f_max_ref) / true_f - 1.0))),
    }

    def pct(x: float | None) -> str:
        return "n/a" if x is None else f"{100 * x:.0f} %"

    log(
        f"[{exercise}] calibrated in {report['seconds']:.1f} s; median |F_max error| vs truth: all groups "
        f"{pct(report['strength_error_median'])}, EMG-measured ({int(measured.sum())}) "
        f"{pct(report['strength_error_median_emg'])}, identified ({int(identified.sum())}: "
        f"{', '.join(report['identified_groups']) or 'none'}) {pct(report['strength_error_median_identified'])} "
        f"(model reference: {pct(report['reference_error_median'])})"
    )
    return path, report


GRAPH_READY_S = 60.0
DRAIN_S = 600.0  # the whole replay at rate max on a loaded 2-core machine takes ~1-2 min; generous, and bounded


def run_live_graph(
    recording: Path, out_mcap: Path, subjects: dict[str, Path], endpoint: str, rate: float | None, log, *, joints_from: str = "imu"
) -> dict:
    """Recorder + (kinematics +) estimator nodes as Zenoh peers, the replayer publishing the recording.

    ``joints_from="imu"``: the recording's joint angles are left out and kinematics nodes compute them from the IMU
    streams, as on a real rig; ``"recorded"``: the recorded joint angles are replayed as they are.
    """
    counts = {"imu": 0, "joints": {ex: 0 for ex in subjects}}
    current = ""
    for recorded in read_messages(recording):
        if recorded.type_name == "msk.LoadEvent":
            current = recorded.decode().exercise or current
        elif recorded.type_name == "msk.ImuSample":
            counts["imu"] += 1
        elif recorded.type_name == "msk.JointAngles" and current in counts["joints"]:
            counts["joints"][current] += 1
    rec_stats = recorder.RecorderStats()
    est_stats = {ex: estimator.EstimatorStats() for ex in subjects}
    kin_stats = {ex: kinematics_node.KinematicsStats() for ex in subjects} if joints_from == "imu" else {}

    with Graph(SESSION, endpoint) as graph:
        graph.add_thread("recorder", recorder.main, out_mcap, stats=rec_stats)
        for exercise, subject in subjects.items():
            graph.add_thread(
                f"estimator-{exercise}", estimator.main, pack=exercise, session=SESSION, methods=list(METHODS),
                subject_path=subject, exercise=exercise, stats=est_stats[exercise], after=("recorder",),
            )
        for exercise in kin_stats:
            # its joints go to the recorder and every estimator (each follows the exercise the load events name)
            graph.add_thread(
                f"kinematics-{exercise}", kinematics_node.main, pack=exercise, session=SESSION, stats=kin_stats[exercise],
                after=("recorder", *(f"estimator-{ex}" for ex in subjects)),
            )
        graph.wait_ready(GRAPH_READY_S)
        nodes = f"recorder + {len(subjects)} estimator" + (f" + {len(subjects)} kinematics" if kin_stats else "") + " nodes"
        log(f"live graph up: {nodes}; replaying {recording.name} at rate {rate or 'max'} (joints from {joints_from})")
        started = time.perf_counter()
        replay_stats = replayer.main(
            ZenohOptions(connect=(endpoint,)), recording, rate=rate, session_name=SESSION,
            progress=sys.stderr.isatty(), exclude=(f"msk/{SESSION}/joints",) if joints_from == "imu" else (),
            wait_nodes=tuple(graph.nodes), wait_nodes_s=GRAPH_READY_S,
        )
        deadline = time.monotonic() + DRAIN_S

        def left() -> float:
            return max(1.0, deadline - time.monotonic())

        if kin_stats:
            wait_for(
                f"the kinematics nodes to receive all {counts['imu']} IMU samples",
                lambda: all(k.samples_in >= counts["imu"] for k in kin_stats.values()),
                lambda: ", ".join(f"{ex} {k.samples_in}" for ex, k in kin_stats.items()), left(),
            )
            joints_total = sum(k.frames_out for k in kin_stats.values())
            joints_per_exercise = {ex: k.frames_out for ex, k in kin_stats.items()}
        else:
            joints_total = sum(counts["joints"].values())
            joints_per_exercise = counts["joints"]
        wait_for(
            f"every estimator to receive all {joints_total} joint frames",
            lambda: all(e.frames_in >= joints_total for e in est_stats.values()),
            lambda: ", ".join(f"{ex} {e.frames_in}" for ex, e in est_stats.items()), left(),
        )
        activation_frames = sum(e.frames_out for e in est_stats.values()) * len(METHODS)
        expected_messages = replay_stats.published + (joints_total if kin_stats else 0) + activation_frames
        wait_for(f"the recorder to write all {expected_messages} messages", lambda: rec_stats.written >= expected_messages,
                 lambda: f"{rec_stats.written} written", left())
        elapsed = time.perf_counter() - started
    log(
        f"replayed {replay_stats.published} messages"
        + (f" (left out {replay_stats.excluded} recorded joint frames); kinematics nodes published "
           + ", ".join(f"{n} {ex}" for ex, n in joints_per_exercise.items()) + " joint frames" if kin_stats else "")
        + "; estimated " + ", ".join(f"{est_stats[ex].frames_out} {ex}" for ex in est_stats)
        + f" frames x {len(METHODS)} methods in {elapsed:.1f} s; recorded {rec_stats.written}/{expected_messages} messages"
    )
    return {
        "joints_from": joints_from, "replayed": replay_stats.published, "recorded": rec_stats.written,
        "expected_messages": expected_messages, "joint_frames": joints_per_exercise,
        "estimated_frames": {ex: s.frames_out for ex, s in est_stats.items()},
        "flagged": {ex: s.flagged for ex, s in est_stats.items()},
        "kinematics": {ex: {"frames_out": k.frames_out, "incomplete": k.frames_incomplete, "calibrations": k.calibrations}
                       for ex, k in kin_stats.items()},
        "seconds": elapsed,
    }


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
            frame = recorded.decode()
            frames[frame.method].append(frame)
        elif recorded.type_name == "msk.LoadEvent":
            load_events.append(recorded.decode())
    scores, curves = [], {}
    for window in trial_windows(load_events):
        folders = _trial_folders(recordings, window.exercise)
        folder = next((f for f in folders if f.name == window.name), None)
        if folder is None:
            continue
        role = "calibration" if folder == folders[0] else "held out"
        truth = read_sto(folder / "truth_activations.sto")
        for method in METHODS:
            inside = [f for f in frames[method] if window.start_s - 1e-6 <= f.time_s <= window.end_s + 1e-6 and set(f.groups) == set(truth.columns)]
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
            per_group = {g: float(np.sqrt(np.mean((estimated[ok, i] - true[ok, i]) ** 2))) for i, g in enumerate(groups)}
            scores.append(MethodScore(
                exercise=window.exercise, trial=window.name, role=role, method=method, frames=len(inside),
                activation_rmse=float(np.sqrt(np.mean((estimated[ok] - true[ok]) ** 2))),
                torque_rmse_nm=float(np.sqrt(np.mean(residual[ok] ** 2))),
                flagged=int(sum(1 for f in inside if f.flags)),
                solve_us_median=float(np.median(solve)), solve_us_p99=float(np.percentile(solve, 99)),
                latency_ms_median=float(np.median(latency)), latency_ms_p99=float(np.percentile(latency, 99)),
                per_group_rmse=per_group,
            ))
            curves[(window.name, method)] = (t, estimated, true, groups)
    return scores, curves


def markdown(scores: list[MethodScore]) -> str:
    lines = [
        "| trial | role | method | frames | activation RMSE | torque residual RMS (N·m) | flagged | solve µs (median / p99) | latency ms (median / p99) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for s in scores:
        lines.append(
            f"| {s.trial} | {s.role} | {s.method} | {s.frames} | {s.activation_rmse:.3f} | {s.torque_rmse_nm:.2f} | {s.flagged} | "
            f"{s.solve_us_median:.0f} / {s.solve_us_p99:.0f} | {s.latency_ms_median:.2f} / {s.latency_ms_p99:.2f} |"
        )
    return "\n".join(lines)


def strength_markdown(calibration: dict) -> str:
    """Per exercise: calibrated F_max against the generator's truth and the model's reference, with the status."""
    lines = []
    for exercise, rep in calibration.items():
        lines += [
            f"### {exercise}: calibrated on {rep['trials']['lift']}"
            + (f" + {rep['trials']['isometric']} isometric MVC trials" if rep["trials"]["isometric"] else "")
            + f" in {rep['seconds']:.1f} s",
            "",
            f"Median |F_max / truth - 1|: {100 * rep['strength_error_median']:.1f} % "
            f"(model reference {100 * rep['reference_error_median']:.1f} %).",
            "",
            "| group | status | calibrated F_max (N) | true F_max (N) | error | reference (N) | reference error |",
            "|---|---|---|---|---|---|---|",
        ]
        for g, v in rep["groups"].items():
            lines.append(
                f"| {g} | {v['status']} | {v['f_max_n']:.0f} | {v['truth_n']:.0f} | {100 * (v['f_max_n'] / v['truth_n'] - 1):+.0f} % "
                f"| {v['reference_n']:.0f} | {100 * (v['reference_n'] / v['truth_n'] - 1):+.0f} % |"
            )
        lines.append("")
    return "\n".join(lines)


STRENGTH_COLOURS = {"identified": "tab:green", "not_calibrated": "dimgrey"}


def plot_strength(calibration: dict, out: Path) -> Path:
    """F_max / truth per group: calibrated and the model's reference (1 = exact)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(calibration), 1, figsize=(13, 2.8 * len(calibration)), squeeze=False)
    for ax, (exercise, rep) in zip(axes[:, 0], calibration.items()):
        groups = list(rep["groups"])
        x = np.arange(len(groups))
        cal = [rep["groups"][g]["f_max_n"] / rep["groups"][g]["truth_n"] for g in groups]
        ref = [rep["groups"][g]["reference_n"] / rep["groups"][g]["truth_n"] for g in groups]
        ax.bar(x - 0.2, ref, 0.4, color="lightgrey")
        status = [rep["groups"][g]["status"] for g in groups]
        ax.bar(x + 0.2, cal, 0.4, color=[STRENGTH_COLOURS.get(st, "tab:orange") for st in status])
        ax.axhline(1.0, color="black", lw=1)
        ax.axhspan(0.9, 1.1, color="tab:green", alpha=0.08)
        ax.set_xticks(x, groups, rotation=45, ha="right", fontsize=8)
        ax.set_ylim(0.0, max(1.5, 1.05 * max(cal + ref)))
        ax.set_ylabel("F_max / truth")
        ax.set_title(f"{exercise}: median error {100 * rep['strength_error_median']:.0f} % "
                     f"(reference {100 * rep['reference_error_median']:.0f} %)", fontsize=10)
    from matplotlib.patches import Patch

    handles = [Patch(color="lightgrey", label="model reference"),
               Patch(color=STRENGTH_COLOURS["identified"], label="calibrated: identified"),
               Patch(color="tab:orange", label="calibrated: combination / unidentified / at bound"),
               Patch(color=STRENGTH_COLOURS["not_calibrated"], label="no EMG: kept at reference")]
    axes[0, 0].legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    fig.tight_layout()
    path = out / "strength.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot(curves: dict, scores: list[MethodScore], out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    for trial in sorted({s.trial for s in scores if s.role == "held out"}):
        truth_t, _, truth, groups = curves[(trial, "proposed")]
        # The four groups that work hardest in the truth: where people look first.
        top = np.argsort(truth.max(axis=0))[::-1][:4]
        fig, axes = plt.subplots(len(top), 1, figsize=(10, 2.2 * len(top)), sharex=True)
        for ax, gi in zip(np.atleast_1d(axes), top):
            ax.plot(truth_t, truth[:, gi], color="black", lw=2, label="truth")
            for method, colour in zip(METHODS, ("tab:green", "tab:red", "tab:blue")):
                t, est, _, _ = curves[(trial, method)]
                ax.plot(t, est[:, gi], color=colour, lw=1, label=method)
            ax.set_ylabel(groups[gi])
            ax.set_ylim(0, 1)
        np.atleast_1d(axes)[0].legend(loc="upper right", ncol=4, fontsize=8)
        np.atleast_1d(axes)[-1].set_xlabel("time in trial (s)")
        fig.suptitle(f"{trial} (held out from calibration): live activations vs truth")
        fig.tight_layout()
        path = out / f"{trial}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)
    return written


def main(
    *,
    recordings: Path = DEFAULT_RECORDINGS,
    out: Path,
    rate: float | None = None,
    exercises: list[str] | None = None,
    joints_from: str = "imu",
    endpoint: str | None = None,
    log=print,
) -> dict:
    recording = recordings / "demo_session.mcap"
    if not recording.is_file():
        raise InputError("demo recording not found (generate it with `msk synth`)", path=recording)
    out.mkdir(parents=True, exist_ok=True)
    if endpoint is None:
        from services.zenoh_session import free_loopback_endpoint

        endpoint = free_loopback_endpoint()
    available = sorted(p.name for p in (recordings / "demo").iterdir() if p.is_dir())
    unknown = sorted(set(exercises or []) - set(available))
    if unknown:
        raise InputError(f"no such exercise in the demo session; available: {', '.join(available)}", field="--exercise", value=unknown)
    exercises = exercises or available
    subjects, calibration = {}, {}
    for exercise in exercises:
        subjects[exercise], calibration[exercise] = calibrate(recordings, out, exercise, log)
    live_mcap = out / "live.mcap"
    graph = run_live_graph(recording, live_mcap, subjects, endpoint, rate, log, joints_from=joints_from)
    scores, curves = score(live_mcap, recordings)
    table = markdown(scores)
    plots = plot(curves, scores, out) + [plot_strength(calibration, out)]
    summary = {"calibration": calibration, "graph": graph, "scores": [s.__dict__ for s in scores]}
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=str) + "\n")
    (out / "report.md").write_text(
        "# msk-live demo\n\nLive estimates (Zenoh graph fed by the replayed session) scored against the synthetic truth.\n"
        f"Replay rate: {rate or 'max'}. Latency = estimator publish time - input arrival time"
        + (" (at rate max it includes the queue behind the replay burst; run with --rate 1 for live latency)" if rate is None else "")
        + ".\n\n"
        + table + "\n\n" + "\n".join(f"![{p.stem}]({p.name})" for p in plots) + "\n\n"
        + "## Calibrated strength vs the generator's truth\n\n" + strength_markdown(calibration)
    )
    log("")
    log(table)
    log("")
    log(f"report: {out / 'report.md'}; recording of the live graph: {live_mcap} (open it in Foxglove); plots: "
        + ", ".join(str(p) for p in plots))
    return summary


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder (default: out/demo)")
    parser.add_argument("--recordings", type=Path, default=DEFAULT_RECORDINGS, help="folder with demo_session.mcap and demo/ (default: the embedded one)")
    parser.add_argument("--rate", default="max", help="replay speed: 'max' (default) or a factor, 1 = real time")
    parser.add_argument("--exercise", action="append", default=None, help="only this exercise (repeatable; default: all)")
    parser.add_argument(
        "--joints-from", choices=["imu", "recorded"], default="imu",
        help="imu (default): kinematics nodes compute joint angles from the replayed IMU streams, as on a real rig; "
        "recorded: replay the session's joint angles",
    )


def run_from_args(args: argparse.Namespace) -> int:
    main(recordings=args.recordings, out=args.out, rate=replayer.parse_rate(args.rate), exercises=args.exercise, joints_from=args.joints_from)
    return 0
