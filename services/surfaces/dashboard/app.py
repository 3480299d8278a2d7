"""``msk dashboard``: the coaches' page, served by Starlette + uvicorn, fed by the Zenoh bridge over a WebSocket.

``GET /`` the page; ``GET /static/...`` its script, style and the vendored Chart.js; ``GET /config.json`` the session
and timings; ``GET /bodymap/<pack>.svg`` the body map of a shipped model pack; ``WS /ws`` the frames. Each page
connection sends, every ``send_interval_s``, the newest value of every topic that changed since its last send (and a
heartbeat at least every ``heartbeat_s``): a slow tablet skips frames, nothing queues. The page's one control of the
session is the operator's set buttons (``POST /set/start`` and ``/set/stop``, as ``msk set``; the method switch is
local to each page): a browser's request from another site's page is refused, and on the gym network (``--host``)
anyone who reaches the page can mark sets unless it is served with ``--pki`` (tablet tokens).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urlsplit

import uvicorn
from starlette.applications import Starlette
from starlette.middleware import Middleware
from starlette.middleware.gzip import GZipMiddleware
from starlette.responses import FileResponse, JSONResponse, Response
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.staticfiles import StaticFiles
from starlette.websockets import WebSocket, WebSocketDisconnect

from msk_core.errors import ConfigError, ModelError
from msk_core.model import available_packs, load_pack
from services.sessions.live_session import PREFERRED_METHODS
from services.surfaces.dashboard import bodymap
from services.surfaces.dashboard.access import TokenGate, TokenStore
from services.surfaces.dashboard.bridge import Bridge, DashboardState
from services.transport import messages, topics
from services.transport.roles import facts_refusal
from services.transport.zenoh_session import ZenohOptions, add_zenoh_arguments, options_from_args, run_script

if TYPE_CHECKING:
    from services.sessions.discovery import SessionInfo

log = logging.getLogger(__name__)
STATIC = Path(__file__).resolve().parent / "static"


@dataclass(frozen=True)
class DashboardConfig:
    session: str = "lab"
    send_interval_s: float = 0.05  # at most 20 updates per second to each page
    heartbeat_s: float = 0.5
    no_data_after_s: float = 2.0  # the page shows "no data" when the newest data sample is older than this


def packs_by_groups() -> dict[tuple[str, ...], str]:
    """Group lists of the shipped packs, to recognise the pack behind an ActivationFrame."""
    found = {}
    for name in available_packs():
        try:
            found[tuple(load_pack(name).groups)] = name
        except ModelError as error:  # a broken pack must not take the dashboard down
            log.warning("model pack %s: %s", name, error)
    return found


def page_config(config: DashboardConfig, pack_index: dict[tuple[str, ...], str], role: str | None = None) -> dict:
    """What the page reads at /config.json: the session, its timings, the method shown by default (the first of
    ``default_methods`` that ran, as in the view and the report), each pack's groups, and why this dashboard's Zenoh
    ``role`` may not mark sets (None when it may): the page then offers no buttons that would be refused."""
    return {
        "session": config.session,
        "set_marks_refused": facts_refusal(role, config.session),
        "no_data_after_s": config.no_data_after_s,
        "heartbeat_s": config.heartbeat_s,
        "default_methods": list(PREFERRED_METHODS),
        "packs": {name: list(groups) for groups, name in pack_index.items()},
    }


def create_app(
    attached: DashboardServer,
    *,
    on_startup=(),
    on_shutdown=(),
    on_set_mark: Callable[[str], messages.LoadEvent] | None = None,
) -> Starlette:
    """The page and its websocket, serving ``attached``'s session: its ``config`` and ``state`` are read on every
    request, and a page's websocket closes when ``attached.attachments`` changes (the page then fetches the new
    session's config and connects again). ``on_set_mark(mark)``: publishes the operator's set mark ("start",
    "stop") and returns its LoadEvent (the page's buttons, ``POST /set/start`` and ``/set/stop``); None: the page has
    no buttons to press."""
    pack_index = packs_by_groups()
    svg_cache: dict[str, str] = {}

    async def page(request):
        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-store"})

    async def config_json(request):
        return JSONResponse(page_config(attached.config, pack_index, attached.zenoh_options.role))

    async def body_map(request):
        name = request.path_params["pack"]
        if name not in pack_index.values():
            return Response(f"no shipped model pack {name!r}", status_code=404, media_type="text/plain")
        if name not in svg_cache:
            pack = load_pack(name)
            svg_cache[name] = bodymap.place_groups(pack).svg(names=pack.display_names.groups)
        return Response(svg_cache[name], media_type="image/svg+xml")

    async def set_mark(request):
        mark = request.path_params["mark"]
        origin = request.headers.get("origin")
        if origin is not None and urlsplit(origin).netloc != request.headers.get("host"):
            # a browser's request from another site's page (it sends its Origin): only this page marks sets
            return JSONResponse({"error": f"set marks come from this dashboard's page, not {origin}"}, status_code=403)
        if mark not in ("start", "stop"):
            return JSONResponse({"error": f"no set mark {mark!r}: start or stop"}, status_code=404)
        if on_set_mark is None:
            return JSONResponse({"error": "this dashboard publishes no set marks"}, status_code=503)
        try:
            event = await asyncio.to_thread(on_set_mark, mark)
        except Exception as error:  # the session refused it (secured network) or the bridge is down: say so
            log.warning("set %s: %s", mark, error)
            return JSONResponse({"error": f"set {mark} not published: {error}"}, status_code=503)
        return JSONResponse({"mark": mark, "set_number": int(event.set_number)})

    @contextlib.asynccontextmanager
    async def lifespan(app):
        for hook in on_startup:
            hook()
        try:
            yield
        finally:
            for hook in on_shutdown:
                hook()

    return Starlette(
        routes=[
            Route("/", page),
            Route("/config.json", config_json),
            Route("/bodymap/{pack}.svg", body_map),
            Route("/set/{mark}", set_mark, methods=["POST"]),
            WebSocketRoute("/ws", _frames(attached)),
            Mount("/static", StaticFiles(directory=STATIC), name="static"),
        ],
        lifespan=lifespan,
        middleware=[Middleware(GZipMiddleware, minimum_size=1024)],  # Chart.js: 210 kB -> about 70 kB on the wire
    )


def _frames(attached: DashboardServer):
    """The page's websocket: the session's changes, at most every ``send_interval_s`` (a heartbeat at least every
    ``heartbeat_s``); closed when the dashboard attaches to another session, so the page fetches its config anew."""

    async def frames(websocket: WebSocket):
        await websocket.accept()
        since, last_sent = 0, 0.0
        attachment, state, config = attached.attachments, attached.state, attached.config
        try:
            while True:
                if attached.attachments != attachment:  # another session now: the page reconnects to it
                    await websocket.close(code=1012, reason="the dashboard serves another session now")
                    return
                seq, update = state.changes(since)
                now = time.monotonic()
                if update["topics"] or now - last_sent >= config.heartbeat_s:
                    update["type"] = "update"
                    update["server_time_ns"] = time.time_ns()
                    # Awaiting the send is the back-pressure: meanwhile newer frames overwrite older ones in the state.
                    await websocket.send_text(json.dumps(update, allow_nan=False))
                    since, last_sent = seq, now
                await asyncio.sleep(config.send_interval_s)
        except (WebSocketDisconnect, RuntimeError, ConnectionError):
            return

    return frames


class DashboardServer:
    """Bridge + web server; ``start()`` runs it in a thread (tests, embedding), ``run()`` in the caller's."""

    def __init__(
        self,
        zenoh_options: ZenohOptions,
        config: DashboardConfig,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        pki: Path | None = None,
    ) -> None:
        """``pki``: HTTPS with the deployment's dashboard certificate, and only tablets with a token get in
        (services/surfaces/dashboard/access.py)."""
        topics.check_chunk(config.session, "--session")
        if not 0 < port < 65536:
            raise ConfigError("port must be in 1..65535", field="--port", value=port)
        self.config, self.zenoh_options = config, zenoh_options
        self.state = DashboardState(config.session)
        self.bridge = Bridge(zenoh_options, self.state)
        self.attachments = 0  # sessions attached to after the first (attach())
        self._attach_lock = threading.Lock()  # the bridge is started, swapped and stopped under it
        self._serving = False  # between the server's startup and its shutdown: the bridge runs
        app = create_app(
            self,
            on_startup=(self._start_bridge,),
            on_shutdown=(self._stop_bridge,),
            on_set_mark=lambda mark: self.bridge.publish_set_mark(mark),
        )
        certificate, key = (None, None) if pki is None else secured(pki)
        store = None if pki is None else TokenStore(pki)
        if store is not None:
            store.tablets()  # an unreadable or corrupt tokens file is said now, not as 500s per request
        served = app if store is None else TokenGate(app, store)
        self.server = uvicorn.Server(
            uvicorn.Config(
                served,
                host=host,
                port=port,
                log_level="warning",
                ws="websockets-sansio",
                ssl_certfile=certificate,
                ssl_keyfile=key,
            )
        )
        self.host, self.port, self.scheme, self.pki = host, port, "http" if pki is None else "https", pki
        self._thread: threading.Thread | None = None

    def attach(self, zenoh_options: ZenohOptions, session: str) -> None:
        """Serve ``session`` from ``zenoh_options`` from now on (a dashboard opened before its ``msk live``): a new
        bridge and state; the open pages reconnect and fetch the new session's config."""
        topics.check_chunk(session, "--session")
        with self._attach_lock:
            if self._serving:
                self.bridge.stop()
            self.config, self.zenoh_options = replace(self.config, session=session), zenoh_options
            self.state = DashboardState(session)
            self.bridge = Bridge(zenoh_options, self.state)
            if self._serving:  # else the server's startup starts it
                self.bridge.start()
            self.attachments += 1

    def _start_bridge(self) -> None:
        with self._attach_lock:
            if self._serving:  # run() started it before the server
                return
            self.bridge.start()
            self._serving = True

    def _stop_bridge(self) -> None:
        with self._attach_lock:
            self._serving = False
            self.bridge.stop()

    @property
    def url(self) -> str:
        return f"{self.scheme}://{self.host}:{self.port}/"

    def run(self) -> None:
        # the bridge first: a session it cannot open (a secured router it cannot reach) is said in one line by the
        # command, not as a traceback of the server's start-up
        self._start_bridge()
        try:
            self.server.run()
        finally:  # uvicorn's shutdown stopped it, unless the server failed to start (the bridge would hold the process)
            self._stop_bridge()

    def start(self, timeout_s: float = 20.0) -> None:
        self._thread = threading.Thread(target=self.server.run, name="dashboard", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + timeout_s
        while not self.server.started and self._thread.is_alive() and time.monotonic() < deadline:
            time.sleep(0.02)
        if not self.server.started:
            raise RuntimeError(
                f"dashboard did not start on {self.url} within {timeout_s} s (thread alive: {self._thread.is_alive()})"
            )

    def stop(self, timeout_s: float = 10.0) -> None:
        self.server.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout_s)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--session",
        default=None,
        help="session name: topics msk/<session>/... (default: the running msk live's, else lab)",
    )
    parser.add_argument("--port", type=int, default=8080, help="HTTP port (default 8080)")
    parser.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on (default 127.0.0.1: this machine only; 0.0.0.0 for tablets on the gym network)",
    )
    parser.add_argument(
        "--pki",
        type=Path,
        default=None,
        metavar="DIR",
        help="secured: HTTPS with DIR/dashboard.pem and a tablet token per tablet (`msk certs tablet-token`); joins "
        "Zenoh as the tablet role (DIR/zenoh/tablet.json5) unless Zenoh flags say otherwise",
    )
    add_zenoh_arguments(parser)


