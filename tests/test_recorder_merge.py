"""HistoryMerge: the order and the once-only rule a restarted recorder writes by, without a network."""

from __future__ import annotations

from services.nodes.recorder import HISTORY, LIVE, HistoryMerge, RecorderStats, _digest, _Fetched, _Item
from services.transport import messages
from tests.conftest import emg_chunk

EMG = "msk/s1/emg/trigno"
ACTIVATIONS = "msk/s1/activations/so"


def _message(index: int) -> messages.EmgChunk:
    return emg_chunk(index, n_samples=1)


def _chunk(index: int) -> bytes:
    return messages.encode(_message(index))


def _item(origin: str, key: str, index: int, receive_ns: int = 0) -> _Item:
    return _Item(origin, receive_ns, key, _chunk(index), _message(index))


def _fetched(scope: str, items: list[_Item], errors: list[str] | None = None, finished_ns: int = 10) -> _Fetched:
    return _Fetched(scope, tuple(items), errors or [], finished_ns)


def _written_indices(written: list[_Item], key: str = EMG) -> list[int]:
    return [
        messages.decode("msk.EmgChunk", item.payload).first_sample_index // 27 for item in written if item.key == key
    ]


def test_live_samples_wait_for_the_first_fetch_and_what_both_delivered_is_written_once():
    written: list[_Item] = []
    stats = RecorderStats()
    earlier_part = {EMG: [_digest(_chunk(i)) for i in range(0, 5)]}  # the killed file holds 0..4
    merge = HistoryMerge(written.append, stats, already_recorded=earlier_part)
    merge.begin_fetch("msk/**", initial=True)
    for index in (9, 10, 11):  # live, while the caches are being asked
        assert merge.accept(_item(LIVE, EMG, index), fetch_new_keys=True) == []
    assert merge.accept(_item(LIVE, ACTIVATIONS, 0), fetch_new_keys=False) == []
    assert written == []
    # the cache: 0..10, of which 0..4 are in the earlier part, 9..10 came live too
    merge.accept(_fetched("msk/**", [_item(HISTORY, EMG, i) for i in range(0, 11)]), fetch_new_keys=False)
    assert _written_indices(written) == list(range(5, 12))
    assert [item.origin for item in written if item.key == EMG] == [HISTORY] * 4 + [LIVE] * 3  # live copies kept
    assert _written_indices(written, ACTIVATIONS) == [0]
    assert stats.already_recorded == 5 + 2 and stats.history_fetched == 11 and stats.history_fetches == 1
    merge.accept(_item(LIVE, EMG, 12), fetch_new_keys=True)  # a known key: written at once, no new fetch
    assert _written_indices(written)[-1] == 12


def test_a_key_that_appears_later_is_fetched_on_its_first_live_sample_and_the_arrival_order_is_kept():
    written: list[_Item] = []
    merge = HistoryMerge(written.append, RecorderStats())
    merge.accept(_fetched("msk/**", []), fetch_new_keys=False)  # nothing published yet at the start
    late, other = "msk/s1/emg/second", "msk/s1/emg/third"
    assert merge.accept(_item(LIVE, late, 3), fetch_new_keys=True) == [late]  # published 0..2 before we were seen
    assert merge.accept(_item(LIVE, late, 4), fetch_new_keys=True) == []  # one fetch per key
    assert merge.accept(_item(LIVE, other, 0), fetch_new_keys=True) == [other]  # another new key, its own fetch
    assert merge.accept(_item(LIVE, ACTIVATIONS, 0), fetch_new_keys=True) == []  # keeps no history: no fetch
    assert written == []  # everything waits while a fetch is out: the file keeps the arrival order across keys
    merge.accept(_fetched(late, [_item(HISTORY, late, i) for i in range(0, 4)]), fetch_new_keys=False)
    assert _written_indices(written, late) == [0, 1, 2]  # its cache less live 3; the live samples wait for the other
    merge.accept(_fetched(other, []), fetch_new_keys=False)
    assert [item.key for item in written[3:]] == [late, late, other, ACTIVATIONS]
    assert _written_indices(written, late) == [0, 1, 2, 3, 4]


def test_samples_still_held_when_the_recorder_stops_are_written():
    written: list[_Item] = []
    stats = RecorderStats()
    merge = HistoryMerge(written.append, stats)
    merge.begin_fetch("msk/**", initial=True)
    merge.accept(_item(LIVE, EMG, 7), fetch_new_keys=True)
    merge.accept(_fetched("msk/**", [], ["denied"]), fetch_new_keys=False)  # a fetch that failed still ends
    merge.accept(_item(LIVE, EMG, 8), fetch_new_keys=True)
    assert stats.history_errors == 1 and _written_indices(written) == [7, 8]
    merge.begin_fetch("msk/s1/emg/other")
    merge.accept(_item(LIVE, "msk/s1/emg/other", 1), fetch_new_keys=True)
    merge.release_all()
    assert _written_indices(written, "msk/s1/emg/other") == [1]


