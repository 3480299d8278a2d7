"""Driver benchmarks: Trigno client CPU at 16 channels x 2000 Hz, Xbus parser throughput on real MTi-G-710 bytes.

Trigno: the simulator runs in another process streaming in real time; this process's CPU time (time.process_time)
over wall time is the client's share of one core. Baseline: a bare socket-draining loop on the same stream (the
floor any client pays). Xbus: frames + MTData2 decoding of the real captures (synthetic frames when ../shared is
absent), fed in 4 KiB reads, timed in process CPU time (wall time on a shared machine measures the neighbours'
load); baseline: a byte-at-a-time state-machine parser on the same bytes.
"""

from __future__ import annotations

import multiprocessing
import os
import socket
import time
from pathlib import Path

from services.bench import BenchResult

NAME = "drivers"
REPLY_TIMEOUT_S = 5.0  # the bare client: longest wait for a reply of the simulator
DESCRIPTION = "Trigno client CPU (16 ch x 2000 Hz, target < 5 % of a core); Xbus parse+decode (target >= 50,000 msg/s)"

SHARED = Path(os.environ.get("MSK_SHARED_DIR", Path(__file__).resolve().parents[2].parent / "shared"))


# ------------------------------------------------------------------------------------------------ Trigno


def _serve(ports: dict, ready, stop, seconds: float) -> None:
    from drivers.trigno.simulator import SimulatorConfig, TrignoSimulator
    from drivers.trigno.source import synthetic_source

    source = synthetic_source(seconds=seconds + 5.0, seed=0, sensors=16)
    config = SimulatorConfig(command_port=0, emg_port=0, legacy_emg_port=None, aux_port=None, loop=True)
    with TrignoSimulator(source, config) as sim:
        ports.update(sim.ports)
        ready.set()
        stop.wait(seconds + 30.0)


def _start_server(seconds: float):
    context = multiprocessing.get_context("spawn")
    manager = context.Manager()
    ports, ready, stop = manager.dict(), manager.Event(), manager.Event()
    process = context.Process(target=_serve, args=(ports, ready, stop, seconds), daemon=True)
    process.start()
    if not ready.wait(60.0):
        process.terminate()
        raise RuntimeError("Trigno simulator process did not start")
    return manager, process, dict(ports), stop


def _cpu_share(run, seconds: float) -> tuple[float, int]:
    """(process CPU seconds / wall seconds, samples) of ``run(deadline) -> samples``."""
    wall0, cpu0 = time.monotonic(), time.process_time()
    samples = run(wall0 + seconds)
    return (time.process_time() - cpu0) / (time.monotonic() - wall0), samples


def _client_run(ports: dict, *, with_messages: bool):
    from drivers.trigno.client import EmgBlock, TrignoClient, TrignoConfig
    from services.nodes import driver_nodes

    def run(deadline: float) -> int:
        samples = 0
        with TrignoClient(TrignoConfig(command_port=ports["command"], emg_port=ports["emg"])) as client:
            client.start()
            columns = driver_nodes.emg_columns(client)
            while time.monotonic() < deadline:
                for event in client.poll(0.1):
                    if isinstance(event, EmgBlock):
                        samples += len(event.samples)
                        if with_messages:
                            driver_nodes.emg_chunk(event, source_id="bench", columns=columns).SerializeToString()
        return samples

    return run


def _bare_run(ports: dict):
    from drivers.trigno import protocol as tp

    def run(deadline: float) -> int:
        command = socket.create_connection(("127.0.0.1", ports["command"]), timeout=REPLY_TIMEOUT_S)
        data = socket.create_connection(("127.0.0.1", ports["emg"]), timeout=REPLY_TIMEOUT_S)
        reader = tp.ReplyReader()
        replies: list[str] = []

        def reply(awaited: str) -> None:
            """One more reply, within REPLY_TIMEOUT_S a read (socket timeout), else an error naming what came."""
            while not replies:
                try:
                    chunk = command.recv(4096)
                except TimeoutError:
                    raise RuntimeError(
                        f"bench: no {awaited} from the Trigno simulator within {REPLY_TIMEOUT_S:g} s "
                        f"(buffered: {reader.pending()!r})"
                    ) from None
                if not chunk:
                    raise RuntimeError(f"bench: the Trigno simulator closed its command port before the {awaited}")
                replies.extend(reader.feed(chunk))

        def ask(text: str) -> None:
            command.sendall(tp.encode_command(text))
            reply(f"reply to {text}")
            replies.pop(0)

        reply("banner")
        replies.clear()
        ask("START")
        total = 0
        data.settimeout(0.1)
        while time.monotonic() < deadline:
            try:
                total += len(data.recv(65536))
            except TimeoutError:
                pass
        ask("STOP")
        command.close()
        data.close()
        return total // 64

    return run


