"""Delsys Trigno SDK client: command port handshake, EMG/AUX data ports, gap detection and reconnection.

Single-threaded and explicit: :meth:`TrignoClient.poll` waits on every socket at once and returns the events that
happened (EMG blocks, gaps, status changes). A dropped connection never raises from :meth:`poll`: the client reports
it, retries with exponential backoff, re-runs the handshake, restarts acquisition and reports the estimated gap.
Everything already received has been returned before the disconnection is reported.
"""

from __future__ import annotations

import collections
import enum
import logging
import selectors
import socket
import time
from dataclasses import dataclass, field

import numpy as np

from drivers.trigno import protocol as tp
from msk_core.errors import ConfigError, ProtocolError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrignoConfig:
    host: str = "127.0.0.1"
    command_port: int = tp.COMMAND_PORT
    emg_port: int = tp.EmgPort.AVANTI  # 50043, or 50041 (legacy) for older servers
    # Clients disagree on the default EMG port: when emg_port refuses the connection, this one is tried.
    # None: 50041 when emg_port is the default 50043 (a custom port never falls back to a default one); 0: never.
    emg_port_fallback: int | None = None
    aux_port: int | None = None  # 50044 (Avanti AUX) or 50042 (legacy ACC) to also read an auxiliary stream
    aux_layout: tp.AuxLayout | None = None  # None: from the port number (50042 -> legacy ACC, else Avanti AUX)
    take_master: bool = True  # send MASTER when MASTER? says NO
    upsampling: bool | None = None  # None: leave the server's setting
    endianness: tp.Endianness | None = None  # None: leave the server's setting (LITTLE by default)
    stop_mode: tp.StopMode = tp.StopMode.STOP_THEN_QUIT
    connect_timeout_s: float = 2.0
    reply_timeout_s: float = 3.0
    banner_line_grace_s: float = 0.5  # accept a banner ending in a single CRLF after this long without the blank line
    reconnect: bool = True
    stall_timeout_s: float | None = (
        5.0  # no EMG bytes this long while streaming = lost link (a pulled cable sends no FIN)
    )
    backoff_initial_s: float = 0.05
    backoff_max_s: float = 2.0
    recv_bytes: int = 65536

    def __post_init__(self) -> None:
        if not self.host:
            raise ConfigError("Trigno host must not be empty", field="host", value=self.host)
        for name in ("command_port", "emg_port", "aux_port", "emg_port_fallback"):
            port = getattr(self, name)
            if port is not None and not (0 < int(port) < 65536 or (name == "emg_port_fallback" and port == 0)):
                raise ConfigError("TCP port must be within 1..65535", field=name, value=port)

    @property
    def resolved_emg_fallback(self) -> int | None:
        if self.emg_port_fallback is None:
            return int(tp.EmgPort.LEGACY) if self.emg_port == tp.EmgPort.AVANTI else None
        return self.emg_port_fallback or None

    @property
    def resolved_aux_layout(self) -> tp.AuxLayout:
        if self.aux_layout is not None:
            return self.aux_layout
        return tp.AuxLayout.for_port(self.aux_port) if self.aux_port is not None else tp.AuxLayout.AVANTI


def parse_address(text: str, *, default_port: int = tp.COMMAND_PORT) -> tuple[str, int]:
    """``HOST[:PORT]`` -> (host, command port)."""
    host, sep, port = text.rpartition(":")
    if not sep:
        return text, default_port
    if not port.isdigit() or not 0 < int(port) < 65536:
        raise ConfigError("expected HOST[:PORT]", field="--trigno", value=text)
    return host, int(port)


class ClientState(enum.Enum):
    IDLE = "idle"
    CONNECTED = "connected"
    STREAMING = "streaming"
    RECONNECTING = "reconnecting"
    STOPPED = "stopped"  # stop trigger fired (unsolicited STOPPED) or stop() called
    CLOSED = "closed"


@dataclass(frozen=True)
class SensorInfo:
    sensor: int  # 1..16
    paired: bool
    type_code: str = ""
    start_index: int = -1  # 0-based EMG slot, whatever base the server reports in (-1: unknown)
    active: bool = False  # paired and switched on (a paired sensor that is off streams zeros)
    emg_channels: int = 1  # EMGCHANNELCOUNT? (multi-channel sensors fill consecutive slots from start_index)

    @property
    def emg_slots(self) -> list[int]:
        """0-based EMG-port slots holding this sensor's EMG channels (its own slot when the start is unknown)."""
        first = self.start_index if self.start_index >= 0 else self.sensor - 1
        return [k for k in range(first, first + self.emg_channels) if 0 <= k < tp.N_SENSORS]


@dataclass(frozen=True)
class EmgBlock:
    """Rows of EMG as received: ``samples`` (n, 16) float32 volts for the 16 sensor slots."""

    samples: np.ndarray
    first_sample_index: int
    rate_hz: float
    host_time_ns: int  # when the bytes completing this block arrived

    @property
    def device_time_ns(self) -> int:
        return int(round(self.first_sample_index * 1e9 / self.rate_hz))


@dataclass(frozen=True)
class AuxBlock:
    samples: np.ndarray  # (n, 144) float32, 9 slots per sensor (Avanti AUX), or (n, 48) x,y,z per sensor (legacy ACC)
    first_sample_index: int
    rate_hz: float
    host_time_ns: int


@dataclass(frozen=True)
class GapEvent:
    """Samples that never arrived (estimated from host time across a reconnection or a pause in the data)."""

    first_missing_index: int
    n_missing: int
    host_time_ns: int
    reason: str


#: AUX rows of a resumed stream are held until its EMG says how long the gap was; beyond this span they are dropped
AUX_HOLD_S = 10.0
#: EMG that resumes after this much silence on a live link may have lost what was measured meanwhile: the stream has
#: no counter, so the gap is measured from host time (frames come every 13.5 ms; a base that buffered the pause
#: sends it as a burst, one that dropped it resumes at the present)
PAUSE_CHECK_S = 0.1
#: after a reconnection or such a pause, the resumed EMG is held this long to measure its backlog: the first row was
#: measured at min over the reads of (arrival - rows received so far / rate), whatever size the first read had and
#: however slowly a sender that fell behind catches up within it (the estimate assumes a base that samples in real
#: time: a simulator at speed 2 samples faster than the host clock and is undercounted)
RESUME_WINDOW_S = 0.25
#: a base that buffered a pause and sends its backlog faster than real time but not in one burst (an imitation at 2x:
#: 1 s held, drained over 1 s) keeps moving that estimate earlier: the EMG is held until the estimate has not moved by
#: more than CATCH_UP_STEP_S for RESUME_WINDOW_S (the backlog drained), at most MAX_RESUME_HOLD_S. A fixed window read
#: the undrained backlog as 0.75 s lost, and every later sample 0.75 s late
CATCH_UP_STEP_S = 0.010
MAX_RESUME_HOLD_S = 2.0
#: a pause's estimate below this is not counted: a sender (or a simulator on a loaded host) that fell behind and
#: catches up slower than the window measures reads as a short loss (a reconnection counts any)
PAUSE_TOLERANCE_S = 0.2
#: an AUX port that has sent nothing over this much EMG is said (once)
AUX_SILENT_S = 5.0
#: "Empty slots are 0.0": an active sensor's slot exactly 0.0 this long was emptied (its sensor unpaired or switched
#: off while streaming: an imitation's went on as 5,000 zeros without a word); real EMG is never exactly 0 that long
EMPTY_SLOT_S = 0.5
#: why the data ended when the base sends an unsolicited STOPPED
STOPPED_BY_SERVER = (
    "the base stopped acquiring: it sent STOPPED (its stop trigger fired, or another client on it sent STOP)"
)
#: why the data ended when the base went silent and answers that this connection is no longer its master: another
#: client took control and stopped acquisition (only the master may START/STOP); restarting would override it
TAKEN_OVER = (
    "the base stopped sending data and another client is now its master (MASTER? answers NO): that client stopped "
    "acquisition; not restarted, as it controls the base now"
)
#: how long a silent stream's MASTER? may take: a pulled cable answers nothing, and the poll must not block long
MASTER_PROBE_S = 0.5
#: said while the base's start trigger holds the first data back (TRIGGER? answered START ON): no stall before it
WAITING_FOR_TRIGGER = "waiting for the base's start trigger (TRIGGER? answered START ON): no data until it fires"


