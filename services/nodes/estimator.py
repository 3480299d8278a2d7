"""Estimator node: joint kinematics in, muscle activations out, one warm per-frame QP per method.

Subscribes to ``msk/<session>/joints`` (:class:`JointAngles`) and ``msk/<session>/load`` (:class:`LoadEvent`), runs
:class:`msk_core.estimate.FrameEstimator` for every requested method on every frame, and publishes
:class:`ActivationFrame` on ``msk/<session>/activations/<method>``. Zenoh callbacks only enqueue; one worker thread
estimates frames in arrival order, so none is skipped and the solver stays warm. A frame the estimator cannot solve
(NaN input, torque beyond capacity, a pose the model does not cover) is published with its flag, never dropped.
Phase: the JointAngles' own when set; else, with a subject profile holding a rep template (``msk calibrate`` on a
kinematic phase coordinate), the causal :class:`msk_core.estimate.phase.LivePhase` on that coordinate; else unknown.
EMG (with a subject profile that carries MVC normalisation, or ``--emg-map``): subscribes to ``msk/<session>/emg/**``,
runs the causal envelope chain (:mod:`msk_core.estimate.live_emg`), publishes :class:`EmgEnvelope` on
``msk/<session>/envelopes`` (one per EMG chunk), fills ``ActivationFrame.measured_envelope`` and feeds the ``assisted``
method; EMG gaps, a stalled source and channels without MVC are flagged in the frames (``emg_gap``, ``emg_stalled``,
``no_mvc``) and counted in :class:`EstimatorStats`. With ``--emg-clock host`` each EMG source's clock is mapped onto
the host clock by the driver's receipt times (``EmgChunk.host_time_ns``, so a replay maps as live did) less its
stated latency (``--emg-latency-ms``), until the accelerations say better (``--emg-align acceleration``, the
default): the node also reads the EMG sensors' accelerometers (``msk/<session>/acc/<source>``) and the trackers'
samples (``msk/<session>/imu/<tracker>``, mapped as the kinematics node maps them, ``--imu-latency-ms``), measures
each EMG clock against each tracker's (:mod:`msk_core.estimate.clock_alignment`) and maps the EMG through the
trackers it locks on. ``--emg-wait-ms``: a joint frame waits up to that long for the EMG of its instant (a device
that delivers later than the trackers). The node's status (``msk/<session>/status/estimator``) carries, per stream,
the offset applied, its spread, the latency, the method, why, the arrival mapping an acceleration offset replaces and
every tracker's estimate (``DeviceStatus.clocks``). Electrode quality: one monitor per EMG source judges each
electrode from the raw chunks (:mod:`msk_core.estimate.live_quality`); the status carries per electrode its channel,
group, state (unknown, good, check, bad), reasons, time in check and bad and its fault episodes
(``DeviceStatus.electrodes``), published at once when a state changes; a bad electrode is left out of its group's
envelope, and the frames that read such an envelope carry ``electrode_bad``. Fatigue: per electrode the median and
mean frequency of each rep's raw EMG and their trend over the set (:mod:`msk_core.estimate.live_fatigue`, reps from
the frames' phase, sets by :class:`msk_core.signal.sets.SetTracker` from the operator's marks and rest detection), in the status (``DeviceStatus.fatigue``).
Run ``python -m services.nodes.estimator --pack bench_press --session lab`` or ``msk estimator``.
"""

from __future__ import annotations

import argparse
import bisect
import logging
import queue
import sys
import threading
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from msk_core.errors import ConfigError, MskError, parse_pairs
from msk_core.estimate import FrameEstimator
from msk_core.estimate.clock_alignment import AccelerationAlignment
from msk_core.estimate.emg_chunk import RawEmgChunk
from msk_core.estimate.frame import UNCERTAIN_METHODS, FrameResult, Method
from msk_core.estimate.live_emg import ClockMode, EmgCounters, EmgSetup, JointsClock, LiveEmg
from msk_core.estimate.live_fatigue import ElectrodeFatigueReport, LiveFatigue
from msk_core.estimate.live_quality import ElectrodeReport, LiveQuality
from msk_core.estimate.phase import LivePhase
from msk_core.estimate.profile import SubjectProfile
from msk_core.model.pack import available_packs, is_known_exercise
from msk_core.signal.host_clock import ClockReport, DeviceClocks, latency_argv, parse_latencies
from msk_core.signal.sets import SetTracker
from msk_core.units import GRAVITY, load_problem
from services.nodes.estimator_options import SOLVERS, add_live_synergists_argument, add_solver_argument
from services.nodes.node_runtime import (
    ESTIMATOR_NODE,
    Inbound,
    InputContinuity,
    InputCounts,
    NodeInputs,
    NodeProcess,
    StatusReporter,
    add_process_arguments,
    apply_load_event,
    outages_text,
    serve,
)
from services.nodes.readiness import ReadySpec, declare_ready
from services.transport import messages, session_graph, topics
from services.transport.zenoh_session import ZenohOptions, declare_data_publisher, open_session, publish, run_script

log = logging.getLogger(__name__)


NODE_NAME = ESTIMATOR_NODE
ALIGN_ACCELERATION = "acceleration"  # measure each EMG clock against the trackers' (msk_core.estimate.clock_alignment)
ALIGN_ARRIVAL = "arrival"  # the arrival mapping alone
METHODS_NEEDING_PROFILE = ("proposed", "assisted")  # their prior and strengths are the subject profile's


#: A channel the electrode map names is said missing once EMG has streamed this long without it: a second EMG
#: source (another base) may start a moment after the first
MISSING_CHANNEL_GRACE_S = 3.0


