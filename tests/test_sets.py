"""The set logic (msk_core.signal.sets.SetTracker): rest detection, operator marks, per-set figures."""

from __future__ import annotations

import math

import numpy as np
import pytest

from msk_core.errors import ConfigError
from msk_core.signal.reps import REST_PHASE, PhaseRepCounter
from msk_core.signal.sets import DEFAULT_REST_S, SetTracker

RATE_HZ = 50.0


def stream(pattern: list[tuple[str, float]], t0: float = 0.0) -> list[tuple[float, float]]:
    """(time, phase) samples at RATE_HZ: ("rest", seconds) or ("rep", seconds) pieces, in order."""
    out, t = [], t0
    for kind, seconds in pattern:
        n = int(round(seconds * RATE_HZ))
        for k in range(n):
            out.append((t, k / n if kind == "rep" else REST_PHASE))
            t += 1.0 / RATE_HZ
    return out


def feed(tracker: SetTracker, samples: list[tuple[float, float]]) -> None:
    for t, p in samples:
        tracker.update(t, p)


def test_rest_detection_splits_sets_at_the_stated_rest_and_counts_reps_per_set():
    samples = stream(
        [("rest", 2), ("rep", 2), ("rep", 2), ("rep", 2), ("rest", 25), ("rep", 2), ("rep", 2), ("rest", 5)]
    )
    tracker = SetTracker(rest_s=DEFAULT_REST_S)
    reps_seen = []
    for t, p in samples:
        tracker.update(t, p)
        reps_seen.append((tracker.number, tracker.rep, tracker.resting))
    assert (1, 1, False) in reps_seen and (1, 3, False) in reps_seen and (2, 2, False) in reps_seen
    # 20 s after the third rep ended the set is over, before the next rep: resting, set 1 shown
    rest_t = next(i for i, (t, _) in enumerate(samples) if t > 8.0 + DEFAULT_REST_S + 0.1)
    assert reps_seen[rest_t] == (1, 0, True)
    tracker.finish()
    first, second = tracker.sets
    assert (first.number, len(first.reps), first.started_by, first.ended_by) == (1, 3, "rep", "rest")
    assert first.start_s == pytest.approx(2.0) and first.end_s == pytest.approx(8.0, abs=0.05)
    assert first.time_under_tension_s == pytest.approx(6.0, abs=0.1)
    assert (second.number, len(second.reps), second.ended_by) == (2, 2, "end of data")
    assert second.start_s == pytest.approx(33.0) and second.end_s == pytest.approx(37.0, abs=0.05)  # its last rep


def test_a_shorter_rest_than_stated_keeps_one_set():
    samples = stream([("rep", 2), ("rest", 10), ("rep", 2), ("rest", 1)])
    tracker = SetTracker(rest_s=12.0)
    feed(tracker, samples)
    tracker.finish()
    assert [len(s.reps) for s in tracker.sets] == [2]
    tracker = SetTracker(rest_s=8.0)
    feed(tracker, samples)
    tracker.finish()
    assert [len(s.reps) for s in tracker.sets] == [1, 1]


def test_a_rep_that_does_not_count_opens_no_set():
    tracker = SetTracker()
    blip = stream([("rest", 1), ("rep", 0.1)])
    feed(tracker, blip)
    assert tracker.number == 1 and tracker.rep == 1  # shown at once, as the rep starts
    feed(tracker, stream([("rest", 1)], t0=1.1))
    assert tracker.sets == [] and tracker.number == 0 and tracker.rep == 0
    tracker.finish()
    assert tracker.sets == []


def test_operator_start_and_stop_mark_the_set_and_a_rep_under_way_is_not_counted():
    tracker = SetTracker(rest_s=5.0)
    samples = stream([("rest", 1), ("rep", 2), ("rep", 2), ("rest", 2)])
    tracker.start(0.5, 3)  # the operator numbers it
    feed(tracker, samples[:160])  # 3.2 s: the first rep done, the second under way
    assert (tracker.number, tracker.rep) == (3, 2)
    tracker.stop(3.2)  # stopped during the second rep: it is not counted and opens no set when it ends
    assert tracker.resting and tracker.rep == 0
    feed(tracker, samples[160:])
    tracker.finish()
    (only,) = tracker.sets
    assert (only.number, only.start_s, only.end_s, only.started_by, only.ended_by) == (
        3,
        0.5,
        3.2,
        "operator",
        "operator",
    )
    assert len(only.reps) == 1
    # an operator's set without reps is not ended by rest detection (the athlete gets ready)
    tracker = SetTracker(rest_s=5.0)
    tracker.start(0.0)
    feed(tracker, stream([("rest", 30)]))
    assert not tracker.resting and tracker.number == 1


