"""Tools and nodes joined with a role the router's access control limits say so, and take what the role may:
`msk recorder`, `msk replay`, `msk subscribe` and `msk view` with the Zenoh configs `msk certs` writes, against a
real secured `msk router` process (TLS, mutual authentication, access control). A role that may read (publish)
nothing of what a tool needs is refused at start in one line naming the role and what it may; one that may read
part of it reads that part (a declaration the rules do not wholly cover gets nothing from the router)."""

from __future__ import annotations

import contextlib
import io
import logging
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh
from rich.console import Console

from services.nodes import recorder
from services.nodes.router import wait_until_listening
from services.surfaces import view
from services.transport import messages
from services.transport.mcap_io import McapRecorderWriter, read_messages
from services.transport.zenoh_session import ZenohOptions, declare_data_publisher, publish
from tests.conftest import emg_chunk, free_tcp_port, wait_until

GROUPS = ["PMCla", "DelAnt"]


def _msk(*argv: str) -> tuple[int, str]:
    """``msk ARGV`` in this process: its exit status and what it said on stderr."""
    from services.cli import main

    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        status = main(list(argv))
    return status, err.getvalue()


@pytest.fixture(scope="module")
def secured(tmp_path_factory) -> dict[str, Path]:
    """`msk certs` for a free port and a secured `msk router` process listening there; yields the role configs
    `msk certs` wrote (role -> path)."""
    pki = tmp_path_factory.mktemp("roles") / "pki"
    port = free_tcp_port()
    status, said = _msk("certs", "--out", str(pki), "--router-host", "localhost", "--port", str(port))
    assert status == 0, said
    configs = pki / "zenoh"
    router = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "router", "--zenoh-config", str(configs / "router.json5"),
         "--listen", f"tls/127.0.0.1:{port}"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True,
    )  # fmt: skip
    try:
        wait_until_listening(router, port, timeout_s=90)  # a busy shared machine starts Python slowly
        yield {path.stem: path for path in configs.glob("*.json5")}
    finally:
        router.terminate()
        try:
            router.wait(15)
        except subprocess.TimeoutExpired:
            router.kill()
        router.communicate(timeout=10)


def _options(config: Path) -> ZenohOptions:
    return ZenohOptions(mode=None, config_file=config)


def _frame(index: int) -> messages.ActivationFrame:
    now = time.time_ns()
    return messages.ActivationFrame(
        method="so", time_s=index * 0.02, groups=GROUPS, activations=[0.2, 0.6], publish_ns=now, input_arrival_ns=now
    )


@contextlib.contextmanager
def _publishing(config: Path, key: str, make, period_s: float = 0.02):
    """A client of ``config``'s role publishing ``make(index)`` on ``key`` every ``period_s`` until the block ends."""
    session = zenoh.open(zenoh.Config.from_file(str(config)))
    stop = threading.Event()
    publisher = declare_data_publisher(session, key, messages.type_name(make(0)))

    def run() -> None:
        index = 0
        while not stop.wait(period_s):
            publish(publisher, make(index))
            index += 1

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(5)
        publisher.undeclare()
        session.close()


def test_a_recorder_with_a_role_that_reads_part_says_so_and_records_that_part(secured, tmp_path, caplog):
    """As a tablet, `msk/rr/**` is narrowed to the activations and statuses (said at start and in the summary line),
    and those are recorded while the EMG is not; as a driver (reads nothing), the recorder refuses to start."""
    out = tmp_path / "tablet.mcap"
    stop, ready = threading.Event(), threading.Event()
    stats = recorder.RecorderStats()
    job = threading.Thread(
        target=recorder.main,
        args=(_options(secured["tablet"]), out),
        kwargs={"key_expr": "msk/rr/**", "stop_event": stop, "ready_event": ready, "stats": stats, "history": False},
        daemon=True,
    )
    with caplog.at_level(logging.WARNING):
        job.start()
        assert ready.wait(30)
        with (
            _publishing(secured["estimator"], "msk/rr/activations/so", _frame),
            _publishing(secured["driver"], "msk/rr/emg/trigno", lambda i: emg_chunk(i)),
        ):
            wait_until(lambda: stats.written >= 10, 20, "10 activation frames recorded", lambda: stats.written)
        stop.set()
        job.join(20)
    said = "role 'tablet' may read only msk/rr/activations/**, msk/rr/status/** of msk/rr/**"
    assert said in caplog.text
    assert said in recorder.summary_line(stats, out)
    recorded = {m.topic: m for m in read_messages(out)}
    assert set(recorded) == {"msk/rr/activations/so", "msk/rr/status/recorder"}, set(recorded)  # no EMG
    final_status = recorded["msk/rr/status/recorder"].decode(messages.DeviceStatus)  # its own, written at stop
    assert final_status.errors == 1 and said in final_status.last_error

    refused = subprocess.run(  # a process: a node installs its signal handlers
        [sys.executable, "-m", "services.cli", "recorder", "--out", str(tmp_path / "driver.mcap"),
         "--zenoh-config", str(secured["driver"])],
        capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL,
    )  # fmt: skip
    status, err = refused.returncode, refused.stderr
    assert status == 2, err
    assert "role 'driver' may subscribe only nothing; the router refuses msk/**" in err
    assert "recording" not in err and not (tmp_path / "driver.mcap").exists()


