"""``msk report REC.mcap --out DIR``: an HTML session report (``DIR/report.html`` with PNG plots and inline SVG body
maps beside it, ``DIR/report.json`` with the numbers).

The header names the athlete (``LoadEvent.athlete``), the date of the recording's first message, the exercises
(the load events', else the activation frames' ``exercise``) and the loads. Sets and their reps come from
:class:`msk_core.signal.sets.SetTracker`, the one set logic the view and the dashboard run live, fed in time order
with the load events (the operator's marks: ``set_mark`` start/stop, a new ``set_number``, a mass without a number,
no mass: the bar is off) and the phase the frames carry (``JointAngles.phase``, else ``ActivationFrame.phase``):
without marks, rest detection (no rep for the session's ``set_rest_s``, default 20 s) ends a set and the next rep
opens one. Without any phase, sets come from the load events alone and reps from msk_core's kinematic rep detection
on the pack's phase coordinate. A table of sets, one row per set: reps, time under tension, duration, and peak and
mean activation per muscle group over the set's reps (the SetTracker's figures). Per set and method: peak and mean activation of every muscle group in every rep, time under tension,
the balance of the pairs the pack declares (its spec's ``[balance]``: left and right groups, the agonists and
antagonists of a joint; none declared, none shown), the comparison of the methods
when several ran, and the health of every device over the session. Muscles and joints are named by their display
names (the pack's, with the session file's ``[names]`` from ``LoadEvent.names``; msk_core.model.names); the model
names (abbreviations) only on the method comparison's axis, explained beside it.
"""

from __future__ import annotations

import argparse
import datetime
import functools
import html
import math
import sys
from array import array
from collections.abc import MutableSequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from msk_core.errors import EstimationError, InputError
from msk_core.io.files import json_text
from msk_core.model import load_pack
from msk_core.model.names import DisplayNames
from msk_core.model.pack import names_for
from msk_core.signal.reps import phase_rep_spans
from msk_core.signal.sets import SetRecord, SetTracker
from services.nodes.node_runtime import LoadEventGate
from services.sessions.live import electrode_summary, fatigue_summary, keep_fatigue
from services.sessions.live_session import PREFERRED_METHODS, default_method
from services.surfaces.dashboard import bodymap
from services.transport import messages, topics
from services.transport.mcap_io import ReadReport, chosen_session, read_messages

PRIMARY_METHODS = PREFERRED_METHODS  # the first present is the one the report details (as every surface)
ACTIVE_THRESHOLD = 0.2  # "time active" of a muscle: activation above this


@dataclass
class MethodSeries:
    """One method's frames of one pack, as read, in typed arrays: ``activations`` flat, frame after frame,
    ``len(groups)`` values each; ``residual`` likewise, ``residual_width`` each (the first frame's torque count; a frame
    with another count has NaN there). Python lists of float objects made a long session's report take ~0.27 MB per
    recorded second, 2 GB for two hours."""

    groups: tuple[str, ...]
    time: MutableSequence[float] = field(default_factory=lambda: array("d"))
    activations: MutableSequence[float] = field(default_factory=lambda: array("d"))
    phase: MutableSequence[float] = field(default_factory=lambda: array("d"))  # NaN when unset
    residual: MutableSequence[float] = field(default_factory=lambda: array("d"))
    residual_width: int = -1  # -1 until a frame is added
    solve_s: MutableSequence[float] = field(default_factory=lambda: array("d"))
    flagged: MutableSequence[int] = field(default_factory=lambda: array("b"))  # per frame: 1 when it carried a flag
    _arrays: dict[str, np.ndarray] = field(default_factory=dict, repr=False, compare=False)

    def add(self, frame: messages.ActivationFrame) -> None:
        """One recorded frame of this series."""
        self.time.append(frame.time_s)
        self.activations.extend(frame.activations)
        self.phase.append(frame.phase if frame.HasField("phase") else math.nan)
        if self.residual_width < 0:
            self.residual_width = len(frame.torques)
        if len(frame.torques) == self.residual_width:
            self.residual.extend(t.residual_nm for t in frame.torques)
        else:
            self.residual.extend([math.nan] * self.residual_width)
        self.solve_s.append(frame.solve_time_s)
        self.flagged.append(bool(frame.flags))

    def array(self, name: str) -> np.ndarray:
        """Field ``name`` as an array, one row per frame, made once for the series as read (each set's figures mask
        it: converting the whole session's lists for every set made a long session's report quadratic in its
        length)."""
        cached = self._arrays.get(name)
        if cached is None or len(cached) != len(self.time):
            values = np.array(getattr(self, name), dtype=bool if name == "flagged" else float)
            if name in ("activations", "residual"):
                values = values.reshape(len(self.time), -1 if name == "residual" else len(self.groups))
            cached = self._arrays[name] = values
        return cached


@dataclass(frozen=True, order=True)
class Load:
    """One operator load event, on the devices' clock."""

    time_s: float
    mass_kg: float
    exercise: str
    set_number: int = 0  # 0: not counted
    athlete: str = ""
    set_mark: str = ""  # "start", "stop" or "" (LoadEvent.set_mark)
    rest_s: float = 0.0  # LoadEvent.set_rest_s; 0: the one in effect


@dataclass
class SessionData:
    frames: dict[tuple[str, tuple[str, ...]], MethodSeries] = field(default_factory=dict)
    joint_time: list[float] = field(default_factory=list)
    joint_phase: list[float] = field(default_factory=list)
    joint_q: dict[tuple[str, ...], list[tuple[float, list[float]]]] = field(default_factory=dict)
    loads: list[Load] = field(default_factory=list)
    frame_exercises: list[str] = field(default_factory=list)  # ActivationFrame.exercise values, in order of appearance
    names: dict[str, str] = field(default_factory=dict)  # the session file's display names (the last LoadEvent.names)
    emg: dict[str, list[tuple[float, int, int]]] = field(default_factory=dict)  # source -> (log s, first index, n)
    imu: dict[str, list[tuple[float, int]]] = field(default_factory=dict)  # tracker -> (log s, packet counter)
    status: dict[str, list[tuple[float, bool, int, int]]] = field(default_factory=dict)
    node_drops: dict[str, int] = field(
        default_factory=dict
    )  # node -> inputs dropped (its last DeviceStatus of kind "node")
    # the estimator's EMG electrodes (DeviceStatus of kind "node"): per "source/channel" its newest quality, and its
    # fatigue index per set (services.sessions.live.keep_fatigue: the newest values of each set)
    electrodes: dict[str, messages.ElectrodeQuality] = field(default_factory=dict)
    fatigue: dict[str, list[messages.ElectrodeFatigue]] = field(default_factory=dict)
    start_log_ns: int = 0
    end_log_ns: int = 0
    truncated: bool = False
    damage: str = ""  # what of the file could not be read (ReadReport.damage_text), "" when all of it was
    undecodable: dict[str, int] = field(default_factory=dict)  # topic -> payloads that were not their message
    refused_loads: int = 0  # load events naming an exercise that no pack has and no frame named (not applied)


