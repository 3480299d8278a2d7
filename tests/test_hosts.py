"""The secured deployment across hosts, for real (services/bench/hosts.py): the rack PC (simulated Trigno and Xsens
trackers, ``msk drivers``, ``msk recorder``, ``msk router``), a server (``msk kinematics``, ``msk estimator``) and a
tablet (``msk subscribe`` as the tablet role) each in its own Linux network namespace, joined by veth links to a
switch, with the certificates and access control of ``msk certs``. Faults between hosts: the server's link down 3 s,
the tablet's link down 3 s, the router restarted. Counted: what the drivers published and the rack's recorder holds,
what the estimator got and published after each fault, what the tablet received. Needs root (skips otherwise)."""

from __future__ import annotations

import contextlib
import io
import json
import math
import re
import time
from pathlib import Path

import pytest

from services.bench import hosts
from services.cli import main

pytestmark = pytest.mark.slow

#: a bound on every wait for the estimator to publish again, not a speed goal (docs/deployment.md has the figures)
RESUME_BOUND_S = 30.0
DOWN_S = 3.0
#: the server's outage as the estimator counts it: from its last input before the cable went to its first after it
#: came back; at least the time the cable was out less one threshold, at most that plus the issue's resume bound (2 s)
OUTAGE_BOUNDS_S = (DOWN_S - 0.5, DOWN_S + 2.0)
#: frames `so` may flag reserve (torque beyond capacity): 12 of 3569 (0.3 %) offline on the trial's aligned IMU data
#: at its load, 11 of 3746 in a run; desynchronised trackers gave 5-9 %
RESERVE_SHARE = 0.02


@pytest.fixture
def deployment(tmp_path):
    reason = hosts.unavailable()
    if reason is not None:
        pytest.skip(f"the deployment across network namespaces is not run: {reason}")
    with hosts.Hosts() as made:
        yield hosts.Deployment(made, tmp_path)
    left = hosts.namespaces() & set(made.names.values())
    assert not left, f"namespaces left behind: {left}"


def test_secured_deployment_across_hosts_survives_link_and_router_faults(deployment, tmp_path):
    try:
        deployment.start()
        faults = hosts.run_faults(deployment, down_s=DOWN_S, settle_s=2.0, timeout_s=RESUME_BOUND_S)
        browser_from = time.time_ns()  # Chromium's start takes the cores: latencies are reported before it
        browser = _tablet_browser(deployment, tmp_path)
    finally:
        logs = deployment.stop()
    result = hosts.outcome(deployment, faults, logs, until_ns=browser_from)
    print(json.dumps(result, indent=1))
    server, tablet, router = result["faults"]
    assert result["emg_published"] > 0 and result["imu_published"] > 0, logs.get("drivers")
    # every EMG sample the drivers published is in the rack's recording once, or counted missing in an index gap
    assert result["emg_repeats"] == 0
    assert result["emg_samples"] + result["emg_samples_missing"] == result["emg_published"], result
    # the server's and the tablet's outages cost the rack PC's recorder nothing: device data never left the rack
    assert server["emg_samples_missing"] == 0 and tablet["emg_samples_missing"] == 0, result["faults"]
    # the server got nothing while its cable was out (what it held when it went is not counted), and published
    # again after it came back
    assert server["frames_during"] == 0, server
    assert math.isfinite(server["resume_s"]) and server["resume_s"] < RESUME_BOUND_S, server
    # the estimator counted the server's outage in its status: one outage of about the 3 s the cable was out, every
    # input stream silent in it (the EMG and the joint angles: what crosses the server's link to it)
    assert len(server["estimator_outages"]) == 1, server
    outage = server["estimator_outages"][0]
    assert OUTAGE_BOUNDS_S[0] <= outage["s"] <= OUTAGE_BOUNDS_S[1], server
    assert "joints" in outage["keys"] and any(key.startswith("emg/") for key in outage["keys"]), server
    # and in its summary: that one and the router's (and any other silence it had, each in the final status too)
    counted_outages = re.search(r"(\d+) input outages? \(([\d.]+) s, longest ([\d.]+) s\)", result["estimator_summary"])
    assert counted_outages is not None, result["estimator_summary"]
    assert int(counted_outages.group(1)) == result["estimator_outages"]["count"] >= 2, result
    assert float(counted_outages.group(3)) >= outage["s"] - 0.05, result
    # the tablet's outage does not stop the estimator; the tablet receives again when its cable is back
    assert tablet["frames_during"] > 50, tablet
    assert math.isfinite(tablet["tablet_resume_s"]), tablet
    # every node reconnects to a restarted router by itself: activation frames again, at the recorder and the tablet
    assert math.isfinite(router["resume_s"]) and math.isfinite(router["tablet_resume_s"]), router
    # every joint frame (the kinematics node's, on the server) that reached the rack was estimated; activation frames
    # are newest-wins (docs/topics.md, "Delivery"): a burst after an outage may drop some on the way, counted here
    assert result["estimator_inputs"] > 0 and abs(result["frames_estimated"] - result["joints"]) <= 5, result
    # every frame's input is a pose of the lift: the rack's simulators sample one trial on one clock (as msk live's),
    # and the router restart's gap (IMU publications lost on their way) keeps the kinematics' calibration instead of
    # redoing it mid-rep. Unsynchronised trackers or a recalibration there made up to 2/3 of the frames invalid_input
    # (elbow 90 deg off), and 5-9 % reserve; the trial at its own load (50 kg) gives 0.3 % reserve offline
    assert "calibrations 1 (gaps: 0 new sets" in result["kinematics_summary"], result["kinematics_summary"]
    assert result["estimator_flagged"].get("invalid_input", 0) == 0, (result["estimator_invalid"], result)
    assert result["estimator_flagged"].get("reserve", 0) <= RESERVE_SHARE * result["frames_estimated"], result
    # the router's restart: the estimator counts the EMG it missed while the router was away (in its summary) and
    # the outage (status); the recorder fetches again what it missed from the drivers' caches (1000 messages per key,
    # 13 s of EMG) and counts what they no longer held, exactly: the file's EMG gap in chunks is the count it gives
    counted = re.search(r"EMG: (\d+) chunks, (\d+) gaps \((\d+) samples lost\)", result["estimator_summary"])
    assert counted is not None, result["estimator_summary"]
    assert int(counted.group(1)) > 0 and int(counted.group(3)) > 0, result
    assert router["estimator_outages"], router
    recorder = result["recorder_outages"]
    assert recorder["missed"] > 0 and recorder["recovered"] <= recorder["missed"], result
    emg_lost = sum(n for key, n in result["recorder_lost"].items() if "/emg/" in key)
    if emg_lost == 0:  # everything fetched again: the file has every EMG sample
        assert result["emg_samples_missing"] == 0, result
    else:  # the file misses exactly those chunks' samples
        smallest, largest = result["emg_chunk_sizes"]
        assert emg_lost * smallest <= result["emg_samples_missing"] <= emg_lost * largest, result
    assert recorder["missed"] - recorder["recovered"] == sum(result["recorder_lost"].values()), result
    # the tablet's role reads activations and status only, and got them across the switch
    assert result["frames_at_tablet"] > 0 and result["statuses_at_tablet"] > 0
    # the dashboard on the rack PC, from the tablet's browser: nothing without a token, the live session with one
    print(f"browser on the tablet: {browser}")
    if "skipped" not in browser:
        assert browser["without_token"] == 401 and browser["websockets_without_token"] == 0, browser
        assert not browser["session_data_without_token"], browser
        assert browser["with_token"] == 200 and browser["groups_shown"] > 0, browser


