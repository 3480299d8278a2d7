"""`msk dashboard --pki` checks what it serves with before serving, and says what went wrong in one line:
its HTTPS certificate and key (readable, the key the certificate's, valid now, from the deployment's CA), and the
tablet tokens file (at start; and while it runs, a file gone bad refuses every tablet with 503 and one log line). A bad
key printed an ssl error and the process ran on without listening; an expired certificate was served; a corrupt tokens
file gave 500 and a traceback per request; a revoked tablet's page said "reconnecting" for ever (found by QA of the
secured deployment). Real certificates of `msk certs`, a real dashboard server and, for the page, Chromium."""

from __future__ import annotations

import datetime as dt
import http.client
import logging
import shutil
import ssl
import subprocess
import sys
import time
from pathlib import Path

import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec

from msk_core.errors import InputError
from services.surfaces.dashboard.access import TokenStore
from services.surfaces.dashboard.app import DashboardConfig, DashboardServer
from services.transport.zenoh_session import ZenohOptions, free_loopback_endpoint
from tests.conftest import free_tcp_port
from tests.test_security_tls_files import certs, deployment_ca, leaf

NOW = dt.datetime.now(dt.UTC)
DAY = dt.timedelta(days=1)


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> Path:
    pki = tmp_path_factory.mktemp("dashboard-checks") / "pki"
    certs("--out", str(pki), "--router-host", "localhost", "--router-host", "127.0.0.1")
    return pki


def _server(pki: Path) -> DashboardServer:
    """A dashboard server over ``pki`` whose bridge is a Zenoh peer of its own (nothing to attach to)."""
    options = ZenohOptions(mode="peer", listen=(free_loopback_endpoint(),))
    return DashboardServer(options, DashboardConfig(session="s"), port=free_tcp_port(), pki=pki)


def _broken(pki: Path, folder: Path, case: str) -> tuple[Path, str]:
    """A copy of ``pki`` with its dashboard certificate or key broken as ``case`` says; (copy, expected start)."""
    copy = folder / "pki"
    shutil.copytree(pki, copy)
    if case == "key of another run":
        other = ec.generate_private_key(ec.SECP256R1())
        pem = other.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )
        (copy / "dashboard.key").write_bytes(pem)
        return copy, f"{copy / 'dashboard.key'}, field 'dashboard key': not the key of {copy / 'dashboard.pem'}"
    dates = {"expired": (NOW - 30 * DAY, NOW - DAY), "not yet valid": (NOW + DAY, NOW + 30 * DAY)}[case]
    leaf(folder, "dashboard", deployment_ca(pki), not_before=dates[0], not_after=dates[1], cn="msk-dashboard")
    for suffix in ("pem", "key"):
        shutil.copy(folder / f"dashboard.{suffix}", copy / f"dashboard.{suffix}")
    said = "certificate expired" if case == "expired" else "certificate not valid before"
    return copy, f"{copy / 'dashboard.pem'}, field 'dashboard certificate': {said}"


@pytest.mark.parametrize("case", ["key of another run", "expired", "not yet valid"])
def test_an_unusable_https_certificate_is_refused_naming_the_file(pki, tmp_path, case):
    broken, expected = _broken(pki, tmp_path, case)
    with pytest.raises(InputError) as raised:
        _server(broken)
    assert str(raised.value).startswith(expected), str(raised.value)


