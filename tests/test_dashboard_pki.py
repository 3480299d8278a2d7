"""`msk dashboard --pki` as a real process behind a real secured `msk router`: HTTPS with the certificate `msk certs`
issued from the deployment's CA, and a token per tablet (`msk certs tablet-token` / `revoke-token`). Without a valid
token the page, its files and its websocket are refused and nothing of the session is sent; with it the page and the
live frames arrive; once revoked, the tablet is refused again and its open websocket is closed. Plain HTTP is not
served. Clients: Python's ssl/http.client and websockets trusting only the deployment's CA, and Debian's Chromium with
the CA in its certificate store (certificate errors not ignored)."""

from __future__ import annotations

import asyncio
import contextlib
import http.client
import io
import json
import os
import ssl
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import pytest
import zenoh

from services.nodes.router import wait_until_listening
from services.transport import security
from services.transport.schemas import msk_pb2
from services.transport.zenoh_session import declare_data_publisher, publish
from tests.conftest import free_tcp_port

pytestmark = pytest.mark.slow

SESSION = "gym1"
GROUPS = ["PMCla", "DelAnt", "TriLong"]


def _certs(*argv: str) -> str:
    from services.cli import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["certs", *argv]) == 0
    return out.getvalue()


def _msk(*argv: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "services.cli", *argv],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        stdin=subprocess.DEVNULL,
        text=True,
    )


def _stop(process: subprocess.Popen) -> str:
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(15)
        except subprocess.TimeoutExpired:
            process.kill()
    return (process.communicate(timeout=10)[1] or "")[-2000:]


@pytest.fixture(scope="module")
def secured(tmp_path_factory):
    """The PKI of `msk certs` (router and dashboard on localhost/127.0.0.1), a secured `msk router`, an estimator
    publishing activation frames, and `msk dashboard --pki` joined as the tablet role; yields (pki, dashboard port,
    the router's endpoint)."""
    work = tmp_path_factory.mktemp("dashboard-pki")
    pki = work / "pki"
    _certs("--out", str(pki), "--router-host", "localhost", "--router-host", "127.0.0.1")
    router_port, dashboard_port = free_tcp_port(), free_tcp_port()
    endpoint = f"tls/localhost:{router_port}"
    router = _msk(
        "router", "--zenoh-config", str(pki / "zenoh" / "router.json5"), "--listen", f"tls/127.0.0.1:{router_port}"
    )
    processes = [router]
    stop = threading.Event()
    try:
        wait_until_listening(router, router_port, timeout_s=90)  # a busy shared machine starts Python slowly
        tablet_config = work / "tablet.json5"
        tablet_config.write_text(json.dumps(security.client_config(pki, "tablet", connect=(endpoint,))))
        dashboard = _msk(
            "dashboard", "--pki", str(pki), "--port", str(dashboard_port), "--session", SESSION,
            "--zenoh-config", str(tablet_config),
        )  # fmt: skip
        processes.append(dashboard)
        wait_until_listening(dashboard, dashboard_port, timeout_s=90)
        estimator = zenoh.open(
            zenoh.Config.from_json5(json.dumps(security.client_config(pki, "estimator", connect=(endpoint,))))
        )
        publisher = declare_data_publisher(estimator, f"msk/{SESSION}/activations/so", "msk.ActivationFrame")

        def frames() -> None:
            index = 0
            while not stop.wait(0.02):
                now = time.time_ns()
                publish(
                    publisher,
                    msk_pb2.ActivationFrame(
                        method="so", time_s=index * 0.02, groups=GROUPS, activations=[0.2, 0.5, 0.8],
                        publish_ns=now, input_arrival_ns=now,
                    ),
                )  # fmt: skip
                index += 1

        thread = threading.Thread(target=frames, daemon=True)
        thread.start()
        yield pki, dashboard_port, endpoint
        stop.set()
        thread.join(5)
        estimator.close()
    finally:
        stop.set()
        logs = [_stop(p) for p in reversed(processes)]
        print("\n".join(logs))


def _context(pki: Path) -> ssl.SSLContext:
    """A client that trusts the deployment's CA and nothing else, and checks the host name."""
    return ssl.create_default_context(cafile=str(pki / "ca.pem"))


def _get(pki: Path, port: int, path: str, cookie: str | None = None) -> tuple[int, dict[str, str], bytes]:
    connection = http.client.HTTPSConnection("127.0.0.1", port, context=_context(pki), timeout=10)
    try:
        connection.request("GET", path, headers={"Cookie": cookie} if cookie else {})
        response = connection.getresponse()
        return response.status, {k.lower(): v for k, v in response.getheaders()}, response.read()
    finally:
        connection.close()


