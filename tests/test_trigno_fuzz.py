"""Fuzzing the Trigno parsers (hypothesis): no crash, no hang, errors surface as ProtocolError and are counted."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.trigno import protocol as tp
from msk_core.errors import ProtocolError


@settings(max_examples=300, deadline=None)
@given(
    st.binary(max_size=2000),
    st.lists(st.integers(1, 300), min_size=1, max_size=10),
    st.sampled_from(list(tp.Endianness)),
)
def test_sample_decoder_any_bytes_any_split(data, cuts, endianness):
    decoder = tp.SampleDecoder(16, endianness)
    rows, position, k = [], 0, 0
    while position < len(data):
        size = cuts[k % len(cuts)]
        rows.append(decoder.feed(data[position : position + size]))
        position += size
        k += 1
    total = sum(len(r) for r in rows)
    assert total == len(data) // 64 and decoder.pending_bytes == len(data) % 64
    if total:
        expected = np.frombuffer(data[: total * 64], dtype=endianness.dtype).reshape(total, 16)
        got = np.concatenate(rows)
        assert np.array_equal(got.view(np.uint32), expected.astype(np.float32).view(np.uint32))


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=500), st.lists(st.integers(1, 50), min_size=1, max_size=10))
def test_reply_reader_and_reply_parsers_any_bytes(data, cuts):
    reader = tp.ReplyReader()
    replies, position, k = [], 0, 0
    while position < len(data):
        replies += reader.feed(data[position : position + cuts[k % len(cuts)]])
        position += cuts[k % len(cuts)]
        k += 1
    # TCP fragmentation must not change what the reader sees: the same bytes in one piece give the same replies.
    assert replies == tp.ReplyReader().feed(data)
    for reply in replies:
        assert reply == reply.strip() and reply
        for parse in (tp.parse_yes_no, tp.parse_int, tp.parse_float, tp.parse_endianness, tp.parse_banner):
            try:
                parse(reply)
            except ProtocolError:
                pass  # the only exception a parser may raise on garbage; anything else fails the test


def test_reply_reader_gives_up_on_an_endless_reply():
    reader = tp.ReplyReader()
    try:
        reader.feed(b"x" * (tp.MAX_REPLY_BYTES + 1))
    except ProtocolError as error:
        assert "no reply terminator" in str(error)
    else:
        raise AssertionError("an endless reply must be an error")
    assert reader.feed(b"OK\r\n\r\n") == ["OK"]


@settings(max_examples=300, deadline=None)
@given(st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126), max_size=40))
def test_simulator_answers_every_command_with_one_reply(command):
    from drivers.trigno.simulator import TrignoSimulator, _CommandConnection
    from drivers.trigno.source import synthetic_source

    sim = TrignoSimulator(synthetic_source(seconds=0.1))
    reply = sim._handle(_CommandConnection(None, 1), command)  # type: ignore[arg-type]
    assert isinstance(reply, str) and reply and "\r\n\r\n" not in reply