def secured(pki: Path) -> tuple[str, str]:
    """uvicorn's TLS files (certificate, key): the dashboard certificate ``msk certs`` made in ``pki``, checked before
    serving (:func:`services.transport.security.check_tls_files`: readable, valid now, the key the certificate's,
    signed by ``ca.pem`` when the folder has it; then as the server's TLS loads them). uvicorn itself refused a bad
    key only once the Zenoh bridge ran, and the process stayed up without listening."""
    import ssl

    from services.transport.security import Pki, check_tls_files

    files = Pki(Path(pki))
    for path in (files.dashboard_cert, files.dashboard_key):
        if not path.is_file():
            raise ConfigError("no dashboard certificate: make the folder with `msk certs --out DIR`", path=path)
    fields = ("dashboard certificate", "dashboard key", "deployment CA")
    check_tls_files(
        files.dashboard_cert, files.dashboard_key, files.ca_cert if files.ca_cert.is_file() else None, fields=fields
    )
    try:
        ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER).load_cert_chain(files.dashboard_cert, files.dashboard_key)
    except ssl.SSLError as error:
        raise ConfigError(f"HTTPS cannot use it: {error.reason or error}", path=files.dashboard_key) from None
    return str(files.dashboard_cert), str(files.dashboard_key)


def is_loopback(host: str) -> bool:
    import ipaddress

    try:
        return host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def refused_plain(info: SessionInfo | None, host: str, pki: Path | None) -> str | None:
    """Why a dashboard without ``--pki`` may not serve the secured session ``info`` (a ``SessionInfo``) on ``host``:
    it would join with the session's operator config and serve it, set buttons included, over plain HTTP with no
    token to whoever reaches ``host``. None: allowed (``--pki``, a plain session, or loopback: this machine only)."""
    if pki is not None or info is None or not info.pki or is_loopback(host):
        return None
    return (
        f"session {info.session!r} is secured (msk live --pki {info.pki}): without --pki this dashboard would serve it "
        f"with operator rights over plain HTTP on {host}, with no token; serve it to tablets with `msk dashboard "
        f"--pki {info.pki} --session {info.session} --host {host}`, or keep --host on loopback"
    )


