"""The facts of a session that the operator changes while it runs: the barbell load, the set under way, the exercise
and the athlete, each change one :class:`~services.transport.messages.LoadEvent` on ``msk/<session>/load``.

Built here once for every place that changes them: ``msk load`` and ``msk sets`` (services.commands), the view's keys
and the dashboard's set button (services.surfaces).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from msk_core.errors import ConfigError
from msk_core.signal.sets import SetTracker
from msk_core.units import load_problem
from services.nodes.node_runtime import NodeInputs, apply_load_event
from services.sessions import discovery
from services.transport import messages

#: The key of the announced facts (``OUT/session.json``) that holds the sets as ``msk live`` counted them, oldest
#: first (:meth:`~msk_core.signal.sets.SetRecord.as_dict`: number, start, end, who ended it, rep spans, on the
#: activation frames' clock), for pages that join late.
SETS_COUNTED = "sets_counted"
#: The key of the announced facts that holds when the rep under way began (None between reps).
REP_START = "rep_start_s"
#: The sets announced at the most (the newest): a page that joins a long session shows these.
MAX_ANNOUNCED_SETS = 50


def check_facts(load_kg: float | None, set_number: int | None) -> None:
    """The operator's load (finite, 0 to ``MAX_LOAD_KG``) and set number (from 1), each when given."""
    if load_kg is not None and (problem := load_problem(load_kg)) is not None:
        raise ConfigError(problem, field="KG", value=load_kg)
    if set_number is not None and set_number < 1:
        raise ConfigError("sets are counted from 1", field="--set", value=set_number)


def new_facts(
    current: dict,
    *,
    load_kg: float | None,
    set_number: int | None,
    next_set: bool,
    exercise: str | None,
    athlete: str | None,
    set_mark: str = "",
) -> messages.LoadEvent:
    """The LoadEvent that changes ``current`` (a session's facts: exercise, load_kg, set_number, athlete);
    ``set_mark``: "start" (the next set starts: ``next_set``) or "stop" (the set under way ends), "" none."""
    check_facts(load_kg, set_number)
    now = messages.now_ns()
    number = int(current.get("set_number", 0) or 0)
    if set_number is not None and set_number < number:
        # the facts apply to the frames from now on: a past set's number would start set number + 1 instead
        raise ConfigError(
            f"set {set_number} is over: the session is at set {number}, and facts apply from now on "
            f"(the set under way: --set {number} or no --set; a new set: --next-set)",
            field="--set",
            value=set_number,
        )
    if next_set:
        number += 1
    elif set_number is not None:
        number = set_number
    return messages.LoadEvent(
        barbell_mass_kg=float(load_kg if load_kg is not None else current.get("load_kg", 0.0)),
        exercise=exercise if exercise is not None else str(current.get("exercise", "")),
        set_number=number,
        athlete=athlete if athlete is not None else str(current.get("athlete", "")),
        set_mark=set_mark,
        device_time_ns=now,
        host_time_ns=now,
    )  # msk live maps the device clocks onto the host clock


def set_mark_event(load: messages.LoadEvent | None, set_number: int, mark: str) -> messages.LoadEvent:
    """The session fact of the operator's set ``mark`` ("start": the next set; "stop") from a surface that holds the
    newest LoadEvent (``load``: the facts in effect) and shows set ``set_number`` (the view's key, the dashboard's
    button)."""
    facts: dict = {"set_number": max(set_number, int(load.set_number) if load is not None else 0)}
    if load is not None:
        facts |= {"load_kg": load.barbell_mass_kg, "exercise": load.exercise, "athlete": load.athlete}
    return new_facts(
        facts, load_kg=None, set_number=None, next_set=mark == "start", exercise=None, athlete=None, set_mark=mark
    )