def read_session(path: Path, *, session: str | None = None, progress: bool = False) -> SessionData:
    """The recorded session ``session`` (default: the only one; :func:`chosen_session`)."""
    if not Path(path).is_file():
        raise InputError("recording not found", path=path)
    prefix = None if (name := chosen_session(path, session)) is None else f"{topics.session_prefix(name)}/"
    data, report = SessionData(), ReadReport()
    gate = LoadEventGate()  # the load events the estimator took: one naming no pack and no frame's is not a fact
    for recorded in tqdm(
        read_messages(path, report=report), desc=f"read {Path(path).name}", unit="msg", disable=not progress
    ):
        if prefix is not None and not recorded.topic.startswith(prefix):
            continue
        data.start_log_ns = data.start_log_ns or recorded.log_time_ns
        data.end_log_ns = recorded.log_time_ns
        try:
            _take(data, gate, recorded, (recorded.log_time_ns - data.start_log_ns) / 1e9)
        except messages.MessageDecodeError:  # bytes that are not the message their channel says: counted, left out
            data.undecodable[recorded.topic] = data.undecodable.get(recorded.topic, 0) + 1
    data.truncated = report.truncated
    data.damage = report.damage_text()
    data.refused_loads = gate.refused + len(gate.held)
    if data.start_log_ns == 0:
        left_out = sum(report.left_out.values())
        raise InputError(
            "the recording holds no messages"
            + (f" of this project's ({left_out} others left out: another tool's channels)" if left_out else ""),
            path=path,
        )
    return data


def _take(data: SessionData, gate: LoadEventGate, recorded, log_s: float) -> None:
    """One recorded message into ``data`` (``log_s``: seconds since the recording's first message)."""
    kind = recorded.type_name
    if kind == "msk.ActivationFrame":
        f = recorded.decode(messages.ActivationFrame)
        key = (f.method, tuple(f.groups))
        series = data.frames.get(key) or data.frames.setdefault(key, MethodSeries(tuple(f.groups)))
        series.add(f)
        if f.exercise and f.exercise not in data.frame_exercises:
            data.frame_exercises.append(f.exercise)
            for e in gate.on_frame(f.exercise):
                _add_load(data, e)
    elif kind == "msk.JointAngles":
        j = recorded.decode(messages.JointAngles)
        t = j.device_time_ns / 1e9
        data.joint_time.append(t)
        data.joint_phase.append(j.phase if j.HasField("phase") else math.nan)
        data.joint_q.setdefault(tuple(j.coordinates), []).append((t, list(j.q)))
    elif kind == "msk.LoadEvent":
        for e in gate.offer(recorded.decode(messages.LoadEvent)):
            _add_load(data, e)
    elif kind == "msk.EmgChunk":
        c = recorded.decode(messages.EmgChunk)
        data.emg.setdefault(c.source_id or recorded.topic.rsplit("/", 1)[-1], []).append(
            (log_s, c.first_sample_index, c.n_samples)
        )
    elif kind == "msk.ImuSample":
        s = recorded.decode(messages.ImuSample)
        data.imu.setdefault(s.tracker_id or recorded.topic.rsplit("/", 1)[-1], []).append((log_s, s.packet_counter))
    elif kind == "msk.DeviceStatus":
        status = recorded.decode(messages.DeviceStatus)
        if status.kind == "node":  # a node's own status: its dropped inputs, not a device
            data.node_drops[status.device_id] = sum(int(d.count) for d in status.dropped)
            data.electrodes.update((f"{e.source}/{e.channel}", e) for e in status.electrodes)
            for fatigue in status.fatigue:
                keep_fatigue(data.fatigue.setdefault(f"{fatigue.source}/{fatigue.channel}", []), fatigue)
        else:
            data.status.setdefault(status.device_id, []).append(
                (log_s, status.connected, status.samples_lost, status.errors)
            )


def _add_load(data: SessionData, e: messages.LoadEvent) -> None:
    data.loads.append(
        Load(
            e.device_time_ns / 1e9,
            e.barbell_mass_kg,
            e.exercise,
            int(e.set_number),
            e.athlete,
            e.set_mark,
            e.set_rest_s,
        )
    )
    data.names = dict(e.names) or data.names  # an event without names leaves them in effect


# ---- sets and repetitions -----------------------------------------------------------------------------------------
@dataclass
class SetWindow:
    index: int  # position in the session, from 1 (file names)
    exercise: str  # "" when not known: frames of any pack belong to the set
    load_kg: float  # 0 when not known
    start_s: float
    end_s: float
    number: int = 0  # the operator's set number; 0: not counted (``index`` is shown)
    record: SetRecord | None = None  # the SetTracker's set: its reps and figures; None without a phase stream
    rep_source: str = ""  # what the record's reps were counted on
    athlete: str = ""  # who lifted (the load event in effect); "" when not named
    several_athletes: bool = False  # the session's sets name more than one: each set's name says whose it is

    @property
    def name(self) -> str:
        exercise = self.exercise.replace("_", " ") or "exercise not named"
        load = f"{self.load_kg:g} kg" if self.load_kg > 0 else "load unknown"
        who = f" ({self.athlete or 'athlete not named'})" if self.several_athletes else ""
        return f"set {self.number or self.index}{who}: {exercise}, {load}"


def _whose(windows: list[SetWindow]) -> list[SetWindow]:
    """Two athletes on one rack (``msk load --athlete``): each set is named with its athlete."""
    several = len({w.athlete for w in windows if w.athlete}) > 1
    for window in windows:
        window.several_athletes = several
    return windows


def set_windows(data: SessionData) -> list[SetWindow]:
    """The session's sets (module doc): from the SetTracker when there is a phase stream, else from the load events
    alone; without either, the whole session is one set."""
    phase_t, phase_p, source = _phase_stream(data)
    if phase_t.size == 0:
        return _fact_windows(data)
    tracker = SetTracker()
    loads = sorted(data.loads)
    frames = _frames_with_phase(data, phase_t, phase_p)
    # in time order; at one instant a fact first, then the phase, then the frame
    events: list[tuple[float, int, int]] = [(load.time_s, 0, k) for k, load in enumerate(loads)]
    events += [(float(t), 1, k) for k, t in enumerate(phase_t)] + [(f[0], 2, k) for k, f in enumerate(frames)]
    for t, kind, k in sorted(events):
        if kind == 0:
            load = loads[k]
            tracker.on_facts(
                t, set_number=load.set_number, set_mark=load.set_mark, mass_kg=load.mass_kg, rest_s=load.rest_s
            )
        elif kind == 1:
            tracker.update(t, float(phase_p[k]))
        else:
            tracker.add_activations(t, frames[k][1], frames[k][2], frames[k][3].tolist())
    tracker.finish()
    windows = []
    for index, record in enumerate(tracker.sets, start=1):
        end = record.end_s if record.end_s is not None else math.inf
        fact = _fact_of(loads, record.start_s, end, record.number)
        exercise = (fact.exercise if fact is not None else "") or (
            data.frame_exercises[0] if len(data.frame_exercises) == 1 else ""
        )
        mass = fact.mass_kg if fact is not None else 0.0
        athlete = fact.athlete if fact is not None else ""
        windows.append(
            SetWindow(index, exercise, mass, record.start_s, end, record.number, record, source, athlete=athlete)
        )
    return _whose(windows)


def _fact_of(loads: list[Load], start_s: float, end_s: float, number: int = 0) -> Load | None:
    """The load event in effect for a set: the last one before its end (a correction within it counts), else none;
    a later correction that names the set (``msk load 65 --set 1`` after its last rep, while the rest has not yet
    ended it: the set ends at its last rep) counts too."""
    before = [load for load in loads if load.time_s < end_s or load.time_s <= start_s]
    fact = before[-1] if before else None
    named = [
        load for load in loads if number and load.set_number == number and not load.set_mark and load.time_s >= start_s
    ]
    if named and (fact is None or named[-1].time_s > fact.time_s):
        fact = named[-1]
    return fact