def _check_port_free(host: str, port: int) -> None:
    import socket

    if not 0 < port < 65536:
        raise ConfigError("port must be in 1..65535", field="--port", value=port)
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as error:
            raise ConfigError(
                f"cannot listen on {host}:{port} ({error.strerror}); choose another --port or --host",
                field="--port",
                value=port,
            ) from None


def _drops_text(state: DashboardState) -> str:
    return ", ".join(f"{d.key}: {d.reason} {d.count}" for d in state.input_counts.drops())


def follow_announced(
    server: DashboardServer,
    explicit: ZenohOptions,
    session: str | None,
    attached: ZenohOptions,
    stop: threading.Event,
    every_s: float = 1.0,
) -> None:
    """Every ``every_s`` until ``stop``: serve the session a :class:`services.sessions.discovery.SessionFollower` says
    (one that started after this dashboard, before it received anything or after its session ended)."""
    from services.sessions import discovery

    follower = discovery.SessionFollower(session, attached, every_s=0.0)
    refused: set[int] = set()  # the secured sessions said once (pids of their msk live)
    while not stop.wait(every_s):
        info = follower.next_session(server.state.received)
        if info is None:
            continue
        refusal = refused_plain(info, server.host, server.pki)
        if refusal is not None:
            if info.pid not in refused:
                refused.add(info.pid)
                log.warning("msk dashboard: not attached: %s", refusal)
            continue
        try:
            options, name = discovery.client_options(explicit, session, "lab", "msk dashboard")
            server.attach(options, name)
        except Exception as error:  # e.g. a second session announced meanwhile: said, looked at again a second later
            log.warning("msk dashboard: could not attach to the announced session: %s", error)
            continue
        follower.moved(options)


