"""Shared by the dashboard and report tests: a headless Chromium (skipped with a reason when absent), trimmed
replays of the demo recording, and a live graph (estimator + optional recorder) on a private endpoint."""

from __future__ import annotations

import os
import shutil
import threading
from pathlib import Path

import pytest

from services import estimator
from services.mcap_io import McapRecorderWriter, read_messages
from services.zenoh_session import ZenohOptions

REPO_ROOT = Path(__file__).resolve().parents[1]
DEMO_MCAP = REPO_ROOT / "recordings" / "demo_session.mcap"
ARTIFACTS = REPO_ROOT / "out" / "test-artifacts"
CHROMIUM = os.environ.get("MSK_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
    "--disable-component-update", "--disable-sync",
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


def trimmed_recording(source: Path, out: Path, start_s: float, end_s: float) -> Path:
    """The messages of ``source`` logged in [start_s, end_s) after its first message, as a new MCAP."""
    first = None
    with McapRecorderWriter(out) as writer:
        for recorded in read_messages(source):
            first = recorded.log_time_ns if first is None else first
            t = (recorded.log_time_ns - first) / 1e9
            if start_s <= t < end_s:
                writer.write(recorded.topic, recorded.type_name, recorded.data, recorded.log_time_ns, recorded.publish_time_ns)
    return out


def start_estimator(endpoint: str, stop: threading.Event, *, pack: str, session: str, methods: list[str]) -> estimator.EstimatorStats:
    stats, ready = estimator.EstimatorStats(), threading.Event()
    threading.Thread(
        target=estimator.main, args=(ZenohOptions(connect=(endpoint,)),),
        kwargs=dict(pack=pack, session=session, methods=methods, stop_event=stop, ready_event=ready, stats=stats),
        daemon=True,
    ).start()
    assert ready.wait(60), "estimator node did not start within 60 s"
    return stats


def record_with_estimates(source: Path, out: Path, endpoint: str, *, packs: dict[str, list[str]], session: str = "rep") -> dict:
    """Replay ``source`` at full speed through one estimator per pack (``{pack: methods}``) and record everything."""
    import time

    from services import recorder, replayer

    joints = sum(1 for r in read_messages(source) if r.type_name == "msk.JointAngles")
    stop, ready = threading.Event(), threading.Event()
    rec_stats = recorder.RecorderStats()
    rec = threading.Thread(target=recorder.main, args=(ZenohOptions(listen=(endpoint,)), out),
                           kwargs=dict(stats=rec_stats, stop_event=stop, ready_event=ready), daemon=True)
    rec.start()
    assert ready.wait(30), "recorder did not start within 30 s"
    stats = {pack: start_estimator(endpoint, stop, pack=pack, session=session, methods=methods) for pack, methods in packs.items()}
    replayed = replayer.main(ZenohOptions(connect=(endpoint,)), source, rate=None, session_name=session, wait_subscribers_s=5.0)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not all(s.frames_done >= joints for s in stats.values()):
        time.sleep(0.1)
    expected = replayed.published + sum(s.frames_out * len(packs[p]) for p, s in stats.items())
    while time.monotonic() < deadline and rec_stats.written < expected:
        time.sleep(0.1)
    stop.set()
    rec.join(30)
    counts = {"replayed": replayed.published, "recorded": rec_stats.written, "expected": expected, "joints": joints,
              "estimated": {p: s.frames_out for p, s in stats.items()}, "frames_in": {p: s.frames_in for p, s in stats.items()}}
    assert rec_stats.written == expected, f"recorded {rec_stats.written} of {expected} messages: {counts}"
    return counts
