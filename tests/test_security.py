"""Security of the network mode, on loopback with certificates made here: a real ``msk router`` process with TLS,
mutual authentication and access control (services/transport/security.py), and Zenoh clients presenting role certificates.
Every check counts messages: what was sent, what each subscriber received."""

from __future__ import annotations

import copy
import ipaddress
import json
import os
import socket
import subprocess
import sys
import threading
import time
from collections import Counter

import pytest
import zenoh

from services.nodes.router import wait_until_listening
from services.transport import messages, security, zenoh_session
from services.transport.schemas import msk_pb2
from services.transport.zenoh_session import ZenohOptions, declare_data_publisher, declare_history_publisher, publish
from tests.conftest import free_tcp_port, wait_until

SESSION = "gym1"
N = 120  # messages per allowed flow


def _config(document: dict) -> zenoh.Config:
    return zenoh.Config.from_json5(json.dumps(document))


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    return security.write_pki(tmp_path_factory.mktemp("pki"), router_hosts=("localhost", "127.0.0.1"))


@pytest.fixture(scope="module")
def rogue_pki(tmp_path_factory):
    """Same role names, same CNs, but signed by a CA the router does not trust."""
    return security.write_pki(tmp_path_factory.mktemp("rogue"), router_hosts=("localhost",))


@pytest.fixture(scope="module")
def router(pki, tmp_path_factory):
    """``msk router`` as its own process, from the JSON5 config ``msk certs`` would write; yields its TLS endpoint."""
    configs = security.write_configs(
        tmp_path_factory.mktemp("zenoh"),
        pki.directory,
        router_listen=("tls/0.0.0.0:7447",),
        client_connect=("tls/localhost:7447",),
    )
    port = free_tcp_port()
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.cli",
            "router",
            "--zenoh-config",
            str(configs["router"]),
            "--listen",
            f"tls/127.0.0.1:{port}",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        try:
            wait_until_listening(process, port)
        except RuntimeError as error:
            pytest.fail(str(error))
        yield f"tls/localhost:{port}"
    finally:
        process.terminate()
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=10)


def _client(pki: security.Pki, role: str, endpoint: str) -> zenoh.Session:
    return zenoh.open(_config(security.client_config(pki.directory, role, connect=(endpoint,))))


class Inbox:
    """A subscriber's received samples, counted by key and by a payload marker."""

    def __init__(self) -> None:
        self.keys: Counter[str] = Counter()
        self.payloads: list[tuple[str, bytes]] = []
        self._lock = threading.Lock()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.keys[str(sample.key_expr)] += 1
            self.payloads.append((str(sample.key_expr), sample.payload.to_bytes()))

    def count(self, key: str) -> int:
        with self._lock:
            return self.keys[key]


def _wait_matched(publisher: zenoh.Publisher, what: str) -> None:
    wait_until(lambda: publisher.matching_status.matching, 20, f"a subscriber matching {what}")


def _emg(source_tag: str, index: int) -> msk_pb2.EmgChunk:
    return msk_pb2.EmgChunk(
        source_id=source_tag,
        channel_labels=["ch1"],
        sample_rate_hz=2000.0,
        first_sample_index=index * 27,
        n_samples=27,
        n_channels=1,
        samples=[0.001] * 27,
        units="V",
    )


# --- loopback by default --------------------------------------------------------------------------------------


def _listening_addresses(pid: int) -> list[tuple[str, int]]:
    """(address, port) of every TCP socket the process ``pid`` listens on, from /proc."""
    inodes = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    found = []
    for table, family in (("tcp", 4), ("tcp6", 6)):
        with open(f"/proc/{pid}/net/{table}") as f:
            next(f)
            for line in f:
                fields = line.split()
                local, state, inode = fields[1], fields[3], fields[9]
                if state != "0A" or inode not in inodes:  # 0A = LISTEN
                    continue
                address_hex, port_hex = local.split(":")
                raw = bytes.fromhex(address_hex)
                if family == 4:
                    address = socket.inet_ntop(socket.AF_INET, raw[::-1])
                else:
                    address = socket.inet_ntop(socket.AF_INET6, b"".join(raw[i : i + 4][::-1] for i in range(0, 16, 4)))
                found.append((address, int(port_hex, 16)))
    return found


