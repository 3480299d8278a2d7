"""Shared by the tests that run ``msk`` as a user would: the CLI in a subprocess of the repository, a whole
``msk live --sim`` session (:class:`LiveProcess`), the wait for its graph to be up and the clean-up after a failed test
(msk live and the node processes it started, each in a process group of its own)."""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import IO, Any

from services.sessions.graph import kill_live

REPO = Path(__file__).resolve().parents[1]
STARTUP_S = 150.0  # calibration (~3 s when not cached, ~20 s more when numba compiles its kernel) + five processes
# importing and warming up on 2 shared cores


def run_msk(*argv: str, env: dict[str, str] | None = None, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    """``msk ARGV`` to the end, its output captured (``env`` None: this process's environment)."""
    return subprocess.run(
        [sys.executable, "-m", "services.cli", *argv],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def start_msk(*argv: str, env: dict[str, str]) -> subprocess.Popen[str]:
    """``msk ARGV`` started in a process group of its own (a Ctrl-C goes to it and its nodes), stderr into stdout, with
    SIGHUP's default action as under a terminal: a suite started with ``nohup`` passes its ignored SIGHUP on, and
    ``msk live`` rightly keeps running when started so (services.transport.stop_signals)."""
    return subprocess.Popen(
        [sys.executable, "-c", _MSK_WITH_SIGHUP_DEFAULT, *argv],  # not preexec_fn: unsafe in a threaded parent
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )


_MSK_WITH_SIGHUP_DEFAULT = (
    "import runpy, signal; signal.signal(signal.SIGHUP, signal.SIG_DFL); "
    "runpy.run_module('services.cli', run_name='__main__', alter_sys=True)"
)


def start_subscribe(key: str, *options: str) -> subprocess.Popen[str]:
    """``msk subscribe KEY --json OPTIONS``, stdout and stderr on pipes of their own; returned once it said on stderr
    that it subscribed to KEY (read in a thread, at most 60 s; else it is killed and the test fails)."""
    process = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "subscribe", key, "--json", *options],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    stderr = process.stderr
    assert stderr is not None
    first_line: list[str] = []
    reader = threading.Thread(target=lambda: first_line.append(stderr.readline()), daemon=True)
    reader.start()
    reader.join(60)
    if not (first_line and f"subscribed to {key}" in first_line[0]):
        process.kill()
        raise AssertionError(f"msk subscribe did not say within 60 s that it subscribed to {key}: {first_line}")
    return process


def wait_running(process: subprocess.Popen[str], lines: list[str]) -> None:
    """Read ``process``'s output into ``lines`` until msk live says its session is running (at most STARTUP_S), whole
    lines only. Read from the pipe itself: a buffered ``readline`` after ``select`` left the lines that came in the same
    chunk in Python's buffer, unseen by the next ``select``, which then waited for output that had already come (a
    line more before "running" made a test wait out msk live's whole duration). The reader's own buffer stays empty,
    so ``readline`` and ``communicate`` go on from here."""
    stdout: IO[str] | None = process.stdout
    assert stdout is not None
    fd = stdout.fileno()
    deadline = time.monotonic() + STARTUP_S
    partial = b""
    while partial or not any("live session" in line and "running" in line for line in lines):
        left = deadline - time.monotonic()
        assert left > 0 and process.poll() is None, (
            f"msk live --sim not running after {STARTUP_S:g} s; output:\n" + "".join(lines) + partial.decode()
        )
        ready, _, _ = select.select([fd], [], [], min(left, 1.0))
        if ready:
            chunk = os.read(fd, 65536)
            assert chunk, "msk live closed its output; output:\n" + "".join(lines) + partial.decode()
            *complete, partial = (partial + chunk).split(b"\n")
            lines.extend(line.decode() + "\n" for line in complete)


def kill_session(process: subprocess.Popen[str], out: Path) -> None:
    """After a failed test: msk live and its nodes killed (:func:`services.sessions.graph.kill_live`), msk live
    reaped."""
    kill_live(process, out)
    process.wait(10)


def live_environment(tmp_path: Path) -> dict[str, str]:
    """This process's environment with the user's calibration cache (the calibrated bundled subject), a registry of
    sessions of the test's own and unbuffered output."""
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return {
        **os.environ,
        "XDG_CACHE_HOME": str(cache),
        "MSK_SESSIONS_DIR": str(tmp_path / "sessions"),
        "PYTHONUNBUFFERED": "1",
    }


def run_sim_graph(session: Any, tmp: Path, duration_s: float, **patched: Any) -> tuple[dict, Any, Any, int]:
    """The graph of ``session`` (a LiveSession) on its simulators for ``duration_s``, in this process
    (``live.plan_for`` and ``live.run_graph`` on a free loopback endpoint), with a session registry under ``tmp`` and
    the attributes ``patched`` of services.sessions.live replaced meanwhile. Returns (summary, plan, simulators,
    CLOCK_REALTIME minus the monotonic clock in ns, read just before the graph starts)."""
    import pytest

    from services.sessions import live
    from services.transport.zenoh_session import free_loopback_endpoint

    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MSK_SESSIONS_DIR", str(tmp / "sessions"))
        for name, value in patched.items():
            patch.setattr(live, name, value)
        plan, simulators = live.plan_for(session, sim=True, log=print)
        real_minus_monotonic_ns = time.time_ns() - time.monotonic_ns()
        try:
            summary = live.run_graph(
                plan,
                duration_s=duration_s,
                view=False,
                endpoint=free_loopback_endpoint(),
                log=print,
                simulators=simulators,
            )
        finally:
            simulators.close()
    return summary, plan, simulators, real_minus_monotonic_ns


class LiveProcess:
    """``msk live --sim`` in a subprocess; :meth:`wait_running` reads its output until the graph is up."""

    def __init__(self, out: Path, env: dict[str, str], *extra: str) -> None:
        self.out = out
        self.lines: list[str] = []
        self.process = start_msk("live", "--sim", "--no-view", "--duration", "150", "--out", str(out), *extra, env=env)

    def wait_running(self) -> str:
        wait_running(self.process, self.lines)
        return next(line for line in self.lines if "live session" in line)

    def stop(self) -> tuple[int, str, dict]:
        os.killpg(self.process.pid, signal.SIGINT)  # Ctrl-C
        rest, _ = self.process.communicate(timeout=90)
        output = "".join(self.lines) + rest
        return self.process.returncode, output, json.loads((self.out / "summary.json").read_text())

    def kill(self) -> None:
        """After a failed test: msk live and its nodes."""
        kill_session(self.process, self.out)


def write_subject(path: Path, emg_normalisation: dict | None = None, pack: str = "bench_press") -> Path:
    """A subject profile of ``pack`` at its reference strengths, with ``emg_normalisation``: what ``msk live``
    checks before it starts (a session file's subject must be a profile of the session's pack)."""
    import numpy as np

    from msk_core.estimate.profile import SubjectProfile
    from msk_core.model import load_pack

    model = load_pack(pack)
    ones = np.ones(len(model.groups))
    profile = SubjectProfile(model.name, str(model.version), list(model.groups), ones, ones)
    profile.emg_normalisation = dict(emg_normalisation or {})
    profile.save(path)
    return path
