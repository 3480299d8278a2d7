"""The one Zenoh helper every node uses: flags, JSON5 config files and clear errors."""

from __future__ import annotations

import argparse
import time

import pytest

from msk_core.errors import ConfigError
from services.transport import messages
from services.transport.zenoh_session import (
    ZenohOptions,
    add_zenoh_arguments,
    declare_data_publisher,
    open_session,
    options_from_args,
    publish,
    type_name_of_sample,
)


def test_json5_config_file_and_flags_connect_two_peers(tmp_path, zenoh_endpoint):
    config = tmp_path / "zenoh.json5"
    config.write_text(
        f'{{ // a comment, as JSON5 allows\n mode: "peer", listen: {{ endpoints: ["{zenoh_endpoint}"] }},\n'
        f" scouting: {{ multicast: {{ enabled: false }} }} }}\n"
    )
    parser = argparse.ArgumentParser()
    add_zenoh_arguments(parser)
    listener = options_from_args(parser.parse_args(["--zenoh-config", str(config)]))
    connector = options_from_args(parser.parse_args(["--connect", zenoh_endpoint]))
    received = []
    with open_session(listener) as a, open_session(connector) as b:
        a.declare_subscriber("msk/**", lambda s: received.append((type_name_of_sample(s), s.payload.to_bytes())))
        publisher = declare_data_publisher(b, "msk/x/load", "msk.LoadEvent")
        deadline = time.monotonic() + 10
        while not publisher.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.01)
        publish(publisher, messages.LoadEvent(barbell_mass_kg=42.5))
        while not received and time.monotonic() < deadline:
            time.sleep(0.01)
    assert received[0][0] == "msk.LoadEvent"
    assert messages.decode("msk.LoadEvent", received[0][1]).barbell_mass_kg == 42.5


def test_bad_configuration_is_reported_precisely(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        ZenohOptions(config_file=tmp_path / "nope.json5").to_config()
    broken = tmp_path / "broken.json5"
    broken.write_text("{ mode: ")
    with pytest.raises(ConfigError, match="broken.json5"):
        ZenohOptions(config_file=broken).to_config()
    with pytest.raises(ConfigError, match="mode"):
        ZenohOptions(mode="satellite").to_config()
    with pytest.raises(messages.MessageDecodeError, match="unknown message type"):
        with open_session(ZenohOptions(listen=("tcp/127.0.0.1:0",))) as session:
            declare_data_publisher(session, "msk/x/y", "msk.Nope")


def test_a_recovery_nobody_answers_says_so(zenoh_endpoint):
    """A recorder's recovery query that no cache answered (its publisher gone, or not yet known to a restarted
    router) was reported as publications "no longer in their publisher's cache"; it now comes back as an error
    naming the publisher and the wait."""
    from services.transport.zenoh_session import fetch_missed

    with open_session(ZenohOptions(listen=(zenoh_endpoint,))) as session:
        started = time.monotonic()
        samples, errors = fetch_missed(session, "msk/s/emg/trigno", ("0123abcd", 7), 3, 9, timeout_s=0.6)
    assert samples == [] and errors == ["no answer from publisher 0123abcd/7's cache of msk/s/emg/trigno within 0.6 s"]
    assert time.monotonic() - started < 3


def test_a_client_waits_a_moment_for_its_router_and_says_how_long_it_tried(zenoh_endpoint):
    """A Zenoh client tries its endpoints once: a node started while its router was still coming up (or whose TLS
    handshake a busy machine delayed) failed at once; seen on CI as a secured session's monitor node that could not
    connect. A client now tries a few times, bounded, and a refusal says how often and for how long."""
    import threading

    import zenoh

    from services.transport.zenoh_session import (
        CLIENT_CONNECT_ATTEMPTS,
        CLIENT_CONNECT_RETRY_S,
        SessionUnavailable,
    )

    routers: list = []
    late_router = threading.Timer(
        0.6, lambda: routers.append(open_session(ZenohOptions(mode="router", listen=(zenoh_endpoint,))))
    )
    started = time.monotonic()
    late_router.start()
    try:
        with open_session(ZenohOptions(mode="client", connect=(zenoh_endpoint,))) as client:
            assert isinstance(client, zenoh.Session)
        assert time.monotonic() - started >= 0.6
    finally:
        late_router.join()
        for router in routers:
            router.close()
    # nobody ever answers: refused after the bounded attempts, with their count
    started = time.monotonic()
    with pytest.raises(SessionUnavailable, match=rf"Unable to connect.*\({CLIENT_CONNECT_ATTEMPTS} attempts over"):
        open_session(ZenohOptions(mode="client", connect=(zenoh_endpoint,)))
    elapsed = time.monotonic() - started
    assert (CLIENT_CONNECT_ATTEMPTS - 1) * CLIENT_CONNECT_RETRY_S <= elapsed < 10.0


def test_a_port_whose_connections_wait_in_time_wait_is_free_one_with_a_listener_is_not():
    """Found by a new user: `msk live` started again at once after a stop was refused for about a minute ("--listen
    ... is in use by another program") while only TIME_WAIT sockets of the stopped session were on its port."""
    import socket

    from services.transport.zenoh_session import endpoint_is_free

    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    endpoint = f"tcp/127.0.0.1:{port}"
    assert not endpoint_is_free(endpoint)  # listening: in use
    client = socket.create_connection(("127.0.0.1", port))
    accepted, _ = listener.accept()
    accepted.close()  # the listening side closes first: its end waits in TIME_WAIT on the port
    time.sleep(0.05)
    client.close()
    listener.close()
    assert endpoint_is_free(endpoint)
