"""`msk dashboard` in a real headless Chromium while the demo recording is replayed through a live estimator:
the bars, the rep counter and the body-map colours change, the method can be switched, the page says "no data" when
the replay stops and recovers when it resumes, and it reconnects by itself when the dashboard server restarts."""

from __future__ import annotations

import json
import threading
import time

import pytest

from services import replayer
from services.dashboard.app import DashboardConfig, DashboardServer
from services.zenoh_session import ZenohOptions
from tests.conftest import free_tcp_port
from tests.dashboard_helpers import ARTIFACTS, DEMO_MCAP, launch_chromium, require_chromium, start_estimator, trimmed_recording


SESSION = "dash"
PROBE = """() => {
  const s = window.mskDashboard.state, c = window.mskDashboard.charts;
  return {
    status: document.getElementById('status').dataset.state,
    reps: document.getElementById('reps').textContent,
    set: document.getElementById('set').textContent,
    method: document.getElementById('method').value,
    bars: c.bars ? c.bars.data.datasets[0].data.slice() : null,
    frame: s.method && s.activations[s.method] ? s.activations[s.method].activations : null,
    fills: [...document.querySelectorAll('#bodymap .muscle')].map(e => e.getAttribute('fill')),
    torqueCharts: Object.keys(c.torques),
    devices: Object.keys(s.devices),
    updates: s.updates, dataAge: s.dataAge,
  };
}"""


def wait_for(page, predicate, timeout_s: float, what: str) -> dict:
    """Poll the page until ``predicate(probe)``; on time-out say what was waited for and what the page showed."""
    deadline = time.monotonic() + timeout_s
    probe = page.evaluate(PROBE)
    while not predicate(probe):
        if time.monotonic() > deadline:
            shown = {k: probe[k] for k in ("status", "reps", "set", "method", "updates", "dataAge", "devices")}
            raise AssertionError(f"waited {timeout_s} s for {what}; the page shows {json.dumps(shown)}")
        time.sleep(0.1)
        probe = page.evaluate(PROBE)
    return probe


def replay_in_background(endpoint: str, recording, rate: float) -> threading.Thread:
    thread = threading.Thread(
        target=replayer.main, args=(ZenohOptions(connect=(endpoint,)), recording),
        kwargs=dict(rate=rate, session_name=SESSION, wait_subscribers_s=2.0), daemon=True,
    )
    thread.start()
    return thread


@pytest.mark.slow
def test_dashboard_follows_a_replayed_session_in_chromium(tmp_path, zenoh_endpoint):
    require_chromium()
    from playwright import sync_api
    # Two pieces of the bench press: reps end at 4.9 s and 8.6 s of the first set, 23.8 s and 28.0 s of the second.
    first_set = trimmed_recording(DEMO_MCAP, tmp_path / "set1.mcap", 0.0, 9.5)
    second_set = trimmed_recording(DEMO_MCAP, tmp_path / "set2.mcap", 18.0, 28.5)
    port = free_tcp_port()
    config = DashboardConfig(session=SESSION, no_data_after_s=1.5)
    dashboard = DashboardServer(ZenohOptions(listen=(zenoh_endpoint,)), config, port=port)
    dashboard.start()
    stop = threading.Event()
    estimator_stats = start_estimator(zenoh_endpoint, stop, pack="bench_press", session=SESSION, methods=["so", "hybrid"])
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    try:
        with sync_api.sync_playwright() as playwright:
            browser = launch_chromium(playwright)
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            errors: list[str] = []
            page.on("pageerror", lambda error: errors.append(str(error)))
            page.goto(dashboard.url)
            # Before anything is published: the explicit "no data" state.
            wait_for(page, lambda p: p["status"] == "nodata", 10, "the 'no data' state before the replay")
            assert page.is_visible("#nodata") and "Nothing received yet" in page.inner_text("#nodata-detail")

            replay = replay_in_background(zenoh_endpoint, first_set, rate=2.0)
            first = wait_for(page, lambda p: p["status"] == "live" and p["bars"] and p["fills"], 15, "live frames")
            assert first["reps"] == "0" and first["set"] == "1"
            assert set(first["torqueCharts"]) == {"elv_angle_r", "elbow_flex_r"}
            assert {"trigno-synth", "xsens"} <= set(first["devices"])
            # The bars show what the selected method estimated, and they move with the lift.
            later = wait_for(page, lambda p: p["bars"] != first["bars"] and p["fills"] != first["fills"], 10,
                             "bars and body-map colours to change")
            wait_for(page, lambda p: p["bars"] == [a if a is not None else 0 for a in p["frame"]], 5,
                     "the bars to show the newest frame of the selected method")
            counted = wait_for(page, lambda p: p["reps"] == "2", 15, "the rep counter to reach 2 (two reps in the first set)")
            page.screenshot(path=str(ARTIFACTS / "dashboard.png"))
            # Method switch: the bars follow the other method.
            other = "so" if counted["method"] == "hybrid" else "hybrid"
            page.select_option("#method", other)
            switched = wait_for(page, lambda p: p["method"] == other and p["bars"] == [a if a is not None else 0 for a in p["frame"]],
                                5, f"the bars of method {other}")
            replay.join(30)
            assert not replay.is_alive(), "the replay of the first set did not finish within 30 s"
            stopped = wait_for(page, lambda p: p["status"] == "nodata", 10, "'no data' after the replay stopped")
            assert page.is_visible("#nodata") and "Nothing new" in page.inner_text("#nodata-detail")
            assert stopped["method"] == other and switched["bars"] is not None
            # Where a frame carries measured EMG envelopes (estimator with EMG), they are drawn beside the estimate (checked
            # while the replay is stopped, so that no newer frame replaces the one given to the page).
            envelope = [0.5] + [None] * (len(switched["frame"]) - 1)
            page.evaluate("""([method, envelope]) => {
                const frame = {...window.mskDashboard.state.activations[method], envelope};
                const s = window.mskDashboard.state;
                window.mskDashboard.merge({topics: {['activations/' + method]: frame}, data_age_s: s.dataAge, activation_age_s: s.activationAge});
            }""", [other, envelope])
            page.wait_for_function("() => window.mskDashboard.charts.bars.data.datasets[2].data[0] !== null", timeout=5000)
            envelope_bars = page.evaluate("window.mskDashboard.charts.bars.data.datasets[2].data")
            assert envelope_bars[0] == pytest.approx([0.492, 0.508]) and all(v is None for v in envelope_bars[1:])

            replay = replay_in_background(zenoh_endpoint, second_set, rate=2.0)
            resumed = wait_for(page, lambda p: p["status"] == "live", 15, "live again after the replay resumed")
            assert not page.is_visible("#nodata")
            wait_for(page, lambda p: p["set"] == "2" and p["reps"] == "2", 15, "two reps counted in the second set")
            replay.join(30)
            assert resumed["updates"] > first["updates"]

            # The dashboard server restarts (same port): the page notices and reconnects by itself.
            dashboard.stop()
            wait_for(page, lambda p: p["status"] == "reconnecting", 10, "'reconnecting' while the server is down")
            dashboard = DashboardServer(ZenohOptions(connect=(zenoh_endpoint,)), config, port=port)
            dashboard.start()
            wait_for(page, lambda p: p["status"] == "nodata", 15, "the page to reconnect to the restarted server")
            assert not errors, errors
            browser.close()
    finally:
        stop.set()
        dashboard.stop()
    assert estimator_stats.frames_out > 0