@dataclass(frozen=True)
class EmgTiming:
    """How the node puts the EMG and the joint frames on one clock, and how long a frame waits for its EMG.

    ``joints_clock``: the joint frames' instant (arrival, or their device time mapped onto the host clock);
    ``emg_latency_ns`` / ``default_emg_latency_ns``: the stated latency of each EMG source / of the others (host clock
    mapping); ``emg_align``: with the EMG clock "host", ``"acceleration"`` measures each EMG clock against the
    trackers' from the accelerations (the trackers mapped with ``imu_latency_ns`` / ``default_imu_latency_ns`` as the
    kinematics node maps them); ``emg_wait_s``: how long a joint frame (:meth:`EstimatorNode.offer_joints`) may wait
    for the EMG of its instant."""

    joints_clock: JointsClock | str = JointsClock.ARRIVAL
    emg_latency_ns: dict[str, int] | None = None
    default_emg_latency_ns: int = 0
    emg_align: str = ALIGN_ARRIVAL
    imu_latency_ns: dict[str, int] | None = None
    default_imu_latency_ns: int = 0
    emg_wait_s: float = 0.0

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> EmgTiming:
        """The timing of the command line (:func:`add_arguments`); ``--emg-align`` counts only with ``--emg-clock
        host``."""
        latency_ns, default_latency_ns = parse_latencies(args.emg_latency_ms, "--emg-latency-ms")
        imu_latency_ns, default_imu_latency_ns = parse_latencies(args.imu_latency_ms, "--imu-latency-ms")
        return cls(
            joints_clock=args.joints_clock,
            emg_latency_ns=latency_ns,
            default_emg_latency_ns=default_latency_ns,
            emg_align=args.emg_align if args.emg_clock == ClockMode.HOST.value else ALIGN_ARRIVAL,
            imu_latency_ns=imu_latency_ns,
            default_imu_latency_ns=default_imu_latency_ns,
            emg_wait_s=args.emg_wait_ms / 1e3,
        )

    def argv(self) -> list[str]:
        """These timings as the node's command line (:func:`add_emg_arguments`); :meth:`from_args` reads them back."""
        return [
            "--joints-clock",
            JointsClock(self.joints_clock).value,
            "--emg-align",
            self.emg_align,
            "--emg-wait-ms",
            f"{self.emg_wait_s * 1e3:.15g}",
            *latency_argv("--emg-latency-ms", self.emg_latency_ns, self.default_emg_latency_ns),
            *latency_argv("--imu-latency-ms", self.imu_latency_ns, self.default_imu_latency_ns),
        ]


@dataclass(frozen=True)
class EstimatorSettings:
    """What one estimator node estimates and how, checked once where it is built: from the node's command line
    (:meth:`from_args`), by ``msk live`` from the session file (services.sessions.live.estimator_settings, which starts
    the node with :meth:`argv`), or by whoever runs the node in a thread (the demo, the tests).

    ``methods``: default proposed with a subject profile, else so; proposed and assisted need the profile's prior.
    ``emg``: the EMG path on, off, or (None) on when the profile or ``electrode_map`` maps electrodes; ``emg_stall_s``:
    how long a silent EMG source is waited for before frames are flagged ``emg_stalled`` (not on the command line);
    ``initial_load_kg``: the barbell until the first load event; ``exercise``: estimate only while load events name it
    (default the pack's name); ``solver``: one of :data:`SOLVERS`; ``timing``: :class:`EmgTiming`."""

    pack: str
    session: str
    methods: tuple[str, ...] = ()
    subject_path: Path | None = None
    emg: bool | None = False
    electrode_map: dict[str, str] | None = None
    emg_clock: ClockMode | str = ClockMode.DEVICE
    emg_stall_s: float = 0.25
    timing: EmgTiming = EmgTiming()
    initial_load_kg: float = 0.0
    exercise: str | None = None
    solver: str = "active-set"
    live_synergists: bool = True  # assisted: groups without EMG follow their measured synergist's live envelope

    def __post_init__(self) -> None:
        methods = tuple(self.methods) or (("proposed",) if self.subject_path is not None else ("so",))
        object.__setattr__(self, "methods", methods)
        if self.solver not in SOLVERS:
            raise ConfigError(f"unknown solver; choose {', '.join(SOLVERS)}", field="--solver", value=self.solver)
        if (problem := load_problem(self.initial_load_kg)) is not None:  # as msk load and the session file
            raise ConfigError(problem, field="--load-kg", value=self.initial_load_kg)
        for needs_prior in METHODS_NEEDING_PROFILE:
            if needs_prior in methods and self.subject_path is None:
                raise ConfigError(
                    f"method {needs_prior!r} needs --subject (a calibrated profile with its prior)",
                    field="--method",
                    value=needs_prior,
                )

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> EstimatorSettings:
        """The settings of the node's command line (:func:`add_arguments`)."""
        return cls(
            args.pack,
            args.session,
            tuple(args.method or ()),
            args.subject,
            emg=args.emg,
            electrode_map=parse_pairs(args.emg_map, field="--emg-map", form="CHANNEL=GROUP|ELECTRODE")
            if args.emg_map
            else None,
            emg_clock=args.emg_clock,
            timing=EmgTiming.from_args(args),
            initial_load_kg=args.load_kg,
            exercise=args.exercise,
            solver=args.solver,
            live_synergists=args.live_synergists == "on",
        )

    def argv(self) -> list[str]:
        """These settings as the node's command line, but ``emg_stall_s`` (:meth:`from_args` reads them back)."""
        return [
            *("--pack", self.pack, "--session", self.session, "--solver", self.solver),
            *("--live-synergists", "on" if self.live_synergists else "off"),
            *("--load-kg", repr(self.initial_load_kg), "--emg-clock", ClockMode(self.emg_clock).value),
            *(a for method in self.methods for a in ("--method", method)),
            *(["--subject", str(self.subject_path)] if self.subject_path is not None else []),
            *(["--exercise", self.exercise] if self.exercise is not None else []),
            *([] if self.emg is None else ["--emg" if self.emg else "--no-emg"]),
            *(a for item in (self.electrode_map or {}).items() for a in ("--emg-map", "=".join(item))),
            *self.timing.argv(),
        ]


