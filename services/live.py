"""``msk live``: one command runs a whole session graph on the real devices (or, with ``--sim``, on the simulators).

Processes, each a Zenoh peer on one private loopback endpoint (services.graph): the recorder (``msk/<session>/**``
-> ``OUT/session.mcap``), the estimator (methods of the session file, EMG path on), the kinematics node (IMU ->
joints, each tracker's clock mapped to the host clock), one driver node per device kind (``msk drivers``: Trigno,
Xsens) and the live view (``msk view``). The drivers start acquiring only once the recorder, kinematics and estimator
have declared their subscribers, so nothing a device sends is lost at start.

Stop (``--duration``, Ctrl-C or SIGTERM) runs downstream: (simulators stop sending;) drivers end acquisition and
exit, then kinematics, estimator and last the recorder, which closes the MCAP. The summary (duration, samples per
device, samples lost, frames estimated, flags) is read back from the MCAP, printed and written to
``OUT/summary.json``. With ``--sim`` it also holds what each simulator sent, to compare with what was recorded.

``--sim``: a Trigno simulator (TCP) and one Xsens simulator per tracker (pty, own SampleTimeFine clock) stream the
held-out trial of the bundled synthetic session (``recordings/demo_session.mcap``) of the pack; the subject is
calibrated on the bundled calibration trials as ``msk demo`` does (cached). Docs: docs/live.md.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from msk_core.errors import ConfigError, InputError
from services import topics
from services.graph import Graph, GraphTimeout, python_module, wait_for
from services.live_session import SIM_METHODS, LiveSession, check_against_pack
from services.mcap_io import read_messages

REPO_ROOT = Path(__file__).resolve().parents[1]
RECORDINGS = REPO_ROOT / "recordings"
READY_TIMEOUT_S = 90.0
STOP_TIMEOUT_S = 20.0
DRAIN_S = 0.6  # after the simulators stop sending: bytes in flight reach the drivers, messages the nodes


# ------------------------------------------------------------------------------------------------ simulator sources


@dataclass
class SimSources:
    """What the simulators stream: the bundled session's held-out trial of one pack."""

    emg: object  # drivers.trigno.source.EmgSource
    imu: dict[str, tuple[str, object]]  # tracker id -> (segment, ImuSource)
    electrodes: dict[str, str]  # Trigno channel label (sensorNN.EMG) -> electrode name of the profile
    load_kg: float
    trial: str


def sim_sources(recording: Path, pack: str) -> SimSources:
    """Arrays of the last (held-out) trial of ``pack`` in the bundled recording: EMG chunks -> one (n, 16) Trigno
    source, IMU samples -> one Xsens source per tracker (quaternion, acceleration, rate of turn, magnetic field)."""
    from drivers.trigno.protocol import N_SENSORS
    from drivers.trigno.source import EmgSource
    from drivers.xsens.source import ImuSource

    if not recording.is_file():
        raise InputError("bundled session not found (generate it with `msk synth`, recordings/README.md)", path=recording)
    windows, start = [], None
    for m in read_messages(recording):
        if m.type_name == "msk.LoadEvent":
            e = m.decode()
            if e.exercise != pack:
                continue
            if e.barbell_mass_kg > 0:
                start = (e.device_time_ns, e.barbell_mass_kg)
            elif start is not None:
                windows.append((start[0], e.device_time_ns, start[1]))
                start = None
    if not windows:
        raise InputError(f"the bundled session has no trial of pack {pack!r}", path=recording, field="session.pack", value=pack)
    t0, t1, load = windows[-1]
    emg_rows, labels, rate, imu = [], None, None, {}
    for m in read_messages(recording):
        if m.type_name == "msk.EmgChunk":
            c = m.decode()
            if t0 <= c.device_time_ns < t1:
                emg_rows.append(np.asarray(c.samples, dtype=np.float32).reshape(c.n_samples, c.n_channels))
                labels, rate = list(c.channel_labels), c.sample_rate_hz
        elif m.type_name == "msk.ImuSample":
            s = m.decode()
            if t0 <= s.device_time_ns < t1:
                o, a, g, b = s.orientation, s.acceleration, s.rate_of_turn, s.magnetic_field
                imu.setdefault(s.tracker_id, (s.segment, []))[1].append(
                    (s.device_time_ns, [o.w, o.x, o.y, o.z], [a.x, a.y, a.z], [g.x, g.y, g.z], [b.x, b.y, b.z]))
    if not emg_rows or not imu:
        raise InputError(f"no EMG or IMU samples in the {pack} trial of the bundled session", path=recording)
    emg = np.concatenate(emg_rows)
    if emg.shape[1] > N_SENSORS:
        raise InputError(f"{emg.shape[1]} EMG channels exceed the Trigno's {N_SENSORS} sensors", path=recording)
    samples = np.zeros((emg.shape[0], N_SENSORS), dtype=np.float32)
    samples[:, : emg.shape[1]] = emg
    names = tuple(labels) + ("",) * (N_SENSORS - len(labels))
    source = EmgSource(samples, float(rate), names, tuple(k < len(labels) for k in range(N_SENSORS)), f"{recording.name}:{pack}")
    trackers = {}
    for tracker, (segment, rows) in imu.items():
        rows.sort(key=lambda r: r[0])
        times = np.array([r[0] for r in rows], dtype=float) / 1e9
        imu_rate = float(round(1.0 / np.median(np.diff(times))))
        arrays = {name: np.array([r[k] for r in rows], dtype=float)
                  for k, name in enumerate(("quaternion", "acceleration", "rate_of_turn", "magnetic_field"), start=1)}
        trackers[tracker] = (segment, ImuSource(imu_rate, arrays, f"{recording.name}:{segment}"))
    electrodes = {f"sensor{k + 1:02d}.EMG": label for k, label in enumerate(labels)}
    return SimSources(source, trackers, electrodes, float(load), f"{pack}_{load:g}kg")


