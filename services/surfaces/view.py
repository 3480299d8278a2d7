"""Live terminal view of a session (``msk view``), drawn with ``rich``.

Per muscle group, by its display name (the pack's, or the session file's ``[names]`` carried by ``LoadEvent.names``;
the model names with a legend when the terminal is too narrow): the estimated activation in % as a bar with its
uncertainty (+- one Laplace std) and, where an electrode is, the measured EMG envelope in % beside it and the
electrode's signal quality (good, check or bad with the reason, from the estimator's status); torque tracking
per joint (inverse dynamics vs muscle model, with the joint's unit); "set N · rep n" and the phase; the time in the
set; exercise and load (the operator's ``LoadEvent``; the exercise else from the frames); per set its reps, time
under tension and, in the muscle table, the peak and mean activation of the set under way (or the last); device
health (connected, samples received and lost, estimator latency); the inputs the view dropped as unusable. Sets come
from :class:`msk_core.signal.sets.SetTracker` (the operator's marks, rest detection), fed with the first method's
frames. In a terminal, the key ``s`` starts the next set and ``e`` ends the set under way (the session fact ``msk set
start|stop`` publishes).

Inputs come through :class:`services.nodes.node_runtime.NodeInputs` (a malformed message is dropped and counted, never shown
and never fatal); the view's thread takes them in order and overwrites one slot per topic, and the screen is redrawn
at ``refresh_hz`` from whatever is newest. Run ``msk view --session NAME`` beside ``msk live`` or a replay.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import zenoh
from google.protobuf.message import Message
from rich.console import Console, Group
from rich.live import Live
from rich.panel import Panel
from rich.table import Table
from rich.text import Text

from msk_core.errors import ConfigError
from msk_core.estimate.flags import flag_text
from msk_core.model.names import DisplayNames
from msk_core.model.pack import names_for
from msk_core.signal.reps import joint_movement
from msk_core.signal.sets import SetTracker
from services.nodes import node_runtime
from services.nodes.node_runtime import InputCounts, LoadEventGate, NodeInputs, apply_load_event, serve
from services.sessions.facts import join_late
from services.sessions.live_session import default_method
from services.transport import messages, topics
from services.transport.stop_signals import stop_on_signals
from services.transport.zenoh_session import (
    ZenohOptions,
    add_zenoh_arguments,
    open_session,
    options_from_args,
)

log = logging.getLogger(__name__)

BAR_WIDTH = 30
#: How long the view's input thread waits for a message before looking at its stop flag again.
POLL_S = 0.1
#: After this long without any message the view says the session has gone quiet (ended, or its graph stopped).
QUIET_S = 5.0
#: Sets shown in the view's table of sets (the newest).
SETS_SHOWN = 5
#: An electrode's state as the muscle table colours it (ElectrodeQuality.state).
ELECTRODE_STYLES = {"good": "green", "check": "bold yellow", "bad": "bold red", "unknown": "grey50"}


@dataclass
class ViewState:
    """Newest message per topic (overwritten, never queued) and counters the view derives from them."""

    frames: dict[str, messages.ActivationFrame] = field(default_factory=dict)  # method -> newest frame
    status: dict[str, messages.DeviceStatus] = field(default_factory=dict)  # device -> newest status
    load: messages.LoadEvent | None = None
    envelope: messages.EmgEnvelope | None = None
    received: int = 0
    sets: SetTracker = field(default_factory=SetTracker)  # sets and reps per set (msk_core.signal.sets)
    names: dict[str, str] = field(default_factory=dict)  # the session's display names (LoadEvent.names), kept
    first_frame_s: float | None = None  # the first frame's time (the time shown when no set has started)
    last_frame_s: float | None = None  # the newest frame's time: the frames' clock
    inputs: InputCounts = field(default_factory=InputCounts)  # what the view's NodeInputs took and dropped
    loads: LoadEventGate = field(default_factory=LoadEventGate)  # load events as the estimator takes them
    movement: str | None = None  # lifting / lowering / turning: the joint power's sign (msk_core.signal.reps.movement)
    last_message_at: float | None = None  # time.monotonic() of the newest message: a silent session shows
    torques: dict[str, float] = field(default_factory=dict)  # the first method's newest inverse-dynamics torques
    figures_method: str | None = None  # whose frames the sets' peak and mean are of (--method; else the default)
    keys: SetKeys = field(default_factory=lambda: SetKeys())  # the terminal's set-mark keys (defined below)
    access_note: str = ""  # what the view's role may not read or mark, so cannot show (:func:`access_note`)
    marks: bool = True  # its keys mark sets (:func:`marks_sets`)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_message(self, key: str, message: Message) -> None:
        """One checked message of ``key`` (its topic's type, :func:`services.nodes.node_runtime.check_payload`: so the type
        says the topic)."""
        with self.lock:
            self.received += 1
            self.last_message_at = time.monotonic()
            if isinstance(message, messages.ActivationFrame):
                self._apply_loads(key, self.loads.on_frame(message.exercise))
                phase = message.phase if message.HasField("phase") else None
                if not self.frames or message.method == next(iter(self.frames)):  # reps from the first method
                    self.sets.update(message.time_s, phase)
                    if self.first_frame_s is None:
                        self.first_frame_s = message.time_s
                    self.last_frame_s = message.time_s
                    self.torques = {t.coordinate: t.inverse_dynamics_nm for t in message.torques}
                self.frames[message.method] = message
                # the sets' activation figures: of the method shown, as the report's (not of whichever came first)
                if message.method == (self.figures_method or default_method(list(self.frames))):
                    self.sets.add_activations(message.time_s, phase, message.groups, message.activations)
            elif isinstance(message, messages.JointAngles):
                self.movement = joint_movement(self.torques, message.coordinates, message.qd)
            elif isinstance(message, messages.DeviceStatus):
                self.status[message.device_id] = message
                if node_runtime.estimates_ended(message):  # no frame follows: as the report's end of data
                    self.sets.finish()
            elif isinstance(message, messages.LoadEvent):
                self._apply_loads(key, self.loads.offer(message))
            elif isinstance(message, messages.EmgEnvelope):
                self.envelope = message

    def _apply_loads(self, key: str, loads: list[messages.LoadEvent]) -> None:
        """The load events the gate lets through; those it refused count as the view's invalid inputs of the load
        topic of ``key``'s session (``key``: the frame's or the event's)."""
        for load in loads:
            self._on_load(load)
        self.loads.count_refused(self.inputs, topics.load_key(topics.split_key(key)[0]))

    def _on_load(self, load: messages.LoadEvent) -> None:
        """The operator's marks and set numbers, as :meth:`SetTracker.on_facts` reads them, at the event's time on the
        frames' clock (the newest frame's when the event carries none or one of another clock)."""
        apply_load_event(self.sets, load)
        if load.names:  # a load event without names (msk load) leaves the session's names in effect
            self.names = dict(load.names)
        self.load = load