@dataclass
class EstimatorStats:
    frames_in: int = 0
    frames_done: int = 0  # input frames whose activation frames are all published: a waiter's exact end condition
    frames_out: int = 0
    load_events: int = 0
    flagged: dict[str, int] = field(default_factory=dict)
    invalid: dict[str, int] = field(default_factory=dict)  # invalid_input frames per reason (FrameResult.reason)
    rejected: int = 0  # input frames whose coordinates do not match the pack
    other_exercise: int = 0  # frames skipped while a LoadEvent says another exercise is under way
    last_error: str = ""
    inputs: InputCounts | None = None  # received and dropped inputs per key (services.nodes.node_runtime)
    continuity: InputContinuity | None = (
        None  # its inputs' outages and missed publications (services.nodes.node_runtime)
    )
    emg_chunks: int = 0
    envelopes_out: int = 0
    emg_flags: dict[str, int] = field(default_factory=dict)  # frames carrying each EMG flag
    emg: EmgCounters | None = None  # gaps, lost and duplicate samples, channels without MVC (None: no EMG path)
    acc_chunks: int = 0
    imu_samples: int = 0
    frames_waited: int = 0  # joint frames held back for the EMG of their instant (--emg-wait-ms)
    quality_changes: int = 0  # EMG chunks after which an electrode's state or reasons changed
    fatigue_reps: int = 0  # reps whose spectral fatigue values are in (per EMG source)


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

    def take(self, message, field_name: str, names: tuple[str, ...] | None = None) -> np.ndarray:
        """``message``'s ``field_name`` in the pack's order (zeros when the field is empty); ``names``: the
        message's coordinates when the caller has them already (:meth:`take_all`)."""
        field = getattr(message, field_name)
        if not len(field):
            return np.zeros(len(self.pack_coordinates))
        values = np.fromiter(field, dtype=float, count=len(field))  # ~3x faster than np.asarray on a repeated field
        return values[self.indices(tuple(message.coordinates) if names is None else names)]

    def take_all(self, message, field_names: tuple[str, ...]) -> list[np.ndarray]:
        """:meth:`take` of each field, the coordinates read once."""
        names = tuple(message.coordinates)
        return [self.take(message, f, names) for f in field_names]


def to_message(
    result: FrameResult, *, method: str, groups, coordinates, time_s: float, arrival_ns: int
) -> messages.ActivationFrame:
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
    if result.flagged:
        frame.flags.append(result.status.value)
    elif method in UNCERTAIN_METHODS:  # so's and hybrid's objectives give no uncertainty
        std = result.activation_std
        if std is not None and np.all(np.isfinite(std)):
            frame.activation_std.extend(std.tolist())
    for name, tau_id, tau_model, residual in zip(coordinates, result.torques, result.model_torques, result.residual):
        frame.torques.add(
            coordinate=name, inverse_dynamics_nm=float(tau_id), model_nm=float(tau_model), residual_nm=float(residual)
        )
    return frame


def emg_to_envelope(block, arrival_ns: int) -> messages.EmgEnvelope:
    """The envelope at the chunk's last sample (the topic's documented decimation: one message per chunk)."""
    t = int(block.device_time_ns[-1])
    return messages.EmgEnvelope(
        time_s=t / 1e9,
        groups=block.groups,
        envelope=block.envelope[-1].tolist(),
        device_time_ns=t,
        host_time_ns=arrival_ns,
        flags=block.flags,
    )


def electrode_quality(report: ElectrodeReport) -> messages.ElectrodeQuality:
    """One electrode's quality as the status carries it (times in s on the EMG device clock)."""
    return messages.ElectrodeQuality(
        source=report.source,
        channel=report.channel,
        group=report.group,
        state=report.state.value,
        reasons=[f.value for f in report.faults],
        detail=report.detail,
        since_s=report.since_ns / 1e9,
        check_s=report.check_s,
        bad_s=report.bad_s,
        episodes=report.episodes,
        episode_reasons={f.value: n for f, n in report.episode_faults.items()},
        recent=[
            messages.FaultEpisode(
                start_s=e.start_ns / 1e9,
                worst=e.worst.value,
                reasons=[f.value for f in e.faults],
                **({} if e.end_ns is None else {"end_s": e.end_ns / 1e9}),
            )
            for e in report.recent
        ],
    )


class FatigueWorker:
    """The live fatigue index off the estimator's thread: EMG chunks, the frames' EMG read times and phases, and set
    changes go through a queue to one thread that runs :class:`LiveFatigue` (a rep's spectra take 30 ms, several
    times that on a busy machine, which must not hold up the frames). :meth:`report` is the newest snapshot of the
    values, made by that thread whenever they change; ``stats.fatigue_reps`` counts the reps whose values are in."""

    def __init__(self, fatigue: LiveFatigue, stats: EstimatorStats) -> None:
        self.fatigue = fatigue
        self.set_number = 0  # the set last asked for (the worker may not have started it yet)
        self._stats = stats
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._report: list[ElectrodeFatigueReport] = []
        self._thread = threading.Thread(target=self._run, name="estimator-fatigue", daemon=True)
        self._thread.start()

    def add_chunk(self, chunk: RawEmgChunk) -> None:
        self._queue.put(("chunk", (chunk,)))

    def add_frame(self, read_at_ns: dict[str, int], phase: float | None) -> None:
        self._queue.put(("frame", (dict(read_at_ns), phase)))

    def start_set(self, number: int) -> None:
        self.set_number = number
        self._queue.put(("set", (number,)))

    def drop_rep_under_way(self) -> None:
        self._queue.put(("drop", ()))

    def report(self) -> list[ElectrodeFatigueReport]:
        return self._report

    def close(self, timeout_s: float = 5.0) -> None:
        """Take what is queued, then stop."""
        self._queue.put(None)
        self._thread.join(timeout_s)

    def _run(self) -> None:
        sources = 0
        while (item := self._queue.get()) is not None:
            kind, args = item
            try:
                if kind == "chunk":
                    done = self.fatigue.add_chunk(*args)
                elif kind == "frame":
                    done = self.fatigue.add_frame(*args)
                elif kind == "drop":
                    self.fatigue.drop_rep_under_way()
                    done = []
                else:
                    self.fatigue.start_set(*args)
                    done = []
            except MskError as error:  # a chunk the EMG path took but the index cannot: said, the node goes on
                log.warning("fatigue index: %s", error)
                continue
            if done or kind == "set" or len(self.fatigue.sources) != sources:
                sources = len(self.fatigue.sources)
                self._report = self.fatigue.report()
                self._stats.fatigue_reps += len(done)