def test_the_command_with_a_bad_key_exits_non_zero_at_once(pki, tmp_path):
    """The process ran on for ever (its Zenoh bridge up, nothing listening); now it says the file and exits 2."""
    broken, expected = _broken(pki, tmp_path, "key of another run")
    started = time.monotonic()
    process = subprocess.run(
        [
            sys.executable, "-m", "services.cli", "dashboard", "--pki", str(broken), "--port", str(free_tcp_port()),
            "--session", "s", "--mode", "peer", "--connect", free_loopback_endpoint(),
        ],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    elapsed = time.monotonic() - started
    assert process.returncode == 2, process.stderr
    errors = [line for line in process.stderr.splitlines() if "error" in line]
    assert len(errors) == 1 and errors[0].startswith(f"msk dashboard: error: {expected}"), process.stderr
    assert "waited" not in process.stderr and elapsed < 30, (elapsed, process.stderr)


def _get(pki: Path, port: int, path: str, cookie: str | None = None) -> tuple[int, bytes]:
    context = ssl.create_default_context(cafile=str(pki / "ca.pem"))
    connection = http.client.HTTPSConnection("127.0.0.1", port, context=context, timeout=10)
    try:
        connection.request("GET", path, headers={"Cookie": cookie} if cookie else {})
        response = connection.getresponse()
        return response.status, response.read()
    finally:
        connection.close()


def test_a_corrupt_tokens_file_is_refused_at_start_and_answered_503_while_running(pki, tmp_path, caplog):
    copy = tmp_path / "pki"
    shutil.copytree(pki, copy)
    tokens = copy / "tablet-tokens.json"
    tokens.write_text('{"ipad1": {"sha256": "')
    with pytest.raises(InputError, match=rf"^{tokens}: cannot read the tablet tokens"):
        _server(copy)
    tokens.write_text("[]")
    with pytest.raises(InputError, match=rf"^{tokens}: the tablet tokens file must hold an object"):
        _server(copy)
    tokens.unlink()
    token = TokenStore(copy).issue("ipad1")
    good = tokens.read_text()
    server = _server(copy)
    server.start()
    try:
        cookie = f"msk_tablet={token}"
        assert _get(copy, server.port, "/", cookie)[0] == 200
        tokens.write_text('{"ipad1": {"sha256": "')  # goes bad while the dashboard runs
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            answers = [_get(copy, server.port, path, cookie) for path in ("/", "/config.json", "/")]
            login = _get(copy, server.port, f"/login?token={token}")
        assert [status for status, _ in answers] == [503, 503, 503] and login[0] == 503
        assert str(tokens).encode() in answers[0][1]
        errors = [r for r in caplog.records if r.levelno >= logging.WARNING]
        assert len(errors) == 1 and str(tokens) in errors[0].getMessage(), [r.getMessage() for r in errors]
        assert all(r.exc_info is None for r in caplog.records)  # no traceback
        tokens.write_text(good)  # repaired: the tablet is back without a restart
        assert _get(copy, server.port, "/", cookie)[0] == 200
    finally:
        server.stop()


def test_a_revoked_tablet_is_told_its_access_was_withdrawn_and_stops_retrying(pki, tmp_path):
    from tests.dashboard_helpers import CHROMIUM, CHROMIUM_ARGS, require_chromium

    require_chromium()
    from playwright import sync_api

    copy = tmp_path / "pki"
    shutil.copytree(pki, copy)
    token = TokenStore(copy).issue("coach-ipad")
    server = _server(copy)
    server.start()
    try:
        with sync_api.sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
            try:
                page = browser.new_context(ignore_https_errors=True).new_page()
                sockets: list[str] = []
                page.on("websocket", lambda ws: sockets.append(ws.url))
                page.goto(f"https://127.0.0.1:{server.port}/login?token={token}")
                page.wait_for_function("() => window.mskDashboard.state.connection === 'open'", timeout=20_000)
                TokenStore(copy).revoke("coach-ipad")
                page.wait_for_function("() => window.mskDashboard.state.connection === 'withdrawn'", timeout=10_000)
                opened = len(sockets)
                time.sleep(1.6)  # a page that retries would have tried twice by now (after 0.5 s, then 1 s)
                assert len(sockets) == opened == 1, sockets
                assert page.inner_text("#status") == "ACCESS WITHDRAWN"
                assert page.inner_text(".nodata-title") == "Access withdrawn"
                detail = page.inner_text("#nodata-detail")
                assert "access to the dashboard was withdrawn" in detail and "ask the operator for a new link" in detail
                page.reload()  # a reload is refused by the server (401), not a page that retries
                assert "needs a tablet token" in page.content()
            finally:
                browser.close()
    finally:
        server.stop()