@dataclass
class Simulators:
    trigno: object
    xsens: dict[str, object]  # tracker id -> XsensSimulator

    def hold(self) -> None:
        self.trigno.hold()
        for sim in self.xsens.values():
            sim.hold()

    def close(self) -> None:
        self.trigno.close()
        for sim in self.xsens.values():
            sim.close()

    def sent(self) -> dict:
        return {"trigno": {"samples": self.trigno.stats.samples_sent, "frames": self.trigno.stats.frames_sent},
                **{t: {"samples": s.stats.messages_sent, "bytes_dropped": s.stats.bytes_dropped} for t, s in self.xsens.items()}}


def start_simulators(sources: SimSources) -> Simulators:
    from drivers.trigno.simulator import SimulatorConfig, TrignoSimulator
    from drivers.xsens.simulator import XsensSimulator

    # free ports: several sessions (tests, users) may run side by side; no legacy/aux listeners needed
    trigno = TrignoSimulator(sources.emg, SimulatorConfig(command_port=0, emg_port=0, legacy_emg_port=None, aux_port=None)).start()
    xsens = {}
    try:
        for tracker, (_, source) in sources.imu.items():
            # a long wake-up window: the simulator waits in Config for the driver instead of streaming into a port
            # nobody has opened yet (a real MTi would, and those messages would never be read)
            xsens[tracker] = XsensSimulator(source, device_id=int(tracker, 16), wakeup_window_s=3600.0).start()
    except BaseException:
        trigno.close()
        for sim in xsens.values():
            sim.close()
        raise
    return Simulators(trigno, xsens)


# ------------------------------------------------------------------------------------------------ subject


def sim_subject(pack: str, log) -> Path:
    """The bundled subject calibrated for ``pack`` as ``msk demo`` does, cached under the user cache folder and reused
    while it is newer than the bundled recordings."""
    from services import demo

    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "msk-live" / "live-sim"
    path = cache / f"subject_{pack}.json"
    newest = max(p.stat().st_mtime for p in (RECORDINGS / "demo").rglob("*") if p.is_file())
    if path.is_file() and path.stat().st_mtime >= newest:
        log(f"reusing the calibrated bundled subject {path}")
        return path
    cache.mkdir(parents=True, exist_ok=True)
    made, _ = demo.calibrate(RECORDINGS, cache, pack, log)
    return made


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


