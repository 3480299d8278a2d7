"""Sets of a session: when each starts and ends, its reps, time under tension, and peak and mean activation per
muscle group. The one set logic of the project: the terminal view, the dashboard bridge and the session report each
feed a :class:`SetTracker` the same inputs and show what it says.

A set starts
  - when the operator starts one (``msk set start``, the view's key, the dashboard's button: a session fact with
    ``set_mark = "start"``; or a session fact naming another set number, as ``msk load --next-set`` does), or
  - without an operator, with the first rep after a rest: the set opens when that rep starts (shown at once) and is
    dropped again when the rep does not count (shorter than ``msk_core.signal.reps.MIN_REP_S``).

A set ends
  - when the operator ends it (``set_mark = "stop"``; a fact with no mass and no set number: the bar is off), when
    the next set starts, or at the end of the data, or
  - by rest detection: once it has a rep, no rep for ``rest_s`` (default :data:`DEFAULT_REST_S`, the session file's
    ``session.rest_s``). The set then ends where its last rep ended.

Reps are counted by the one segmenter (:class:`msk_core.signal.reps.PhaseRepCounter`) from the phase stream; after
the operator starts or ends a set, a rep under way is not counted (the count waits for the next rest sample). Marks
may arrive before the phase stream reaches their instant (a lagging estimator, a fast replay): a rep whose data comes
after a mark belongs to the set that held its start, and one inside a rest the marks declared opens no set.
Time under tension is the sum of the set's rep durations; peak and mean activation per group are taken over the
activation frames inside the set's reps (under tension), or over the whole set when the phase is unknown.
Explicit state, one sample at a time; no clock of its own (every time is the caller's, in seconds).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

from msk_core.errors import ConfigError
from msk_core.signal.reps import PhaseRepCounter

#: Rest detection: a set with reps ends after this long without one (s), unless the session says otherwise.
DEFAULT_REST_S = 20.0
#: A session fact further than this from the phase samples' times is not on their clock (a load event of another
#: clock, or none): it takes the newest sample's time.
MAX_FACT_GAP_S = 6 * 3600.0
#: The marks a session fact (``LoadEvent.set_mark``) may carry: none, the operator starts a set, ends it.
SET_MARKS = ("", "start", "stop")


#: :attr:`SetRecord.ended_by` of a set closed by :meth:`SetTracker.finish`
END_OF_DATA = "end of data"


def check_rest_s(rest_s: float, field_name: str = "rest_s") -> float:
    """A rest-detection time: finite and > 0 s."""
    if isinstance(rest_s, bool) or not isinstance(rest_s, (int, float)) or not (math.isfinite(rest_s) and rest_s > 0):
        raise ConfigError("must be a time > 0 s", field=field_name, value=rest_s)
    return float(rest_s)


@dataclass
class SetRecord:
    """One set: its number, start and end (None while under way), reps and activation figures."""

    number: int
    start_s: float
    # who started it: "operator" (a start mark: msk set start, the view's key, the dashboard's button), "session" (the
    # session's opening facts, e.g. msk live's set 1), "load event" (facts without a mark: msk load --next-set, a new
    # load) or "rep" (rest detection: the first rep after a rest)
    started_by: str
    end_s: float | None = None
    ended_by: str = ""  # "operator", "rest", "next set" or "end of data"; "" while under way
    reps: list[tuple[float, float]] = field(default_factory=list)  # (first, last sample time) of each rep
    groups: tuple[str, ...] = ()  # the groups of the activation figures (the first frame's)
    peak: list[float] = field(default_factory=list)  # per group, NaN until a frame counted
    _sum: list[float] = field(default_factory=list)
    _n: list[int] = field(default_factory=list)

    @property
    def time_under_tension_s(self) -> float:
        return float(sum(b - a for a, b in self.reps))

    @property
    def mean(self) -> list[float]:
        """Mean activation per group over the frames counted (NaN where none)."""
        return [s / n if n else math.nan for s, n in zip(self._sum, self._n)]

    def add(self, groups: Sequence[str], values: Sequence[float]) -> None:
        """One activation frame of the set (frames of other groups than the first one's are not mixed in)."""
        if not self.groups:
            self.groups = tuple(groups)
            self.peak, self._sum, self._n = [math.nan] * len(groups), [0.0] * len(groups), [0] * len(groups)
        if tuple(groups) != self.groups or len(values) != len(groups):
            return
        for i, v in enumerate(values):
            v = float(v)
            if math.isfinite(v):
                self.peak[i] = v if math.isnan(self.peak[i]) else max(self.peak[i], v)
                self._sum[i] += v
                self._n[i] += 1

    def as_dict(self) -> dict:
        """JSON-ready: number, times, reps, time under tension and per group peak and mean (None where unknown)."""
        return {
            "number": self.number,
            "start_s": self.start_s,
            "end_s": self.end_s,
            "started_by": self.started_by,
            "ended_by": self.ended_by,
            "reps": len(self.reps),
            "rep_spans": [list(r) for r in self.reps],
            "time_under_tension_s": self.time_under_tension_s,
            "groups": list(self.groups),
            "peak": [v if math.isfinite(v) else None for v in self.peak],
            "mean": [v if math.isfinite(v) else None for v in self.mean],
        }


class SetTracker:
    """Sets from operator marks and the phase stream (module doc). Feed in time order: :meth:`on_facts` (or
    :meth:`start` / :meth:`stop`), :meth:`update` per phase sample, :meth:`add_activations` per frame; :meth:`finish`
    at the end of the data. ``sets`` holds every set, the one under way last."""

    def __init__(self, rest_s: float = DEFAULT_REST_S) -> None:
        self.rest_s = check_rest_s(rest_s)
        self.sets: list[SetRecord] = []
        self._counter = PhaseRepCounter()
        self._wait_rest = False  # after an operator mark: the rep under way is not counted
        self._tentative = False  # the set under way was opened by a rep that has not counted yet
        self._last_t = -math.inf
        self._phase: float | None = None
        self._rep_began: float | None = None  # the start of the rep under way as another tracker saw it
        # operator marks that dropped the rep under way (start, stop): a consumer with reps of its own (the estimator's
        # fatigue index) drops its rep under way too, so both count the same reps
        self.reps_dropped = 0

    # ---- what the surfaces show ------------------------------------------------------------------------------------
    @property
    def _uncounted(self) -> bool:
        """The newest set was opened by a rep under way that has not counted yet (it may go again)."""
        return self._tentative and bool(self.sets) and not self.sets[-1].reps

    @property
    def current(self) -> SetRecord | None:
        """The set under way, None at rest."""
        return self.sets[-1] if self.sets and self.sets[-1].end_s is None else None

    @property
    def number(self) -> int:
        """The set under way, else the last one (0 before the first)."""
        return self.sets[-1].number if self.sets else 0

    @property
    def settled(self) -> tuple[int, bool]:
        """(set number, resting) leaving out a set that a rep opened and that has not counted yet (it may go again:
        what an announcement that others start from should say)."""
        if self._uncounted:
            return (self.sets[-2].number if len(self.sets) > 1 else 0), True
        return self.number, self.resting

    @property
    def rep(self) -> int:
        """Rep n of the set: the rep under way, else the last one done (0 at rest or before the first)."""
        current = self.current
        if current is None:
            return 0
        return len(current.reps) + (1 if self._counter.in_rep and not self._wait_rest else 0)

    @property
    def rep_start_s(self) -> float | None:
        """When the rep under way began (None between reps, or when it does not count: after an operator's mark)."""
        return None if self._wait_rest else self._counter.rep_start_s

    @property
    def resting(self) -> bool:
        return self.current is None

    def status(self, time_s: float | None = None) -> dict:
        """JSON-ready: set number, rep of the set, resting, time in the set (s, at ``time_s``), the set under way and
        every set done."""
        current = self.current
        return {
            "set": self.number,
            "rep": self.rep,
            "resting": current is None,
            "time_in_set_s": None if current is None or time_s is None else time_s - current.start_s,
            "rest_s": self.rest_s,
            "sets": [s.as_dict() for s in self.sets],
        }

    # ---- operator --------------------------------------------------------------------------------------------------
    def start(self, t: float, number: int = 0, by: str = "operator") -> None:
        """A set starts at ``t``: set ``number`` when it is after the last one, else the next; the set under way
        ends there; a set that a rep opened and that has not counted yet is replaced (the operator who presses start
        as the first rep begins means that set, not the one after it). ``by``: who started it
        (:attr:`SetRecord.started_by`)."""
        if self._uncounted:
            self.sets.pop()
        self._close(t, "next set")
        last = self.number
        self.sets.append(SetRecord(number if number > last else last + 1, t, by))
        self._tentative = False
        self._reset_reps()

    def stop(self, t: float) -> None:
        """The operator ends the set under way at ``t`` (nothing when at rest)."""
        self._close(t, "operator")
        self._reset_reps()

    def on_facts(
        self,
        t: float | None,
        *,
        set_number: int,
        set_mark: str,
        mass_kg: float,
        rest_s: float = 0.0,
        set_start_s: float | None = None,
        rep_spans: Sequence[tuple[float, float]] = (),
        set_end_s: float | None = None,
        set_ended_by: str = "",
        set_started_by: str = "",
        rep_start_s: float | None = None,
    ) -> None:
        """A session fact at ``t`` (``LoadEvent``: its time, None when it has none, set number, mark, barbell mass
        and rest-detection time, 0 for the one in effect; a time more than :data:`MAX_FACT_GAP_S` from the newest
        phase sample takes that sample's): "start" starts set ``set_number`` (or the next), "stop" ends the set; without a mark a
        new set number starts that set (``msk load --next-set``), a mass without a number the next set (a load
        change of an operator who does not number sets), and neither mass nor number ends the set (the bar is
        off); the same set number changes nothing.

        ``set_start_s``, ``set_started_by``, ``rep_spans``, ``set_end_s``, ``set_ended_by`` and ``rep_start_s``: set
        ``set_number`` as another tracker counted it (what ``msk live`` announces to a page that joins late,
        :meth:`counted`): its start and who made it, the reps it had (kept beside the reps counted here), once it
        ended when and by whom, and when the rep under way began, so the set's clock, reps, time under tension and
        end are the session's."""
        if set_mark not in SET_MARKS:
            raise ConfigError(f"must be one of {SET_MARKS}", field="set_mark", value=set_mark)
        if rest_s:
            self.rest_s = check_rest_s(rest_s, "set_rest_s")
        last = self._last_t if math.isfinite(self._last_t) else None
        if t is None or (last is not None and abs(t - last) > MAX_FACT_GAP_S):
            t = last if last is not None else 0.0
        if not set_mark and set_start_s is not None and math.isfinite(set_start_s):
            counted = SetRecord(set_number, float(set_start_s), set_started_by or "session", ended_by=set_ended_by)
            self._resume(counted, rep_spans, set_end_s)
            self._rep_begun(rep_start_s)
            return
        # facts without a mark start a set as the session's opening facts (before any set) or as a load event
        by = "load event" if self.sets else "session"
        if set_mark == "start":
            self.start(t, set_number)
        elif set_mark == "stop":
            self.stop(t)
        elif set_number > 0 and set_number != self.number:
            self.start(t, set_number, by)
        elif set_number == 0 and mass_kg > 0:
            self.start(t, by=by)
        elif set_number == 0 and mass_kg <= 0:
            self.stop(t)
        if not set_mark:
            self._rep_begun(rep_start_s)

    def counted(self) -> list[SetRecord]:
        """The sets, leaving out one that a rep opened and that has not counted yet (as :attr:`settled`): what a
        tracker that joins late takes, one set after the other (:meth:`on_facts`)."""
        if self._uncounted:
            return self.sets[:-1]
        return list(self.sets)

    # ---- data ------------------------------------------------------------------------------------------------------
    def update(self, t: float, phase: float | None) -> None:
        """The phase of the sample at ``t`` ([0, 1) inside a rep, negative at rest, None or NaN unknown)."""
        self._resume_after_end_of_data(t)
        self._last_t, self._phase = t, phase
        inside = phase is not None and phase >= 0.0  # NaN compares False
        if not inside:
            self._rep_began = None  # the rep another tracker saw under way has ended
        if self._wait_rest:
            if inside:
                return
            self._wait_rest = False
        done = self._counter.update(t, phase)
        self._begin_rep_early()
        current = self.current
        if done is not None:
            # a rep belongs to the set under way, else (data that came after the operator's mark) to the set that
            # held its start; one that starts after every set opens the next; one in a rest the marks declared is
            # dropped
            owner = current if current is not None and done[0] >= current.start_s else self._closed_set_at(done[0])
            if owner is None and current is None and not self._past(done[0]):
                owner = SetRecord(self.number + 1, done[0], "rep")
                self.sets.append(owner)
                current = owner
            if owner is not None:
                owner.reps.append(done)
            self._tentative = False
        elif current is not None and self._tentative and not self._counter.in_rep:
            self.sets.pop()  # the rep that opened it did not count
            self._tentative = False
            current = None
        start = self._counter.rep_start_s
        if current is None and start is not None and not self._past(start):
            self.sets.append(SetRecord(self.number + 1, start, "rep"))
            self._tentative = True
        elif (
            current is not None and current.reps and not self._counter.in_rep and t - current.reps[-1][1] >= self.rest_s
        ):
            self._close(current.reps[-1][1], "rest")

    def add_activations(self, t: float, phase: float | None, groups: Sequence[str], values: Sequence[float]) -> None:
        """An activation frame at ``t`` with its phase: counted in the set under way when inside a rep (or when the
        phase is unknown)."""
        current = self.current
        if current is None or t < current.start_s:
            return
        if phase is None or math.isnan(phase) or phase >= 0.0:
            current.add(groups, values)

    def finish(self, t: float | None = None) -> None:
        """End of the data: the rep under way counts if long enough, the set under way ends at its last rep's end
        when the data end at rest after it, else at ``t`` (default the last sample's time)."""
        under_way = self._counter.in_rep and not self._wait_rest
        done = None if self._wait_rest else self._counter.finish()
        current = self.current
        if current is not None and done is not None:
            current.reps.append(done)
            self._tentative = False
        if current is not None and self._tentative and not current.reps:
            self.sets.pop()
            current = None
        if current is not None:
            end = self._last_t if t is None else t
            if current.reps and not under_way:
                end = min(end, current.reps[-1][1])  # at rest since its last rep
            self._close(max(end, current.start_s), END_OF_DATA)

    # ---- inside ----------------------------------------------------------------------------------------------------
    def _resume_after_end_of_data(self, t: float) -> None:
        """Data after :meth:`finish` (a page closed the set when the estimator said it stopped, and the estimator was
        restarted): the set goes on when the data come back within ``rest_s`` of its end, as if never closed."""
        last = self.sets[-1] if self.sets else None
        if last is None or last.ended_by != END_OF_DATA or last.end_s is None:
            return
        if last.end_s <= t < last.end_s + self.rest_s:
            last.end_s, last.ended_by = None, ""

    def _resume(self, counted: SetRecord, spans: Sequence[tuple[float, float]], end_s: float | None) -> None:
        """A set as another tracker ``counted`` it (:meth:`on_facts`: its number, start, who started it and who
        ended it): it started at its ``start_s`` (the set under way here ended then), its reps ``spans`` are kept
        beside those counted here (one that overlaps a rep counted here is that rep) and it ended at ``end_s``.
        These are past instants, not a mark made now: the rep under way here still counts, in the set that holds its
        start."""
        number, start_s = counted.number, counted.start_s
        if self._uncounted:
            self.sets.pop()  # opened by the rep under way, which finds its set when it counts
            self._tentative = False
        record = next((r for r in reversed(self.sets) if r.number == number), None)
        if record is None:
            if self.sets and number < self.sets[-1].number:
                return  # older than the sets here: not one to add behind them
            self._close(start_s, "next set")
            record = SetRecord(number, start_s, counted.started_by)
            self.sets.append(record)
        for earlier in self.sets[: self.sets.index(record)]:
            # reps this tracker filed in an earlier set (counted before the facts came) that began in this one
            moved = [r for r in earlier.reps if r[0] >= start_s]
            earlier.reps = [r for r in earlier.reps if r[0] < start_s]
            record.reps += moved
            if earlier.end_s is not None and earlier.end_s > start_s:  # a set this one followed, ended here later
                earlier.end_s = max(earlier.start_s, start_s)
        record.reps = _merged([(float(a), float(b)) for a, b in spans] + record.reps)
        record.start_s = min([start_s] + [a for a, _ in record.reps])
        if record is self.current and end_s is not None and math.isfinite(end_s):
            self._close(max(float(end_s), record.start_s), counted.ended_by or "operator")

    def _rep_begun(self, rep_start_s: float | None) -> None:
        """Another tracker saw the rep under way begin at ``rep_start_s``: for the rep under way here, or the first
        this tracker sees; not for one after an operator's mark, nor when a rep counted here ended after it (facts
        that came twice, or late)."""
        if rep_start_s is None or not math.isfinite(rep_start_s) or self._wait_rest:
            return
        last_end = next((r.reps[-1][1] for r in reversed(self.sets) if r.reps), -math.inf)
        if rep_start_s > last_end:
            self._rep_began = float(rep_start_s)
            self._begin_rep_early()

    def _begin_rep_early(self) -> None:
        """The rep under way began when another tracker saw it begin (:meth:`on_facts`' ``rep_start_s``)."""
        if self._rep_began is not None and self._counter.in_rep:
            self._counter.began_at(self._rep_began)
            self._rep_began = None

    def _past(self, t: float) -> bool:
        """``t`` is before the end of the last set (data older than the operator's last mark)."""
        last = self.sets[-1] if self.sets else None
        return last is not None and last.end_s is not None and t < last.end_s

    def _closed_set_at(self, t: float) -> SetRecord | None:
        """The set that ended and held the instant ``t``."""
        for record in reversed(self.sets):
            if record.end_s is not None and record.start_s <= t < record.end_s:
                return record
        return None

    def _close(self, t: float, by: str) -> None:
        current = self.current
        if current is None:
            return
        if self._tentative and not current.reps:
            self.sets.pop()  # opened by a rep under way that never counted
        else:
            current.end_s, current.ended_by = t, by
        self._tentative = False

    def _reset_reps(self) -> None:
        self.reps_dropped += 1
        self._counter = PhaseRepCounter()
        self._rep_began = None
        self._wait_rest = self._phase is not None and self._phase >= 0.0


def _merged(spans: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Rep spans in time order, two that overlap being one rep seen by two trackers (its widest extent: one of them
    joined during it)."""
    out: list[tuple[float, float]] = []
    for a, b in sorted(spans):
        if out and a < out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out
