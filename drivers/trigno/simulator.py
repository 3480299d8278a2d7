"""A Trigno Control Utility stand-in: a real TCP server speaking the SDK protocol and streaming EMG from a recording.

It serves the command port (banner, replies, errors, master rule, unsolicited ``STOPPED``), the EMG port (50043 and
the legacy 50041) and the AUX port, in 13.5 ms frames of 26/27 samples. The protocol variants public clients
disagree about are :class:`TrignoQuirks`, so a driver can be tested against each. :meth:`TrignoSimulator.kill`
drops every connection at once, like a crashed server; a new simulator on the same ports is a restarted one.

One world: with ``SimulatorConfig.trial_clock`` (a :class:`drivers.trial_clock.TrialClock` shared with the Xsens
simulators of a session), a START at wall time t streams the trial from its sample of that instant (modulo the
trial's length when looping), as a physical base samples the one world; without one every START plays the trial
from sample 0. Either way the sample index the client counts starts at 0 with START: the device clock is the base's
own. ``SimulatorConfig.latency_s`` delays every frame: the base measures a frame's last sample at t and its bytes
leave at t + latency.

The AUX port (and the legacy ACC port) carry each paired sensor's accelerometer in g: the source's ``acc`` (the
synthetic session's site accelerations) sampled at the AUX instants, 2 per frame, AUX sample k measured at EMG
device time k / 148.148 Hz (with the frame's EMG sample 0 and its middle), on the trial's grid like the EMG; a source
without accelerations has its sensors lying flat and still (z = 1 g).

Electrode faults (``SimulatorConfig.faults``, :class:`SensorFault`): per sensor and time span, what a failing
electrode does to its EMG, as the stream shows it, at physical amplitudes (the quality monitor,
:mod:`msk_core.signal.quality`, then judges them as it judges a real sensor):

- ``lift_off``: the electrode comes off the skin. The muscle's EMG fades out (50 ms) and the floating inputs carry the
  electrode's moving half-cell potential: a baseline wander below 10 Hz of ``amplitude_v`` RMS (default 2 mV) over the
  sensor's own noise floor (0.75 uV RMS, the Avanti's stated baseline noise); pressed back, the EMG fades in again.
- ``hum``: mains interference picked up by the leads: ``mains_hz`` (default 50 Hz) of ``amplitude_v`` peak (default
  300 uV) with its 3rd and 5th harmonics at 30 % and 10 % of it, phase-locked to the device clock, added to the EMG.
- ``saturation``: the electrode knocked and pressed (against the bench, by the bar): an impact artefact 4 times a
  second (each a 30 Hz oscillation of ``amplitude_v`` peak, default 25 mV, decaying in 20 ms, the intervals jittered
  by +-20 %) on top of the EMG, which the converter clips at its +-11 mV range.
- ``flat``: the sensor stops sampling (battery out, out of radio range) and its slot holds the last value it sent.

Times are on the base's device clock: seconds after START (the EMG sample index / rate), the clock the EMG chunks
carry; a new START plays the faults again from 0. Every frame is clipped to the sensors' input range
(+-:data:`msk_core.units.TRIGNO_EMG_RANGE_V`), as the converter does.
"""

from __future__ import annotations

import collections
import enum
import math
import select
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy import signal as sp_signal

from drivers.trial_clock import TrialClock
from drivers.trigno import protocol as tp
from drivers.trigno.source import EmgSource, resample
from msk_core.errors import ConfigError
from msk_core.units import TRIGNO_EMG_RANGE_V

AUX_SAMPLES_PER_FRAME = 2


class UpsamplingReply(enum.Enum):
    """Reply style to ``UPSAMPLING?``: the manual's ``UPSAMPLING ON|OFF`` or the ``YES|NO`` one client expects."""

    ON_OFF = "on_off"
    YES_NO = "yes_no"


@dataclass(frozen=True)
class TrignoQuirks:
    """Server behaviours that differ between Trigno software versions (and between what clients assume)."""

    protocol_version: str = "3.6.0"
    banner_trailing_space: bool = False
    start_index_base: int = 1  # STARTINDEX? counts slots from 0 or from 1
    upsampling_reply: UpsamplingReply = UpsamplingReply.ON_OFF
    bare_rate_cannot_complete: bool = True  # a bare "RATE?" answers CANNOT COMPLETE
    first_connection_is_master: bool = True  # else every connection must ask MASTER before START
    stop_trigger_after_s: float | None = None  # fire the stop trigger (unsolicited STOPPED) after streaming this long
    quit_stops_acquisition: bool = True  # QUIT alone (one client's way) also ends streaming
    start_delay_s: float = 0.0  # a real system sends its first data ~2 s after START
    #: the first data after START come this much later as one burst of what was measured since START (a base that
    #: buffers until its link is ready), instead of start_delay_s's later start of the measurement
    start_burst_s: float = 0.0
    #: with TRIGGER START ON, the measurement starts when the start trigger fires, this long after START
    start_trigger_fires_after_s: float = 1.0
    aux_silent: bool = False  # the AUX ports accept connections but send nothing (sensors with their AUX off)
    #: each AUX frame leaves this much after the EMG frame of the same instant (the ports are separate streams with no
    #: counter: a base may send the AUX behind), also while the EMG pauses
    aux_lag_s: float = 0.0


