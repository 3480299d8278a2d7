"""Estimator node: joint kinematics in, muscle activations out, one warm per-frame QP per method.

Subscribes to ``msk/<session>/joints`` (:class:`JointAngles`) and ``msk/<session>/load`` (:class:`LoadEvent`), runs
:class:`msk_core.estimate.FrameEstimator` for every requested method on every frame, and publishes
:class:`ActivationFrame` on ``msk/<session>/activations/<method>``. Zenoh callbacks only enqueue; one worker thread
estimates frames in arrival order, so none is skipped and the solver stays warm. A frame the estimator cannot solve
(NaN input, torque beyond capacity, a pose the model does not cover) is published with its flag, never dropped.
Phase: the JointAngles' own when set; else, with a subject profile holding a rep template (``msk calibrate`` on a
kinematic phase coordinate), the causal :class:`msk_core.estimate.phase.LivePhase` on that coordinate; else unknown.
Run ``python -m services.estimator --pack bench_press --session lab`` or ``msk estimator``.
"""

from __future__ import annotations

import argparse
import bisect
import logging
import queue
import signal
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zenoh

from msk_core.errors import ConfigError
from msk_core.estimate import FrameEstimator
from msk_core.estimate.frame import FrameResult
from msk_core.estimate.phase import LivePhase
from msk_core.estimate.profile import SubjectProfile
from msk_core.estimate.trial import GRAVITY
from services import messages, topics
from services.graph import ReadySpec, declare_ready
from services.zenoh_session import (
    ZenohOptions,
    add_zenoh_arguments,
    declare_data_publisher,
    open_session,
    options_from_args,
    publish,
)

log = logging.getLogger(__name__)



@dataclass
class EstimatorStats:
    frames_in: int = 0
    frames_out: int = 0
    load_events: int = 0
    flagged: dict[str, int] = field(default_factory=dict)
    rejected: int = 0  # input frames whose coordinates do not match the pack
    other_exercise: int = 0  # frames skipped while a LoadEvent says another exercise is under way
    last_error: str = ""


class LoadTimeline:
    """Barbell load and exercise in effect at a given device time.

    Load events and joint angles reach the estimator by different paths (the joints through a kinematics node, which
    lags), so a load event is applied to the frames by device time, not by arrival order. An event without a device
    time takes effect from the latest frame seen.
    """

    def __init__(self, initial_load_kg: float = 0.0) -> None:
        self._times: list[int] = [-1]
        self._events: list[tuple[float, str]] = [(float(initial_load_kg), "")]
        self._latest_frame_ns = 0

    def add(self, device_time_ns: int, mass_kg: float, exercise: str) -> None:
        when = int(device_time_ns) if device_time_ns else self._latest_frame_ns
        index = bisect.bisect_right(self._times, when)
        previous_exercise = self._events[index - 1][1]
        self._times.insert(index, when)
        self._events.insert(index, (float(mass_kg), exercise or previous_exercise))

    def at(self, device_time_ns: int) -> tuple[float, str]:
        """(mass in kg, exercise or "" when never named) in effect at ``device_time_ns``."""
        self._latest_frame_ns = max(self._latest_frame_ns, int(device_time_ns))
        return self._events[bisect.bisect_right(self._times, int(device_time_ns)) - 1]


class CoordinateMapper:
    """Reorders a JointAngles message's coordinates into the pack's order (names must all be present)."""

    def __init__(self, pack_coordinates: list[str]) -> None:
        self.pack_coordinates = pack_coordinates
        self._cache: dict[tuple[str, ...], np.ndarray] = {}

    def indices(self, names: tuple[str, ...]) -> np.ndarray:
        index = self._cache.get(names)
        if index is None:
            missing = [c for c in self.pack_coordinates if c not in names]
            if missing:
                raise ConfigError(
                    f"joint-angle messages lack the pack's coordinates {missing}; they carry {list(names)}",
                    field="JointAngles.coordinates",
                )
            position = {name: i for i, name in enumerate(names)}
            index = np.array([position[c] for c in self.pack_coordinates], dtype=int)
            self._cache[names] = index
        return index

    def take(self, message, field_name: str) -> np.ndarray:
        values = np.asarray(getattr(message, field_name), dtype=float)
        if values.size == 0:
            return np.zeros(len(self.pack_coordinates))
        return values[self.indices(tuple(message.coordinates))]


def to_message(result: FrameResult, *, method: str, groups, coordinates, time_s: float, arrival_ns: int) -> messages.ActivationFrame:
    frame = messages.ActivationFrame(
        time_s=time_s,
        method=method,
        groups=list(groups),
        activations=result.activations.tolist(),
        forces_n=result.forces.tolist(),
        solver_status=result.status.value,
        iterations=int(result.iterations),
        solve_time_s=float(result.solve_time_s),
        input_arrival_ns=arrival_ns,
    )
    if result.phase is not None:
        frame.phase = float(result.phase)
    if not result.flagged:
        std = result.activation_std
        if std is not None and np.all(np.isfinite(std)):
            frame.activation_std.extend(std.tolist())
    else:
        frame.flags.append(result.status.value)
    for name, tau_id, tau_model, residual in zip(coordinates, result.torques, result.model_torques, result.residual):
        frame.torques.add(coordinate=name, inverse_dynamics_nm=float(tau_id), model_nm=float(tau_model), residual_nm=float(residual))
    return frame


