"""Shared by the dashboard and report tests: a headless Chromium (skipped with a reason when absent), trimmed
replays of the demo recording, and a live graph (estimator + optional recorder) on a private endpoint."""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from services.nodes import estimator
from services.transport import messages
from services.transport.mcap_io import McapRecorderWriter, read_messages
from services.transport.topics import Delivery, delivery_for_key
from services.transport.zenoh_session import ZenohOptions

REPO_ROOT = Path(__file__).resolve().parents[1]
DEMO_MCAP = REPO_ROOT / "recordings" / "demo_session.mcap"
ARTIFACTS = REPO_ROOT / "out" / "test-artifacts"
CHROMIUM = os.environ.get("MSK_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def require_chromium() -> None:
    """Skip (with the reason) before any set-up when Debian's Chromium or Playwright is missing."""
    if not Path(CHROMIUM).is_file() and shutil.which(CHROMIUM) is None:
        pytest.skip(f"Chromium not found at {CHROMIUM} (apt-get install chromium; .ci/run installs it)")
    pytest.importorskip("playwright.sync_api", reason="playwright is not installed (pip install -e .[test])")


def launch_chromium(playwright):
    """Debian's Chromium through Playwright; never a downloaded browser."""
    require_chromium()
    return playwright.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)


def trigno_chunk(k: int, host_time_ns: int) -> messages.EmgChunk:
    """The ``k``-th EMG chunk of a Trigno base with one electrode (sensor01.EMG, 27 samples of zeros at 2 kHz)."""
    return messages.EmgChunk(
        source_id="trigno",
        first_sample_index=27 * k,
        n_samples=27,
        n_channels=1,
        samples=[0.0] * 27,
        channel_labels=["sensor01.EMG"],
        sample_rate_hz=2000.0,
        host_time_ns=host_time_ns,
    )


def chromium_page(playwright, width: int = 1280, height: int = 800) -> tuple[Any, Any, list[str]]:
    """Debian's Chromium (:func:`launch_chromium`) with one page of ``width`` x ``height``: (browser, page, the page's
    uncaught script errors, collected as they happen)."""
    browser = launch_chromium(playwright)
    page = browser.new_page(viewport={"width": width, "height": height})
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    return browser, page, errors


@contextlib.contextmanager
def dashboard_in_chromium(endpoint: str, config: Any) -> Iterator[tuple[Any, Any, Any, list[str]]]:
    """A dashboard server (``config``: its DashboardConfig) listening on ``endpoint`` and, inside the block, a Zenoh
    client session of it and Chromium's page on it: (session, browser, page, the page's script errors). The server
    stops after the block, also when it fails."""
    from playwright import sync_api

    from services.surfaces.dashboard.app import DashboardServer
    from services.transport.zenoh_session import open_session
    from tests.conftest import free_tcp_port

    dashboard = DashboardServer(ZenohOptions(listen=(endpoint,)), config, port=free_tcp_port())
    dashboard.start()
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    try:
        with (
            open_session(ZenohOptions(connect=(endpoint,))) as zsession,
            sync_api.sync_playwright() as playwright,
        ):
            browser, page, errors = chromium_page(playwright)
            page.goto(dashboard.url)
            yield zsession, browser, page, errors
    finally:
        dashboard.stop()


def replay_demo_without_raw(endpoint: str, session: str) -> Any:
    """The demo recording (DEMO_MCAP) as fast as it goes, renamed to ``session``, through a client of ``endpoint``: every
    message but the raw IMU and EMG (the joint angles for an estimator, the load, the statuses). Its ReplayStats."""
    from services.nodes import replayer

    return replayer.main(
        ZenohOptions(connect=(endpoint,)),
        DEMO_MCAP,
        rate=None,
        session_name=session,
        exclude=(f"msk/{session}/imu/*", f"msk/{session}/emg/*"),
    )


class TimedRecording:
    """A recording of the session ``s`` being written: each message at ``t_s`` seconds after ``start_ns`` (log and
    publish time alike)."""

    def __init__(self, writer: McapRecorderWriter, start_ns: int) -> None:
        self.writer, self.start_ns = writer, start_ns

    def write(self, message: Any, t_s: float, topic: str) -> None:
        ns = self.start_ns + int(t_s * 1e9)
        self.writer.write(f"msk/s/{topic}", messages.type_name(message), messages.encode(message), ns, ns)

    def load_events(self, events: list[tuple[float, Any]]) -> None:
        """(seconds, LoadEvent) pairs on the load topic, each with its device time."""
        for t_s, event in events:
            event.device_time_ns = self.start_ns + int(t_s * 1e9)
            self.write(event, t_s, "load")

    def joints_and_frame(self, t_s: float, phase: float, groups: list[str], activations: list[float]) -> None:
        """At ``t_s``: the elbow's joint angles carrying ``phase`` and the bench press's ``so`` frame of ``groups``."""
        joints = messages.JointAngles(
            coordinates=["elbow_flex_r"], q=[1.0], phase=phase, device_time_ns=self.start_ns + int(t_s * 1e9)
        )
        self.write(joints, t_s, "joints")
        frame = messages.ActivationFrame(
            time_s=self.start_ns / 1e9 + t_s,
            method="so",
            groups=groups,
            activations=activations,
            exercise="bench_press",
        )
        self.write(frame, t_s, "activations/so")