def make_fatigue(live_emg: LiveEmg | None, stats: EstimatorStats) -> FatigueWorker | None:
    """The fatigue index of the EMG path's electrodes (None without EMG)."""
    return None if live_emg is None else FatigueWorker(LiveFatigue(live_emg.setup.channel_group), stats)


def electrode_fatigue(report: ElectrodeFatigueReport) -> messages.ElectrodeFatigue:
    """One electrode's fatigue index over the set as the status carries it."""
    return messages.ElectrodeFatigue(
        source=report.source,
        channel=report.channel,
        group=report.group,
        set_number=report.set_number,
        median_hz=report.median_hz,
        mean_hz=report.mean_hz,
        rep_end_s=report.rep_end_s,
        median_slope_hz_per_rep=report.median_slope_hz_per_rep,
        median_slope_se_hz_per_rep=report.median_slope_se_hz_per_rep,
        median_slope_pct_per_rep=report.median_slope_pct_per_rep,
        median_change_pct=report.median_change_pct,
        mean_slope_pct_per_rep=report.mean_slope_pct_per_rep,
        mean_change_pct=report.mean_change_pct,
    )


def make_live_emg(
    subject: SubjectProfile | None,
    groups: list[str],
    *,
    emg: bool | None,
    electrode_map: dict[str, str] | None,
    clock: ClockMode | str,
    stall_s: float = 0.25,
    timing: EmgTiming = EmgTiming(),
) -> LiveEmg | None:
    """The EMG path: on with ``emg=True``; with None, on when the profile or ``electrode_map`` maps electrodes."""
    setup = (
        EmgSetup.from_profile(subject, electrode_map)
        if subject is not None
        else EmgSetup(dict(electrode_map or {}), {})
    )
    if emg is None:
        emg = bool(setup.channel_group)
    if not emg:
        return None
    if not setup.channel_group:
        raise ConfigError(
            "the EMG path needs an electrode -> group map (from the subject profile or --emg-map)", field="emg_map"
        )
    return LiveEmg(
        groups,
        setup,
        clock=clock,
        stall_s=stall_s,
        joints_clock=timing.joints_clock,
        latency_ns=timing.emg_latency_ns,
        default_latency_ns=timing.default_emg_latency_ns,
    )


def make_estimators(settings: EstimatorSettings, subject: SubjectProfile | None) -> dict[str, FrameEstimator]:
    """One estimator per method, its compiled kernels and solvers warmed up before the first live frame."""
    hot_start = settings.solver == "active-set"
    estimators = {
        m: FrameEstimator(
            settings.pack, subject=subject, method=m, hot_start=hot_start, live_synergists=settings.live_synergists
        )
        for m in settings.methods
    }
    for estimator in estimators.values():
        estimator.warm_up()
    return estimators


def make_alignment(live_emg: LiveEmg | None, timing: EmgTiming) -> AccelerationAlignment | None:
    """The EMG clock measured against the trackers' (``timing.emg_align`` "acceleration"): only where device clocks
    are mapped onto the host clock; a tracker latency given for anything else is refused."""
    if timing.emg_align not in (ALIGN_ACCELERATION, ALIGN_ARRIVAL):
        raise ConfigError(
            f"choose {ALIGN_ACCELERATION} or {ALIGN_ARRIVAL}", field="--emg-align", value=timing.emg_align
        )
    if live_emg is not None and live_emg.clock is ClockMode.HOST and timing.emg_align == ALIGN_ACCELERATION:
        trackers = DeviceClocks(
            "imu",
            latency_ns=timing.imu_latency_ns,
            default_latency_ns=timing.default_imu_latency_ns,
            window_s=live_emg.clock_window_s,
        )
        return AccelerationAlignment(live_emg, trackers)
    if live_emg is not None and (timing.imu_latency_ns or timing.default_imu_latency_ns):
        raise ConfigError(
            "a tracker latency is used to measure the EMG clock against the trackers' (--emg-clock "
            "host --emg-align acceleration)",
            field="--imu-latency-ms",
            value={**(timing.imu_latency_ns or {}), "default": timing.default_imu_latency_ns},
        )
    return None


def emg_wait_ns(emg_wait_s: float) -> int:
    """How long a joint frame may wait for the EMG of its instant, checked (0..1 s), in ns."""
    if not (np.isfinite(emg_wait_s) and 0 <= emg_wait_s <= 1.0):
        raise ConfigError("the wait for the EMG is 0..1000 ms", field="--emg-wait-ms", value=emg_wait_s * 1e3)
    return int(round(emg_wait_s * 1e9))


@dataclass
class _Held:
    joints: messages.JointAngles
    arrival_ns: int
    waited: bool = False