@dataclass(frozen=True)
class StatusEvent:
    state: ClientState
    detail: str
    host_time_ns: int


Event = EmgBlock | AuxBlock | GapEvent | StatusEvent


@dataclass
class ClientStats:
    samples_received: int = 0
    samples_lost: int = 0
    bytes_discarded: int = 0  # partial samples cut by a dropped connection
    stale_bytes_discarded: int = 0  # data-port bytes of an earlier acquisition, received before our START
    non_finite_values: int = 0  # NaN/Inf EMG and AUX values received (passed on unchanged; the estimator flags them)
    aux_samples_dropped: int = 0  # AUX rows held for an EMG stream that did not resume in time, then dropped
    reconnects: int = 0
    errors: int = 0
    last_error: str = ""


def _samples_per_frame(command: str, reply: str) -> int:
    per_frame = tp.parse_int(reply, command=command)
    if not 1 <= per_frame <= 1000:
        raise ProtocolError(f"{command} answered {reply!r}: not a sample count per frame")
    return per_frame


#: Informative queries of one connection that may go unanswered in time before the server is taken as not answering.
INFORMATIVE_TIMEOUTS = 3


@dataclass
class _Link:
    """The sockets of one connection to the server."""

    command: socket.socket
    emg: socket.socket | None  # None until the handshake on the command port is done
    aux: socket.socket | None
    replies: tp.ReplyReader = field(default_factory=tp.ReplyReader)
    pending_replies: list[str] = field(default_factory=list)
    late_replies: int = 0  # commands that timed out: their replies, when they come, belong to nobody
    informative_timeouts: int = 0  # informative queries that timed out and were taken as unanswered
    start_sent: bool = False  # START went out on this link (a START that failed may still have started the base)

    def close(self) -> None:
        for sock in (self.command, self.emg, self.aux):
            if sock is not None:
                try:
                    sock.close()
                except OSError:
                    pass


def _first_measured(reads: list[tuple[int, float]], rate_hz: float) -> float:
    """When the first row of resumed data was measured, from its reads' (rows, arrival): the earliest of (arrival -
    rows so far / rate) over them (:data:`RESUME_WINDOW_S`)."""
    counts = np.cumsum([rows for rows, _ in reads])
    return min(arrived - n / rate_hz for (_, arrived), n in zip(reads, counts, strict=True))


