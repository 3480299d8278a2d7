"""HistoryMerge: the order and the once-only rule a restarted recorder writes by, without a network."""

from __future__ import annotations

from services import messages
from services.recorder import HISTORY, LIVE, HistoryMerge, RecorderStats, _digest, _FetchDone, _Item

EMG = "msk/s1/emg/trigno"
ACTIVATIONS = "msk/s1/activations/so"


def _chunk(index: int) -> bytes:
    return messages.encode(messages.EmgChunk(source_id="trigno", first_sample_index=27 * index, n_samples=27))


def _item(origin: str, key: str, index: int) -> _Item:
    return _Item(origin, 0, key, "msk.EmgChunk", _chunk(index))


def _written_indices(written: list[_Item], key: str = EMG) -> list[int]:
    return [messages.decode("msk.EmgChunk", item.payload).first_sample_index // 27 for item in written if item.key == key]


def test_live_samples_wait_for_the_first_fetch_and_what_both_delivered_is_written_once():
    written: list[_Item] = []
    stats = RecorderStats()
    earlier_part = {EMG: {_digest(_chunk(i)) for i in range(0, 5)}}  # the killed file holds 0..4
    merge = HistoryMerge(written.append, stats, already_recorded=earlier_part)
    merge.begin_fetch("msk/**", initial=True)
    for index in (9, 10, 11):  # live, while the caches are being asked
        assert merge.accept(_item(LIVE, EMG, index), fetch_new_keys=True) == []
    assert merge.accept(_item(LIVE, ACTIVATIONS, 0), fetch_new_keys=False) == []
    assert written == []
    for index in range(0, 11):  # the cache: 0..10, of which 0..4 are in the earlier part, 9..10 came live too
        merge.accept(_item(HISTORY, EMG, index), fetch_new_keys=False)
    merge.accept(_FetchDone("msk/**", []), fetch_new_keys=False)
    assert _written_indices(written) == list(range(5, 12))
    assert _written_indices(written, ACTIVATIONS) == [0]
    assert stats.already_recorded == 5 + 2 and stats.history_fetched == 11 and stats.history_fetches == 1
    merge.accept(_item(LIVE, EMG, 12), fetch_new_keys=True)  # a known key: written at once, no new fetch
    assert _written_indices(written)[-1] == 12


def test_a_key_that_appears_later_is_fetched_on_its_first_live_sample_and_the_arrival_order_is_kept():
    written: list[_Item] = []
    merge = HistoryMerge(written.append, RecorderStats())
    merge.accept(_FetchDone("msk/**", []), fetch_new_keys=False)  # nothing published yet at the start
    late, other = "msk/s1/emg/second", "msk/s1/emg/third"
    assert merge.accept(_item(LIVE, late, 3), fetch_new_keys=True) == [late]  # published 0..2 before we were seen
    assert merge.accept(_item(LIVE, late, 4), fetch_new_keys=True) == []  # one fetch per key
    assert merge.accept(_item(LIVE, other, 0), fetch_new_keys=True) == [other]  # another new key, its own fetch
    assert merge.accept(_item(LIVE, ACTIVATIONS, 0), fetch_new_keys=True) == []  # keeps no history: no fetch
    assert written == []  # everything waits while a fetch is out: the file keeps the arrival order across keys
    for index in range(0, 4):
        merge.accept(_item(HISTORY, late, index), fetch_new_keys=False)
    merge.accept(_FetchDone(late, []), fetch_new_keys=False)
    assert _written_indices(written, late) == [0, 1, 2, 3]  # its cache; the live samples wait for the other fetch
    merge.accept(_FetchDone(other, []), fetch_new_keys=False)
    assert [item.key for item in written[4:]] == [late, other, ACTIVATIONS]  # live 3 came from the cache already
    assert _written_indices(written, late) == [0, 1, 2, 3, 4]


def test_samples_still_held_when_the_recorder_stops_are_written():
    written: list[_Item] = []
    stats = RecorderStats()
    merge = HistoryMerge(written.append, stats)
    merge.begin_fetch("msk/**", initial=True)
    merge.accept(_item(LIVE, EMG, 7), fetch_new_keys=True)
    merge.accept(_FetchDone("msk/**", ["denied"]), fetch_new_keys=False)  # a fetch that failed still ends
    merge.accept(_item(LIVE, EMG, 8), fetch_new_keys=True)
    assert stats.history_errors == 1 and _written_indices(written) == [7, 8]
    merge.begin_fetch("msk/s1/emg/other")
    merge.accept(_item(LIVE, "msk/s1/emg/other", 1), fetch_new_keys=True)
    merge.release_all()
    assert _written_indices(written, "msk/s1/emg/other") == [1]


def test_the_remembered_digests_are_bounded_per_key():
    written: list[_Item] = []
    merge = HistoryMerge(written.append, RecorderStats(), remembered_per_key=3)
    for index in range(5):
        merge.accept(_item(LIVE, EMG, index), fetch_new_keys=False)
    merge.accept(_item(LIVE, EMG, 4), fetch_new_keys=False)  # remembered: dropped
    merge.accept(_item(LIVE, EMG, 0), fetch_new_keys=False)  # forgotten (older than 3 back): written again
    assert _written_indices(written) == [0, 1, 2, 3, 4, 0]