def main(
    config: ZenohOptions,
    *,
    pack: str,
    session: str,
    methods: list[str],
    subject_path: Path | None = None,
    initial_load_kg: float = 0.0,
    exercise: str | None = None,
    stop_event: threading.Event | None = None,
    ready_event: threading.Event | None = None,
    ready_key: ReadySpec | None = None,
    stats: EstimatorStats | None = None,
) -> EstimatorStats:
    stop_event = stop_event or threading.Event()
    stats = stats if stats is not None else EstimatorStats()
    subject = SubjectProfile.load(subject_path) if subject_path is not None else None
    estimators = {m: FrameEstimator(pack, subject=subject, method=m) for m in methods}
    for estimator in estimators.values():  # compiled kernels and solvers ready before the first live frame
        estimator.warm_up()
    first = next(iter(estimators.values()))
    mapper = CoordinateMapper(list(first.coordinates))
    # The subject's rep template (calibration) gives the phase when JointAngles carry none (None: no template).
    live_phase = LivePhase.from_profile(subject, first.coordinates) if subject is not None else None
    inbox: queue.SimpleQueue = queue.SimpleQueue()
    loads = LoadTimeline(initial_load_kg)
    # Several estimators (one per exercise pack) may share a session: each follows the exercise the load events name.
    exercise = exercise if exercise is not None else first.pack.name

    joints_key, load_key = topics.joints_key(session), topics.load_key(session)

    def on_sample(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        if key in (joints_key, load_key):
            inbox.put(("load" if key == load_key else "joints", messages.now_ns(), sample.payload.to_bytes()))

    with open_session(config) as zsession:
        publishers = {
            m: declare_data_publisher(zsession, topics.activations_key(session, m), "msk.ActivationFrame") for m in methods
        }
        # One subscriber for both keys keeps load events and frames in their publication order.
        subscribers = [zsession.declare_subscriber(f"{topics.session_prefix(session)}/*", on_sample)]
        token = declare_ready(zsession, ready_key)  # noqa: F841 - alive while the node runs (services.graph)
        if ready_event is not None:
            ready_event.set()
        try:
            while not stop_event.is_set():
                try:
                    kind, arrival_ns, payload = inbox.get(timeout=0.05)
                except queue.Empty:
                    continue
                if kind == "load":
                    event = messages.decode("msk.LoadEvent", payload)
                    loads.add(event.device_time_ns, event.barbell_mass_kg, event.exercise)
                    stats.load_events += 1
                    continue
                stats.frames_in += 1
                joints = messages.decode("msk.JointAngles", payload)
                load_kg, current_exercise = loads.at(joints.device_time_ns)
                if current_exercise and current_exercise != exercise:
                    stats.other_exercise += 1
                    continue
                try:
                    q, qd, qdd = (mapper.take(joints, f) for f in ("q", "qd", "qdd"))
                except ConfigError as error:
                    stats.rejected += 1
                    if stats.rejected == 1:
                        log.error("%s", error)
                    stats.last_error = str(error)
                    continue
                # Unset = unknown (prior pooled over phases); negative = between reps (rest prior); else [0, 1).
                time_s = joints.device_time_ns / 1e9
                if joints.HasField("phase"):
                    phase = float(joints.phase)
                elif live_phase is not None:  # no phase upstream: track it on the subject's rep template
                    phase = live_phase.update(time_s, q)
                else:
                    phase = None
                for method, estimator in estimators.items():
                    result = estimator.step(q, qd, qdd, hand_load_newton=load_kg * GRAVITY, phase=phase)
                    frame = to_message(
                        result, method=method, groups=estimator.groups, coordinates=estimator.coordinates,
                        time_s=time_s, arrival_ns=arrival_ns,
                    )
                    if result.flagged:
                        stats.flagged[result.status.value] = stats.flagged.get(result.status.value, 0) + 1
                    frame.publish_ns = messages.now_ns()
                    publish(publishers[method], frame)
                stats.frames_out += 1
        finally:
            for subscriber in subscribers:
                subscriber.undeclare()
    return stats


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--pack", required=True, help="model pack name (e.g. bench_press, deadlift) or path")
    parser.add_argument("--session", required=True, help="session name: topics msk/<session>/...")
    parser.add_argument(
        "--method", action="append", choices=["proposed", "so", "hybrid"], default=None,
        help="estimation method (repeatable; default: proposed with --subject, else so)",
    )
    parser.add_argument("--subject", type=Path, default=None, help="subject profile JSON from `msk calibrate`")
    parser.add_argument("--load-kg", type=float, default=0.0, help="barbell mass until the first LoadEvent (default 0)")
    parser.add_argument(
        "--exercise", default=None,
        help="estimate only while load events name this exercise (default: the pack's name, e.g. bench_press)",
    )
    add_zenoh_arguments(parser)


def run_from_args(args: argparse.Namespace) -> int:
    methods = args.method or (["proposed"] if args.subject else ["so"])
    if "proposed" in methods and args.subject is None:
        raise ConfigError("method 'proposed' needs --subject (a calibrated profile with its prior)", field="--method", value="proposed")
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    print(f"estimating {', '.join(methods)} on msk/{args.session}/joints with pack {args.pack}", file=sys.stderr, flush=True)
    stats = main(
        options_from_args(args), pack=args.pack, session=args.session, methods=methods,
        subject_path=args.subject, initial_load_kg=args.load_kg, exercise=args.exercise, stop_event=stop,
    )
    print(f"estimated {stats.frames_out} frames; flagged {stats.flagged or 'none'}; rejected {stats.rejected}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO)
    _parser = argparse.ArgumentParser(description=__doc__)
    add_arguments(_parser)
    sys.exit(run_from_args(_parser.parse_args()))