def _frames_with_phase(
    data: SessionData, phase_t: np.ndarray, phase_p: np.ndarray
) -> list[tuple[float, float, tuple[str, ...], np.ndarray]]:
    """The primary method's frames (of every pack it ran with, :func:`_primary_keys`) as (time, phase, groups,
    activations), in time order: their own phase, else the phase stream's newest sample at the frame (NaN before
    it)."""
    out = []
    for key in _primary_keys(data):
        series = data.frames[key]
        t = np.asarray(series.time, dtype=float)
        own = np.asarray(series.phase, dtype=float)
        at = np.clip(np.searchsorted(phase_t, t, side="right") - 1, 0, phase_t.size - 1)
        phase = np.where(np.isfinite(own), own, np.where(t >= phase_t[0], phase_p[at], np.nan))
        out += [(float(a), float(b), series.groups, row) for a, b, row in zip(t, phase, series.array("activations"))]
    return sorted(out, key=lambda frame: frame[0])


def _phase_stream(data: SessionData) -> tuple[np.ndarray, np.ndarray, str]:
    """(times, phases) the reps are counted on: the joint angles' phase, else the primary method's frames' (of every
    pack it ran with); empty when neither carries one."""
    jt, jp = np.asarray(data.joint_time, dtype=float), np.asarray(data.joint_phase, dtype=float)
    if jp.size and np.any(np.isfinite(jp)):
        order = np.argsort(jt, kind="stable")
        return jt[order], jp[order], "phase of the joint angles"
    keys = _primary_keys(data)
    if keys:
        ft = np.concatenate([np.asarray(data.frames[key].time, dtype=float) for key in keys])
        fp = np.concatenate([np.asarray(data.frames[key].phase, dtype=float) for key in keys])
        if np.any(np.isfinite(fp)):
            order = np.argsort(ft, kind="stable")
            return ft[order], fp[order], "phase of the activation frames"
    return np.array([]), np.array([]), ""


def _primary_keys(data: SessionData) -> list[tuple[str, tuple[str, ...]]]:
    """The frames' series the sets' figures come from: the first of PRIMARY_METHODS present, with every pack it ran
    with one after the other (a bench press, then a deadlift: each set's reps are in its own pack's frames); where
    two packs' frames overlap in time (two estimators at once), the one with the most frames."""
    keys = sorted(data.frames, key=lambda key: -len(data.frames[key].time))
    method = next((m for m in PRIMARY_METHODS if any(key[0] == m for key in keys)), keys[0][0] if keys else None)
    chosen: list[tuple[str, tuple[str, ...]]] = []
    spans: list[tuple[float, float]] = []
    for key in (key for key in keys if key[0] == method):
        time = data.frames[key].time
        if not time:
            continue
        span = (min(time), max(time))
        if all(span[1] < a or span[0] > b for a, b in spans):
            chosen.append(key)
            spans.append(span)
    return chosen


def _fact_windows(data: SessionData) -> list[SetWindow]:
    """Sets of a session without any phase: from the load events alone (the SetTracker's reading of them)."""
    tracker = SetTracker()
    loads = sorted(data.loads)
    for load in loads:
        tracker.on_facts(
            load.time_s, set_number=load.set_number, set_mark=load.set_mark, mass_kg=load.mass_kg, rest_s=load.rest_s
        )
    windows: list[SetWindow] = []
    for record in tracker.sets:
        end = record.end_s if record.end_s is not None else math.inf
        fact = _fact_of(loads, record.start_s, end)
        assert fact is not None  # every set here opened at a load event
        windows.append(
            SetWindow(
                len(windows) + 1, fact.exercise, fact.mass_kg, record.start_s, end, record.number, athlete=fact.athlete
            )
        )
    if not windows:  # no load events: the whole session is one set, of the frames' exercise when they name one
        times = [t for s in data.frames.values() for t in s.time] or data.joint_time
        if times:
            exercise = data.frame_exercises[0] if len(data.frame_exercises) == 1 else ""
            windows.append(SetWindow(1, exercise, 0.0, min(times), max(times)))
    return _whose(windows)


def session_facts(data: SessionData) -> dict:
    """Athlete, date (the first message's, local time of this machine), exercises and loads of the session."""
    athletes = list(dict.fromkeys(load.athlete for load in sorted(data.loads) if load.athlete))
    declared = list(dict.fromkeys(load.exercise for load in sorted(data.loads) if load.exercise))
    # with estimates, the exercises they are of (a replay of a two-exercise recording into one pack's estimator
    # declares both); their loads alone
    exercises = [e for e in declared if e in data.frame_exercises] if data.frame_exercises else declared
    exercises = exercises or data.frame_exercises
    loads = list(
        dict.fromkeys(
            load.mass_kg
            for load in sorted(data.loads)
            if load.mass_kg > 0 and (not load.exercise or load.exercise in exercises)
        )
    )
    started = datetime.datetime.fromtimestamp(data.start_log_ns / 1e9).astimezone()
    return {
        "athlete": ", ".join(athletes) or None,
        "date": started.strftime("%Y-%m-%d %H:%M %Z").strip(),
        "started_at": started.isoformat(timespec="seconds"),
        "exercises": list(exercises),
        "loads_kg": loads,
        "declared_not_estimated": [e for e in declared if e not in exercises],
    }


def facts_line(facts: dict) -> str:
    """``bench press · 40, 50 kg``: the exercises and loads of the header (said to be unknown when they are)."""
    exercises = ", ".join(e.replace("_", " ") for e in facts["exercises"]) or "exercise not named"
    loads = ", ".join(f"{kg:g}" for kg in facts["loads_kg"]) + " kg" if facts["loads_kg"] else "load unknown"
    return f"{exercises} · {loads}"


def reps_in_set(
    data: SessionData, window: SetWindow, series: MethodSeries, pack
) -> tuple[list[tuple[float, float]], str]:
    jt, jp = np.asarray(data.joint_time), np.asarray(data.joint_phase)
    inside = (jt >= window.start_s) & (jt <= window.end_s)
    if np.any(np.isfinite(jp[inside])):
        return phase_rep_spans(jt[inside], jp[inside]), "phase of the joint angles"
    ft, fp = np.asarray(series.time), np.asarray(series.phase)
    inside = (ft >= window.start_s) & (ft <= window.end_s)
    if np.any(np.isfinite(fp[inside])):
        return phase_rep_spans(ft[inside], fp[inside]), "phase of the activation frames"
    from msk_core.estimate.phase import DEFAULT_PHASE_COORDINATES, kinematic_phase

    for coordinates, samples in data.joint_q.items():
        coordinate = DEFAULT_PHASE_COORDINATES.get(pack.name) if pack is not None else None
        if coordinate not in coordinates:
            continue
        t = np.array([s[0] for s in samples])
        q = np.array([s[1][coordinates.index(coordinate)] for s in samples])
        keep = (t >= window.start_s) & (t <= window.end_s)
        try:
            phase, rep_index = kinematic_phase(t[keep], q[keep])
        except EstimationError:
            return [], f"no repetition found on {coordinate}"
        tk = t[keep]
        return [
            (float(tk[rep_index == k][0]), float(tk[rep_index == k][-1])) for k in range(rep_index.max() + 1)
        ], f"rep detection on {coordinate} (msk_core.signal.reps)"
    return [], "no phase and no joint angles of the pack's phase coordinate"


