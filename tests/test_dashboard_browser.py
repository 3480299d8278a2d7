"""`msk dashboard` in a real headless Chromium while the demo recording is replayed through a live estimator:
the bars, the rep counter and the body-map colours change, the method can be switched, the page says "no data" when
the replay stops and recovers when it resumes, and it reconnects by itself when the dashboard server restarts. And, fed
over Zenoh without an estimator, the "no data" state (last values greyed beside a notice) and a row per device."""

from __future__ import annotations

import json
import threading
import time

import pytest

from services.nodes import replayer
from services.surfaces.dashboard.app import DashboardConfig, DashboardServer
from services.transport.zenoh_session import ZenohOptions
from tests.conftest import free_tcp_port
from tests.dashboard_helpers import (
    ARTIFACTS,
    DEMO_MCAP,
    chromium_page,
    dashboard_in_chromium,
    require_chromium,
    start_estimator,
    trigno_chunk,
    trimmed_recording,
)

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
    labels: c.bars ? c.bars.data.labels.map((l) => (Array.isArray(l) ? l.join(' ') : l)) : [],
    torqueTitles: [...document.querySelectorAll('#torques .torque-title')].map((e) => e.textContent),
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
        target=replayer.main,
        args=(ZenohOptions(connect=(endpoint,)), recording),
        kwargs=dict(rate=rate, session_name=SESSION, wait_subscribers_s=2.0),
        daemon=True,
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
    estimator_stats = start_estimator(
        zenoh_endpoint, stop, pack="bench_press", session=SESSION, methods=["so", "hybrid"]
    )
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    try:
        with sync_api.sync_playwright() as playwright:
            browser, page, errors = chromium_page(playwright)
            page.goto(dashboard.url)
            # Before anything is published: the explicit "no data" state.
            wait_for(page, lambda p: p["status"] == "nodata", 10, "the 'no data' state before the replay")
            assert page.is_visible("#nodata") and "Nothing received yet" in page.inner_text("#nodata-detail")

            replay = replay_in_background(zenoh_endpoint, first_set, rate=2.0)
            first = wait_for(page, lambda p: p["status"] == "live" and p["bars"] and p["fills"], 15, "live frames")
            # the first rep ends 2.45 s into the replay at rate 2: on busy cores the page may first be seen after it
            assert first["set"] == "1" and first["reps"] in ("0", "1"), first
            assert set(first["torqueCharts"]) == {"elv_angle_r", "elbow_flex_r"}
            assert not page.is_disabled("#set-start") and page.inner_text("#set-reply") == ""  # no role: may mark
            # muscles and joints by their display names, torques with their unit
            named = wait_for(page, lambda p: "Biceps brachii, long head" in p["labels"], 5, "display names on the bars")
            assert "Triceps brachii, lateral and medial heads" in named["labels"] and "BicLong" not in named["labels"]
            assert sorted(named["torqueTitles"]) == ["Elbow flexion (N·m)", "Shoulder flexion (N·m)"]
            # every tracker under its own id (ImuSample.tracker_id), the Trigno base under its source id
            wait_for(
                page, lambda p: {"trigno-synth", "00B4EB80", "00B497B2"} <= set(p["devices"]), 10, "a row per device"
            )
            assert "xsens" not in page.evaluate(PROBE)["devices"]
            # The bars show what the selected method estimated, and they move with the lift.
            wait_for(
                page,
                lambda p: p["bars"] != first["bars"] and p["fills"] != first["fills"],
                10,
                "bars and body-map colours to change",
            )
            wait_for(
                page,
                lambda p: p["bars"] == [a if a is not None else 0 for a in p["frame"]],
                5,
                "the bars to show the newest frame of the selected method",
            )
            counted = wait_for(
                page, lambda p: p["reps"] == "2", 15, "the rep counter to reach 2 (two reps in the first set)"
            )
            page.screenshot(path=str(ARTIFACTS / "dashboard.png"))
            assert_readable(page, fits_height=True)
            # an arm exercise's map is the upper body, also in a box taller than it (a new user saw the legs drawn)
            drawn = page.evaluate(
                """() => { const svg = document.querySelector('#bodymap svg'), r = svg.getBoundingClientRect();
                  const vb = svg.viewBox.baseVal, rows = [];
                  for (let fy = 0.025; fy < 1; fy += 0.05) { let n = 0;
                    for (let fx = 0.01; fx < 1; fx += 0.02) {
                      const e = document.elementFromPoint(r.x + fx * r.width, r.y + fy * r.height);
                      n += e !== null && e.classList.contains('body'); }
                    rows.push([fy, n]); }
                  return {rows, band: (r.width * vb.height / vb.width) / r.height}; }"""
            )  # per twentieth of the map's box, top to bottom: the points that hit the grey figure
            band = drawn["band"]  # the part shown, fitted in the box and centred: the share of its height it fills
            outside = [(fy, n) for fy, n in drawn["rows"] if n and abs(fy - 0.5) > band / 2 + 0.03]
            assert band < 0.9 and not outside, drawn
            # the table of sets says whose figures it holds: the report's method (so before hybrid), not the menu's
            assert page.inner_text("#sets-hint").endswith("peak / mean activation % of so")
            # Method switch: the bars follow the other method.
            other = "so" if counted["method"] == "hybrid" else "hybrid"
            page.select_option("#method", other)
            switched = wait_for(
                page,
                lambda p: p["method"] == other and p["bars"] == [a if a is not None else 0 for a in p["frame"]],
                5,
                f"the bars of method {other}",
            )
            replay.join(30)
            assert not replay.is_alive(), "the replay of the first set did not finish within 30 s"
            stopped = wait_for(page, lambda p: p["status"] == "nodata", 10, "'no data' after the replay stopped")
            assert page.is_visible("#nodata") and "it has ended or stopped sending" in page.inner_text("#nodata-detail")
            assert page.evaluate("getComputedStyle(document.querySelector('.panel.bars')).filter") == "grayscale(1)"
            assert stopped["method"] == other and switched["bars"] is not None
            # Where a frame carries measured EMG envelopes (estimator with EMG), they are drawn beside the estimate (checked
            # while the replay is stopped, so that no newer frame replaces the one given to the page).
            envelope = [0.5] + [None] * (len(switched["frame"]) - 1)
            page.evaluate(
                """([method, envelope]) => {
                const frame = {...window.mskDashboard.state.activations[method], envelope};
                const s = window.mskDashboard.state;
                window.mskDashboard.merge({topics: {['activations/' + method]: frame}, data_age_s: s.dataAge, activation_age_s: s.activationAge});
            }""",
                [other, envelope],
            )
            page.wait_for_function(
                "() => window.mskDashboard.charts.bars.data.datasets[2].data[0] !== null", timeout=5000
            )
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