def _tablet_browser(deployment: hosts.Deployment, work: Path) -> dict:
    """Debian's Chromium on the tablet (its network namespace), trusting the deployment's CA (certificate errors not
    ignored), against ``msk dashboard --pki`` on the rack PC: what it got without a token and with one."""
    from tests.dashboard_helpers import CHROMIUM, CHROMIUM_ARGS, chromium_trusting

    environment = chromium_trusting(deployment.pki / "ca.pem", work / "home")
    if not Path(CHROMIUM).is_file() or environment is None:
        return {"skipped": f"needs {CHROMIUM} and NSS's certutil (apt-get install chromium libnss3-tools)"}
    sync_api = pytest.importorskip("playwright.sync_api")
    url = deployment.start_dashboard()
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        main(["certs", "tablet-token", "tablet-1", "--out", str(deployment.pki), "--dashboard-url", url])
    login = next(line for line in out.getvalue().splitlines() if line.startswith("https://"))
    browser_on_tablet = deployment.hosts.executable("tablet", CHROMIUM, work / "chromium-on-tablet")
    seen: dict = {}
    with sync_api.sync_playwright() as playwright:
        browser = playwright.chromium.launch(
            executable_path=str(browser_on_tablet), headless=True, args=CHROMIUM_ARGS, env=environment
        )
        try:
            page = browser.new_context(ignore_https_errors=False).new_page()
            sockets: list[str] = []
            page.on("websocket", lambda ws: sockets.append(ws.url))
            refused = page.goto(f"{url}/")
            seen["without_token"] = refused.status if refused is not None else None
            seen["session_data_without_token"] = deployment.session in page.content() or "PMCla" in page.content()
            seen["websockets_without_token"] = len(sockets)
            opened = page.goto(login)
            seen["with_token"] = opened.status if opened is not None else None
            page.wait_for_function(
                "() => window.mskDashboard && window.mskDashboard.state.activations.so", timeout=60_000
            )
            seen["groups_shown"] = page.evaluate("() => window.mskDashboard.state.activations.so.groups.length")
        finally:
            browser.close()
    return seen