def set_text(number: int, rep: int, resting: bool) -> str:
    """``set 2 · rep 3`` (the rep under way, else the last done), ``set 2 done · resting``, or ``set –``."""
    if not number:
        return "set –"
    return f"set {number} done · resting" if resting else f"set {number} · rep {rep}"


def session_facts(load: messages.LoadEvent | None, frame: messages.ActivationFrame | None, sets: str) -> str:
    """``exercise bench press · load 60 kg · set 2 · rep 3``: the load event's, the exercise else the frame's;
    ``sets``: :func:`set_text`."""
    exercise = (load.exercise if load is not None else "") or (frame.exercise if frame is not None else "")
    return (
        f"exercise {exercise.replace('_', ' ') if exercise else 'unknown'}"
        + f" · load {f'{load.barbell_mass_kg:g} kg' if load is not None else 'unknown'}"
        + f" · {sets}"
        + (f" · {load.athlete}" if load is not None and load.athlete else "")
    )


def sets_table(sets: list[dict]) -> Table:
    """The newest :data:`SETS_SHOWN` sets (:meth:`SetRecord.as_dict`): reps, time under tension, duration, how the
    set ended."""
    table = Table(title="sets")
    for column in ("set", "reps", "under tension (s)", "duration (s)", "ended"):
        table.add_column(column, justify="left" if column == "ended" else "right")
    for record in sets[-SETS_SHOWN:]:
        end = record["end_s"]
        table.add_row(
            str(record["number"]),
            str(record["reps"]),
            f"{record['time_under_tension_s']:.1f}",
            f"{end - record['start_s']:.1f}" if end is not None else "under way",
            record["ended_by"] or "–",
        )
    return table