class LiveStreams:
    """Publishes, 20 times a second until told to stop, what a running session does: activation frames of the
    bench press, two Xsens trackers, the Trigno base; each stream can be stopped on its own."""

    def __init__(self, zsession, session: str) -> None:
        from msk_core.model import load_pack

        self.groups = list(load_pack("bench_press").groups)
        self.running = {"activations": True, "00B4EB80": True, "00B497B2": True, "trigno": True}
        self._stop = threading.Event()
        self._zsession, self._session = zsession, session
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> LiveStreams:
        self._thread.start()
        return self

    def _run(self) -> None:
        from services.transport import messages, topics
        from services.transport.zenoh_session import declare_data_publisher, publish

        s = self._session
        publishers = {
            "activations": declare_data_publisher(
                self._zsession, topics.activations_key(s, "so"), "msk.ActivationFrame"
            ),
            "00B4EB80": declare_data_publisher(self._zsession, topics.imu_key(s, "upper_arm_r"), "msk.ImuSample"),
            "00B497B2": declare_data_publisher(self._zsession, topics.imu_key(s, "forearm_r"), "msk.ImuSample"),
            "trigno": declare_data_publisher(self._zsession, topics.emg_key(s, "trigno"), "msk.EmgChunk"),
        }
        k = 0
        while not self._stop.wait(0.05):
            k += 1
            now = time.time_ns()
            if self.running["activations"]:
                a = [0.2 + 0.6 * ((i * 7 + k) % 10) / 10 for i in range(len(self.groups))]
                publish(
                    publishers["activations"],
                    messages.ActivationFrame(
                        time_s=k * 0.05,
                        method="so",
                        groups=self.groups,
                        activations=a,
                        activation_std=[0.05] * len(a),
                        exercise="bench_press",
                        solver_status="ok",
                        publish_ns=now,
                        input_arrival_ns=now - 500_000,
                    ),
                )
            for tracker, segment in (("00B4EB80", "upper_arm_r"), ("00B497B2", "forearm_r")):
                if self.running[tracker]:
                    sample = messages.ImuSample(tracker_id=tracker, segment=segment, packet_counter=k, host_time_ns=now)
                    sample.orientation.w = 1.0
                    publish(publishers[tracker], sample)
            if self.running["trigno"]:
                publish(publishers["trigno"], trigno_chunk(k, now))
        for publisher in publishers.values():
            publisher.undeclare()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)


ROWS = """() => Object.fromEntries([...document.querySelectorAll('#devices tbody tr')].map(
    tr => [tr.dataset.device, [...tr.cells].slice(1, 3).map(c => c.textContent)]))"""