class EstimatorNode:
    """The node's state between Zenoh and the estimators: load timeline, coordinate order, phase tracking, the EMG
    path; one ``handle_*`` per input kind, each returning the messages to publish (no Zenoh in here)."""

    def __init__(self, settings: EstimatorSettings, subject: SubjectProfile | None, stats: EstimatorStats) -> None:
        """``subject``: the profile at ``settings.subject_path``, loaded by the caller."""
        self.stats = stats
        timing = settings.timing
        self.estimators = make_estimators(settings, subject)
        first = next(iter(self.estimators.values()))
        self.mapper = CoordinateMapper(list(first.coordinates))
        # The subject's rep template (calibration) gives the phase when JointAngles carry none (None: no template).
        self.live_phase = LivePhase.from_profile(subject, first.coordinates) if subject is not None else None
        self.live_emg = make_live_emg(
            subject,
            list(first.groups),
            emg=settings.emg,
            electrode_map=settings.electrode_map,
            clock=settings.emg_clock,
            stall_s=settings.emg_stall_s,
            timing=timing,
        )
        if "assisted" in self.estimators and self.live_emg is None:
            raise ConfigError(
                "method 'assisted' needs EMG: a subject profile with MVC normalisation or an electrode map",
                field="method",
                value="assisted",
            )
        if self.live_emg is not None:
            stats.emg = self.live_emg.counters
        # each electrode judged from its raw EMG; a bad one is left out of its group's envelope
        self.quality = LiveQuality(self.live_emg.setup.channel_group) if self.live_emg is not None else None
        self.fatigue = make_fatigue(self.live_emg, stats)  # per electrode and rep: median/mean frequency, their trend
        self.sets = SetTracker()  # the sets the fatigue trend runs over: operator marks, rest detection
        self._missing_said: list[str] = []  # mapped channels no source streams, as last logged
        self._first_emg_ns: int | None = None  # arrival of the first EMG chunk: other sources may start later
        self.alignment = make_alignment(self.live_emg, timing)
        self.emg_wait_ns = emg_wait_ns(timing.emg_wait_s)
        self._held: deque[_Held] = deque()  # joint frames waiting for their EMG, oldest first
        self.loads = LoadTimeline(settings.initial_load_kg)
        # Several estimators (one per exercise pack) may share a session: each follows the exercise the load events
        # name.
        self.exercise = settings.exercise if settings.exercise is not None else first.pack.name
        self.own_exercises = (self.exercise, first.pack.name)

    def handle_emg(self, chunk: messages.EmgChunk | bytes, arrival_ns: int) -> messages.EmgEnvelope | None:
        chunk = messages.as_message(messages.EmgChunk, chunk)
        self.stats.emg_chunks += 1
        live_emg, quality = self.live_emg, self.quality
        if live_emg is None or quality is None:
            raise ConfigError(
                "EMG reached an estimator running without its EMG path (--emg)", field="emg", value=chunk.source_id
            )
        raw = RawEmgChunk(
            chunk.source_id,
            chunk.channel_labels,
            chunk.sample_rate_hz,
            chunk.first_sample_index,
            chunk.device_time_ns,
            np.asarray(chunk.samples, dtype=float).reshape(chunk.n_samples, chunk.n_channels),
            chunk.units,
        )
        if quality.add_chunk(raw):
            self.stats.quality_changes += 1
        live_emg.exclude_channels(chunk.source_id, quality.bad_channels(chunk.source_id))
        if self.fatigue is not None:
            self.fatigue.add_chunk(raw)
        block = live_emg.add_chunk(raw, arrival_ns, chunk.host_time_ns or arrival_ns)  # the driver's receipt, else ours
        missing = live_emg.counters.missing_channels
        self._first_emg_ns = self._first_emg_ns or arrival_ns
        waited = arrival_ns - self._first_emg_ns >= MISSING_CHANNEL_GRACE_S * 1e9
        if missing and missing != self._missing_said and waited:
            self._missing_said = list(missing)
            log.warning(
                "the electrode map names %s, which no EMG source streams (%s has %s): %s estimated without EMG",
                ", ".join(missing),
                chunk.source_id,
                ", ".join(chunk.channel_labels) or "no channel",
                ", ".join(sorted({live_emg.setup.channel_group[ch] for ch in missing})),
            )
        if block is None or not block.groups:
            return None
        self.stats.envelopes_out += 1
        return emg_to_envelope(block, arrival_ns)

    def handle_acc(self, chunk: messages.AccChunk | bytes) -> None:
        """The accelerometers on an EMG source's clock (Trigno AUX): to the clock alignment (ignored without one)."""
        if self.alignment is None:
            return
        chunk = messages.as_message(messages.AccChunk, chunk)
        self.stats.acc_chunks += 1
        n = chunk.n_samples
        times = chunk.device_time_ns + np.round(np.arange(n) * 1e9 / chunk.sample_rate_hz).astype(np.int64)
        acc = np.asarray(chunk.samples, dtype=float).reshape(n, chunk.n_sensors, 3)
        self.alignment.add_acc(chunk.source_id, chunk.sensor_labels, times, acc)

    def handle_imu(self, key: str, sample: messages.ImuSample | bytes) -> None:
        """A tracker sample (``key``: its topic, whose last chunk names the tracker, as for the kinematics node): its
        clock mapping and acceleration to the clock alignment (ignored without one)."""
        if self.alignment is None:
            return
        sample = messages.as_message(messages.ImuSample, sample)
        if not sample.HasField("orientation"):  # an MTi-G's GNSS message, up to 62 ms late: as the kinematics node,
            return  # which maps the tracker's clock on the samples with a pose only
        self.stats.imu_samples += 1
        a = sample.acceleration
        self.alignment.add_tracker_sample(
            key.rsplit("/", 1)[1],
            sample.device_time_ns,
            sample.host_time_ns,
            (a.x, a.y, a.z) if sample.HasField("acceleration") else None,
        )

    def offer_joints(self, joints: messages.JointAngles | bytes, arrival_ns: int) -> None:
        """A joint frame to estimate once its EMG is here (:meth:`release`), in arrival order."""
        self._held.append(_Held(messages.as_message(messages.JointAngles, joints), int(arrival_ns)))

    def release(self, now_ns: int, *, flush: bool = False) -> list[tuple[messages.JointAngles, int]]:
        """The held joint frames (with their arrival times) to estimate now, oldest first: each once the EMG of its
        instant has arrived (:meth:`LiveEmg.awaits`), it has waited ``emg_wait_s`` or ``flush``."""
        out = []
        while self._held:
            head = self._held[0]
            if (
                not flush
                and self.live_emg is not None
                and now_ns - head.arrival_ns < self.emg_wait_ns
                and self.live_emg.awaits(head.joints.device_time_ns, now_ns)
            ):
                for held in self._held:  # the frames behind it wait with it
                    held.waited = True
                break
            self._held.popleft()
            self.stats.frames_waited += head.waited
            out.append((head.joints, head.arrival_ns))
        return out

    def handle_load(self, event: messages.LoadEvent | bytes) -> None:
        """Apply a load event; one naming an exercise no pack has is refused (:class:`ConfigError`), since it would
        stop the estimates of this pack while nothing is estimated for that exercise."""
        event = messages.as_message(messages.LoadEvent, event)
        if event.exercise and not is_known_exercise(event.exercise, self.own_exercises):
            raise ConfigError(
                f"load event names an exercise that is not a model pack (known: {', '.join(available_packs())})",
                field="LoadEvent.exercise",
                value=event.exercise,
            )
        self.loads.add(event.device_time_ns, event.barbell_mass_kg, event.exercise)
        self.stats.load_events += 1
        # the one set logic (msk_core.signal.sets), as the view, the dashboard and the report run it
        dropped = self.sets.reps_dropped
        apply_load_event(self.sets, event)
        if self.fatigue is not None and self.sets.reps_dropped != dropped:  # a mark during a rep: not counted
            self.fatigue.drop_rep_under_way()
        self._follow_set()

    def _follow_set(self) -> None:
        """The fatigue index follows the set under way (or the last one, at rest)."""
        if self.fatigue is not None and self.sets.number != self.fatigue.set_number:
            self.fatigue.start_set(self.sets.number)

    def handle_joints(
        self, payload: messages.JointAngles | bytes, arrival_ns: int
    ) -> list[tuple[str, messages.ActivationFrame]]:
        """(method, frame) for every method; empty when the frame is skipped (other exercise, wrong coordinates)."""
        return list(self.frames_for_joints(payload, arrival_ns))

    def frames_for_joints(
        self, joints: messages.JointAngles | bytes, arrival_ns: int
    ) -> Iterator[tuple[str, messages.ActivationFrame]]:
        """:meth:`handle_joints` one method at a time, so each frame can be published as soon as it is solved."""
        stats = self.stats
        stats.frames_in += 1
        joints = messages.as_message(messages.JointAngles, joints)
        load_kg, current_exercise = self.loads.at(joints.device_time_ns)
        if current_exercise and current_exercise != self.exercise:
            stats.other_exercise += 1
            if stats.other_exercise == 1:
                log.info(
                    "load events say %r is under way: frames are not estimated with pack %r until the "
                    "exercise changes back",
                    current_exercise,
                    self.exercise,
                )
            return
        try:
            q, qd, qdd = self.mapper.take_all(joints, ("q", "qd", "qdd"))
        except ConfigError as error:
            stats.rejected += 1
            if stats.rejected == 1:
                log.error("%s", error)
            stats.last_error = str(error)
            return
        time_s = joints.device_time_ns / 1e9
        phase = self._phase(joints, time_s, q)
        self.sets.update(time_s, phase)
        self._follow_set()
        envelope, emg_flags = (
            (None, [])
            if self.live_emg is None
            else self.live_emg.at(joints.device_time_ns, arrival_ns, joints.host_time_ns or arrival_ns)
        )
        for flag in emg_flags:
            stats.emg_flags[flag] = stats.emg_flags.get(flag, 0) + 1
        if self.fatigue is not None and self.live_emg is not None:
            self.fatigue.add_frame(self.live_emg.read_at_ns, phase)
        for method, estimator in self.estimators.items():
            result = estimator.step(q, qd, qdd, hand_load_newton=load_kg * GRAVITY, phase=phase, emg=envelope)
            frame = to_message(
                result,
                method=method,
                groups=estimator.groups,
                coordinates=estimator.coordinates,
                time_s=time_s,
                arrival_ns=arrival_ns,
            )
            frame.exercise = self.exercise
            if envelope is not None:
                frame.measured_envelope.extend(envelope.tolist())
                frame.flags.extend(emg_flags)
            if result.flagged:
                stats.flagged[result.status.value] = stats.flagged.get(result.status.value, 0) + 1
                if result.reason:
                    stats.invalid[result.reason] = stats.invalid.get(result.reason, 0) + 1
            yield method, frame
        stats.frames_out += 1

    def electrode_report(self) -> list[messages.ElectrodeQuality]:
        """Each electrode's quality (:class:`msk_core.estimate.live_quality.LiveQuality`); empty without EMG."""
        return [] if self.quality is None else [electrode_quality(r) for r in self.quality.report()]

    def fatigue_report(self) -> list[messages.ElectrodeFatigue]:
        """Each electrode's fatigue index over the set (:class:`msk_core.estimate.live_fatigue.LiveFatigue`); empty
        without EMG."""
        return [] if self.fatigue is None else [electrode_fatigue(r) for r in self.fatigue.report()]

    def clock_report(self) -> list[ClockReport]:
        """The EMG path's clock mappings per stream (:meth:`LiveEmg.clock_report`), with the acceleration alignment's
        findings on each EMG stream (:meth:`AccelerationAlignment.report`); empty without EMG."""
        if self.live_emg is None:
            return []
        reports = self.live_emg.clock_report()
        return reports if self.alignment is None else self.alignment.report(reports)

    def _phase(self, joints, time_s: float, q: np.ndarray) -> float | None:
        """Unset = unknown (prior pooled over phases); negative = between reps (rest prior); else [0, 1)."""
        if joints.HasField("phase"):
            return float(joints.phase)
        if self.live_phase is not None:  # no phase upstream: track it on the subject's rep template
            return self.live_phase.update(time_s, q)
        return None


