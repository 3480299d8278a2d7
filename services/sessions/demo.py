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

import sys
import time
from dataclasses import dataclass
from pathlib import Path

from msk_core.errors import InputError
from msk_core.io.files import json_text
from services.nodes import estimator, kinematics_node, recorder, replayer
from services.nodes.readiness import NODE_READY_TIMEOUT_S
from services.sessions.demo_subject import RECORDINGS, calibrate
from services.sessions.graph import Graph, wait_for
from services.sessions.live_scoring import (  # noqa: F401 - re-exported: imported from services.sessions.demo before
    METHODS,
    MethodScore,
    TrialWindow,
    _trial_folders,
    markdown,
    score,
    trial_windows,
)
from services.surfaces.reports.demo import plot_activations, plot_strength, strength_markdown
from services.transport import messages, session_graph
from services.transport.mcap_io import read_messages
from services.transport.zenoh_session import ZenohOptions

DEFAULT_RECORDINGS = RECORDINGS
SESSION = "demo"


GRAPH_READY_S = NODE_READY_TIMEOUT_S
#: With every node done, the recorder writing nothing new for this long has all it will get (s).
RECORDER_STALL_S = 15.0
DRAIN_S = 600.0  # the whole replay at rate max on a loaded 2-core machine takes ~1-2 min; generous, and bounded


def run_live_graph(
    recording: Path,
    out_mcap: Path,
    subjects: dict[str, Path],
    endpoint: str,
    rate: float | None,
    log,
    *,
    joints_from: str = "imu",
) -> dict:
    """Recorder + (kinematics +) estimator nodes as Zenoh peers, the replayer publishing the recording.

    ``joints_from="imu"``: the recording's joint angles are left out and kinematics nodes compute them from the IMU
    streams, as on a real rig; ``"recorded"``: the recorded joint angles are replayed as they are.
    """
    imu_samples, recorded_joints = _recorded_counts(recording, list(subjects))
    stats = _DemoStats(
        recorder.RecorderStats(),
        {ex: estimator.EstimatorStats() for ex in subjects},
        {ex: kinematics_node.KinematicsStats() for ex in subjects} if joints_from == "imu" else {},
    )
    with Graph(SESSION, endpoint) as graph:
        _start_demo_nodes(graph, subjects, out_mcap, stats)
        graph.wait_ready(GRAPH_READY_S)
        nodes = (
            f"recorder + {len(subjects)} estimator"
            + (f" + {len(subjects)} kinematics" if stats.kinematics else "")
            + " nodes"
        )
        log(f"live graph up: {nodes}; replaying {recording.name} at rate {rate or 'max'} (joints from {joints_from})")
        started = time.perf_counter()
        replay_stats = replayer.main(
            ZenohOptions(connect=(endpoint,)),
            recording,
            rate=rate,
            session_name=SESSION,
            progress=sys.stderr.isatty(),
            exclude=(f"msk/{SESSION}/joints",) if joints_from == "imu" else (),
            wait_nodes=tuple(graph.nodes),
            wait_nodes_s=GRAPH_READY_S,
        )
        joints_per_exercise, expected_messages = _wait_drained(stats, imu_samples, recorded_joints, replay_stats)
        elapsed = time.perf_counter() - started
    est_stats, kin_stats, rec_stats = stats.estimators, stats.kinematics, stats.recorder
    log(
        f"replayed {replay_stats.published} messages"
        + (
            f" (left out {replay_stats.excluded} recorded joint frames); kinematics nodes published "
            + ", ".join(f"{n} {ex}" for ex, n in joints_per_exercise.items())
            + " joint frames"
            if kin_stats
            else ""
        )
        + "; estimated "
        + ", ".join(f"{est_stats[ex].frames_out} {ex}" for ex in est_stats)
        + f" frames x {len(METHODS)} methods in {elapsed:.1f} s; recorded {rec_stats.written - rec_stats.node_status}/{expected_messages} messages"
        + f" (and {rec_stats.node_status} node status)"
    )
    missed = expected_messages - (rec_stats.written - rec_stats.node_status)
    if missed > 0:
        log(
            f"the recorder missed {missed} data messages: it received nothing for {RECORDER_STALL_S:.0f} s after the "
            "nodes were done (the newest-wins topics, activations, envelopes and status, drop what a subscriber "
            "starved of CPU cannot take; docs/topics.md)"
        )
    return {
        "joints_from": joints_from,
        "replayed": replay_stats.published,
        "recorded": rec_stats.written - rec_stats.node_status,
        "expected_messages": expected_messages,
        "joint_frames": joints_per_exercise,
        "estimated_frames": {ex: s.frames_out for ex, s in est_stats.items()},
        "flagged": {ex: s.flagged for ex, s in est_stats.items()},
        "kinematics": {
            ex: {"frames_out": k.frames_out, "incomplete": k.frames_incomplete, "calibrations": k.calibrations}
            for ex, k in kin_stats.items()
        },
        "seconds": elapsed,
    }