class TrignoClient:
    """Use as ``with TrignoClient(config) as client: client.start(); events = client.poll(0.1)``."""

    def __init__(self, config: TrignoConfig) -> None:
        self.config = config
        self.state = ClientState.IDLE
        self.stats = ClientStats()
        self.protocol_version = ""
        self.sensors: tuple[SensorInfo, ...] = ()
        self.rate_hz = 0.0
        self.aux_rate_hz = 0.0
        self.aux_unavailable = ""  # why the AUX port asked for is not read (refused), empty while it is
        self.start_trigger = False  # TRIGGER? said START ON: the first data wait for the trigger, however long
        self.endianness = tp.Endianness.LITTLE
        self.upsampling: bool | None = None
        self.emg_port = 0  # the EMG port actually connected (emg_port, or emg_port_fallback when it was refused)
        self._link: _Link | None = None
        self._selector = selectors.DefaultSelector()
        self._emg_decoder = tp.SampleDecoder(tp.FLOATS_PER_SAMPLE[tp.DataPort.EMG])
        self._aux_decoder = tp.SampleDecoder(config.resolved_aux_layout.floats_per_sample)
        self._next_index = 0
        self._next_aux_index = 0
        # AUX rows of a resumed stream, before its gap is known: (rows, host time ns, arrival time.monotonic)
        self._aux_after_gap: list[tuple[np.ndarray, int, float]] = []
        # the AUX port's lag behind the EMG port, per AUX read: its arrival minus that of the EMG read that reached the
        # same instant (s); and the EMG reads' (end index, arrival) it is measured against
        self._aux_lags: collections.deque[float] = collections.deque(maxlen=64)
        self._emg_arrivals: collections.deque[tuple[int, float]] = collections.deque(maxlen=256)
        # after a lost link, the resumed EMG's (first index, when its first row was measured) until the first AUX read
        # places the AUX stream against it
        self._aux_anchor: tuple[int, float] | None = None
        # gaps of a pause the AUX stream has still to reach: (its first missing AUX index, AUX samples missing)
        self._aux_gaps: list[tuple[int, int]] = []
        self._aux_rows_seen = False  # any AUX row since START (a silent AUX port is said once)
        self._aux_silence_said = False
        self._emg_rows_since_aux = 0
        self._zero_run = np.zeros(tp.N_SENSORS, dtype=np.int64)  # per EMG slot: exact 0.0 rows in a row, up to now
        self._slot_said = np.zeros(tp.N_SENSORS, dtype=bool)  # active slots said empty; inactive ones said carrying
        self._slot_owner: dict[int, int] = {}  # EMG slot -> its active sensor (of the handshake's sensors)
        self._slot_active = np.zeros(tp.N_SENSORS, dtype=bool)
        self._last_data_time = 0.0  # time.monotonic() of the last EMG bytes
        self._last_activity = 0.0  # last EMG bytes, START or reconnection: the stall timer's origin
        self._gap_pending = False
        self._gap_reason = ""  # why the gap being measured began: "connection lost" or the pause's silence
        #: EMG rows received since the gap's data resumed, with their arrival (monotonic, ns), held until it is known
        self._emg_after_gap: list[tuple[np.ndarray, float, int]] = []
        self._rate_at_loss = 0.0  # EMG rate when the link was lost (a server may come back at another)
        self._backoff = config.backoff_initial_s
        self._next_attempt = 0.0
        self._events: list[Event] = []
        self._want_streaming = False

    # ------------------------------------------------------------------------------------------ lifecycle
    def __enter__(self) -> TrignoClient:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def paired_sensors(self) -> list[int]:
        return [s.sensor for s in self.sensors if s.paired]

    @property
    def active_sensors(self) -> list[int]:
        return [s.sensor for s in self.sensors if s.active]

    @property
    def emg_columns(self) -> list[tuple[str, int]]:
        """(label, 0-based slot) of every EMG channel of the active sensors: ``sensorNN.EMG`` for single-channel
        sensors, ``sensorNN.EMGk`` (k = 1..) for multi-channel ones."""
        out = []
        for info in self.sensors:
            if not info.active:
                continue
            slots = info.emg_slots
            for k, slot in enumerate(slots, start=1):
                out.append((f"sensor{info.sensor:02d}.EMG" + (str(k) if len(slots) > 1 else ""), slot))
        return out

    def connect(self) -> None:
        """Open the command port, read the banner, configure and query the server, open the data ports."""
        self._link = self._open_link()
        self.state = ClientState.CONNECTED
        self._emit_status(ClientState.CONNECTED, f"protocol {self.protocol_version}")

    def start(self) -> None:
        """START acquisition (this connection must be master)."""
        self._start_acquisition(self._require_link())
        self._want_streaming = True
        self.state = ClientState.STREAMING
        self._last_activity = time.monotonic()
        self._last_data_time = 0.0  # no EMG yet: its first row is sample 0, however long after START it comes
        self._gap_pending = False  # a gap of an earlier acquisition (stopped while reconnecting) is not this one's
        self.stats.aux_samples_dropped += sum(len(rows) for rows, _, _ in self._aux_after_gap)
        self._aux_after_gap = []
        self._aux_anchor = None
        self._pass_aux_gaps()
        self._emit_status(ClientState.STREAMING, "started")

    def stop(self, *, drain_s: float = 1.0) -> list[Event]:
        """End acquisition the configured way (STOP then QUIT, or QUIT alone) and close the connection.

        Returns the data events not yet polled (status events stay for :meth:`poll`): what was read before, and, after
        STOP, the frames the server had already sent (read until the data ports are quiet for 0.1 s, at most
        ``drain_s``), which closing the sockets would otherwise throw away. Idempotent, and safe after a failed
        :meth:`start` or :meth:`close`: QUIT is sent whenever the command connection is up, even when STOP fails, so
        that the base is always told."""
        self._want_streaming = False
        link = self._link
        already = self.state is ClientState.CLOSED or (link is None and self.state is ClientState.STOPPED)
        try:
            if link is not None:
                self._stop_link(link, drain_s)
        finally:
            self._drop_link()
            self._settle_gap()
        pending: list[Event] = [e for e in self._events if not isinstance(e, StatusEvent)]
        self._events = [e for e in self._events if isinstance(e, StatusEvent)]  # still for poll()
        if not already:  # a second stop(), or one after close(), changes nothing and says nothing
            self.state = ClientState.STOPPED
            self._emit_status(ClientState.STOPPED, "stopped by client")
        return pending

    def _stop_link(self, link: _Link, drain_s: float) -> None:
        """STOP (when acquiring, or when a START went out that may have started the base although it failed), then
        QUIT in a try of its own: a STOP that times out or breaks must not keep the base from being told."""
        acquiring = self.state is ClientState.STREAMING or (link.start_sent and self.state is ClientState.CONNECTED)
        if self.config.stop_mode is tp.StopMode.STOP_THEN_QUIT and acquiring:
            try:
                self._command("STOP", link)
                self._read_until_quiet(link, drain_s)
            except (OSError, ProtocolError) as error:
                self._note_error(f"while stopping (STOP): {error}")
        try:
            link.command.sendall(tp.encode_command("QUIT"))
        except OSError as error:
            self._note_error(f"while stopping (QUIT): {error}")
            return
        try:
            reply = self._read_reply(link, "QUIT")
        except ConnectionResetError:
            return  # the server closes after QUIT: told, even when its reply went to a STOP that timed out
        except (OSError, ProtocolError) as error:
            self._note_error(f"while stopping (QUIT): {error}")
            return
        if tp.is_error(reply):
            self._note_error(f"while stopping: QUIT answered {reply!r}")

    def _read_until_quiet(self, link: _Link, drain_s: float, quiet_s: float = 0.1) -> None:
        """Read the data ports after STOP until nothing comes for ``quiet_s`` (or ``drain_s`` has passed)."""
        ports = [sock for sock in (link.emg, link.aux) if sock is not None and sock.fileno() >= 0]
        if not ports:
            return
        deadline = time.monotonic() + drain_s
        with selectors.DefaultSelector() as selector:
            for sock in ports:
                selector.register(sock, selectors.EVENT_READ)
            while (left := deadline - time.monotonic()) > 0:
                ready = selector.select(min(quiet_s, left))
                if not ready:
                    return
                for key, _ in ready:
                    if key.fileobj is link.emg:
                        self._read_emg(link)
                    else:
                        self._read_aux(link)

    def close(self) -> None:
        """STOP/QUIT as :meth:`stop` does when still connected, then release everything; idempotent."""
        try:
            if self._link is not None:  # also after a stop trigger or a failed start(): QUIT politely
                self.stop()
        finally:
            self._drop_link()
            self.state = ClientState.CLOSED
            self._selector.close()

    # ------------------------------------------------------------------------------------------ commands
    def command(self, text: str) -> str:
        """Send one command and return its reply; ``INVALID COMMAND``/``CANNOT COMPLETE`` raise CommandFailed."""
        self._require_link()
        return self._command(text)

    def _require_link(self) -> _Link:
        if self._link is None:
            raise ProtocolError(f"Trigno client is not connected (state {self.state.value})")
        return self._link

    def _command(self, text: str, link: _Link | None = None, timeout_s: float | None = None) -> str:
        link = link or self._require_link()
        link.command.sendall(tp.encode_command(text))
        reply = self._read_reply(link, text, timeout_s)
        if tp.is_error(reply):
            raise tp.CommandFailed(text, reply)
        return reply

    def _start_acquisition(self, link: _Link) -> None:
        """START; a server still acquiring for an earlier connection (ours before a network drop, or a crashed
        client's) may refuse it, so a refused START is retried once after a STOP.

        The data ports were opened before START, so they may hold an earlier acquisition's samples: what they hold
        when START goes out is dropped (nothing of ours can be in it), and after the STOP of a retry, what comes
        until they are quiet. Only when they were still receiving as START went out (the base was acquiring and
        took our START) is what beat the START's reply dropped too: its tail, which cannot be told from our first
        frame. A base idle before START loses nothing, even one that streams at once."""
        link.start_sent = True
        receiving = self._discard_stale(link)
        try:
            self._command("START", link)
        except tp.CommandFailed:
            try:
                self._command("STOP", link)
            except tp.CommandFailed:  # not stopped (not master?): no end of the stream to wait for
                receiving = self._discard_stale(link)
            else:
                receiving = not self._discard_stale_until_quiet(link)
            self._command("START", link)
        if receiving:
            self._discard_stale(link)

    def _discard_stale(self, link: _Link) -> bool:
        """Drop the whole samples the data sockets hold now (not waiting for more); a partial sample stays in its
        decoder, to keep the alignment of a stream that goes on. True when there was anything."""
        found = False
        for sock, decoder in ((link.emg, self._emg_decoder), (link.aux, self._aux_decoder)):
            while sock is not None and (chunk := self._recv(sock)):
                decoder.feed(chunk)
                self.stats.stale_bytes_discarded += len(chunk)
                found = True
        return found

    def _discard_stale_until_quiet(self, link: _Link, quiet_s: float = 0.1, max_s: float = 1.0) -> bool:
        """After STOP: drop what the data ports receive until nothing has come for ``quiet_s`` (frames the base sent
        just before it stopped are still on their way), at most ``max_s``. True when they went quiet; then a partial
        sample left can never complete and is dropped too."""
        ports = [sock for sock in (link.emg, link.aux) if sock is not None]
        deadline = time.monotonic() + max_s
        with selectors.DefaultSelector() as selector:
            for sock in ports:
                selector.register(sock, selectors.EVENT_READ)
            while (left := deadline - time.monotonic()) > 0:
                if not selector.select(min(quiet_s, left)):
                    if left < quiet_s:
                        break
                    self._emg_decoder.discard_partial()  # its bytes are counted already
                    self._aux_decoder.discard_partial()
                    return True
                self._discard_stale(link)
        return False

    def _set_option(self, link: _Link, command: str, query: str, wanted: bool | tp.Endianness) -> None:
        """Send a setting; a refusal is an error only when the server is not already set that way (some servers
        refuse settings while acquiring, e.g. after a reconnection)."""
        try:
            self._command(command, link)
        except tp.CommandFailed:
            reply = self._query(link, query)
            if reply is None:
                raise
            current = (
                tp.parse_endianness(reply)
                if isinstance(wanted, tp.Endianness)
                else tp.parse_yes_no(reply, command=query)
            )
            if current != wanted:
                raise

    def _read_reply(self, link: _Link, command: str, timeout_s: float | None = None) -> str:
        """The next reply on the command port (within ``timeout_s``, default ``reply_timeout_s``). An unsolicited
        ``STOPPED`` is never taken as the reply: it is the stop trigger (handled at once), except while we STOP/QUIT
        ourselves, where it is the reply only when nothing else arrives shortly after it."""
        timeout_s = self.config.reply_timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout_s
        stopping = command.upper() in ("STOP", "QUIT")
        stopped_seen = False
        while True:
            while link.pending_replies:
                reply = link.pending_replies.pop(0)
                if reply.upper() == tp.UNSOLICITED_STOPPED:
                    if stopping:
                        stopped_seen = True
                        deadline = min(deadline, time.monotonic() + 0.5)
                    else:
                        self._on_stopped()
                    continue
                if link.late_replies:  # one reply per command: this one answers a command that timed out
                    link.late_replies -= 1
                    continue
                return reply
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                if stopped_seen:
                    return tp.UNSOLICITED_STOPPED
                link.late_replies += 1  # so a late reply is not taken as the next command's
                raise tp.NoReply(f"no reply to {command!r} within {timeout_s:g} s")
            self._receive(link, remaining, f"Trigno server closed the command connection (waiting for {command!r})")

    @staticmethod
    def _receive(link: _Link, timeout_s: float, closed_message: str) -> None:
        """Whatever the command port delivers within ``timeout_s``, parsed into pending replies (nothing on timeout)."""
        link.command.settimeout(timeout_s)
        try:
            chunk = link.command.recv(4096)
        except TimeoutError:
            return
        finally:
            link.command.settimeout(None)
        if not chunk:
            raise ConnectionResetError(closed_message)
        link.pending_replies.extend(link.replies.feed(chunk))

    def _query(
        self, link: _Link, text: str, *, informative: bool = False, timeout_s: float | None = None
    ) -> str | None:
        """A query whose failure is tolerated (servers differ in what they support). ``informative``: its answer only
        describes (a sensor's type, slot, channel count), so one the server does not answer in time is taken as
        unanswered too, said, up to :data:`INFORMATIVE_TIMEOUTS` a connection (one slow reply ended the start)."""
        try:
            return self._command(text, link, timeout_s)
        except tp.CommandFailed:
            return None
        except tp.NoReply as error:
            if not informative or link.informative_timeouts >= INFORMATIVE_TIMEOUTS:
                raise
            link.informative_timeouts += 1
            self._note_error(f"{error}: taken as unanswered")
            return None

    # ------------------------------------------------------------------------------------------ handshake
    def _open_link(self) -> _Link:
        cfg = self.config
        command = socket.create_connection((cfg.host, cfg.command_port), timeout=cfg.connect_timeout_s)
        command.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        link = _Link(command=command, emg=None, aux=None)
        try:
            self.protocol_version = tp.parse_banner(self._read_banner(link))
            self._configure(link)
            link.emg = self._open_emg()
            if cfg.aux_port is not None:
                link.aux = self._open_aux(cfg.aux_port)
        except BaseException:
            link.close()
            raise
        return link

    def _read_banner(self, link: _Link) -> str:
        """The greeting, read before anything is sent: normally a line and a blank line, but a banner ending in a
        single CRLF is accepted once nothing more has come for ``banner_line_grace_s``."""
        start = time.monotonic()
        deadline = start + self.config.reply_timeout_s
        while True:
            if link.pending_replies:
                return link.pending_replies.pop(0)
            now = time.monotonic()
            if now - start >= self.config.banner_line_grace_s:
                line = link.replies.take_line()
                if line is not None:
                    return line
            if now >= deadline:
                came = link.replies.pending()
                raise ProtocolError(
                    f"no banner from the Trigno server within {self.config.reply_timeout_s} s ("
                    + (f"received {len(came)} bytes without a line end: {came[:40]!r}" if came else "received nothing")
                    + ")"
                )
            grace_end = start + self.config.banner_line_grace_s
            self._receive(
                link,
                max(0.01, (grace_end if now < grace_end else deadline) - now),
                "Trigno server closed the command connection before its banner",
            )

    def _open_emg(self) -> socket.socket:
        cfg = self.config
        try:
            sock = self._open_data(cfg.emg_port)
            self.emg_port = cfg.emg_port
        except ConnectionRefusedError:
            fallback = cfg.resolved_emg_fallback
            if fallback is None or fallback == cfg.emg_port:
                raise
            sock = self._open_data(fallback)
            self.emg_port = fallback
        return sock

    def _open_aux(self, port: int) -> socket.socket | None:
        """The auxiliary (accelerometer) port, or None when the server refuses it: the EMG is what the session needs
        (the accelerations only check the clocks), so a server or sensors without an AUX stream leave EMG streaming,
        with the reason in :attr:`aux_unavailable`, the stats' last error and a status event."""
        try:
            sock = self._open_data(port)
        except OSError as error:
            self.aux_unavailable = f"AUX port {port} refused ({error}); streaming EMG without accelerations"
            self._note_error(self.aux_unavailable)
            self._emit_status(ClientState.CONNECTED, self.aux_unavailable)
            return None
        self.aux_unavailable = ""
        return sock

    def _open_data(self, port: int) -> socket.socket:
        sock = socket.create_connection((self.config.host, port), timeout=self.config.connect_timeout_s)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        sock.setblocking(False)
        return sock

    def _configure(self, link: _Link) -> None:
        cfg = self.config
        master = self._query(link, "MASTER?")
        if master is not None and not tp.parse_yes_no(master, command="MASTER?"):
            if not cfg.take_master:
                raise ProtocolError("this connection is not the Trigno master and take_master is off")
            answer = self._command("MASTER", link)
            if not tp.is_new_master(answer):
                raise ProtocolError(f"MASTER answered {answer!r}, expected NEW MASTER")
        if cfg.endianness is not None:
            self._set_option(link, f"ENDIAN {cfg.endianness.value}", "ENDIANNESS?", cfg.endianness)
        reply = self._query(link, "ENDIANNESS?")
        self.endianness = tp.parse_endianness(reply) if reply is not None else (cfg.endianness or tp.Endianness.LITTLE)
        if cfg.upsampling is not None:
            self._set_option(link, f"UPSAMPLE {'ON' if cfg.upsampling else 'OFF'}", "UPSAMPLING?", cfg.upsampling)
        reply = self._query(link, "UPSAMPLING?")
        self.upsampling = tp.parse_yes_no(reply, command="UPSAMPLING?") if reply is not None else cfg.upsampling
        interval_reply = self._query(link, "FRAME INTERVAL?")
        interval = tp.parse_float(interval_reply, command="FRAME INTERVAL?") if interval_reply else tp.FRAME_INTERVAL_S
        if not 0.001 <= interval <= 1.0:
            raise ProtocolError(f"FRAME INTERVAL? answered {interval_reply!r}: not a frame interval in seconds")
        trigger = self._query(link, "TRIGGER?", informative=True)
        self.start_trigger = trigger is not None and "START ON" in " ".join(trigger.upper().split())
        self.sensors = self._query_sensors(link)
        self._watch_slots()
        per_frame = self._emg_samples_per_frame(link)
        aux_reply = self._query(link, "MAX SAMPLES AUX?")
        aux_per_frame = tp.parse_int(aux_reply, command="MAX SAMPLES AUX?") if aux_reply else 2
        self._set_rates(per_frame / interval, (aux_per_frame if aux_per_frame > 0 else 2) / interval)
        self._emg_decoder = tp.SampleDecoder(tp.FLOATS_PER_SAMPLE[tp.DataPort.EMG], self.endianness)
        self._aux_decoder = tp.SampleDecoder(cfg.resolved_aux_layout.floats_per_sample, self.endianness)

    def _set_rates(self, rate_hz: float, aux_rate_hz: float) -> None:
        """A server back at another rate (restarted with upsampling switched) goes on counting in the new rate: the
        samples counted so far become the same span of device time at the new rate, so that index / rate stays
        continuous and the gap of the reconnection is reckoned in the new rate."""
        if self.rate_hz > 0 and rate_hz != self.rate_hz:
            self._next_index = int(round(self._next_index * rate_hz / self.rate_hz))
        if self.aux_rate_hz > 0 and aux_rate_hz != self.aux_rate_hz:
            self._next_aux_index = int(round(self._next_aux_index * aux_rate_hz / self.aux_rate_hz))
        self.rate_hz, self.aux_rate_hz = rate_hz, aux_rate_hz

    def _query_sensors(self, link: _Link) -> tuple[SensorInfo, ...]:
        paired: dict[int, str] = {}
        active: set[int] = set()
        starts: dict[int, int] = {}
        channels: dict[int, int] = {}
        for n in range(1, tp.N_SENSORS + 1):
            reply = self._query(link, f"SENSOR {n} PAIRED?")
            if reply is None or not tp.parse_yes_no(reply, command=f"SENSOR {n} PAIRED?"):
                continue
            paired[n] = ""
            # A paired sensor that is not active answers further queries with garbage (trignoclient's experience):
            # ask nothing more of it. A server without ACTIVE? is taken to mean every paired sensor is on.
            reply = self._query(link, f"SENSOR {n} ACTIVE?")
            if reply is not None and not tp.parse_yes_no(reply, command=f"SENSOR {n} ACTIVE?"):
                continue
            active.add(n)
            paired[n] = (self._query(link, f"SENSOR {n} TYPE?", informative=True) or "").strip()
            start_reply = self._query(link, f"SENSOR {n} STARTINDEX?", informative=True)
            if start_reply is not None:
                try:
                    starts[n] = tp.parse_int(start_reply, command=f"SENSOR {n} STARTINDEX?")
                except ProtocolError as error:  # informative only: never a reason to refuse the server
                    self._note_error(str(error))
            count_reply = self._query(link, f"SENSOR {n} EMGCHANNELCOUNT?", informative=True)
            if count_reply is not None:
                try:
                    channels[n] = max(
                        0, min(tp.N_SENSORS, tp.parse_int(count_reply, command=f"SENSOR {n} EMGCHANNELCOUNT?"))
                    )
                except ProtocolError as error:
                    self._note_error(str(error))
        slots = tp.normalise_start_indices(starts, channels=channels)
        return tuple(
            SensorInfo(
                n,
                n in paired,
                paired.get(n, ""),
                slots.get(n, n - 1 if n in paired else -1),
                n in active,
                channels.get(n, 1),
            )
            for n in range(1, tp.N_SENSORS + 1)
        )

    def _emg_samples_per_frame(self, link: _Link) -> int:
        """EMG samples per frame: ``MAX SAMPLES EMG?``; else the most ``SENSOR n CHANNEL 1 SAMPLES?`` of the active
        sensors with EMG (the port carries every sensor at its fastest sensor's count: the first sensor's, a
        Trigno IM's 15 beside Avantis' 26, dated the stream at 1111 Hz instead of 1926); else 27 with upsampling on,
        26 otherwise (the counts a real system reported)."""
        reply = self._query(link, "MAX SAMPLES EMG?")
        if reply is not None:
            return _samples_per_frame("MAX SAMPLES EMG?", reply)
        counts = []
        for sensor in self.sensors:
            if sensor.active and sensor.emg_channels > 0:
                command = f"SENSOR {sensor.sensor} CHANNEL 1 SAMPLES?"
                if (reply := self._query(link, command)) is not None:
                    counts.append(_samples_per_frame(command, reply))
        if counts:
            return max(counts)
        return 27 if self.upsampling else 26

    # ------------------------------------------------------------------------------------------ streaming
    def poll(self, timeout: float = 0.1) -> list[Event]:
        """Wait up to ``timeout`` s for data; return every event since the last call (never raises on I/O loss)."""
        if self.state is ClientState.RECONNECTING:
            self._try_reconnect(timeout)
        elif self._link is not None:
            self._wait_and_read(timeout)
            if self._gap_measured(time.monotonic()):
                self._report_gap()
            stall = self.config.stall_timeout_s
            if (
                stall is not None
                and self.state is ClientState.STREAMING
                and self._link is not None
                and time.monotonic() - self._last_activity > stall
            ):
                self._on_silence(self._link, stall)
        else:
            time.sleep(timeout)
        events, self._events = self._events, []
        return events

    def _wait_and_read(self, timeout: float) -> None:
        link = self._link
        assert link is not None
        self._watch(link)
        ready = self._selector.select(timeout)
        try:
            for key, _ in ready:
                if key.fileobj is not link.command and self.state is ClientState.CONNECTED:
                    self._discard_stale(link)  # no START of ours yet: an earlier acquisition's samples
                elif key.fileobj is link.emg:
                    self._read_emg(link)
                elif key.fileobj is link.aux:
                    self._read_aux(link)
                else:
                    self._read_command(link)
        except (OSError, ProtocolError) as error:
            self._on_connection_lost(str(error) or type(error).__name__)

    def _watch(self, link: _Link) -> None:
        """Keep the selector's registrations the link's open sockets, changed only when they change (a poll per
        frame re-registering every socket cost three epoll calls and their bookkeeping each time)."""
        wanted = {sock for sock in (link.command, link.emg, link.aux) if sock is not None and sock.fileno() >= 0}
        registered = {key.fileobj for key in self._selector.get_map().values()}
        if wanted == registered:
            return
        for sock in registered - wanted:  # closed or replaced: the old object is found by identity
            self._selector.unregister(sock)
        for sock in wanted - registered:
            self._selector.register(sock, selectors.EVENT_READ)

    def _recv(self, sock: socket.socket) -> bytes:
        try:
            chunk = sock.recv(self.config.recv_bytes)
        except BlockingIOError:
            return b""
        if not chunk:
            raise ConnectionResetError("Trigno server closed a data connection")
        return chunk

    def _read_emg(self, link: _Link) -> None:
        assert link.emg is not None  # called only once the handshake opened it, as _read_aux for link.aux
        chunk = self._recv(link.emg)
        if not chunk:
            return
        now = time.monotonic()
        rows = self._emg_decoder.feed(chunk)
        if not len(rows):
            return
        if not self._gap_pending and self.rate_hz > 0 and self._emg_quiet(now):
            rows = self._with_queued_rows(link.emg, rows)  # a reader that was late finds the pause queued here
            if now - len(rows) / self.rate_hz - self._last_data_time >= PAUSE_TOLERANCE_S:
                self._gap_pending = True
                self._gap_reason = f"no EMG data for {now - self._last_data_time:.2f} s"
        self._last_activity = now
        if self.stats.last_error == WAITING_FOR_TRIGGER:  # it fired
            self.stats.last_error = ""
        self._check_aux_silence(link, len(rows))
        self._count_non_finite(rows)
        self._check_slots(rows)
        self.stats.samples_received += len(rows)
        if self._gap_pending:  # held until the backlog of the resumed stream says how long the gap was
            self._emg_after_gap.append((rows, now, time.time_ns()))
            if self._gap_measured(now):
                self._report_gap()
            return
        self._last_data_time = now
        self._emit_emg(rows, time.time_ns())
        self._emg_arrivals.append((self._next_index, now))
        self._release_held_aux()  # held while the EMG was quiet: there was no gap

    def _with_queued_rows(self, sock: socket.socket, rows: np.ndarray, max_reads: int = 64) -> np.ndarray:
        """``rows`` and the whole rows the socket holds already (not waiting for more)."""
        parts = [rows]
        for _ in range(max_reads):
            try:
                chunk = self._recv(sock)
            except OSError:  # closed or broken: the next read says so, after these rows are delivered
                break
            if not chunk:
                break
            parts.append(self._emg_decoder.feed(chunk))
        return np.concatenate([p for p in parts if len(p)]) if len(parts) > 1 else rows

    def _emit_emg(self, rows: np.ndarray, host_time_ns: int) -> None:
        self._events.append(EmgBlock(rows, self._next_index, self.rate_hz, host_time_ns))
        self._next_index += len(rows)

    def _check_aux_silence(self, link: _Link, rows: int) -> None:
        """Say once when the AUX port is open but has sent nothing over AUX_SILENT_S of EMG (sensors whose AUX
        channels are off, a server that does not stream them): without accelerations the EMG clock is mapped by
        arrival times alone."""
        if link.aux is None or self._aux_rows_seen or self._aux_silence_said or self.rate_hz <= 0:
            return
        self._emg_rows_since_aux += rows
        if self._emg_rows_since_aux > AUX_SILENT_S * self.rate_hz:
            self._aux_silence_said = True  # a condition, not an error of the link: said, not counted
            self.stats.last_error = (
                f"the AUX port {self.config.aux_port} is connected but sent nothing in {AUX_SILENT_S:g} s of EMG: no "
                "accelerations (the EMG clock is mapped by arrival times)"
            )
            log.warning("%s", self.stats.last_error)

    def _read_aux(self, link: _Link) -> None:
        assert link.aux is not None
        chunk = self._recv(link.aux)
        rows = self._aux_decoder.feed(chunk) if chunk else np.empty((0, 0))
        self._count_non_finite(rows)
        self._aux_rows_seen = self._aux_rows_seen or bool(len(rows))
        # placed on the EMG clock once the EMG says how long the gap was (or, silent for now, whether there is one)
        quiet = self.state is ClientState.STREAMING and self._emg_quiet(time.monotonic())
        if len(rows) and (self._gap_pending or quiet):
            self._aux_after_gap.append((rows, time.time_ns(), time.monotonic()))
            held = sum(len(r) for r, _, _ in self._aux_after_gap)
            if self.aux_rate_hz > 0 and held > AUX_HOLD_S * self.aux_rate_hz:  # the EMG is not coming back soon
                dropped = len(self._aux_after_gap.pop(0)[0])
                self.stats.aux_samples_dropped += dropped
                self._note_error(
                    f"{self.stats.aux_samples_dropped} AUX samples dropped: the EMG stream has not resumed for "
                    f"{AUX_HOLD_S:g} s to place them on its clock"
                )
        elif len(rows):
            now = time.monotonic()
            if self._aux_anchor is not None:
                self._place_aux_after_loss([(len(rows), now)])
            self._emit_aux(rows, time.time_ns())
            self._measure_aux_lag(now)

    def _measure_aux_lag(self, now: float) -> None:
        """One sample of the AUX port's lag behind the EMG port: this AUX read's arrival minus the arrival of the EMG
        read that first reached the same instant (none yet: the AUX is not behind; left out)."""
        if self.rate_hz <= 0 or self.aux_rate_hz <= 0:
            return
        instant = self._next_aux_index * self.rate_hz / self.aux_rate_hz  # in EMG samples
        reached = None
        for end, arrived in reversed(self._emg_arrivals):  # the matching read is among the last few
            if end < instant:
                break
            reached = arrived
        if reached is not None and self._emg_arrivals[0][0] < instant:  # the first read to reach it is still kept
            self._aux_lags.append(now - reached)

    def _place_aux_after_loss(self, reads: list[tuple[int, float]]) -> None:
        """After a lost link the base may have gone on acquiring: the first AUX rows received then were measured
        (their arrival, less the reads' rows, less the port's lag measured before) at an instant the EMG's resumed
        first row (measured at its own arrival estimate) puts on the EMG index. Anchoring the AUX on the EMG's index
        at the moment of the gap instead put it a frame late with 5 ms of lag, eight frames with 0.1 s (an
        independent imitation whose AUX frames leave after their EMG frames)."""
        assert self._aux_anchor is not None  # set by _report_gap before any call
        first_index, emg_measured = self._aux_anchor
        self._aux_anchor = None
        lag = float(np.median(self._aux_lags)) if self._aux_lags else 0.0
        aux_measured = _first_measured(reads, self.aux_rate_hz) - lag
        anchor = int(
            round(first_index * self.aux_rate_hz / self.rate_hz + (aux_measured - emg_measured) * self.aux_rate_hz)
        )
        self._next_aux_index = max(self._next_aux_index, anchor)

    def _watch_slots(self) -> None:
        """The EMG slots of the handshake's active sensors, whose conditions :meth:`_check_slots` judges afresh."""
        self._slot_owner = {slot: s.sensor for s in self.sensors if s.active for slot in s.emg_slots}
        self._slot_active = np.isin(np.arange(tp.N_SENSORS), list(self._slot_owner))
        self._slot_said[:], self._zero_run[:] = False, 0

    def _check_slots(self, rows: np.ndarray) -> None:
        """Say (once each, in last_error: a condition, not counted) an active sensor's slot that has become exactly 0.0
        for :data:`EMPTY_SLOT_S` (unpaired or switched off while streaming) and when it sends again, and a slot that
        carries data though no active sensor had it at the handshake (paired while streaming: read after a restart).
        Vectorised over the slots: a read that changes nothing runs no Python loop."""
        if self.rate_hz <= 0 or rows.ndim != 2 or rows.shape[1] != tp.N_SENSORS:
            return
        carries = rows.any(axis=0)  # NaN counts as data
        run = self._zero_run  # reads wholly 0.0 in a row, in rows (a read's trailing zeros are not counted: < a read)
        run += len(rows)
        run[carries] = 0
        active, said = self._slot_active, self._slot_said
        # what is said is what is so: active slots carry data, inactive ones do not (~4 us a read when nothing changed)
        if np.array_equal(carries, active ^ said) and not (run[active & ~said] >= EMPTY_SLOT_S * self.rate_hz).any():
            return
        empty = run >= EMPTY_SLOT_S * self.rate_hz
        changed = np.flatnonzero((active & empty & ~said) | (active & said & carries) | (~active & carries & ~said))
        if not changed.size:  # an active slot at 0.0 for less than EMPTY_SLOT_S so far
            return
        said[changed] = ~said[changed]
        conditions = []  # every slot's condition now, in one line (one slot's would hide another's)
        for slot in np.flatnonzero(said):
            sensor = self._slot_owner.get(int(slot))
            conditions.append(
                f"EMG slot {slot + 1} carries data though no active sensor had it at the start (a sensor paired or "
                "switched on while streaming): not published until the acquisition is restarted"
                if sensor is None
                else f"sensor {sensor} (EMG slot {slot + 1}) sends exactly 0.0 for {EMPTY_SLOT_S:g} s and more: the "
                "base empties the slot of a sensor unpaired or switched off"
            )
        back = [self._slot_owner[int(k)] for k in changed if not said[k] and int(k) in self._slot_owner]
        conditions += [f"sensor {sensor} sends again" for sensor in back]
        self.stats.last_error = "; ".join(conditions)
        log.warning("%s", self.stats.last_error)

    def _count_non_finite(self, rows: np.ndarray) -> None:
        """NaN/Inf from the base are passed on as they came (they are what it sent) and counted (``stats``)."""
        if rows.size and not np.isfinite(rows).all():
            self.stats.non_finite_values += int(rows.size - np.count_nonzero(np.isfinite(rows)))

    def _emit_aux(self, rows: np.ndarray, host_time_ns: int) -> None:
        """AUX rows on the next AUX index; a pause's gap the rows reach is jumped where it starts, so that the rows
        measured before it (late behind the EMG) keep their indices and those after it are placed after it."""
        while self._aux_gaps and self._next_aux_index + len(rows) > self._aux_gaps[0][0]:
            start, missing = self._aux_gaps.pop(0)
            before = max(0, start - self._next_aux_index)
            if before:
                self._events.append(AuxBlock(rows[:before], self._next_aux_index, self.aux_rate_hz, host_time_ns))
                self._next_aux_index += before
                rows = rows[before:]
            self._next_aux_index += missing
        if len(rows):
            self._events.append(AuxBlock(rows, self._next_aux_index, self.aux_rate_hz, host_time_ns))
            self._next_aux_index += len(rows)

    def _pass_aux_gaps(self) -> None:
        """The pauses' gaps the AUX stream never reached (its rows before them lost with a link, or a new START):
        its index jumps past them, so that it stays on the EMG's."""
        for start, missing in self._aux_gaps:
            self._next_aux_index = max(self._next_aux_index, start) + missing
        self._aux_gaps = []

    def _read_command(self, link: _Link) -> None:
        chunk = link.command.recv(4096)
        if not chunk:
            raise ConnectionResetError("Trigno server closed the command connection")
        for reply in link.replies.feed(chunk):
            if reply.upper() == tp.UNSOLICITED_STOPPED:
                self._on_stopped()
            elif link.late_replies:
                link.late_replies -= 1
            else:
                self._note_error(f"unexpected reply {reply!r} on the command port")

    def _on_silence(self, link: _Link, stall_s: float) -> None:
        """No EMG for ``stall_s`` while streaming: the base's start trigger not fired yet (said once, waited for),
        another client that took the base over and stopped it (its command port answers that we are no longer master:
        the end of our acquisition, not a fault), else a lost link (a pulled cable sends neither FIN nor RST)."""
        if self.start_trigger and self._last_data_time == 0.0:  # nothing since START, also after a reconnection
            if self.stats.last_error != WAITING_FOR_TRIGGER:
                self.stats.last_error = WAITING_FOR_TRIGGER  # a condition, not an error: said, not counted
                self._emit_status(ClientState.STREAMING, WAITING_FOR_TRIGGER)
            self._last_activity = time.monotonic()
            return
        try:
            master = self._query(link, "MASTER?", timeout_s=MASTER_PROBE_S)  # a pulled cable: not 3 s more
            still_master = None if master is None else tp.parse_yes_no(master, command="MASTER?")
        except (OSError, ProtocolError):  # no answer either: the link is gone
            master, still_master = None, None
        if still_master is False:
            self._on_stopped(TAKEN_OVER)
        elif master is not None:  # restarted like a lost link, but said as what it is
            self._on_connection_lost(
                f"no EMG data for {stall_s:g} s though the base answers on its command port (acquisition stopped "
                "at the base or its utility, the base station unplugged, or its data path stuck)"
            )
        else:
            self._on_connection_lost(f"no EMG data for {stall_s:g} s")

    def _on_stopped(self, why: str = STOPPED_BY_SERVER) -> None:
        """The base stopped acquiring (its stop trigger fired; another client took it over): acquisition is over,
        not a fault (no reconnection)."""
        if self._link is not None:
            self._drain(self._link)  # frames sent before STOPPED are already here: deliver them first
        self._settle_gap()
        self._want_streaming = False
        self.state = ClientState.STOPPED
        self.stats.last_error = why  # the status carries it: not a link error, but why the data ended
        self._emit_status(ClientState.STOPPED, why)

    def _report_gap(self) -> None:
        """The gap before the held EMG: its first row was measured at the earliest of (arrival - rows received up to
        then / rate) over the held reads (a burst of backlog arrives at once, later rows at the pace they are
        measured), and the last row before the gap when it arrived."""
        held, self._emg_after_gap = self._emg_after_gap, []
        first_measured = _first_measured([(len(rows), arrived) for rows, arrived, _ in held], self.rate_hz)
        # before any EMG since START the first row is sample 0: nothing was received to count a gap from
        since = self._last_data_time or first_measured
        missing = max(0, int(round((first_measured - since) * self.rate_hz)))
        pause = self._gap_reason != "connection lost"
        if pause and missing < PAUSE_TOLERANCE_S * self.rate_hz:
            missing = 0  # a buffered pause: arrival jitter, not samples lost
        self._gap_pending = False
        if missing or not pause:
            reason = (
                f"{self._gap_reason}: the base resumed without what it measured meanwhile"
                if pause
                else "connection lost"
            )
            self._events.append(GapEvent(self._next_index, missing, time.time_ns(), reason))
            if pause:
                self._note_error(f"{missing} EMG samples lost ({reason})")
        first_missing = self._next_index
        self._next_index += missing
        self.stats.samples_lost += missing
        # the AUX stream's sample index jumps over the same gap, so that AUX sample k stays measured at EMG device time
        # k / aux rate (the accelerometers on the EMG clock). After a pause, where the AUX stream reaches it: AUX may
        # come behind the EMG, and its rows measured before the pause still arrive after the EMG resumed (0.3 s behind
        # an imitated base: every later AUX row was placed 46 samples late). After a lost link, at once: its rows
        # before the gap came before the link closed or never will (the loss's _settle_gap passed the pending gaps).
        if self.aux_rate_hz > 0 and self.rate_hz > 0:
            ratio = self.aux_rate_hz / self.rate_hz
            if pause:
                if missing:
                    self._aux_gaps.append((int(round(first_missing * ratio)), int(round(missing * ratio))))
            else:  # placed by when its first rows were measured: now from those held, else from the next AUX read
                self._aux_anchor = (self._next_index, first_measured)
                if self._aux_after_gap:
                    self._place_aux_after_loss([(len(rows), arrived) for rows, _, arrived in self._aux_after_gap])
        for rows, _, host_time_ns in held:
            self._emit_emg(rows, host_time_ns)
        self._last_data_time = held[-1][1]
        self._release_held_aux()

    def _release_held_aux(self) -> None:
        """Emit the AUX rows held until the EMG said whether (and how long) there was a gap, on the index it left."""
        for rows, host_time_ns, _ in self._aux_after_gap:
            self._emit_aux(rows, host_time_ns)
        self._aux_after_gap = []

    def _gap_measured(self, now: float) -> bool:
        """The backlog of the EMG held for a gap is known: it has been received for :data:`RESUME_WINDOW_S` and the
        estimate of when its first row was measured has stopped moving earlier for as long (a sender catching up
        faster than real time moves it with every read), or it has been held :data:`MAX_RESUME_HOLD_S`."""
        held = self._emg_after_gap
        if not held or now - held[0][1] < RESUME_WINDOW_S:
            return False
        # a re-START after a lost link has no backlog to drain (and a sender at another pace than the rate, a
        # simulator at speed 2, would move the estimate until the cap)
        if self._gap_reason == "connection lost" or now - held[0][1] >= MAX_RESUME_HOLD_S or self.rate_hz <= 0:
            return True
        arrivals = np.array([arrived for _, arrived, _ in held])
        earliest = np.minimum.accumulate(arrivals - np.cumsum([len(r) for r, _, _ in held]) / self.rate_hz)
        before = int(np.searchsorted(arrivals, now - RESUME_WINDOW_S, side="right")) - 1  # >= 0: the first read is
        return bool(earliest[before] - earliest[-1] <= CATCH_UP_STEP_S)  # not moved over the last window

    def _emg_quiet(self, now: float) -> bool:
        """The EMG has been silent long enough on a live stream that its return will be checked for a gap."""
        return bool(self._last_data_time) and now - self._last_data_time > PAUSE_CHECK_S

    def _settle_gap(self) -> None:
        """The data end (a stop, STOPPED, a lost link): the EMG held for a gap's measurement placed now, with what has
        arrived of its backlog; the AUX rows held while the EMG was quiet (measured before the end: behind the EMG,
        they were put after the reconnection's gap, or lost at a stop) placed after it; and the pauses' gaps the AUX
        stream never reached passed, in the AUX rate they were measured in (a reconnection may bring another)."""
        if self._emg_after_gap:
            self._report_gap()
        self._release_held_aux()
        self._pass_aux_gaps()

    # ------------------------------------------------------------------------------------------ reconnection
    def _drain(self, link: _Link) -> None:
        """Deliver every byte the kernel already holds for the data sockets before they are closed."""
        for sock, reader in ((link.emg, self._read_emg), (link.aux, self._read_aux)):
            if sock is None:
                continue
            for _ in range(1024):
                try:
                    pending = sock.recv(self.config.recv_bytes, socket.MSG_PEEK)
                except OSError:
                    break
                if not pending:
                    break
                reader(link)

    def _on_connection_lost(self, reason: str) -> None:
        self._note_error(f"connection lost: {reason}")
        if self._link is not None:
            self._drain(self._link)
        self._settle_gap()
        self.stats.bytes_discarded += self._emg_decoder.discard_partial() + self._aux_decoder.discard_partial()
        self._drop_link()
        if not self.config.reconnect:
            self.state = ClientState.CLOSED
            self._emit_status(ClientState.CLOSED, f"connection lost: {reason}")
            return
        self.state = ClientState.RECONNECTING
        self._rate_at_loss = self.rate_hz
        self._gap_pending, self._gap_reason = self._want_streaming, "connection lost"
        self._backoff = self.config.backoff_initial_s
        self._next_attempt = time.monotonic() + self._backoff
        self._emit_status(ClientState.RECONNECTING, f"connection lost: {reason}")

    def _try_reconnect(self, timeout: float) -> None:
        delay = self._next_attempt - time.monotonic()
        if delay > 0:
            time.sleep(min(delay, timeout))
            return
        try:
            self._link = self._open_link()
            if self._want_streaming:
                self._start_acquisition(self._link)
        except (OSError, ProtocolError) as error:
            self._drop_link()
            self._backoff = min(self._backoff * 2, self.config.backoff_max_s)
            self._next_attempt = time.monotonic() + self._backoff
            self.stats.last_error = f"reconnect failed: {error}"
            return
        self.stats.reconnects += 1
        if self.stats.last_error.startswith("reconnect failed"):  # that is over now
            self.stats.last_error = ""
        self._last_activity = time.monotonic()
        self.state = ClientState.STREAMING if self._want_streaming else ClientState.CONNECTED
        was = self._rate_at_loss
        changed = f"; EMG rate now {self.rate_hz:.3f} Hz, was {was:.3f}" if was and self.rate_hz != was else ""
        self._emit_status(self.state, f"reconnected (protocol {self.protocol_version}{changed})")

    def _drop_link(self) -> None:
        if self._link is not None:
            self._link.close()
            self._link = None

    # ------------------------------------------------------------------------------------------ bookkeeping
    def _note_error(self, text: str) -> None:
        self.stats.errors += 1
        self.stats.last_error = text

    def _emit_status(self, state: ClientState, detail: str) -> None:
        self._events.append(StatusEvent(state, detail, time.time_ns()))

    @property
    def connected(self) -> bool:
        return self._link is not None
