"""Finding a running session: ``msk live`` announces itself, a second terminal's tools attach with no flags.

``msk live`` writes ``OUT/session.json`` as soon as its graph is up (:class:`SessionInfo`: the session's name, the
Zenoh endpoints a client connects to, and in the secured mode the client config of the ``operator`` role) and the
same document into the registry folder (:func:`registry_dir`, one file per running ``msk live``), which it removes
at stop. ``msk dashboard``, ``msk subscribe``, ``msk view`` and ``msk load`` without ``--connect`` /
``--zenoh-config`` look there (:func:`attach_options`): the one running session, or the one named with
``--session``; several sessions on one machine stay possible, each on its own endpoint.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from msk_core.errors import ConfigError, InputError
from services.transport.zenoh_session import ZenohOptions

SESSION_FILE = "session.json"
REGISTRY_ENV = "MSK_SESSIONS_DIR"


@dataclass(frozen=True)
class SessionInfo:
    """What a client needs to attach to a running session (``OUT/session.json``)."""

    session: str
    connect: list[str]
    pid: int
    out: str
    pack: str = ""
    #: secured mode: the operator role's Zenoh client config (TLS + certificate); "" in the plain mode
    zenoh_config: str = ""
    attach: list[str] = field(default_factory=list)
    #: the session facts in effect (exercise, load_kg, set_number, athlete): the latest LoadEvent msk live saw
    facts: dict = field(default_factory=dict)
    #: secured mode: the deployment's folder of ``msk certs`` (``msk live --pki DIR``); "" in the plain mode
    pki: str = ""

    def options(self, mode: str = "peer") -> ZenohOptions:
        """The Zenoh options to attach with: the secured mode's client config, else ``mode`` on msk live's endpoint
        (``"client"`` for a one-shot publisher, :func:`attach_options`)."""
        if self.zenoh_config:
            return ZenohOptions(mode=None, config_file=Path(self.zenoh_config))
        return ZenohOptions(mode=mode, connect=tuple(self.connect))


def registry_dir() -> Path:
    """Where running sessions announce themselves: ``$MSK_SESSIONS_DIR``, else ``$XDG_RUNTIME_DIR/msk-live/sessions``,
    else ``~/.cache/msk-live/sessions``."""
    if os.environ.get(REGISTRY_ENV):
        return Path(os.environ[REGISTRY_ENV])
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    base = (
        Path(runtime) / "msk-live"
        if runtime
        else Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "msk-live"
    )
    return base / "sessions"


def attach_commands(info: SessionInfo) -> list[str]:
    """What to type in a second terminal (no flags needed while it is the only session; else ``--session``). The
    dashboard of a secured session is ``--pki``: HTTPS, tablet tokens and the tablet role (:func:`role_config`)."""
    dashboard = f"msk dashboard --pki {info.pki} --session {info.session}" if info.pki else ""
    return [
        dashboard or f"msk dashboard --session {info.session}",
        f"msk view --session {info.session}",
        f"msk subscribe 'msk/{info.session}/activations/*'",
        f"msk load --session {info.session} KG",
    ]


def role_config(info: SessionInfo, role: str) -> Path | None:
    """The Zenoh client config of ``role`` that a secured ``msk live`` wrote for its own router
    (``OUT/zenoh/<role>.json5``: its actual TLS endpoint, not the port of ``msk certs``); None for a plain session
    or when the file is not there."""
    if not info.pki:
        return None
    path = Path(info.out) / "zenoh" / f"{role}.json5"
    return path if path.is_file() else None


def announce(info: SessionInfo, out: Path) -> list[Path]:
    """Write ``OUT/session.json`` and the registry entry; returns both paths (remove the registry one with
    :func:`withdraw`)."""
    document = json.dumps(asdict(info), indent=2) + "\n"
    written = []
    for path in (Path(out) / SESSION_FILE, registry_dir() / f"{info.session}-{info.pid}.json"):
        path.parent.mkdir(parents=True, exist_ok=True)
        temporary = path.with_suffix(".tmp")
        temporary.write_text(document)
        temporary.replace(path)  # a reader never sees half a file
        written.append(path)
    return written


class Announcement:
    """The announcement of one running ``msk live``, re-written when the session facts change (an operator's
    ``msk load`` then starts from the facts in effect). Thread-safe: the facts come from a Zenoh callback."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._info: SessionInfo | None = None
        self._out: Path | None = None
        self._facts: dict = {}

    def announce(self, info: SessionInfo, out: Path) -> list[Path]:
        with self._lock:
            self._info, self._out = info, Path(out)
            return announce(replace(info, facts=self._facts or info.facts), out)

    def update_facts(self, facts: dict) -> None:
        with self._lock:
            self._facts = dict(facts)
            if self._info is not None and self._out is not None:
                announce(replace(self._info, facts=self._facts), self._out)


