"""The secured deployment across hosts, for real: Linux network namespaces on this machine, one per host.

docs/deployment.md draws a rack PC (drivers, recorder, router), a server (kinematics, estimator) and tablets on the
gym network. :class:`Hosts` makes those hosts as network namespaces joined by veth links to a bridge in the rack PC's
namespace (the gym's switch), with only addresses inside them (``10.77.0.0/24``: rack 10.77.0.1, server 10.77.0.2,
tablet 10.77.0.3); each namespace has its own loopback, so the Trigno simulator the rack's driver reads is on the
rack's loopback and nowhere else. :class:`Deployment` runs the real ``msk`` commands there with the certificates and
access control of ``msk certs`` (the router's certificate names 10.77.0.1): ``msk router``, ``msk sim trigno``, one
``msk sim xsens`` per tracker, ``msk drivers`` and ``msk recorder`` on the rack PC; ``msk kinematics`` and
``msk estimator`` on the server; ``msk subscribe`` (the tablet role: activations and status only) on the tablet.

Faults are made between hosts: :meth:`Hosts.link` takes a host's cable out of the switch and puts it back,
:meth:`Deployment.restart_router` stops the router and starts it again on the same address. Namespace names are
unique per run (``msk<pid>x<random>-<host>``) and always deleted when the context ends; namespaces left by a run that
died (its pid gone) are deleted by the next. Creating namespaces needs root and ``ip`` (iproute2): :func:`unavailable`
says why not otherwise. Used by tests/test_hosts.py and ``msk bench sessions`` (services/bench/sessions.py).
"""

from __future__ import annotations

import contextlib
import ctypes
import io
import json
import os
import re
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

SUBNET = "10.77.0"
HOST_NUMBERS = {"rack": 1, "server": 2, "tablet": 3}
ROUTER_PORT = 7447
DASHBOARD_PORT = 8443
PACK = "bench_press"
DEMO = Path(__file__).resolve().parents[2] / "recordings" / "demo_session.mcap"
_CLONE_NEWNET = 0x40000000
#: an input that reached the estimator this soon after a fault began was on its way before it
IN_FLIGHT_NS = 200_000_000
_NAME = re.compile(r"^msk(\d+)x[0-9a-f]+-(rack|server|tablet)$")