def summarise(mcap: Path, duration_s: float) -> dict:
    """What the recording holds: samples per device, samples lost (last DeviceStatus), frames and flags per method."""
    emg, imu, lost, status_seen = Counter(), Counter(), {}, {}
    frames, flags = Counter(), {}
    envelopes = joints = 0
    for m in read_messages(mcap):
        t = m.type_name
        if t == "msk.EmgChunk":
            c = m.decode()
            emg[c.source_id] += c.n_samples
        elif t == "msk.ImuSample":
            imu[m.decode().tracker_id] += 1
        elif t == "msk.DeviceStatus":
            s = m.decode()
            lost[s.device_id] = int(s.samples_lost)
            status_seen[s.device_id] = {"connected": s.connected, "errors": int(s.errors), "last_error": s.last_error}
        elif t == "msk.ActivationFrame":
            f = m.decode()
            frames[f.method] += 1
            for flag in f.flags:
                flags.setdefault(f.method, Counter())[flag] += 1
        elif t == "msk.EmgEnvelope":
            envelopes += 1
        elif t == "msk.JointAngles":
            joints += 1
    return {
        "duration_s": round(duration_s, 3),
        "samples": {**{f"emg/{k}": v for k, v in emg.items()}, **{f"imu/{k}": v for k, v in imu.items()}},
        "samples_lost": lost,
        "devices": status_seen,
        "joint_frames": joints,
        "envelopes": envelopes,
        "frames_estimated": dict(frames),
        "flags": {m: dict(c) for m, c in flags.items()},
    }


def summary_text(summary: dict) -> str:
    lines = [f"session of {summary['duration_s']:.1f} s"]
    for device, n in summary["samples"].items():
        name = device.split("/", 1)[1]
        lines.append(f"  {device}: {n} samples, {summary['samples_lost'].get(name, 0)} lost")
    lines.append(f"  joint frames: {summary['joint_frames']}; EMG envelopes: {summary['envelopes']}")
    for method, n in summary["frames_estimated"].items():
        f = summary["flags"].get(method, {})
        lines.append(f"  {method}: {n} frames estimated; flags {', '.join(f'{k} {v}' for k, v in f.items()) or 'none'}")
    if "simulators_sent" in summary:
        lines.append("  simulators sent: " + ", ".join(f"{k} {v['samples']}" for k, v in summary["simulators_sent"].items()))
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------ the graph


@dataclass
class LivePlan:
    """Everything the graph needs, resolved from the session file (and ``--sim``)."""

    session: LiveSession
    methods: tuple[str, ...]
    subject: Path
    trigno: tuple[str, int] | None = None  # (HOST[:PORT], EMG port)
    xsens_ports: list[str] = field(default_factory=list)
    trackers: dict[str, str] = field(default_factory=dict)


def driver_argv(plan: LivePlan, kind: str) -> list[str]:
    s = plan.session
    argv = python_module("services.cli", "drivers", "--session", s.name)
    if kind == "trigno":
        host, emg_port = plan.trigno
        argv += ["--trigno", host, "--trigno-emg-port", str(emg_port), "--trigno-id", s.trigno_id]
    else:
        for port in plan.xsens_ports:
            argv += ["--xsens", port]
        argv += ["--imu-rate", str(s.imu_rate_hz), "--xsens-baud", str(s.xsens_baud)]
        argv += [f"--segment={t}={seg}" for t, seg in plan.trackers.items()]
    return argv


@dataclass
class FlowCounts:
    """Messages of the session seen by the graph's monitor node (updated live)."""

    joints: int = 0
    activations: Counter = field(default_factory=Counter)  # method -> frames

    def text(self) -> str:
        return f"{self.joints} joint frames; activation frames " + (
            ", ".join(f"{m} {n}" for m, n in self.activations.items()) or "none")


def monitor(options, *, session: str, counts: FlowCounts, stop_event: threading.Event, ready_event: threading.Event,
            ready_key) -> None:
    """A graph node of ``msk live`` itself: counts joints and activation frames, so the stop can wait (bounded)
    until the estimator has answered every joint frame before it is stopped."""
    from services.graph import declare_ready
    from services.zenoh_session import open_session

    prefix = topics.session_prefix(session)

    def on_joints(_sample) -> None:
        counts.joints += 1

    def on_activation(sample) -> None:
        counts.activations[str(sample.key_expr).rsplit("/", 1)[1]] += 1

    with open_session(options) as zsession:
        subscribers = [zsession.declare_subscriber(f"{prefix}/joints", on_joints),
                       zsession.declare_subscriber(f"{prefix}/activations/*", on_activation)]
        token = declare_ready(zsession, ready_key)  # noqa: F841 - alive while the node runs
        ready_event.set()
        stop_event.wait()
        for subscriber in subscribers:
            subscriber.undeclare()