def withdraw(path: Path) -> None:
    path.unlink(missing_ok=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process: alive
        return True
    return True


def read_session_file(path: Path) -> SessionInfo:
    try:
        document = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise InputError(f"cannot read the session announcement: {error}", path=path) from None
    try:
        return SessionInfo(**document)
    except TypeError as error:
        raise InputError(f"not a session announcement of msk live: {error}", path=path) from None


@contextlib.contextmanager
def claimed(session: str, out: Path) -> Iterator[None]:
    """Hold the session's name and output folder for one ``msk live`` while it runs: an exclusive lock on a file per
    name in the registry folder and one in the output folder, released by the kernel however the process ends.
    Raises :class:`ConfigError` when another process holds either, so two ``msk live`` started at the same moment
    (neither announced yet) cannot both take one name or one folder."""
    held = (
        (_claim_path(session), "session", f"a session named {session!r} starts or runs now"),
        (Path(out) / ".msk-live.lock", "out", f"an msk live writes to {out} now"),
    )
    with contextlib.ExitStack() as stack:
        stack.callback(_claimed_here.discard, session)
        for path, field_name, what in held:
            path.parent.mkdir(parents=True, exist_ok=True)
            handle = stack.enter_context(open(path, "a+"))
            if not _lock_exclusive(handle):
                handle.seek(0)
                holder = handle.read().strip() or "?"
                raise ConfigError(
                    f"{what} (pid {holder}); stop it first, or run this one under another name ([session] name in a "
                    "session file) with another --out",
                    field=field_name,
                    value=session if field_name == "session" else str(out),
                ) from None
            handle.truncate(0)
            handle.write(f"{os.getpid()}\n")
            handle.flush()
        _claimed_here.add(session)
        yield


def claim_endpoint(endpoint: str) -> contextlib.AbstractContextManager | None:
    """An exclusive lock on ``endpoint``'s claim file in the registry folder, held until the returned handle is
    closed (or the process ends); None when another process holds it. Two ``msk live`` started at the same moment
    both found the well-known endpoint free and both took it: the second one's recorder could not listen."""
    path = registry_dir() / "claims" / ("endpoint-" + "".join(c if c.isalnum() else "_" for c in endpoint) + ".lock")
    path.parent.mkdir(parents=True, exist_ok=True)
    handle = open(path, "a+")  # noqa: SIM115 - held for the session, closed by the caller
    if not _lock_exclusive(handle):
        handle.close()
        return None
    return handle


#: how long a claim waits out a lock held for a moment: another tool's probe (:func:`_claim_held`) holds a shared lock
#: for microseconds, msk live holds its claim for the whole session
CLAIM_PROBE_WAIT_S = 0.25


def _lock_exclusive(handle) -> bool:
    """Take ``handle``'s exclusive lock; False when another process keeps it longer than a probe would."""
    deadline = time.monotonic() + CLAIM_PROBE_WAIT_S
    while True:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except BlockingIOError:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)


def _claim_path(session: str) -> Path:
    return registry_dir() / "claims" / f"{session}.lock"


#: the session names this process holds (:func:`claimed`): their announcements by other pids are stale
_claimed_here: set[str] = set()


