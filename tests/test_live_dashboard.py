"""As a user would, together: ``msk dashboard`` opened on the tablet first, with no endpoint flags, then ``msk live
--sim`` started, which the page follows; looked at in Chromium (Playwright with Debian's chromium); after the session stops, the last values
stay greyed beside a readable "No data" notice; a declared exercise the session does not estimate is named as the
cause of the pause; ``msk report`` on the recording names exercise, load and date."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import time
from pathlib import Path

from tests.conftest import free_tcp_port
from tests.dashboard_helpers import ARTIFACTS, chromium_page, require_chromium
from tests.live_helpers import LiveProcess, live_environment, run_msk, start_msk
from tests.test_dashboard_browser import LAYOUT, MIN_TEXT_PX, ROWS, assert_readable

LIVE = "() => document.getElementById('status').dataset.state === 'live'"
FACTS = "() => ['exercise', 'load', 'set'].map(id => document.getElementById(id).textContent)"
BOX = "(s) => { const r = document.querySelector(s).getBoundingClientRect(); return {x: r.x, y: r.y, width: r.width, height: r.height}; }"
OVERLAY = """() => { const d = window.mskDashboard.charts.traces.data.datasets, xs = d.flatMap((s) => s.data.map((p) => p.x));
  return {reps: d.length, x: [Math.min(...xs), Math.max(...xs)], scale: window.mskDashboard.charts.traces.options.scales.x.max}; }"""
OVERLAID = f"() => {{ const o = ({OVERLAY})(); return o.scale === 100 && o.reps >= 1; }}"
#: What a coach reads from the rack: bar labels, traces, electrodes, fatigue, and the sizes they are drawn at.
COACH = """() => {
  const c = window.mskDashboard.charts, s = window.mskDashboard.state;
  const px = (e) => (e ? parseFloat(getComputedStyle(e).fontSize) : null);
  const traced = c.traces ? c.traces.data.datasets.filter((d) => d.borderWidth > 0) : [];
  return {
    labels: c.bars ? c.bars.data.labels.map((l) => (Array.isArray(l) ? l.join(' ') : l)) : [],
    barLabelPx: c.bars ? c.bars.options.scales.y.ticks.font.size : null,
    barLabelColour: c.bars ? c.bars.options.scales.y.ticks.color : null,
    traces: traced.map((d) => [d.label, d.data.length, d.data.slice(-20).map((p) => p.y)]),
    chips: [...document.querySelectorAll('#trace-groups .chip.on')].map((e) => e.textContent),
    electrodes: [...document.querySelectorAll('#electrodes tbody tr')].map((r) => [r.cells[0].textContent, r.dataset.state]),
    electrodePx: px(document.querySelector('#electrodes td')),
    devicePx: px(document.querySelector('#devices td')),
    fatigue: [...document.querySelectorAll('#fatigue tbody tr')].map((r) => [...r.cells].map((c) => c.textContent)),
    fatigueVisible: !document.getElementById('fatigue-panel').hidden,
    mapPart: (document.querySelector('#bodymap svg') || {dataset: {}}).dataset.part,
    set: document.getElementById('set').textContent, rep: document.getElementById('reps').textContent,
    inRep: s.reps !== null && s.reps.phase !== null && s.reps.phase >= 0,
  };
}"""


def _coach_view(page, screenshots: Path) -> None:
    """Display names, readable sizes, a trace that moves, every electrode's state and the fatigue panel with values
    (a rep ended since the estimator started), in the running session; screenshots of the page and of the traces."""
    deadline = time.monotonic() + 30
    view = page.evaluate(COACH)
    while not (view["fatigueVisible"] and any(int(row[1]) >= 2 for row in view["fatigue"])):
        assert time.monotonic() < deadline, f"waited 30 s for a fatigue row with 2 reps; the page shows {view}"
        time.sleep(0.5)
        view = page.evaluate(COACH)
    assert any("Triceps brachii" in label for label in view["labels"]) and "TriLat" not in view["labels"], view
    assert view["barLabelPx"] >= 18 and view["barLabelColour"] == "#1d2630", view
    assert view["electrodePx"] >= MIN_TEXT_PX and view["devicePx"] >= MIN_TEXT_PX and view["mapPart"] == "upper", view
    assert re.fullmatch(r"\d+( done)?", view["set"]) and view["rep"].isdigit(), view  # set N (done), rep n of it
    assert view["electrodes"] and {state for _, state in view["electrodes"]} <= {"good", "check", "bad", "unknown"}
    assert "good" in {state for _, state in view["electrodes"]}, view["electrodes"]
    assert len(view["chips"]) == 3 and len(view["traces"]) >= 3, view  # estimate and envelope of the default three
    for row in view["fatigue"]:  # muscle, reps, last rep's median frequency, slope per rep, change since the start
        assert row[2] == "–" or 30 <= float(row[2].split()[0]) <= 300, row
    if os.environ.get("MSK_SCREENSHOT_DIR"):  # the docs' pictures during a rep (the simulator rests between sets)
        deadline = time.monotonic() + 60
        while not page.evaluate(COACH)["inRep"] and time.monotonic() < deadline:
            time.sleep(0.2)
        page.wait_for_timeout(1500)  # most of the rep on the traces
    traces = page.evaluate(BOX, "#traces")  # clipped from the page: the canvas redraws all the time
    first = page.screenshot(clip=traces)
    page.screenshot(path=str(screenshots / "dashboard-live.png"))
    page.wait_for_timeout(1000)
    later = page.evaluate(COACH)
    assert page.screenshot(clip=traces) != first, "the traces did not move in 1 s"
    assert [t[2] for t in later["traces"]] != [t[2] for t in view["traces"]], (view["traces"], later["traces"])
    page.screenshot(path=str(screenshots / "dashboard-traces-fatigue.png"), clip=page.evaluate(BOX, ".panel.side"))
    # the other mode: the set's reps overlaid on rep time (0-100 %), each chosen muscle in its colour
    page.click("#trace-reps")
    page.wait_for_function(OVERLAID, timeout=10000)
    overlay = page.evaluate(OVERLAY)
    assert overlay["x"][0] >= 0 and overlay["x"][1] <= 100 and overlay["reps"] >= 1, overlay
    page.wait_for_timeout(300)  # the shorter hint of this mode moves the chart up: the picture where it is now
    page.locator("#traces").screenshot(path=str(screenshots / "dashboard-rep-overlay.png"))
    page.click("#trace-time")
    readable = assert_readable(page, fits_height=True)  # 1280x800: every text >= 18 px, one screen
    # the tablet held upright: body map and bars side by side, the side panel below them (the page scrolls)
    page.set_viewport_size({"width": 800, "height": 1280})
    page.wait_for_function(LIVE, timeout=15000)  # the picture of a live page, not one waiting for data
    page.wait_for_timeout(500)
    upright = assert_readable(page, fits_height=False)
    panels = {name: page.evaluate(BOX, f".panel.{name}") for name in ("map", "bars", "side")}
    assert panels["map"]["x"] < panels["bars"]["x"] and abs(panels["map"]["y"] - panels["bars"]["y"]) < 1, panels
    assert panels["side"]["y"] >= panels["bars"]["y"] + panels["bars"]["height"], panels
    page.screenshot(path=str(screenshots / "dashboard-portrait.png"))
    page.set_viewport_size({"width": 1280, "height": 800})
    print(f"smallest text: {readable['min']} px at 1280x800, {upright['min']} px at 800x1280 (>= {MIN_TEXT_PX})")
    print("coach view:", json.dumps({k: later[k] for k in ("labels", "chips", "electrodes", "fatigue")}))


def _declared_another_exercise(page, env: dict[str, str]) -> None:
    """The operator declares the deadlift in the bench session: the estimator pauses (it estimates bench press only),
    and the page says so, not "is the estimator running?"; declaring the bench press again resumes the estimates."""
    declared = run_msk("load", "--exercise", "deadlift", env=env)
    assert declared.returncode == 0, declared.stderr
    page.wait_for_function("() => document.getElementById('status').dataset.state === 'nodata'", timeout=15000)
    notice = page.inner_text("#nodata-detail")
    assert page.inner_text(".nodata-title") == "Estimates paused", page.inner_text("#nodata")
    assert page.inner_text("#status").lower() == "paused", page.inner_text("#status")
    assert "declares deadlift" in notice and "this session estimates bench press" in notice, notice
    assert "msk load --exercise bench_press" in notice and "is the estimator running" not in notice, notice
    page.screenshot(path=str(ARTIFACTS / "live-dashboard-paused.png"))
    resumed = run_msk("load", "--exercise", "bench_press", env=env)
    assert resumed.returncode == 0, resumed.stderr
    page.wait_for_function(LIVE, timeout=15000)
    assert page.evaluate(FACTS)[0] == "bench press"


def test_dashboard_opened_before_live_follows_the_session_in_chromium(tmp_path):
    require_chromium()
    from playwright import sync_api

    env = live_environment(tmp_path)
    out = tmp_path / "live"
    live = None
    port = free_tcp_port()
    dashboard = None
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    # MSK_SCREENSHOT_DIR=docs/img: the pictures of docs/dashboard.md, from this run
    screenshots = Path(os.environ.get("MSK_SCREENSHOT_DIR") or ARTIFACTS)
    try:
        dashboard = start_msk("dashboard", "--port", str(port), env=env)
        with sync_api.sync_playwright() as playwright:
            browser, page, errors = chromium_page(playwright)
            deadline = time.monotonic() + 60
            while True:  # the server takes a few seconds to import and bind
                try:
                    page.goto(f"http://127.0.0.1:{port}/")
                    break
                except sync_api.Error:
                    assert time.monotonic() < deadline and dashboard.poll() is None, "msk dashboard did not serve"
                    time.sleep(0.5)
            page.wait_for_function("() => document.getElementById('session').textContent === 'lab'", timeout=15000)
            assert page.evaluate("() => document.getElementById('status').dataset.state") != "live"
            assert page.evaluate(FACTS)[2] == "–" and page.inner_text("#reps") == "–"  # no set yet, no rep count
            live = LiveProcess(out, env)
            live.wait_running()
            page.wait_for_function("() => document.getElementById('session').textContent === 'sim'", timeout=30000)
            page.wait_for_function("() => document.getElementById('status').dataset.state === 'live'", timeout=30000)
            page.wait_for_function(f"() => ({FACTS})()[0] !== '–' && ({FACTS})()[2] !== '–'", timeout=15000)
            assert page.evaluate(FACTS) == ["bench press", "50.0 kg", "1"]
            deadline = time.monotonic() + 15
            rows = page.evaluate(ROWS)
            devices = ("00B497B2", "00B4EB80", "trigno")  # each under its own id (beside the estimator's envelopes)
            while set(rows) - {"EMG envelopes"} != set(devices) or {rows[d][0] for d in devices} != {"delivering"}:
                assert time.monotonic() < deadline, f"waited 15 s for a delivering row per device; rows: {rows}"
                time.sleep(0.2)
                rows = page.evaluate(ROWS)
            first_reps = int(page.inner_text("#reps"))
            page.wait_for_function(
                f"() => Number(document.getElementById('reps').textContent) > {first_reps}", timeout=30000
            )  # the rep counter moves
            _coach_view(page, screenshots)
            _declared_another_exercise(page, env)
            page.screenshot(path=str(ARTIFACTS / "live-dashboard.png"))
            printed = run_msk("subscribe", "msk/sim/activations/*", "--count", "2", env=env)
            assert printed.returncode == 0 and printed.stdout.count("msk.ActivationFrame") == 2, printed.stderr
            facts_before = page.evaluate(FACTS)  # the simulator plays sets with rests: the set number moves on
            code, output, summary = live.stop()
            assert code == 0, output
            # the frames the estimator left while the deadlift was declared: counted, and said in the summary
            assert summary["joint_frames_paused"] > 0 and "estimates paused for about" in output, output[-2000:]
            # the estimator's fatigue values are in the summary, per electrode and set
            sets = [s for per_electrode in summary["fatigue"].values() for s in per_electrode]
            assert sets and max(s["reps"] for s in sets) >= 2, summary["fatigue"]
            page.wait_for_function("() => document.getElementById('status').dataset.state === 'nodata'", timeout=15000)
            page.wait_for_timeout(300)
            page.screenshot(path=str(ARTIFACTS / "live-dashboard-stopped.png"))
            stale = page.evaluate(LAYOUT)
            facts_after = page.evaluate(FACTS)
            assert not errors, errors
            browser.close()
    finally:
        if live is not None:
            live.kill()
        if dashboard is not None and dashboard.poll() is None:
            dashboard.send_signal(signal.SIGINT)
            try:
                dashboard_output = dashboard.communicate(timeout=20)[0]
            except subprocess.TimeoutExpired:
                dashboard.kill()
                dashboard_output = dashboard.communicate()[0]
    assert "no running msk live announced" in dashboard_output, dashboard_output  # opened first: waits on 'lab'
    assert "attached to the running session 'sim'" in dashboard_output, dashboard_output
    # the last values, greyed, beside a readable notice; not one opaque box
    assert stale["noticeVisible"] and stale["noticeTitle"] == "No data" and stale["mapVisibleBesideNotice"], stale
    assert "grayscale(1)" in stale["panelFilter"] and facts_after[:2] == facts_before[:2], (facts_before, facts_after)
    # the set under way ends with the estimator's last status, when it reaches the page before the session is gone
    set_number = facts_before[2].removesuffix(" done")
    assert facts_after[2] in (facts_before[2], f"{set_number} done"), (facts_before, facts_after)
    # the recording's report names exercise, load and date in its header
    reported = run_msk("report", *(summary["recordings"]), "--out", str(tmp_path / "report"), env=env, timeout=180)
    assert reported.returncode == 0, reported.stderr
    page_text = re.sub(r"<style.*?</style>|<[^>]+>", " ", (tmp_path / "report" / "report.html").read_text(), flags=re.S)
    header = " ".join(page_text.split())[:300]
    assert re.search(r"\d{4}-\d{2}-\d{2} \d{2}:\d{2}", header) and "bench press" in header and "50" in header, header
    json.loads((out / "session.json").read_text())  # still there as the session's record
