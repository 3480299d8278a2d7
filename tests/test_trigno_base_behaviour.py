"""Trigno client fixes found by QA with an independent server imitation: device time across a reconnection to a
server at another rate, samples of an earlier acquisition never published as ours, QUIT sent even when STOP or
START fail, STARTINDEX base of multi-channel sensors, non-finite values counted. Real TCP sockets on 127.0.0.1."""

from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest

from drivers.trigno import protocol as tp
from drivers.trigno.client import ClientState, EmgBlock, GapEvent, StatusEvent, TrignoClient, TrignoConfig
from drivers.trigno.simulator import SimulatorConfig, TrignoSimulator
from drivers.trigno.source import synthetic_source
from msk_core.errors import ProtocolError
from tests.test_driver_conformance_trigno import LoopbackServer

TERM = b"\r\n\r\n"
SPF = 27  # EMG samples per frame: 2000 Hz
GEN = 2**20  # EMG slot 0 of sample i of the base's acquisition g holds g * GEN + i (exact in float32)


class ScriptedBase(LoopbackServer):
    """A Trigno base whose acquisitions can be told apart: each START begins acquisition g (1, 2, ...) and EMG slot 0
    of its sample i is g * GEN + i. Behaviours the tests script: already acquiring before any client (``prestream``),
    START refused while acquiring, a last frame of the stopped acquisition ``late_frame_s`` after the STOP reply,
    frame 0 sent before the START reply, replies never sent (``silent``) or late (``delays``), NaN/Inf samples."""

    def __init__(
        self,
        *,
        answers: dict[str, str] | None = None,
        prestream: bool = False,
        refuse_start_while_acquiring: bool = False,
        start_delay_s: float = 0.0,
        frame_before_start_reply: bool = False,
        late_frame_s: float | None = None,
        silent: tuple[str, ...] = (),
        delays: dict[str, float] | None = None,
        specials: bool = False,
    ) -> None:
        self.answers = {"MASTER?": "YES", "MAX SAMPLES EMG?": str(SPF), "SENSOR 1 PAIRED?": "YES", **(answers or {})}
        self.refuse = refuse_start_while_acquiring
        self.start_delay_s = start_delay_s
        self.frame_before_start_reply = frame_before_start_reply
        self.late_frame_s = late_frame_s
        self.silent = silent
        self.delays = delays or {}
        self.specials = specials
        self.commands: list[str] = []
        self.acquiring = False
        self._gen = 0
        self._index = 0
        self._due = 0.0
        self._late: tuple[float, int, int] | None = None  # (when, acquisition, first index) of a frame after STOP
        self._lock = threading.Lock()
        self._emg: list[socket.socket] = []
        self._conns: list[socket.socket] = []
        self._listen(("command", "emg"), 0.05, extra=(self._stream,))
        if prestream:  # an earlier client's acquisition, under way for a while
            self._begin(0.0)
        self._start()

    def _connections(self) -> list[socket.socket]:
        return [*self._emg, *self._conns]

    @property
    def emg_connections(self) -> int:
        with self._lock:
            return len(self._emg)

    def wait_for(self, command: str, seconds: float = 3.0) -> None:
        deadline = time.monotonic() + seconds
        while command not in self.commands and time.monotonic() < deadline:
            time.sleep(0.01)

    def _accept(self, name: str) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._listeners[name].accept()
            except (TimeoutError, OSError):
                continue
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                (self._conns if name == "command" else self._emg).append(conn)
            if name == "command":
                threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        conn.sendall(b"Delsys Trigno System Digital Protocol Version 3.6.0" + TERM)
        buffer = b""
        while not self._stop.is_set():
            try:
                chunk = conn.recv(1024)
            except OSError:
                return
            if not chunk:
                return
            buffer += chunk
            while TERM in buffer:
                packet, buffer = buffer.split(TERM, 1)
                for command in [c.strip() for c in packet.decode("ascii").split("\r\n") if c.strip()]:
                    reply = self._answer(command)
                    time.sleep(self.delays.get(command, 0.0))
                    if command not in self.silent:
                        conn.sendall(reply.encode("ascii") + TERM)
                    if command == "QUIT":
                        conn.close()
                        return

    def _answer(self, command: str) -> str:
        self.commands.append(command)
        with self._lock:
            if command == "START":
                if self.acquiring and self.refuse:
                    return "CANNOT COMPLETE"
                self._begin(self.start_delay_s)
                if self.frame_before_start_reply:
                    self._send_frame(self._gen, 0)
                    self._index, self._due = SPF, time.monotonic() + tp.FRAME_INTERVAL_S
                return "OK"
            if command == "STOP":
                if self.acquiring and self.late_frame_s is not None:
                    self._late = (time.monotonic() + self.late_frame_s, self._gen, self._index)
                self.acquiring = False
                return "OK"
        if command == "QUIT":
            return "OK"  # QUIT alone does not stop this base: only STOP does
        return self.answers.get(command, "INVALID COMMAND")

    def _begin(self, delay_s: float) -> None:
        self._gen += 1
        self._index = 0
        self._due = time.monotonic() + delay_s
        self.acquiring = True

    def _stream(self) -> None:
        while not self._stop.wait(0.002):
            with self._lock:
                now = time.monotonic()
                if self._late is not None and now >= self._late[0]:
                    self._send_frame(self._late[1], self._late[2])
                    self._late = None
                if self.acquiring and now >= self._due:
                    self._send_frame(self._gen, self._index)
                    self._index += SPF
                    self._due += tp.FRAME_INTERVAL_S

    def _send_frame(self, gen: int, first: int) -> None:
        rows = np.zeros((SPF, 16), np.float32)
        rows[:, 0] = gen * GEN + first + np.arange(SPF)
        if self.specials and first == 0:
            rows[3, 5], rows[4, 5], rows[4, 6] = np.nan, np.inf, -np.inf
        for sock in list(self._emg):
            try:
                sock.sendall(tp.encode_samples(rows))
            except OSError:
                self._emg.remove(sock)