def _claim_held(session: str, pid: int) -> bool | None:
    """Whether the announcement of ``session`` by ``pid`` has a process holding its claim (:func:`claimed`); None
    when the name was never claimed here. An announcement whose pid lives but whose claim nobody else holds is stale:
    its pid was reused by another program."""
    if session in _claimed_here:
        return pid == os.getpid()
    path = _claim_path(session)
    try:
        with open(path) as handle:
            try:
                fcntl.flock(handle, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                return True
            return False
    except FileNotFoundError:
        return None


def running_sessions() -> list[SessionInfo]:
    """Announced sessions whose ``msk live`` still runs (entries of stopped or killed ones are removed)."""
    found = []
    folder = registry_dir()
    for path in sorted(folder.glob("*.json")) if folder.is_dir() else []:
        try:
            info = read_session_file(path)
        except InputError:
            continue
        if _alive(info.pid) and _claim_held(info.session, info.pid) is not False:
            found.append(info)
        else:
            withdraw(path)
    return found


def announced(session: str) -> SessionInfo | None:
    """The running session named ``session`` as it announces itself on this machine; None when it does not."""
    named = [s for s in running_sessions() if s.session == session]
    return named[-1] if named else None


def announced_facts(session: str) -> dict | None:
    """The facts in effect of the running session named ``session`` as it announces them here; None when no session
    of that name is announced on this machine."""
    info = announced(session)
    return info.facts if info is not None else None


def find_session(
    session: str | None, *, strict: bool = False, running: list[SessionInfo] | None = None
) -> SessionInfo | None:
    """The running session named ``session`` (or the only one when None); None when no session of that name is
    announced (a graph msk live did not start, e.g. a replay, is looked for on the well-known endpoint).

    Raises :class:`ConfigError` when the choice is ambiguous, or with ``strict`` (a one-shot command such as
    ``msk load``, which would otherwise publish to nobody's topic and succeed) when sessions are announced and none
    has that name. ``running``: the sessions of a registry scan the caller made already (default: scan now)."""
    running = running_sessions() if running is None else running
    if session is not None:
        named = [s for s in running if s.session == session]
        if not named and running and strict:
            raise ConfigError(
                "no running session of this name (running: "
                + ", ".join(f"{s.session} on {', '.join(s.connect)}" for s in running)
                + "); a session msk live does not announce here is reached with --connect",
                field="--session",
                value=session,
            )
        return named[-1] if named else None
    if len(running) > 1:
        raise ConfigError(
            "several sessions are running; name one with --session (running: "
            + ", ".join(f"{s.session} on {', '.join(s.connect)}" for s in running)
            + ")",
            field="--session",
        )
    return running[0] if running else None


def gives_endpoint(explicit: ZenohOptions) -> bool:
    """Whether the command line says where to attach (``--connect``, ``--listen``, ``--zenoh-config``): then no
    announced session is looked for."""
    return bool(explicit.connect or explicit.listen or explicit.config_file is not None)


def announced_elsewhere(
    session: str | None, attached: ZenohOptions, running: list[SessionInfo] | None = None
) -> SessionInfo | None:
    """The running session named ``session`` (or the only one) when it is announced somewhere other than where a
    tool is ``attached``: a view or dashboard opened before its ``msk live`` then follows it. None when there is none,
    it is where the tool is, or several run and none is named. ``running`` as :func:`find_session`'s."""
    try:
        info = find_session(session, running=running)
    except ConfigError:
        return None
    return info if info is not None and info.options() != attached else None


class SessionFollower:
    """When a view or dashboard attached to ``attached`` moves to another session (:meth:`next_session`): one announced
    elsewhere (the one named ``session``, or the only one), once the tool has received nothing (it was opened before
    its ``msk live``) or the announced session it showed has ended (the next athlete's session on a tablet left open);
    and a new ``msk live`` announced where the tool is (the next session on the same endpoint, often under the same
    name), which the tool then shows from its start rather than as more of the last one. A tool on a session nobody
    announced (a replay on the well-known endpoint) that receives stays."""

    def __init__(self, session: str | None, attached: ZenohOptions, every_s: float = 1.0) -> None:
        self.session, self.attached, self.every_s = session, attached, every_s
        self._was_announced = False  # the session shown was announced by its msk live at some point
        self._shown_pid: int | None = None  # the msk live that announced it
        self._looked = -float("inf")

    def next_session(self, received: int) -> SessionInfo | None:
        """The session to move to now (looked for at most every ``every_s``; None: stay)."""
        now = time.monotonic()
        if now - self._looked < self.every_s:
            return None
        self._looked = now
        running = running_sessions()  # one registry scan (and claim probe) per look
        here = [info for info in running if info.options() == self.attached]
        if here and (self.session is None or here[-1].session == self.session):
            if self._shown_pid is not None and here[-1].pid != self._shown_pid and received:
                return here[-1]  # another msk live where the tool is: a new session, shown from its start
            self._shown_pid = here[-1].pid
        self._was_announced = self._was_announced or bool(here)
        if received and (here or not self._was_announced):
            return None
        return announced_elsewhere(self.session, self.attached, running)

    def moved(self, attached: ZenohOptions) -> None:
        self.attached, self._was_announced, self._shown_pid = attached, False, None


def attach_options(
    explicit: ZenohOptions, session: str | None, *, one_shot: bool = False
) -> tuple[ZenohOptions, SessionInfo | None]:
    """The Zenoh options of a client: the explicit ones when ``--connect``, ``--listen`` or ``--zenoh-config`` were
    given, else those of the running session :func:`find_session` finds, else the explicit defaults (the well-known
    loopback endpoint).

    ``one_shot``: a command that publishes once and leaves (``msk load``, ``msk set``) attaches as a Zenoh client of
    the node that holds the session's endpoint, which routes its sample to every node of the session. As a peer it would reach only the
    peers it had connected to by then (they find each other by gossip, a moment after joining): the recorder got
    the operator's load event and the estimator did not."""
    if one_shot and explicit.connect and explicit.config_file is None and explicit.mode is None:
        explicit = replace(explicit, mode="client")  # also with --connect: the endpoint's node passes it on
    if gives_endpoint(explicit):
        return explicit, None
    info = find_session(session, strict=one_shot)
    if info is None:
        return explicit, None
    return info.options("client" if one_shot else "peer"), info


def client_options(
    explicit: ZenohOptions, session: str | None, default_session: str, tool: str
) -> tuple[ZenohOptions, str]:
    """A second terminal's tool (``msk dashboard``, ``msk view``, ``msk subscribe``): its Zenoh options and session
    name, from its flags or the running session (:func:`attach_options`); says on stderr where it attaches."""
    options, info = attach_options(explicit, session)
    name = session or (info.session if info is not None else default_session)
    if info is not None:
        print(
            f"{tool}: attached to the running session {name!r} on {', '.join(info.connect)} "
            f"(announced in {info.out}/{SESSION_FILE})",
            file=sys.stderr,
            flush=True,
        )
    elif not gives_endpoint(explicit):
        running = ", ".join(s.session for s in running_sessions())
        print(
            f"{tool}: no running msk live announced in {registry_dir()}"
            + (f" is named {name!r} (running: {running})" if running else "")
            + f"; looking for session {name!r} on {where(options)}",
            file=sys.stderr,
            flush=True,
        )
    return options, name


def silence_notice(
    tool: str,
    waiting_for: Callable[[], tuple[str, ZenohOptions]],
    received,
    *,
    first_s: float = 3.0,
    every_s: float = 15.0,
    stop: threading.Event | None = None,
) -> threading.Thread:
    """A thread that says on stderr, ``first_s`` after start and then every ``every_s`` while ``received()`` stays 0,
    what ``tool`` waits for and where, as ``waiting_for()`` says now (a tool that follows a session it found later
    waits for that one): a wait that says nothing looks like a hang."""
    stop = stop or threading.Event()

    def watch() -> None:
        started = time.monotonic()
        wait = first_s
        while not stop.wait(wait):
            if received():
                return
            what, options = waiting_for()
            print(
                f"{tool}: waited {time.monotonic() - started:.0f} s for {what} on {where(options)}: "
                "0 messages so far (is `msk live` running? `msk live` prints the session and its endpoint)",
                file=sys.stderr,
                flush=True,
            )
            wait = every_s

    thread = threading.Thread(target=watch, name=f"{tool}-silence", daemon=True)
    thread.start()
    return thread


def where(options: ZenohOptions) -> str:
    """Where a client looks, for "waiting for ..." messages."""
    if options.config_file is not None:
        return f"the endpoints of {options.config_file}"
    endpoints = options.connect or options.listen
    return ", ".join(endpoints) if endpoints else "the default loopback endpoint"
