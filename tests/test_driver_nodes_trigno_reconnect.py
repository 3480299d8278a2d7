"""``msk drivers``' Trigno loop across a base that comes back with other sensors (found with an independent server
imitation): the channels published follow what the base reports at its reconnection."""

from __future__ import annotations

import threading
import time

from drivers.trigno.simulator import SimulatorConfig, TrignoSimulator
from drivers.trigno.source import synthetic_source
from services.nodes import driver_nodes
from services.transport import topics
from tests.test_trigno import EPHEMERAL, client_for


def test_a_base_back_with_other_sensors_is_published_with_its_new_channels():
    """Before: the labels of the first connection stayed, a sensor switched off was published as zeros and a newly
    paired one never."""
    config = SimulatorConfig(**EPHEMERAL, speed=2.0, seed=1)
    sim = TrignoSimulator(synthetic_source(seconds=30.0, sensors=4), config).start()
    ports = dict(sim.ports)
    client = client_for(sim, backoff_initial_s=0.02, backoff_max_s=0.2)
    published: list[tuple[str, object]] = []
    stop = threading.Event()
    client.connect()
    loop = threading.Thread(
        target=driver_nodes.trigno_loop,
        kwargs=dict(
            client=client,
            session="s",
            source_id="trigno",
            sink=lambda key, m, *_: published.append((key, m)),
            stop=stop,
        ),
    )
    loop.start()
    try:
        deadline = time.monotonic() + 10
        while sum(1 for k, _ in published if k.endswith("/emg/trigno")) < 20 and time.monotonic() < deadline:
            time.sleep(0.05)
        sim.kill()
        time.sleep(0.3)
        restarted = SimulatorConfig(
            command_port=ports["command"], emg_port=ports["emg"], legacy_emg_port=ports["legacy_emg"],
            aux_port=ports["aux"], speed=2.0, seed=2,
        )  # fmt: skip
        sim = TrignoSimulator(synthetic_source(seconds=30.0, sensors=2), restarted).start()
        mark = len(published)
        deadline = time.monotonic() + 10
        while sum(1 for k, _ in published[mark:] if k.endswith("/emg/trigno")) < 20 and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        stop.set()
        loop.join(10)
        client.close()
        sim.close()
    chunks = [m for k, m in published if k == topics.emg_key("s", "trigno")]
    labels = [tuple(m.channel_labels) for m in chunks]
    assert labels[0] == ("sensor01.EMG", "sensor02.EMG", "sensor03.EMG", "sensor04.EMG"), labels[0]
    assert labels[-1] == ("sensor01.EMG", "sensor02.EMG"), labels[-1]
    statuses = [m for k, m in published if k == topics.status_key("s", "trigno")]
    assert any("sensor03.EMG, sensor04.EMG gone" in s.last_error for s in statuses), [s.last_error for s in statuses]