def test_session_facts_map_onto_marks():
    tracker = SetTracker()
    tracker.on_facts(0.0, set_number=1, set_mark="", mass_kg=60.0)  # msk live's facts at start: set 1
    assert tracker.number == 1 and not tracker.resting
    tracker.on_facts(1.0, set_number=1, set_mark="", mass_kg=62.5)  # a load correction: same set
    assert len(tracker.sets) == 1
    tracker.on_facts(2.0, set_number=2, set_mark="", mass_kg=62.5)  # msk load --next-set
    assert [s.number for s in tracker.sets] == [1, 2] and tracker.sets[0].ended_by == "next set"
    tracker.on_facts(3.0, set_number=2, set_mark="stop", mass_kg=62.5, rest_s=30.0)
    assert tracker.resting and tracker.rest_s == 30.0
    tracker.on_facts(4.0, set_number=2, set_mark="start", mass_kg=62.5)  # a stale number: the next set
    assert tracker.number == 3
    tracker.on_facts(5.0, set_number=0, set_mark="", mass_kg=0.0)  # the bar is off
    assert tracker.resting
    with pytest.raises(ConfigError, match="set_mark"):
        tracker.on_facts(6.0, set_number=0, set_mark="begin", mass_kg=0.0)
    with pytest.raises(ConfigError, match="rest_s"):
        SetTracker(rest_s=0.0)


def test_peak_and_mean_are_over_the_frames_inside_the_sets_reps():
    tracker = SetTracker(rest_s=3.0)
    groups = ("A", "B")
    for t, p in stream([("rest", 1), ("rep", 2), ("rest", 1)]):
        tracker.update(t, p)
        inside = p >= 0
        tracker.add_activations(t, p, groups, [0.5 + 0.2 * p if inside else 0.9, 0.1 if inside else math.nan])
    tracker.finish()
    (only,) = tracker.sets
    assert only.peak[0] == pytest.approx(0.5 + 0.2 * 0.99) and only.peak[1] == 0.1  # the 0.9 at rest is not counted
    assert only.mean[0] == pytest.approx(0.5 + 0.2 * np.mean(np.arange(100) / 100))
    assert only.mean[1] == pytest.approx(0.1)
    figures = only.as_dict()
    assert figures["reps"] == 1 and figures["groups"] == ["A", "B"] and figures["time_under_tension_s"] > 1.9


def test_reps_over_all_sets_are_the_segmenters():
    """Without operator marks the sets' reps add up to what msk_core.signal.reps.PhaseRepCounter counts."""
    rng = np.random.default_rng(30)
    pattern = []
    for _ in range(60):
        pattern.append(("rep", float(rng.uniform(0.1, 3.0))))
        pattern.append(("rest", float(rng.choice([0.02, 0.5, 4.0, 12.0]))))
    samples = stream(pattern)
    tracker, counter = SetTracker(rest_s=10.0), PhaseRepCounter()
    for t, p in samples:
        tracker.update(t, p)
        counter.update(t, p)
    tracker.finish()
    counter.finish()
    assert sum(len(s.reps) for s in tracker.sets) == counter.count > 30
    assert len(tracker.sets) > 3 and all(s.reps for s in tracker.sets)
    assert all(a.end_s is not None and a.end_s <= b.start_s for a, b in zip(tracker.sets, tracker.sets[1:]))


def test_a_rep_whose_data_comes_after_the_operators_stop_belongs_to_the_set_it_stopped():
    """Live, the operator's mark can arrive before the phase stream reaches its instant (a lagging estimator): a rep
    that started before the stop counts in the stopped set and opens no new one."""
    tracker = SetTracker()
    samples = stream([("rest", 1), ("rep", 2), ("rest", 1), ("rep", 2), ("rest", 3)])
    tracker.start(0.5)
    feed(tracker, samples[:200])  # up to 4 s: one rep done, at rest
    tracker.stop(6.5)  # the operator's stop, stamped 6.5 s, arrives now
    feed(tracker, samples[200:])  # the second rep (4-6 s) arrives after it
    tracker.finish()
    (only,) = tracker.sets
    assert len(only.reps) == 2 and only.end_s == 6.5 and only.ended_by == "operator"
    # all marks first (a fast replay), the data after: each rep in the set that held it, none in the declared rest
    tracker = SetTracker()
    samples = stream([("rest", 1), ("rep", 2), ("rest", 2), ("rep", 2), ("rest", 2), ("rep", 2), ("rest", 1)])
    tracker.start(0.5)
    tracker.stop(3.5)  # set 1: the first rep (1-3 s); the second (5-7 s) in the rest
    tracker.start(8.5)  # set 2: the third (9-11 s)
    feed(tracker, samples)
    tracker.finish()
    assert [(s.number, len(s.reps)) for s in tracker.sets] == [(1, 1), (2, 1)]