async def _websocket(pki: Path, port: int, cookie: str | None, *, until_revoked: Path | None = None) -> dict:
    """Open wss://.../ws; return the first update holding an activation frame (or, with ``until_revoked``, what
    happened once the token in that store was revoked: the close code). Refusals come back as {"refused": status}."""
    from websockets.asyncio.client import connect
    from websockets.exceptions import ConnectionClosed, InvalidStatus

    headers = {"Cookie": cookie} if cookie else {}
    try:
        async with connect(f"wss://127.0.0.1:{port}/ws", ssl=_context(pki), additional_headers=headers) as socket:
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline:
                try:
                    update = json.loads(await asyncio.wait_for(socket.recv(), timeout=5))
                except ConnectionClosed as closed:
                    return {"closed": closed.rcvd.code if closed.rcvd else None}
                if until_revoked is None and "activations/so" in update.get("topics", {}):
                    return update
            return {"timeout": True}
    except InvalidStatus as refused:
        return {"refused": refused.response.status_code}


def test_without_a_token_nothing_of_the_session_is_served(secured):
    pki, port, _ = secured
    for path in ("/", "/config.json", "/static/dashboard.js", "/bodymap/bench_press.svg"):
        status, _, body = _get(pki, port, path)
        assert status == 401, (path, status)
        assert SESSION.encode() not in body and b"PMCla" not in body
    assert _get(pki, port, "/login?token=not-a-token")[0] == 401
    assert asyncio.run(_websocket(pki, port, None)) == {"refused": 403}
    assert asyncio.run(_websocket(pki, port, "msk_tablet=forged"))["refused"] == 403
    # plain HTTP is not served on the port; a client that does not trust the deployment's CA does not connect
    plain = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    with pytest.raises((http.client.HTTPException, ConnectionError)):
        plain.request("GET", "/")
        plain.getresponse()
    plain.close()
    stranger = http.client.HTTPSConnection("127.0.0.1", port, context=ssl.create_default_context(), timeout=10)
    with pytest.raises(ssl.SSLCertVerificationError):
        stranger.request("GET", "/")
    stranger.close()


def test_a_tablet_token_opens_the_page_and_live_data_until_revoked(secured):
    pki, port, _ = secured
    printed = _certs("tablet-token", "coach-ipad", "--out", str(pki), "--dashboard-url", f"https://127.0.0.1:{port}")
    url = next(line for line in printed.splitlines() if line.startswith("https://"))
    token = url.split("token=", 1)[1]
    stored = json.loads((pki / "tablet-tokens.json").read_text())
    assert token not in json.dumps(stored) and stored["coach-ipad"]["revoked"] is False  # kept hashed
    status, headers, _ = _get(pki, port, url.split(str(port), 1)[1])
    assert status == 303 and headers["location"] == "/"
    cookie = headers["set-cookie"].split(";", 1)[0]
    assert "HttpOnly" in headers["set-cookie"] and "Secure" in headers["set-cookie"]
    status, _, page = _get(pki, port, "/", cookie)
    assert status == 200 and b"<html" in page.lower()
    status, _, config = _get(pki, port, "/config.json", cookie)
    assert status == 200 and json.loads(config)["session"] == SESSION
    assert "role 'tablet' may publish only" in json.loads(config)["set_marks_refused"]  # the buttons are not offered
    update = asyncio.run(_websocket(pki, port, cookie))
    frame = update["topics"]["activations/so"]
    assert frame["groups"] == GROUPS, frame

    async def revoke_while_open() -> dict:
        watching = asyncio.create_task(_websocket(pki, port, cookie, until_revoked=pki))
        await asyncio.sleep(1.0)
        await asyncio.to_thread(_certs, "revoke-token", "coach-ipad", "--out", str(pki))
        return await watching

    assert asyncio.run(revoke_while_open()) == {"closed": 1008}
    assert _get(pki, port, "/", cookie)[0] == 401
    assert asyncio.run(_websocket(pki, port, cookie)) == {"refused": 403}
    assert _get(pki, port, url.split(str(port), 1)[1])[0] == 401  # the URL itself no longer logs in


