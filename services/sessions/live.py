"""``msk live``: one command runs a whole session graph on the real devices (or, with ``--sim``, on the simulators).

Processes, each a Zenoh peer on one private loopback endpoint (services.sessions.graph): the recorder (``msk/<session>/**``
-> ``OUT/session.mcap``), the estimator (methods of the session file, EMG path on), the kinematics node (IMU ->
joints, each tracker's clock mapped to the host clock), one driver node per device kind (``msk drivers``: Trigno,
Xsens) and the live view (``msk view``). The drivers start acquiring only once the recorder, kinematics and estimator
have declared their subscribers, so nothing a device sends is lost at start.

Stop (``--duration``, Ctrl-C, SIGTERM or SIGHUP) runs downstream: (simulators stop sending;) drivers end acquisition and
exit, then kinematics, estimator and last the recorder, which closes the MCAP. The summary (duration, samples per
device, samples lost, frames estimated, flags) is read back from the MCAP, printed and written to
``OUT/summary.json``. With ``--sim`` it also holds what each simulator sent, to compare with what was recorded.

``--sim``: a Trigno simulator (TCP) and one Xsens simulator per tracker (pty, own SampleTimeFine clock) stream the
held-out trial of the bundled synthetic session (``recordings/demo_session.mcap``) of the pack; the subject is
calibrated on the bundled calibration trials as ``msk demo`` does (cached). ``sim_faults``
(``msk live --sim --sim-fault SENSOR:KIND:START-END``): electrode faults the Trigno simulator injects
(:class:`drivers.trigno.simulator.SensorFault`), for a demonstration of the electrode quality the estimator reports;
the summary then holds, per electrode, its time in check and bad and its fault episodes, beside what was injected.
Docs: docs/live.md.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from drivers.trigno.protocol import AuxLayout
from msk_core.errors import ConfigError, InputError
from msk_core.estimate.flags import flag_counts_text
from msk_core.io.files import json_text
from msk_core.signal.sets import END_OF_DATA
from services.nodes.node_runtime import outages_summary, outages_text
from services.nodes.readiness import GraphTimeout
from services.nodes.recorder import next_part_path
from services.sessions.demo_subject import RECORDINGS, sim_subject
from services.sessions.graph import Graph, pids_path, python_module, wait_for, zenoh_flags
from services.sessions.live_session import (
    SIM_METHODS,
    LiveSession,
    check_against_pack,
    session_error,
    session_names,
    stated_latencies,
)
from services.transport import messages, session_graph, topics
from services.transport.mcap_io import read_messages
from services.transport.stop_signals import StopOnSignals, exit_text, stop_with_parent_env

if TYPE_CHECKING:  # imported where used: a session without --sim needs no simulator
    from drivers.trial_clock import TrialClock
    from drivers.trigno.simulator import SensorFault, TrignoSimulator
    from drivers.trigno.source import EmgSource
    from drivers.xsens.simulator import XsensSimulator
    from drivers.xsens.source import ImuSource
    from services.nodes.estimator import EstimatorSettings
    from services.nodes.kinematics_node import KinematicsSettings
    from services.sessions import discovery
    from services.sessions.sim_sets import SimSets

READY_TIMEOUT_S = 90.0
STOP_TIMEOUT_S = 20.0
FAILED_STOP_S = 5.0  # after a node failed: how long the others have to stop before they are killed
#: At the stop, an estimator that published nothing for this long answers no more (paused for another exercise)
ESTIMATOR_IDLE_S = 3.0
DRAIN_S = 0.6  # after the simulators stop sending: bytes in flight reach the drivers, messages the nodes
#: how long a joint frame may wait in the estimator for the EMG of its instant: a Trigno delivers each 13.5 ms frame
#: after its last sample, plus the base's own latency; beyond this the frame reads the newest EMG there is
EMG_WAIT_MS = 150.0


# ------------------------------------------------------------------------------------------------ simulator sources


@dataclass
class SimSources:
    """What the simulators stream: the bundled session's held-out trial of one pack."""

    emg: EmgSource
    imu: dict[str, tuple[str, ImuSource]]  # tracker id -> (segment, source)
    electrodes: dict[str, str]  # Trigno channel label (sensorNN.EMG) -> electrode name of the profile
    load_kg: float
    trial: str  # its name, as the bundled recordings' folder (``<exercise>_<load>kg``) holding its truth
    exercise: str = ""  # the pack
    rep_ends_s: tuple[float, ...] = ()  # the end of each of the trial's reps (s from its start; its joint phase)
    lead_s: float = 0.0  # the trial's static start, before its first rep (s)
    schedule: tuple[tuple[float, float], ...] = ()  # sets: one cycle as (trial start, duration); () the trial loops
    sets: SimSets | None = None  # what the cycle plays (services.sessions.sim_sets.with_sets); None: the trial loops
    trial_loop_s: float = 0.0  # with sets: the trial's own length (s), which the cycle's segments cut


def sim_sources(recording: Path, pack: str) -> SimSources:
    """Arrays of the last (held-out) trial of ``pack`` in the bundled recording: EMG chunks -> one (n, 16) Trigno
    source, IMU samples -> one Xsens source per tracker (quaternion, acceleration, rate of turn, magnetic field).
    Every source starts at the trial's first instant and is cut to one common duration, so sample k of each is the
    same instant of the trial, in every round of the loop. The recording holds no accelerometer data of the EMG
    sensors: each sensor's (on the Trigno's AUX port) is computed from the recorded joint angles
    (:func:`electrode_accelerations`)."""
    from drivers.trigno.protocol import N_SENSORS
    from drivers.xsens.source import ImuSource

    if not recording.is_file():
        raise InputError(
            "bundled session not found (generate it with `msk synth`, recordings/README.md)", path=recording
        )
    t0, t1, load = _last_trial_window(recording, pack)
    streams = _read_trial(recording, pack, t0, t1)
    emg = np.concatenate(streams.emg_rows)
    if emg.shape[1] > N_SENSORS:
        raise InputError(f"{emg.shape[1]} EMG channels exceed the Trigno's {N_SENSORS} sensors", path=recording)
    imu_rates = {}
    for tracker, (_, rows) in streams.imu.items():
        rows.sort(key=lambda r: r[0])
        imu_rates[tracker] = float(round(1.0 / np.median(np.diff(np.array([r[0] for r in rows], dtype=float) / 1e9))))
    counts = _common_loop(
        {
            "emg": (emg.shape[0], streams.rate),
            **{t: (len(rows), imu_rates[t]) for t, (_, rows) in streams.imu.items()},
        },
        pack,
        recording,
    )
    source = _emg_source(recording, pack, streams, emg[: counts["emg"]])
    trackers = {}
    for tracker, (segment, rows) in streams.imu.items():
        rows = rows[: counts[tracker]]
        arrays = {
            name: np.array([r[k] for r in rows], dtype=float)
            for k, name in enumerate(("quaternion", "acceleration", "rate_of_turn", "magnetic_field"), start=1)
        }
        trackers[tracker] = (segment, ImuSource(imu_rates[tracker], arrays, f"{recording.name}:{segment}"))
    electrodes = {f"sensor{k + 1:02d}.EMG": label for k, label in enumerate(streams.labels)}
    rep_ends, lead = trial_reps(streams.joints, streams.emg_start)
    return SimSources(source, trackers, electrodes, float(load), f"{pack}_{load:g}kg", pack, rep_ends, lead)