# ---- the numbers ----------------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=1)
def _packs_by_groups() -> dict[tuple[str, ...], str]:
    from services.surfaces.dashboard.app import packs_by_groups

    return packs_by_groups()


@functools.cache
def _pack_for(groups: tuple[str, ...]):
    name = _packs_by_groups().get(groups)
    return load_pack(name) if name else None


def balance(pack, groups: list[str], activations: np.ndarray, rep_masks: list[np.ndarray]) -> dict:
    """The balance of the pairs the pack declares (its spec's ``[balance]``, msk_core.model.spec.parse_balance), per
    rep: each left/right pair's mean activation, and per declared joint the mean activation of its agonists and of
    its antagonists (weighted by the groups' reference strengths: a big muscle counts more) with the co-contraction
    (smaller / larger). Pairs whose groups the frames lack are left out; a pack declaring none gives empty lists."""
    index = {g: k for k, g in enumerate(groups)}
    means = [np.nanmean(activations[m], axis=0) for m in rep_masks if m.any()]  # per rep, per group
    out: dict = {"left_right": [], "agonist_antagonist": []}
    for left, right in pack.balance.left_right:
        if left in index and right in index:
            per_rep = [(float(a[index[left]]), float(a[index[right]])) for a in means]
            out["left_right"].append({"left": left, "right": right, "per_rep": per_rep})
    strength = dict(zip(pack.groups, np.asarray(pack.f_max_ref, dtype=float)))
    for joint in pack.balance.agonist_antagonist:
        agonists = [g for g in joint.agonists if g in index]
        antagonists = [g for g in joint.antagonists if g in index]
        if not agonists or not antagonists:
            continue
        rows = []
        for a in means:
            ag, ant = _weighted(a, agonists, index, strength), _weighted(a, antagonists, index, strength)
            rows.append((ag, ant, min(ag, ant) / max(ag, ant) if max(ag, ant) > 0 else 0.0))
        out["agonist_antagonist"].append(
            {
                "coordinate": joint.coordinate,
                "label": joint.label,
                "agonists": agonists,
                "antagonists": antagonists,
                "per_rep": rows,
            }
        )
    return out


def _weighted(a: np.ndarray, groups: list[str], index: dict[str, int], strength: dict[str, float]) -> float:
    """Mean of the activations ``a`` of ``groups`` weighted by their reference strengths."""
    w = np.array([strength[g] for g in groups])
    return float(np.sum(a[[index[g] for g in groups]] * w) / np.sum(w))


def summarise_set(data: SessionData, window: SetWindow) -> dict | None:
    in_set = {}
    for (method, frame_groups), series in data.frames.items():
        t = series.array("time")
        m = (t >= window.start_s) & (t <= window.end_s)
        if m.sum() >= 3 and (window.exercise == "" or _pack_name_matches(frame_groups, window.exercise)):
            in_set[method] = (series, m)
    if not in_set:
        return None
    primary = next((m for m in PRIMARY_METHODS if m in in_set), sorted(in_set)[0])
    series, mask = in_set[primary]
    groups = list(series.groups)
    pack = _pack_for(series.groups)
    if window.record is not None:  # the SetTracker's reps (the ones the view and the dashboard counted)
        reps, rep_source = list(window.record.reps), window.rep_source
    else:
        reps, rep_source = reps_in_set(data, window, series, pack)
    names = names_for(pack.name if pack is not None else window.exercise, groups, data.names)
    methods: dict[str, dict[str, Any]] = {}  # per method: its figures, and "_t", "_a" (times, activations) for below
    result = {
        "name": window.name,
        "index": window.index,
        "set_number": window.number,
        "exercise": window.exercise,
        "load_kg": window.load_kg,
        "athlete": window.athlete or None,
        "start_s": window.start_s,
        "end_s": window.end_s if math.isfinite(window.end_s) else float(series.array("time")[mask][-1]),
        "pack": pack.name if pack else None,
        "groups": groups,
        "names": names.as_dict(),
        "_names": names,
        "primary": primary,
        "rep_source": rep_source,
        "reps": [{"start_s": a, "end_s": b, "duration_s": b - a} for a, b in reps],
        "time_under_tension_s": float(sum(b - a for a, b in reps)),
        "set": window.record.as_dict() if window.record is not None else None,  # the SetTracker's figures
        "methods": methods,
    }
    for method, (s, m) in in_set.items():
        t = s.array("time")[m]
        a = s.array("activations")[m]
        rep_masks = [(t >= r0) & (t <= r1) for r0, r1 in reps]
        # each frame stands for the time to the next one inside its rep (the rep's last frame for none), so the time
        # above a threshold is at most the time under tension (frame count x median interval overshot it)
        held = _frame_durations(t, rep_masks) if rep_masks else np.r_[np.diff(t), 0.0] if len(t) else np.zeros(0)
        per_group = {}
        # the set's figures under tension, as the tables' caption says: over the reps' frames (the whole set when it
        # has no rep); the set mean over the whole set stays for the set without reps
        tension = np.logical_or.reduce(rep_masks) if rep_masks else np.ones(len(t), dtype=bool)
        for i, g in enumerate(s.groups):
            per_group[g] = {
                "peak": [float(np.nanmax(a[rm, i])) if rm.any() else None for rm in rep_masks],
                "mean": [float(np.nanmean(a[rm, i])) if rm.any() else None for rm in rep_masks],
                "set_peak": float(np.nanmax(a[tension, i])) if tension.any() else float("nan"),
                "set_mean": float(np.nanmean(a[:, i])),
                "time_active_s": float(np.sum(held[a[:, i] > ACTIVE_THRESHOLD])),
            }
        residual = s.array("residual")[m]
        methods[method] = {
            "frames": int(m.sum()),
            "flagged": int(s.array("flagged")[m].sum()),
            "groups": per_group,
            "torque_residual_rms_nm": float(np.sqrt(np.nanmean(residual**2))) if residual.size else None,
            "solve_ms_median": float(np.median(s.array("solve_s")[m]) * 1e3),
            "_t": t,
            "_a": a,
        }
    # methods against the primary, on the frames both estimated (same input times)
    ref_t, ref_a = methods[primary]["_t"], methods[primary]["_a"]
    for info in methods.values():
        common, ia, ib = np.intersect1d(ref_t, info["_t"], return_indices=True)
        diff = info["_a"][ib] - ref_a[ia]
        info["rms_difference_to_primary"] = float(np.sqrt(np.nanmean(diff**2))) if common.size else None
    if pack is not None:
        t, a = methods[primary]["_t"], methods[primary]["_a"]
        rep_masks = [(t >= r0) & (t <= r1) for r0, r1 in reps]
        result["balance"] = balance(pack, groups, a, rep_masks)
    return result


def _pack_name_matches(groups: tuple[str, ...], exercise: str) -> bool:
    name = _packs_by_groups().get(groups)
    return name is None or name == exercise