@pytest.fixture
def scripted():
    """``scripted(client_options, **base_options)``: a ScriptedBase and a client connected to it, once the base has
    accepted the client's EMG socket (so that it gets frame 0); both closed at teardown whatever happened."""
    made: list = []

    def make(client_options: dict | None = None, **options) -> tuple[ScriptedBase, TrignoClient]:
        base = ScriptedBase(**options)
        made.append(base)
        config = TrignoConfig(command_port=base.ports["command"], emg_port=base.ports["emg"], **(client_options or {}))
        client = TrignoClient(config)
        made.append(client)
        client.connect()
        deadline = time.monotonic() + 3.0
        while not base.emg_connections and time.monotonic() < deadline:
            time.sleep(0.005)
        return base, client

    yield make
    for thing in reversed(made):
        thing.close()


def collect(client: TrignoClient, *, samples: int, seconds: float = 5.0) -> list:
    events: list = []
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and sum(len(e.samples) for e in events if isinstance(e, EmgBlock)) < samples:
        events += client.poll(0.02)
    return events


def emg(events: list) -> np.ndarray:
    blocks = [e.samples for e in events if isinstance(e, EmgBlock)]
    return np.concatenate(blocks) if blocks else np.empty((0, 16), np.float32)


# ------------------------------------------------------------------------------------ 1. rate across a reconnection


def test_device_time_stays_continuous_when_the_server_comes_back_at_another_rate():
    """The base is restarted with upsampling on (1925.926 Hz -> 2000 Hz) while we stream: the samples counted so far
    become the same device time at the new rate, and the gap is counted at the new rate."""
    source = synthetic_source(seconds=20.0, seed=3)
    ephemeral = dict(command_port=0, emg_port=0, legacy_emg_port=None, aux_port=None)
    sim = TrignoSimulator(source, SimulatorConfig(**ephemeral, speed=2.0, upsampling=False)).start()
    ports = dict(sim.ports)
    client = TrignoClient(
        TrignoConfig(command_port=ports["command"], emg_port=ports["emg"], backoff_initial_s=0.02, backoff_max_s=0.2)
    )
    try:
        client.connect()
        old_rate = client.rate_hz
        assert old_rate == pytest.approx(26 / tp.FRAME_INTERVAL_S)
        client.start()
        before = collect(client, samples=1500, seconds=10)
        sim.kill()
        down = []
        deadline = time.monotonic() + 0.4
        while time.monotonic() < deadline:
            down += client.poll(0.02)
        restarted = dict(ephemeral, command_port=ports["command"], emg_port=ports["emg"])
        sim = TrignoSimulator(source, SimulatorConfig(**restarted, speed=2.0, upsampling=True)).start()
        after = collect(client, samples=500, seconds=10)
    finally:
        client.close()
        sim.close()
    events = before + down + after
    gap = next(e for e in events if isinstance(e, GapEvent))
    lost_at = next(
        i for i, e in enumerate(events) if isinstance(e, StatusEvent) and e.state is ClientState.RECONNECTING
    )
    end_before = len(emg(events[:lost_at]))
    assert end_before >= 1500
    new_rate = 27 / tp.FRAME_INTERVAL_S
    # the first missing sample is measured when the last received one ended: the same device time in either rate
    assert abs(gap.first_missing_index / new_rate - end_before / old_rate) <= 0.5 / new_rate
    first_after = next(e for e in events if isinstance(e, EmgBlock) and e.rate_hz != old_rate)
    assert first_after.rate_hz == pytest.approx(new_rate)
    assert first_after.first_sample_index == gap.first_missing_index + gap.n_missing
    assert client.stats.samples_lost == gap.n_missing > 0
    reconnected = [e.detail for e in events if isinstance(e, StatusEvent) and "reconnected" in e.detail]
    assert reconnected and "EMG rate now 2000.000 Hz" in reconnected[0]


