"""The dashboard's access under ``--pki``: one token per tablet, issued and revoked by the operator, kept hashed.

``msk certs tablet-token NAME --out PKI`` issues a token for the tablet NAME and prints the URL to open on it once
(``https://<dashboard>/login?token=...``): the dashboard checks the token and answers with a cookie that carries it
(HttpOnly, Secure, SameSite=Strict), so the page, its data and its websocket work from then on.
``msk certs revoke-token NAME --out PKI`` revokes it: the next request and the next websocket message of that tablet
are refused (an open websocket is closed with code 1008). The tokens are kept as SHA-256 digests in
``PKI/tablet-tokens.json`` (a token is 256 random bits: a plain digest cannot be reversed); the file is read again
whenever it changes, so issuing and revoking need no restart. Without a valid token every path answers 401 (HTTP)
or 403 (websocket handshake) and nothing of the session.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import hmac
import json
import logging
import os
import secrets
import threading
from collections.abc import Awaitable, Callable, MutableMapping
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs

from msk_core.errors import ConfigError, InputError
from msk_core.io.files import write_text_atomic

log = logging.getLogger(__name__)
TOKENS_FILE = "tablet-tokens.json"
COOKIE = "msk_tablet"
LOGIN_PATH = "/login"

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
App = Callable[[Scope, Receive, Send], Awaitable[None]]


def _digest(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def _check_name(name: str) -> str:
    if not name or not all(c.isalnum() or c in "-_." for c in name):
        raise ConfigError("a tablet name is letters, digits, '-', '_' or '.'", field="NAME", value=name)
    return name


class TokenStore:
    """``PKI/tablet-tokens.json``: tablet name -> SHA-256 of its token, when it was issued, whether it is revoked."""

    def __init__(self, pki_dir: Path | str) -> None:
        self.path = Path(pki_dir) / TOKENS_FILE
        self._lock = threading.Lock()
        self._seen: tuple[float, int] | None = None
        self._valid: dict[str, str] = {}  # digest -> tablet name

    def _read(self) -> dict[str, dict[str, Any]]:
        if not self.path.is_file():
            return {}
        try:
            document = json.loads(self.path.read_text())
        except (OSError, ValueError) as error:
            raise InputError(f"cannot read the tablet tokens: {error}", path=self.path) from None
        if not isinstance(document, dict):
            raise InputError("the tablet tokens file must hold an object of tablets", path=self.path)
        return document

    def _write(self, document: dict[str, dict[str, Any]]) -> None:
        write_text_atomic(self.path, json.dumps(document, indent=2) + "\n", mode=0o600)  # never half a file

    def issue(self, name: str) -> str:
        """A new token for tablet ``name`` (a previous one of that name stops working); returns the token."""
        token = secrets.token_urlsafe(32)
        document = self._read()
        document[_check_name(name)] = {
            "sha256": _digest(token),
            "issued": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "revoked": False,
        }
        self._write(document)
        return token

    def revoke(self, name: str) -> None:
        document = self._read()
        if name not in document:
            raise ConfigError(
                f"no tablet of that name has a token (known: {', '.join(document) or 'none'})", field="NAME", value=name
            )
        document[name]["revoked"] = True
        document[name]["revoked_at"] = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
        self._write(document)

    def tablets(self) -> dict[str, dict[str, Any]]:
        return self._read()

    def tablet_of(self, token: str | None) -> str | None:
        """The tablet a token belongs to, None when it is unknown or revoked (the file is re-read when changed)."""
        if not token:
            return None
        with self._lock:
            try:
                stat = os.stat(self.path)
                seen: tuple[float, int] | None = (stat.st_mtime, stat.st_size)
            except FileNotFoundError:
                seen = None
            if seen != self._seen:
                self._valid = {
                    str(entry.get("sha256", "")): name
                    for name, entry in self._read().items()
                    if isinstance(entry, dict) and not entry.get("revoked")
                }
                self._seen = seen
            digest = _digest(token)
            return next((name for known, name in self._valid.items() if hmac.compare_digest(known, digest)), None)


def _cookie(scope: Scope) -> str | None:
    for key, value in scope.get("headers", []):
        if key == b"cookie":
            for part in value.decode("latin-1").split(";"):
                name, _, content = part.strip().partition("=")
                if name == COOKIE:
                    return content
    return None


class TokenGate:
    """ASGI middleware: only requests carrying a valid tablet token (cookie) reach the app; ``/login?token=``
    sets the cookie. A websocket is refused at its handshake and closed (1008) when its token is revoked."""

    def __init__(self, app: App, store: TokenStore) -> None:
        self.app, self.store = app, store
        self._said: str | None = None  # the tokens file's problem last logged (once, not once per request)

    def _tablet(self, token: str | None) -> str | None:
        """The tablet of ``token``; raises :class:`InputError` when the tokens file cannot be read now, logged once
        per new problem (a file that went bad while serving: every request is refused until it is repaired)."""
        try:
            tablet = self.store.tablet_of(token)
        except InputError as error:
            if str(error) != self._said:
                self._said = str(error)
                log.error("msk dashboard: %s; every tablet is refused (503) until the file is repaired", error)
            raise
        self._said = None
        return tablet

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        try:
            if scope["type"] == "http" and scope["path"] == LOGIN_PATH:
                await self._login(scope, send)
                return
            token = _cookie(scope)
            tablet = self._tablet(token)
        except InputError:
            await self._refuse(scope, send, status=503)
            return
        if tablet is None:
            await self._refuse(scope, send)
            return
        if scope["type"] == "websocket":
            send = self._guarded(token, send)
        await self.app(scope, receive, send)

    def _guarded(self, token: str | None, send: Send) -> Send:
        closed = False

        async def guarded(message: Message) -> None:
            nonlocal closed
            if closed:
                raise ConnectionError("the tablet's token was revoked")
            if message["type"] == "websocket.send":
                try:
                    revoked = self._tablet(token) is None
                except InputError:  # cannot tell: closed as a server error, the page reconnects (and gets 503)
                    closed = True
                    await send({"type": "websocket.close", "code": 1011, "reason": "tablet tokens unreadable"})
                    raise ConnectionError("the tablet tokens file cannot be read") from None
                if revoked:
                    closed = True
                    await send({"type": "websocket.close", "code": 1008, "reason": "token revoked"})
                    raise ConnectionError("the tablet's token was revoked")
            await send(message)

        return guarded

    async def _login(self, scope: Scope, send: Send) -> None:
        token = parse_qs(scope.get("query_string", b"").decode("latin-1")).get("token", [""])[0]
        if self._tablet(token) is None:
            await self._refuse(scope, send)
            return
        cookie = f"{COOKIE}={token}; Path=/; HttpOnly; Secure; SameSite=Strict; Max-Age=31536000"
        headers = [(b"location", b"/"), (b"set-cookie", cookie.encode()), (b"cache-control", b"no-store")]
        await send({"type": "http.response.start", "status": 303, "headers": headers})
        await send({"type": "http.response.body", "body": b""})

    async def _refuse(self, scope: Scope, send: Send, status: int = 401) -> None:
        """401: no valid token; 503: the tokens file cannot be read (nobody is let in; the operator repairs it)."""
        if scope["type"] == "websocket":  # before accept: the server answers the handshake with 403
            await send({"type": "websocket.close", "code": 1008})
            return
        body = (
            b"401: this dashboard needs a tablet token. Ask the operator for one "
            b"(msk certs tablet-token NAME prints the URL to open on this tablet).\n"
            if status == 401
            else f"503: the dashboard cannot read its tablet tokens ({self.store.path}); ask the operator to "
            "repair it (or remove it and issue the tablets' tokens again).\n".encode()
        )
        headers = [(b"content-type", b"text/plain; charset=utf-8"), (b"cache-control", b"no-store")]
        await send({"type": "http.response.start", "status": status, "headers": headers})
        await send({"type": "http.response.body", "body": body})