def trigno_results(quick: bool) -> list[BenchResult]:
    seconds = 3.0 if quick else 10.0
    manager, process, ports, stop = _start_server(3 * seconds)
    try:
        bare, bare_samples = _cpu_share(_bare_run(ports), seconds)
        client, client_samples = _cpu_share(_client_run(ports, with_messages=False), seconds)
        node, node_samples = _cpu_share(_client_run(ports, with_messages=True), seconds)
    finally:
        stop.set()
        process.join(10.0)
        manager.shutdown()
    expected = 2000.0 * seconds
    sustained = client_samples >= 0.95 * expected and node_samples >= 0.95 * expected
    details: dict[str, float | str] = {
        "seconds": seconds,
        "client_samples": client_samples,
        "node_samples": node_samples,
        "bare_samples": bare_samples,
        "expected_samples": expected,
    }
    return [
        BenchResult(
            "trigno client CPU share (16 ch x 2000 Hz)",
            client,
            "core",
            "bare recv loop",
            bare,
            "< 0.05",
            bool(client < 0.05 and sustained),
            details,
        ),
        BenchResult(
            "trigno client + EmgChunk encoding CPU share",
            node,
            "core",
            "bare recv loop",
            bare,
            "< 0.05",
            bool(node < 0.05 and sustained),
            details,
        ),
    ]


# ------------------------------------------------------------------------------------------------ Xbus


def _capture_bytes() -> bytes:
    from drivers.xsens import xbus
    from drivers.xsens.source import synthetic_imu

    files = [SHARED / f"data/xsens-captures/mtig710_set{k}.bin" for k in range(1, 5)]
    if all(f.is_file() for f in files):
        return b"".join(f.read_bytes() for f in files)
    source = synthetic_imu(seconds=4.0)
    out = bytearray()
    for k in range(source.n_samples):
        items = [(0x1020, (k & 0xFFFF,)), (0x1060, (k * 100,))]
        items += [
            (xbus.make_data_id(q), tuple(source.arrays[n][k]))
            for q, n in (
                (0x2010, "quaternion"),
                (0x4020, "acceleration"),
                (0x8020, "rate_of_turn"),
                (0xC020, "magnetic_field"),
            )
        ]
        out += xbus.encode_message(xbus.Mid.MT_DATA2, xbus.encode_mtdata2(items))
    return bytes(out)


def _naive_parse(data: bytes) -> int:
    """Byte-at-a-time state machine, the textbook way (baseline)."""
    import struct

    count, state, frame = 0, 0, bytearray()
    need = 0
    for byte in data:
        if state == 0:
            if byte == 0xFA:
                frame = bytearray([byte])
                state = 1
            continue
        frame.append(byte)
        if state == 1 and len(frame) == 4:
            need = 4 + frame[3] + 1 if frame[3] != 0xFF else -1
            state = 2
        elif state == 2 and need < 0 and len(frame) == 6:
            need = 6 + ((frame[4] << 8) | frame[5]) + 1
        if state == 2 and need > 0 and len(frame) == need:
            if sum(frame[1:]) & 0xFF == 0 and frame[2] == 0x36:
                payload = bytes(frame[4:-1])
                i = 0
                while i + 3 <= len(payload):
                    size = payload[i + 2]
                    struct.unpack(f">{size}B", payload[i + 3 : i + 3 + size])
                    i += 3 + size
                count += 1
            state = 0
    return count


def xbus_results(quick: bool) -> list[BenchResult]:
    from drivers.xsens import xbus

    one = _capture_bytes()
    repeats = 25 if quick else 100
    data = one * repeats
    start = time.process_time()
    parser = xbus.XbusParser()
    messages = 0
    for offset in range(0, len(data), 4096):
        for message in parser.feed(data[offset : offset + 4096]):
            if message.mid == xbus.Mid.MT_DATA2:
                xbus.decode_mtdata2(message.data)
            messages += 1
    elapsed = time.process_time() - start
    baseline_data = one * max(1, repeats // 10)
    start = time.process_time()
    baseline_messages = _naive_parse(baseline_data)
    baseline_elapsed = time.process_time() - start
    per_message_us = elapsed / messages * 1e6
    baseline_us = baseline_elapsed / baseline_messages * 1e6
    rate = messages / elapsed
    return [
        BenchResult(
            "xbus parse + MTData2 decode",
            per_message_us,
            "us/msg",
            "byte-at-a-time parser",
            baseline_us,
            "<= 20 us/msg (>= 50,000 msg/s)",
            bool(rate >= 50_000),
            {"messages_per_s": round(rate), "messages": messages, "bytes": len(data), "errors": parser.stats.errors},
        ),
    ]


def run(quick: bool) -> list[BenchResult]:
    return xbus_results(quick) + trigno_results(quick)