def device_health(data: SessionData) -> dict:
    devices: dict[str, dict[str, Any]] = {}  # per device, its row of the health table (JSON values)
    for source, chunks in data.emg.items():
        lost, gaps, restarts, expected = 0, 0, 0, None
        for _, first, n in chunks:
            if expected is not None and first > expected:
                lost, gaps = lost + first - expected, gaps + 1
            elif expected is not None and first < expected:
                restarts += 1
            expected = first + n
        devices[source] = {
            "kind": "EMG",
            "messages": len(chunks),
            "samples": int(sum(c[2] for c in chunks)),
            "samples_lost": int(lost),
            "gaps": gaps,
            "restarts": restarts,
            "times": [c[0] for c in chunks],
            "weights": [c[2] for c in chunks],
        }
    for tracker, samples in data.imu.items():
        counters = np.array([s[1] for s in samples], dtype=np.int64)
        steps = np.diff(counters) % 65536 if len(counters) > 1 else np.array([], dtype=np.int64)  # 16-bit counter
        restarted = steps >= 32768  # the counter went back: the tracker restarted its measurement, nothing was lost
        # under the tracker's own id, the id its DeviceStatus carries: one row per device
        devices[tracker] = {
            "kind": "IMU",
            "messages": len(samples),
            "samples": len(samples),
            "samples_lost": int(np.sum(np.maximum(steps[~restarted] - 1, 0))) if steps.size else 0,
            "gaps": int(np.sum((steps > 1) & ~restarted)),
            "restarts": int(np.sum(restarted)),
            "times": [s[0] for s in samples],
            "weights": [1] * len(samples),
        }
    for device, statuses in data.status.items():
        entry = devices.setdefault(
            device, {"kind": "status", "messages": 0, "samples": 0, "samples_lost": 0, "times": [], "weights": []}
        )
        entry["status_messages"] = len(statuses)
        # the last status of a driver that stopped cleanly says disconnected: the stop, not a loss of the device
        entry["disconnected_reports"] = int(sum(1 for s in statuses[:-1] if not s[1]))
        entry["samples_lost"] = max(entry["samples_lost"], max(s[2] for s in statuses))
        entry["errors"] = max(s[3] for s in statuses)
    return devices


# ---- plots ------------------------------------------------------------------------------------------------------------
def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_set(result: dict, out: Path, stem: str) -> list[str]:
    plt = _plt()
    primary = result["methods"][result["primary"]]
    t, a, groups = primary["_t"], primary["_a"], result["groups"]
    names: DisplayNames = result["_names"]
    t0 = result["start_s"]
    files = []
    # 1. activation over the set, the 6 busiest groups, reps shaded
    top = np.argsort(np.nanmax(a, axis=0))[::-1][:6]
    fig, ax = plt.subplots(figsize=(10, 3.6))
    fig.subplots_adjust(left=0.07, right=0.86, bottom=0.14, top=0.93)
    for k, rep in enumerate(result["reps"]):  # numbered above each shaded rep ("rep 13" and "rep 14" overlapped)
        ax.axvspan(rep["start_s"] - t0, rep["end_s"] - t0, color="tab:blue", alpha=0.08)
        ax.text((rep["start_s"] + rep["end_s"]) / 2 - t0, 102, str(k + 1), ha="center", fontsize=8, color="tab:blue")
    if result["reps"]:
        ax.text(1.0, 1.01, "reps numbered", transform=ax.transAxes, ha="right", fontsize=7, color="tab:blue")
    colours = plt.get_cmap("tab20")  # one colour per muscle, the same in every set's plot (by its place in the pack)
    for i in top:
        ax.plot(t - t0, 100 * a[:, i], lw=1.4, label=names.group(groups[i]), color=colours(i % 20))
    ax.set_ylim(0, 108)
    ax.set_xlabel("time in set (s)")
    ax.set_ylabel(f"activation (%, {result['primary']})")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    files.append(f"{stem}_activation.png")
    fig.savefig(out / files[-1], dpi=90, bbox_inches="tight")  # the legend's display names beside the plot
    plt.close(fig)
    # 2. peak per rep and muscle (heat map)
    if result["reps"]:
        peak = np.array([[100 * v if v is not None else np.nan for v in primary["groups"][g]["peak"]] for g in groups])
        fig, ax = plt.subplots(figsize=(2.4 + 0.7 * len(result["reps"]), 0.3 * len(groups) + 1.0))
        fig.subplots_adjust(
            left=0.2, right=0.88, bottom=0.3 / (0.3 * len(groups) + 1.0), top=1 - 0.35 / (0.3 * len(groups) + 1.0)
        )
        image = ax.imshow(peak, vmin=0, vmax=100, cmap="YlOrRd", aspect="auto")
        for (i, j), v in np.ndenumerate(peak):
            if np.isfinite(v):
                ax.text(j, i, f"{v:.0f}", ha="center", va="center", fontsize=7, color="white" if v > 60 else "black")
        ax.set_xticks(range(len(result["reps"])), [f"rep {k + 1}" for k in range(len(result["reps"]))], fontsize=8)
        ax.set_yticks(range(len(groups)), [names.group(g) for g in groups], fontsize=8)
        ax.set_title("peak activation per rep (%)", fontsize=9)
        fig.colorbar(image, ax=ax, fraction=0.05, label="%")
        files.append(f"{stem}_peaks.png")
        fig.savefig(out / files[-1], dpi=90, bbox_inches="tight")  # the display names left of the map
        plt.close(fig)
    # 3. methods side by side: mean activation over the set
    if len(result["methods"]) > 1:
        methods = sorted(result["methods"])
        fig, ax = plt.subplots(figsize=(10, 3.2))
        fig.subplots_adjust(left=0.07, right=0.98, bottom=0.22, top=0.95)
        x = np.arange(len(groups))
        width = 0.8 / len(methods)
        # under tension, as the tables' means: the mean of the rep means (the whole set without reps to average)
        under_tension = bool(result["reps"])
        for k, method in enumerate(methods):
            figures = result["methods"][method]["groups"]
            means = [100 * (_mean_of(figures[g]["mean"]) if under_tension else figures[g]["set_mean"]) for g in groups]
            ax.bar(x + (k - (len(methods) - 1) / 2) * width, means, width, label=method)
        ax.set_xticks(x, groups, rotation=45, ha="right", fontsize=8)  # abbreviations: the legend is under the plot
        ax.set_ylabel("mean over the reps (%)" if under_tension else "mean over the set (%)")
        ax.legend(fontsize=8)
        files.append(f"{stem}_methods.png")
        fig.savefig(out / files[-1], dpi=90)
        plt.close(fig)
    return files


def _mean_of(values: list[float | None]) -> float:
    """The mean of the rep figures that exist (NaN when none)."""
    finite = [v for v in values if v is not None and np.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


def plot_devices(devices: dict, duration_s: float, out: Path) -> str | None:
    if not any(d["times"] for d in devices.values()):
        return None
    plt = _plt()
    fig, ax = plt.subplots(figsize=(10, 2.8))
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.17, top=0.95)
    bins = np.arange(0, max(duration_s, 1.0) + 1.0, 1.0)
    for name, d in devices.items():
        if d["times"]:
            counts, _ = np.histogram(d["times"], bins=bins, weights=d["weights"])
            ax.step(bins[:-1], counts, where="post", label=f"{name} ({d['kind']})")
    ax.set_yscale("log")
    ax.set_xlabel("time received (s, the recording's log time: a recording of a fast replay is compressed)")
    ax.set_ylabel("samples per second")
    ax.legend(fontsize=8, loc="lower right")
    fig.savefig(out / "devices.png", dpi=90)
    plt.close(fig)
    return "devices.png"


