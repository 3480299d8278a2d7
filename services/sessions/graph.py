"""Starting a graph of Zenoh nodes (threads or processes), knowing when it is ready, and stopping it cleanly.

Shared by ``msk demo``, ``msk live``, ``msk replay`` and the tests. A node says it is ready, and a publisher waits for
the nodes it feeds, through :mod:`services.nodes.readiness`; :class:`Graph` starts the nodes in that order and every
wait here is bounded the same way (:class:`~services.nodes.readiness.GraphTimeout` says what was awaited and what
arrived).
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from services.nodes.readiness import NODE_READY_TIMEOUT_S, GraphTimeout, ReadySpec, ready_key, wait_for_nodes
from services.transport import topics
from services.transport.stop_signals import stop_with_parent_env
from services.transport.zenoh_session import ZenohOptions, open_session

log = logging.getLogger(__name__)


def wait_for(
    what: str, condition: Callable[[], bool], progress: Callable[[], str], timeout_s: float, poll_s: float = 0.05
) -> float:
    """Poll ``condition`` until true; on expiry raise :class:`GraphTimeout` with ``what`` and ``progress()``."""
    started = time.monotonic()
    deadline = started + timeout_s
    while not condition():
        if time.monotonic() >= deadline:
            raise GraphTimeout(f"waited {timeout_s:g} s for {what}; arrived: {progress()}")
        time.sleep(poll_s)
    return time.monotonic() - started


@dataclass
class _ThreadNode:
    name: str
    thread: threading.Thread
    ready: threading.Event
    error: list[BaseException] = field(default_factory=list)


@dataclass
class _ProcessNode:
    name: str
    process: subprocess.Popen
    log_path: Path | None


class Graph:
    """Nodes of one session on one private endpoint: the first node listens, the others connect.

    Use as a context manager; :meth:`stop` sets every thread node's stop event and SIGINTs every process node, then
    joins them (bounded), so a recorder closes its MCAP.
    """

    def __init__(
        self,
        session: str,
        endpoint: str,
        *,
        external_listener: bool = False,
        role_configs: Callable[[str], Path] | None = None,
        observer_role: str = "operator",
    ) -> None:
        """``external_listener``: someone else (e.g. the caller's own session, a router) listens on ``endpoint``;
        every node connects to it. ``role_configs``: the secured mode; each member joins with the Zenoh config file
        of its role (TLS client of the router, ``services.transport.security``), ``observer_role``'s for the readiness check."""
        self.session = topics.check_chunk(session, "session")
        self.endpoint = endpoint
        self.role_configs = role_configs
        self.observer_role = observer_role
        self.stop_event = threading.Event()
        self._threads: list[_ThreadNode] = []
        self._processes: list[_ProcessNode] = []
        self._listening = external_listener

    # -- membership ---------------------------------------------------------------------------------------------

    @property
    def nodes(self) -> list[str]:
        return [n.name for n in self._threads] + [n.name for n in self._processes]

    def options(self, role: str | None = None) -> ZenohOptions:
        """Zenoh options for the next member: the first listens on the endpoint, the rest connect to it; in the
        secured mode, the config of ``role``."""
        if self.role_configs is not None:
            if role is None:
                raise GraphTimeout("a member of a secured graph needs a role")  # a programming error, said plainly
            return ZenohOptions(mode=None, config_file=self.role_configs(role))
        if not self._listening:
            self._listening = True
            return ZenohOptions(listen=(self.endpoint,))
        return ZenohOptions(connect=(self.endpoint,))

    def add_thread(
        self, name: str, target: Callable, *args, after: Sequence[str] = (), role: str | None = None, **kwargs
    ) -> None:
        """Run ``target(options, *args, **kwargs, stop_event=, ready_event=, ready_key=)`` in a thread.

        ``after``: the nodes this one publishes to (see :class:`ReadySpec`)."""
        ready = threading.Event()
        errors: list[BaseException] = []  # the node's, read by wait_ready and stop
        options = self.options(role)

        def run() -> None:
            try:
                target(
                    options,
                    *args,
                    **kwargs,
                    stop_event=self.stop_event,
                    ready_event=ready,
                    ready_key=ReadySpec(self.session, name, tuple(after)),
                )
            except BaseException as error:  # reported by wait_ready/stop, not lost in a thread
                errors.append(error)
                log.exception("node %s failed", name)
                ready.set()

        node = _ThreadNode(name, threading.Thread(target=run, name=f"node-{name}", daemon=True), ready, errors)
        node.thread.start()
        self._threads.append(node)

    def add_process(
        self,
        name: str,
        argv: Sequence[str],
        *,
        after: Sequence[str] = (),
        log_path: Path | None = None,
        env: dict[str, str] | None = None,
        own_session: bool = False,
        role: str | None = None,
    ) -> subprocess.Popen:
        """Start ``argv`` (its Zenoh flags, ``--ready-key`` and ``--ready-after`` appended) as a separate process.

        ``own_session``: in its own process group, so a Ctrl-C in the terminal reaches only the caller, which then
        stops the nodes in the order it chooses (``msk live``); the node stops by itself if the caller is gone
        (:func:`~services.transport.stop_signals.stop_with_parent_env`)."""
        options = self.options(role)
        flags = zenoh_flags(options)
        flags += [f"--ready-after={n}" for n in after]
        out = open(log_path, "wb") if log_path is not None else subprocess.DEVNULL
        process = subprocess.Popen(
            [*argv, *flags, "--ready-key", ready_key(self.session, name)],
            stdout=out,
            stderr=subprocess.STDOUT,
            env={**os.environ, **(stop_with_parent_env() if own_session else {}), **(env or {})},
            start_new_session=own_session,
        )
        self._processes.append(_ProcessNode(name, process, log_path))
        return process

    def process(self, name: str) -> subprocess.Popen | None:
        """The process of node ``name`` (None for a thread node or an unknown name)."""
        return next((n.process for n in self._processes if n.name == name), None)

    # -- readiness ----------------------------------------------------------------------------------------------

    def wait_ready(self, timeout_s: float = NODE_READY_TIMEOUT_S) -> float:
        """Every node up with its subscribers declared, as seen from a fresh session on the graph's endpoint."""
        started = time.monotonic()
        for thread_node in self._threads:
            # in slices: a node process that dies meanwhile (e.g. it could not listen) is said now, not at the timeout
            while not thread_node.ready.wait(min(0.2, max(0.0, started + timeout_s - time.monotonic()))):
                self._raise_failed()
                self._raise_exited()
                if time.monotonic() >= started + timeout_s:
                    ready = sum(n.ready.is_set() for n in self._threads)
                    raise GraphTimeout(
                        f"waited {timeout_s:g} s for node {thread_node.name} (a thread of this process) of session "
                        f"{self.session!r} to be ready: not ready; {ready} of its {len(self._threads)} thread nodes "
                        "ready"
                    )
            self._raise_failed()
        self._raise_exited()
        with open_session(self.observer_options()) as zsession:
            # at least a second for the tokens' history to arrive, however long the threads took
            left = max(1.0, started + timeout_s - time.monotonic())
            wait_for_nodes(zsession, self.session, self.nodes, left, give_up=self._exited_before_ready)
        return time.monotonic() - started

    def _raise_exited(self) -> None:
        for node in self._processes:
            if node.process.poll() is not None:
                raise GraphTimeout(
                    f"node {node.name} exited with code {node.process.returncode} before it was ready"
                    + self._log_tail(node)
                )

    def _exited_before_ready(self) -> str | None:
        """The node processes that exited while the graph waits for readiness (each with its exit code and log)."""
        dead = [n for n in self._processes if n.process.poll() is not None]
        if not dead:
            return None
        return "exited: " + ", ".join(f"{n.name} (exit {n.process.returncode}){self._log_tail(n)}" for n in dead)

    def observer_options(self) -> ZenohOptions:
        """How a client that watches the graph (readiness, ``msk live``'s view) joins it."""
        if self.role_configs is not None:
            return ZenohOptions(mode=None, config_file=self.role_configs(self.observer_role))
        return ZenohOptions(connect=(self.endpoint,))

    def failed(self) -> list[str]:
        """Nodes that stopped with an error (threads) or exited (processes) while the graph runs."""
        bad = [f"{n.name}: {n.error[0]!r}" for n in self._threads if n.error]
        bad += [f"{n.name}: exit {n.process.returncode}" for n in self._processes if n.process.poll() is not None]
        return bad

    def _raise_failed(self) -> None:
        for node in self._threads:
            if node.error:
                raise node.error[0]

    @staticmethod
    def _log_tail(node: _ProcessNode) -> str:
        if node.log_path is None or not node.log_path.is_file():
            return ""
        return "; its log ends with:\n" + "\n".join(node.log_path.read_text(errors="replace").splitlines()[-15:])

    # -- stop ---------------------------------------------------------------------------------------------------

    def stop(self, timeout_s: float = 30.0) -> dict[str, int | None]:
        """Stop every node; returns the exit code of each process node (None: it had to be killed)."""
        self.stop_event.set()
        for node in self._processes:
            if node.process.poll() is None:
                node.process.send_signal(signal.SIGINT)
        deadline = time.monotonic() + timeout_s
        codes: dict[str, int | None] = {}
        for node in self._processes:
            try:
                codes[node.name] = node.process.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.error("node %s did not stop within %g s after SIGINT; killed", node.name, timeout_s)
                node.process.kill()
                node.process.wait(5)
                codes[node.name] = None
        for thread_node in self._threads:
            thread_node.thread.join(max(0.1, deadline - time.monotonic()))
            if thread_node.thread.is_alive():
                log.error("node %s did not stop within %g s", thread_node.name, timeout_s)
        return codes

    def __enter__(self) -> Graph:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def zenoh_flags(options: ZenohOptions) -> list[str]:
    """The command-line flags (services.transport.zenoh_session.add_zenoh_arguments) that give a process ``options``."""
    flags = [f"--listen={e}" for e in options.listen] + [f"--connect={e}" for e in options.connect]
    if options.config_file is not None:
        flags.append(f"--zenoh-config={options.config_file}")
    if options.mode is not None and options.config_file is None:
        flags.append(f"--mode={options.mode}")
    return flags


def python_module(module: str, *args: str) -> list[str]:
    """argv running ``python -m module args`` with this interpreter."""
    return [sys.executable, "-m", module, *args]


def pids_path(out: Path) -> Path:
    """Where ``msk live --out OUT`` lists the process ids of the nodes it started (node name -> pid, JSON)."""
    return out / "logs" / "pids.json"


def kill_live(process: subprocess.Popen, out: Path) -> None:
    """Kill ``msk live --out OUT`` by hand (a session that did not end): its process group and those of the nodes it
    started (each runs in a group of its own), listed in :func:`pids_path`; the caller then reaps ``process``."""
    pids = pids_path(out)
    groups = [process.pid, *(json.loads(pids.read_text()).values() if pids.is_file() else [])]
    for pid in groups:
        try:
            os.killpg(pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
