"""Live terminal view of a session (``msk view``), drawn with ``rich``.

Per muscle group: the estimated activation as a bar with its uncertainty (+- one Laplace std) and, where an electrode
is, the measured EMG envelope beside it; torque tracking per joint (inverse dynamics vs muscle model); repetition
counter and phase; the barbell load; device health (connected, samples received and lost, estimator latency).

It keeps up by showing the newest frame: Zenoh callbacks overwrite one slot per topic (no queue), and the screen is
redrawn at ``refresh_hz`` from whatever is newest. Run ``msk view --session NAME`` beside ``msk live`` or a replay.
"""

from __future__ import annotations

import argparse
import math
import signal
import threading
import time
from dataclasses import dataclass, field

from rich.console import Console, Group
from rich.live import Live
from rich.panel import Panel
from rich.table import Table
from rich.text import Text

from services import messages, topics
from services.zenoh_session import ZenohOptions, add_zenoh_arguments, open_session, options_from_args

BAR_WIDTH = 30


@dataclass
class RepCounter:
    """Counts repetitions from the phase stream: a rep starts when the phase enters [0, 0.5) from rest (-1) or from
    the end of the previous rep (>= 0.5)."""

    reps: int = 0
    _last: float | None = None

    def update(self, phase: float | None) -> None:
        if phase is None or not math.isfinite(phase):
            return
        if 0.0 <= phase < 0.5 and (self._last is None or self._last < 0.0 or self._last >= 0.5):
            self.reps += 1
        self._last = phase


@dataclass
class ViewState:
    """Newest message per topic (overwritten, never queued) and counters the view derives from them."""

    frames: dict[str, messages.ActivationFrame] = field(default_factory=dict)  # method -> newest frame
    status: dict[str, messages.DeviceStatus] = field(default_factory=dict)  # device -> newest status
    load: messages.LoadEvent | None = None
    envelope: messages.EmgEnvelope | None = None
    received: int = 0
    reps: RepCounter = field(default_factory=RepCounter)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_sample(self, key: str, payload: bytes) -> None:
        try:
            _, rest = topics.split_key(key)
        except Exception:
            return
        kind = rest.split("/", 1)[0]
        try:
            with self.lock:
                self.received += 1
                if kind == "activations":
                    frame = messages.decode("msk.ActivationFrame", payload)
                    if not self.frames or frame.method == next(iter(self.frames)):  # reps from the first method only
                        self.reps.update(frame.phase if frame.HasField("phase") else None)
                    self.frames[frame.method] = frame
                elif kind == "status":
                    status = messages.decode("msk.DeviceStatus", payload)
                    self.status[status.device_id or rest] = status
                elif kind == "load":
                    self.load = messages.decode("msk.LoadEvent", payload)
                elif kind == "envelopes":
                    self.envelope = messages.decode("msk.EmgEnvelope", payload)
        except messages.MessageDecodeError:
            pass  # a bad message must not stop the view; the next one replaces it


def bar(value: float, std: float | None, width: int = BAR_WIDTH, marker: float = math.nan) -> Text:
    """``value`` in [0, 1] as a filled bar, the +- std span shaded around its end, ``marker`` (the measured EMG
    envelope) as a magenta ``┃`` at its place."""
    text = Text()
    if not math.isfinite(value):
        return Text("-" * width, style="red")
    v = min(max(value, 0.0), 1.0)
    lo = min(max(v - (std or 0.0), 0.0), 1.0)
    hi = min(max(v + (std or 0.0), 0.0), 1.0)
    mark = int(min(max(marker, 0.0), 1.0) * (width - 1e-9)) if math.isfinite(marker) else -1
    for i in range(width):
        x = (i + 0.5) / width
        if i == mark:
            text.append("┃", style="bold magenta")
        elif x <= lo:
            text.append("█", style="green")
        elif x <= v:
            text.append("▓", style="green")
        elif x <= hi:
            text.append("░", style="yellow")
        else:
            text.append("·", style="grey50")
    return text