class _Stopper:
    """SIGINT/SIGTERM set an event (the main thread then stops the graph in order) instead of raising mid-way."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.signal: str | None = None
        self._previous = {}

    def __enter__(self) -> "_Stopper":
        for signum in (signal.SIGINT, signal.SIGTERM):
            self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def _handle(self, signum, _frame) -> None:
        self.signal = signal.Signals(signum).name
        self.event.set()

    def __exit__(self, *exc) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)


def run_graph(plan: LivePlan, *, duration_s: float | None, view: bool, endpoint: str, log,
              simulators: Simulators | None = None) -> dict:
    s = plan.session
    out = s.out
    mcap = out / "session.mcap"
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    graph = Graph(s.name, endpoint)
    counts = FlowCounts()
    drivers = []
    started = time.monotonic()
    with _Stopper() as stopper:
        try:
            graph.add_process("recorder", python_module("services.recorder", "--out", str(mcap)),
                              log_path=logs / "recorder.log", own_session=True)
            graph.add_thread("monitor", monitor, session=s.name, counts=counts)
            estimator = python_module("services.estimator", "--pack", s.pack, "--session", s.name, "--subject", str(plan.subject),
                                      "--emg-clock", "host", "--load-kg", str(s.load_kg))
            for method in plan.methods:
                estimator += ["--method", method]
            graph.add_process("estimator", estimator, after=("recorder", "monitor"), log_path=logs / "estimator.log",
                              own_session=True)
            graph.add_process("kinematics", python_module("services.kinematics_node", "--pack", s.pack, "--session", s.name,
                                                          "--imu-clock", "host"),
                              after=("recorder", "estimator", "monitor"), log_path=logs / "kinematics.log",
                              own_session=True)
            if plan.trigno is not None:
                drivers.append("drivers-trigno")
                graph.add_process("drivers-trigno", driver_argv(plan, "trigno"), after=("recorder", "estimator"),
                                  log_path=logs / "drivers-trigno.log", own_session=True)
            if plan.xsens_ports:
                drivers.append("drivers-xsens")
                graph.add_process("drivers-xsens", driver_argv(plan, "xsens"), after=("recorder", "kinematics"),
                                  log_path=logs / "drivers-xsens.log", own_session=True)
            # process ids, to stop the nodes by hand should msk live itself be killed (they have their own groups)
            (logs / "pids.json").write_text(json.dumps({n: graph.process(n).pid for n in graph.nodes if graph.process(n)}) + "\n")
            _wait_ready(graph, stopper)
            viewer = None
            if view and not stopper.event.is_set():
                viewer = subprocess.Popen(python_module("services.cli", "view", "--session", s.name, f"--connect={endpoint}"),
                                          start_new_session=True)  # Ctrl-C reaches msk live only: it stops in order
            log(f"live session {s.name!r} running: {', '.join(graph.nodes)}" + (" + view" if viewer else "")
                + f"; recording to {mcap}" + (f"; stops after {duration_s:g} s" if duration_s else "; Ctrl-C stops"))
            started = time.monotonic()
            deadline = None if duration_s is None else started + duration_s
            reason = "duration"
            while not stopper.event.wait(0.1):
                if deadline is not None and time.monotonic() >= deadline:
                    break
                failed = graph.failed()
                if failed:
                    reason = f"node failed: {failed}"
                    log(f"stopping: {reason} (logs in {logs})")
                    break
            if stopper.event.is_set():
                reason = stopper.signal or "signal"
            elapsed = time.monotonic() - started
        finally:
            codes = stop_in_order(graph, drivers, simulators, locals().get("viewer"), counts, plan.methods, log)
    summary = summarise(mcap, elapsed)
    summary["stopped_by"] = reason
    summary["exit_codes"] = codes
    if simulators is not None:
        summary["simulators_sent"] = simulators.sent()
    return summary


def _wait_ready(graph: Graph, stopper: _Stopper) -> None:
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
    if error:
        raise error[0]


def _settle(what: str, done, counts: FlowCounts, timeout_s: float, log) -> None:
    """Bounded wait for the downstream nodes to catch up; on expiry say so with the counts, and go on stopping."""
    try:
        wait_for(what, done, counts.text, timeout_s)
    except GraphTimeout as error:
        log(f"warning: {error}")


def stop_in_order(graph: Graph, drivers: list[str], simulators: Simulators | None, viewer, counts: FlowCounts,
                  methods, log) -> dict:
    """Sources first, the recorder last, so what the devices sent flows through and is recorded."""
    if simulators is not None:
        simulators.hold()
        time.sleep(DRAIN_S)
    # Xsens before Trigno: the last joint frames still find EMG (no ``emg_stalled`` flags at the end of a session)
    order = sorted(drivers, key=lambda d: d != "drivers-xsens") + ["kinematics", "estimator", "recorder"]
    codes = {}
    for name in order:
        process = graph.process(name)
        if process is None:
            continue
        if name == "kinematics":  # joints stop changing: the drivers' last samples went through
            last = [counts.joints, time.monotonic()]

            def quiet() -> bool:
                if counts.joints != last[0]:
                    last[:] = [counts.joints, time.monotonic()]
                return time.monotonic() - last[1] >= DRAIN_S

            _settle("the kinematics node to publish its last joint frames", quiet, counts, STOP_TIMEOUT_S, log)
        elif name == "estimator":  # every joint frame answered by every method
            _settle(f"the estimator to answer all joint frames ({', '.join(methods)})",
                    lambda: all(counts.activations[m] >= counts.joints for m in methods), counts, STOP_TIMEOUT_S, log)
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


def plan_for(session: LiveSession, *, sim: bool, log) -> tuple[LivePlan, Simulators | None]:
    from msk_core.imu.mapping import mapping_for
    from msk_core.model import load_pack

    session.out.mkdir(parents=True, exist_ok=True)
    model = load_pack(session.pack)
    segments = list(mapping_for(model.name).segments)
    simulators = None
    if sim:
        sources = sim_sources(RECORDINGS / "demo_session.mcap", model.name)
        subject = session.subject or sim_subject(model.name, log)
        if "session.load_kg" not in session.given:
            session.load_kg = sources.load_kg
        electrodes = session.electrodes or sources.electrodes
        trackers = session.trackers or {t: seg for t, (seg, _) in sources.imu.items() if seg in segments}
        methods = session.methods or SIM_METHODS
    else:
        if session.subject is None:
            raise ConfigError("missing: the subject profile (`msk calibrate`)", path=session.path, field="session.subject")
        subject, electrodes, trackers = session.subject, session.electrodes, session.trackers
        methods = session.methods or (("proposed", "assisted") if session.trigno_host else ("proposed",))
    profile = json.loads(Path(subject).read_text())
    check_against_pack(LiveSession(session.path, trackers=trackers, electrodes=electrodes), list(model.groups),
                       segments, profile.get("emg_normalisation", {}))
    if "assisted" in methods and not electrodes:
        raise ConfigError("method 'assisted' needs EMG: a [trigno] device and an [electrodes] map", path=session.path,
                          field="session.methods", value="assisted")
    profile_path = session_profile(Path(subject), electrodes, list(model.groups), session.out)
    plan = LivePlan(session, tuple(methods), profile_path, trackers=trackers)
    if sim:
        simulators = start_simulators(sources)
        plan.trigno = (f"127.0.0.1:{simulators.trigno.ports['command']}", simulators.trigno.ports["emg"])
        plan.xsens_ports = [simulators.xsens[t].path for t in trackers]
        session.imu_rate_hz = int(round(next(iter(sources.imu.values()))[1].rate_hz))
        log(f"simulators: Trigno on 127.0.0.1:{simulators.trigno.ports['command']} ({sources.emg.rate_hz:g} Hz, "
            f"{sum(sources.emg.paired)} sensors), Xsens " + ", ".join(f"{t} ({seg}) on {simulators.xsens[t].path}"
                                                                      for t, seg in trackers.items())
            + f"; streaming the bundled {sources.trial} trial")
        for tracker in set(sources.imu) - set(trackers):
            simulators.xsens.pop(tracker).close()  # trackers of segments the pack does not use
    else:
        if session.trigno_host is not None:
            from drivers.trigno import protocol as tp

            plan.trigno = (session.trigno_host, session.trigno_emg_port or int(tp.EmgPort.AVANTI))
        plan.xsens_ports = list(session.xsens_ports)
    return plan, simulators


def main(session: LiveSession, *, sim: bool, duration_s: float | None, view: bool, log=print) -> dict:
    from services.zenoh_session import free_loopback_endpoint

    plan, simulators = plan_for(session, sim=sim, log=log)
    try:
        summary = run_graph(plan, duration_s=duration_s, view=view, endpoint=free_loopback_endpoint(), log=log,
                            simulators=simulators)
    except BaseException:
        if simulators is not None:
            simulators.close()
        raise
    summary["methods"] = list(plan.methods)
    (session.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    log(summary_text(summary))
    log(f"recording: {session.out / 'session.mcap'}; summary: {session.out / 'summary.json'}")
    return summary
