"""The Trigno client against a *different* server than our simulator: a minimal TCU imitation written here from the
protocol facts (../shared/protocols/trigno-tcp.md) alone, exercising what the facts allow but our simulator never
does — another banner wording and terminator, replies split across TCP segments with a trailing space, refused
queries with documented fallbacks, 0-based start indices of a multi-channel sensor, big-endian data by default,
odd-sized data chunks, a refused START, ``STOPPED`` racing the reply to ``STOP``, the legacy ACC port.
"""

from __future__ import annotations

import itertools
import socket
import threading
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.trigno import protocol as tp
from drivers.trigno.client import AuxBlock, ClientState, EmgBlock, StatusEvent, TrignoClient, TrignoConfig
from drivers.trigno.simulator import SimulatorConfig, TrignoSimulator
from drivers.trigno.source import synthetic_source
from msk_core.errors import ProtocolError

TERM = b"\r\n\r\n"
BANNER = b"Delsys Trigno System Digital Protocol Version 3.6.0" + TERM  # the current protocol's greeting


def known_rows(n: int, channels: int, paired: tuple[int, ...]) -> np.ndarray:
    """Distinct float32 values per sample and slot (0.0 in unpaired slots, as the SDK streams them)."""
    rows = np.zeros((n, channels), np.float32)
    k = np.arange(n, dtype=np.float64)[:, None]
    for slot in paired:
        rows[:, slot - 1 : slot] = (np.sin(0.01 * k * slot) * 1e-3).astype(np.float32)
    return rows