def render(state: ViewState, session: str, primary: str | None = None) -> Group:
    with state.lock:
        frames = dict(state.frames)
        status = dict(state.status)
        load, received, reps = state.load, state.received, state.reps.reps
    methods = list(frames)
    method = primary if primary in frames else (methods[0] if methods else None)
    header = Text(f"msk view · session {session} · {received} messages", style="bold")
    if method is None:
        return Group(header, Text("waiting for activations on " + f"msk/{session}/activations/* ..."))
    frame = frames[method]
    groups = list(frame.groups)
    std = list(frame.activation_std) if len(frame.activation_std) == len(groups) else [None] * len(groups)
    envelope = list(frame.measured_envelope) if len(frame.measured_envelope) == len(groups) else [math.nan] * len(groups)
    muscles = Table(title=f"activations · {method} (█ estimate, ░ ±1 sd, ┃ EMG envelope)", expand=False)
    muscles.add_column("group")
    muscles.add_column("estimate")
    muscles.add_column("a", justify="right")
    muscles.add_column("EMG", justify="right")
    for other in methods:
        if other != method:
            muscles.add_column(other, justify="right")
    for i, g in enumerate(groups):
        a = frame.activations[i] if i < len(frame.activations) else math.nan
        env = envelope[i]
        row = [g, bar(a, std[i], marker=env), f"{a:.2f}", "" if not math.isfinite(env) else f"{env:.2f}"]
        for other in methods:
            if other != method:
                of = frames[other]
                row.append(f"{of.activations[list(of.groups).index(g)]:.2f}" if g in of.groups else "")
        muscles.add_row(*row)
    torques = Table(title="torque tracking (N·m)")
    for column in ("joint", "inverse dynamics", "muscles", "residual"):
        torques.add_column(column, justify="right" if column != "joint" else "left")
    for c in frame.torques:
        torques.add_row(c.coordinate, f"{c.inverse_dynamics_nm:.1f}", f"{c.model_nm:.1f}", f"{c.residual_nm:.1f}")
    phase = frame.phase if frame.HasField("phase") else None
    phase_text = "unknown" if phase is None else ("rest" if phase < 0 else f"{phase:.2f}")
    latency_ms = (frame.publish_ns - frame.input_arrival_ns) / 1e6 if frame.publish_ns and frame.input_arrival_ns else math.nan
    session_line = Text(
        f"rep {reps} · phase {phase_text} · load "
        + (f"{load.barbell_mass_kg:g} kg {load.exercise}" if load is not None else "unknown")
        + f" · t {frame.time_s:.2f} s · latency {latency_ms:.2f} ms · solver {frame.solver_status}"
        + (f" · flags {', '.join(frame.flags)}" if frame.flags else "")
    )
    health = Table(title="devices")
    for column in ("device", "kind", "connected", "samples", "lost", "errors"):
        health.add_column(column)
    for name, s in status.items():
        health.add_row(name, s.kind, "yes" if s.connected else "NO", str(s.samples_received), str(s.samples_lost), str(s.errors))
    if not status:
        health.add_row("(no device status on this session)", "", "", "", "", "")
    return Group(header, session_line, muscles, torques, health)


def main(config: ZenohOptions, *, session: str, method: str | None = None, refresh_hz: float = 10.0,
         duration_s: float | None = None, stop_event: threading.Event | None = None,
         console: Console | None = None) -> ViewState:
    stop_event = stop_event or threading.Event()
    state = ViewState()
    deadline = None if duration_s is None else time.monotonic() + duration_s
    with open_session(config) as zsession:
        subscriber = zsession.declare_subscriber(
            f"{topics.session_prefix(session)}/**", lambda s: state.on_sample(str(s.key_expr), s.payload.to_bytes())
        )
        try:
            with Live(render(state, session, method), console=console, refresh_per_second=refresh_hz,
                      screen=False, transient=False) as live:
                while not stop_event.is_set() and (deadline is None or time.monotonic() < deadline):
                    live.update(Panel(render(state, session, method)))
                    stop_event.wait(1.0 / refresh_hz)
        finally:
            subscriber.undeclare()
    return state


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--session", default="live", help="session name (default: live)")
    parser.add_argument("--method", default=None, help="method drawn as bars (default: the first seen)")
    parser.add_argument("--refresh-hz", type=float, default=10.0, help="redraws per second (default 10)")
    parser.add_argument("--duration", type=float, default=None, metavar="SECONDS", help="stop after this long")
    add_zenoh_arguments(parser)


def run_from_args(args: argparse.Namespace) -> int:
    topics.check_chunk(args.session, "session")
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    main(options_from_args(args), session=args.session, method=args.method, refresh_hz=args.refresh_hz,
         duration_s=args.duration, stop_event=stop)
    return 0