@dataclass
class _DemoStats:
    """The demo graph's thread nodes' live counters: the recorder's, and per exercise the estimator's and (joints
    from the IMUs) the kinematics node's."""

    recorder: recorder.RecorderStats
    estimators: dict[str, estimator.EstimatorStats]
    kinematics: dict[str, kinematics_node.KinematicsStats]


def _recorded_counts(recording: Path, exercises: list[str]) -> tuple[int, dict[str, int]]:
    """The recording's IMU samples, and its joint frames per exercise (of the exercise its load events name)."""
    imu_samples, recorded_joints = 0, {ex: 0 for ex in exercises}
    current = ""
    for recorded in read_messages(recording):
        if recorded.type_name == "msk.LoadEvent":
            current = recorded.decode(messages.LoadEvent).exercise or current
        elif recorded.type_name == "msk.ImuSample":
            imu_samples += 1
        elif recorded.type_name == "msk.JointAngles" and current in recorded_joints:
            recorded_joints[current] += 1
    return imu_samples, recorded_joints


def _start_demo_nodes(graph: Graph, subjects: dict[str, Path], out_mcap: Path, stats: _DemoStats) -> None:
    """The declared graph (services.transport.session_graph) with one estimator (and kinematics node) per exercise, as thread
    nodes; each waits for the nodes that read what it publishes (the kinematics' joints go to the recorder and every
    estimator, each following the exercise the load events name)."""
    declared = [session_graph.NODES["recorder"]]
    declared += [session_graph.instance("estimator", f"estimator-{ex}") for ex in subjects]
    declared += [session_graph.instance("kinematics", f"kinematics-{ex}") for ex in stats.kinematics]

    def start(node: session_graph.NodeDecl, after: tuple[str, ...]) -> None:
        kind, _, exercise = node.name.partition("-")
        if kind == "recorder":
            graph.add_thread(node.name, recorder.main, out_mcap, stats=stats.recorder, after=after)
        elif kind == "estimator":
            settings = estimator.EstimatorSettings(
                exercise, SESSION, tuple(METHODS), subjects[exercise], exercise=exercise
            )
            graph.add_thread(node.name, estimator.main, settings, stats=stats.estimators[exercise], after=after)
        else:
            kinematics = kinematics_node.KinematicsSettings(exercise, SESSION)
            graph.add_thread(node.name, kinematics_node.main, kinematics, stats=stats.kinematics[exercise], after=after)

    session_graph.start_declared(declared, start)