def _ip(*argv: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    result = subprocess.run(["ip", *argv], capture_output=True, text=True, timeout=20)
    if check and result.returncode != 0:
        raise RuntimeError(f"ip {' '.join(argv)} failed ({result.returncode}): {result.stderr.strip()}")
    return result


def namespaces() -> set[str]:
    """The names of the network namespaces there are now."""
    return {line.split(" ", 1)[0] for line in _ip("netns", "list", check=False).stdout.splitlines() if line}


def unavailable() -> str | None:
    """Why network namespaces cannot be made here (None when they can): they need root and iproute2's ``ip``."""
    if not sys.platform.startswith("linux"):
        return f"network namespaces are Linux only (this is {sys.platform})"
    if os.geteuid() != 0:
        return "network namespaces need root (ip netns add); run as root to deploy across namespaces"
    if shutil.which("ip") is None:
        return "iproute2's `ip` is not installed (apt-get install iproute2)"
    probe = f"msk{os.getpid()}x{secrets.token_hex(3)}-rack"
    made = _ip("netns", "add", probe, check=False)
    if made.returncode != 0:
        return f"`ip netns add` is refused here: {made.stderr.strip()}"
    _ip("netns", "delete", probe, check=False)
    return None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def delete_stale() -> list[str]:
    """Delete the namespaces of runs whose process is gone (a killed test); returns their names."""
    stale = []
    for name in namespaces():
        match = _NAME.match(name)
        if match and not _alive(int(match.group(1))):
            _ip("netns", "delete", name, check=False)
            stale.append(name)
    return stale


class Hosts:
    """The rack PC, the server and the tablet as network namespaces behind one switch (a bridge in the rack's)."""

    def __init__(self) -> None:
        tag = f"msk{os.getpid()}x{secrets.token_hex(3)}"
        self.names = {host: f"{tag}-{host}" for host in HOST_NUMBERS}
        self.made: list[str] = []

    def __enter__(self) -> Hosts:
        delete_stale()
        try:
            self._make()
        except BaseException:
            self.delete()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.delete()

    def address(self, host: str) -> str:
        return f"{SUBNET}.{HOST_NUMBERS[host]}"

    def _make(self) -> None:
        rack = self.names["rack"]
        for name in self.names.values():
            _ip("netns", "add", name)
            self.made.append(name)
            _ip("-n", name, "link", "set", "lo", "up")
        _ip("-n", rack, "link", "add", "switch", "type", "bridge")
        _ip("-n", rack, "addr", "add", f"{self.address('rack')}/24", "dev", "switch")
        _ip("-n", rack, "link", "set", "switch", "up")
        for host in ("server", "tablet"):
            # the host's cable: "eth0" in its namespace, "port-<host>" on the rack's switch
            _ip(
                "-n",
                rack,
                "link",
                "add",
                self.port(host),
                "type",
                "veth",
                "peer",
                "name",
                "eth0",
                "netns",
                self.names[host],
            )
            _ip("-n", rack, "link", "set", self.port(host), "master", "switch")
            _ip("-n", rack, "link", "set", self.port(host), "up")
            _ip("-n", self.names[host], "addr", "add", f"{self.address(host)}/24", "dev", "eth0")
            _ip("-n", self.names[host], "link", "set", "eth0", "up")

    @staticmethod
    def port(host: str) -> str:
        return f"port-{host}"

    def link(self, host: str, *, up: bool) -> None:
        """Put ``host``'s cable into the switch (``up``) or pull it out."""
        _ip("-n", self.names["rack"], "link", "set", self.port(host), "up" if up else "down")

    def delete(self) -> None:
        for name in reversed(self.made):
            _ip("netns", "delete", name, check=False)
        self.made.clear()

    def argv(self, host: str, argv: list[str]) -> list[str]:
        """``argv`` run on ``host`` (``ip netns exec`` execs it: the process id is the command's own)."""
        return ["ip", "netns", "exec", self.names[host], *argv]

    def run_inside(self, host: str, function: Callable[[], Any]) -> Any:
        """Call ``function`` in a thread that joined ``host``'s network namespace (sockets it opens are there)."""
        outcome: dict[str, Any] = {}

        def target() -> None:
            libc = ctypes.CDLL(None, use_errno=True)
            with open(f"/run/netns/{self.names[host]}") as handle:
                if libc.setns(handle.fileno(), _CLONE_NEWNET) != 0:
                    outcome["error"] = OSError(ctypes.get_errno(), f"setns into {self.names[host]}")
                    return
            try:
                outcome["value"] = function()
            except BaseException as error:  # handed to the caller
                outcome["error"] = error

        thread = threading.Thread(target=target, name=f"in-{host}")
        thread.start()
        thread.join()
        if "error" in outcome:
            raise outcome["error"]
        return outcome.get("value")

    def executable(self, host: str, program: str, path: Path) -> Path:
        """A script at ``path`` that runs ``program`` (with its arguments) on ``host``: for a tool that starts a
        program itself, such as Playwright a browser."""
        path.write_text(f'#!/bin/sh\nexec ip netns exec {self.names[host]} {program} "$@"\n')
        path.chmod(0o755)
        return path

    def accepts(self, host: str, address: str, port: int) -> bool:
        """Whether a TCP connection from ``host`` to ``address:port`` is accepted now."""

        def probe() -> bool:
            try:
                socket.create_connection((address, port), timeout=0.5).close()
                return True
            except OSError:
                return False

        return bool(self.run_inside(host, probe))


def msk_argv(*argv: str) -> list[str]:
    return [sys.executable, "-m", "services.cli", *argv]


@dataclass
class Tablet:
    """What the tablet's ``msk subscribe --json`` printed: (arrival host time ns, key, message) per line."""

    received: list[tuple[int, str, dict]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def read(self, stream: IO[str]) -> None:
        for line in stream:
            arrival = time.time_ns()
            try:
                document = json.loads(line)
            except json.JSONDecodeError:
                continue
            with self.lock:
                self.received.append((arrival, document["key"], document["message"]))

    def frames(self, since_ns: int = 0) -> list[tuple[int, dict]]:
        with self.lock:
            return [(t, m) for t, k, m in self.received if "/activations/" in k and t >= since_ns]

    def statuses(self, since_ns: int = 0) -> list[tuple[int, dict]]:
        with self.lock:
            return [(t, m) for t, k, m in self.received if "/status/" in k and t >= since_ns]


@dataclass
class Process:
    host: str
    name: str
    popen: subprocess.Popen[str]
    log: Path


class Deployment:
    """The secured session across the three hosts (see the module's doc). ``start()`` returns once the tablet
    receives activation frames; ``stop()`` stops in order and returns each process's log (the drivers' and the
    estimator's summaries are there)."""

    def __init__(self, hosts: Hosts, work: Path, *, session: str = "gym", methods: tuple[str, ...] = ("so",)) -> None:
        self.hosts, self.work, self.session, self.methods = hosts, Path(work), session, methods
        self.processes: dict[str, Process] = {}
        self.tablet = Tablet()
        self.recording = self.work / "rack.mcap"
        self.pki = self.work / "pki"
        self.router_address = hosts.address("rack")

    # --- start ------------------------------------------------------------------------------------------------

    def config(self, role: str) -> str:
        return str(self.pki / "zenoh" / f"{role}.json5")

    def _spawn(self, host: str, name: str, argv: list[str], *, stdout_pipe: bool = False) -> Process:
        log = self.work / "logs" / f"{name}.log"
        log.parent.mkdir(parents=True, exist_ok=True)
        with open(log, "ab") as err:
            popen = subprocess.Popen(
                self.hosts.argv(host, argv),
                stdout=subprocess.PIPE if stdout_pipe else err,
                stderr=err,
                stdin=subprocess.DEVNULL,
                text=True,
                start_new_session=True,
            )
        process = Process(host, name, popen, log)
        self.processes[name] = process
        return process

    def make_pki(self) -> None:
        """``msk certs`` for a router reached at the rack's address: every role's certificate and Zenoh config."""
        from services.cli import main

        with contextlib.redirect_stdout(io.StringIO()):
            main(["certs", "--out", str(self.pki), "--router-host", self.router_address, "--port", str(ROUTER_PORT)])

    def start_router(self, timeout_s: float = 60.0) -> None:
        router = self._spawn("rack", "router", msk_argv("router", "--zenoh-config", self.config("router")))
        self.wait(
            lambda: self.hosts.accepts("rack", self.router_address, ROUTER_PORT),
            timeout_s,
            f"msk router listening on {self.router_address}:{ROUTER_PORT}",
            have=lambda: f"router log: {_tail(router.log, 600)}",
            watch=(router,),
        )

    def _start_devices(self) -> Process:
        """The simulators on the rack PC, in one process (:func:`serve_simulators`)."""
        return self._spawn("rack", "sim-devices", [sys.executable, "-m", "services.bench.hosts", "simulators"],
                           stdout_pipe=True)  # fmt: skip

    @staticmethod
    def _devices(sims: Process) -> tuple[dict[str, int], dict[str, str], dict[str, str], dict[str, Any]]:
        """What the simulators said once ready: the Trigno's ports on the rack's loopback, each tracker's
        pseudo-terminal and segment, and the trial's facts (electrode map, load)."""
        line = sims.popen.stdout.readline() if sims.popen.stdout is not None else ""
        try:
            said = json.loads(line)
        except json.JSONDecodeError:
            raise RuntimeError(f"the simulators did not report their ports: {line!r}; {_tail(sims.log)}") from None
        ptys = {tracker: pty for tracker, (_, pty) in said["trackers"].items()}
        segments = {tracker: segment for tracker, (segment, _) in said["trackers"].items()}
        return said["ports"], ptys, segments, said["trial"]

    def start(self, timeout_s: float = 120.0) -> None:
        """The router, then the readers (recorder, kinematics, estimator, tablet), then, once the kinematics node and
        the estimator report (their status reaches the tablet), the devices and the drivers, as ``msk live`` waits
        for the readers; returns when the tablet receives activation frames."""
        sims = self._start_devices()  # while the processes start (reading the trial takes seconds)
        self.make_pki()
        self.start_router()
        s = ("--session", self.session)
        # with its session, the recorder reports its status (what it missed live and fetched again) on status/recorder
        self._spawn("rack", "recorder", msk_argv("recorder", "--out", str(self.recording), "--flush-interval", "0.5",
                                                 *s, "--zenoh-config", self.config("recorder")))  # fmt: skip
        self._spawn("server", "kinematics", msk_argv("kinematics", "--pack", PACK, *s, "--imu-clock", "host",
                                                     "--zenoh-config", self.config("kinematics")))  # fmt: skip
        for what in ("activations", "status"):
            tablet = self._spawn(
                "tablet", f"tablet-{what}",
                msk_argv("subscribe", "--json", f"msk/{self.session}/{what}/*", "--zenoh-config", self.config("tablet")),
                stdout_pipe=True,
            )  # fmt: skip
            if tablet.popen.stdout is not None:
                threading.Thread(target=self.tablet.read, args=(tablet.popen.stdout,), daemon=True).start()
        # the devices start streaming when the drivers start them (one trial clock, from its static start)
        ports, ptys, segments, trial = self._devices(sims)
        # the estimator reads the EMG too (its largest input, across the server's link), counting gaps and losses
        methods = [a for m in self.methods for a in ("--method", m)]
        emg = ["--emg", *(f"--emg-map={c}={g}" for c, g in trial["electrodes"].items()), "--emg-clock", "host",
               "--joints-clock", "host", "--emg-align", "arrival"]  # fmt: skip
        self._spawn("server", "estimator", msk_argv("estimator", "--pack", PACK, *s, *methods, *emg, "--load-kg",
                                                    str(trial["load_kg"]), "--zenoh-config", self.config("estimator")))  # fmt: skip

        def reporting() -> set[str]:
            return {str(m.get("device_id")) for _, m in self.tablet.statuses()}

        self.wait(
            lambda: {"kinematics", "estimator"} <= reporting(),
            timeout_s,
            "the kinematics node's and the estimator's status at the tablet",
            have=lambda: f"statuses of {sorted(reporting())}",
        )
        drivers = [
            "drivers", *s, "--trigno", f"127.0.0.1:{ports['command']}", "--trigno-emg-port", str(ports["emg"]),
            *(a for path in ptys.values() for a in ("--xsens", path)),
            *(f"--segment={tracker}={segment}" for tracker, segment in segments.items()),
            "--zenoh-config", self.config("driver"),
        ]  # fmt: skip
        self._spawn("rack", "drivers", msk_argv(*drivers))
        self.wait(
            lambda: len(self.tablet.frames()) > 20,
            timeout_s,
            "20 activation frames at the tablet",
            have=lambda: f"{len(self.tablet.frames())} frames, {len(self.tablet.statuses())} statuses",
        )

    def start_dashboard(self, timeout_s: float = 90.0) -> str:
        """``msk dashboard --pki`` on the rack PC at the rack's address (the dashboard certificate of ``msk certs``
        names it), joined to the router as the tablet role; returns its URL once a tablet can connect to it."""
        address = self.router_address
        dashboard = self._spawn(
            "rack", "dashboard",
            msk_argv("dashboard", "--pki", str(self.pki), "--host", address, "--port", str(DASHBOARD_PORT),
                     "--session", self.session),
        )  # fmt: skip
        self.wait(
            lambda: self.hosts.accepts("tablet", address, DASHBOARD_PORT),
            timeout_s,
            f"msk dashboard --pki listening on {address}:{DASHBOARD_PORT}, seen from the tablet",
            watch=(dashboard,),
        )
        return f"https://{address}:{DASHBOARD_PORT}"

    # --- faults -----------------------------------------------------------------------------------------------

    def restart_router(self, down_s: float = 1.0) -> dict[str, float]:
        """Stop the router (SIGTERM), wait ``down_s``, start it again; returns how long stopping and starting took."""
        router = self.processes["router"].popen
        began = time.monotonic()
        router.send_signal(signal.SIGTERM)
        try:
            router.wait(15)
        except subprocess.TimeoutExpired:
            router.kill()
            router.wait(10)
        stopped = time.monotonic()
        time.sleep(down_s)
        self.start_router()
        return {"router_stop_s": stopped - began, "router_start_s": time.monotonic() - stopped - down_s}

    # --- waiting and stopping ---------------------------------------------------------------------------------

    def wait(
        self,
        predicate: Callable[[], bool],
        timeout_s: float,
        what: str,
        have: Callable[[], str] = lambda: "",
        watch: tuple[Process, ...] | None = None,
    ) -> None:
        """Until ``predicate()``; on expiry, or when a watched process (default: all) exits, raise saying what was
        waited for, what arrived and which process exited."""
        deadline = time.monotonic() + timeout_s
        watched = list(self.processes.values()) if watch is None else list(watch)
        while not predicate():
            gone = [p for p in watched if p.popen.poll() is not None]
            if gone or time.monotonic() > deadline:
                reason = "; ".join(f"{p.name} exited {p.popen.returncode}: {_tail(p.log)}" for p in gone)
                raise RuntimeError(
                    f"waited {timeout_s:.0f} s for {what}; have {have() or 'nothing'}"
                    + (f"; {reason}" if reason else "")
                )
            time.sleep(0.05)

    def stop(self) -> dict[str, str]:
        """Stop in order (drivers, then the readers, then the router) and return each process's log."""
        order = ["drivers", *(n for n in self.processes if n.startswith("sim-")), "kinematics", "estimator",
                 "recorder", "dashboard", "tablet-activations", "tablet-status", "router"]  # fmt: skip
        for name in order:
            process = self.processes.get(name)
            if process is not None:
                _stop(process.popen)
        for process in self.processes.values():
            _stop(process.popen)
        return {name: p.log.read_text(errors="replace") for name, p in self.processes.items() if p.log.exists()}


def _stop(popen: subprocess.Popen[str], timeout_s: float = 20.0) -> None:
    if popen.poll() is None:
        popen.send_signal(signal.SIGINT)
        try:
            popen.wait(timeout_s)
        except subprocess.TimeoutExpired:
            popen.kill()
            popen.wait(10)
    if popen.stdout is not None:
        popen.stdout.close()


def _tail(path: Path, chars: int = 1500) -> str:
    try:
        return path.read_text(errors="replace")[-chars:]
    except OSError:
        return "(no log)"


# --- the faults between hosts, and what each host got -------------------------------------------------------------


@dataclass
class Fault:
    """One fault: what, when it began and ended (host clock, ns; all namespaces share the machine's clock)."""

    name: str
    begin_ns: int
    end_ns: int
    detail: dict[str, float] = field(default_factory=dict)


def run_faults(
    deployment: Deployment, *, down_s: float = 3.0, settle_s: float = 3.0, timeout_s: float = 40.0
) -> list[Fault]:
    """The server's link down ``down_s`` and back, the tablet's link down ``down_s`` and back, the router stopped and
    started again; after each, wait until the tablet receives activation frames again (the estimator resumed and its
    frames cross the network), then ``settle_s`` of normal running."""
    faults = []

    def resumed(after_ns: int, what: str) -> None:
        deployment.wait(
            lambda: any(int(m.get("publish_ns", 0)) > after_ns for _, m in deployment.tablet.frames(after_ns)),
            timeout_s,
            f"activation frames at the tablet after {what}",
            have=lambda: (
                f"{len(deployment.tablet.frames())} frames in all, {len(deployment.tablet.frames(after_ns))} after it"
            ),
        )
        time.sleep(settle_s)

    for host in ("server", "tablet"):
        begin = time.time_ns()
        deployment.hosts.link(host, up=False)
        time.sleep(down_s)
        deployment.hosts.link(host, up=True)
        faults.append(Fault(f"{host} link down {down_s:g} s", begin, time.time_ns()))
        resumed(faults[-1].end_ns, faults[-1].name)
    begin = time.time_ns()
    took = deployment.restart_router()
    faults.append(Fault("router restarted", begin, time.time_ns(), took))
    resumed(faults[-1].end_ns, faults[-1].name)
    return faults


def _published(log: str, kind: str, what: str = "samples") -> int:
    """Samples (or ``what="messages"``) ``msk drivers`` says it published for the Trigno (its first summary line) or
    the trackers (second)."""
    found = re.findall(r"published (\d+) samples in (\d+) messages", log)
    index = 0 if kind == "trigno" else 1
    return int(found[index][0 if what == "samples" else 1]) if len(found) > index else -1


def _summaries(logs: dict[str, str]) -> dict[str, Any]:
    """The estimator's and the kinematics node's summary lines; the frames the estimator flagged per status (all
    methods) and the invalid_input ones per reason, as its summary says."""

    def line(node: str, start: str) -> str:
        return next((text for text in logs.get(node, "").splitlines() if text.startswith(start)), "")

    return {
        "estimator_summary": line("estimator", "estimated "),
        **_flagged(logs.get("estimator", "")),
        "kinematics_summary": line("kinematics", "published "),
    }


def _flagged(log: str) -> dict[str, dict[str, int]]:
    """The estimator summary's ``flagged {...}`` and ``(invalid input: {...})``: frames per status and per reason."""
    import ast

    flagged = re.search(r"^estimated \d+ frames; flagged (\{[^}]*\}|none)( \(invalid input: (\{[^}]*\})\))?", log, re.M)
    if flagged is None:
        return {"estimator_flagged": {}, "estimator_invalid": {}}
    return {
        "estimator_flagged": {} if flagged.group(1) == "none" else ast.literal_eval(flagged.group(1)),
        "estimator_invalid": ast.literal_eval(flagged.group(3)) if flagged.group(3) else {},
    }


def _recorder_lost(log: str) -> dict[str, int]:
    """Per key, the publications the recorder's summary line says it missed live and could not fetch again."""
    found = re.search(r"lost \d+ \(([^)]*)\)", log)
    if found is None:
        return {}
    return {key: int(n) for key, n in (part.rsplit(" ", 1) for part in found.group(1).split(", "))}


def _recorded(path: Path) -> dict[str, Any]:
    """What the rack's recorder holds: EMG chunks and samples, index gaps and repeats, IMU samples, joint frames,
    activation frames (with their publish times), and the last status of each node."""
    from services.transport import messages
    from services.transport.mcap_io import read_messages

    emg_next: int | None = None
    last_ns = 0  # host time of the chunk before
    got: dict[str, Any] = {"emg_chunks": 0, "emg_samples": 0, "emg_gaps": [], "emg_repeats": 0, "imu": 0, "joints": 0}
    frames: list[tuple[int, int]] = []  # (publish, input arrival) host times
    statuses: dict[str, Any] = {}
    outages: dict[tuple[int, int], tuple[float, list[str]]] = {}  # the estimator's last outage, as each status said
    sizes: set[int] = set()  # EMG chunk sizes
    for message in read_messages(path):
        kind = message.topic.split("/")[2]
        if kind == "emg":
            chunk = message.decode(messages.EmgChunk)
            got["emg_chunks"] += 1
            got["emg_samples"] += chunk.n_samples
            sizes.add(chunk.n_samples)
            if emg_next is not None and chunk.first_sample_index < emg_next:
                got["emg_repeats"] += 1
            elif emg_next is not None and chunk.first_sample_index > emg_next:
                got["emg_gaps"].append((last_ns, chunk.first_sample_index - emg_next))  # when the missing ones began
            emg_next = max(emg_next or 0, chunk.first_sample_index + chunk.n_samples)
            last_ns = chunk.host_time_ns
        elif kind == "imu":
            got["imu"] += 1
        elif kind == "joints":
            got["joints"] += 1
        elif kind == "activations":
            frame = message.decode(messages.ActivationFrame)
            frames.append((int(frame.publish_ns), int(frame.input_arrival_ns)))
        elif kind == "status":
            status = message.decode(messages.DeviceStatus)
            statuses[message.topic.rsplit("/", 1)[1]] = status
            last = status.outages
            if status.device_id == "estimator" and last.count:
                outages[(last.last_start_ns, last.last_end_ns)] = (
                    (last.last_end_ns - last.last_start_ns) / 1e9,
                    [key.split("/", 2)[-1] for key in last.last_keys],
                )
    got["frames_publish_ns"] = sorted(frames)
    got["emg_chunk_sizes"] = [min(sizes), max(sizes)] if sizes else []
    got["estimator_inputs"] = int(statuses["estimator"].samples_received) if "estimator" in statuses else -1
    got["estimator_status_outages"] = _union(outages)
    for node in ("estimator", "recorder"):
        if node in statuses:
            got[f"{node}_outages"] = {
                "count": int(statuses[node].outages.count),
                "total_s": round(statuses[node].outages.total_s, 3),
                "missed": int(statuses[node].outages.missed),
                "recovered": int(statuses[node].outages.recovered),
            }
    return got


def _union(said: dict[tuple[int, int], tuple[float, list[str]]]) -> list[tuple[int, int, float, list[str]]]:
    """The outages the estimator's statuses reported as their last one, each once: a status sent while a silence's
    streams come back one by one shows it growing (one key's silence, then merged with the next), so overlapping
    reports are one outage. (begin ns, end ns, seconds, streams)."""
    merged: list[tuple[int, int, float, list[str]]] = []
    for (start, end), (_, keys) in sorted(said.items()):
        if merged and start <= merged[-1][1]:
            begin, until, _, known = merged.pop()
            start, end, keys = begin, max(end, until), sorted(set(known) | set(keys))
        merged.append((start, end, (end - start) / 1e9, keys))
    return merged


def outcome(
    deployment: Deployment, faults: list[Fault], logs: dict[str, str], *, until_ns: int | None = None
) -> dict[str, Any]:
    """Counts per host after a stopped run: what the drivers published and the rack's recorder holds, what reached
    the estimator and what it published, what the tablet received; per fault the estimator's frames during it and
    how soon after its end the estimator published again (``resume_s``) and the tablet received again; latencies
    outside the faults and before ``until_ns`` (estimator input to output; estimator to tablet across the network)."""
    import numpy as np

    from services.bench.sessions import latency_figures

    recorded = _recorded(deployment.recording)
    frames = recorded.pop("frames_publish_ns")
    status_outages = recorded.pop("estimator_status_outages")
    published_ns = [p for p, _ in frames]
    tablet = deployment.tablet.frames()
    per_fault = []
    for fault in faults:
        after = [t for t in published_ns if t > fault.end_ns]
        tablet_after = [t for t, _ in tablet if t > fault.end_ns]
        per_fault.append(
            {
                "fault": fault.name,
                "down_s": (fault.end_ns - fault.begin_ns) / 1e9,
                **fault.detail,
                # frames of inputs that reached the estimator during the fault (what it still held or what was on
                # its way when the fault began is not counted: an estimator that lags publishes those later)
                "frames_during": sum(1 for _, a in frames if fault.begin_ns + IN_FLIGHT_NS <= a <= fault.end_ns),
                "resume_s": (after[0] - fault.end_ns) / 1e9 if after else float("nan"),
                "tablet_resume_s": (tablet_after[0] - fault.end_ns) / 1e9 if tablet_after else float("nan"),
                # the gaps that began during the fault (the last chunk before them is at most a second older)
                "emg_samples_missing": sum(
                    n for t, n in recorded["emg_gaps"] if fault.begin_ns - 10**9 <= t <= fault.end_ns
                ),
                # the input outages the estimator's status reported that overlap the fault (start, end: s from the
                # fault's begin; the streams silent): the link's outage as the estimator counted it
                "estimator_outages": [
                    {"from_s": (a - fault.begin_ns) / 1e9, "to_s": (b - fault.begin_ns) / 1e9, "s": d, "keys": k}
                    for a, b, d, k in status_outages
                    if a <= fault.end_ns and b >= fault.begin_ns
                ],
            }
        )

    def outside(t: int) -> bool:
        return not any(f.begin_ns - 10**9 <= t <= f.end_ns + 3 * 10**9 for f in faults)

    steady = [(t, m) for t, m in tablet if outside(int(m["publish_ns"])) and (until_ns is None or t < until_ns)]
    estimator_ms = [(int(m["publish_ns"]) - int(m["input_arrival_ns"])) / 1e6 for _, m in steady]
    network_ms = [(t - int(m["publish_ns"])) / 1e6 for t, m in steady]
    return {
        "emg_published": _published(logs.get("drivers", ""), "trigno"),
        "emg_messages_published": _published(logs.get("drivers", ""), "trigno", "messages"),
        "recorder_summary": next(
            (line for line in logs.get("recorder", "").splitlines() if line.startswith("recorded ")), ""
        ),
        "recorder_lost": _recorder_lost(logs.get("recorder", "")),
        "imu_published": _published(logs.get("drivers", ""), "xsens"),
        **{k: v for k, v in recorded.items() if k != "emg_gaps"},
        "emg_gaps": len(recorded["emg_gaps"]),
        "emg_samples_missing": sum(n for _, n in recorded["emg_gaps"]),
        "frames_recorded": len(published_ns),
        "frames_at_tablet": len(tablet),
        "statuses_at_tablet": len(deployment.tablet.statuses()),
        "frames_estimated": int(next(iter(re.findall(r"estimated (\d+) frames", logs.get("estimator", ""))), -1)),
        **_summaries(logs),
        "faults": per_fault,
        # every outage the estimator's status reported: begin (s after the first fault began), length (s), streams
        "estimator_outage_list": [
            (round((a - faults[0].begin_ns) / 1e9, 2), round(d, 3), k) for a, _, d, k in status_outages
        ]
        if faults
        else [],
        "estimator_latency": latency_figures(np.asarray(estimator_ms)),
        "network_latency": latency_figures(np.asarray(network_ms)),
    }


# --- the rack PC's devices -----------------------------------------------------------------------------------------


def serve_simulators() -> int:
    """The rack PC's simulated devices as ``msk live --sim`` runs them (:func:`services.sessions.live.start_simulators`): the
    Trigno and one Xsens simulator per tracker playing the held-out trial of :data:`PACK` on one trial clock, which
    starts when the drivers start the first device; each tracker waits in Config for its driver. So every device
    samples the same instant of the trial and the trial's static start is what the kinematics node calibrates on.
    (Standalone ``msk sim`` processes each play the trial from their own start, streaming before their driver reads:
    the trackers then sample instants seconds apart, and the kinematics node calibrates on a moving pose: elbow angles
    off by up to 90 deg, most frames ``invalid_input``.) Prints one JSON line (ports, trackers, the trial's electrode
    map and load), then runs until SIGINT or SIGTERM."""
    from services.sessions.live import sim_sources, start_simulators
    from services.transport.stop_signals import stop_on_signals

    sources = sim_sources(DEMO, PACK)
    stop = stop_on_signals()
    simulators = start_simulators(sources)
    try:
        said = {
            "ports": {"command": simulators.trigno.ports["command"], "emg": simulators.trigno.ports["emg"]},
            "trackers": {t: (segment, simulators.xsens[t].path) for t, (segment, _) in sources.imu.items()},
            "trial": {"name": sources.trial, "electrodes": sources.electrodes, "load_kg": sources.load_kg},
        }
        print(json.dumps(said), flush=True)
        while not stop.wait(0.5):
            pass
    finally:
        simulators.close()
    return 0


if __name__ == "__main__":
    if sys.argv[1:] != ["simulators"]:
        sys.exit("usage: python -m services.bench.hosts simulators")
    sys.exit(serve_simulators())