LAYOUT = """() => {
  const box = (e) => { const r = e.getBoundingClientRect(); return {x: r.x, y: r.y, w: r.width, h: r.height}; };
  const main = document.querySelector('main'), notice = document.getElementById('nodata');
  const mapPanel = document.querySelector('.panel.map').getBoundingClientRect();
  const probe = document.elementFromPoint(mapPanel.x + 20, mapPanel.y + mapPanel.height - 30);
  return {
    pill: box(document.getElementById('status')), main: box(main), notice: box(notice),
    noticeVisible: !notice.hidden && getComputedStyle(notice).display !== 'none',
    noticeBackground: getComputedStyle(notice).backgroundColor,
    noticeTitle: document.querySelector('.nodata-title').textContent,
    panelFilter: getComputedStyle(document.querySelector('.panel.bars')).filter,
    panelOpacity: Number(getComputedStyle(document.querySelector('.panel.bars')).opacity),
    mapVisibleBesideNotice: document.querySelector('.panel.map').contains(probe),
    bodyState: document.body.dataset.state,
  };
}"""


#: Readable from the rack: the drawn size of every visible text of the page (its computed font size; an SVG text's
#: times the SVG's scale on screen), the smallest ones, the colour of the labels and whether the page fits the window.
TEXT_SIZES = """() => {
  const walker = document.createTreeWalker(document.body, NodeFilter.SHOW_TEXT), sizes = [];
  for (let node = walker.nextNode(); node; node = walker.nextNode()) {
    const text = node.textContent.trim(), e = node.parentElement;
    if (!text || !e || e.closest('script, style, [hidden]') || getComputedStyle(e).visibility === 'hidden') continue;
    const range = document.createRange();
    range.selectNodeContents(node);
    const r = range.getBoundingClientRect();
    if (r.width === 0 || r.height === 0) continue;  // not rendered (display: none somewhere above)
    let px = parseFloat(getComputedStyle(e).fontSize);
    if (e instanceof SVGElement && e.ownerSVGElement) px *= e.getScreenCTM().a;
    sizes.push([Math.round(px * 10) / 10, text.slice(0, 30), e.tagName.toLowerCase() + (e.id ? '#' + e.id : '')]);
  }
  sizes.sort((a, b) => a[0] - b[0]);
  const colours = (s) => [...new Set([...document.querySelectorAll(s)].map((e) => getComputedStyle(e).color))];
  const html = document.documentElement;
  const wrapped = [...document.querySelectorAll('#sets td:not(:first-child), #devices td:nth-child(n+3)')].filter((td) => {
    const range = document.createRange();
    range.selectNodeContents(td);
    return new Set([...range.getClientRects()].map((r) => Math.round(r.top))).size > 1;  // on two lines
  }).map((td) => td.textContent);
  return {
    wrapped,
    min: sizes.length ? sizes[0][0] : null, count: sizes.length, smallest: sizes.slice(0, 5),
    panelLabels: colours('main h2, main .hint, main th, .scale, .torque-title'), headerLabels: colours('header .label'),
    overflowX: html.scrollWidth - window.innerWidth, overflowY: html.scrollHeight - window.innerHeight,
  };
}"""
MIN_TEXT_PX = 18
FOREGROUND = "rgb(29, 38, 48)"  # the panels' text colour (#1d2630); the header's is white


def assert_readable(page, *, fits_height: bool) -> dict:
    """Every visible text at least MIN_TEXT_PX, the labels in the foreground colour, nothing wider than the window
    (and, ``fits_height``, nothing below it: the landscape layout is one screen), no number of the sets' and devices'
    tables broken over two lines."""
    seen = page.evaluate(TEXT_SIZES)
    assert seen["count"] > 50 and seen["min"] >= MIN_TEXT_PX, seen
    assert seen["panelLabels"] == [FOREGROUND] and seen["headerLabels"] == ["rgb(255, 255, 255)"], seen
    assert seen["overflowX"] <= 0 and (seen["overflowY"] <= 0 or not fits_height), seen
    assert seen["wrapped"] == [], seen["wrapped"]  # a number and its unit on one line (a new user saw "25.1⏎s")
    return seen