def _common_loop(streams: dict[str, tuple[int, float]], pack: str, recording: Path) -> dict[str, int]:
    """Per stream name, (samples, rate in Hz) -> the most samples, no more than it has, such that every stream
    spans one and the same duration: looping simulators then stay on one world round after round (a 60 Hz and
    a 2000 Hz stream loop together only on multiples of 50 ms)."""
    slowest = min(streams, key=lambda name: streams[name][1])
    n_slow, rate_slow = streams[slowest]
    for m in range(n_slow, n_slow // 2, -1):
        counts = {name: m / rate_slow * rate for name, (_, rate) in streams.items()}
        if all(abs(c - round(c)) < 1e-6 and round(c) <= streams[name][0] for name, c in counts.items()):
            return {name: int(round(c)) for name, c in counts.items()}
    raise InputError(
        f"the {pack} trial's streams have no common duration within its shorter half, so the "
        "simulators could not loop together",
        path=recording,
        value={name: rate for name, (_, rate) in streams.items()},
    )


def _last_trial_window(recording: Path, pack: str) -> tuple[int, int, float]:
    """(start, end device time in ns, load in kg) of the last trial of ``pack``: between its load event with a load
    and the next one without."""
    windows, start = [], None
    for m in read_messages(recording):
        if m.type_name == "msk.LoadEvent":
            e = m.decode(messages.LoadEvent)
            if e.exercise != pack:
                continue
            if e.barbell_mass_kg > 0:
                start = (e.device_time_ns, e.barbell_mass_kg)
            elif start is not None:
                windows.append((start[0], e.device_time_ns, start[1]))
                start = None
    if not windows:
        raise InputError(
            f"the bundled session has no trial of pack {pack!r}", path=recording, field="session.pack", value=pack
        )
    return windows[-1]


# one IMU sample: (device time, quaternion, acceleration, rate of turn, magnetic field)
_ImuRow = tuple[int, list[float], list[float], list[float], list[float]]


@dataclass
class _TrialStreams:
    """The recorded streams of one trial window, as read (EMG chunks as rows, IMU samples per tracker)."""

    emg_rows: list[np.ndarray]
    labels: list[str]
    rate: float
    emg_start: int
    imu: dict[str, tuple[str, list[_ImuRow]]]  # tracker id -> (segment, samples)
    joints: list[messages.JointAngles]


def _read_trial(recording: Path, pack: str, t0: int, t1: int) -> _TrialStreams:
    """The joint angles, EMG chunks and IMU samples with device times in [t0, t1), checked to start together."""
    emg_rows: list[np.ndarray] = []
    labels: list[str] | None = None
    rate: float | None = None
    emg_start: int | None = None
    imu: dict[str, tuple[str, list[_ImuRow]]] = {}
    joints: list[messages.JointAngles] = []
    for m in read_messages(recording):
        if m.type_name == "msk.JointAngles":
            j = m.decode(messages.JointAngles)
            if t0 <= j.device_time_ns < t1:
                joints.append(j)
        elif m.type_name == "msk.EmgChunk":
            c = m.decode(messages.EmgChunk)
            if t0 <= c.device_time_ns < t1:
                emg_rows.append(np.asarray(c.samples, dtype=np.float32).reshape(c.n_samples, c.n_channels))
                labels, rate = list(c.channel_labels), c.sample_rate_hz
                emg_start = c.device_time_ns if emg_start is None else min(emg_start, c.device_time_ns)
        elif m.type_name == "msk.ImuSample":
            s = m.decode(messages.ImuSample)
            if t0 <= s.device_time_ns < t1:
                o, a, g, b = s.orientation, s.acceleration, s.rate_of_turn, s.magnetic_field
                imu.setdefault(s.tracker_id, (s.segment, []))[1].append(
                    (s.device_time_ns, [o.w, o.x, o.y, o.z], [a.x, a.y, a.z], [g.x, g.y, g.z], [b.x, b.y, b.z])
                )
    if not emg_rows or not imu or labels is None or rate is None or emg_start is None:  # all set with the EMG
        raise InputError(f"no EMG or IMU samples in the {pack} trial of the bundled session", path=recording)
    starts = {"emg": emg_start, **{t: min(r[0] for r in rows) for t, (_, rows) in imu.items()}}
    if max(starts.values()) - min(starts.values()) > 1e9 / (2 * rate):
        raise InputError(
            f"the {pack} trial's streams do not start at one instant (first samples at device times "
            f"{starts} ns): the simulators could not sample one world",
            path=recording,
        )
    return _TrialStreams(emg_rows, labels, float(rate), emg_start, imu, joints)


def _emg_source(recording: Path, pack: str, streams: _TrialStreams, emg: np.ndarray) -> EmgSource:
    """The Trigno source: ``emg`` in the first sensor slots, the rest empty, with each sensor's accelerations."""
    from drivers.trigno.protocol import N_SENSORS
    from drivers.trigno.source import EmgSource

    labels = streams.labels
    samples = np.zeros((emg.shape[0], N_SENSORS), dtype=np.float32)
    samples[:, : emg.shape[1]] = emg
    names = tuple(labels) + ("",) * (N_SENSORS - len(labels))
    acc_rate, acc = electrode_accelerations(streams.joints, labels, pack, streams.emg_start, recording)
    slot_acc = np.zeros((acc.shape[0], N_SENSORS, 3), dtype=np.float32)
    slot_acc[:, : len(labels)] = acc
    return EmgSource(
        samples,
        streams.rate,
        names,
        tuple(k < len(labels) for k in range(N_SENSORS)),
        f"{recording.name}:{pack}",
        slot_acc,
        acc_rate,
    )


def trial_reps(joints: list, start_ns: int) -> tuple[tuple[float, ...], float]:
    """(the end of each rep, the static start before the first) in s from ``start_ns``, from the recorded joint
    frames' phase, counted by the one segmenter (msk_core.signal.reps.phase_rep_spans); a rep ends at the next
    one's first sample (the trial's reps follow each other without rest) or one frame after its last."""
    from msk_core.signal.reps import phase_rep_spans

    t = np.array([(j.device_time_ns - start_ns) / 1e9 for j in joints])
    phase = np.array([j.phase if j.HasField("phase") else math.nan for j in joints])
    if t.size < 3 or not np.any(np.isfinite(phase)):
        return (), 0.0
    spans = phase_rep_spans(t, phase)
    if not spans:
        return (), 0.0
    step = float(np.median(np.diff(t)))
    ends = [a for a, _ in spans[1:]] + [spans[-1][1] + step]
    return tuple(ends), spans[0][0]


def electrode_accelerations(
    joints: list, channels: list[str], pack: str, start_ns: int, recording: Path
) -> tuple[float, np.ndarray]:
    """(rate in Hz, (n, channels, 3) in g): what each EMG sensor's accelerometer measures during the recorded trial,
    at the recorded joint frames' instants from ``start_ns`` (the trial's first EMG sample) on. The synthetic
    generator's own model (:func:`msk_core.synth.imu.simulate_electrode_acc`): each channel's site on the pack body
    of the exercise's electrode sites (a site on a part the pack keeps still measures gravity alone), its specific
    force from the pack's rigid-body kinematics of the recorded angles, velocities and accelerations, in a random
    mounting (seeded), plus 0.02 m/s² noise; the trackers' recorded accelerations come from the same kinematics."""
    from msk_core.model import load_pack
    from msk_core.signal.clock_sync import STANDARD_GRAVITY
    from msk_core.synth import SPECS
    from msk_core.synth.imu import Motion, simulate_electrode_acc

    model = load_pack(pack)
    specs = [spec for spec in SPECS.values() if spec.pack == model.name]
    if not joints or not specs:
        raise InputError(
            f"the {pack} trial of the bundled session has no joint frames, or no synthetic exercise "
            "uses the pack: the simulated Trigno sensors' accelerations cannot be computed",
            path=recording,
            value=(len(joints), model.name),
        )
    names = list(joints[0].coordinates)
    missing = [c for c in model.coordinates if c not in names]
    if missing:
        raise InputError(f"the recorded joint frames lack the pack's coordinates {missing}", path=recording)
    order = [names.index(c) for c in model.coordinates]
    q, qd, qdd = (np.array([np.asarray(getattr(j, f), dtype=float)[order] for j in joints]) for f in ("q", "qd", "qdd"))
    times = np.array([j.device_time_ns for j in joints], dtype=np.int64)
    step_ns = float(np.median(np.diff(times)))
    if abs(times[0] - start_ns) > 1000 or np.any(np.abs(np.diff(times) - step_ns) > 1000):  # 1 µs: rounding
        raise InputError(
            "the recorded joint frames do not start with the EMG or are not evenly spaced",
            path=recording,
            value=(int(times[0]), int(start_ns)),
        )
    time_s = np.arange(len(joints)) * step_ns / 1e9
    motion = Motion(time_s, q, qd, qdd)
    stream = simulate_electrode_acc(
        model, specs[0].electrode_sites, list(channels), motion, seed=0, key=("live-sim", model.name)
    )
    return 1e9 / step_ns, (stream.acceleration / STANDARD_GRAVITY).astype(np.float32)


@dataclass
class Simulators:
    """The session's simulated devices, sampling one world: one trial clock is shared by all, so a device that starts
    streaming at t streams the trial from the instant t, whatever the others did; each keeps its own device clock and
    counters."""

    trigno: TrignoSimulator
    xsens: dict[str, XsensSimulator]  # by tracker id
    clock: TrialClock
    trial: str = ""  # SimSources.trial
    exercise: str = ""  # SimSources.exercise
    schedule: tuple[tuple[float, float], ...] = ()  # SimSources.schedule: sets with rests; () the trial loops
    trial_loop_s: float = 0.0  # SimSources.trial_loop_s

    def world(self) -> dict:
        """The trial clock as ``summary.json`` states it (``trial_clock``), so that a frame's host time says which
        instant of the trial it is: the trial's sample 0 was measured at ``origin_ns`` (host time, ns since the
        epoch, as every mapped time of the session) and the trial loops every ``loop_s``: trial time = (host time -
        origin) x speed, modulo the loop. With sets (``schedule``: one cycle of set and rest as [trial start,
        duration] segments, ``cycle_s`` long) the cycle repeats instead, and a moment of it is the trial instant of
        its segment (services.sessions.live_scoring.SimWorld). Empty while no device has started streaming."""
        if self.clock.start is None:
            return {}
        realtime_minus_monotonic_ns = time.time_ns() - time.monotonic_ns()
        return {
            "exercise": self.exercise,
            "trial": self.trial,
            "origin_ns": round(self.clock.start * 1e9) + realtime_minus_monotonic_ns,
            "loop_s": self.trial_loop_s or self.trigno.source.n_samples / self.trigno.source.rate_hz,
            "speed": self.trigno.config.speed,  # trial seconds per host second
        } | (
            {
                "schedule": [list(segment) for segment in self.schedule],
                "cycle_s": self.trigno.source.n_samples / self.trigno.source.rate_hz,
            }
            if self.schedule
            else {}
        )

    def hold(self) -> None:
        self.trigno.hold()
        for sim in self.xsens.values():
            sim.hold()

    def close(self) -> None:
        self.trigno.close()
        for sim in self.xsens.values():
            sim.close()

    def sent(self) -> dict:
        """Per device: what it sent, its stated latency and the trial sample it started streaming at."""
        t = self.trigno.stats
        return {
            "trigno": {
                "samples": t.samples_sent,
                "frames": t.frames_sent,
                "latency_s": t.latency_s,
                "start_index": t.start_index,
                **({"faults": [f.describe() for f in self.trigno.config.faults]} if self.trigno.config.faults else {}),
            },
            **{
                tracker: {
                    "samples": s.stats.messages_sent,
                    "bytes_dropped": s.stats.bytes_dropped,
                    "latency_s": s.stats.latency_s,
                    "start_index": s.stats.start_index,
                    "samples_skipped": s.stats.samples_skipped,
                }
                for tracker, s in self.xsens.items()
            },
        }


def start_simulators(
    sources: SimSources,
    *,
    trigno_latency_s: float = 0.0,
    xsens_latency_s: float | dict[str, float] = 0.0,
    clock: TrialClock | None = None,
    trackers_after_trigno_s: float | None = None,
    trigno_faults: tuple[SensorFault, ...] = (),
) -> Simulators:
    """The Trigno and one Xsens simulator per tracker on one trial clock (``clock``, a ``TrialClock``; default: one
    that starts when the first device starts streaming, so the set begins with its static pose as the first device
    is switched on): whenever a driver starts a device streaming, it streams the trial from that instant.
    ``*_latency_s``: each device's delivery latency (a sample measured at t leaves at t + latency);
    ``xsens_latency_s`` one for every tracker, or per tracker id (0 for a tracker not named).
    ``trackers_after_trigno_s``: the trackers measure from that long after the Trigno's first sample on (each waits
    for the Trigno to start), as trackers switched on after the base; None: as soon as their driver asks.
    ``trigno_faults``: electrode faults the Trigno injects (:class:`drivers.trigno.simulator.SensorFault`)."""
    from drivers.trial_clock import TrialClock
    from drivers.trigno.simulator import SimulatorConfig, TrignoSimulator
    from drivers.xsens.simulator import XsensSimulator

    clock = TrialClock() if clock is None else clock
    # free ports: several sessions (tests, users) may run side by side; the AUX port carries the sensors'
    # accelerometers, no legacy listeners needed
    trigno = TrignoSimulator(
        sources.emg,
        SimulatorConfig(
            command_port=0,
            emg_port=0,
            legacy_emg_port=None,
            aux_port=0,
            trial_clock=clock,
            latency_s=trigno_latency_s,
            faults=tuple(trigno_faults),
        ),
    ).start()

    def after_trigno() -> float | None:  # passed on only with trackers_after_trigno_s
        start = trigno.stats.start_index
        if start is None or trackers_after_trigno_s is None:
            return None
        return clock.instant(start, trigno.rate_hz) + trackers_after_trigno_s

    xsens = {}
    try:
        for tracker, (_, source) in sources.imu.items():
            # a long wake-up window: the simulator waits in Config for the driver instead of streaming into a port
            # nobody has opened yet (a real MTi would, and those messages would never be read)
            latency_s = xsens_latency_s.get(tracker, 0.0) if isinstance(xsens_latency_s, dict) else xsens_latency_s
            xsens[tracker] = XsensSimulator(
                source,
                device_id=int(tracker, 16),
                wakeup_window_s=3600.0,
                trial_clock=clock,
                latency_s=latency_s,
                measure_not_before=None if trackers_after_trigno_s is None else after_trigno,
            ).start()
    except BaseException:
        trigno.close()
        for sim in xsens.values():
            sim.close()
        raise
    return Simulators(trigno, xsens, clock, sources.trial, sources.exercise, sources.schedule, sources.trial_loop_s)


# ------------------------------------------------------------------------------------------------ subject


def session_profile(subject: Path, electrodes: dict[str, str], groups: list[str], out: Path) -> Path:
    """The subject profile with its EMG normalisation keyed by the live channel labels of the session file: a label
    mapped to a profile electrode takes that electrode's group and MVC amplitude; one mapped to a group has no MVC
    (flagged ``no_mvc`` by the estimator, never used raw)."""
    doc = json.loads(subject.read_text())
    norm = doc.get("emg_normalisation", {})
    live = {}
    for label, target in electrodes.items():
        live[label] = dict(norm[target]) if target in norm else {"group": target}
    doc["emg_normalisation"] = live
    path = out / "subject_session.json"
    path.write_text(json.dumps(doc, indent=1) + "\n")
    return path


# ------------------------------------------------------------------------------------------------ summary


class _DeviceStatuses:
    """The devices' statuses of a recording, in order: each one's last state, and the connection losses while the
    session ran with the newest problem it reported."""

    def __init__(self) -> None:
        self.lost: dict[str, int] = {}
        self.last: dict[str, messages.DeviceStatus] = {}
        self.drops: Counter[str] = Counter()
        self.was_connected: dict[str, bool] = {}  # before its newest status
        self.problem: dict[str, str] = {}

    def add(self, status: messages.DeviceStatus) -> None:
        device, before = status.device_id, self.last.get(status.device_id)
        connected = before is not None and before.connected
        self.lost[device] = int(status.samples_lost)
        self.drops[device] += int(connected and not status.connected)
        self.was_connected[device] = connected
        self.problem[device] = status.last_error or self.problem.get(device, "")
        self.last[device] = status

    def summary(self) -> dict[str, dict[str, object]]:
        """Per device: kind, connected, errors and last error of its last status, disconnections (the last status,
        disconnected at the stop, is not a loss) and problem."""
        return {
            device: {
                "kind": s.kind,
                "connected": s.connected,
                "errors": int(s.errors),
                "last_error": s.last_error,
                "disconnections": self.drops[device] - int(self.was_connected[device] and not s.connected),
                "problem": self.problem[device],
            }
            for device, s in self.last.items()
        }


def summarise(mcap: Path | list[Path], duration_s: float) -> dict:
    """What the recording (one file, or the parts this session wrote) holds: samples per device, samples lost and the
    final state of each device (its last DeviceStatus), frames and flags per method, per node of the graph what
    it received, dropped as unusable (per topic and reason) and could not use (its last status), and per stream the
    clock mapping the node that maps it reported last (offset, spread, latency, method)."""
    emg: Counter[str] = Counter()  # samples per source
    imu: Counter[str] = Counter()  # samples per tracker
    devices = _DeviceStatuses()
    frames: Counter[str] = Counter()  # per method
    flags: dict[str, Counter[str]] = {}  # per method, per flag
    envelopes = joints = chunks = 0
    nodes: dict[str, messages.DeviceStatus] = {}
    fatigue: dict[str, list[messages.ElectrodeFatigue]] = {}  # per electrode, its newest values of each set
    for part in [mcap] if isinstance(mcap, Path) else mcap:
        for m in read_messages(part):
            t = m.type_name
            if t == "msk.EmgChunk":
                c = m.decode(messages.EmgChunk)
                emg[c.source_id] += c.n_samples
                chunks += 1
            elif t == "msk.ImuSample":
                imu[m.decode(messages.ImuSample).tracker_id] += 1
            elif t == "msk.DeviceStatus":
                s = m.decode(messages.DeviceStatus)
                if s.kind == "node":
                    nodes[s.device_id] = s
                    for e in s.fatigue:
                        keep_fatigue(fatigue.setdefault(f"{e.source}/{e.channel}", []), e)
                    continue
                devices.add(s)
            elif t == "msk.ActivationFrame":
                f = m.decode(messages.ActivationFrame)
                frames[f.method] += 1
                for flag in f.flags:
                    flags.setdefault(f.method, Counter())[flag] += 1
            elif t == "msk.EmgEnvelope":
                envelopes += 1
            elif t == "msk.JointAngles":
                joints += 1
    dropped: dict[str, dict[str, dict[str, int]]] = {}
    for name, status in nodes.items():
        per_key = dropped.setdefault(name, {})
        for drop in status.dropped:
            per_key.setdefault(drop.key, {})[drop.reason] = int(drop.count)
    return {
        "duration_s": round(duration_s, 3),
        "samples": {**{f"emg/{k}": v for k, v in emg.items()}, **{f"imu/{k}": v for k, v in imu.items()}},
        "samples_lost": devices.lost,
        "devices": devices.summary(),
        "joint_frames": joints,
        "emg_chunks": chunks,
        "envelopes": envelopes,
        "frames_estimated": dict(frames),
        "flags": {m: dict(c) for m, c in flags.items()},
        "inputs_dropped": dropped,
        "node_errors": {name: int(s.errors) for name, s in nodes.items()},
        "node_last_error": {name: s.last_error for name, s in nodes.items() if s.last_error},
        # per node, its input streams' silences longer than the threshold, and publications it missed (node_runtime)
        "input_outages": {name: outages_summary(s.outages) for name, s in nodes.items() if s.HasField("outages")},
        "clocks": {c.source: clock_summary(c, name) for name, s in nodes.items() for c in s.clocks},
        "electrodes": {f"{e.source}/{e.channel}": electrode_summary(e) for s in nodes.values() for e in s.electrodes},
        "fatigue": {name: [fatigue_summary(e) for e in sets] for name, sets in fatigue.items()},
    }


_COUNTS = ("count", "total_s", "longest_s", "missed", "recovered")


def keep_fatigue(sets: list[messages.ElectrodeFatigue], electrode: messages.ElectrodeFatigue) -> None:
    """One status's fatigue values of an electrode: the newest of its set (a new set when the set number changes or
    the reps start again)."""
    if sets and sets[-1].set_number == electrode.set_number and len(electrode.median_hz) >= len(sets[-1].median_hz):
        sets[-1] = electrode
    elif electrode.median_hz or not sets:
        sets.append(electrode)


def fatigue_summary(electrode: messages.ElectrodeFatigue) -> dict:
    """One electrode's fatigue index over one set as ``summary.json`` says it: per rep the median and mean
    frequency (Hz), the median frequency's slope per rep (Hz and % of the first reps) with its standard error, and
    the change of both from the set's first reps (%); null where there is no value."""

    def value(x: float, digits: int = 3) -> float | None:
        return round(x, digits) if math.isfinite(x) else None

    return {
        "group": electrode.group,
        "set_number": int(electrode.set_number),
        "reps": len(electrode.median_hz),
        "median_hz": [value(v, 2) for v in electrode.median_hz],
        "mean_hz": [value(v, 2) for v in electrode.mean_hz],
        "median_slope_hz_per_rep": value(electrode.median_slope_hz_per_rep),
        "median_slope_se_hz_per_rep": value(electrode.median_slope_se_hz_per_rep),
        "median_slope_pct_per_rep": value(electrode.median_slope_pct_per_rep),
        "median_change_pct": value(electrode.median_change_pct, 2),
        "mean_slope_pct_per_rep": value(electrode.mean_slope_pct_per_rep),
        "mean_change_pct": value(electrode.mean_change_pct, 2),
    }


def electrode_summary(electrode: messages.ElectrodeQuality) -> dict:
    """One electrode's quality over the session as ``summary.json`` says it (the estimator's last status): the muscle
    group, the state at the end, the time spent in check and bad, the fault episodes (how many, per fault how many
    it was raised in, and the last ones with their device times)."""
    return {
        "group": electrode.group,
        "state": electrode.state,
        "reasons": list(electrode.reasons),
        "check_s": round(electrode.check_s, 3),
        "bad_s": round(electrode.bad_s, 3),
        "episodes": int(electrode.episodes),
        "episode_reasons": dict(sorted(electrode.episode_reasons.items())),
        "recent_episodes": [
            {
                "start_s": round(e.start_s, 4),
                "end_s": round(e.end_s, 4) if e.HasField("end_s") else None,
                "worst": e.worst,
                "reasons": list(e.reasons),
            }
            for e in electrode.recent
        ],
    }


def clock_summary(clock: messages.ClockOffset, node: str) -> dict:
    """One stream's clock mapping as ``summary.json`` says it: the offset applied (ms since the epoch), its spread,
    the latency taken off, the method and why, and, with an offset measured another way, the arrival mapping it
    replaces and that mapping's error (arrival minus applied: how much later it would have put every sample); per
    tracker the acceleration alignment's estimate (``device_offset_ms``: tracker device time minus EMG device time)."""
    out = {
        "offset_ms": clock.offset_ms,
        "spread_ms": round(clock.spread_ms, 3),
        "latency_ms": round(clock.latency_ms, 3),
        "method": clock.method,
        "samples": int(clock.samples),
        "node": node,
    }
    if clock.reason:
        out["reason"] = clock.reason
    if clock.HasField("arrival_offset_ms"):
        out["arrival_offset_ms"] = clock.arrival_offset_ms
        out["arrival_error_ms"] = round(clock.arrival_offset_ms - clock.offset_ms, 3)
    if clock.alignments:
        out["alignments"] = {
            a.reference: {
                "status": a.status,
                "reason": a.reason,
                "device_offset_ms": a.device_offset_ms,
                "spread_ms": round(a.spread_ms, 3),
                "drift_ppm": round(a.drift_ppm, 3),
                "peak_correlation": round(a.peak_correlation, 4),
                "sensor": a.sensor,
                "windows": int(a.windows),
                "host_offset_ms": a.host_offset_ms,
            }
            for a in clock.alignments
        }
    return out


def set_summary(record: dict) -> str:
    """One set of the summary, e.g. ``2: 6 reps, 16.7 s under tension, ended by rest`` (``ended with the session``:
    under way when it stopped)."""
    reps = record["reps"]
    by = record.get("ended_by", "")
    ended = ", ended with the session" if by == END_OF_DATA else f", ended by {by}" if by else ""
    return f"{record['number']}: {reps} rep{'s' if reps != 1 else ''}, {record['time_under_tension_s']:.1f} s under tension{ended}"


def _electrode_lines(summary: dict) -> list[str]:
    """The summary's lines on the electrodes: how many judged, those that never streamed and why, each with fault
    episodes."""
    lines: list[str] = []
    electrodes = summary.get("electrodes", {})
    faulty = {name: e for name, e in electrodes.items() if e["episodes"]}
    if electrodes:
        lines.append(f"  electrodes: {len(electrodes)} judged, {len(faulty)} with fault episodes")
    if summary.get("electrodes_never_streamed"):
        emg = sum(n for device, n in summary["samples"].items() if device.startswith("emg/"))
        why = (
            "no EMG arrived from the Trigno at all: see its line and status"
            if not emg
            else "their sensors not paired or not on, or a wrong channel in [electrodes]"
        )
        lines.append(
            f"  electrodes never streamed ({why}; their muscles estimated without EMG): "
            + ", ".join(f"{ch} ({e})" for ch, e in summary["electrodes_never_streamed"].items())
        )
    for name, e in faulty.items():
        lines.append(
            f"  electrode {name}"
            + (f" ({e['group']})" if e["group"] else "")
            + f": {e['episodes']} fault episode{'s' if e['episodes'] != 1 else ''} ("
            + ", ".join(f"{reason} {n}" for reason, n in e["episode_reasons"].items())
            + f"), {e['check_s']:.1f} s check, {e['bad_s']:.1f} s bad; now {e['state']}"
        )
    return lines


def _troubles(summary: dict, name: str, *, alone: bool = False) -> str:
    """What device ``name``'s statuses said went wrong (``; ...`` parts, "" for nothing): its connection losses
    and, with them or errors, the problem it last reported. ``alone``: a device without a samples line of its own
    (an MVN suit, whose samples are its segments'), whose samples lost and problem are said whatever."""
    status = summary.get("devices", {}).get(name, {})
    away, missing = int(status.get("disconnections", 0)), summary["samples_lost"].get(name, 0)
    problem = status.get("problem") if (away or status.get("errors") or alone) else ""
    return (
        (f"; {missing} samples lost" if alone and missing else "")
        + (f"; connection lost {away}x" if away else "")
        + (f"; last said: {problem}" if problem else "")
    )


def summary_text(summary: dict) -> str:
    lines = [
        f"session of {summary['duration_s']:.1f} s"
        + (f", stopped by {summary['stopped_by']}" if "stopped_by" in summary else "")
    ]
    for device, n in summary["samples"].items():
        name = device.split("/", 1)[1]
        lines.append(f"  {device}: {n} samples, {summary['samples_lost'].get(name, 0)} lost{_troubles(summary, name)}")
    shown = {device.split("/", 1)[1] for device in summary["samples"]}
    for name in summary.get("devices", {}):  # a device whose samples are another's (an MVN suit's segments), or none
        if name not in shown and (troubles := _troubles(summary, name, alone=True)):
            lines.append(f"  {name}:{troubles.removeprefix(';')}")
    lines.append(f"  joint frames: {summary['joint_frames']}; EMG envelopes: {summary['envelopes']}")
    # without a joint frame there was no lift to count (a session that failed at the start): no "1: 0 reps"
    if summary.get("sets") and (summary["joint_frames"] or any(record.get("reps") for record in summary["sets"])):
        lines.append("  sets: " + "; ".join(set_summary(record) for record in summary["sets"]))
    if summary.get("reps_not_counted"):
        lines.append(f"  reps not counted live: {summary['reps_not_counted']}")
    if summary.get("joint_frames_paused"):
        lines.append(
            f"  estimates paused for about {summary['joint_frames_paused']} joint frames: load events declared "
            "another exercise than the session's"
        )
    for method, n in summary["frames_estimated"].items():
        f = summary["flags"].get(method, {})
        lines.append(f"  {method}: {n} frames estimated; flagged frames: {flag_counts_text(f)}")
    for node, per_key in summary.get("inputs_dropped", {}).items():
        if per_key:
            lines.append(
                f"  {node} dropped unusable inputs: "
                + ", ".join(f"{key} {reason} {n}" for key, reasons in per_key.items() for reason, n in reasons.items())
            )
    for node, text in summary.get("node_last_error", {}).items():
        lines.append(f"  {node}: {summary['node_errors'][node]} inputs not used, last: {text}")
    for node, outages in summary.get("input_outages", {}).items():
        if outages["count"] or outages["missed"]:
            lines.append(
                f"  {node}: {outages_text(messages.InputOutages(**{k: v for k, v in outages.items() if k in _COUNTS}))}"
                + (f", the last {outages['last_start']} to {outages['last_end']}" if outages["count"] else "")
            )
    for restart in summary.get("router_restarts", []):
        lines.append(
            f"  router {restart['exit']} {restart['at_s']:.1f} s into the session; started again, back after "
            f"{restart['back_after_s']:.1f} s"
        )
    for source, clock in summary.get("clocks", {}).items():
        lines.append(
            f"  clock of {source}: {clock['method']}, spread {clock['spread_ms']:.1f} ms, latency "
            f"{clock['latency_ms']:g} ms ({clock['node']})"
            + (
                f"; the arrival mapping was {clock['arrival_error_ms']:+.1f} ms off"
                if "arrival_error_ms" in clock
                else ""
            )
            + (f"; {clock['reason']}" if clock.get("method") == "arrival" and clock.get("reason") else "")
        )
    lines += _electrode_lines(summary)
    if "simulators_sent" in summary:
        lines.append(
            "  simulators sent: " + ", ".join(f"{k} {v['samples']}" for k, v in summary["simulators_sent"].items())
        )
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------ the graph


@dataclass(frozen=True)
class LivePlan:
    """Everything the graph needs, resolved from the session file (and ``--sim``) by :func:`plan_for`."""

    session: LiveSession
    methods: tuple[str, ...]
    subject: Path | None  # the session's copy of the profile; None: not calibrated yet, 'so' alone
    trigno: tuple[str, int] | None = None  # (HOST[:PORT], EMG port)
    trigno_aux_port: int | None = None  # the sensors' accelerometers (AUX port), for the EMG clock's alignment
    trigno_aux_layout: AuxLayout | None = None  # what that port carries (the session file's; None: from its number)
    xsens_ports: tuple[str, ...] = ()
    trackers: dict[str, str] = field(default_factory=dict)
    exercise: str = ""  # the pack's name (session.pack may be a path)
    trigno_latency_ms: float = (
        0.0  # stated device latencies the clock mappings take off (live_session.stated_latencies)
    )
    tracker_latency_ms: dict[str, float] = field(default_factory=dict)
    names: dict[str, str] = field(default_factory=dict)  # the session file's display names (over the pack's)
    electrodes: dict[str, str] = field(default_factory=dict)  # Trigno channel -> electrode or group, as run


def driver_argv(plan: LivePlan, kind: str) -> list[str]:
    s = plan.session
    argv = python_module("services.cli", "drivers", "--session", s.name)
    if kind == "trigno":
        if plan.trigno is None:
            raise ConfigError("the Trigno driver needs the Trigno's address: the session plan has none", field="trigno")
        host, emg_port = plan.trigno
        argv += ["--trigno", host, "--trigno-emg-port", str(emg_port), "--trigno-id", s.trigno_id]
        if plan.trigno_aux_port is not None:
            argv += ["--trigno-aux-port", str(plan.trigno_aux_port)]
            if plan.trigno_aux_layout is not None:
                argv += ["--trigno-aux-layout", plan.trigno_aux_layout.value]
    else:
        for port in plan.xsens_ports:
            argv += ["--xsens", port]
        if s.xsens_mvn is not None:
            argv += ["--mvn", s.xsens_mvn]
        argv += ["--imu-rate", str(s.imu_rate_hz), "--xsens-baud", str(s.xsens_baud)]
        argv += [f"--segment={t}={seg}" for t, seg in plan.trackers.items()]
    return argv


@dataclass
class FlowCounts:
    """Messages of the session seen by the graph's monitor node (updated live)."""

    joints: int = 0
    activations: Counter = field(default_factory=Counter)  # method -> frames
    # load events declare another exercise than the session's: the estimator leaves the joint frames unanswered
    paused: bool = False
    paused_joints: int = 0  # joint frames that arrived meanwhile
    sets: list[dict] = field(default_factory=list)  # the sets as the monitor counted them, once the session ended

    def text(self) -> str:
        return f"{self.joints} joint frames; activation frames " + (
            ", ".join(f"{m} {n}" for m, n in self.activations.items()) or "none"
        )


@dataclass
class SessionFacts:
    """What the session is about, published by ``msk live`` on ``msk/<session>/load`` at start and when the operator
    changes them (``msk load``): the exercise (pack), the barbell load, the set under way and the athlete."""

    exercise: str
    load_kg: float
    set_number: int = 1
    athlete: str = ""
    names: dict[str, str] = field(default_factory=dict)  # display names the session file gives (LoadEvent.names)
    rest_s: float = 0.0  # rest detection (session.rest_s, LoadEvent.set_rest_s); 0: the default

    def message(self) -> messages.LoadEvent:
        now = messages.now_ns()  # msk live maps every device clock onto the host clock: its device time is now
        return messages.LoadEvent(
            barbell_mass_kg=float(self.load_kg),
            exercise=self.exercise,
            set_number=int(self.set_number),
            athlete=self.athlete,
            names=self.names,
            set_rest_s=float(self.rest_s),
            device_time_ns=now,
            host_time_ns=now,
        )


def monitor(
    options,
    *,
    session: str,
    counts: FlowCounts,
    facts: queue.Queue,
    stop_event: threading.Event,
    ready_event: threading.Event,
    ready_key,
    on_facts=None,
    exercise: str = "",
) -> None:
    """The graph node of ``msk live`` itself (``monitor`` in services.transport.session_graph): counts joints and activation
    frames, so the stop can wait (bounded) until the estimator has answered every joint frame, and publishes the
    session facts put on ``facts`` (a history publisher: a late ``msk load`` or a restarted recorder fetches them);
    ``on_facts`` gets the facts in effect as they change (:class:`services.sessions.facts.FactsFollower`)."""
    from msk_core.model.pack import is_known_exercise
    from services.nodes.node_runtime import Rejected, check_payload
    from services.nodes.readiness import declare_ready
    from services.sessions.facts import FactsFollower
    from services.transport.zenoh_session import declare_history_publisher, open_session, publish

    prefix = topics.session_prefix(session)

    def on_joints(sample) -> None:
        try:  # as the estimator checks it: a payload it drops is no joint frame it will answer
            check_payload(str(sample.key_expr), sample.payload.to_bytes(), expected_type="msk.JointAngles")
        except Rejected:
            return
        counts.joints += 1
        counts.paused_joints += counts.paused

    follower = FactsFollower(on_facts) if on_facts is not None else None

    def on_activation(sample) -> None:
        method = str(sample.key_expr).rsplit("/", 1)[1]
        counts.activations[method] += 1
        if follower is not None and follower.wants(method):
            try:  # checked as every node checks it: a stray payload must not move the sets
                frame = check_payload(
                    str(sample.key_expr), sample.payload.to_bytes(), expected_type="msk.ActivationFrame"
                )
            except Rejected:  # counted by the nodes that use the frames; here only the sets matter
                return
            follower.on_frame(method, messages.as_message(messages.ActivationFrame, frame))

    def on_load(sample) -> None:  # its own facts and an operator's (`msk load`): the session's current ones
        try:
            event = messages.as_message(
                messages.LoadEvent,
                check_payload(str(sample.key_expr), sample.payload.to_bytes(), expected_type="msk.LoadEvent"),
            )
        except Rejected:
            return  # the estimator and recorder count bad inputs; here only the facts matter
        if event.exercise and not is_known_exercise(event.exercise, (exercise,)):
            return  # as the estimator refuses it: not a fact of this session
        if event.exercise:
            counts.paused = event.exercise != exercise
        if follower is not None:
            follower.on_event(event)

    with open_session(options) as zsession:
        load = declare_history_publisher(zsession, topics.load_key(session), "msk.LoadEvent", history_samples=100)
        subscribers = [
            zsession.declare_subscriber(f"{prefix}/joints", on_joints),
            zsession.declare_subscriber(f"{prefix}/activations/*", on_activation),
            zsession.declare_subscriber(topics.load_key(session), on_load),
        ]
        token = declare_ready(zsession, ready_key)  # noqa: F841 - alive while the node runs
        ready_event.set()
        while not stop_event.is_set():
            try:
                publish(load, facts.get(timeout=0.1).message())
            except queue.Empty:
                continue
        for subscriber in subscribers:
            subscriber.undeclare()
    if follower is not None:
        counts.sets = follower.finish()


def estimator_settings(plan: LivePlan) -> EstimatorSettings:
    """The estimator of a live session: the session's pack, methods, solver and load, its subject, the EMG path on when
    the profile maps electrodes. The joints are on the host clock already: the kinematics node maps each tracker's
    clock. With a Trigno, the EMG clock is measured against the trackers' from the accelerations, the trackers mapped
    as the kinematics node maps them, and each joint frame waits (bounded) for the EMG of its instant."""
    from msk_core.estimate.live_emg import ClockMode, JointsClock  # noqa: PLC0415
    from msk_core.signal.host_clock import latency_ns_from_ms  # noqa: PLC0415
    from services.nodes.estimator import ALIGN_ACCELERATION, EmgTiming, EstimatorSettings  # noqa: PLC0415

    s, trigno = plan.session, plan.trigno is not None
    timing = EmgTiming(
        joints_clock=JointsClock.HOST,
        emg_latency_ns={s.trigno_id: latency_ns_from_ms(plan.trigno_latency_ms, "trigno latency")},
        emg_align=ALIGN_ACCELERATION,
        imu_latency_ns=kinematics_settings(plan).latency_ns if trigno else {},
        emg_wait_s=EMG_WAIT_MS / 1e3 if trigno else 0.0,
    )
    return EstimatorSettings(
        s.pack,
        s.name,
        plan.methods,
        plan.subject,
        emg=None,
        emg_clock=ClockMode.HOST,
        timing=timing,
        initial_load_kg=s.load_kg,
        solver=s.solver,
        live_synergists=s.live_synergists,
    )


def kinematics_settings(plan: LivePlan) -> KinematicsSettings:
    """The kinematics node of a live session: the session's pack, each tracker's own clock mapped onto the host clock
    less its stated latency."""
    from msk_core.signal.host_clock import latency_ns_from_ms  # noqa: PLC0415
    from services.nodes.kinematics_node import KinematicsSettings  # noqa: PLC0415

    latency_ns = {t: latency_ns_from_ms(ms, "tracker latency") for t, ms in plan.tracker_latency_ms.items()}
    return KinematicsSettings(plan.session.pack, plan.session.name, clock="host", latency_ns=latency_ns)


def node_argv(plan: LivePlan, name: str, mcap: Path) -> list[str]:
    """The command line of node ``name`` of the declared graph (services.transport.session_graph.NODES)."""
    if name == "recorder":  # this session's keys only: another session on the endpoint is not this athlete's
        return python_module(
            "services.nodes.recorder", "--out", str(mcap), "--key", f"{topics.session_prefix(plan.session.name)}/**"
        )
    if name == "estimator":
        return python_module("services.nodes.estimator", *estimator_settings(plan).argv())
    if name == "kinematics":
        return python_module("services.nodes.kinematics_node", *kinematics_settings(plan).argv())
    if name in ("drivers-trigno", "drivers-xsens"):
        return driver_argv(plan, name.split("-", 1)[1])
    raise ConfigError("not a process node of msk live's graph", field="node", value=name)


@dataclass
class _Running:
    """What a running ``msk live`` graph holds, for its stop in order (each part set as it starts)."""

    facts: queue.Queue = field(default_factory=queue.Queue)  # SessionFacts for the monitor node to publish
    graph: Graph | None = None
    drivers: list[str] = field(default_factory=list)
    viewer: subprocess.Popen | None = None
    router: SecuredRouter | None = None
    announced: list[Path] = field(default_factory=list)
    recording: Path | None = None  # the file this run's recorder writes (session-001.mcap... after earlier runs)


#: What an earlier run in the same folder leaves besides its recording, kept with its logs (the new run writes its own;
#: subject_session.json is written again from the same profile, by this run's plan, before this is called).
EARLIER_RUN_FILES = ("summary.json",)


def keep_earlier_run(out: Path) -> Path | None:
    """An earlier run's ``OUT/logs`` and ``summary.json`` (a session stopped or killed, then
    started again in the same folder) moved together to the first free ``OUT/logs-NNN``, as the recorder continues
    into ``session-NNN.mcap``; the new run then writes its own. Its summary names its recordings. The summary was
    overwritten before (found by a new user running ``msk live --sim`` twice). Returns where they went (None: nothing
    to keep)."""
    logs = out / "logs"
    has_logs = logs.is_dir() and any(logs.iterdir())
    files = [out / name for name in EARLIER_RUN_FILES if (out / name).is_file()]
    if not has_logs and not files:
        return None
    index = 1
    while (kept := out / f"logs-{index:03d}").exists():
        index += 1
    if has_logs:
        logs.rename(kept)
    else:
        kept.mkdir()
    for path in files:
        path.rename(kept / path.name)
    return kept


def run_graph(
    plan: LivePlan,
    *,
    duration_s: float | None,
    view: bool,
    endpoint: str,
    log,
    simulators: Simulators | None = None,
    pki: Path | None = None,
) -> dict:
    """Start the declared graph (services.transport.session_graph.live_nodes), announce it (OUT/session.json, the registry of
    services.sessions.discovery), publish the session facts, run until the duration, a signal or a failed node, then stop in
    order. ``pki``: the secured mode (a TLS router with access control, each node with its role's certificate)."""
    from services.sessions import discovery

    out = plan.session.out
    if (kept := keep_earlier_run(out)) is not None:
        log(f"{out} held an earlier run: its logs and summary are now in {kept} (its recordings stay in {out})")
    (out / "logs").mkdir(parents=True, exist_ok=True)
    recorded_before = set(out.glob("session*.mcap"))
    counts = FlowCounts()
    running = _Running(recording=next_part_path(out / "session.mcap"))
    announcement = discovery.Announcement()
    failed_at_start = False
    with StopOnSignals() as stopper:
        try:
            graph, endpoint = _start_live_graph(plan, endpoint, pki, counts, announcement, running, log)
            try:
                _wait_ready(graph, stopper)
            except GraphTimeout:  # a node never ready: nothing flowed (the drivers start last), stop at once
                failed_at_start = True
                raise
            failed_at_start = bool(graph.failed())  # e.g. the recorder could not listen: no "running" line
            if not failed_at_start:
                _announce_live_graph(plan, graph, endpoint, view, duration_s, pki, stopper, announcement, running, log)
            reason, elapsed = _run_until_stopped(graph, duration_s, stopper, out / "logs", log, running.router)
        finally:
            for path in running.announced[1:]:  # the registry entry; OUT/session.json stays as a record
                discovery.withdraw(path)
            codes = {}
            if running.graph is not None:
                if failed_at_start:  # nothing flowed yet: nothing to drain in order, no node worth waiting for
                    codes = stop_at_once(running.graph, simulators)
                else:
                    codes = stop_in_order(
                        running.graph, running.drivers, simulators, running.viewer, counts, plan.methods, log
                    )
            if running.router is not None:
                codes["router"] = running.router.stop()
    # the parts this session's recorder wrote (it continues into session-001.mcap ... when OUT holds older ones)
    parts = sorted(set(out.glob("session*.mcap")) - recorded_before)
    summary = summarise(parts, elapsed)
    summary["recordings"] = [str(p) for p in parts]
    summary["stopped_by"] = reason
    summary["exit_codes"] = codes
    if running.router is not None:  # the secured router's restarts while the session ran
        summary["router_restarts"] = running.router.restarts
    summary["joint_frames_paused"] = counts.paused_joints  # while load events declared another exercise
    summary["sets"] = counts.sets  # as msk live counted them (the view's and the report's rule)
    if plan.subject is None:  # the live rep phase follows the profile's rep template
        summary["reps_not_counted"] = (
            "no subject profile: no rep template to follow the reps live (msk report counts them afterwards "
            "from the joint angles)"
        )
    # electrodes of the map the estimator never judged: no source streamed their channel (a sensor not paired, a typo)
    # (without a subject profile the estimator reads no EMG and judges none: nothing to say about them)
    judged = {name.split("/", 1)[-1] for name in summary.get("electrodes", {})}
    summary["electrodes_never_streamed"] = (
        {ch: e for ch, e in plan.electrodes.items() if ch not in judged} if plan.subject is not None else {}
    )
    if simulators is not None:
        summary["simulators_sent"] = simulators.sent()
        summary["trial_clock"] = simulators.world()
    return summary


def _start_live_graph(
    plan: LivePlan,
    endpoint: str,
    pki: Path | None,
    counts: FlowCounts,
    announcement: discovery.Announcement,
    running: _Running,
    log,
) -> tuple[Graph, str]:
    """The graph (secured: behind its router, started first) with its nodes started: the monitor a thread of this
    process, the others processes logging to OUT/logs; their process ids in OUT/logs/pids.json. Returns the graph
    and its endpoint."""
    s = plan.session
    logs = s.out / "logs"
    if pki is not None:
        running.router, endpoint, role_configs = start_secured_router(pki, s.out, log)
        graph = Graph(s.name, endpoint, external_listener=True, role_configs=role_configs)
    else:
        graph = Graph(s.name, endpoint)
    running.graph = graph
    nodes = session_graph.live_nodes(
        trigno=plan.trigno is not None, xsens=bool(plan.xsens_ports) or plan.session.xsens_mvn is not None
    )
    running.drivers = [n.name for n in nodes if n.role == "driver"]

    def start(decl: session_graph.NodeDecl, after: tuple[str, ...]) -> None:
        if decl.name == "monitor":
            graph.add_thread(
                "monitor",
                monitor,
                session=s.name,
                counts=counts,
                facts=running.facts,
                after=after,
                role=decl.role,
                on_facts=announcement.update_facts,
                exercise=plan.exercise,
            )
        else:
            graph.add_process(
                decl.name,
                node_argv(plan, decl.name, s.out / "session.mcap"),
                after=after,
                role=decl.role,
                log_path=logs / f"{decl.name}.log",
                own_session=True,
            )

    session_graph.start_declared(nodes, start)
    # process ids, to stop the nodes by hand should msk live itself be killed (they have their own groups)
    pids = {n: node_process.pid for n in graph.nodes if (node_process := graph.process(n)) is not None}
    router = {"router": running.router.pid} if running.router is not None else {}
    pids_path(s.out).write_text(json.dumps({**pids, **router}) + "\n")
    return graph, endpoint


def _announce_live_graph(
    plan: LivePlan,
    graph: Graph,
    endpoint: str,
    view: bool,
    duration_s: float | None,
    pki: Path | None,
    stopper: StopOnSignals,
    announcement: discovery.Announcement,
    running: _Running,
    log,
) -> None:
    """The ready graph's session facts published, the session announced (services.sessions.discovery), the viewer started
    (``view``, unless stopping already) and the operator told how to attach."""
    from services.sessions import discovery

    s = plan.session
    running.facts.put(
        SessionFacts(
            exercise=plan.exercise,
            load_kg=s.load_kg,
            athlete=getattr(s, "athlete", ""),
            names=plan.names,
            rest_s=s.rest_s,
        )
    )
    observer = graph.observer_options()
    info = discovery.SessionInfo(
        session=s.name,
        connect=[endpoint],
        pid=os.getpid(),
        out=str(s.out.resolve()),
        pack=plan.exercise,
        zenoh_config=str(observer.config_file.resolve()) if observer.config_file is not None else "",
        pki=str(Path(pki).resolve()) if pki is not None else "",
    )
    info = dataclasses.replace(info, attach=discovery.attach_commands(info))
    running.announced = announcement.announce(info, s.out)
    if view and not sys.stdout.isatty():  # piped (| tee, a log file): the view would draw into the pipe, unseen
        log(f"no view: the output is not a terminal; watch from one with msk view --session {s.name}")
        view = False
    if view and not stopper.event.is_set():
        running.viewer = subprocess.Popen(
            python_module("services.cli", "view", "--session", s.name, *zenoh_flags(observer)),
            start_new_session=True,
            env={**os.environ, **stop_with_parent_env()},
        )  # Ctrl-C reaches msk live only: it stops in order
    log(
        f"live session {s.name!r} running on {endpoint}"
        + (" (TLS, access control)" if pki is not None else "")
        + f"; attach: {'; '.join(info.attach)}"
    )
    log(
        f"running: {', '.join(graph.nodes)}"
        + (" + view" if running.viewer else "")
        + f"; recording to {running.recording or s.out / 'session.mcap'}"
        + (f"; stops after {duration_s:g} s" if duration_s else "; Ctrl-C stops")
    )


def _run_until_stopped(
    graph: Graph, duration_s: float | None, stopper: StopOnSignals, logs: Path, log, router: SecuredRouter | None
) -> tuple[str, float]:
    """Run until the duration, a signal or a failed node (the secured ``router`` kept up meanwhile); returns why it
    stopped and how long it ran (s)."""
    started = time.monotonic()
    deadline = None if duration_s is None else started + duration_s
    reason = "duration"
    while not stopper.event.wait(0.1):
        if deadline is not None and time.monotonic() >= deadline:
            break
        if router is not None and (gone := router.keep_up(time.monotonic() - started, log)) is not None:
            reason = gone
            log(f"stopping: {reason}")
            break
        failed = graph.failed()
        if failed:
            reason = f"node failed: {failed}"
            log(f"stopping: {reason} (logs in {logs})")
            break
    if stopper.event.is_set():
        reason = stopper.signal or "signal"
    return reason, time.monotonic() - started


def router_host(pki: Path) -> str:
    """The loopback name the router certificate of ``pki`` is valid for (the nodes verify it on connect)."""
    from cryptography import x509

    from services.transport.security import Pki

    path = Pki(pki).cert("router")
    if not path.is_file():
        raise ConfigError("no router certificate: make the folder with `msk certs --out DIR`", path=path)
    certificate = x509.load_pem_x509_certificate(path.read_bytes())
    try:
        names = certificate.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        hosts = [str(getattr(n, "value", "")) for n in names]
    except x509.ExtensionNotFound:
        hosts = []
    for host in ("127.0.0.1", "localhost"):
        if host in hosts:
            return host
    raise ConfigError(
        f"the router certificate is for {hosts or 'no host'}, not for this machine's loopback "
        "(127.0.0.1 or localhost): make it with `msk certs` (its default hosts)",
        path=path,
    )


#: Restarts of the secured router one session takes (each said and counted); one more stops the session.
MAX_ROUTER_RESTARTS = 3
#: How long a restarted router may take to listen again.
ROUTER_RESTART_TIMEOUT_S = 15.0


@dataclass
class SecuredRouter:
    """The secured mode's ``msk router``, kept up while the session runs: a router that exits (a crash, a kill) is
    started again on the same port at once (the nodes reconnect; the recorder fetches what the devices published
    meanwhile from their history), said and counted (``restarts``: the summary's ``router_restarts``). It ran on
    without a word before, the nodes cut off: 76 % of the EMG never reached the recording, "0 lost"."""

    argv: list[str]
    port: int
    log_path: Path
    env: dict[str, str]
    process: subprocess.Popen | None = None
    restarts: list[dict] = field(default_factory=list)

    @property
    def pid(self) -> int:
        assert self.process is not None
        return self.process.pid

    def start(self, timeout_s: float = 30.0) -> None:
        from services.nodes import router as router_node

        with open(self.log_path, "ab") as log_file:  # a restart appends: the log of the one that exited stays
            self.process = subprocess.Popen(
                self.argv, stdout=log_file, stderr=subprocess.STDOUT, start_new_session=True, env=self.env
            )
        try:
            router_node.wait_until_listening(self.process, self.port, timeout_s=timeout_s)
        except RuntimeError as error:
            raise GraphTimeout(f"{error}; router log: {self.log_path}") from None

    def keep_up(self, elapsed_s: float, log) -> str | None:
        """Called while the session runs: None while the router runs (or came back); else why the session stops."""
        if self.process is None or (code := self.process.poll()) is None:
            return None
        how = exit_text(code)
        if len(self.restarts) >= MAX_ROUTER_RESTARTS:
            return f"router failed: it {how}, after {len(self.restarts)} restarts (log: {self.log_path})"
        log(
            f"router {how} {elapsed_s:.1f} s into the session; starting it again on port {self.port} (log: {self.log_path})"
        )
        started = time.monotonic()
        try:
            self.start(ROUTER_RESTART_TIMEOUT_S)
        except GraphTimeout as error:
            return f"router failed: it {how}, and did not start again: {error}"
        back_s = time.monotonic() - started
        self.restarts.append({"at_s": round(elapsed_s, 3), "exit": how, "back_after_s": round(back_s, 3)})
        log(f"router back after {back_s:.1f} s; the nodes reconnect by themselves")
        return None

    def stop(self) -> int | None:
        return None if self.process is None else stop_process(self.process)


def check_roles(pki: Path, configs: dict[str, Path]) -> None:
    """Each role's files usable (:func:`services.transport.security.check_zenoh_tls`) and its certificate in ``pki``
    that role's (its CN): one swapped for another's (the tablet's copied over
    the estimator's) let the router refuse the node's subscriptions, and the session waited 88 s for it to be ready."""
    from services.transport import security
    from services.transport.zenoh_session import ZenohOptions, check_tls

    for role, config in configs.items():
        # each node checks its files too, but says so only in its log under OUT/logs: here the terminal says it
        check_tls(ZenohOptions(mode=None, config_file=config).to_config(), config)
        if role == security.ROUTER_ROLE:
            continue
        found = security.role_of_config(config)
        if found != role:
            raise ConfigError(
                f"the certificate for role {role!r} is "
                + (f"the {found}'s (CN {security.common_name(found)})" if found else "no role's")
                + f": the router would refuse that node what it needs; make {role}.pem again with `msk certs --out "
                f"{pki} --role {role}`",
                path=security.Pki(pki).cert(role),
                field="role",
                value=found,
            )


def start_secured_router(pki: Path, out: Path, log) -> tuple[SecuredRouter, str, Callable[[str], Path]]:
    """``msk router`` on a free loopback TLS port with the access control of the declared graph, and one Zenoh client
    config per role (OUT/zenoh/<role>.json5) connecting to it; returns (router, endpoint, role -> config path)."""
    from services.transport import security
    from services.transport.zenoh_session import free_loopback_endpoint

    pki = Path(pki).resolve()
    host = router_host(pki)
    port = int(free_loopback_endpoint().rsplit(":", 1)[1])
    endpoint = f"tls/{host}:{port}"
    configs = security.write_configs(
        out / "zenoh", pki, router_listen=(f"tls/127.0.0.1:{port}",), client_connect=(endpoint,)
    )
    check_roles(pki, configs)
    router = SecuredRouter(
        python_module("services.cli", "router", f"--zenoh-config={configs['router']}"),
        port,
        out / "logs" / "router.log",
        {**os.environ, **stop_with_parent_env(), "RUST_LOG": os.environ.get("RUST_LOG", "warn")},
    )
    router.start()
    log(f"secured: router on {endpoint} (TLS, client certificates of {pki}, access control of the session graph)")
    return router, endpoint, lambda role: configs[role]


def stop_process(process: subprocess.Popen, timeout_s: float = STOP_TIMEOUT_S) -> int | None:
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
    try:
        return process.wait(timeout_s)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait(5)
        return None


def _wait_ready(graph: Graph, stopper: StopOnSignals) -> None:
    done = threading.Event()
    error: list[BaseException] = []

    def wait() -> None:
        try:
            graph.wait_ready(READY_TIMEOUT_S)
        except BaseException as e:  # reported in the main thread
            error.append(e)
        done.set()

    threading.Thread(target=wait, daemon=True).start()
    while not done.wait(0.1):
        if stopper.event.is_set():
            return
    if error and not (isinstance(error[0], GraphTimeout) and graph.failed()):
        raise error[0]
    # a node that exited before it was ready is a failed node: _run_until_stopped says which, and msk live exits 3


def _settle(what: str, done, counts: FlowCounts, timeout_s: float, log) -> None:
    """Bounded wait for the downstream nodes to catch up; on expiry say so with the counts, and go on stopping."""
    try:
        wait_for(what, done, counts.text, timeout_s)
    except GraphTimeout as error:
        log(f"warning: {error}")


def _unchanged_for(value: Callable[[], int], seconds: float) -> Callable[[], bool]:
    """A check, polled by :func:`_settle`, that is true once ``value()`` has not changed for ``seconds``."""
    last = [value(), time.monotonic()]

    def unchanged() -> bool:
        now = value()
        if now != last[0]:
            last[:] = [now, time.monotonic()]
        return time.monotonic() - last[1] >= seconds

    return unchanged


def stop_at_once(graph: Graph, simulators: Simulators | None) -> dict:
    """After a node failed at the start, before any data flowed (and before the view was started): every node asked
    to stop at the same moment, those still running after :data:`FAILED_STOP_S` killed (a node waiting on an endpoint
    nobody serves does not answer SIGINT)."""
    codes = graph.stop(FAILED_STOP_S)
    if simulators is not None:
        simulators.close()
    return codes


def stop_in_order(
    graph: Graph, drivers: list[str], simulators: Simulators | None, viewer, counts: FlowCounts, methods, log
) -> dict:
    """Sources first, the recorder last, so what the devices sent flows through and is recorded."""
    if simulators is not None:
        simulators.hold()
        time.sleep(DRAIN_S)
    # Xsens before Trigno: the last joint frames still find EMG (no ``emg_stalled`` flags at the end of a session)
    order = sorted(drivers, key=lambda d: d != "drivers-xsens") + ["kinematics", "estimator", "recorder"]
    codes: dict[str, int | None] = {}  # None: killed after the stop timeout
    for name in order:
        process = graph.process(name)
        if process is None:
            continue
        if name == "kinematics":  # joints stop changing: the drivers' last samples went through
            quiet = _unchanged_for(lambda: counts.joints, DRAIN_S)
            _settle("the kinematics node to publish its last joint frames", quiet, counts, STOP_TIMEOUT_S, log)
        elif name == "estimator":  # every joint frame answered by every method, or none answered for a while
            idle = _unchanged_for(lambda: sum(counts.activations.values()), ESTIMATOR_IDLE_S)

            def done(idle: Callable[[], bool] = idle) -> bool:  # a paused estimator answers no more
                still = idle()  # called every time, so it sees every change
                return (counts.paused_joints > 0 and still) or all(
                    counts.activations[m] >= counts.joints for m in methods
                )

            _settle(
                f"the estimator to answer all joint frames ({', '.join(methods)})", done, counts, STOP_TIMEOUT_S, log
            )
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
        try:
            codes[name] = process.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(5)
            codes[name] = None
        if name != "recorder":
            time.sleep(DRAIN_S / 2)  # its last messages reach the nodes after it
    if viewer is not None:
        viewer.send_signal(signal.SIGINT)
        try:
            viewer.wait(5)
        except subprocess.TimeoutExpired:
            viewer.kill()
    graph.stop(5.0)  # anything left (none normally)
    if simulators is not None:
        simulators.close()
    return codes


def checked_subject(path: Path, pack, session_path: Path | None):
    """The subject profile at ``path``, read and checked against ``pack`` before anything starts (the estimator
    would otherwise refuse it once the whole graph runs, and name the session copy it reads, not this file)."""
    from msk_core.errors import EstimationError
    from msk_core.estimate.profile import SubjectProfile

    profile = SubjectProfile.load(path)  # a missing, unreadable or malformed file: named with its field
    try:
        profile.check_pack(pack)
    except EstimationError as error:
        raise session_error(session_path, "session.subject", str(error), str(path)) from None
    return profile


def plan_for(
    session: LiveSession, *, sim: bool, log, sim_faults: tuple = (), sim_sets: SimSets | None = None
) -> tuple[LivePlan, Simulators | None]:
    """The graph's plan and, with ``sim``, the started simulators (the Trigno injecting ``sim_faults``), playing
    ``sim_sets`` (default :class:`services.sessions.sim_sets.SimSets`: sets of 9 reps with 30 s rests). The plan's
    session is ``session`` with what ``--sim`` decides (the bundled trial's load unless the file states one, the
    simulators' IMU rate)."""
    from msk_core.imu.mapping import mapping_for
    from msk_core.model import load_pack

    if sim_faults and not sim:
        raise ConfigError(
            "electrode faults are injected by the simulated Trigno: add --sim",
            field="--sim-fault",
            value=[f"{f.sensor}:{f.kind.value}:{f.start_s:g}-{f.end_s:g}" for f in sim_faults],
        )
    session.out.mkdir(parents=True, exist_ok=True)
    model = load_pack(session.pack)
    segments = list(mapping_for(model.name).segments)
    sources = None
    if sim:
        sources, session, (subject, electrodes, trackers, methods) = _sim_inputs(
            session, model.name, segments, sim_sets, log
        )
    else:
        subject, electrodes, trackers, methods = _device_inputs(session)
    check_against_pack(
        LiveSession(session.path, trackers=trackers, electrodes=electrodes),
        list(model.groups),
        segments,
        {} if subject is None else checked_subject(Path(subject), model, session.path).emg_normalisation,
    )
    if subject is None:
        log(
            "no subject profile (session.subject): estimating with "
            + ", ".join(methods)
            + " only; the EMG is recorded, not used (no MVC to normalise it by). Calibrate one with `msk calibrate` "
            "for proposed and assisted (docs/estimation.md)"
        )
    if "assisted" in methods and not electrodes:
        raise session_error(
            session.path,
            "session.methods",
            "method 'assisted' needs EMG: a [trigno] device and an [electrodes] map",
            "assisted",
        )
    profile_path = (
        None if subject is None else session_profile(Path(subject), electrodes, list(model.groups), session.out)
    )
    trigno_latency_ms, tracker_latency_ms = stated_latencies(session, trackers, simulated=sim)
    names = session_names(session, model.display_names)
    simulators = None
    if sources is not None:
        simulators = _start_planned_simulators(
            sources, electrodes, trackers, trigno_latency_ms, tracker_latency_ms, sim_faults, log
        )
        ports = _simulator_ports(simulators, trackers)
    else:
        ports = _device_ports(session)
    plan = LivePlan(
        session,
        tuple(methods),
        profile_path,
        trigno=ports.trigno,
        trigno_aux_port=ports.trigno_aux_port,
        trigno_aux_layout=session.trigno_aux_layout if sources is None else None,  # a simulator's ports say theirs
        xsens_ports=ports.xsens,
        trackers=trackers,
        exercise=model.name,
        trigno_latency_ms=trigno_latency_ms,
        tracker_latency_ms=tracker_latency_ms,
        names=names,
        electrodes=dict(electrodes),
    )
    return plan, simulators


# (subject profile or None, electrode map, tracker -> segment map, methods) of a session
_SessionInputs = tuple[Path | None, dict[str, str], dict[str, str], tuple[str, ...]]


def _sim_inputs(
    session: LiveSession, pack: str, segments: list[str], sim_sets: SimSets | None, log
) -> tuple[SimSources, LiveSession, _SessionInputs]:
    """Under --sim: the bundled trial's sources, the session with what they decide (their IMU rate; their load
    unless the file states one), and what the session file leaves out taken from the bundled session (its subject,
    calibrated and cached; its electrodes and trackers of the pack's segments)."""
    from services.sessions.sim_sets import SimSets, with_sets

    sources = with_sets(sim_sources(RECORDINGS / "demo_session.mcap", pack), sim_sets or SimSets())
    subject = session.subject or sim_subject(pack, log)
    session = dataclasses.replace(
        session,
        load_kg=session.load_kg if "session.load_kg" in session.given else sources.load_kg,
        imu_rate_hz=int(round(next(iter(sources.imu.values()))[1].rate_hz)),
    )
    electrodes = session.electrodes or sources.electrodes
    wrong = {ch: g for ch, g in session.electrodes.items() if sources.electrodes.get(ch) != g}
    if wrong:  # allowed (a rehearsal of the real placement), but the envelopes are then another muscle's
        log(
            "--sim: the simulated Trigno plays "
            + ", ".join(
                f"{sources.electrodes.get(ch) or 'nothing'} on {ch} (the file maps {g})" for ch, g in wrong.items()
            )
            + f"; its sensors: {', '.join(f'{ch} {g}' for ch, g in sources.electrodes.items())}"
        )
    trackers = _sim_trackers(session, sources, segments, log)
    methods = session.methods or SIM_METHODS
    return sources, session, (Path(subject), electrodes, trackers, tuple(methods))


def _sim_trackers(session: LiveSession, sources: SimSources, segments: list[str], log) -> dict[str, str]:
    """The simulated trackers (by id) of the segments the session file's trackers are on (its own ids, printed on
    the real trackers, are played by the simulated tracker of the same segment), else of the pack's segments."""
    simulated = {seg: t for t, (seg, _) in sources.imu.items()}
    if not session.trackers:
        return {t: seg for seg, t in simulated.items() if seg in segments}
    missing = sorted(set(session.trackers.values()) - set(simulated))
    if missing:
        raise session_error(
            session.path, "trackers", f"--sim plays trackers on {', '.join(sorted(simulated))} only", missing
        )
    trackers = {simulated[seg]: seg for seg in session.trackers.values()}
    if set(trackers) != set(session.trackers):
        log(
            "--sim: "
            + ", ".join(
                f"{t} ({seg}) is played by the simulated {simulated[seg]}"
                for t, seg in session.trackers.items()
                if simulated[seg] != t
            )
        )
    return trackers


def _device_inputs(session: LiveSession) -> _SessionInputs:
    """With devices: the session file's subject and maps; methods by default proposed (+ assisted with a Trigno).
    Without a subject profile (an athlete not calibrated yet) the session runs static optimisation alone: the
    estimates need no EMG, the EMG is recorded but not used (no MVC to normalise it by)."""
    from services.nodes.estimator import METHODS_NEEDING_PROFILE  # noqa: PLC0415

    if session.subject is None:
        needing = [m for m in session.methods if m in METHODS_NEEDING_PROFILE]
        if needing:
            raise session_error(
                session.path,
                "session.methods",
                f"{', '.join(needing)} need session.subject, a subject profile (`msk calibrate`); without one the "
                "session runs 'so' (static optimisation)",
                needing,
            )
        return None, session.electrodes, session.trackers, tuple(session.methods or ("so",))
    methods = session.methods or (("proposed", "assisted") if session.trigno_host else ("proposed",))
    return session.subject, session.electrodes, session.trackers, tuple(methods)


def _start_planned_simulators(
    sources: SimSources,
    electrodes: dict[str, str],
    trackers: dict[str, str],
    trigno_latency_ms: float,
    tracker_latency_ms: dict[str, float],
    sim_faults: tuple,
    log,
) -> Simulators:
    """Start the simulators with the latencies the session states (0 unless it says); the trackers of segments the
    pack does not use are closed."""
    simulators = start_simulators(
        sources,
        trigno_latency_s=trigno_latency_ms / 1e3,
        xsens_latency_s={t: ms / 1e3 for t, ms in tracker_latency_ms.items()},
        trigno_faults=sim_faults,
    )
    log(
        f"simulators: Trigno on 127.0.0.1:{simulators.trigno.ports['command']} ({sources.emg.rate_hz:g} Hz, "
        f"{sum(sources.emg.paired)} sensors), Xsens "
        + ", ".join(f"{t} ({seg}) on {simulators.xsens[t].path}" for t, seg in trackers.items())
        + f"; streaming the bundled {sources.trial} trial"
        + (
            f" as sets of {sources.sets.reps} rep{'s' if sources.sets.reps != 1 else ''} with "
            f"{sources.sets.rest_s:g} s rests"
            if sources.sets is not None
            else " in a loop"
        )
    )
    for fault in sim_faults:
        label = f"sensor{fault.sensor:02d}.EMG"
        log(
            f"injecting {fault.kind.value} on {label} ({electrodes.get(label, 'not in the electrode map')}) "
            f"from {fault.start_s:g} to {fault.end_s:g} s after the Trigno starts streaming"
        )
    for tracker in set(sources.imu) - set(trackers):
        simulators.xsens.pop(tracker).close()  # trackers of segments the pack does not use
    return simulators


@dataclass(frozen=True)
class _DevicePorts:
    """Where the drivers find the devices: the Trigno's (HOST[:PORT], EMG port) and AUX port, the Xsens serial
    ports."""

    trigno: tuple[str, int] | None
    trigno_aux_port: int | None
    xsens: tuple[str, ...]


def _simulator_ports(simulators: Simulators, trackers: dict[str, str]) -> _DevicePorts:
    """The started simulators' addresses and ports, one pty per tracker of ``trackers``."""
    ports = simulators.trigno.ports
    return _DevicePorts(
        (f"127.0.0.1:{ports['command']}", ports["emg"]),
        ports["aux"],
        tuple(simulators.xsens[t].path for t in trackers),
    )


def _device_ports(session: LiveSession) -> _DevicePorts:
    """The Trigno address and ports and the Xsens serial ports from the session file."""
    trigno = aux_port = None
    if session.trigno_host is not None:
        from drivers.trigno import protocol as tp

        trigno = (session.trigno_host, session.trigno_emg_port or int(tp.EmgPort.AVANTI))
        if session.trigno_aux_port is not None:  # as the file says (0: no accelerometers)
            aux_port = session.trigno_aux_port or None
        elif trigno[1] in (tp.EmgPort.AVANTI, tp.EmgPort.LEGACY):
            # the TCU's: the AUX port beside the Avanti EMG port, the legacy ACC port beside the legacy one
            aux_port = int(tp.DataPort.LEGACY_ACC if trigno[1] == tp.EmgPort.LEGACY else tp.DataPort.AUX)
        else:
            raise ConfigError(
                f"the EMG port {trigno[1]} is not the TCU's, so the accelerometers' port cannot be guessed: give "
                "trigno.aux_port (0: none; the EMG clock is then aligned by arrival)",
                path=session.path,
                field="trigno.aux_port",
            )
    return _DevicePorts(trigno, aux_port, session.xsens_ports)


def default_live_endpoint(stack: contextlib.ExitStack) -> str:
    """The well-known loopback endpoint when no other session holds it (a client with no flags, or the ten-line
    subscriber of docs/apps.md, then finds this session there), else a free loopback port (found through
    services.sessions.discovery). The well-known one is claimed for as long as ``stack`` lives
    (:func:`services.sessions.discovery.claim_endpoint`), so a session started at the same moment takes another."""
    from services.sessions import discovery
    from services.transport.zenoh_session import DEFAULT_ENDPOINT, endpoint_is_free, free_loopback_endpoint

    claim = discovery.claim_endpoint(DEFAULT_ENDPOINT)
    if claim is not None:
        stack.enter_context(claim)
        if endpoint_is_free(DEFAULT_ENDPOINT):
            return DEFAULT_ENDPOINT
    return free_loopback_endpoint()


def check_not_running(name: str, out: Path) -> None:
    """Refuse a session whose name or output folder a running ``msk live`` announces: the attach commands could not
    tell two sessions of one name apart, and a second recorder would truncate the first one's recording."""
    from services.sessions import discovery

    for info in discovery.running_sessions():
        if Path(info.out).resolve() == Path(out).resolve():
            raise ConfigError(
                f"session {info.session!r} (pid {info.pid}) is recording there now; choose another --out",
                path=Path(out),
            )
        if info.session == name:
            raise ConfigError(
                f"a session of this name runs now (pid {info.pid}, recording to {info.out}); stop it or give this one "
                "another name (the session file's name)",
                field="session",
                value=name,
            )


def main(
    session: LiveSession,
    *,
    sim: bool,
    duration_s: float | None,
    view: bool,
    log=print,
    listen: str | None = None,
    pki: Path | None = None,
    sim_faults: tuple = (),
    sim_sets: SimSets | None = None,
) -> dict:
    """``listen``: the loopback endpoint of the graph (default :func:`default_live_endpoint`); ``pki``: a folder
    written by ``msk certs``, for the secured mode; ``sim_faults``: electrode faults the simulated Trigno injects
    (:class:`drivers.trigno.simulator.SensorFault`, with ``sim``); ``sim_sets``: the sets the simulators play."""
    if pki is not None and listen is not None:
        raise ConfigError(
            "the secured mode picks its own TLS endpoint; give --pki or --listen, not both",
            field="--listen",
            value=listen,
        )
    from services.sessions import discovery

    with discovery.claimed(session.name, session.out), contextlib.ExitStack() as endpoint_claim:
        check_not_running(session.name, session.out)
        if pki is not None:  # before the calibration and the simulators: a folder without a router certificate
            router_host(pki)
        plan, simulators = plan_for(session, sim=sim, log=log, sim_faults=tuple(sim_faults), sim_sets=sim_sets)
        try:
            summary = run_graph(
                plan,
                duration_s=duration_s,
                view=view,
                endpoint=listen or default_live_endpoint(endpoint_claim),
                log=log,
                simulators=simulators,
                pki=pki,
            )
        except BaseException:
            if simulators is not None:
                simulators.close()
            raise
        summary["methods"] = list(plan.methods)
        (session.out / "summary.json").write_text(json_text(summary))  # the folder still held: no one else's run
    log(summary_text(summary))
    log(f"recording: {', '.join(summary.get('recordings', [])) or 'none'}; summary: {session.out / 'summary.json'}")
    return summary