class FaultKind(str, enum.Enum):
    """What goes wrong with an electrode (module docstring: what each does to the signal)."""

    LIFT_OFF = "lift_off"
    HUM = "hum"
    SATURATION = "saturation"
    FLAT = "flat"


#: ``amplitude_v`` when a fault states none: lift-off wander RMS, hum peak of the fundamental, impact peak (volts)
DEFAULT_FAULT_AMPLITUDE_V = {FaultKind.LIFT_OFF: 2e-3, FaultKind.HUM: 300e-6, FaultKind.SATURATION: 25e-3}
SENSOR_NOISE_RMS_V = 0.75e-6  # Trigno Avanti baseline noise (< 750 nV RMS): what a sensor off the skin still reads
LIFT_OFF_FADE_S = 0.05  # the EMG fades out as the electrode comes off, in as it is pressed back
WANDER_CUTOFF_HZ = 10.0  # the lifted electrode's baseline wander: movement of its half-cell potential, below 10 Hz
HUM_HARMONICS = ((3, 0.3), (5, 0.1))  # mains pickup: odd harmonics (non-linear loads), relative to the fundamental
IMPACT_RATE_HZ = 4.0  # saturation: impacts per second (a sensor pressed and knocked during the lift)
IMPACT_JITTER = 0.2  # +- share of the interval between impacts
IMPACT_RING_HZ = 30.0  # each impact: the electrode-skin interface ringing through the sensor's band
IMPACT_DECAY_S = 0.020


@dataclass(frozen=True)
class SensorFault:
    """One injected electrode fault: ``sensor`` (1..16) shows ``kind`` from ``start_s`` to ``end_s`` (device clock:
    seconds after START). ``amplitude_v``: the kind's size (None: :data:`DEFAULT_FAULT_AMPLITUDE_V`; not used by
    ``flat``); ``mains_hz``: the hum's fundamental."""

    sensor: int
    kind: FaultKind
    start_s: float
    end_s: float
    amplitude_v: float | None = None
    mains_hz: float = 50.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "kind", FaultKind(self.kind))
        if not (isinstance(self.sensor, int) and 1 <= self.sensor <= tp.N_SENSORS):
            raise ConfigError(f"a sensor is numbered 1..{tp.N_SENSORS}", field="sensor", value=self.sensor)
        if not (math.isfinite(self.start_s) and math.isfinite(self.end_s) and 0 <= self.start_s < self.end_s):
            raise ConfigError(
                "need 0 <= start_s < end_s (seconds after START)", field="start_s", value=(self.start_s, self.end_s)
            )
        if self.amplitude_v is not None and not (math.isfinite(self.amplitude_v) and self.amplitude_v > 0):
            raise ConfigError("an amplitude is a positive number of volts", field="amplitude_v", value=self.amplitude_v)
        if not (math.isfinite(self.mains_hz) and 40.0 <= self.mains_hz <= 70.0):
            raise ConfigError("mains frequency must be 40..70 Hz (50 or 60)", field="mains_hz", value=self.mains_hz)

    @property
    def amplitude(self) -> float:
        return self.amplitude_v if self.amplitude_v is not None else DEFAULT_FAULT_AMPLITUDE_V.get(self.kind, 0.0)

    @classmethod
    def parse(cls, text: str) -> SensorFault:
        """``SENSOR:KIND:START-END`` (seconds after START), e.g. ``5:hum:10-15`` (the ``msk live --sim-fault`` form)."""
        parts = text.split(":")
        kinds = ", ".join(k.value for k in FaultKind)
        if len(parts) != 3 or "-" not in parts[2]:
            raise ConfigError(
                f"expected SENSOR:KIND:START-END, e.g. 5:hum:10-15 (kinds: {kinds})", field="fault", value=text
            )
        sensor, kind, span = parts
        start, _, end = span.partition("-")
        try:
            return cls(int(sensor), FaultKind(kind.strip().lower().replace("-", "_")), float(start), float(end))
        except ValueError:
            raise ConfigError(
                f"expected SENSOR:KIND:START-END with a sensor number, one of {kinds} and times in seconds",
                field="fault",
                value=text,
            ) from None

    def describe(self) -> dict:
        """As ``summary.json`` records it."""
        return {
            "sensor": self.sensor,
            "kind": self.kind.value,
            "start_s": self.start_s,
            "end_s": self.end_s,
            "amplitude_v": self.amplitude if self.kind is not FaultKind.FLAT else None,
            **({"mains_hz": self.mains_hz} if self.kind is FaultKind.HUM else {}),
        }