# ------------------------------------------------------------------------------------ 2. stale data before START


def test_an_acquisition_still_running_before_start_is_never_published_as_ours(scripted):
    """QA's p2: a crashed client left the base acquiring. Its samples fill our data socket between connect() and
    start(); START is refused, STOP, a last old frame arrives after the STOP reply, START: our first sample is the
    new acquisition's sample 0."""
    base, client = scripted(prestream=True, refuse_start_while_acquiring=True, start_delay_s=0.2, late_frame_s=0.02)
    time.sleep(0.3)  # another device being opened meanwhile: ~20 frames of the old acquisition arrive
    client.start()
    rows = emg(collect(client, samples=300))
    assert base.commands.count("START") == 2 and "STOP" in base.commands
    assert len(rows) >= 300
    first = int(rows[0, 0])
    assert first == 2 * GEN, f"first sample published: acquisition {first // GEN} sample {first % GEN}"
    assert np.array_equal(rows[:, 0], 2 * GEN + np.arange(len(rows), dtype=np.float32))
    assert client.stats.stale_bytes_discarded >= 10 * SPF * 64


def test_samples_before_start_are_dropped_even_when_polled_and_when_the_base_takes_start_while_acquiring(scripted):
    """The base accepts START while acquiring and begins a new acquisition: nothing polled before start() and
    nothing left over from the old acquisition is published."""
    _, client = scripted(prestream=True, start_delay_s=0.1)
    early = []
    deadline = time.monotonic() + 0.3
    while time.monotonic() < deadline:
        early += client.poll(0.02)
    assert not [e for e in early if isinstance(e, EmgBlock)]
    client.start()
    events = collect(client, samples=200)
    rows = emg(events)
    assert rows[0, 0] == 2 * GEN and next(e for e in events if isinstance(e, EmgBlock)).first_sample_index == 0
    assert np.array_equal(rows[:, 0], 2 * GEN + np.arange(len(rows), dtype=np.float32))


def test_an_idle_base_that_streams_at_once_loses_nothing(scripted):
    """Frame 0 sent even before the START reply: with nothing on the data ports before START, none of it is ours
    to drop."""
    _, client = scripted(frame_before_start_reply=True)
    client.start()
    rows = emg(collect(client, samples=100))
    assert np.array_equal(rows[:, 0], GEN + np.arange(len(rows), dtype=np.float32))
    assert client.stats.stale_bytes_discarded == 0


# ------------------------------------------------------------------------------------ 3. QUIT always sent


def test_quit_is_sent_when_stop_gets_no_reply(scripted):
    base, client = scripted({"reply_timeout_s": 0.3}, silent=("STOP",))
    client.start()
    collect(client, samples=50)
    client.stop()
    base.wait_for("QUIT")
    assert base.commands[-2:] == ["STOP", "QUIT"]
    assert client.state is ClientState.STOPPED and not client.connected
    # the one error is STOP's: the server closing the connection after QUIT is QUIT done
    assert client.stats.errors == 1 and "no reply to 'STOP'" in client.stats.last_error


def test_close_after_a_failed_start_stops_the_base_and_quits(scripted):
    """START's reply comes too late: start() fails, but the base did start. close() (what a caller's finally does)
    sends STOP and QUIT, so the base is not left acquiring."""
    base, client = scripted({"reply_timeout_s": 0.5}, delays={"START": 0.7})
    with pytest.raises(ProtocolError, match="no reply to 'START'"):
        client.start()
    client.close()
    base.wait_for("QUIT")
    assert base.commands[-3:] == ["START", "STOP", "QUIT"] and not base.acquiring


def test_stop_and_close_are_idempotent(scripted):
    base, client = scripted()
    client.start()
    collect(client, samples=30)
    client.stop()
    client.stop()
    client.close()
    client.close()
    assert client.stop() == [] and client.state is ClientState.CLOSED
    stopped = [e for e in client.poll(0.01) if isinstance(e, StatusEvent) and e.state is ClientState.STOPPED]
    assert len(stopped) == 1 and base.commands.count("QUIT") == 1


