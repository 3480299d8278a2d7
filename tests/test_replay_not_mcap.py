"""`msk replay` of a file that is not an MCAP recording says so and fails (it is not a recording cut short)."""

from __future__ import annotations

import pytest

from services.cli import main as msk


@pytest.mark.parametrize("content", [b"", b"time,emg\n0.0,1.0\n", b"\x89PNG\r\n\x1a\n" + bytes(64)])
def test_replay_of_a_non_mcap_file_names_it_and_exits_non_zero(tmp_path, zenoh_endpoint, capsys, content):
    path = tmp_path / "session.mcap"
    path.write_bytes(content)
    code = msk(["replay", str(path), "--rate", "max", "--wait-subscribers", "0", "--listen", zenoh_endpoint])
    err = capsys.readouterr().err
    assert code != 0
    assert "not an MCAP recording" in err and str(path) in err
    assert "cut short" not in err


def test_replay_of_a_truncated_mcap_still_replays_its_readable_part(tmp_path, zenoh_endpoint, capsys, repo_root):
    whole = (repo_root / "recordings" / "demo_session.mcap").read_bytes()
    path = tmp_path / "cut.mcap"
    path.write_bytes(whole[: len(whole) * 3 // 5])  # past the first complete chunks
    code = msk(["replay", str(path), "--rate", "max", "--wait-subscribers", "0", "--listen", zenoh_endpoint])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "cut short" in err and "published 0 " not in err


def test_keys_nobody_reads_are_named_and_the_paced_clock_does_not_burst_after_the_wait(
    tmp_path, zenoh_endpoint, capsys
):
    """The wait for a reader on each new key used to be ignored: a replay under the wrong --session said
    "published N messages" and nothing else. Keys with no subscriber after the wait are named in the last line; a key
    with one is not. At a rate, the wait is not counted as replay time (the next messages went out in a burst)."""
    import time

    from services.transport import messages, topics
    from services.transport.zenoh_session import ZenohOptions, open_session
    from tests.dashboard_helpers import timed_recording

    path = tmp_path / "two_keys.mcap"
    with timed_recording(path, 1_773_480_600_000_000_000) as recording:
        for k in range(20):  # 1 s of joints; the load key first appears half-way
            recording.write(messages.JointAngles(coordinates=["c"], q=[0.1 * k]), 0.05 * k, "joints")
            if k == 10:
                recording.write(messages.LoadEvent(barbell_mass_kg=40.0), 0.05 * k, "load")
    received: list[float] = []
    with open_session(ZenohOptions(listen=(zenoh_endpoint,))) as session:
        subscriber = session.declare_subscriber(
            topics.joints_key("s"), lambda sample: received.append(time.monotonic())
        )
        started = time.monotonic()
        code = msk(["replay", str(path), "--wait-subscribers", "0.5", "--connect", zenoh_endpoint])
        took = time.monotonic() - started
        subscriber.undeclare()
    err = capsys.readouterr().err
    assert code == 0, err
    assert "published 21 messages" in err
    assert "no subscriber within 0.5 s on 1 of the keys (msk/s/load)" in err, err
    assert len(received) == 20
    # the joints after the load key's 0.5 s wait keep their 50 ms spacing (not sent at once when the wait ends)
    gaps = sorted(b - a for a, b in zip(received[10:], received[11:]))
    assert gaps[len(gaps) // 2] > 0.025, gaps  # the median: a busy machine may bunch one or two
    assert took < 1.0 + 0.5 + 0.5 + 5.0, took