# ---- HTML -------------------------------------------------------------------------------------------------------------
CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:0;background:#f4f6f8;color:#1d2630}
header{background:#1d2630;color:#fff;padding:14px 22px}header h1{margin:0;font-size:22px}header div{color:#aab4c0;font-size:14px}
header div.facts{color:#fff;font-size:17px;margin:4px 0 2px}
main{padding:12px 22px;max-width:1200px}section{background:#fff;border-radius:10px;padding:12px 16px;margin:12px 0;box-shadow:0 1px 3px rgba(0,0,0,.08)}
h2{font-size:18px;margin:4px 0 8px}h3{font-size:15px;margin:12px 0 6px}table{border-collapse:collapse;font-size:13px;margin:6px 0}
th,td{padding:3px 8px;border-bottom:1px solid #e6e9ed;text-align:right}th:first-child,td:first-child{text-align:left}
.row{display:flex;gap:16px;flex-wrap:wrap;align-items:flex-start}.bodymap{width:300px}img{max-width:100%}.note{color:#6b7684;font-size:13px}
.kpi{display:inline-block;margin-right:22px}.kpi b{font-size:22px;display:block}
"""


def _pct(v) -> str:
    return "–" if v is None or not math.isfinite(v) else f"{100 * v:.0f}"


def _table(headers: list[str], rows: list[list[str]]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in headers)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


#: Sets side by side in one table of the per-set muscle figures (more: the table is split), so it fits 1200 px.
SETS_PER_TABLE = 8


def sets_html(sets: list[dict]) -> str:
    """The table of sets, one row per set: reps, time under tension, duration and how the set ended; then, per
    exercise's muscle groups, the peak / mean activation % of each group (rows) in each set (columns, at most
    :data:`SETS_PER_TABLE` a table) over the set's reps."""
    rows = [
        [
            html.escape(r["name"]),
            str(len(r["reps"])),
            f"{r['time_under_tension_s']:.1f}",
            f"{r['end_s'] - r['start_s']:.1f}",
            html.escape(r["set"]["started_by"] if r.get("set") is not None else "load event"),
            html.escape(r["set"]["ended_by"] if r.get("set") is not None else "load event"),
        ]
        for r in sets
    ]
    parts = [
        "<section class='sets'><h2>Sets</h2>",
        _table(["set", "reps", "time under tension (s)", "duration (s)", "started by", "ended by"], rows),
    ]
    by_groups: dict[tuple[str, ...], list[dict]] = {}
    for result in sets:
        by_groups.setdefault(tuple(result["groups"]), []).append(result)
    for groups, results in by_groups.items():
        names: DisplayNames = results[0]["_names"]
        figures = [_set_figures(r) for r in results]
        for k in range(0, len(results), SETS_PER_TABLE):
            chunk = range(k, min(k + SETS_PER_TABLE, len(results)))
            headers = ["muscle"] + [f"set {results[i]['set_number'] or results[i]['index']}" for i in chunk]
            table = [
                [html.escape(names.group(g))]
                + [
                    f"{_pct(figures[i].get(g, (None, None))[0])} / {_pct(figures[i].get(g, (None, None))[1])}"
                    for i in chunk
                ]
                for g in groups
            ]
            parts.append("<h3>Peak / mean activation per set (%)</h3>" + _table(headers, table))
    parts.append(
        "<p class='note'>Peak / mean: activation of each muscle group over the frames inside the set's reps (under "
        "tension), of the method the report details. A set starts by the operator (a start mark), with the "
        "session (its opening facts), at a load event (a new set number or load) or at the first rep after a rest; it "
        "ends by the operator, when the next starts, by rest detection (rest: no rep for the session's rest time) or "
        "at the end of the recording.</p></section>"
    )
    return "".join(parts)


def _set_figures(result: dict) -> dict[str, tuple[float | None, float | None]]:
    """Per group, (peak, mean) activation of a set: the SetTracker's over its reps, else (no phase) the primary
    method's over the whole set."""
    figures = result.get("set")
    if figures is not None and figures["groups"]:
        return dict(zip(figures["groups"], zip(figures["peak"], figures["mean"])))
    return {g: (v["set_peak"], v["set_mean"]) for g, v in result["methods"][result["primary"]]["groups"].items()}


def _balance_html(bal: dict | None, names: DisplayNames, n_reps: int) -> str:
    """The balance tables of a set: only the pairs its pack declares (:func:`balance`); one short note when it
    declares none."""
    if not bal or not (bal["left_right"] or bal["agonist_antagonist"]):
        return "<p class='note'>Balance: the model pack declares no left/right or agonist/antagonist pairs.</p>"
    reps = [f"rep {k + 1}" for k in range(n_reps)]
    parts = []
    if bal["left_right"]:
        rows = [
            [f"{html.escape(names.group(p['left']))} / {html.escape(names.group(p['right']))}"]
            + [f"{_pct(left)} / {_pct(right)}" for left, right in p["per_rep"]]
            for p in bal["left_right"]
        ]
        parts.append(
            "<h3>Left / right balance (mean activation per rep, left / right %)</h3>" + _table(["pair"] + reps, rows)
        )
    if bal["agonist_antagonist"]:
        rows = [
            [
                html.escape(j["label"]),
                html.escape(", ".join(map(names.group, j["agonists"]))),
                html.escape(", ".join(map(names.group, j["antagonists"]))),
            ]
            + [f"{_pct(ag)} / {_pct(ant)} ({100 * c:.0f} %)" for ag, ant, c in j["per_rep"]]
            for j in bal["agonist_antagonist"]
        ]
        parts.append(
            "<h3>Agonist / antagonist balance</h3><p class='note'>Per joint the model pack declares: mean activation of "
            "the first muscles / of the second over each rep, in % (weighted by the muscles' reference strengths); in "
            "brackets the co-contraction, smaller / larger.</p>" + _table(["muscles", "first", "second"] + reps, rows)
        )
    return "".join(parts)


def set_html(result: dict, plots: list[str]) -> str:
    primary = result["methods"][result["primary"]]
    groups, reps = result["groups"], result["reps"]
    names: DisplayNames = result["_names"]
    parts = [f'<section class="set" id="set-{result["index"]}"><h2>{html.escape(result["name"])}</h2>']
    parts.append(
        f'<div class="kpi"><b>{len(reps)}</b>reps</div><div class="kpi"><b>{result["time_under_tension_s"]:.1f} s</b>time under tension</div>'
        f'<div class="kpi"><b>{result["end_s"] - result["start_s"]:.1f} s</b>set duration</div>'
        f'<div class="kpi"><b>{html.escape(result["primary"])}</b>method shown</div>'
        f'<p class="note">Repetitions from the {html.escape(result["rep_source"])}; rep durations: '
        + (", ".join(f"{r['duration_s']:.1f} s" for r in reps) or "none")
        + ".</p>"
    )
    body_svg = ""
    if result["pack"]:
        fills = {g: bodymap.activation_colour(primary["groups"][g]["set_peak"]) for g in groups}
        svg = bodymap.place_groups(load_pack(result["pack"])).svg(fills=fills, names=names.groups)
        body_svg = f'<div class="bodymap">{svg}<div class="note">peak activation in the set</div></div>'
    images = "".join(f'<img src="{p}" alt="{html.escape(p)}">' for p in plots)
    legend = names.legend(groups) if any(p.endswith("_methods.png") for p in plots) else ""
    if legend:  # the method comparison's axis names the muscles by their model names
        images += f'<p class="note">Abbreviations: {html.escape(legend)}.</p>'
    parts.append(f'<div class="row">{body_svg}<div style="flex:1;min-width:300px">{images}</div></div>')
    headers = (
        ["muscle"]
        + [f"rep {k + 1} peak / mean %" for k in range(len(reps))]
        + ["set peak %", f"time > {ACTIVE_THRESHOLD:.0%} (s)"]
    )
    rows = []
    for g in groups:
        v = primary["groups"][g]
        rows.append(
            [html.escape(names.group(g))]
            + [f"{_pct(p)} / {_pct(m)}" for p, m in zip(v["peak"], v["mean"])]
            + [_pct(v["set_peak"]), f"{v['time_active_s']:.1f}"]
        )
    parts.append(f"<h3>Per muscle and rep ({html.escape(result['primary'])})</h3>" + _table(headers, rows))
    parts.append(_balance_html(result.get("balance"), names, len(reps)))
    if len(result["methods"]) > 1:
        rows = []
        for method in sorted(result["methods"]):
            info = result["methods"][method]
            rows.append(
                [
                    html.escape(method),
                    str(info["frames"]),
                    f"{100 * info['rms_difference_to_primary']:.1f}"
                    if info["rms_difference_to_primary"] is not None
                    else "–",
                    f"{info['torque_residual_rms_nm']:.2f}" if info["torque_residual_rms_nm"] is not None else "–",
                    str(info["flagged"]),
                    f"{info['solve_ms_median']:.2f}",
                ]
            )
        parts.append(
            "<h3>Methods compared</h3>"
            + _table(
                [
                    "method",
                    "frames",
                    f"RMS difference to {result['primary']} (%)",
                    "torque residual RMS (N·m)",
                    "flagged frames",
                    "solve time median (ms)",
                ],
                rows,
            )
        )
    parts.append("</section>")
    return "".join(parts)


def emg_summary(data: SessionData) -> dict:
    """``report.json``'s electrodes and fatigue, as ``msk live``'s ``summary.json`` says them (services.sessions.live)."""
    return {
        "electrodes": {name: electrode_summary(e) for name, e in sorted(data.electrodes.items())},
        "fatigue": {name: [fatigue_summary(e) for e in sets] for name, sets in sorted(data.fatigue.items())},
    }


def _session_names(data: SessionData, facts: dict) -> DisplayNames:
    """Display names of the session's muscle groups for its session-wide tables: the first exercise's pack's, with
    the session file's names."""
    return names_for(facts["exercises"][0] if facts["exercises"] else "", (), data.names)


def electrodes_html(data: SessionData, facts: dict) -> str:
    """The estimator's verdict on every EMG electrode over the session (its last status): the state at the end, the
    time spent in check and bad, and the fault episodes with their reasons; empty when no estimator judged any."""
    if not data.electrodes:
        return ""
    names = _session_names(data, facts)
    rows = []
    for name, e in sorted(data.electrodes.items()):
        episodes = "; ".join(
            f"{p.worst} {p.start_s:.1f}-{f'{p.end_s:.1f}' if p.HasField('end_s') else 'end'} s: {', '.join(p.reasons)}"
            for p in e.recent
        )
        rows.append(
            [
                html.escape(name),
                html.escape(names.group(e.group) if e.group else "–"),
                html.escape(e.state + (f" ({', '.join(e.reasons)})" if e.reasons else "")),
                f"{e.check_s:.1f}",
                f"{e.bad_s:.1f}",
                str(e.episodes),
                html.escape(episodes or "none"),
            ]
        )
    return (
        "<section class='electrodes'><h2>EMG electrodes: signal quality</h2>"
        + _table(["electrode", "muscle", "state at the end", "check (s)", "bad (s)", "episodes", "reasons"], rows)
        + "<p class='note'>Judged live by the estimator from the raw EMG (contact, mains interference, saturation, "
        "flat line); its last status. Episodes (the last 16): worst state, start-end on the EMG device clock, the "
        "faults raised. A bad electrode is left out of its muscle's envelope.</p></section>"
    )


def fatigue_html(data: SessionData, facts: dict) -> str:
    """Per electrode and set, the estimator's spectral fatigue index: the median frequency of the first and the last
    rep, its slope per rep (Hz and % of the first reps) and its change over the set; empty without any."""
    names = _session_names(data, facts)
    rows = []
    for name, sets in sorted(data.fatigue.items()):
        for e in sets:
            if not e.median_hz:
                continue
            slope = e.median_slope_hz_per_rep
            rows.append(
                [
                    html.escape(name),
                    html.escape(names.group(e.group) if e.group else "–"),
                    str(e.set_number or "–"),
                    str(len(e.median_hz)),
                    _hz(e.median_hz[0]),
                    _hz(e.median_hz[-1]),
                    "–" if not math.isfinite(slope) else f"{slope:+.1f} ({e.median_slope_pct_per_rep:+.1f} %)",
                    "–" if not math.isfinite(e.median_change_pct) else f"{e.median_change_pct:+.1f}",
                ]
            )
    if not rows:
        return ""
    headers = [
        "electrode",
        "muscle",
        "set",
        "reps",
        "first rep (Hz)",
        "last rep (Hz)",
        "slope per rep (Hz)",
        "change (%)",
    ]
    return (
        "<section class='fatigue'><h2>Fatigue: median frequency of the EMG per rep</h2>"
        + _table(headers, rows)
        + "<p class='note'>Computed live by the estimator from the raw EMG of each rep's active part (20-450 Hz, "
        "Welch): the median frequency of the set's first and last rep, its least-squares slope per rep (in brackets, "
        "in % of the first reps' mean) and the change from the mean of the first reps to that of the last reps (3 each, "
        "or half the set's reps in a set of fewer than 6: a set's single first and last reps can both read the same "
        "while the change does not). A falling median "
        "frequency is the standard EMG sign of fatigue.</p></section>"
    )


def _hz(v: float) -> str:
    return f"{v:.1f}" if math.isfinite(v) else "–"


def health_html(data: SessionData, devices: dict, device_plot: str | None) -> str:
    """The section on the health of every device over the session (its table, the samples-per-second plot, the
    nodes' dropped inputs)."""
    rows = [
        [
            html.escape(name),
            d["kind"],
            str(d["messages"]),
            str(d["samples"]),
            str(d["samples_lost"]),
            str(d.get("gaps", "–")),
            str(d.get("restarts", "–")),
            str(d.get("disconnected_reports", "–")),
            str(d.get("errors", "–")),
        ]
        for name, d in sorted(devices.items())
    ]
    return (
        "<section><h2>Device health over the session</h2>"
        + _table(
            [
                "device",
                "kind",
                "messages",
                "samples",
                "samples missing",
                "gaps",
                "restarts",
                "disconnected reports",
                "errors",
            ],
            rows,
        )
        + "<p class='note'>Samples missing: jumps of the EMG sample index or of the IMU packet counter (a pause between "
        "trials of a recording shows as one gap); restarts: the counter went back to an earlier value; disconnected "
        "reports: status messages saying the device was not connected, the last one (the driver's stop) left out.</p>"
        + (f'<img src="{device_plot}" alt="samples per second">' if device_plot else "")
        + "".join(f"<p class='note'>{html.escape(note)}</p>" for note in _recording_notes(data))
        + "</section>"
    )


def _recording_notes(data: SessionData) -> list[str]:
    """What the report left out of the recording, or could not read, in words (none when nothing)."""
    notes = []
    if data.node_drops:
        notes.append(
            "Inputs the nodes dropped as unusable: "
            + ", ".join(f"{node} {n}" for node, n in sorted(data.node_drops.items()))
            + "."
        )
    if data.refused_loads:
        notes.append(
            f"{data.refused_loads} load event(s) named an exercise that no model pack has and no activation frame "
            "named; as the estimator refused them, the report leaves them out."
        )
    if data.damage:
        notes.append(f"The recording could not be read whole ({data.damage}); its readable part is reported.")
    if data.undecodable:
        notes.append(
            "Payloads that were not the message their topic says, left out: "
            + ", ".join(f"{n} on {t}" for t, n in sorted(data.undecodable.items()))
        )
    return notes


def _frame_durations(t: np.ndarray, rep_masks: list[np.ndarray]) -> np.ndarray:
    """Per frame, the time it stands for under tension: to the next frame of its rep (0 outside reps and for a rep's
    last frame)."""
    held = np.zeros(len(t))
    for mask in rep_masks:
        idx = np.flatnonzero(mask)
        if len(idx) > 1:
            held[idx[:-1]] = np.diff(t[idx])
    return held


def session_length_s(data: SessionData) -> float:
    """The session's length on the devices' clock: a recording of a fast replay is shorter in log time than the
    session, and the log time of a live one includes the start-up before the first frame. Each pack's frames are one
    stream (two exercises replayed together interleave theirs: the demo's joint frames go 34 s back and forth, and its
    report said "16 s recorded" of 73 s); a stream whose clock started again (a tracker's power cycle) has no span, and
    the log's is taken then."""
    streams = [series.array("time") for series in data.frames.values() if series.time]
    if not streams and data.joint_time:
        streams = [np.asarray(data.joint_time, dtype=float)]
    log_span = (data.end_log_ns - data.start_log_ns) / 1e9
    if not streams or not all(np.all(np.diff(t) >= 0) for t in streams):
        return log_span
    span = max(float(t[-1]) for t in streams) - min(float(t[0]) for t in streams)
    return span if span > 0 else log_span


def write_report(recording: Path, out: Path, *, session: str | None = None, progress: bool = False) -> dict:
    data = read_session(recording, session=session, progress=progress)
    out.mkdir(parents=True, exist_ok=True)
    sets = []
    for window in set_windows(data):
        result = summarise_set(data, window)
        if result is not None:
            result["plots"] = plot_set(result, out, f"set{window.index}")
            sets.append(result)
    devices = device_health(data)
    duration = session_length_s(data)
    device_plot = plot_devices(devices, (data.end_log_ns - data.start_log_ns) / 1e9, out)
    methods = sorted({m for m, _ in data.frames})
    facts = session_facts(data)
    title = f"Session report: {facts['athlete'] or 'athlete not named'}, {facts['date']}"
    sections = [set_html(s, s["plots"]) for s in sets]
    if not data.frames:
        sections.insert(
            0,
            "<section><h2>No activation frames</h2><p>This recording holds no <code>activations/&lt;method&gt;</code> "
            "topic: record while an estimator runs (e.g. <code>msk demo</code> writes <code>out/demo/live.mcap</code>) "
            "and report on that recording. Sets, repetitions and device health below come from the raw data.</p></section>",
        )
    health = health_html(data, devices, device_plot) + electrodes_html(data, facts) + fatigue_html(data, facts)
    overview = (
        f"<section><h2>Overview</h2><div class='kpi'><b>{duration:.0f} s</b>recorded</div>"
        f"<div class='kpi'><b>{len(sets)}</b>{'set' if len(sets) == 1 else 'sets'} with estimates</div><div class='kpi'><b>{sum(len(s['reps']) for s in sets)}</b>reps</div>"
        f"<div class='kpi'><b>{html.escape(', '.join(methods) or 'none')}</b>methods</div>"
        + (
            f"<p class='note'>Also declared, without estimates (the estimator ran another exercise's model): "
            f"{html.escape(', '.join(e.replace('_', ' ') for e in facts['declared_not_estimated']))}.</p>"
            if facts["declared_not_estimated"]
            else ""
        )
        + "</section>"
    )
    page = (
        f"<!doctype html><html lang='en'><head><meta charset='utf-8'><meta name='viewport' content='width=device-width, initial-scale=1'>"
        f"<title>{html.escape(title)}</title><style>{CSS}</style></head><body><header><h1>{html.escape(title)}</h1>"
        f"<div class='facts'>{html.escape(facts_line(facts))}</div>"
        f"<div>msk-live · {html.escape(Path(recording).name)} · {len(sets)} set{'' if len(sets) == 1 else 's'} · methods: "
        f"{html.escape(', '.join(methods) or 'none')} · method shown: {html.escape(default_method(methods) or 'none')}"
        "</div></header><main>"
        + overview
        + (sets_html(sets) if sets else "")
        + "".join(sections)
        + health
        + "</main></body></html>"
    )
    (out / "report.html").write_text(page)
    summary = {
        "recording": str(recording),
        **facts,
        "duration_s": duration,
        "recording_damage": data.damage,  # "" when the whole file was read
        "undecodable_payloads": dict(sorted(data.undecodable.items())),
        "methods": methods,
        "sets": [
            {k: v for k, v in s.items() if k != "methods" and not k.startswith("_")}
            | {
                "methods": {
                    m: {k: v for k, v in info.items() if not k.startswith("_")} for m, info in s["methods"].items()
                }
            }
            for s in sets
        ],
        "devices": {name: {k: v for k, v in d.items() if k not in ("times", "weights")} for name, d in devices.items()},
        "node_inputs_dropped": dict(sorted(data.node_drops.items())),
        "load_events_refused": data.refused_loads,
        **emg_summary(data),
    }
    (out / "report.json").write_text(json_text(summary, indent=1, default=float))
    return summary


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recording", type=Path, help="MCAP recording of a session (with activations/<method> topics)")
    parser.add_argument("--out", type=Path, required=True, help="output folder: report.html, report.json and the plots")
    parser.add_argument(
        "--session", default=None, help="the recorded session to report (needed when the recording holds several)"
    )


def run_from_args(args: argparse.Namespace) -> int:
    summary = write_report(args.recording, args.out, session=args.session, progress=sys.stderr.isatty())
    if summary["recording_damage"]:
        print(
            f"warning: {args.recording}: {summary['recording_damage']}; the readable part is reported", file=sys.stderr
        )
    if summary["undecodable_payloads"]:
        print(
            f"warning: {args.recording}: payloads that were not their topic's message, left out: "
            + ", ".join(f"{n} on {t}" for t, n in summary["undecodable_payloads"].items()),
            file=sys.stderr,
        )
    print(
        f"report of {args.recording}: {len(summary['sets'])} set{'' if len(summary['sets']) == 1 else 's'}, {sum(len(s['reps']) for s in summary['sets'])} reps, "
        f"methods {', '.join(summary['methods']) or 'none'} -> {args.out / 'report.html'}",
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    from services.transport.zenoh_session import run_script

    run_script(__doc__, add_arguments, run_from_args)