# ------------------------------------------------------------------------------------ 4. STARTINDEX base


@pytest.mark.parametrize("base", [0, 1])
def test_start_index_base_of_multi_channel_sensors(base):
    # a 2-channel sensor 2 in its own slot (0-based 1) pushes sensor 3 to slot 3
    assert tp.normalise_start_indices({2: 1 + base, 3: 3 + base}, channels={2: 2, 3: 1}) == {2: 1, 3: 3}
    # a 4-channel sensor 1 pushes sensors 2 and 3 to slots 4 and 5
    assert tp.normalise_start_indices({1: base, 2: 4 + base, 3: 5 + base}, channels={1: 4}) == {1: 0, 2: 4, 3: 5}
    # a 2-channel sensor in the last slots: its second channel must fit in the port
    assert tp.normalise_start_indices({15: 14 + base}, channels={15: 2}) == {15: 14}


@pytest.mark.parametrize("start_base", [0, 1])
def test_multi_channel_sensor_columns_over_tcp_in_either_base(scripted, start_base):
    """QA's s8: sensor 2 with 2 EMG channels starting in slot 1 (0-based), sensor 3 in slot 3."""
    answers = {"SENSOR 1 PAIRED?": "NO", "SENSOR 2 PAIRED?": "YES", "SENSOR 3 PAIRED?": "YES"}
    answers |= {"SENSOR 2 EMGCHANNELCOUNT?": "2", "SENSOR 3 EMGCHANNELCOUNT?": "1"}
    answers |= {"SENSOR 2 STARTINDEX?": str(1 + start_base), "SENSOR 3 STARTINDEX?": str(3 + start_base)}
    _, client = scripted(answers=answers)
    assert client.emg_columns == [("sensor02.EMG1", 1), ("sensor02.EMG2", 2), ("sensor03.EMG", 3)]


# ------------------------------------------------------------------------------------ 5. non-finite values


def test_non_finite_values_are_counted_and_passed_on_unchanged(scripted):
    _, client = scripted(specials=True)
    client.start()
    rows = emg(collect(client, samples=SPF))
    assert np.isnan(rows[3, 5]) and rows[4, 5] == np.inf and rows[4, 6] == -np.inf
    assert client.stats.non_finite_values == 3


# ------------------------------------------------------------------------------------ found by the second imitation


def test_a_late_reply_to_an_informative_query_is_taken_as_unanswered_not_the_end_of_the_start(scripted):
    """One reply to `SENSOR 1 TYPE?` 0.6 s late (the client waits 0.4 s) ended `msk drivers` at start-up. An
    informative query (type, slot, channel count) that times out is now said and taken as unanswered; its late reply
    is not taken as the next command's; the stream starts and its samples are the base's."""
    base, client = scripted(
        {"reply_timeout_s": 0.4},
        answers={"SENSOR 1 TYPE?": "O", "SENSOR 1 STARTINDEX?": "1"},
        delays={"SENSOR 1 TYPE?": 0.6},
    )
    assert "no reply to 'SENSOR 1 TYPE?' within 0.4 s: taken as unanswered" in client.stats.last_error
    assert client.sensors[0].type_code == "" and client.sensors[0].start_index == 0  # STARTINDEX? got its own reply
    client.start()
    samples = emg(collect(client, samples=100))[:, 0]
    assert len(samples) >= 100 and np.array_equal(samples, GEN + np.arange(len(samples)))


def test_a_query_that_decides_how_samples_are_read_still_fails_when_unanswered(scripted):
    """Only informative queries are forgiven: a sensor whose pairing the base does not say in time is not guessed."""
    with pytest.raises(ProtocolError, match="no reply to 'SENSOR 1 PAIRED\\?'"):
        scripted({"reply_timeout_s": 0.3}, silent=("SENSOR 1 PAIRED?",))


def test_without_max_samples_the_rate_is_the_fastest_sensors(scripted):
    """`MAX SAMPLES EMG?` refused and a Trigno IM (15 samples a frame) in slot 1 beside an Avanti (27): the client took
    the first sensor's count and dated a 2000 Hz stream at 1111 Hz (9.6 s of device time in 5.5 s)."""
    base, client = scripted(
        answers={
            "MAX SAMPLES EMG?": "CANNOT COMPLETE",
            "SENSOR 2 PAIRED?": "YES",
            "SENSOR 1 CHANNEL 1 SAMPLES?": "15",
            "SENSOR 2 CHANNEL 1 SAMPLES?": str(SPF),
        }
    )
    assert client.rate_hz == pytest.approx(SPF / tp.FRAME_INTERVAL_S)