def dropped_text(inputs: InputCounts) -> str:
    """``2 dropped (msk/s/joints: oversized 1, ...)``, or "" when nothing was dropped."""
    drops = inputs.drops()
    if not drops:
        return ""
    return f"{sum(d.count for d in drops)} dropped (" + ", ".join(f"{d.key}: {d.reason} {d.count}" for d in drops) + ")"


def percent(value: float) -> str:
    """An activation or normalised envelope in [0, 1] as a whole percentage ("" when not known)."""
    return f"{100 * value:.0f}" if math.isfinite(value) else ""


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


def set_line(tracker: SetTracker, first_frame_s: float | None) -> tuple[str, int, float | None, tuple | None]:
    """What the session line says of the sets: :func:`set_text`, the set under way (0: none), its start (the first
    frame's time when none) and, at rest after a set, (its number, its end)."""
    current = tracker.current
    done = tracker.sets[-1] if tracker.sets and current is None else None
    return (
        set_text(tracker.number, tracker.rep, current is None),
        current.number if current is not None else 0,
        current.start_s if current is not None else first_frame_s,
        (done.number, done.end_s) if done is not None and done.end_s is not None else None,
    )


def set_time_text(set_number: int, start_s: float | None, time_s: float, rest: tuple[int, float] | None = None) -> str:
    """``12.3 s in set 2``: the frame's time from its set's start; at rest after a set (``rest``: its number and end)
    ``for 40.2 s``, which follows "set N done · resting"; before any set, from the first frame."""
    if rest is not None:  # a frame from before the set's end (the estimates paused) cannot say how long
        return f"for {time_s - rest[1]:.1f} s" if time_s >= rest[1] else ""
    if start_s is None:
        return "time in set unknown"
    return f"{time_s - start_s:.1f} s " + (f"in set {set_number}" if set_number else "since the first frame")


def set_columns(record: dict | None, groups: list[str]) -> list[str]:
    """Per group, ``peak / mean`` % of the set (:meth:`SetRecord.as_dict`), "" where unknown."""
    if record is None:
        return [""] * len(groups)
    by_group = dict(zip(record["groups"], zip(record["peak"], record["mean"])))
    out = []
    for g in groups:
        peak, mean = by_group.get(g, (None, None))
        out.append("" if peak is None else f"{percent(peak)} / {percent(mean if mean is not None else math.nan)}")
    return out


def muscle_labels(
    names: DisplayNames, groups: list[str], methods: int, width: int | None, extra: int = 0
) -> tuple[list[str], str]:
    """The group labels of the muscle table: display names, or the model names (abbreviations) when the table would
    not fit ``width`` columns with them (and ``extra`` more, e.g. the electrode column), and then the legend that
    explains them."""
    full = [names.group(g) for g in groups]
    # label, bar, activation % and EMG envelope % columns, one per other method; rich draws 3 characters per column
    needed = (
        max(map(len, full), default=0)
        + BAR_WIDTH
        + len("activation %")
        + len("EMG envelope %")
        + 10 * max(methods - 1, 0)
        + 3 * (3 + methods)
        + 1
        + extra
    )
    if width is None or needed <= width or full == groups:
        return full, ""
    return list(groups), names.legend(groups)


def electrodes_by_group(status: dict[str, messages.DeviceStatus]) -> dict[str, list[messages.ElectrodeQuality]]:
    """Per muscle group, the quality of its electrodes (``DeviceStatus.electrodes`` of the estimator's status)."""
    out: dict[str, list[messages.ElectrodeQuality]] = {}
    for s in status.values():
        for electrode in s.electrodes:
            if electrode.group:
                out.setdefault(electrode.group, []).append(electrode)
    return out