@contextlib.contextmanager
def timed_recording(path: Path, start_ns: int) -> Iterator[TimedRecording]:
    """A new MCAP at ``path`` written through a :class:`TimedRecording`; closed after the block."""
    with McapRecorderWriter(path) as writer:
        yield TimedRecording(writer, start_ns)


def trimmed_recording(source: Path, out: Path, start_s: float, end_s: float) -> Path:
    """The messages of ``source`` logged in [start_s, end_s) after its first message, as a new MCAP."""
    first = None
    with McapRecorderWriter(out) as writer:
        for recorded in read_messages(source):
            first = recorded.log_time_ns if first is None else first
            t = (recorded.log_time_ns - first) / 1e9
            if start_s <= t < end_s:
                writer.write(
                    recorded.topic, recorded.type_name, recorded.data, recorded.log_time_ns, recorded.publish_time_ns
                )
    return out


def start_estimator(
    endpoint: str, stop: threading.Event, *, pack: str, session: str, methods: list[str]
) -> estimator.EstimatorStats:
    stats, ready = estimator.EstimatorStats(), threading.Event()
    threading.Thread(
        target=estimator.main,
        args=(ZenohOptions(connect=(endpoint,)), estimator.EstimatorSettings(pack, session, tuple(methods))),
        kwargs=dict(stop_event=stop, ready_event=ready, stats=stats),
        daemon=True,
    ).start()
    assert ready.wait(60), "estimator node did not start within 60 s"
    return stats


#: how much faster than real time record_with_estimates replays (see its docstring)
REPLAY_RATE = 8.0


RECORDER_SETTLED_S = 3.0  # a count that has not moved for this long after the replay: nothing more is on its way


def _settle(count: Callable[[], int], wanted: int, deadline: float) -> None:
    """Until ``count()`` reaches ``wanted``, stays unchanged for RECORDER_SETTLED_S, or ``deadline`` (monotonic)."""
    import time

    last, since = -1, time.monotonic()
    while time.monotonic() < deadline and (now := count()) < wanted:
        if now != last:
            last, since = now, time.monotonic()
        elif time.monotonic() - since > RECORDER_SETTLED_S:
            return
        time.sleep(0.1)


def record_with_estimates(
    source: Path, out: Path, endpoint: str, *, packs: dict[str, list[str]], session: str = "rep"
) -> dict:
    """Replay ``source`` at 8x real time through one estimator per pack (``{pack: methods}``) and record everything.

    Every lossless message (the replayed data) must be recorded. Activation frames, envelopes and statuses are
    newest-wins (services.transport.topics, Delivery): a publisher flooded faster than the recorder drains drops some,
    by design (in clean-clone suites on busy cores 13 and 138 of 32,396 were missing, all newest-wins); at most 1 % of
    them may be missing. Not at full speed: 8x keeps the graph far from that while the replay takes ~9 s."""
    import time

    from services.nodes import recorder, replayer

    joints = sum(1 for r in read_messages(source) if r.type_name == "msk.JointAngles")
    stop, ready = threading.Event(), threading.Event()
    rec_stats = recorder.RecorderStats()
    rec = threading.Thread(
        target=recorder.main,
        args=(ZenohOptions(listen=(endpoint,)), out),
        kwargs=dict(stats=rec_stats, stop_event=stop, ready_event=ready),
        daemon=True,
    )
    rec.start()
    assert ready.wait(30), "recorder did not start within 30 s"
    stats = {
        pack: start_estimator(endpoint, stop, pack=pack, session=session, methods=methods)
        for pack, methods in packs.items()
    }
    replayed = replayer.main(
        ZenohOptions(connect=(endpoint,)), source, rate=REPLAY_RATE, session_name=session, wait_subscribers_s=5.0
    )
    deadline = time.monotonic() + 120
    # Newest-wins messages may be dropped on a busy machine (joint frames on their way to an estimator, activation
    # frames to the recorder): waiting for every one ran to the 120 s deadline then. Each wait ends when its count
    # is reached or has not moved for RECORDER_SETTLED_S.
    _settle(lambda: sum(min(s.frames_done, joints) for s in stats.values()), joints * len(stats), deadline)
    expected = replayed.published + sum(s.frames_out * len(packs[p]) for p, s in stats.items())
    _settle(lambda: rec_stats.written - rec_stats.node_status, expected, deadline)
    stop.set()
    rec.join(30)
    # the replayed data and the estimates; the nodes' status messages (kind "node") come on top
    recorded = [r for r in read_messages(out) if not (r.type_name == "msk.DeviceStatus" and r.decode().kind == "node")]
    lossless = sum(1 for r in read_messages(source) if delivery_for_key(r.topic) is Delivery.LOSSLESS)
    counts = {
        "replayed": replayed.published,
        "recorded": len(recorded),
        "expected": expected,
        "lossless_expected": lossless,
        "lossless_recorded": sum(1 for r in recorded if delivery_for_key(r.topic) is Delivery.LOSSLESS),
        "joints": joints,
        "estimated": {p: s.frames_out for p, s in stats.items()},
        "frames_in": {p: s.frames_in for p, s in stats.items()},
    }
    assert counts["lossless_recorded"] == lossless, f"lost lossless messages: {counts}"
    newest_wins_missing = expected - len(recorded)
    assert 0 <= newest_wins_missing <= 0.01 * (expected - lossless), f"recorded {len(recorded)} of {expected}: {counts}"
    return counts