def test_chromium_sees_the_session_only_with_a_token(secured, tmp_path):
    from tests.dashboard_helpers import CHROMIUM, CHROMIUM_ARGS, chromium_trusting, require_chromium

    require_chromium()
    pki, port, _ = secured
    environment = chromium_trusting(pki / "ca.pem", tmp_path / "home")
    if environment is None:
        pytest.skip(
            "NSS's certutil is missing (apt-get install libnss3-tools): Chromium cannot be made to trust the CA"
        )
    from playwright import sync_api

    printed = _certs("tablet-token", "chromium", "--out", str(pki), "--dashboard-url", f"https://127.0.0.1:{port}")
    url = next(line for line in printed.splitlines() if line.startswith("https://"))
    with sync_api.sync_playwright() as playwright:
        browser = playwright.chromium.launch(
            executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS, env=environment
        )
        try:
            context = browser.new_context(ignore_https_errors=False)
            page = context.new_page()
            sockets: list[str] = []
            page.on("websocket", lambda ws: sockets.append(ws.url))
            refused = page.goto(f"https://127.0.0.1:{port}/")
            assert refused is not None and refused.status == 401
            assert SESSION not in page.content() and "PMCla" not in page.content()
            assert sockets == []  # the refusal page opens no websocket
            opened = page.goto(url)  # the URL the operator gave: sets the cookie, then the page
            assert opened is not None and opened.status == 200 and page.url == f"https://127.0.0.1:{port}/"
            page.wait_for_function(
                "() => window.mskDashboard && window.mskDashboard.state.updates > 2"
                " && Object.keys(window.mskDashboard.state.activations).length > 0",
                timeout=30_000,
            )
            shown = page.evaluate("() => window.mskDashboard.state.activations.so.activations")
            assert shown == [0.2, 0.5, 0.8]
            # the tablet may not mark sets: its buttons are disabled, the header says so in two lines at most
            assert page.is_disabled("#set-start") and page.is_disabled("#set-stop")
            assert page.inner_text("#set-reply") == "view only: sets are marked at the rack"
            assert "role 'tablet' may publish only" in (page.get_attribute("#set-reply", "title") or "")
            _certs("revoke-token", "chromium", "--out", str(pki))
            assert page.reload().status == 401
        finally:
            browser.close()


def test_pki_attaches_to_the_running_secured_session_and_a_plain_dashboard_stays_on_loopback(
    secured, tmp_path, monkeypatch
):
    """`msk live --pki DIR` runs its router on a free port and writes OUT/zenoh/<role>.json5 for it; `msk dashboard
    --pki DIR` with no Zenoh flags used DIR/zenoh/tablet.json5 (the port of `msk certs`) and the session 'lab', and
    failed to connect, while the attach line `msk live` printed led to a plain HTTP dashboard with operator rights (found
    by QA). Announced here as `msk live --pki` announces itself (services.sessions.discovery), on the module's router:
    the --pki dashboard takes the session's name and tablet config and streams its frames to a tablet; the attach line
    says --pki; a plain dashboard is refused on the network and still attaches on loopback."""
    from services.sessions import discovery

    pki, _, endpoint = secured
    monkeypatch.setenv("MSK_SESSIONS_DIR", str(tmp_path / "sessions"))
    out = tmp_path / "out"
    security.write_configs(out / "zenoh", pki, router_listen=("tls/127.0.0.1:1",), client_connect=(endpoint,))
    info = discovery.SessionInfo(
        session=SESSION, connect=[endpoint], pid=os.getpid(), out=str(out), pack="bench_press",
        zenoh_config=str(out / "zenoh" / "operator.json5"), pki=str(pki),
    )  # fmt: skip
    info = replace(info, attach=discovery.attach_commands(info))
    assert info.attach[0] == f"msk dashboard --pki {pki} --session {SESSION}"
    with discovery.claimed(SESSION, out):
        discovery.announce(info, out)
        port = free_tcp_port()
        dashboard = _msk("dashboard", "--pki", str(pki), "--port", str(port))  # no --session, no Zenoh flags
        try:
            wait_until_listening(dashboard, port, timeout_s=90)
            printed = _certs(
                "tablet-token", "attach", "--out", str(pki), "--dashboard-url", f"https://127.0.0.1:{port}"
            )
            token = printed.split("token=", 1)[1].split()[0]
            status, headers, _ = _get(pki, port, f"/login?token={token}")
            cookie = headers["set-cookie"].split(";", 1)[0]
            assert json.loads(_get(pki, port, "/config.json", cookie)[2])["session"] == SESSION
            assert asyncio.run(_websocket(pki, port, cookie))["topics"]["activations/so"]["groups"] == GROUPS
        finally:
            said = _stop(dashboard)
        assert f"attached to the running secured session {SESSION!r} on {endpoint} as the tablet role" in said, said
        assert str(out / "zenoh" / "tablet.json5") in said
        refused = subprocess.run(
            [sys.executable, "-m", "services.cli", "dashboard", "--host", "0.0.0.0", "--port", str(free_tcp_port())],
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert refused.returncode == 2, refused.stderr
        assert refused.stderr.count("\n") == 1 and f"session {SESSION!r} is secured" in refused.stderr, refused.stderr
        assert f"msk dashboard --pki {pki} --session {SESSION}" in refused.stderr
        local_port = free_tcp_port()
        local = _msk("dashboard", "--port", str(local_port))  # loopback: this machine only, as before
        try:
            wait_until_listening(local, local_port, timeout_s=90)
        finally:
            said = _stop(local)
        assert f"attached to the running session {SESSION!r}" in said, said