def _wait_drained(
    stats: _DemoStats, imu_samples: int, recorded_joints: dict[str, int], replay_stats: replayer.ReplayStats
) -> tuple[dict[str, int], int]:
    """Bounded waits (DRAIN_S in all) until the kinematics nodes processed every IMU sample, the estimators every
    joint frame and the recorder wrote every data message; returns the joint frames per exercise and the number of
    data messages recorded."""
    kin_stats, est_stats, rec_stats = stats.kinematics, stats.estimators, stats.recorder
    deadline = time.monotonic() + DRAIN_S

    def left() -> float:
        return max(1.0, deadline - time.monotonic())

    if kin_stats:
        wait_for(
            f"the kinematics nodes to process all {imu_samples} IMU samples",
            lambda: all(k.samples_done >= imu_samples for k in kin_stats.values()),
            lambda: ", ".join(f"{ex} {k.samples_done}" for ex, k in kin_stats.items()),
            left(),
        )
        joints_total = sum(k.frames_out for k in kin_stats.values())
        joints_per_exercise = {ex: k.frames_out for ex, k in kin_stats.items()}
    else:
        joints_total = sum(recorded_joints.values())
        joints_per_exercise = recorded_joints
    wait_for(
        f"every estimator to process all {joints_total} joint frames",
        lambda: all(e.frames_done >= joints_total for e in est_stats.values()),
        lambda: ", ".join(f"{ex} {e.frames_done}" for ex, e in est_stats.items()),
        left(),
    )
    activation_frames = sum(e.frames_out for e in est_stats.values()) * len(METHODS)
    expected_messages = replay_stats.published + (joints_total if kin_stats else 0) + activation_frames
    # the data messages; the nodes' own status (one a second each) is recorded beside them and not counted here
    _wait_recorded(rec_stats, expected_messages, left())
    return joints_per_exercise, expected_messages


def _wait_recorded(rec_stats: recorder.RecorderStats, expected: int, timeout_s: float) -> None:
    """Until the recorder wrote ``expected`` data messages, or (every node done) wrote nothing new for
    :data:`RECORDER_STALL_S`: then the run says what it missed and its summary counts it (``recorded`` against
    ``expected_messages``), rather than the wait running out minutes later."""
    last, changed = -1, time.monotonic()

    def recorded() -> bool:
        nonlocal last, changed
        written = rec_stats.written - rec_stats.node_status
        if written != last:
            last, changed = written, time.monotonic()
        return written >= expected or time.monotonic() - changed >= RECORDER_STALL_S

    wait_for(
        f"the recorder to write all {expected} messages",
        recorded,
        lambda: f"{rec_stats.written - rec_stats.node_status} written",
        timeout_s,
    )


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
        from services.transport.zenoh_session import free_loopback_endpoint

        endpoint = free_loopback_endpoint()
    available = sorted(p.name for p in (recordings / "demo").iterdir() if p.is_dir())
    unknown = sorted(set(exercises or []) - set(available))
    if unknown:
        raise InputError(
            f"no such exercise in the demo session; available: {', '.join(available)}",
            field="--exercise",
            value=unknown,
        )
    exercises = exercises or available
    subjects, calibration = {}, {}
    for exercise in exercises:
        subjects[exercise], calibration[exercise] = calibrate(recordings, out, exercise, log)
    live_mcap = out / "live.mcap"
    graph = run_live_graph(recording, live_mcap, subjects, endpoint, rate, log, joints_from=joints_from)
    scores, curves = score(live_mcap, recordings)
    table = markdown(scores)
    plots = plot_activations(curves, scores, out) + [plot_strength(calibration, out)]
    summary = {"calibration": calibration, "graph": graph, "scores": [s.__dict__ for s in scores]}
    (out / "summary.json").write_text(json_text(summary, default=str))
    (out / "report.md").write_text(
        "# msk-live demo\n\nLive estimates (Zenoh graph fed by the replayed session) scored against the synthetic truth.\n"
        f"Replay rate: {rate or 'max'}. Latency = estimator publish time - input arrival time"
        + (
            " (at rate max it includes the queue behind the replay burst; run with --rate 1 for live latency)"
            if rate is None
            else ""
        )
        + ".\n\n"
        + table
        + "\n\n"
        + "\n".join(f"![{p.stem}]({p.name})" for p in plots)
        + "\n\n"
        + "## Calibrated strength vs the generator's truth\n\n"
        + strength_markdown(calibration)
    )
    log("")
    log(table)
    log("")
    log(
        f"report: {out / 'report.md'}; recording of the live graph: {live_mcap} (open it in Foxglove); plots: "
        + ", ".join(str(p) for p in plots)
    )
    return summary