def _recording(path: Path, session: str) -> dict[str, int]:
    """A small recording of ``session``: EMG, joints, a load event and activation frames; returns messages per key."""
    counts = {f"msk/{session}/emg/trigno": 30, f"msk/{session}/joints": 12, f"msk/{session}/activations/so": 7}
    t0 = time.time_ns()
    with McapRecorderWriter(path) as writer:
        for index in range(30):
            writer.write_message(f"msk/{session}/emg/trigno", emg_chunk(index), t0 + index * 1000)
            if index < 12:
                joints = messages.JointAngles(coordinates=["x"], q=[0.1], device_time_ns=t0 + index)
                writer.write_message(f"msk/{session}/joints", joints, t0 + index * 1000 + 1)
            if index < 7:
                writer.write_message(f"msk/{session}/activations/so", _frame(index), t0 + index * 1000 + 2)
        load = messages.LoadEvent(exercise="bench_press", barbell_mass_kg=60.0, set_number=1)
        writer.write_message(f"msk/{session}/load", load, t0 + 40_000)
    return {**counts, f"msk/{session}/load": 1}


def test_replay_names_the_keys_its_role_may_not_publish_and_counts_them(secured, tmp_path):
    """As a driver, the joints, the load and the activations are named with their counts before publishing, not
    sent, and counted in the final line; the EMG arrives whole. As a tablet (publishes nothing) it refuses to start."""
    path = tmp_path / "rec.mcap"
    counts = _recording(path, "rp")
    reader = zenoh.open(zenoh.Config.from_file(str(secured["recorder"])))
    got: dict[str, int] = {}
    lock = threading.Lock()

    def take(sample: zenoh.Sample) -> None:
        with lock:
            got[str(sample.key_expr)] = got.get(str(sample.key_expr), 0) + 1

    try:
        subscriber = reader.declare_subscriber("msk/rp/**", take)
        status, err = _msk("replay", str(path), "--rate", "max", "--zenoh-config", str(secured["driver"]))
        assert status == 0, err
        wait_until(lambda: got.get("msk/rp/emg/trigno", 0) >= 30, 20, "the 30 EMG chunks", lambda: dict(got))
        time.sleep(0.3)
        subscriber.undeclare()
    finally:
        reader.close()
    assert got == {"msk/rp/emg/trigno": 30}
    lines = err.splitlines()
    assert "role 'driver' may publish only" in err and "20 messages on 3 keys" in err
    for key in ("msk/rp/activations/so", "msk/rp/joints", "msk/rp/load"):
        assert f"replay:   {key}: {counts[key]} message{'s' if counts[key] > 1 else ''}" in lines
    final = next(line for line in lines if line.startswith("published "))
    assert final.startswith("published 30 messages") and "refused 20 on 3 keys role 'driver' may not publish" in final

    status, err = _msk("replay", str(path), "--rate", "max", "--zenoh-config", str(secured["tablet"]))
    assert status == 2
    assert "role 'tablet' may publish only nothing: the router would drop all 50 messages" in err
    assert "published" not in err


def test_subscribe_refuses_a_key_its_role_may_not_read_and_narrows_a_broader_one(secured):
    """`msk subscribe msk/rs/emg/**` as a tablet: one line naming the role and what it may read, exit 2.
    `msk subscribe msk/rs/**` as a tablet: says it reads the activations and statuses of it, and prints frames."""
    status, err = _msk("subscribe", "msk/rs/emg/**", "--duration", "5", "--zenoh-config", str(secured["tablet"]))
    assert status == 2
    assert "role 'tablet' may subscribe only ['msk/*/activations/**', 'msk/*/status/**']" in err
    assert "msk/rs/emg/**" in err and "waited" not in err

    out = io.StringIO()
    with _publishing(secured["estimator"], "msk/rs/activations/so", _frame):
        from services.cli import main

        err_buffer = io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err_buffer):
            status = main(["subscribe", "msk/rs/**", "--count", "3", "--duration", "20",
                           "--zenoh-config", str(secured["tablet"])])  # fmt: skip
    err = err_buffer.getvalue()
    assert status == 0, err
    assert "role 'tablet' may read only msk/rs/activations/**, msk/rs/status/** of msk/rs/**" in err
    assert out.getvalue().count("msk/rs/activations/so msk.ActivationFrame") == 3


def test_the_view_as_a_tablet_shows_the_activations_and_says_what_it_cannot_show(secured):
    """`msk view` as a tablet subscribes to what it may read of msk/rv/** and draws the activation frames; it says
    once that the load and the movement are not shown and that its keys mark no set."""
    console = Console(file=io.StringIO(), width=160, force_terminal=False)
    redraws_with_frames = []

    def drawn(state: view.ViewState) -> bool:  # a few redraws once frames came: the screen shows them
        if state.frames:
            redraws_with_frames.append(1)
        return len(redraws_with_frames) > 3

    with _publishing(secured["estimator"], "msk/rv/activations/so", _frame):
        state = view.main(_options(secured["tablet"]), session="rv", duration_s=30, console=console, leave_for=drawn)
    assert "so" in state.frames
    note = state.access_note
    assert note.startswith("role 'tablet' may not read") and "msk/rv/load" in note and "msk/rv/joints" in note
    assert "keys s and e mark no set" in note and "activations (" not in note
    text = console.file.getvalue()
    assert "activations · so" in text and "keys: s start set" not in text

    with pytest.raises(Exception, match="role 'driver' may subscribe only nothing"):
        view.main(_options(secured["driver"]), session="rv", duration_s=1, console=console)