def test_a_start_mark_as_the_first_rep_begins_takes_the_place_of_the_set_that_rep_opened():
    """After a rest, the first rep opens the next set (not counted yet); the operator presses start just then: that
    set is the one meant (it was 4 after set 2, with no set 3 anywhere), and the button's number says the same."""
    from services.sessions.facts import set_mark_event
    from services.transport import messages

    tracker = SetTracker()
    tracker.on_facts(0.0, set_number=1, set_mark="", mass_kg=50)
    t = 0.0
    for _rep in range(2):  # set 1: two reps
        for k in range(50):
            tracker.update(t, k / 50)
            t += 0.04
        tracker.update(t, -1.0)
        t += 0.5
    tracker.on_facts(t, set_number=1, set_mark="stop", mass_kg=50)
    for k in range(30):  # the rest, then the first rep of set 2 begins
        tracker.update(t + 0.1 * k, -1.0)
    t += 3.0
    for k in range(3):
        tracker.update(t + 0.04 * k, k / 50)
    assert tracker.number == 2 and tracker.settled == (1, True)  # opened by the rep, not counted yet
    mark = set_mark_event(messages.LoadEvent(barbell_mass_kg=50, set_number=1), tracker.settled[0], "start")
    assert mark.set_number == 2
    tracker.on_facts(t + 0.1, set_number=int(mark.set_number), set_mark="start", mass_kg=50)
    assert [s.number for s in tracker.sets] == [1, 2] and tracker.sets[-1].started_by == "operator"


def _feed_phase(tracker: SetTracker, t0: float, t1: float, phase) -> None:
    """Samples at 50 Hz from ``t0`` to ``t1``, phase ``phase(t)`` (>= 0 in a rep, -1 at rest)."""
    t = t0
    while t < t1 - 1e-9:
        tracker.update(round(t, 2), phase(t))
        t += 0.02


def test_a_rep_counted_before_the_facts_came_goes_to_the_set_that_holds_its_start():
    """A page that joined in set 2 counted the end of its rep, then the facts: set 1 took that rep (3 reps)."""
    page = SetTracker()
    _feed_phase(page, 32.0, 33.0, lambda t: t - 32.0)
    _feed_phase(page, 33.0, 33.2, lambda t: -1.0)
    page.on_facts(0.0, set_number=1, set_mark="", mass_kg=60)  # the opening facts
    page.on_facts(
        None, set_number=1, set_mark="", mass_kg=60, set_start_s=0.0, rep_spans=[(1.0, 2.98), (4.0, 5.98)],
        set_end_s=5.98, set_ended_by="rest",
    )  # fmt: skip
    page.on_facts(None, set_number=2, set_mark="", mass_kg=60, set_start_s=31.0, rep_spans=[(31.0, 32.98)])
    assert [(s.number, s.start_s, s.end_s, s.reps) for s in page.sets] == [
        (1, 0.0, 5.98, [(1.0, 2.98), (4.0, 5.98)]),
        (2, 31.0, None, [(31.0, 32.98)]),  # one rep, seen by both, from where the session saw it start
    ]


@pytest.mark.parametrize("join_s", [10.5, 11.8])
def test_a_page_that_joins_during_a_sets_first_rep_counts_it_from_its_start(join_s):
    """The set that rep opens had not counted yet, so no set was announced; the page counted the rep from the join
    (or, joining late in it, not at all: shorter than a rep)."""
    session, page = SetTracker(), SetTracker()
    _feed_phase(session, 0.0, 10.0, lambda t: -1.0)
    _feed_phase(session, 10.0, join_s, lambda t: (t - 10.0) / 2)
    page.on_facts(None, set_number=0, set_mark="", mass_kg=0, rep_start_s=session.rep_start_s)
    for tracker in (session, page):
        _feed_phase(tracker, join_s, 12.0, lambda t: (t - 10.0) / 2)
        _feed_phase(tracker, 12.0, 13.0, lambda t: -1.0)
        tracker.finish()
    assert [(s.number, s.start_s, s.reps) for s in page.sets] == [(s.number, s.start_s, s.reps) for s in session.sets]
    assert len(page.sets) == 1 and page.sets[0].reps == [(10.0, 11.98)]


def test_facts_that_come_again_do_not_move_a_later_rep_back():
    page = SetTracker()
    page.on_facts(0.0, set_number=1, set_mark="", mass_kg=60)
    announced = dict(set_number=1, set_mark="", mass_kg=60, set_start_s=0.0, rep_spans=[], rep_start_s=1.0)
    page.on_facts(None, **announced)
    _feed_phase(page, 2.0, 3.0, lambda t: (t - 1.0) / 2)
    _feed_phase(page, 3.0, 4.0, lambda t: -1.0)
    _feed_phase(page, 4.0, 4.2, lambda t: (t - 4.0) / 2)
    page.on_facts(None, **announced)  # the same announcement once more, 0.2 s into rep 2
    _feed_phase(page, 4.2, 6.0, lambda t: (t - 4.0) / 2)
    _feed_phase(page, 6.0, 7.0, lambda t: -1.0)
    assert page.sets[0].reps == [(1.0, 2.98), (4.0, 5.98)]
