"""Zenoh router node: the meeting point of a multi-machine deployment (``msk router``).

Zenoh's own ``zenohd`` is not packaged for pip or Debian, so the router is the router mode of the Zenoh library that
every node already uses; the same JSON5 config file works for both. Every other node joins as a client of it
(``--mode client --connect tcp/<router-host>:7447``). See docs/deployment.md.
"""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import threading
import time
from dataclasses import replace

import zenoh

from services.transport.stop_signals import stop_on_signals
from services.transport.zenoh_session import (
    DEFAULT_ENDPOINT,
    ZenohOptions,
    add_zenoh_arguments,
    open_session,
    options_from_args,
    run_script,
)


def router_options(options: ZenohOptions) -> ZenohOptions:
    """Router mode; with neither endpoints nor a config file, it listens on loopback :data:`DEFAULT_ENDPOINT`."""
    listen = options.listen
    if options.config_file is None and not options.listen and not options.connect:
        listen = (DEFAULT_ENDPOINT,)
    return replace(options, mode="router", listen=listen)


def listen_endpoints(options: ZenohOptions) -> list[str]:
    """The endpoints a router of ``options`` listens on (its flags', else its config file's; Zenoh's default lists
    them per mode)."""
    endpoints = json.loads(options.to_config().get_json("listen/endpoints"))
    if isinstance(endpoints, dict):
        endpoints = endpoints.get("router", [])
    return [str(e) for e in endpoints] or ["nothing (no listen endpoint)"]


def wait_until_listening(process: subprocess.Popen, port: int, *, timeout_s: float = 30.0) -> None:
    """Return once the router ``process`` accepts TCP connections on loopback ``port``. When it exits first, or
    ``timeout_s`` passes, raise :class:`RuntimeError` naming the port, the wait, the exit code and its stderr's tail
    (the process is killed first when still running)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            return
        except OSError:
            if process.poll() is None and time.monotonic() <= deadline:
                time.sleep(0.05)
                continue
        if process.poll() is None:
            process.kill()
        _, err = process.communicate(timeout=10)
        raise RuntimeError(
            f"msk router did not listen on 127.0.0.1:{port} within {timeout_s:g} s "
            f"(exit {process.returncode}): {(err or '')[-2000:]}"
        )


def main(
    config: ZenohOptions,
    *,
    duration_s: float | None = None,
    stop_event: threading.Event | None = None,
    ready_event: threading.Event | None = None,
) -> str:
    """Run a router until ``stop_event`` is set or ``duration_s`` elapses; returns its Zenoh id."""
    stop_event = stop_event or threading.Event()
    # Zenoh's own log (RUST_LOG, default warn): the access control says there which declaration it refused to whom
    zenoh.init_log_from_env_or("warn")
    options = router_options(config)
    with open_session(options) as session:
        zid = str(session.zid())
        print(f"router {zid} up, listening on {', '.join(listen_endpoints(options))}", file=sys.stderr, flush=True)
        if ready_event is not None:
            ready_event.set()
        deadline = None if duration_s is None else time.monotonic() + duration_s
        while not stop_event.wait(0.2):
            if deadline is not None and time.monotonic() >= deadline:
                break
    return zid


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--duration", type=float, default=None, help="seconds to run (default: until Ctrl-C)")
    add_zenoh_arguments(parser)


def run_from_args(args: argparse.Namespace) -> int:
    stop = stop_on_signals()
    main(options_from_args(args), duration_s=args.duration, stop_event=stop)
    return 0


if __name__ == "__main__":
    run_script(__doc__, add_arguments, run_from_args)