def electrode_text(electrodes: list[messages.ElectrodeQuality]) -> Text:
    """``bad: flat line``: each electrode's state, coloured, with its reasons (its sensor first when a muscle has
    several electrodes); "" for a muscle without one."""
    text = Text()
    for k, electrode in enumerate(electrodes):
        if k:
            text.append("; ")
        if len(electrodes) > 1:
            text.append(electrode.channel.split(".", 1)[0] + " ")
        text.append(electrode.state, style=ELECTRODE_STYLES.get(electrode.state, ""))
        if electrode.reasons:
            text.append(": " + ", ".join(electrode.reasons), style=ELECTRODE_STYLES.get(electrode.state, ""))
    return text


def view_header(session: str, received: int, inputs: InputCounts, keys: bool = True) -> Text:
    """The view's first line: the session, the messages taken and dropped, the keys (when they mark sets)."""
    dropped = dropped_text(inputs)
    return Text(
        f"msk view · session {session} · {received} messages"
        + (f" · {dropped}" if dropped else "")
        + (" · keys: s start set, e end set" if keys else ""),
        style="bold",
    )


#: What the view shows of each topic of the session (docs/topics.md), for :func:`access_note`.
VIEW_TOPICS = (
    ("activations/*", "activations"),
    ("status/*", "device and node health"),
    ("load", "exercise, load and sets marked"),
    ("joints", "movement"),
)


def access_note(role: str | None, session: str) -> str:
    """What the view cannot show as ``role`` of the secured network (the router's access control,
    :func:`services.transport.security.refused`), and whether its keys can mark sets; "" when it may read all it
    shows. A :class:`ConfigError` when it may read nothing of the session: a view that waits for nothing."""
    if role is None:
        return ""
    from services.transport.roles import parts_text, permitted_parts
    from services.transport.security import refused

    everything = f"{topics.session_prefix(session)}/**"
    if not permitted_parts(role, "subscribe", everything):
        raise ConfigError(f"{parts_text(role, 'subscribe', everything, ())}: the view would show nothing")
    prefix = topics.session_prefix(session)
    hidden = [
        f"{what} ({prefix}/{topic})" for topic, what in VIEW_TOPICS if refused(role, "subscribe", f"{prefix}/{topic}")
    ]
    unmarked = not marks_sets(role, session)
    if not hidden and not unmarked:
        return ""
    return (
        f"role {role!r}"
        + (f" may not read, so the view does not show: {'; '.join(hidden)}" if hidden else "")
        + (" ·" if hidden and unmarked else "")
        + (" keys s and e mark no set (it may not publish the load key)" if unmarked else "")
    )


def marks_sets(role: str | None, session: str) -> bool:
    """Whether the view's keys can mark sets as ``role`` (:func:`services.transport.roles.facts_refusal`)."""
    from services.transport.roles import facts_refusal

    return facts_refusal(role, session) is None


#: How long the registry scan of a waiting view is reused (a render runs several times a second).
RUNNING_SCAN_S = 2.0
_running_scan: tuple[float, list[str]] = (-RUNNING_SCAN_S, [])


def _running_names() -> list[str]:
    """The sessions msk live announces here, scanned at most every :data:`RUNNING_SCAN_S`."""
    global _running_scan
    from services.sessions import discovery

    scanned_at, names = _running_scan
    if time.monotonic() - scanned_at >= RUNNING_SCAN_S:
        names = [s.session for s in discovery.running_sessions()]
        _running_scan = (time.monotonic(), names)
    return names


def waiting_text(session: str, paused: str) -> Text:
    """What the view says before its first activation frame: why the estimator is paused, or what it waits for."""
    if paused:
        return Text(f"Estimates paused. {paused}", style="bold yellow")
    # a typo waited in silence (the line on stderr that says so is under the full screen): the sessions that do run
    running = _running_names()
    text = f"waiting for activations on msk/{session}/activations/* ..."
    if running and session not in running:
        text += f" No msk live here is named {session!r} (running: {', '.join(running)}): msk view --session NAME"
    return Text(text)