class LoopbackServer:
    """A listening socket on a free loopback port per name (``ports``), each served by ``_accept(name)`` in a thread
    (plus any ``extra`` thread targets) until :meth:`close`."""

    def _listen(self, names: tuple[str, ...], timeout_s: float, extra: tuple = ()) -> None:
        self._stop = threading.Event()
        self._listeners = {name: socket.create_server(("127.0.0.1", 0)) for name in names}
        for listener in self._listeners.values():
            listener.settimeout(timeout_s)  # accept() wakes up to see the stop
        self.ports = {name: listener.getsockname()[1] for name, listener in self._listeners.items()}
        self._threads = [threading.Thread(target=self._accept, args=(name,), daemon=True) for name in self._listeners]
        self._threads += [threading.Thread(target=target, daemon=True) for target in extra]

    def _start(self) -> None:
        for thread in self._threads:
            thread.start()

    def _accept(self, name: str) -> None:
        raise NotImplementedError

    def _connections(self) -> list[socket.socket]:
        """The accepted sockets to close with the listeners."""
        return []

    def close(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(2)
        for sock in [*self._listeners.values(), *self._connections()]:
            sock.close()


class FakeTcu(LoopbackServer):
    """One command connection at a time, EMG and AUX data ports; answers from a table, streams on START."""

    def __init__(
        self,
        *,
        banner: bytes = BANNER,
        answers: dict[str, str],
        emg: bytes = b"",
        aux: bytes = b"",
        chunk_sizes: tuple[int, ...] = (7, 1, 13, 64, 3, 250, 5),
        refuse_first_start: bool = False,
        stopped_before_stop_reply: bool = False,
        delays: dict[str, float] | None = None,
        reply_pad: bytes = b" ",
        split_fraction: float = 0.5,
    ) -> None:
        self.reply_pad = reply_pad
        self.split_fraction = split_fraction
        self.banner = banner
        self.answers = answers
        self.payloads = {"emg": emg, "aux": aux}
        self.chunk_sizes = chunk_sizes
        self.refuse_first_start = refuse_first_start
        self.stopped_before_stop_reply = stopped_before_stop_reply
        self.delays = delays or {}
        self.commands: list[str] = []
        self.acquiring = False
        self._data: dict[str, list[socket.socket]] = {"emg": [], "aux": []}
        self._listen(("command", "emg", "aux"), 0.1)
        self._start()

    def _connections(self) -> list[socket.socket]:
        return [sock for socks in self._data.values() for sock in socks]

    def _accept(self, name: str) -> None:
        listener = self._listeners[name]
        while not self._stop.is_set():
            try:
                conn, _ = listener.accept()
            except (TimeoutError, OSError):
                continue
            if name == "command":
                # no Nagle: the split replies go out as two segments at once instead of waiting for delayed ACKs
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                threading.Thread(target=self._serve, args=(conn,), daemon=True).start()
            else:
                self._data[name].append(conn)

    def _send_split(self, conn: socket.socket, data: bytes) -> None:
        """Two TCP segments per message: a reader must not assume a reply arrives whole."""
        half = max(1, int(len(data) * self.split_fraction))
        conn.sendall(data[:half])
        time.sleep(0.002)
        conn.sendall(data[half:])

    def _serve(self, conn: socket.socket) -> None:
        with conn:
            self._send_split(conn, self.banner)
            buffer = b""
            while not self._stop.is_set():
                chunk = conn.recv(1024)
                if not chunk:
                    return
                buffer += chunk
                while TERM in buffer:
                    packet, buffer = buffer.split(TERM, 1)
                    for command in packet.decode("ascii").split("\r\n"):
                        if command.strip():
                            time.sleep(self.delays.get(command.strip(), 0.0))
                            self._send_split(conn, self._answer(command.strip()) + TERM)
                            if command.strip() == "QUIT":
                                return

    def _answer(self, command: str) -> bytes:
        self.commands.append(command)
        if command == "START":
            if self.refuse_first_start and self.acquiring:
                return b"CANNOT COMPLETE" + self.reply_pad
            self.acquiring = True
            threading.Thread(target=self._stream, daemon=True).start()
            return b"OK" + self.reply_pad
        if command == "STOP":
            self.acquiring = False
            return (b"STOPPED" + TERM + b"OK") if self.stopped_before_stop_reply else b"OK" + self.reply_pad
        if command == "QUIT":
            return b"OK"
        return self.answers.get(command, "INVALID COMMAND").encode("ascii") + self.reply_pad

    def _stream(self) -> None:
        time.sleep(0.05)
        for name, payload in self.payloads.items():
            for sock in self._data[name]:
                sizes = itertools.cycle(self.chunk_sizes)
                pos = 0
                while pos < len(payload):
                    size = next(sizes)
                    sock.sendall(payload[pos : pos + size])
                    pos += size


def base_answers(paired: dict[int, int]) -> dict[str, str]:
    """A master base sending 27 EMG samples a frame, with the sensors of :func:`sensor_answers`."""
    return {"MASTER?": "YES", "MAX SAMPLES EMG?": "27", **sensor_answers(paired)}


def sensor_answers(paired: dict[int, int]) -> dict[str, str]:
    """PAIRED?/TYPE?/STARTINDEX? answers for {sensor: reported start index}."""
    answers = {}
    for n in range(1, 17):
        answers[f"SENSOR {n} PAIRED?"] = "YES" if n in paired else "NO"
        if n in paired:
            answers[f"SENSOR {n} TYPE?"] = "O"
            answers[f"SENSOR {n} STARTINDEX?"] = str(paired[n])
    return answers


def run_until(client: TrignoClient, n_rows: int, *, aux_rows: int = 0, seconds: float = 5.0) -> list:
    events: list = []
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        events += client.poll(0.02)
        emg = sum(len(e.samples) for e in events if isinstance(e, EmgBlock))
        aux = sum(len(e.samples) for e in events if isinstance(e, AuxBlock))
        if emg >= n_rows and aux >= aux_rows:
            break
    return events


def stack(events: list, kind: type) -> np.ndarray:
    return np.concatenate([e.samples for e in events if isinstance(e, kind)])


@pytest.mark.parametrize(
    "banner",
    [
        b"Delsys Trigno System Digital Protocol Version 4.0.1" + TERM,
        b"Delsys Trigno System Digital Protocol Version 3.6.0 " + TERM,
        b"Delsys Trigno System Digital Protocol Version 3.6.2\r\n",  # no blank line after the greeting
    ],
)
def test_independent_server_big_endian_odd_chunks_and_fallback_queries(banner):
    # sensor 1 is a 4-channel sensor (slots 1-4), the next sensor starts in slot 5; 0-based STARTINDEX replies
    rows = known_rows(600, 16, paired=(1, 2, 3, 4, 5))
    answers = {
        "MASTER?": "YES",
        "ENDIANNESS?": "BIG",  # server-side setting the client did not ask for
        "UPSAMPLING?": "UPSAMPLING OFF",
        "FRAME INTERVAL?": "0.0135",
        "SENSOR 1 CHANNEL 1 SAMPLES?": "26",  # MAX SAMPLES EMG? is refused: INVALID COMMAND
        "MAX SAMPLES AUX?": "2",
        **sensor_answers({1: 0, 5: 4, 9: 8}),
        "SENSOR 1 ACTIVE?": "YES",  # sensor 5's ACTIVE? is refused (INVALID COMMAND): taken as active
        "SENSOR 1 EMGCHANNELCOUNT?": "4",
        "SENSOR 5 EMGCHANNELCOUNT?": "1",
        "SENSOR 9 ACTIVE?": "NO",  # paired but switched off: its other answers would be garbage
        "SENSOR 9 STARTINDEX?": "\x7f\x01",
    }
    server = FakeTcu(banner=banner, answers=answers, emg=tp.encode_samples(rows, tp.Endianness.BIG))
    client = TrignoClient(TrignoConfig(command_port=server.ports["command"], emg_port=server.ports["emg"]))
    try:
        client.connect()
        assert client.protocol_version == banner.split(b"Version ")[1].strip().decode()
        assert client.endianness is tp.Endianness.BIG and client.upsampling is False
        assert client.rate_hz == pytest.approx(26 / 0.0135)
        assert client.paired_sensors == [1, 5, 9] and client.active_sensors == [1, 5]
        assert [s.start_index for s in client.sensors if s.active] == [0, 4]
        assert client.emg_columns == [
            ("sensor01.EMG1", 0),
            ("sensor01.EMG2", 1),
            ("sensor01.EMG3", 2),
            ("sensor01.EMG4", 3),
            ("sensor05.EMG", 4),
        ]
        assert not any(
            c.startswith("SENSOR 9 ") and c != "SENSOR 9 PAIRED?" and c != "SENSOR 9 ACTIVE?" for c in server.commands
        )
        client.start()
        events = run_until(client, len(rows))
        received = stack(events, EmgBlock)
        assert np.array_equal(received.view(np.uint32), rows.view(np.uint32))
        assert not np.any(received[:, 5:])
        client.stop()
        assert client.stats.errors == 0
    finally:
        client.close()
        server.close()
    assert server.commands[-2:] == ["STOP", "QUIT"]


def test_refused_start_is_retried_after_stop_and_stopped_racing_the_stop_reply_is_not_an_error():
    rows = known_rows(300, 16, paired=(2,))
    answers = {**base_answers({2: 2}), "UPSAMPLING?": "YES"}
    server = FakeTcu(
        answers=answers,
        emg=tp.encode_samples(rows),
        refuse_first_start=True,
        stopped_before_stop_reply=True,
    )
    server.acquiring = True  # a previous client left the server acquiring: START answers CANNOT COMPLETE
    client = TrignoClient(TrignoConfig(command_port=server.ports["command"], emg_port=server.ports["emg"]))
    try:
        client.connect()
        assert client.rate_hz == pytest.approx(2000.0) and client.sensors[1].start_index == 1
        client.start()
        events = run_until(client, len(rows))
        assert np.array_equal(stack(events, EmgBlock).view(np.uint32), rows.view(np.uint32))
        client.stop()
        events = client.poll(0.05)
    finally:
        client.close()
        server.close()
    assert server.commands.count("START") == 2 and server.commands[-2:] == ["STOP", "QUIT"]
    assert client.stats.errors == 0, client.stats.last_error
    assert [e.state for e in events if isinstance(e, StatusEvent)] == [ClientState.STOPPED]


def test_legacy_acc_port_carries_three_axes_per_sensor():
    emg = known_rows(54, 16, paired=(1,))
    acc = known_rows(4, 48, paired=(1, 2, 3))  # sensor 1: x, y, z
    server = FakeTcu(
        banner=b"Delsys Trigno System Digital Protocol Version 3.1.0" + TERM,
        answers=base_answers({1: 1}),
        emg=tp.encode_samples(emg),
        aux=tp.encode_samples(acc),
        chunk_sizes=(11, 100),
    )
    config = TrignoConfig(
        command_port=server.ports["command"],
        emg_port=server.ports["emg"],
        aux_port=server.ports["aux"],
        aux_layout=tp.AuxLayout.LEGACY_ACC,  # an ephemeral port: the layout cannot come from the number 50042
    )
    client = TrignoClient(config)
    try:
        client.connect()
        client.start()
        events = run_until(client, len(emg), aux_rows=len(acc))
    finally:
        client.close()
        server.close()
    received = stack(events, AuxBlock)
    assert received.shape == (4, 48)
    assert np.array_equal(received.view(np.uint32), acc.view(np.uint32))
    assert TrignoConfig(aux_port=50042).resolved_aux_layout is tp.AuxLayout.LEGACY_ACC
    assert TrignoConfig(aux_port=50044).resolved_aux_layout is tp.AuxLayout.AVANTI


def test_our_simulator_serves_the_legacy_acc_port():
    source = synthetic_source(seconds=1.0)
    config = SimulatorConfig(
        command_port=0, emg_port=0, legacy_emg_port=None, aux_port=None, legacy_acc_port=0, speed=4.0
    )
    with TrignoSimulator(source, config) as sim:
        client = TrignoClient(
            TrignoConfig(
                command_port=sim.ports["command"],
                emg_port=sim.ports["emg"],
                aux_port=sim.ports["legacy_acc"],
                aux_layout=tp.AuxLayout.LEGACY_ACC,
            )
        )
        with client:
            # one public client asks MAX SAMPLES EMG without the "?"
            assert client.command("MAX SAMPLES EMG") == client.command("MAX SAMPLES EMG?") == "27"
            client.start()
            events = run_until(client, 100, aux_rows=4)
    acc = stack(events, AuxBlock)
    assert acc.shape[1] == 48
    # paired sensors 1-4 lie flat: z = 1 g; x, y = 0; unpaired sensors all zero
    assert np.all(acc[:, [2, 5, 8, 11]] == 1.0) and not np.any(acc[:, [0, 1, 3, 4]]) and not np.any(acc[:, 12:])


def test_emg_port_falls_back_when_the_configured_one_refuses():
    """Clients disagree on the default EMG port (50043 vs 50041): a server offering only the other one still works."""
    from tests.conftest import free_tcp_port

    rows = known_rows(100, 16, paired=(3,))
    server = FakeTcu(answers=base_answers({3: 3}), emg=tp.encode_samples(rows))
    closed = free_tcp_port()  # nobody listens there: connection refused
    config = TrignoConfig(command_port=server.ports["command"], emg_port=closed, emg_port_fallback=server.ports["emg"])
    client = TrignoClient(config)
    try:
        client.connect()
        assert client.emg_port == server.ports["emg"]
        client.start()
        received = stack(run_until(client, len(rows)), EmgBlock)
    finally:
        client.close()
        server.close()
    assert np.array_equal(received.view(np.uint32), rows.view(np.uint32))
    with pytest.raises(ConnectionRefusedError):
        TrignoClient(TrignoConfig(command_port=free_tcp_port())).connect()
    assert TrignoConfig().resolved_emg_fallback == 50041
    assert TrignoConfig(emg_port=6000).resolved_emg_fallback is None  # custom ports never fall back to defaults
    assert TrignoConfig(emg_port_fallback=0).resolved_emg_fallback is None


def test_a_reply_arriving_after_its_timeout_is_not_taken_for_the_next_one():
    answers = {**base_answers({1: 1}), "BASE SERIAL?": "SP-W01D-1771", "BASE FIRMWARE?": "MA2919"}
    server = FakeTcu(answers=answers, delays={"BASE SERIAL?": 0.45})  # answered while the next command waits
    client = TrignoClient(
        TrignoConfig(command_port=server.ports["command"], emg_port=server.ports["emg"], reply_timeout_s=0.3)
    )
    try:
        client.connect()
        with pytest.raises(ProtocolError, match="no reply to 'BASE SERIAL\\?'"):
            client.command("BASE SERIAL?")
        assert client.command("BASE FIRMWARE?") == "MA2919"  # not the late serial number
        assert client.command("MASTER?") == "YES"
    finally:
        client.close()
        server.close()


def test_raw_capture_cut_inside_its_last_sample_loads_the_whole_samples(tmp_path, caplog):
    from drivers.trigno.source import load_source
    from msk_core.errors import FileFormatError

    rows = known_rows(10, 16, paired=(1, 4))
    path = tmp_path / "cut.bin"
    path.write_bytes(tp.encode_samples(rows) + tp.encode_samples(rows[:1])[:37])
    with caplog.at_level("WARNING", logger="drivers.trigno.source"):
        source = load_source(path)
    assert np.array_equal(source.samples.view(np.uint32), rows.view(np.uint32))
    assert source.paired == tuple(k in (0, 3) for k in range(16))
    assert "37 trailing bytes" in caplog.text and "cut.bin" in caplog.text
    path.write_bytes(bytes(63))
    with pytest.raises(FileFormatError, match="less than one 64-byte sample"):
        load_source(path)


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    version=st.from_regex(r"[0-9]{1,2}\.[0-9]{1,2}\.[0-9]{1,3}", fullmatch=True),
    banner_end=st.sampled_from([TERM, b" " + TERM, b"\r\n"]),
    pad=st.sampled_from([b"", b" ", b"  ", b"\t"]),
    split=st.floats(0.05, 0.95),
    chunks=st.lists(st.integers(1, 300), min_size=1, max_size=6),
    endianness=st.sampled_from(list(tp.Endianness)),
    base=st.sampled_from([0, 1]),
    per_frame=st.sampled_from([None, 15, 26, 27, 29]),  # None: MAX SAMPLES EMG? refused
    upsampling_reply=st.sampled_from(["UPSAMPLING ON", "UPSAMPLING OFF", "YES", "NO"]),
    sensors=st.sets(st.integers(1, 16), min_size=1, max_size=5),
)
def test_any_conformant_server_variant(
    version, banner_end, pad, split, chunks, endianness, base, per_frame, upsampling_reply, sensors
):
    """Every combination of what the facts leave open: the client gets the version, rate, sensors and every sample."""
    rows = known_rows(120, 16, paired=tuple(sorted(sensors)))
    answers = {
        "MASTER?": "YES",
        "ENDIANNESS?": endianness.value,
        "UPSAMPLING?": upsampling_reply,
        "FRAME INTERVAL?": "0.0135",
        **sensor_answers({n: n - 1 + base for n in sensors}),
    }
    if per_frame is not None:
        answers["MAX SAMPLES EMG?"] = str(per_frame)
    upsampled = upsampling_reply in ("UPSAMPLING ON", "YES")
    server = FakeTcu(
        banner=f"Delsys Trigno System Digital Protocol Version {version}".encode() + banner_end,
        answers=answers,
        emg=tp.encode_samples(rows, endianness),
        chunk_sizes=tuple(chunks),
        reply_pad=pad,
        split_fraction=split,
    )
    client = TrignoClient(
        TrignoConfig(command_port=server.ports["command"], emg_port=server.ports["emg"], banner_line_grace_s=0.1)
    )
    try:
        client.connect()
        client.start()
        received = stack(run_until(client, len(rows)), EmgBlock)
    finally:
        client.close()
        server.close()
    assert client.protocol_version == version
    assert client.upsampling is upsampled and client.endianness is endianness
    expected_per_frame = per_frame if per_frame is not None else (27 if upsampled else 26)
    assert client.rate_hz == pytest.approx(expected_per_frame / 0.0135)
    assert client.paired_sensors == sorted(sensors)
    assert [s.start_index for s in client.sensors if s.paired] == [n - 1 for n in sorted(sensors)]
    assert np.array_equal(received.view(np.uint32), rows.view(np.uint32))
    assert client.stats.errors == 0, client.stats.last_error
