"""The Trigno driver node publishes the sensors' accelerometers (AUX port, or the legacy ACC port) on
``msk/<s>/acc/<source>``: one AccChunk per AUX block, the active sensors' ACC x, y, z in g, on the EMG device clock.
A real simulator over TCP streams a source whose sensors carry known accelerations."""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest

from drivers.trigno import protocol as tp
from drivers.trigno.client import TrignoClient, TrignoConfig
from drivers.trigno.simulator import SimulatorConfig, TrignoSimulator
from drivers.trigno.source import synthetic_source
from services.nodes import driver_nodes
from services.transport import messages, topics

ACC_HZ = 100.0


def _source():
    """4 sensors; sensor k's accelerometer reads (k, sin 2πt, 1 - t/100) g at 100 Hz over the trial."""
    emg = synthetic_source(seconds=5.0, seed=3, sensors=4)
    t = np.arange(0.0, 5.0, 1.0 / ACC_HZ)
    acc = np.zeros((t.size, tp.N_SENSORS, 3), dtype=np.float32)
    for k in range(4):
        acc[:, k] = np.column_stack([np.full(t.size, k), np.sin(2 * np.pi * t), 1.0 - t / 100.0])
    return dataclasses.replace(emg, acc=acc, acc_rate_hz=ACC_HZ), t


@pytest.mark.parametrize("port", ["aux", "legacy_acc"])
def test_the_trigno_loop_publishes_each_aux_block_as_an_acc_chunk_on_the_emg_clock(port):
    source, t = _source()
    config = SimulatorConfig(
        command_port=0,
        emg_port=0,
        legacy_emg_port=None,
        aux_port=0,
        legacy_acc_port=0 if port == "legacy_acc" else None,
        speed=2.0,
    )
    published: list[tuple[str, object, int]] = []
    lock = threading.Lock()

    def sink(key, message, host_time_ns, device_time_ns):
        with lock:
            published.append((key, message, device_time_ns))

    stop = threading.Event()
    with TrignoSimulator(source, config) as sim:
        layout = tp.AuxLayout.LEGACY_ACC if port == "legacy_acc" else tp.AuxLayout.AVANTI
        client = TrignoClient(
            TrignoConfig(
                command_port=sim.ports["command"],
                emg_port=sim.ports["emg"],
                aux_port=sim.ports[port],
                aux_layout=layout,
            )
        )
        try:
            client.connect()
            threading.Timer(1.0, stop.set).start()
            driver_nodes.trigno_loop(client, session="s", source_id="trigno", sink=sink, stop=stop)
        finally:
            client.close()
    chunks = [(m, d) for k, m, d in published if k == topics.acc_key("s", "trigno")]
    assert len(chunks) > 50, len(chunks)  # ~148 AUX samples a second of trial, 2 s of trial at speed 2
    index = [(m.first_sample_index, m.n_samples) for m, _ in chunks]
    assert index[0][0] == 0 and all(a + n == b for (a, n), (b, _) in zip(index, index[1:])), "one contiguous stream"
    for message, device_ns in chunks:
        assert not messages.problems(message)
        assert list(message.sensor_labels) == ["sensor01", "sensor02", "sensor03", "sensor04"]
        assert message.units == "g" and message.source_id == "trigno" and device_ns == message.device_time_ns
        assert message.sample_rate_hz == pytest.approx(2 / tp.FRAME_INTERVAL_S, rel=1e-3)
        assert message.device_time_ns == round(message.first_sample_index * 1e9 / message.sample_rate_hz)
        # row k: the source's accelerations at EMG device time (first + k) / rate (the trial from START)
        rows = np.asarray(message.samples).reshape(message.n_samples, message.n_sensors, 3)
        instants = (message.first_sample_index + np.arange(message.n_samples)) / message.sample_rate_hz
        for k in range(4):
            expected = np.column_stack([np.interp(instants, t, source.acc[:, k, j]) for j in range(3)])
            assert np.allclose(rows[:, k], expected, atol=1e-5), (k, rows[:, k], expected)