def render(state: ViewState, session: str, primary: str | None = None, width: int | None = None) -> Group:
    """The screen; ``width`` (the terminal's columns) decides whether muscles show by display name or abbreviation."""
    with state.lock:
        frames = dict(state.frames)
        status = dict(state.status)
        overrides, load, received = dict(state.names), state.load, state.received
        paused = state.loads.paused_notice(load.exercise if load is not None else "")
        sets, set_number, set_start_s, rest = set_line(state.sets, state.first_frame_s)
        records = [r.as_dict() for r in state.sets.sets]  # the set under way (or the last) in the muscle table
        quiet_s = None if state.last_message_at is None else time.monotonic() - state.last_message_at
    methods = list(frames)
    method = primary if primary in frames else default_method(methods)  # named in the muscle table's title
    header: Text | Group = view_header(session, received, state.inputs, keys=state.marks)
    if state.access_note:  # said once, under the header: what this role's view cannot show
        header = Group(header, Text(state.access_note, style="yellow"))
    if method is None:
        return Group(header, Text(session_facts(load, None, sets)), waiting_text(session, paused))
    frame = frames[method]
    groups = list(frame.groups)
    exercise = frame.exercise or (load.exercise if load is not None else "")  # the names of the frame's pack
    names = names_for(exercise, groups, overrides)
    quality = electrodes_by_group(status)  # the electrodes' signal quality, once the estimator has said it
    extra_width = (len("electrode") + 3 if quality else 0) + (len("set 1 peak / mean %") + 3 if state.sets.sets else 0)
    labels, legend = muscle_labels(names, groups, len(methods), width, extra=extra_width)
    std = list(frame.activation_std) if len(frame.activation_std) == len(groups) else [None] * len(groups)
    envelope = (
        list(frame.measured_envelope) if len(frame.measured_envelope) == len(groups) else [math.nan] * len(groups)
    )
    muscles = Table(title=f"activations · {method} (█ estimate, ░ ±1 sd, ┃ EMG envelope)", expand=False)
    muscles.add_column("muscle")
    muscles.add_column("estimate")
    muscles.add_column("activation %", justify="right")
    muscles.add_column("EMG envelope %", justify="right")
    for other in methods:
        if other != method:
            muscles.add_column(f"{other} %", justify="right")
    if records:
        muscles.add_column(f"set {records[-1]['number']} peak / mean %", justify="right")
    if quality:
        muscles.add_column("electrode")
    set_figures = set_columns(records[-1] if records else None, groups)
    for i, g in enumerate(groups):
        a = frame.activations[i] if i < len(frame.activations) else math.nan
        env = envelope[i]
        row: list[Text | str] = [Text(labels[i]), bar(a, std[i], marker=env), percent(a), percent(env)]
        for other in methods:
            if other != method:
                of = frames[other]
                row.append(percent(of.activations[list(of.groups).index(g)]) if g in of.groups else "")
        if records:
            row.append(set_figures[i])
        if quality:
            row.append(electrode_text(quality.get(g, [])))
        muscles.add_row(*row)
    if legend:
        muscles.caption, muscles.caption_justify = legend, "left"
    set_time = set_time_text(set_number, set_start_s, frame.time_s, rest)
    session_line = Text(session_line_text(session_facts(load, frame, sets), frame, state.movement, set_time, rest))
    extra = [sets_table(records)] if records else []
    return Group(
        header,
        session_line,
        *notices(paused, quiet_s, state.keys.notice(time.monotonic())),
        muscles,
        *extra,
        torque_table(frame, names),
        *health_tables(status),
    )


def session_line_text(
    facts: str, frame: messages.ActivationFrame, movement: str | None, set_time: str, rest: tuple[int, float] | None
) -> str:
    """The line under the header: the session's facts, the movement, the time in the set or the rest, latency,
    solver and flags; resting after a set it reads "set 2 done · resting for 40.2 s" (the movement is rest)."""
    latency_ms = (
        (frame.publish_ns - frame.input_arrival_ns) / 1e6 if frame.publish_ns and frame.input_arrival_ns else math.nan
    )
    if rest is not None:
        moving = f" {set_time}".rstrip()
    else:
        moving = f" · {movement_text(frame.phase if frame.HasField('phase') else None, movement)} · {set_time}"
    return (
        facts
        + moving
        + f" · latency {latency_ms:.2f} ms"
        + f" · solver {frame.solver_status}"
        + (f" · {', '.join(flag_text(flag) for flag in frame.flags)}" if frame.flags else "")
    )