class _FaultSignals:
    """The faults' signals on one run's sample grid (sample k of the run at device time k / rate), made once per rate
    from the simulator's seed: what :meth:`apply` does to each frame."""

    def __init__(self, faults: tuple[SensorFault, ...], rate_hz: float, seed: int) -> None:
        self.rate_hz = rate_hz
        self.spans = []
        for i, fault in enumerate(faults):
            k0, k1 = int(round(fault.start_s * rate_hz)), int(round(fault.end_s * rate_hz))
            rng = np.random.default_rng([seed, i])
            self.spans.append((fault, k0, k1, self._signal(fault, k1 - k0, rng)))

    def _signal(self, fault: SensorFault, n: int, rng: np.random.Generator) -> np.ndarray:
        rate, t = self.rate_hz, np.arange(n) / self.rate_hz
        if fault.kind is FaultKind.HUM:
            phase = rng.uniform(0, 2 * np.pi)
            hum = np.sin(2 * np.pi * fault.mains_hz * t + phase)
            for harmonic, share in HUM_HARMONICS:
                hum += share * np.sin(2 * np.pi * harmonic * fault.mains_hz * t + harmonic * phase)
            return fault.amplitude * hum
        if fault.kind is FaultKind.LIFT_OFF:
            pad = int(rate)  # 1 s of run-in, so the wander has its steady spectrum from the first sample
            sos = sp_signal.butter(4, WANDER_CUTOFF_HZ, btype="low", fs=rate, output="sos")
            wander = sp_signal.sosfilt(sos, rng.standard_normal(n + pad))[pad:]
            wander *= fault.amplitude / max(float(np.std(wander)), 1e-30)
            return wander + SENSOR_NOISE_RMS_V * rng.standard_normal(n)
        if fault.kind is FaultKind.SATURATION:
            artefact = np.zeros(n)
            onset = rng.uniform(0, 1 / IMPACT_RATE_HZ)
            ring = np.arange(int(5 * IMPACT_DECAY_S * rate)) / rate
            impact = np.exp(-ring / IMPACT_DECAY_S) * np.sin(2 * np.pi * IMPACT_RING_HZ * ring)
            while onset * rate < n:
                k = int(onset * rate)
                m = min(len(impact), n - k)
                artefact[k : k + m] += rng.choice([-1.0, 1.0]) * fault.amplitude * impact[:m]
                onset += (1 + rng.uniform(-IMPACT_JITTER, IMPACT_JITTER)) / IMPACT_RATE_HZ
            return artefact
        return np.empty(0)  # flat: the held value is the run's own sample

    def apply(self, emg: np.ndarray, first: int, held: Callable[[int, int], float]) -> None:
        """Inject into ``emg`` (the frame's rows, run samples ``first``...) in place; ``held(k, column)``: the clean
        value of run sample ``k`` in that column (what a flat sensor keeps sending)."""
        n = emg.shape[0]
        for fault, k0, k1, sig in self.spans:
            lo, hi = max(k0, first), min(k1, first + n)
            if lo >= hi:
                continue
            column, rows, part = fault.sensor - 1, slice(lo - first, hi - first), slice(lo - k0, hi - k0)
            if fault.kind is FaultKind.FLAT:
                emg[rows, column] = held(k0 - 1, column) if k0 > 0 else 0.0
            elif fault.kind is FaultKind.LIFT_OFF:
                k = np.arange(lo, hi)
                fade = int(LIFT_OFF_FADE_S * self.rate_hz)
                off = np.clip(np.minimum(k - k0 + 1, k1 - k) / fade, 0.0, 1.0)  # 0 on the skin .. 1 off it
                emg[rows, column] = (1 - off) * emg[rows, column] + off * sig[part]
            else:
                emg[rows, column] += sig[part]


@dataclass(frozen=True)
class SimulatorConfig:
    host: str = "127.0.0.1"
    command_port: int = tp.COMMAND_PORT  # 0 = any free port (see TrignoSimulator.ports)
    emg_port: int = tp.DataPort.EMG
    legacy_emg_port: int | None = tp.DataPort.LEGACY_EMG
    aux_port: int | None = tp.DataPort.AUX
    legacy_acc_port: int | None = None  # e.g. 50042: legacy ACC stream, x,y,z per sensor (48 floats per sample)
    upsampling: bool | None = None  # initial UPSAMPLING state; None = whichever matches the source rate
    endianness: tp.Endianness = tp.Endianness.LITTLE
    speed: float = 1.0  # >1 streams faster than real time (tests)
    loop: bool = True  # restart the recording at its end; else stop sending data
    fragment_max: int | None = None  # split each frame into random pieces of 1..fragment_max bytes
    seed: int = 0
    quirks: TrignoQuirks = field(default_factory=TrignoQuirks)
    trial_clock: TrialClock | None = None  # one world shared by a session's simulators (None: START plays from 0)
    latency_s: float = 0.0  # a frame leaves this long (device seconds) after its last sample was measured
    faults: tuple[SensorFault, ...] = ()  # electrode faults injected at stated device times (module docstring)

    def __post_init__(self) -> None:
        object.__setattr__(self, "faults", tuple(self.faults))
        for fault in self.faults:
            if not isinstance(fault, SensorFault):
                raise ConfigError("faults are SensorFault(sensor, kind, start_s, end_s)", field="faults", value=fault)
        if not (math.isfinite(self.speed) and self.speed > 0):
            raise ConfigError("must be a positive number", field="speed", value=self.speed)
        if not (math.isfinite(self.latency_s) and self.latency_s >= 0):
            raise ConfigError(
                "device latency must be a finite number of seconds >= 0", field="latency_s", value=self.latency_s
            )