def test_default_nodes_listen_on_loopback_only(monkeypatch, zenoh_endpoint):
    """With no flags, and with only --connect, nodes (peers) and ``msk router`` listen on 127.0.0.1 and nowhere else."""
    from services.nodes.router import router_options

    monkeypatch.setattr(zenoh_session, "DEFAULT_ENDPOINT", zenoh_endpoint)
    before = set(_listening_addresses(os.getpid()))
    first = zenoh.open(ZenohOptions().to_config())  # listens on the default endpoint
    second = zenoh.open(ZenohOptions().to_config())  # finds it taken and connects to it
    third = zenoh.open(ZenohOptions(connect=(zenoh_endpoint,)).to_config())  # Zenoh alone would listen on tcp/[::]:0
    try:
        opened = set(_listening_addresses(os.getpid())) - before
        assert opened, "the default node should listen somewhere (on loopback)"
        assert ("127.0.0.1", int(zenoh_endpoint.rsplit(":", 1)[1])) in opened
        not_loopback = [a for a in opened if not ipaddress.ip_address(a[0]).is_loopback]
        assert not not_loopback, f"default nodes listen beyond loopback: {not_loopback}"
        assert len(opened) == 3  # one listener each, the two later ones on a loopback port of their own
    finally:
        for session in (third, second, first):
            session.close()
    router_cfg = router_options(ZenohOptions(mode=None)).to_config()
    assert json.loads(router_cfg.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(router_cfg.get_json("mode")) == "router"


# --- TLS with mutual authentication ----------------------------------------------------------------------------


def test_client_without_valid_certificate_gets_no_data(pki, rogue_pki, router):
    """A certificate from another CA (same CN), no client certificate, or plain TCP: the router refuses the link,
    so the client never joins; meanwhile the legitimate recorder receives every one of N messages."""
    recorder = _client(pki, "recorder", router)
    driver = _client(pki, "driver", router)
    inbox = Inbox()
    intruder_inbox = Inbox()
    attempts = {}
    legit = security.client_config(pki.directory, "recorder", connect=(router,))
    rogue = copy.deepcopy(legit)  # trusts our CA, presents a look-alike certificate from its own
    rogue["transport"]["link"]["tls"]["connect_certificate"] = str(rogue_pki.cert("recorder"))
    rogue["transport"]["link"]["tls"]["connect_private_key"] = str(rogue_pki.key("recorder"))
    attempts["certificate from another CA"] = rogue
    no_cert = copy.deepcopy(legit)
    for field in ("connect_certificate", "connect_private_key"):
        del no_cert["transport"]["link"]["tls"][field]
    no_cert["transport"]["link"]["tls"]["enable_mtls"] = False
    attempts["no client certificate"] = no_cert
    plain = copy.deepcopy(legit)
    plain["connect"]["endpoints"] = [router.replace("tls/localhost", "tcp/127.0.0.1")]
    del plain["transport"]
    attempts["plain TCP"] = plain
    intruders = []
    try:
        subscriber = recorder.declare_subscriber(f"msk/{SESSION}/**", inbox)
        refused = {}
        for name, document in attempts.items():
            try:
                session = zenoh.open(_config(document))
            except zenoh.ZError as error:
                refused[name] = str(error)
                continue
            intruders.append(session)
            session.declare_subscriber(f"msk/{SESSION}/**", intruder_inbox)
        key = f"msk/{SESSION}/emg/trigno"
        publisher = declare_data_publisher(driver, key, "msk.EmgChunk")
        _wait_matched(publisher, key)
        for index in range(N):
            publish(publisher, _emg("trigno", index))
        wait_until(lambda: inbox.count(key) >= N, 20, f"{N} EMG chunks at the recorder", lambda: dict(inbox.keys))
        time.sleep(0.3)
        assert inbox.count(key) == N
        assert intruder_inbox.keys == Counter(), f"an intruder received data: {dict(intruder_inbox.keys)}"
        assert set(refused) == set(attempts), f"the router let in: {sorted(set(attempts) - set(refused))}"
        subscriber.undeclare()
    finally:
        for session in [*intruders, driver, recorder]:
            session.close()


# --- access control --------------------------------------------------------------------------------------------


def test_subscribe_only_client_cannot_inject_load_or_emg(pki, router):
    """A tablet (subscribe-only) publishes fake LoadEvents and EMG on the real keys: the estimator and the recorder
    receive none of them, while every real LoadEvent (operator) and EMG chunk (driver) arrives."""
    sessions = {role: _client(pki, role, router) for role in ("tablet", "operator", "driver", "estimator", "recorder")}
    estimator_inbox, recorder_inbox = Inbox(), Inbox()
    load_key, emg_key = f"msk/{SESSION}/load", f"msk/{SESSION}/emg/trigno"
    try:
        sessions["estimator"].declare_subscriber(load_key, estimator_inbox)
        sessions["estimator"].declare_subscriber(f"msk/{SESSION}/emg/**", estimator_inbox)
        sessions["recorder"].declare_subscriber(f"msk/{SESSION}/**", recorder_inbox)
        real_load = declare_data_publisher(sessions["operator"], load_key, "msk.LoadEvent")
        real_emg = declare_history_publisher(sessions["driver"], emg_key, "msk.EmgChunk")  # what msk drivers uses
        fake_load = declare_data_publisher(sessions["tablet"], load_key, "msk.LoadEvent")
        fake_emg = declare_data_publisher(sessions["tablet"], emg_key, "msk.EmgChunk")
        _wait_matched(real_load, load_key)
        probe = sessions["driver"].declare_publisher(emg_key)  # an AdvancedPublisher has no matching status
        _wait_matched(probe, emg_key)
        probe.undeclare()
        for index in range(N):
            publish(fake_load, msk_pb2.LoadEvent(barbell_mass_kg=999.0))
            publish(fake_emg, _emg("fake", index))
            publish(real_load, msk_pb2.LoadEvent(barbell_mass_kg=20.0 + index))
            publish(real_emg, _emg("trigno", index))
        for name, inbox in (("estimator", estimator_inbox), ("recorder", recorder_inbox)):
            wait_until(
                lambda inbox=inbox: inbox.count(load_key) >= N and inbox.count(emg_key) >= N,
                20,
                f"{N} real LoadEvents and EMG chunks at the {name}",
                lambda inbox=inbox: dict(inbox.keys),
            )
        time.sleep(0.5)  # any fake still in flight would land now
        for name, inbox in (("estimator", estimator_inbox), ("recorder", recorder_inbox)):
            decoded = [
                (key, messages.decode("msk.LoadEvent" if key == load_key else "msk.EmgChunk", data))
                for key, data in inbox.payloads
            ]
            fakes = [
                m
                for key, m in decoded
                if (key == load_key and m.barbell_mass_kg == 999.0) or (key == emg_key and m.source_id == "fake")
            ]
            assert not fakes, f"the {name} received {len(fakes)} injected messages"
            assert inbox.count(load_key) == N and inbox.count(emg_key) == N, f"{name}: {dict(inbox.keys)}"
            masses = sorted(m.barbell_mass_kg for key, m in decoded if key == load_key)
            assert masses == [20.0 + i for i in range(N)]
    finally:
        for session in sessions.values():
            session.close()


def test_allowed_flows_deliver_every_message_and_tablets_see_only_theirs(pki, router):
    """Tablet: every activation frame and status of the session arrives (counted); EMG and joints, which it may not
    read, do not. Driver: may not publish activations (the tablet gets none of those)."""
    sessions = {role: _client(pki, role, router) for role in ("tablet", "driver", "estimator", "kinematics")}
    tablet = Inbox()
    activations_key, status_key = f"msk/{SESSION}/activations/so", f"msk/{SESSION}/status/trigno"
    emg_key, joints_key = f"msk/{SESSION}/emg/trigno", f"msk/{SESSION}/joints"
    try:
        sessions["tablet"].declare_subscriber(f"msk/{SESSION}/activations/**", tablet)
        sessions["tablet"].declare_subscriber(f"msk/{SESSION}/status/**", tablet)
        sessions["tablet"].declare_subscriber(f"msk/{SESSION}/emg/**", tablet)  # refused by the router
        sessions["tablet"].declare_subscriber(joints_key, tablet)  # refused by the router
        activations = declare_data_publisher(sessions["estimator"], activations_key, "msk.ActivationFrame")
        status = declare_data_publisher(sessions["driver"], status_key, "msk.DeviceStatus")
        emg = declare_data_publisher(sessions["driver"], emg_key, "msk.EmgChunk")
        joints = declare_data_publisher(sessions["kinematics"], joints_key, "msk.JointAngles")
        forged = declare_data_publisher(sessions["driver"], activations_key, "msk.ActivationFrame")
        _wait_matched(activations, activations_key)
        _wait_matched(status, status_key)
        for index in range(N):
            publish(activations, msk_pb2.ActivationFrame(method="so", time_s=index * 0.01))
            publish(
                status,
                msk_pb2.DeviceStatus(device_id="trigno-1", kind="trigno", connected=True, samples_received=index),
            )
            publish(emg, _emg("trigno", index))
            publish(joints, msk_pb2.JointAngles(coordinates=["elbow"], q=[index * 0.01]))
            publish(forged, msk_pb2.ActivationFrame(method="forged", time_s=index * 0.01))
        wait_until(
            lambda: tablet.count(activations_key) >= N and tablet.count(status_key) >= N,
            20,
            f"{N} activation frames and {N} statuses at the tablet",
            lambda: dict(tablet.keys),
        )
        time.sleep(0.5)
        assert tablet.keys == Counter({activations_key: N, status_key: N}), dict(tablet.keys)
        frames = [messages.decode("msk.ActivationFrame", d) for k, d in tablet.payloads if k == activations_key]
        assert [f.time_s for f in frames] == [i * 0.01 for i in range(N)] and {f.method for f in frames} == {"so"}
    finally:
        for session in sessions.values():
            session.close()


def test_certs_command_writes_a_usable_pki_and_configs(tmp_path):
    from services.cli import main

    assert (
        main(
            [
                "certs",
                "--out",
                str(tmp_path / "pki"),
                "--router-host",
                "gym-router.local",
                "--router-host",
                "10.0.0.2",
                "--pki-path",
                "/pki",
            ]
        )
        == 0
    )
    names = sorted(p.name for p in (tmp_path / "pki").iterdir() if p.is_file())
    roles = list(security.ROLE_POLICIES)
    assert names == sorted(
        ["ca.key", "ca.pem", "router.key", "router.pem", "dashboard.key", "dashboard.pem"]
        + [f"{r}.{e}" for r in roles for e in ("key", "pem")]
    )
    from cryptography import x509

    router_cert = x509.load_pem_x509_certificate((tmp_path / "pki" / "router.pem").read_bytes())
    sans = router_cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert sans.get_values_for_type(x509.DNSName) == ["gym-router.local"]
    assert [str(a) for a in sans.get_values_for_type(x509.IPAddress)] == ["10.0.0.2"]
    # the dashboard's HTTPS certificate: from the same CA, for the router's hosts unless --dashboard-host says
    dashboard_cert = x509.load_pem_x509_certificate((tmp_path / "pki" / "dashboard.pem").read_bytes())
    assert dashboard_cert.issuer == router_cert.issuer
    dashboard_sans = dashboard_cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert dashboard_sans.get_values_for_type(x509.DNSName) == ["gym-router.local"]
    tablet = json.loads((tmp_path / "pki" / "zenoh" / "tablet.json5").read_text())
    assert tablet["connect"]["endpoints"] == ["tls/gym-router.local:7447"]
    assert tablet["transport"]["link"]["tls"]["connect_certificate"] == "/pki/tablet.pem"
    assert oct((tmp_path / "pki" / "tablet.key").stat().st_mode & 0o777) == "0o600"
    for path in (tmp_path / "pki" / "zenoh").iterdir():
        zenoh.Config.from_file(str(path))  # Zenoh itself parses every config


def test_a_late_recorder_fetches_the_drivers_history_through_the_access_control(pki, router, tmp_path):
    """What a restarted recorder does (tests/test_faults.py): the driver published 50 EMG chunks before the recorder
    joined; the recorder (``services.nodes.recorder.main`` as role recorder) writes all 50 from the driver's history, then
    the 10 live ones, in order. A tablet asking the same history gets none of it (device data is not its to read)."""
    from services.nodes import recorder as recorder_node
    from services.transport.mcap_io import read_messages
    from services.transport.zenoh_session import fetch_history

    sessions = {role: _client(pki, role, router) for role in ("driver", "tablet")}
    key = f"msk/{SESSION}/emg/history"
    config = tmp_path / "recorder.json5"
    config.write_text(json.dumps(security.client_config(pki.directory, "recorder", connect=(router,))))
    out = tmp_path / "late.mcap"
    stats, stop, ready = recorder_node.RecorderStats(), threading.Event(), threading.Event()
    thread = threading.Thread(
        target=recorder_node.main,
        args=(ZenohOptions(mode=None, config_file=config), out),
        kwargs=dict(stop_event=stop, ready_event=ready, stats=stats, flush_interval_s=0.2),
    )
    try:
        publisher = declare_history_publisher(sessions["driver"], key, "msk.EmgChunk")
        for index in range(50):
            publish(publisher, _emg("trigno", index))
        time.sleep(0.3)
        thread.start()
        wait_until(ready.is_set, 20, "the recorder to subscribe")
        wait_until(lambda: stats.history_fetches >= 1, 20, "the recorder's history fetch", lambda: stats)
        for index in range(50, 60):
            publish(publisher, _emg("trigno", index))
        wait_until(lambda: stats.written >= 60, 20, "60 chunks written by the recorder", lambda: stats)
        tablet_history, tablet_errors = fetch_history(sessions["tablet"], f"msk/{SESSION}/emg/**", timeout_s=3)
    finally:
        stop.set()
        thread.join(20)
        for session in sessions.values():
            session.close()
    assert not thread.is_alive(), "the recorder did not stop within 20 s"
    indices = [messages.decode("msk.EmgChunk", m.data).first_sample_index for m in read_messages(out) if m.topic == key]
    assert indices == [27 * i for i in range(60)]
    assert stats.history_fetched == 50 and stats.history_errors == 0, stats
    assert tablet_history == [], (
        f"the tablet read {len(tablet_history)} device messages from the history ({tablet_errors})"
    )


def test_the_dashboard_joins_the_secured_network_as_a_tablet(pki, router, tmp_path):
    """`msk dashboard --zenoh-config tablet.json5`: its bridge gets every activation frame and status the tablet may
    read, nothing of the device data it may not, and the page state shows them."""
    from services.surfaces.dashboard.bridge import Bridge, DashboardState
    from services.transport.zenoh_session import ZenohOptions

    config = tmp_path / "tablet.json5"
    config.write_text(json.dumps(security.client_config(pki.directory, "tablet", connect=(router,))))
    state = DashboardState(SESSION)
    bridge = Bridge(ZenohOptions(mode=None, config_file=config), state)
    sessions = {role: _client(pki, role, router) for role in ("driver", "estimator")}
    bridge.start()
    try:
        activations_key, status_key = f"msk/{SESSION}/activations/so", f"msk/{SESSION}/status/trigno"
        activations = declare_data_publisher(sessions["estimator"], activations_key, "msk.ActivationFrame")
        status = declare_data_publisher(sessions["driver"], status_key, "msk.DeviceStatus")
        emg = declare_data_publisher(sessions["driver"], f"msk/{SESSION}/emg/trigno", "msk.EmgChunk")
        _wait_matched(activations, activations_key)
        _wait_matched(status, status_key)
        for index in range(N):
            publish(
                activations,
                msk_pb2.ActivationFrame(method="so", time_s=index * 0.01, groups=["BicLong"], activations=[0.5]),
            )
            publish(
                status,
                msk_pb2.DeviceStatus(device_id="trigno-1", kind="trigno", connected=True, samples_received=index),
            )
            publish(emg, _emg("trigno", index))
        wait_until(
            lambda: state.changes(0)[1]["topics"].get("activations/so") is not None,
            20,
            "the dashboard state to hold an activation frame",
            lambda: list(state.changes(0)[1]["topics"]),
        )
        time.sleep(0.5)
        update = state.changes(0)[1]
        assert "activations/so" in update["topics"]
        # the status names its device; EMG chunks (refused to tablets) would add their source as a second one
        assert set(update["devices"]) == {"trigno-1"}, update["devices"]
    finally:
        bridge.stop()
        for session in sessions.values():
            session.close()