def movement_text(phase: float | None, movement: str | None) -> str:
    """Inside a rep: lifting / lowering / turning (the joint power), else how far through it; rest; unknown."""
    if phase is None:
        return "unknown"
    if phase < 0:
        return "rest"
    return movement or f"{100 * phase:.0f} % through the rep"


def notices(paused: str, quiet_s: float | None, keys_notice: str = "") -> list[Text]:
    """Over the last values: the session gone quiet (ended, or its graph stopped), else the estimates paused; and
    typed keys not taken for set marks."""
    typed = [Text(keys_notice, style="bold yellow")] if keys_notice else []
    if quiet_s is not None and quiet_s > QUIET_S:
        text = f"Nothing received for {quiet_s:.0f} s: the session has ended or stopped sending."
        return [Text(f"{text} The values below are the last.", style="bold red"), *typed]
    if paused:
        text = f"Estimates paused. {paused} The values below are the last before it."
        return [Text(text, style="bold yellow"), *typed]
    return typed


def torque_table(frame: messages.ActivationFrame, names: DisplayNames) -> Table:
    """Torque tracking per joint: inverse dynamics, the muscles' model torque and their difference, with the unit."""
    torques = Table(title="torque tracking")
    for column in ("joint", "inverse dynamics", "muscles", "residual", "unit"):
        torques.add_column(column, justify="right" if column not in ("joint", "unit") else "left")
    for c in frame.torques:
        torques.add_row(
            Text(names.coordinate(c.coordinate)),
            f"{c.inverse_dynamics_nm:.1f}",
            f"{c.model_nm:.1f}",
            f"{c.residual_nm:.1f}",
            names.torque_unit(c.coordinate) or "N·m",
        )  # *_nm fields: N·m
    return torques


def health_tables(status: dict[str, messages.DeviceStatus]) -> list[Table]:
    """The devices (connected, samples, lost, errors) and, when any node reported, the nodes' dropped inputs."""
    devices = {name: s for name, s in status.items() if s.kind != "node"}
    health = Table(title="devices")
    for column in ("device", "kind", "connected", "samples", "lost", "errors"):
        health.add_column(column)
    for name, s in devices.items():
        health.add_row(
            f"{name} ({s.segment})" if s.segment else name,
            s.kind,
            "yes" if s.connected else "NO",
            str(s.samples_received),
            str(s.samples_lost),
            str(s.errors),
        )
    if not devices:
        health.add_row("(no device status on this session)", "", "", "", "", "")
    nodes = {name: s for name, s in status.items() if s.kind == "node"}
    if not nodes:
        return [health]
    node_table = Table(title="nodes (inputs dropped as unusable; input outages)")
    for column in ("node", "running", "received", "dropped", "outages"):
        node_table.add_column(column)
    for name, s in nodes.items():
        o = s.outages
        node_table.add_row(
            name,
            "yes" if s.connected else "stopped",
            str(s.samples_received),
            str(sum(d.count for d in s.dropped)),
            (f"{o.count} ({o.total_s:.1f} s)" if o.count else "0")
            + (f", silent {o.silent_s:.1f} s" if o.silent_s and s.connected else ""),
        )
    return [health, node_table]


#: The view's keys: the session fact each publishes (``msk set start|stop``).
KEYS = {"s": "start", "e": "stop"}
#: A key this close to another one is typing (a command line typed into the view's terminal by mistake), not a mark:
#: a mark key counts only when it stands alone, and is published once this long has passed without another key.
TYPING_GAP_S = 0.5
#: How long the view says that typed keys were not taken for marks.
TYPING_NOTICE_S = 5.0