def pki_zenoh_config(pki: Path, session: str | None) -> tuple[Path, str | None]:
    """``--pki`` without Zenoh flags: the tablet config a running secured ``msk live`` wrote for its router
    (``OUT/zenoh/tablet.json5``, its actual endpoint) and its session's name; else ``PKI/zenoh/tablet.json5`` of
    ``msk certs`` (a standalone ``msk router``) and ``session`` as given."""
    from services.sessions import discovery

    info = discovery.find_session(session)
    config = discovery.role_config(info, "tablet") if info is not None else None
    if info is None or config is None:
        return Path(pki) / "zenoh" / "tablet.json5", session
    print(
        f"msk dashboard: attached to the running secured session {info.session!r} on {', '.join(info.connect)} as "
        f"the tablet role ({config}; announced in {info.out}/{discovery.SESSION_FILE})",
        file=sys.stderr,
        flush=True,
    )
    return config, info.session


def run_from_args(args: argparse.Namespace) -> int:
    _check_port_free(args.host, args.port)
    from services.sessions import discovery

    if args.pki is not None and args.zenoh_config is None and not args.connect:
        args.zenoh_config, args.session = pki_zenoh_config(args.pki, args.session)
    explicit = options_from_args(args)
    if args.pki is None and not is_loopback(args.host) and not discovery.gives_endpoint(explicit):
        refusal = refused_plain(discovery.find_session(args.session), args.host, None)
        if refusal is not None:
            raise ConfigError(refusal, field="--host", value=args.host)
    options, session = discovery.client_options(explicit, args.session, "lab", "msk dashboard")
    server = DashboardServer(options, DashboardConfig(session=session), host=args.host, port=args.port, pki=args.pki)
    quiet = threading.Event()
    discovery.silence_notice(
        "msk dashboard",
        lambda: (f"msk/{server.config.session}/**", server.zenoh_options),
        lambda: server.state.received,
        stop=quiet,
    )
    if not discovery.gives_endpoint(explicit):
        follow = threading.Thread(
            target=follow_announced, args=(server, explicit, args.session, options, quiet), daemon=True
        )
        follow.start()
    where = (
        server.url
        if args.host not in ("0.0.0.0", "::")
        else f"port {args.port} of every network interface of this machine"
    )
    print(f"dashboard of session {session!r} on {where} (Ctrl-C stops)", file=sys.stderr, flush=True)
    try:
        server.run()  # uvicorn handles SIGINT/SIGTERM: closes the sockets, then the lifespan stops the bridge
    except KeyboardInterrupt:  # uvicorn re-raises the Ctrl-C it handled, once shut down
        pass
    finally:
        quiet.set()
    if not server.server.started:  # uvicorn said why (its log); the bridge is stopped, the command fails
        print(f"msk dashboard: error: the dashboard did not start serving on {server.url}", file=sys.stderr)
        return 1
    dropped = server.state.input_counts.total_dropped
    print(
        f"dashboard stopped; the bridge received {server.state.received} messages"
        + (f" and dropped {dropped} it could not use ({_drops_text(server.state)})" if dropped else ""),
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    run_script(__doc__, add_arguments, run_from_args)