# ---- unusable inputs over a real Zenoh session (the readers must drop and count them, and go on) ---------------------
#: A payload far over services.nodes.node_runtime.MAX_PAYLOAD_BYTES.
HUGE_PAYLOAD_BYTES = 50 * 1024 * 1024


@dataclass
class BadInputs:
    """Publishers on a session's topics, one per key, for unusable payloads and then valid messages after them (the
    same publisher keeps them in order). ``expected`` collects the drops the reader should count: {(key, reason): n}."""

    zsession: object
    session: str
    expected: dict[tuple[str, str], int] = field(default_factory=dict)
    _publishers: dict[str, object] = field(default_factory=dict)

    def publisher(self, rest: str):
        import zenoh

        key = f"msk/{self.session}/{rest}"
        if key not in self._publishers:
            self._publishers[key] = self.zsession.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE
            )
        return self._publishers[key]

    def wait_matched(self, rests: list[str], timeout_s: float = 30.0) -> None:
        """Wait until the reader's subscriptions match every key of ``rests`` (else a payload could go nowhere)."""
        import time

        publishers = {rest: self.publisher(rest) for rest in rests}
        deadline = time.monotonic() + timeout_s
        while not all(p.matching_status.matching for p in publishers.values()):
            assert time.monotonic() < deadline, (
                f"no subscriber within {timeout_s} s on {[r for r, p in publishers.items() if not p.matching_status.matching]}"
            )
            time.sleep(0.05)

    def bad(self, rest: str, payload: bytes, reason: str, *, encoding_type: str | None = None) -> None:
        self._put(rest, payload, encoding_type)
        key = f"msk/{self.session}/{rest}"
        self.expected[(key, reason)] = self.expected.get((key, reason), 0) + 1

    def good(self, rest: str, message) -> None:
        from services.transport import messages

        self._put(rest, messages.encode(message), messages.type_name(message))

    def _put(self, rest: str, payload: bytes, encoding_type: str | None) -> None:
        from services.transport.zenoh_session import encoding_for

        publisher = self.publisher(rest)
        if encoding_type is None:
            publisher.put(payload)
        else:
            publisher.put(payload, encoding=encoding_for(encoding_type))

    def publish_every_kind(self) -> None:
        """Garbage bytes, an empty payload, a message of the wrong type and a 50 MB payload, on several topics."""
        from services.transport import messages

        chunk = messages.EmgChunk(
            source_id="trigno", n_samples=1, n_channels=1, samples=[0.0], channel_labels=["a"], sample_rate_hz=2000.0
        )
        self.bad("activations/so", b"\xff\xff not protobuf", "undecodable")
        self.bad("activations/so", b"", "invalid")  # decodes to a frame without method or groups
        self.bad("status/trigno", messages.encode(chunk), "wrong_type", encoding_type="msk.EmgChunk")
        self.bad("load", b"\xff\xff not protobuf", "undecodable")
        self.bad("joints", bytes(HUGE_PAYLOAD_BYTES), "oversized")

    def every_kind_then(self, goods: dict[str, object]) -> None:
        """Once the reader listens: every kind of unusable payload, then the valid messages ``goods`` (topic after
        ``msk/<session>/`` -> message), each after the bad ones on its key."""
        self.wait_matched(BAD_INPUT_TOPICS)
        self.publish_every_kind()
        for rest, message in goods.items():
            self.good(rest, message)

    def close(self) -> None:
        for publisher in self._publishers.values():
            publisher.undeclare()
        self._publishers.clear()


BAD_INPUT_TOPICS = ["activations/so", "status/trigno", "load", "joints"]


def chromium_trusting(ca: Path, home: Path) -> dict[str, str] | None:
    """An environment whose HOME holds an NSS store trusting ``ca`` (Chromium on Linux reads $HOME/.pki/nssdb);
    None when NSS's certutil is missing."""
    certutil = shutil.which("certutil")
    if certutil is None:
        return None
    store = home / ".pki" / "nssdb"
    store.mkdir(parents=True)
    subprocess.run([certutil, "-d", f"sql:{store}", "-N", "--empty-password"], check=True, capture_output=True)
    subprocess.run(
        [certutil, "-d", f"sql:{store}", "-A", "-t", "C,,", "-n", "msk-live CA", "-i", str(ca)],
        check=True,
        capture_output=True,
    )
    return {**os.environ, "HOME": str(home)}