def test_no_data_keeps_the_last_values_greyed_and_every_device_is_a_row(tmp_path, zenoh_endpoint):
    """The page fed over Zenoh without an estimator: the header shows the load event's exercise, load and set; each
    tracker and the Trigno base are rows of their own, and the tracker that stops goes silent; when the frames stop,
    the badge stays a badge and the last values stay visible, greyed out, beside a readable "No data" notice."""
    require_chromium()

    from services.transport import messages, topics
    from services.transport.zenoh_session import declare_data_publisher, publish
    from tests.dashboard_helpers import BAD_INPUT_TOPICS, BadInputs

    session = "floor"
    config = DashboardConfig(session=session, no_data_after_s=1.5)
    with dashboard_in_chromium(zenoh_endpoint, config) as (zsession, browser, page, errors):
        bad = BadInputs(zsession, session)
        bad.wait_matched(BAD_INPUT_TOPICS)
        bad.publish_every_kind()
        load = declare_data_publisher(zsession, topics.load_key(session), "msk.LoadEvent")
        publish(
            load,
            messages.LoadEvent(
                barbell_mass_kg=60,
                exercise="bench_press",
                set_number=2,
                athlete="Ana",
                names={"PMCla": "Upper chest"},
            ),
        )  # the session file's name
        node = declare_data_publisher(zsession, topics.status_key(session, "estimator"), "msk.DeviceStatus")
        publish(
            node,
            messages.DeviceStatus(
                device_id="estimator",
                kind="node",
                connected=True,
                samples_received=50,
                dropped=[messages.InputDrop(key=f"msk/{session}/joints", reason="invalid", count=2)],
            ),
        )
        streams = LiveStreams(zsession, session).start()
        try:
            page.wait_for_function("() => document.getElementById('status').dataset.state === 'live'", timeout=15000)
            page.wait_for_function("() => document.querySelectorAll('#devices tbody tr').length === 3", timeout=10000)
            rows = page.evaluate(ROWS)
            assert sorted(rows) == ["00B497B2", "00B4EB80", "trigno"] and {r[0] for r in rows.values()} == {
                "delivering"
            }
            assert [page.inner_text(f"#{k}") for k in ("exercise", "load", "set")] == [
                "bench press",
                "60.0 kg",
                "2",
            ]
            # who lifts, and on which rack, shown whole at 1280x800 (the header cut them to "msk-live · An…")
            shown = page.evaluate(
                """() => ['#athlete', '.brand .where'].map((selector) => {
                  const e = document.querySelector(selector);
                  return [e.textContent, e.clientWidth > 0 && e.scrollWidth <= e.clientWidth];
                })"""
            )
            assert shown == [["Ana", True], [f"msk-live · {session}", True]], shown
            assert page.title().startswith(f"Ana · {session}"), page.title()
            labels = page.evaluate(PROBE)["labels"]
            assert "Upper chest" in labels and "Brachialis" in labels and "PMCla" not in labels, labels
            page.wait_for_function(
                "() => document.querySelector('#nodes tr[data-node=\"dashboard\"] td:nth-child(4)').textContent === '5'",
                timeout=10000,
            )
            assert page.inner_text('#nodes tr[data-node="estimator"]').split("\t")[1:] == ["running", "50", "2"]
            streams.running["00B4EB80"] = False  # the upper-arm tracker stops; the others go on
            page.wait_for_function(
                "() => document.querySelector('#devices tr[data-device=\"00B4EB80\"] td:nth-child(2)').textContent === 'silent'",
                timeout=10000,
            )
            rows = page.evaluate(ROWS)
            assert rows["00B497B2"][0] == rows["trigno"][0] == "delivering" and int(rows["00B4EB80"][1]) > 0
            page.locator(".panel.side").screenshot(path=str(ARTIFACTS / "dashboard-devices.png"))
            live = page.evaluate(LAYOUT)
        finally:
            streams.stop()
        page.wait_for_function("() => document.getElementById('status').dataset.state === 'nodata'", timeout=10000)
        page.wait_for_timeout(300)
        page.screenshot(path=str(ARTIFACTS / "dashboard-nodata.png"))
        stale = page.evaluate(LAYOUT)
        bad.close()
        assert not errors, errors
        browser.close()
    assert not live["noticeVisible"] and live["panelFilter"] == "none" and live["bodyState"] == "live"
    # the badge stays a badge in the header
    assert stale["pill"]["h"] < 60 and stale["pill"]["w"] < 300 and stale["pill"]["y"] < stale["main"]["y"]
    # a notice of its own size, opaque and readable, not a veil over the page
    assert (
        stale["noticeVisible"]
        and stale["noticeTitle"] == "No data"
        and stale["noticeBackground"] == "rgb(255, 255, 255)"
    )
    assert stale["notice"]["w"] * stale["notice"]["h"] < 0.3 * stale["main"]["w"] * stale["main"]["h"]
    # the last values are still there, greyed out, and not covered
    assert (
        "grayscale(1)" in stale["panelFilter"] and 0.3 < stale["panelOpacity"] < 1 and stale["mapVisibleBesideNotice"]
    )