@dataclass
class SimulatorStats:
    frames_sent: int = 0
    samples_sent: int = 0
    frames_dropped: int = 0  # measured during a pause that drops them (TrignoSimulator.pause), never sent
    commands: int = 0
    connections: int = 0
    latency_s: float = 0.0  # the stated device latency applied to every frame (SimulatorConfig.latency_s)
    start_index: int | None = None  # trial (stream) sample index the latest START streamed first; None: no START yet
    started_s: float | None = None  # time.monotonic() at which the latest START's first sample was measured


class _CommandConnection:
    def __init__(self, sock: socket.socket, conn_id: int) -> None:
        self.sock = sock
        self.id = conn_id
        self.lock = threading.Lock()

    def send_reply(self, text: str) -> None:
        with self.lock:
            self.sock.sendall(text.encode("ascii") + tp.TERMINATOR)


class TrignoSimulator:
    """Start with :meth:`start` (or as a context manager); :meth:`close` stops cleanly, :meth:`kill` abruptly."""

    def __init__(self, source: EmgSource, config: SimulatorConfig | None = None) -> None:
        self.source = source
        self.config = config or SimulatorConfig()
        for fault in self.config.faults:
            if not source.paired[fault.sensor - 1]:
                raise ConfigError(
                    f"sensor {fault.sensor} is not paired in {source.name} (paired: "
                    f"{[k + 1 for k, p in enumerate(source.paired) if p]}): no EMG to inject a fault in",
                    field="faults",
                    value=fault.sensor,
                )
        self.stats = SimulatorStats(latency_s=self.config.latency_s)
        self._stop = threading.Event()
        self._lock = threading.RLock()
        self._listeners: dict[str, socket.socket] = {}
        self._accept_locks: dict[str, threading.Lock] = {}
        self._command_conns: list[_CommandConnection] = []
        self._data_conns: dict[str, list[socket.socket]] = {"emg": [], "aux": [], "legacy_acc": []}
        self._threads: list[threading.Thread] = []
        self._lagged_aux: collections.deque = collections.deque()  # (due, kind, payload): aux_lag_s
        self._master: int | None = None
        self._next_conn_id = 1
        self._running = False
        self._held = False
        self._send_after = 0.0  # no frame leaves before this instant (time.monotonic): a pause or a start burst
        self._drop_until = 0.0  # frames due before this instant are lost (a pause that drops), not sent late
        # a buffering pause drained at a pace: (pause start, resume, speed); frame due d >= start leaves at
        # resume + (d - start) / speed until that is earlier than d (caught up)
        self._catch_up: tuple[float, float, float] | None = None
        self._unpaired: set[int] = set()  # sensors (1-16) unpaired while running: PAIRED? NO, their slot 0.0
        self._deaf = False  # stall(commands_too=True): commands are read and never answered
        self._run_started = 0.0  # wall instant (time.monotonic) the latest START took effect
        self._first_index = 0  # stream sample index of the run's sample 0 (0 without a trial clock)
        self._frame = 0  # frames sent since START
        self._upsampling = self.config.upsampling if self.config.upsampling is not None else source.rate_hz > 1960.0
        self._endianness = self.config.endianness
        self._backwards_compatibility = False
        self._triggers = {"START": False, "STOP": False}
        self._rng = np.random.default_rng(self.config.seed)
        self._stream_samples: np.ndarray | None = None
        self._acc_grid: tuple[np.ndarray, np.ndarray] | None = None  # source accelerations, one loop closed
        self._fault_signals: _FaultSignals | None = None  # the injected faults on the run's grid at the rate in use
        self.ports: dict[str, int] = {}

    # ------------------------------------------------------------------------------------------ lifecycle
    def __enter__(self) -> TrignoSimulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def hold(self) -> None:
        """Stop sending data from now on (sensors switched off) while connections stay open: a clean end of a
        simulated session, after which ``stats.samples_sent`` is final and a reading client can receive all of it."""
        self._held = True

    def start(self) -> TrignoSimulator:
        if self._listeners:
            return self  # already serving (start() then ``with sim:``)
        cfg = self.config
        wanted = {
            "command": cfg.command_port,
            "emg": cfg.emg_port,
            "legacy_emg": cfg.legacy_emg_port,
            "aux": cfg.aux_port,
            "legacy_acc": cfg.legacy_acc_port,
        }
        for name, port in wanted.items():
            if port is None:
                continue
            listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                listener.bind((cfg.host, int(port)))
            except OSError as error:  # nothing left listening, and the error says which port
                listener.close()
                self.close()
                error.strerror = f"{error.strerror} (the {name} port {port})"
                raise
            listener.listen(8)
            listener.settimeout(0.1)
            self._listeners[name] = listener
            self._accept_locks[name] = threading.Lock()
            self.ports[name] = listener.getsockname()[1]
            self._spawn(self._accept_loop, name, listener)
        self._spawn(self._stream_loop)
        if cfg.quirks.aux_lag_s > 0:
            self._spawn(self._lagged_aux_loop)
        return self

    def close(self) -> None:
        """Stop serving: close every connection and listener, join the threads."""
        self._stop.set()
        self._close_all()
        for thread in self._threads:
            thread.join(timeout=2.0)

    def kill(self) -> None:
        """Abrupt server death: connections are reset, nothing more is sent (threads are still joined)."""
        self._stop.set()
        with self._lock:
            conns = [c.sock for c in self._command_conns] + [s for group in self._data_conns.values() for s in group]
        for sock in conns:
            try:  # RST instead of FIN, as when a process dies with data in flight
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
            except OSError:
                pass
        self.close()

    def pause(self, seconds: float, *, drop: bool, catch_up: float | None = None) -> None:
        """The base goes quiet for ``seconds`` from now, its connections open. ``drop``: what it measures meanwhile
        is lost and it resumes at the present; else it sends that as one burst when it resumes (a buffering link),
        or, with ``catch_up``, at that many times real time until it has caught up (a link that drains slowly)."""
        now = time.monotonic()
        self._send_after = now + seconds
        if drop:
            self._drop_until = self._send_after
        elif catch_up is not None:
            if not catch_up > 1:
                raise ValueError(f"catch_up must be > 1 (times real time), got {catch_up}")
            self._catch_up = (now, self._send_after, catch_up)

    def drop_connections(self) -> None:
        """Close every client connection, the base still acquiring (its utility restarted its SDK server, or the
        network between them failed): a client that reconnects finds the streams going on, mid-way."""
        self._close_all(listeners=False)

    def unpair(self, sensor: int) -> None:
        """Sensor ``sensor`` (1-16) is unpaired (or switched off) while the base runs: it answers PAIRED? NO and the
        base sends its slot as 0.0 ("Empty slots are 0.0")."""
        self._unpaired.add(sensor)

    def pair(self, sensor: int) -> None:
        """Sensor ``sensor`` (1-16), unpaired by :meth:`unpair`, is paired again: its slot carries its EMG."""
        self._unpaired.discard(sensor)

    def stall(self, *, commands_too: bool = False) -> None:
        """Stop sending data without telling anyone, as when a cable is pulled (no FIN, no RST, no STOPPED);
        ``commands_too``: the command port answers nothing either (the cable between the client and the utility)."""
        self._running = False
        self._deaf = commands_too

    def _close_all(self, *, listeners: bool = True) -> None:
        """Close every client connection, and the listeners too unless ``listeners`` is False (the base serves on)."""
        with self._lock:
            socks = list(self._listeners.values()) if listeners else []
            socks += [c.sock for c in self._command_conns] + [s for group in self._data_conns.values() for s in group]
            self._command_conns.clear()
            self._master = None
            for group in self._data_conns.values():
                group.clear()
        for sock in socks:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            sock.close()

    def _spawn(self, target, *args) -> None:
        thread = threading.Thread(target=target, args=args, daemon=True, name=f"trigno-sim-{target.__name__}")
        thread.start()
        self._threads.append(thread)

    # ------------------------------------------------------------------------------------------ state
    @property
    def streaming(self) -> bool:
        return self._running

    @property
    def rate_hz(self) -> float:
        return tp.rate_for(self.samples_per_frame)

    @property
    def samples_per_frame(self) -> int:
        return 27 if self._upsampling else 26

    def _stream(self) -> np.ndarray:
        if self._stream_samples is None:
            self._stream_samples = resample(self.source.samples, self.source.rate_hz, self.rate_hz)
        return self._stream_samples

    # ------------------------------------------------------------------------------------------ accepting
    def _accept_loop(self, name: str, listener: socket.socket) -> None:
        while not self._stop.is_set():
            try:
                if not select.select([listener], [], [], 0.1)[0]:  # wait without holding the accept lock
                    continue
            except (OSError, ValueError):  # listener closed
                return
            if self._accept_ready(name, listener) is None:
                return

    def _accept_ready(self, name: str, listener: socket.socket) -> bool | None:
        """Accept and register one connection waiting on ``listener``, as one step under its lock (so that
        :meth:`_accept_pending_data` sees every connection either registered or still waiting). True: one was
        accepted; False: none was waiting; None: the listener is closed."""
        with self._accept_locks[name]:
            try:
                if not select.select([listener], [], [], 0)[0]:
                    return False
                sock, _ = listener.accept()
            except (TimeoutError, BlockingIOError):
                return False
            except (OSError, ValueError):
                return None
            self._register(name, sock)
            return True

    def _register(self, name: str, sock: socket.socket) -> None:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        with self._lock:
            self.stats.connections += 1
        if name == "command":
            with self._lock:
                conn = _CommandConnection(sock, self._next_conn_id)
                self._next_conn_id += 1
                if self._master is None and self.config.quirks.first_connection_is_master:
                    self._master = conn.id
                self._command_conns.append(conn)
            self._spawn(self._command_loop, conn)
        else:
            with self._lock:
                self._data_conns[name if name in ("aux", "legacy_acc") else "emg"].append(sock)

    def _accept_pending_data(self) -> None:
        """Data connections a client opened before START wait in the listeners' backlogs until an accept thread runs,
        which on a busy machine can be after the first frames: accept them now, so that (as on a real TCU) a client
        connected before START receives the stream from its first frame."""
        for name, listener in list(self._listeners.items()):
            if name != "command":
                while self._accept_ready(name, listener):
                    pass

    # ------------------------------------------------------------------------------------------ commands
    def _command_loop(self, conn: _CommandConnection) -> None:
        quirks = self.config.quirks
        banner = f"{tp.BANNER_PREFIX} {quirks.protocol_version}" + (" " if quirks.banner_trailing_space else "")
        buffer = bytearray()
        conn.sock.settimeout(0.1)
        try:
            conn.send_reply(banner)
            while not self._stop.is_set():
                try:
                    chunk = conn.sock.recv(4096)
                except TimeoutError:
                    continue
                if not chunk:
                    break
                buffer += chunk
                while (index := buffer.find(tp.TERMINATOR)) >= 0:
                    packet = buffer[:index].decode("ascii", errors="replace")
                    del buffer[: index + len(tp.TERMINATOR)]
                    for command in tp.split_packet(packet):
                        self.stats.commands += 1
                        if self._deaf:
                            continue
                        reply = self._handle(conn, command)
                        conn.send_reply(reply)
                        if command.upper() == "QUIT":
                            raise ConnectionAbortedError
        except (OSError, ConnectionAbortedError):
            pass
        finally:
            self._drop_command_connection(conn)

    def _drop_command_connection(self, conn: _CommandConnection) -> None:
        with self._lock:
            if conn in self._command_conns:
                self._command_conns.remove(conn)
            if self._master == conn.id:
                self._master = None
        try:
            conn.sock.close()
        except OSError:
            pass

    def _handle(self, conn: _CommandConnection, command: str) -> str:
        """The reply to one command (the SDK answers every command with exactly one reply)."""
        quirks = self.config.quirks
        words = command.upper().split()
        text = " ".join(words)
        if text in ("MAX SAMPLES EMG", "MAX SAMPLES AUX"):  # one public client sends these without the "?"
            text += "?"
        is_master = self._master == conn.id
        if text == "START":
            if not is_master:
                return "CANNOT COMPLETE"
            self._start_streaming()
            return "OK"
        if text == "STOP":
            if not is_master:
                return "CANNOT COMPLETE"
            self._running = False
            return "OK"
        if text == "QUIT":
            if is_master and quirks.quit_stops_acquisition:
                self._running = False
            return "OK"
        if text == "MASTER?":
            return "YES" if is_master else "NO"
        if text == "MASTER":
            with self._lock:
                self._master = conn.id
            return "NEW MASTER"
        if text == "VERSION?":
            return quirks.protocol_version
        if text == "BACKWARDS COMPATIBILITY?":
            return "YES" if self._backwards_compatibility else "NO"
        if len(words) == 3 and words[:2] == ["BACKWARDS", "COMPATIBILITY"] and words[2] in ("ON", "OFF"):
            if self._running:
                return "CANNOT COMPLETE"
            self._backwards_compatibility = words[2] == "ON"
            return "OK"
        if text == "UPSAMPLING?":
            if quirks.upsampling_reply is UpsamplingReply.YES_NO:
                return "YES" if self._upsampling else "NO"
            return "UPSAMPLING ON" if self._upsampling else "UPSAMPLING OFF"
        if len(words) == 2 and words[0] in ("UPSAMPLE", "UPSAMPLING") and words[1] in ("ON", "OFF"):
            if self._running:
                return "CANNOT COMPLETE"
            self._upsampling = words[1] == "ON"
            self._stream_samples = self._acc_grid = self._fault_signals = None
            return "OK"
        if text == "ENDIANNESS?":
            return self._endianness.value
        if len(words) == 2 and words[0] == "ENDIAN" and words[1] in ("LITTLE", "BIG"):
            if self._running:
                return "CANNOT COMPLETE"
            self._endianness = tp.Endianness(words[1])
            return "OK"
        if text == "FRAME INTERVAL?":
            return f"{tp.FRAME_INTERVAL_S}"
        if text == "MAX SAMPLES EMG?":
            return str(self.samples_per_frame)
        if text == "MAX SAMPLES AUX?":
            return str(AUX_SAMPLES_PER_FRAME)
        if text == "RATE?":
            return "CANNOT COMPLETE" if quirks.bare_rate_cannot_complete else f"{self.rate_hz:.3f}"
        if text == "TRIGGER?":
            return f"TRIGGER START {'ON' if self._triggers['START'] else 'OFF'} STOP {'ON' if self._triggers['STOP'] else 'OFF'}"
        if len(words) == 3 and words[0] == "TRIGGER" and words[1] in ("START", "STOP") and words[2] in ("ON", "OFF"):
            self._triggers[words[1]] = words[2] == "ON"
            return "OK"
        if text == "BASE FIRMWARE?":
            return "MA2919-BE1506-DS0806-US2008-DA0901"
        if text == "BASE SERIAL?":
            return "SP-W01D-1771"
        if words and words[0] == "SENSOR":
            return self._sensor_command(words)
        return "INVALID COMMAND"

    def _sensor_command(self, words: list[str]) -> str:
        if len(words) < 3 or not words[1].isdigit() or not 1 <= int(words[1]) <= tp.N_SENSORS:
            return "INVALID COMMAND"
        n = int(words[1])
        rest = " ".join(words[2:])
        paired = self.source.paired[n - 1] and n not in self._unpaired
        if rest in ("PAIRED?", "ACTIVE?"):
            return "YES" if paired else "NO"
        if not paired:
            return "CANNOT COMPLETE"
        base = self.config.quirks.start_index_base
        simple = {
            "TYPE?": "O",
            "MODE?": "40",
            "CHANNELCOUNT?": "4",
            "EMGCHANNELCOUNT?": "1",
            "AUXCHANNELCOUNT?": "3",
            "STARTINDEX?": str(n - 1 + base),
            "AUXSTARTINDEX?": str((n - 1) * tp.AUX_SLOTS_PER_SENSOR + base),
            "SERIAL?": f"SP-W02C-{1000 + n:04d}",
            "FIRMWARE?": "40.51",
        }
        if rest in simple:
            return simple[rest]
        if len(words) == 4 and words[2] == "SETMODE" and words[3].isdigit():
            return f"SENSOR {n} SET TO MODE {words[3]}"
        if len(words) == 5 and words[2] == "CHANNEL" and words[3].isdigit():
            m = int(words[3])
            if not 1 <= m <= 4:
                return "CANNOT COMPLETE"
            emg = m == 1
            answers = {
                "RATE?": f"{self.rate_hz:.3f}" if emg else f"{tp.rate_for(AUX_SAMPLES_PER_FRAME):.3f}",
                "SAMPLES?": str(self.samples_per_frame if emg else AUX_SAMPLES_PER_FRAME),
                "GAIN?": "300" if emg else "1",
                "UNITS?": "V" if emg else "g",
            }
            return answers.get(words[4], "INVALID COMMAND")
        return "INVALID COMMAND"

    # ------------------------------------------------------------------------------------------ streaming
    def _start_streaming(self) -> None:
        if self._running:
            return
        self._accept_pending_data()
        self._frame = 0
        quirks = self.config.quirks
        delay = quirks.start_delay_s + (quirks.start_trigger_fires_after_s if self._triggers["START"] else 0.0)
        self._run_started = time.monotonic() + delay / self.config.speed
        self._first_index = self._index_at(self._run_started)
        self.stats.start_index = self._first_index
        self.stats.started_s = self._run_started
        self._send_after = time.monotonic() + self.config.quirks.start_burst_s / self.config.speed
        self._running = True

    def _index_at(self, wall_s: float) -> int:
        """The stream sample measured first at or after ``wall_s``: 0 without a trial clock (each START plays the
        trial from its start), else the trial's sample of that instant."""
        clock = self.config.trial_clock
        return 0 if clock is None else clock.first_index(wall_s, self.rate_hz, self.config.speed)

    def _frame_due(self, frame: int) -> float:
        """Wall instant (time.monotonic) at which ``frame`` leaves: without a trial clock one frame interval after
        the previous from START; with one, when its last sample is measured on the trial's sample grid. Plus the
        device latency in both cases."""
        cfg = self.config
        latency = cfg.latency_s / cfg.speed
        if cfg.trial_clock is None:
            return self._run_started + frame * tp.FRAME_INTERVAL_S / cfg.speed + latency
        last = self._first_index + (frame + 1) * self.samples_per_frame - 1
        return cfg.trial_clock.instant(last, self.rate_hz, cfg.speed) + latency

    def _fire_stop_trigger(self) -> None:
        self._running = False
        with self._lock:
            conns = list(self._command_conns)
        for conn in conns:
            try:
                conn.send_reply(tp.UNSOLICITED_STOPPED)
            except OSError:
                pass

    def _stream_loop(self) -> None:
        while not self._stop.is_set():
            if not self._running or self._held:
                self._stop.wait(0.005)
                continue
            due = self._frame_due(self._frame)
            send_at = max(due, self._send_after)
            if self._catch_up is not None:
                start, resume, pace = self._catch_up
                if due >= start:
                    send_at = max(due, resume + (due - start) / pace)
                    if send_at == due:  # caught up
                        self._catch_up = None
            delay = send_at - time.monotonic()
            if delay > 0:
                self._stop.wait(min(delay, 0.05))
                continue
            if due < self._drop_until:  # measured during a pause that drops: never sent
                self._frame += 1
                self.stats.frames_dropped += 1
                continue
            limit = self.config.quirks.stop_trigger_after_s
            if limit is not None and self._frame * tp.FRAME_INTERVAL_S >= limit:
                self._fire_stop_trigger()
                continue
            if not self._send_frame(self._frame):
                self._running = False
                continue
            self._frame += 1

    def _send_frame(self, frame: int) -> bool:
        """Send frame ``frame`` to every data connection; False at the end of a non-looping recording."""
        samples = self._stream()
        spf = self.samples_per_frame
        n = samples.shape[0]
        start = self._first_index + frame * spf
        if not self.config.loop and start + spf > n:
            return False
        index = (start + np.arange(spf)) % n
        emg = samples[index]
        if self.config.faults:
            if self._fault_signals is None:
                self._fault_signals = _FaultSignals(self.config.faults, self.rate_hz, self.config.seed)
            self._fault_signals.apply(emg, frame * spf, lambda k, column: samples[(self._first_index + k) % n, column])
        np.clip(emg, -TRIGNO_EMG_RANGE_V, TRIGNO_EMG_RANGE_V, out=emg)  # the converter's range
        for sensor in self._unpaired:
            emg[:, sensor - 1] = 0.0
        lag_s = self.config.quirks.aux_lag_s / self.config.speed
        with self._lock:
            listening = {
                kind: list(conns)
                for kind, conns in self._data_conns.items()
                # a lagged AUX frame goes to whoever reads the port when it leaves, maybe nobody yet
                if (conns or (kind != "emg" and lag_s > 0)) and (kind == "emg" or not self.config.quirks.aux_silent)
            }
        for kind, conns in listening.items():  # a port nobody reads costs nothing (the AUX rows are interpolated)
            payload = tp.encode_samples(emg if kind == "emg" else self._aux_payload(kind, start), self._endianness)
            if kind != "emg" and lag_s > 0:
                self._lagged_aux.append((time.monotonic() + lag_s, kind, payload))
            else:
                self._send_data(kind, conns, payload)
        self.stats.frames_sent += 1
        self.stats.samples_sent += spf
        return True

    def _aux_payload(self, kind: str, start: int) -> np.ndarray:
        """The AUX port's rows (``kind`` "aux") or the legacy ACC port's: the same accelerations, x,y,z per sensor
        (the first 3 of each sensor's 9 AUX slots)."""
        aux = self._aux_rows(start)
        if kind == "aux":
            return aux
        shaped = aux.reshape(AUX_SAMPLES_PER_FRAME, tp.N_SENSORS, tp.AUX_SLOTS_PER_SENSOR)
        return shaped[:, :, :3].reshape(AUX_SAMPLES_PER_FRAME, -1)

    def _aux_rows(self, start: int) -> np.ndarray:
        """The AUX port's samples of the frame whose first EMG sample is stream sample ``start``: ACC x, y, z (g) of
        every paired sensor in the first 3 of its 9 slots (the sensors answer 3 AUX channels), at the instants of
        the frame's first EMG sample and of its middle, the trial looping with the EMG."""
        aux = np.zeros((AUX_SAMPLES_PER_FRAME, tp.N_SENSORS, tp.AUX_SLOTS_PER_SENSOR), dtype=np.float32)
        paired = np.array(self.source.paired)
        if self.source.acc is None:
            aux[:, paired, 2] = 1.0  # accelerometer z of a sensor lying flat: 1 g
            return aux.reshape(AUX_SAMPLES_PER_FRAME, -1)
        if self._acc_grid is None:
            period = self._stream().shape[0] / self.rate_hz
            times = np.arange(self.source.acc.shape[0]) / self.source.acc_rate_hz
            acc = self.source.acc[times < period]  # the trial is the EMG's: a longer tail never plays
            times = np.append(times[: len(acc)], period)
            self._acc_grid = (times, np.concatenate([acc, acc[:1]]))  # the loop closes on its first sample
        times, values = self._acc_grid
        t = start / self.rate_hz + np.arange(AUX_SAMPLES_PER_FRAME) * tp.FRAME_INTERVAL_S / AUX_SAMPLES_PER_FRAME
        t = np.clip(t % times[-1], 0.0, times[-1])
        i = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
        w = ((t - times[i]) / (times[i + 1] - times[i]))[:, None, None]
        aux[:, paired, :3] = ((1.0 - w) * values[i] + w * values[i + 1])[:, paired]
        return aux.reshape(AUX_SAMPLES_PER_FRAME, -1)

    def _send_data(self, kind: str, conns: list[socket.socket], payload: bytes) -> None:
        for sock in conns:
            try:
                self._send_fragmented(sock, payload)
            except OSError:
                with self._lock:
                    if sock in self._data_conns[kind]:
                        self._data_conns[kind].remove(sock)
                sock.close()

    def _lagged_aux_loop(self) -> None:
        """The AUX frames of the ``aux_lag_s`` quirk, each sent when its lag has passed."""
        while not self._stop.wait(0.002):
            while self._lagged_aux and self._lagged_aux[0][0] <= time.monotonic():
                _, kind, payload = self._lagged_aux.popleft()
                with self._lock:  # whoever reads the port when the frame leaves (a client that just connected too)
                    conns = list(self._data_conns[kind])
                if conns:
                    self._send_data(kind, conns, payload)

    def _send_fragmented(self, sock: socket.socket, payload: bytes) -> None:
        limit = self.config.fragment_max
        if not limit:
            sock.sendall(payload)
            return
        pos = 0
        while pos < len(payload):
            size = int(self._rng.integers(1, limit + 1))
            sock.sendall(payload[pos : pos + size])
            pos += size