def declare_outputs(
    zsession: zenoh.Session, node: EstimatorNode, session: str, methods: list[str]
) -> tuple[dict[str, zenoh.Publisher], zenoh.Publisher | None]:
    """A publisher of activation frames per method, and of envelopes with the EMG path."""
    publishers = {
        m: declare_data_publisher(zsession, topics.activations_key(session, m), "msk.ActivationFrame") for m in methods
    }
    envelope_publisher = None
    if node.live_emg is not None:
        envelope_publisher = declare_data_publisher(zsession, topics.envelopes_key(session), "msk.EmgEnvelope")
    return publishers, envelope_publisher


def subscribe_inputs(inputs: NodeInputs, node: EstimatorNode, session: str) -> None:
    """The node's inputs: joints and load; the EMG with the EMG path; the EMG sensors' accelerations and the trackers'
    samples with the clock alignment."""
    prefix = topics.session_prefix(session)
    # One subscription for joints and load keeps a load event and the frames after it in publication order
    # (two subscriptions may hand them over in another order); the role reads the session's one-chunk topics
    # for it (services.transport.session_graph). Envelopes, the other one-chunk topic, are its own output: ignored.
    inputs.subscribe(f"{prefix}/{session_graph.SESSION_TOPICS}")
    if node.live_emg is not None:
        inputs.subscribe(f"{prefix}/emg/*")
    if node.alignment is not None:  # the EMG clock measured against the trackers'
        inputs.subscribe(f"{prefix}/acc/*")
        inputs.subscribe(f"{prefix}/imu/*")