def test_identical_live_messages_are_all_written():
    """A publisher that leaves host_time_ns unset sends byte-identical valid messages: each is a message."""
    written: list[_Item] = []
    stats = RecorderStats()
    merge = HistoryMerge(written.append, stats, already_recorded={EMG: [_digest(_chunk(0))]})
    merge.accept(_fetched("msk/**", []), fetch_new_keys=False)
    for _ in range(10):
        merge.accept(_item(LIVE, EMG, 0, receive_ns=20), fetch_new_keys=True)  # the first one asks EMG's cache
    merge.accept(_fetched(EMG, [], finished_ns=10), fetch_new_keys=False)  # an empty cache
    for _ in range(10):
        merge.accept(_item(LIVE, EMG, 0, receive_ns=30), fetch_new_keys=True)
    assert _written_indices(written) == [0] * 20 and stats.already_recorded == 0


def test_identical_copies_are_matched_one_for_one_with_the_earlier_parts_and_the_live_overlap():
    """The cache holds 8 identical messages: 2 are in the earlier part (its oldest), 3 also came live before the
    fetch returned (its newest); the 3 between are new. A live one received after the fetch returned is new too."""
    written: list[_Item] = []
    stats = RecorderStats()
    merge = HistoryMerge(written.append, stats, already_recorded={EMG: [_digest(_chunk(0))] * 2})
    merge.begin_fetch("msk/**", initial=True)
    for receive_ns in (1, 2, 3, 11):
        merge.accept(_item(LIVE, EMG, 0, receive_ns), fetch_new_keys=True)
    merge.accept(_fetched("msk/**", [_item(HISTORY, EMG, 0) for _ in range(8)], finished_ns=10), fetch_new_keys=False)
    assert [item.origin for item in written] == [HISTORY] * 3 + [LIVE] * 4
    assert stats.already_recorded == 2 + 3 and stats.history_fetched == 8


def test_a_live_copy_held_takes_its_history_samples_place_so_the_file_keeps_publishing_order():
    """The cache's answer overtook the data: it holds 0..3 while only 2 arrived live before it returned (3 arrives
    after). The file holds 0, 1, 2 (its live copy, in place), 3 (from the cache), then 4: each once, in order."""
    publisher = ("zid-1", 7)

    def sourced(origin: str, index: int, receive_ns: int = 0) -> _Item:
        return _Item(origin, receive_ns, EMG, _chunk(index), _message(index), source=(*publisher, index))

    written: list[_Item] = []
    stats = RecorderStats()
    merge = HistoryMerge(written.append, stats)
    merge.begin_fetch("msk/**", initial=True)
    merge.accept(sourced(LIVE, 2, receive_ns=5), fetch_new_keys=True)
    merge.accept(_item(LIVE, ACTIVATIONS, 0), fetch_new_keys=True)
    merge.accept(_fetched("msk/**", [sourced(HISTORY, i) for i in range(4)], finished_ns=10), fetch_new_keys=False)
    for index in (3, 4):  # 3 came with the cache's answer already: not written twice
        merge.accept(sourced(LIVE, index, receive_ns=20), fetch_new_keys=True)
    assert _written_indices(written) == [0, 1, 2, 3, 4]
    assert [item.origin for item in written if item.key == EMG] == [HISTORY, HISTORY, LIVE, HISTORY, LIVE]
    assert _written_indices(written, ACTIVATIONS) == [0]
    assert stats.already_recorded == 2  # the cache's copy of 2 and the live copy of 3


def test_a_publication_a_fetch_returns_twice_is_written_once():
    """Two caches (or one asked twice) answer with the same publications 0..2, of which 2 is also held live."""
    publisher = ("zid-1", 7)

    def sourced(origin: str, index: int) -> _Item:
        return _Item(origin, 0, EMG, _chunk(index), _message(index), source=(*publisher, index))

    written: list[_Item] = []
    stats = RecorderStats()
    merge = HistoryMerge(written.append, stats)
    merge.begin_fetch("msk/**", initial=True)
    merge.accept(sourced(LIVE, 2), fetch_new_keys=True)
    twice = [sourced(HISTORY, i) for i in range(3)] * 2
    merge.accept(_fetched("msk/**", twice), fetch_new_keys=False)
    assert _written_indices(written) == [0, 1, 2]
    assert [item.origin for item in written] == [HISTORY, HISTORY, LIVE]
    assert stats.already_recorded == 4 and stats.history_fetched == 6
