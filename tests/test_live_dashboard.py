"""As a user would, together: ``msk live --sim``, then ``msk dashboard`` started afterwards in another process with no
endpoint flags, looked at in Chromium (Playwright with Debian's chromium); after the session stops, the last values
stay greyed beside a readable "No data" notice; ``msk report`` on the recording names exercise, load and date."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import time

from tests.conftest import free_tcp_port
from tests.dashboard_helpers import ARTIFACTS, launch_chromium, require_chromium
from tests.test_dashboard_browser import LAYOUT, ROWS
from tests.test_live_together import REPO, LiveProcess, _environment, _msk

FACTS = "() => ['exercise', 'load', 'set'].map(id => document.getElementById(id).textContent)"


def _dashboard(port: int, env: dict) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "services.cli", "dashboard", "--port", str(port)],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )


def test_dashboard_attached_to_a_running_live_session_in_chromium(tmp_path):
    require_chromium()
    from playwright import sync_api

    env = _environment(tmp_path)
    out = tmp_path / "live"
    live = LiveProcess(out, env)
    port = free_tcp_port()
    dashboard = None
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    try:
        live.wait_running()
        dashboard = _dashboard(port, env)
        with sync_api.sync_playwright() as playwright:
            browser = launch_chromium(playwright)
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            errors: list[str] = []
            page.on("pageerror", lambda error: errors.append(str(error)))
            deadline = time.monotonic() + 60
            while True:  # the server takes a few seconds to import and bind
                try:
                    page.goto(f"http://127.0.0.1:{port}/")
                    break
                except sync_api.Error:
                    assert time.monotonic() < deadline and dashboard.poll() is None, "msk dashboard did not serve"
                    time.sleep(0.5)
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
            page.screenshot(path=str(ARTIFACTS / "live-dashboard.png"))
            printed = _msk("subscribe", "msk/sim/activations/*", "--count", "2", env=env)
            assert printed.returncode == 0 and printed.stdout.count("msk.ActivationFrame") == 2, printed.stderr
            code, output, summary = live.stop()
            assert code == 0, output
            page.wait_for_function("() => document.getElementById('status').dataset.state === 'nodata'", timeout=15000)
            page.wait_for_timeout(300)
            page.screenshot(path=str(ARTIFACTS / "live-dashboard-stopped.png"))
            stale = page.evaluate(LAYOUT)
            facts_after = page.evaluate(FACTS)
            assert not errors, errors
            browser.close()
    finally:
        live.kill()
        if dashboard is not None and dashboard.poll() is None:
            dashboard.send_signal(signal.SIGINT)
            try:
                dashboard_output = dashboard.communicate(timeout=20)[0]
            except subprocess.TimeoutExpired:
                dashboard.kill()
                dashboard_output = dashboard.communicate()[0]
    assert "attached to the running session 'sim'" in dashboard_output, dashboard_output
    # the last values, greyed, beside a readable notice; not one opaque box
    assert stale["noticeVisible"] and stale["noticeTitle"] == "No data" and stale["mapVisibleBesideNotice"], stale
    assert "grayscale(1)" in stale["panelFilter"] and facts_after == ["bench press", "50.0 kg", "1"]
    # the recording's report names exercise, load and date in its header
    reported = _msk("report", *(summary["recordings"]), "--out", str(tmp_path / "report"), env=env, timeout=180)
    assert reported.returncode == 0, reported.stderr
    page_text = re.sub(r"<style.*?</style>|<[^>]+>", " ", (tmp_path / "report" / "report.html").read_text(), flags=re.S)
    header = " ".join(page_text.split())[:300]
    assert re.search(r"\d{4}-\d{2}-\d{2} \d{2}:\d{2}", header) and "bench press" in header and "50" in header, header
    json.loads((out / "session.json").read_text())  # still there as the session's record