class InputDispatch:
    """Each input to the node's ``handle_*`` by its topic, the frames and envelopes out as they are made; an input
    the node cannot use is counted in the status and said once per kind."""

    def __init__(
        self,
        node: EstimatorNode,
        session: str,
        reporter: StatusReporter,
        publishers: dict[str, zenoh.Publisher],
        envelope_publisher: zenoh.Publisher | None,
    ) -> None:
        self.node, self.stats, self.session, self.reporter = node, node.stats, session, reporter
        self.publishers, self.envelope_publisher = publishers, envelope_publisher
        self.joints_key, self.load_key = topics.joints_key(session), topics.load_key(session)
        prefix = topics.session_prefix(session)
        self.emg_prefix, self.acc_prefix, self.imu_prefix = f"{prefix}/emg/", f"{prefix}/acc/", f"{prefix}/imu/"
        self.said: set[tuple[str, str]] = set()

    def not_used(self, key: str, error: MskError) -> None:
        """An input this node cannot use: counted, said once per kind, the node goes on."""
        self.reporter.error(f"{key}: {error}")
        self.stats.last_error = str(error)
        kind = (key, type(error).__name__)
        if kind not in self.said:
            self.said.add(kind)
            log.error(
                "input on %s not used: %s (further ones counted in msk/%s/status/%s)",
                key,
                error,
                self.session,
                NODE_NAME,
            )

    def estimate(self, final: bool = False) -> None:
        """The joint frames whose EMG is here (or that waited long enough), each method out when solved."""
        for joints, arrival_ns in self.node.release(messages.now_ns(), flush=final):
            try:
                for method, frame in self.node.frames_for_joints(joints, arrival_ns):
                    frame.publish_ns = messages.now_ns()
                    publish(self.publishers[method], frame)
            except MskError as error:
                self.not_used(self.joints_key, error)
            self.stats.frames_done += 1

    def handle(self, item: Inbound) -> None:
        node, stats = self.node, self.stats
        message: Any = item.message  # decoded by the runtime by its topic's type; each handle_* checks the type
        try:
            if item.key == self.load_key:
                node.handle_load(message)
            elif item.key == self.joints_key:
                node.offer_joints(message, item.arrival_ns)
            elif item.key.startswith(self.emg_prefix):
                changes, reps = stats.quality_changes, stats.fatigue_reps
                envelope = node.handle_emg(message, item.arrival_ns)
                if envelope is not None and self.envelope_publisher is not None:  # both only with live EMG
                    publish(self.envelope_publisher, envelope)
                # an electrode's state changed, or a rep's fatigue values are in: said now, not within 1 s
                if stats.quality_changes != changes or stats.fatigue_reps != reps:
                    self.reporter.tick(force=True)
            elif item.key.startswith(self.acc_prefix):
                node.handle_acc(message)
            elif item.key.startswith(self.imu_prefix):
                node.handle_imu(item.key, message)
        except MskError as error:
            self.not_used(item.key, error)