class SetKeys:
    """The view's keys (:data:`KEYS`) as set marks, one key at a time: a key within :data:`TYPING_GAP_S` of another
    is typing, and no key of that burst marks a set (typed into the view, ``clear; msk view --session B`` published
    its 8 letters s and e as 8 marks: 4 empty sets, and the athlete's first set called set 5). A mark is made when
    its key is pressed (the facts in effect then, the time then) and handed out by :meth:`due` once the gap has
    passed without another key. Explicit state; every time is the caller's (s)."""

    def __init__(self, gap_s: float = TYPING_GAP_S) -> None:
        self.gap_s = gap_s
        self.ignored = 0  # mark keys not taken: typed among other keys
        self.ignored_at: float | None = None  # when the last of them came
        self._last_key = -math.inf
        self._pending: tuple[messages.LoadEvent, float] | None = None

    def key(self, key: str, t: float, make_event: Callable[[str], messages.LoadEvent]) -> None:
        """Key ``key`` at ``t``; ``make_event(mark)`` makes the mark's session fact."""
        typing = t - self._last_key < self.gap_s
        self._last_key = t
        if typing:
            if self._pending is not None or key in KEYS:
                self.ignored += (self._pending is not None) + (key in KEYS)
                self.ignored_at = t
            self._pending = None
            return
        self._pending = (make_event(KEYS[key]), t) if key in KEYS else None

    def due(self, t: float) -> messages.LoadEvent | None:
        """The mark to publish at ``t``: a key that stayed alone for the gap (else None)."""
        if self._pending is None or t - self._last_key < self.gap_s:
            return None
        event, self._pending = self._pending[0], None
        return event

    def notice(self, t: float) -> str:
        """What the view says for a while after typed keys were not taken for marks ("" otherwise)."""
        if self.ignored_at is None or t - self.ignored_at > TYPING_NOTICE_S:
            return ""
        return "Typed keys were not taken for set marks: press s (start a set) or e (end it) on its own."


def set_mark_event(state: ViewState, mark: str) -> messages.LoadEvent:
    """The session fact of the operator's ``mark`` ("start": the next set, "stop"), with the facts in effect."""
    from services.sessions.facts import set_mark_event as event

    with state.lock:
        return event(state.load if state.load is not None else state.loads.pending, state.sets.settled[0], mark)


def read_keys(
    keys: SetKeys,
    make_event: Callable[[str], messages.LoadEvent],
    publish_mark: Callable[[messages.LoadEvent], None],
    stop: threading.Event,
    fd: int | None = None,
) -> None:
    """Keys typed in the terminal ``fd`` (default stdin; no Enter needed) through ``keys`` until ``stop``, each mark
    it hands out to ``publish_mark``; the terminal's mode is restored."""
    import select
    import sys
    import termios
    import tty

    fd = sys.stdin.fileno() if fd is None else fd
    saved = termios.tcgetattr(fd)
    try:
        tty.setcbreak(fd)
        while not stop.is_set():
            if select.select([fd], [], [], POLL_S)[0]:
                for key in os.read(fd, 64).decode(errors="ignore").lower():  # a paste comes as one read
                    keys.key(key, time.monotonic(), make_event)
            if (event := keys.due(time.monotonic())) is not None:
                publish_mark(event)
    finally:
        termios.tcsetattr(fd, termios.TCSADRAIN, saved)


def start_keys(
    zsession: zenoh.Session, session: str, state: ViewState, stop: threading.Event
) -> threading.Thread | None:
    """In a terminal: a thread publishing the set mark of each key of :data:`KEYS` (pressed on its own,
    :class:`SetKeys`) on ``msk/<session>/load``."""
    import sys

    if not sys.stdin.isatty():
        return None
    from services.transport.zenoh_session import declare_data_publisher, publish

    publisher = declare_data_publisher(zsession, topics.load_key(session), "msk.LoadEvent")
    thread = threading.Thread(
        target=read_keys,
        args=(state.keys, lambda mark: set_mark_event(state, mark), lambda event: publish(publisher, event), stop),
        name="view-keys",
        daemon=True,
    )
    thread.start()
    return thread