class FactsFollower:
    """The session facts in effect as ``msk live`` announces them (``OUT/session.json``, which ``msk load`` and
    ``msk set`` start from): the operator's load events, and the set number the sets have reached, rest detection's
    sets included (:class:`~msk_core.signal.sets.SetTracker` on the first method's activation frames, as the view and
    the dashboard count them). Without the sets, ``msk load 60`` in a set that rest detection had opened carried
    the previous set's number, and every consumer started a new set at it.

    ``on_facts`` gets the facts dict (exercise, load_kg, set_number, athlete) at every change. Thread-safe: Zenoh calls
    from its threads."""

    def __init__(self, on_facts: Callable[[dict], None]) -> None:
        self._on_facts = on_facts
        self._sets = SetTracker()
        self._facts: dict = {}
        self._method = ""  # the activation stream whose phase counts the reps (the first seen)
        self._lock = threading.Lock()

    def finish(self) -> list[dict]:
        """The end of the session: the rep under way counted if long enough, the set under way closed (as the
        report counts them); every set as :meth:`SetRecord.as_dict`."""
        with self._lock:
            self._sets.finish()
            return [record.as_dict() for record in self._sets.sets]

    def on_event(self, event: messages.LoadEvent) -> None:
        """A load event every node applies (the caller checked it as the estimator does)."""
        with self._lock:
            apply_load_event(self._sets, event)
            self._facts = {
                "exercise": event.exercise or self._facts.get("exercise", ""),  # none named: the one in effect
                "load_kg": event.barbell_mass_kg,
                "set_number": int(event.set_number),
                "athlete": event.athlete,
            }
            self._announce()

    def on_frame(self, method: str, frame: messages.ActivationFrame) -> None:
        """An activation frame of ``method``: the first method's move the sets on."""
        with self._lock:
            self._method = self._method or method
            if method != self._method:
                return
            before = self._state()
            self._sets.update(frame.time_s, frame.phase if frame.HasField("phase") else None)
            if self._state() != before:
                self._announce()

    def wants(self, method: str) -> bool:
        """Whether a frame of ``method`` counts (so a caller decodes only those)."""
        return not self._method or method == self._method

    def _announce(self) -> None:
        if self._facts:
            number, resting = self._sets.settled
            self._on_facts(
                {
                    **self._facts,
                    "set_number": number or self._facts["set_number"],
                    "resting": resting,
                    SETS_COUNTED: self._sets_counted(),
                    REP_START: self._sets.rep_start_s,  # also of a rep whose set has not counted yet
                }
            )

    def _state(self) -> tuple:
        """What the announcement says, cheaply compared per frame: the set number, resting, and the newest set's
        reps and end (a set ends or gets a rep one at a time)."""
        sets = self._sets.sets
        newest = (len(sets), sets[-1].end_s, len(sets[-1].reps)) if sets else None
        return self._sets.settled, newest, self._sets.rep_start_s

    def _sets_counted(self) -> list[dict]:
        """The sets as this session counted them (:meth:`SetRecord.as_dict`)."""
        return [record.as_dict() for record in self._sets.counted()[-MAX_ANNOUNCED_SETS:]]


def announced_events(session: str) -> list[messages.LoadEvent]:
    """The facts in effect of ``session`` as ``msk live`` announces them on this machine (``OUT/session.json``,
    following every operator change and the set under way) as LoadEvents made now: the facts without a set mark,
    then a stop mark when the session rests between sets (so a page that starts then shows the rest, and its set
    button starts the next set); none when the session announces nothing here (a page on another machine keeps the
    opening facts until the next change)."""
    facts = discovery.announced_facts(session)
    if not facts:
        return []
    in_effect = new_facts(facts, load_kg=None, set_number=None, next_set=False, exercise=None, athlete=None)
    events = [_counted_set_event(in_effect, record) for record in facts.get(SETS_COUNTED) or []]
    if not events or events[-1].set_number != in_effect.set_number:
        events.append(in_effect)
    rep_under_way = isinstance(facts.get(REP_START), (int, float))
    if rep_under_way:
        events[-1].set_rep_start_s = float(facts[REP_START])
    if facts.get("resting") and not events[-1].HasField("set_end_s") and not rep_under_way:
        events.append(set_mark_event(in_effect, int(in_effect.set_number), "stop"))
    return events


def _counted_set_event(in_effect: messages.LoadEvent, record: dict) -> messages.LoadEvent:
    """The facts in effect naming one set as msk live counted it: the page keeps its clock, its reps and its end."""
    event = messages.LoadEvent()
    event.CopyFrom(in_effect)
    event.set_number = int(record["number"])
    event.set_start_s = float(record["start_s"])
    event.set_started_by = str(record.get("started_by", ""))
    event.set_rep_spans_s.extend(float(x) for span in record["rep_spans"] for x in span)
    if record.get("end_s") is not None:
        event.set_end_s, event.set_ended_by = float(record["end_s"]), str(record.get("ended_by", ""))
    return event


def join_late(inputs: NodeInputs, session: str) -> str:
    """A page that starts while ``session`` runs (the view, the dashboard): the facts msk live published before it,
    then those in effect now as announced here (:func:`announced_events`), queued on ``inputs``; returns the
    exercise the session announces it estimates ("" when it announces none here), for
    :attr:`LoadEventGate.session_exercise`."""
    inputs.fetch_session_facts(session, current=lambda: announced_events(session))
    info = discovery.announced(session)
    return info.pack if info is not None else ""
