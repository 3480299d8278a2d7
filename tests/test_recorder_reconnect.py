"""A recorder that loses its router for a while (restarted, or the network between them down) fetches the publications
it missed from the device publishers' caches when it hears them again (services/nodes/recorder.py, "Reconnection"): once
each, before the live samples after them; what the caches no longer hold is counted lost. The merge without a network,
then a real router closed and opened again on loopback (tests/test_hosts.py does it across network namespaces)."""

from __future__ import annotations

import threading
import time

from services.nodes import recorder
from services.nodes.recorder import HISTORY, LIVE, HistoryMerge, Missing, RecorderStats, _Fetched, _Item
from services.transport import messages, topics
from services.transport.mcap_io import read_messages
from services.transport.zenoh_session import ZenohOptions, declare_history_publisher, open_session, publish

EMG = topics.emg_key("rc", "trigno")
ACTIVATIONS = topics.activations_key("rc", "so")
PUBLISHER = ("0123abcd", 6)


def _chunk(index: int) -> messages.EmgChunk:
    return messages.EmgChunk(source_id="trigno", channel_labels=["c1"], sample_rate_hz=2000.0, n_samples=1,
                             n_channels=1, samples=[0.0], first_sample_index=index, host_time_ns=index + 1)  # fmt: skip


def _item(origin: str, index: int, missed: int = 0, key: str = EMG) -> _Item:
    chunk = _chunk(index)
    return _Item(origin, index, key, messages.encode(chunk), chunk, None, (*PUBLISHER, index), missed)


def test_publications_skipped_live_are_fetched_and_written_before_the_live_ones_after_them():
    written: list[_Item] = []
    stats = RecorderStats()
    merge = HistoryMerge(written.append, stats)
    merge.begin_fetch("msk/**", initial=True)
    for index in range(3):
        merge.accept(_item(LIVE, index), fetch_new_keys=True)
    merge.accept(_Fetched("msk/**", (), [], 0), fetch_new_keys=False)  # the start: nothing in the caches yet
    assert merge.take_missing(EMG) == []
    # the router was away: numbers 3..9 never came; 10 shows it
    assert merge.accept(_item(LIVE, 10, missed=7), fetch_new_keys=True) == [EMG]
    assert merge.accept(_item(LIVE, 11), fetch_new_keys=True) == []
    assert merge.accept(_item(LIVE, 0, key=ACTIVATIONS), fetch_new_keys=True) == []
    assert merge.take_missing(EMG) == [Missing(PUBLISHER, 3, 9)]
    assert [i.first_sample_index for i in (it.message for it in written[-3:])] == [0, 1, 2]  # the rest wait
    # the cache no longer holds 3 and 4 (its oldest went); it holds 5..9, one of them twice in the replies
    history = tuple(_item(HISTORY, i) for i in (5, 6, 6, 7, 8, 9))
    assert merge.accept(_Fetched(EMG, history, [], 20, (Missing(PUBLISHER, 3, 9),)), fetch_new_keys=False) == []
    emg = [item.message.first_sample_index for item in written if item.key == EMG]
    assert emg == [0, 1, 2, 5, 6, 7, 8, 9, 10, 11]
    assert written[-1].key == ACTIVATIONS  # the arrival order of the live samples is kept
    assert stats.missed == 7 and stats.recovered == 5 and stats.unrecovered == {EMG: 2}
    assert "missed 7 publications live, fetched 5 of them again" in recorder.summary_line(stats, "x.mcap")


def test_a_gap_seen_while_stopping_is_counted_lost():
    stats = RecorderStats()
    merge = HistoryMerge(lambda item: None, stats)
    merge.begin_fetch("msk/**", initial=True)
    merge.accept(_item(LIVE, 0), fetch_new_keys=True)
    merge.accept(_Fetched("msk/**", (), [], 0), fetch_new_keys=False)
    assert merge.accept(_item(LIVE, 5, missed=4), fetch_new_keys=False) == []
    assert stats.missed == 4 and stats.unrecovered == {EMG: 4} and stats.recovered == 0


def test_a_recorder_gets_back_what_was_published_while_its_router_was_away(tmp_path, zenoh_endpoint):
    router_options = ZenohOptions(mode="router", listen=(zenoh_endpoint,))
    client = ZenohOptions(mode="client", connect=(zenoh_endpoint,))
    out = tmp_path / "rec.mcap"
    stop, ready = threading.Event(), threading.Event()
    stats = RecorderStats()
    published = 0
    router = open_session(router_options)
    try:
        with open_session(client) as driver:
            publisher = declare_history_publisher(driver, EMG, "msk.EmgChunk")
            thread = threading.Thread(
                target=recorder.main,
                args=(client, out),
                kwargs={"stop_event": stop, "ready_event": ready, "stats": stats, "session": "rc"},
            )
            thread.start()
            assert ready.wait(30), "the recorder did not start within 30 s"

            def run(seconds: float) -> None:
                nonlocal published
                until = time.monotonic() + seconds
                while time.monotonic() < until:
                    publish(publisher, _chunk(published))
                    published += 1
                    time.sleep(0.01)

            run(1.5)
            router.close()  # the router goes; the driver goes on publishing into its cache
            run(1.5)
            router = open_session(router_options)
            deadline = time.monotonic() + 30
            while stats.recovered < stats.missed or stats.missed == 0:  # reconnected, the gap seen and fetched
                assert time.monotonic() < deadline, f"waited 30 s for the gap to be fetched: {stats}"
                run(0.2)
            run(0.5)
            time.sleep(1.0)
            stop.set()
            thread.join(30)
    finally:
        router.close()
    print(f"published {published}; {recorder.summary_line(stats, out)}")
    indices = [m.decode(messages.EmgChunk).first_sample_index for m in read_messages(out) if m.topic == EMG]
    # every publication once, in order; those published while the router was away came from the cache
    assert indices == list(range(published)), (len(indices), published, stats)
    assert stats.missed > 50 and stats.recovered == stats.missed and not stats.unrecovered, stats