def main(
    config: ZenohOptions,
    *,
    session: str,
    method: str | None = None,
    refresh_hz: float = 10.0,
    duration_s: float | None = None,
    stop_event: threading.Event | None = None,
    console: Console | None = None,
    leave_for: Callable[[ViewState], bool] | None = None,
) -> ViewState:
    """Show ``session`` until ``stop_event``, ``duration_s`` or, checked at every redraw, ``leave_for(state)`` (a
    session to attach to instead: :func:`session_followed`)."""
    stop_event = stop_event or threading.Event()
    state = ViewState(figures_method=method)
    deadline = None if duration_s is None else time.monotonic() + duration_s
    role = config.role
    state.access_note = access_note(role, session)
    with open_session(config) as zsession:
        inputs = NodeInputs(zsession, "view", role=role)
        state.inputs = inputs.counts
        inputs.subscribe_readable(f"{topics.session_prefix(session)}/**")  # a tablet: activations and statuses
        state.loads.session_exercise = join_late(inputs, session)  # the facts msk live had before this view
        taking = threading.Event()
        taker = threading.Thread(target=take_inputs, args=(inputs, state, taking), name="view-inputs", daemon=True)
        taker.start()
        state.marks = marks_sets(role, session)
        keys = start_keys(zsession, session, state, taking) if state.marks else None  # s: start a set, e: end it
        try:
            with Live(
                render(state, session, method),
                console=console,
                refresh_per_second=refresh_hz,
                screen=False,
                transient=False,
            ) as live:
                while not stop_event.is_set() and (deadline is None or time.monotonic() < deadline):
                    live.update(Panel(render(state, session, method, width=live.console.width - 4)))  # the panel
                    stop_event.wait(1.0 / refresh_hz)
                    if leave_for is not None and leave_for(state):
                        break
        finally:
            taking.set()
            inputs.close()
            taker.join(5.0)
            if keys is not None:
                keys.join(1.0)
    return state


def take_inputs(inputs: NodeInputs, state: ViewState, stop: threading.Event) -> None:
    """The view's input thread: every checked message, in arrival order, into ``state`` until ``stop``."""

    def take(inbound) -> None:
        try:
            state.on_message(inbound.key, inbound.message)
        except Exception:  # a message the checks let through must not freeze the screen
            log.exception("msk view: message on %s", inbound.key)

    serve(inputs, take, stop, poll_s=POLL_S)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--session", default=None, help="session name (default: the running msk live's, else live)")
    parser.add_argument("--method", default=None, help="method drawn as bars (default: the first seen)")
    parser.add_argument("--refresh-hz", type=float, default=10.0, help="redraws per second (default 10)")
    parser.add_argument("--duration", type=float, default=None, metavar="SECONDS", help="stop after this long")
    add_zenoh_arguments(parser)


def run_from_args(args: argparse.Namespace) -> int:
    if not (math.isfinite(args.refresh_hz) and 0 < args.refresh_hz <= 100):
        raise ConfigError("redraws per second must be in (0, 100]", field="--refresh-hz", value=args.refresh_hz)
    stop = stop_on_signals()
    from services.sessions import discovery

    explicit = options_from_args(args)
    deadline = None if args.duration is None else time.monotonic() + args.duration
    # no endpoint given: an msk live that starts before this view received anything, or after its session ended,
    # is followed
    follows = not discovery.gives_endpoint(explicit)
    options, session = discovery.client_options(explicit, args.session, "live", "msk view")
    while True:
        topics.check_chunk(session, "session")
        main(
            options,
            session=session,
            method=args.method,
            refresh_hz=args.refresh_hz,
            duration_s=None if deadline is None else max(0.0, deadline - time.monotonic()),
            stop_event=stop,
            leave_for=session_followed(discovery.SessionFollower(args.session, options)) if follows else None,
        )
        if not follows or stop.is_set() or (deadline is not None and time.monotonic() >= deadline):
            return 0
        try:
            options, session = discovery.client_options(explicit, args.session, "live", "msk view")
        except ConfigError as error:  # several sessions announced meanwhile, none named: stay, as at the start
            log.warning("msk view: %s; still on session %r", error, session)


def session_followed(follower) -> Callable[[ViewState], bool]:
    """The view leaves its session for the one ``follower`` (:class:`services.sessions.discovery.SessionFollower`)
    says."""
    return lambda state: follower.next_session(state.received) is not None