def main(
    config: ZenohOptions,
    settings: EstimatorSettings,
    *,
    stop_event: threading.Event | None = None,
    ready_event: threading.Event | None = None,
    ready_key: ReadySpec | None = None,
    stats: EstimatorStats | None = None,
) -> EstimatorStats:
    """Run the node of ``settings`` until ``stop_event``; returns its stats (``stats``, filled as it runs)."""
    stop_event = stop_event or threading.Event()
    stats = stats if stats is not None else EstimatorStats()
    subject = SubjectProfile.load(settings.subject_path) if settings.subject_path is not None else None
    node = EstimatorNode(settings, subject, stats)
    session, methods = settings.session, list(settings.methods)
    with open_session(config) as zsession:
        publishers, envelope_publisher = declare_outputs(zsession, node, session, methods)
        inputs = NodeInputs(zsession, NODE_NAME, role=config.role)
        reporter = StatusReporter(
            zsession,
            session,
            NODE_NAME,
            inputs,
            clocks=node.clock_report,
            electrodes=node.electrode_report,
            fatigue=node.fatigue_report,
        )
        stats.inputs, stats.continuity = inputs.counts, inputs.continuity
        subscribe_inputs(inputs, node, session)
        token = declare_ready(zsession, ready_key)  # noqa: F841 - alive while the node runs (services.nodes.readiness)
        if ready_event is not None:
            ready_event.set()
        reporter.tick(force=True)
        dispatch = InputDispatch(node, session, reporter, publishers, envelope_publisher)
        # what arrived before the stop is still answered; held frames are estimated at the latest then
        serve(inputs, dispatch.handle, stop_event, reporter, tick=dispatch.estimate)
    return stats


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--pack", required=True, help="model pack name (e.g. bench_press, deadlift) or path")
    parser.add_argument("--session", required=True, help="session name: topics msk/<session>/...")
    parser.add_argument(
        "--method",
        action="append",
        choices=[m.value for m in Method if m is not Method.PRIOR],
        default=None,
        help="estimation method (repeatable; default: proposed with --subject, else so)",
    )
    parser.add_argument("--subject", type=Path, default=None, help="subject profile JSON from `msk calibrate`")
    add_emg_arguments(parser)
    add_solver_argument(parser)
    add_live_synergists_argument(parser)
    parser.add_argument("--load-kg", type=float, default=0.0, help="barbell mass until the first LoadEvent (default 0)")
    parser.add_argument(
        "--exercise",
        default=None,
        help="estimate only while load events name this exercise (default: the pack's name, e.g. bench_press)",
    )
    add_process_arguments(parser)


def add_emg_arguments(parser: argparse.ArgumentParser) -> None:
    """The EMG options: whether and which electrodes, and how their clocks meet the kinematics'."""
    parser.add_argument(
        "--emg",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="use the EMG on msk/<session>/emg/** (default: when the profile maps electrodes)",
    )
    parser.add_argument(
        "--emg-map",
        action="append",
        default=[],
        metavar="CHANNEL=GROUP|ELECTRODE",
        help="live channel -> muscle group, or -> one of the subject profile's electrodes (its calibration EMG "
        "column: the channel takes its group and MVC), e.g. sensor01.EMG=PMCla (repeatable; default: the profile's map)",
    )
    parser.add_argument(
        "--emg-clock",
        choices=[c.value for c in ClockMode],
        default=ClockMode.DEVICE.value,
        help="device: EMG and kinematics share one clock (recordings); host: align separate device "
        "clocks by host arrival (docs/topics.md)",
    )
    parser.add_argument(
        "--joints-clock",
        choices=[c.value for c in JointsClock],
        default=JointsClock.ARRIVAL.value,
        help="with --emg-clock host: the joint frames' times are on the host clock already (host: "
        "the kinematics node ran with --imu-clock host) or on a device clock, mapped by their "
        "arrival (default)",
    )
    parser.add_argument(
        "--emg-latency-ms",
        action="append",
        default=[],
        metavar="[SOURCE=]MS",
        help="with --emg-clock host: the stated latency of EMG source SOURCE (without SOURCE=: of "
        "every source not named), taken off before its clock is mapped (repeatable; default 0)",
    )
    parser.add_argument(
        "--emg-align",
        choices=[ALIGN_ACCELERATION, ALIGN_ARRIVAL],
        default=ALIGN_ACCELERATION,
        help="with --emg-clock host: acceleration (default) measures each EMG clock against the "
        "trackers' from the accelerations (msk/<s>/acc/*, msk/<s>/imu/*) and maps the EMG through "
        "them once an EMG sensor moves with a tracker, the arrival mapping until then; arrival: the "
        "arrival mapping alone (docs/live.md, Clocks)",
    )
    parser.add_argument(
        "--imu-latency-ms",
        action="append",
        default=[],
        metavar="[TRACKER=]MS",
        help="with --emg-align acceleration: the trackers' stated latencies, as the kinematics node "
        "is given them (repeatable; default 0)",
    )
    parser.add_argument(
        "--emg-wait-ms",
        type=float,
        default=0.0,
        help="a joint frame waits up to this long for the EMG of its instant before it is estimated "
        "with the newest EMG there is (default 0: never waits)",
    )


def run_from_args(args: argparse.Namespace) -> int:
    settings, process = EstimatorSettings.from_args(args), NodeProcess.from_args(args)
    print(
        f"estimating {', '.join(settings.methods)} on msk/{settings.session}/joints with pack {settings.pack}",
        file=sys.stderr,
        flush=True,
    )
    stats = main(process.options, settings, stop_event=process.stop, ready_key=process.ready)
    dropped = stats.inputs.as_dict()["dropped"] if stats.inputs is not None else {}
    print(
        f"estimated {stats.frames_out} frames; solver flags {stats.flagged or 'none'}"
        + (f" (invalid input: {stats.invalid})" if stats.invalid else "")
        + f"; rejected {stats.rejected}"
        f"; inputs dropped {dropped or 'none'}"
        + (f"; {outages_text(stats.continuity.report(messages.now_ns()))}" if stats.continuity is not None else "")
        + (
            f"; EMG: {stats.emg_chunks} chunks, {stats.emg.gaps} gaps ({stats.emg.samples_lost} samples lost), "
            + (
                f"{stats.emg.not_finite_samples} samples not numbers (taken as 0), "
                if stats.emg.not_finite_samples
                else ""
            )
            + (f"mapped channels never streamed {stats.emg.missing_channels}, " if stats.emg.missing_channels else "")
            + f"EMG flags on frames {stats.emg_flags or 'none'}, frames that waited for their EMG {stats.frames_waited}"
            if stats.emg is not None
            else ""
        )
        + (
            f"; accelerations: {stats.acc_chunks} EMG-clock chunks, {stats.imu_samples} tracker samples"
            if stats.acc_chunks or stats.imu_samples
            else ""
        ),
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    run_script(__doc__, add_arguments, run_from_args, log_level=logging.INFO)
