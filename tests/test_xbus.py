"""Xbus codec: framing, checksum, extended length, MTData2 in every precision and frame, real MTi-G-710 captures,
resynchronisation after injected faults, and fuzzing (hypothesis)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.xsens import frames, xbus
from msk_core.errors import ProtocolError

SET_PRECISION = {
    1: xbus.Precision.FLOAT32,
    2: xbus.Precision.FP1220,
    3: xbus.Precision.FP1632,
    4: xbus.Precision.FLOAT64,
}
REAL_QUANTITIES = ("acceleration", "rate_of_turn", "delta_v", "delta_q")
#: The tolerance unit of each precision in the Xbus and device tests: a float's round trip, a fixed-point format's step.
STEP = {
    xbus.Precision.FLOAT32: 1e-6,
    xbus.Precision.FP1220: 2.0**-20,
    xbus.Precision.FP1632: 2.0**-32,
    xbus.Precision.FLOAT64: 1e-15,
}


def load_set(shared_dir, n: int) -> tuple[bytes, list[xbus.XbusMessage]]:
    data = (shared_dir / f"data/xsens-captures/mtig710_set{n}.bin").read_bytes()
    parser = xbus.XbusParser()
    messages = parser.feed(data)
    assert parser.stats.errors == 0 and parser.stats.bytes_skipped == 0 and parser.pending == 0
    return data, messages


# ------------------------------------------------------------------------------------------------ framing


@pytest.mark.parametrize(
    "mid, frame",
    [
        (xbus.Mid.REQ_DID, "FA FF 00 00 01"),
        (xbus.Mid.GO_TO_MEASUREMENT, "FA FF 10 00 F1"),
        (xbus.Mid.GO_TO_MEASUREMENT_ACK, "FA FF 11 00 F0"),
        (xbus.Mid.REQ_FW_REV, "FA FF 12 00 EF"),
        (xbus.Mid.REQ_PRODUCT_CODE, "FA FF 1C 00 E5"),
        (xbus.Mid.GO_TO_CONFIG, "FA FF 30 00 D1"),
        (xbus.Mid.WAKE_UP, "FA FF 3E 00 C3"),
        (xbus.Mid.WAKE_UP_ACK, "FA FF 3F 00 C2"),
        (xbus.Mid.RESET, "FA FF 40 00 C1"),
        (xbus.Mid.SET_OUTPUT_CONFIGURATION, "FA FF C0 00 41"),
    ],
)
def test_ready_made_frames_from_the_manual(mid, frame):
    assert xbus.encode_message(mid) == bytes.fromhex(frame)


def test_set_output_configuration_example_frame():
    settings_ = [
        xbus.OutputSetting(0x1020, 0xFFFF),
        xbus.OutputSetting(0x1060, 0xFFFF),
        xbus.OutputSetting(0x2010, 100),
        xbus.OutputSetting(0x4020, 100),
        xbus.OutputSetting(0x8020, 100),
        xbus.OutputSetting(0xC020, 100),
    ]
    frame = xbus.encode_message(xbus.Mid.SET_OUTPUT_CONFIGURATION, xbus.encode_output_configuration(settings_))
    assert frame == bytes.fromhex(
        "FA FF C0 18 10 20 FF FF 10 60 FF FF 20 10 00 64 40 20 00 64 80 20 00 64 C0 20 00 64 ED"
    )
    assert xbus.decode_output_configuration(frame[4:-1]) == settings_


def test_extended_length_round_trip_and_limit():
    payload = bytes(range(256)) * 4  # 1024 bytes > 254: extended length
    frame = xbus.encode_message(0x36, payload)
    assert frame[3] == 0xFF and frame[4:6] == (1024).to_bytes(2, "big")
    parser = xbus.XbusParser(validate=False)
    messages = [m for k in range(len(frame)) for m in parser.feed(frame[k : k + 1])]
    assert messages == [xbus.XbusMessage(0xFF, 0x36, payload)]
    with pytest.raises(ProtocolError, match="2048"):
        xbus.encode_message(0x36, bytes(2049))


def test_parser_skips_garbage_and_bad_checksums():
    good = [xbus.encode_message(xbus.Mid.DEVICE_ID, bytes([3, 112, 10, k])) for k in range(3)]
    corrupt = bytearray(good[1])
    corrupt[5] ^= 0x10
    stream = b"\x00\xfa\x13garbage" + good[0] + bytes(corrupt) + b"\xfa" + good[2]
    parser = xbus.XbusParser()
    messages = parser.feed(stream)
    # "\xfa\x13g a" is a plausible header (bus 0x13, MID 0x67 = GravityMagnitude ack, 0x61 = 97 bytes): the parser
    # must wait for 97 bytes before it can reject it, so a false header delays frames but never loses them
    assert messages == []
    messages = parser.feed(bytes(100))  # the line idles (no preamble)
    assert [m.data[-1] for m in messages] == [0, 2]
    assert parser.stats.checksum_errors >= 2 and parser.stats.bytes_skipped > 0 and parser.stats.resyncs == 3


# ------------------------------------------------------------------------------------------------ real captures


@pytest.mark.parametrize("set_number", [1, 2, 3, 4])
def test_real_capture_decodes_in_its_precision_and_reencodes_bit_exact(shared_dir, set_number):
    precision = SET_PRECISION[set_number]
    _, messages = load_set(shared_dir, set_number)
    assert len(messages) == 100 and all(m.mid == xbus.Mid.MT_DATA2 and m.bid == 0xFF for m in messages)
    config = xbus.decode_output_configuration(
        (shared_dir / f"data/xsens-captures/mtig710_set{set_number}_outputconfig.bin").read_bytes()
    )
    assert {xbus.precision_of(s.data_id) for s in config if (s.data_id & 0xFFF0) in xbus.FLOAT_QUANTITIES} == {
        precision
    }
    counters = []
    for message in messages:
        decoded = xbus.decode_mtdata2(message.data)
        counters.append(decoded.first("packet_counter"))
        for data_id, raw in xbus.item_layout(message.data):
            if (data_id & 0xFFF0) in xbus.FLOAT_QUANTITIES:
                assert xbus.precision_of(data_id) is precision
                name = xbus.FLOAT_QUANTITIES[data_id & 0xFFF0][0]
                # decoding then encoding at the same precision gives the device's bytes back
                assert (
                    xbus.encode_item(data_id, decoded.get(name))
                    == bytes([data_id >> 8, data_id & 0xFF, len(raw)]) + raw
                )
    assert np.all(np.diff(counters) == 1)  # 100 consecutive packets, none lost
    acc = next(
        xbus.decode_mtdata2(m.data).get("acceleration")
        for m in messages
        if "acceleration" in xbus.decode_mtdata2(m.data).values
    )
    assert acc == pytest.approx((0.0, -7.26, -1.2), abs=0.06)  # the facts sheet's first sample


def _means(shared_dir, set_number):
    _, messages = load_set(shared_dir, set_number)
    out = {}
    for name in REAL_QUANTITIES:
        rows = np.array(
            [xbus.decode_mtdata2(m.data).get(name) for m in messages if name in xbus.decode_mtdata2(m.data).values]
        )
        rows = rows[1:]  # the first sample after configuration is a start-up transient in every set
        out[name] = (rows.mean(axis=0), rows.std(axis=0, ddof=1) / math.sqrt(len(rows)))
    return out


def test_real_sets_1_to_4_agree_within_precision_and_noise(shared_dir):
    """The sets were captured one after another from a resting device: per-quantity means agree within the
    resolution of each precision plus 5 standard errors of the sensor noise."""
    means = {n: _means(shared_dir, n) for n in SET_PRECISION}
    for a, b in itertools.combinations(SET_PRECISION, 2):
        for name in REAL_QUANTITIES:
            (mean_a, se_a), (mean_b, se_b) = means[a][name], means[b][name]
            tolerance = (
                5 * np.hypot(se_a, se_b)
                + xbus.PRECISION_RESOLUTION[SET_PRECISION[a]]
                + xbus.PRECISION_RESOLUTION[SET_PRECISION[b]]
            )
            assert np.all(np.abs(mean_a - mean_b) <= tolerance), (a, b, name, mean_a, mean_b, tolerance)
    assert means[1]["acceleration"][0] == pytest.approx((0.027, -9.674, -1.64), abs=0.01)


def test_fixed_point_values_sit_on_their_grid(shared_dir):
    for set_number, step in ((2, 2.0**-20), (3, 2.0**-32)):
        _, messages = load_set(shared_dir, set_number)
        values = np.array(
            [
                xbus.decode_mtdata2(m.data).get("acceleration")
                for m in messages[:20]
                if "acceleration" in xbus.decode_mtdata2(m.data).values
            ]
        )
        assert np.all(np.abs(values / step - np.round(values / step)) < 1e-6)


# ------------------------------------------------------------------------------------------------ every precision and frame


@pytest.mark.parametrize("precision", list(xbus.Precision))
@pytest.mark.parametrize("frame", list(xbus.CoordinateFrame))
def test_mtdata2_round_trip_every_precision_and_frame(precision, frame):
    q_enu = (0.7, 0.1, -0.5, 0.5)
    norm = math.sqrt(sum(v * v for v in q_enu))
    q_enu = tuple(v / norm for v in q_enu)
    q = frames.from_enu(q_enu, frame)
    acc = (0.25, -9.80665, 1.5)
    items = [
        (0x1020, (65535,)),
        (0x1060, (863_999_999,)),
        (xbus.make_data_id(0x2010, precision, frame), q),
        (xbus.make_data_id(0x4020, precision, frame), acc),
        (xbus.make_data_id(0xD010, precision, frame), (1.0, 2.0, -3.0)),
        (0xE020, (0x00800007,)),
        (0x7010, b"\x01\x02\x03"),  # unknown to the decoder: skipped by size, kept raw
    ]
    decoded = xbus.decode_mtdata2(xbus.encode_mtdata2(items))
    tolerance = STEP[precision]
    assert decoded.get("quaternion") == pytest.approx(q, abs=tolerance)
    assert decoded.get("acceleration") == pytest.approx(acc, abs=tolerance * 10)
    assert decoded.frame() is frame
    assert xbus.precision_of(decoded.ids["acceleration"]) is precision
    assert (
        xbus.frame_of(decoded.ids["acceleration"]) is xbus.CoordinateFrame.ENU
    )  # frame bits only on orientation/velocity
    assert frames.to_enu(decoded.get("quaternion"), frame) == pytest.approx(q_enu, abs=tolerance * 4)
    assert decoded.first("packet_counter") == 65535 and decoded.first("sample_time_fine") == 863_999_999
    assert decoded.unknown == [(0x7010, b"\x01\x02\x03")]


def test_frames_map_axes_as_documented():
    east, north, up = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
    ned = frames.ENU_TO[xbus.CoordinateFrame.NED]
    nwu = frames.ENU_TO[xbus.CoordinateFrame.NWU]
    assert frames.rotate(ned, north) == pytest.approx((1, 0, 0)) and frames.rotate(ned, east) == pytest.approx(
        (0, 1, 0)
    )
    assert frames.rotate(ned, up) == pytest.approx((0, 0, -1))
    assert frames.rotate(nwu, north) == pytest.approx((1, 0, 0)) and frames.rotate(nwu, east) == pytest.approx(
        (0, -1, 0)
    )


def test_fixed_point_range_errors():
    with pytest.raises(ProtocolError, match="12.20"):
        xbus.encode_real([5000.0], xbus.Precision.FP1220)
    with pytest.raises(ProtocolError, match="16.32"):
        xbus.encode_real([40000.0], xbus.Precision.FP1632)


def test_wrong_item_size_is_a_protocol_error():
    with pytest.raises(ProtocolError, match="0x4020.*expected 12"):
        xbus.decode_mtdata2(bytes.fromhex("4020 08") + bytes(8))
    with pytest.raises(ProtocolError, match="claims 12 bytes"):
        xbus.decode_mtdata2(bytes.fromhex("4020 0c") + bytes(4))


# ------------------------------------------------------------------------------------------------ faults and fuzzing


def _fault_stream(messages: list[bytes], rng: np.random.Generator) -> tuple[bytes, set[int]]:
    """Corrupt about 1 message in 5 (bit flip or dropped byte), add garbage; return the stream and corrupted indices."""
    out = bytearray()
    corrupted = set()
    for index, frame in enumerate(messages):
        draw = rng.random()
        if draw < 0.1:
            data = bytearray(frame)
            data[int(rng.integers(0, len(data)))] ^= 1 << int(rng.integers(0, 8))
            frame = bytes(data)
            corrupted.add(index)
        elif draw < 0.2:
            position = int(rng.integers(0, len(frame)))
            frame = frame[:position] + frame[position + 1 :]
            corrupted.add(index)
        elif draw < 0.3:
            junk = rng.integers(0, 256, int(rng.integers(1, 30)), dtype=np.uint8)
            junk[rng.random(len(junk)) < 0.3] = 0xFA
            out += junk.tobytes()
        out += frame
    return bytes(out), corrupted


def test_faulty_real_stream_recovers_every_intact_message(shared_dir):
    frames_ = [m.encode() for n in SET_PRECISION for m in load_set(shared_dir, n)[1]]
    assert len(frames_) == 400
    rng = np.random.default_rng(7)
    stream, corrupted = _fault_stream(frames_, rng)
    parser = xbus.XbusParser()
    received = []
    position = 0
    while position < len(stream):
        size = int(rng.integers(1, 700))
        received += parser.feed(stream[position : position + size])
        position += size
    intact = [xbus.iter_capture(f)[0] for k, f in enumerate(frames_) if k not in corrupted]
    assert len(corrupted) > 50
    assert received == intact  # every intact message, in order, and nothing else
    assert parser.stats.errors >= len(corrupted) and parser.stats.resyncs >= len(corrupted)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=600), st.lists(st.integers(1, 64), min_size=1, max_size=20))
def test_fuzz_parser_never_crashes_or_hangs(data, cuts):
    parser = xbus.XbusParser()
    position, k = 0, 0
    while position < len(data):
        size = cuts[k % len(cuts)]
        for message in parser.feed(data[position : position + size]):
            assert (sum(message.encode()[1:]) & 0xFF) == 0
            if message.mid == xbus.Mid.MT_DATA2:
                try:
                    xbus.decode_mtdata2(message.data)
                except ProtocolError:
                    pass
        position += size
        k += 1
    stats = parser.stats
    assert stats.bytes_in == len(data)
    assert stats.bytes_skipped + parser.pending <= len(data)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_fuzz_mtdata2_decoder_raises_only_protocol_errors(payload):
    try:
        decoded = xbus.decode_mtdata2(payload)
    except ProtocolError:
        return
    assert isinstance(decoded.values, dict)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.binary(min_size=0, max_size=40), min_size=1, max_size=8), st.binary(max_size=50))
def test_fuzz_valid_frames_survive_surrounding_garbage_free_of_preambles(payloads, junk):
    junk = junk.replace(b"\xfa", b"\x00")  # garbage without a preamble can never hide a frame
    frames_ = [xbus.encode_message(xbus.Mid.DEVICE_ID, p) for p in payloads]
    stream = junk + b"".join(f + junk for f in frames_)
    parser = xbus.XbusParser()
    assert [m.data for m in parser.feed(stream)] == payloads
    assert parser.stats.bytes_skipped == len(junk) * (len(frames_) + 1)


def test_frame_that_lost_a_byte_cannot_swallow_the_next_preamble(shared_dir):
    """Dropping a 0xFA data byte keeps the checksum valid once the next frame's preamble is taken as the checksum
    byte: the parser must still reject it (structure check) and recover the next frame."""
    _, messages = load_set(shared_dir, 1)
    frames_ = [m.encode() for m in messages]
    index, position = next((k, p) for k, f in enumerate(frames_[:-1]) for p in range(5, len(f) - 1) if f[p] == 0xFA)
    damaged = frames_[index][:position] + frames_[index][position + 1 :]
    assert (sum(damaged[1:]) + 0xFA) & 0xFF == 0  # the false frame's checksum passes
    parser = xbus.XbusParser()
    received = parser.feed(b"".join(frames_[:index]) + damaged + b"".join(frames_[index + 1 :]))
    assert received == [m for k, m in enumerate(messages) if k != index]
    assert parser.stats.structure_errors >= 1


def test_noise_that_looks_like_a_header_releases_the_frames_behind_it_once_nothing_more_comes():
    # 200 bytes claimed by an MTData2 header in the noise; the device then answers three times and goes quiet
    ack = xbus.encode_message(xbus.Mid.GO_TO_CONFIG_ACK)
    parser = xbus.XbusParser()
    assert parser.feed(bytes.fromhex("0102030405FAFF36C8112233") + ack * 3) == []  # waits for the 200 bytes
    released = parser.release_stalled()
    assert [m.mid for m in released] == [xbus.Mid.GO_TO_CONFIG_ACK] * 3 and parser.pending == 0
    assert parser.stats.length_errors == 1
    assert xbus.XbusParser().release_stalled() == []
