"""services.transport.mcap_io on real MCAP files: channels without an msk type (the recorder's rejected payloads, a foreign
JSON channel) are left out of what read_messages yields and counted, or yielded with their reason on request."""

from __future__ import annotations

import json

import pytest
from mcap.writer import Writer

from services.transport import messages, topics
from services.transport.mcap_io import McapRecorderWriter, ReadReport, read_messages

JOINTS = topics.joints_key("lab")


def _joints(value: float) -> bytes:
    return messages.encode(messages.JointAngles(coordinates=["elbow_flexion"], q=[value]))


def test_rejected_channels_are_left_out_and_counted_unless_asked_for(tmp_path):
    path = tmp_path / "mixed.mcap"
    with McapRecorderWriter(path) as writer:
        writer.write(JOINTS, "msk.JointAngles", _joints(0.1), 1, 1)
        writer.write_rejected(
            JOINTS, "undecodable", "5 bytes are not a valid msk.JointAngles", b"\xff\xff\xff\xff\x0f", 2
        )
        writer.write_rejected(JOINTS, "invalid", "msk.JointAngles: no coordinates", b"", 3)
        writer.write_rejected(JOINTS, "undecodable", "(a second one)", b"\xff", 4)
        writer.write(JOINTS, "msk.JointAngles", _joints(0.2), 5, 5)
    report = ReadReport()
    typed = list(read_messages(path, report=report))
    assert [m.data for m in typed] == [_joints(0.1), _joints(0.2)]
    assert [m.sequence for m in typed] == [0, 1]  # per channel: the rejected ones do not leave holes
    assert report.left_out == {(JOINTS, "undecodable"): 2, (JOINTS, "invalid"): 1}
    everything = list(read_messages(path, include_rejected=True))
    assert [(m.rejected, m.data) for m in everything] == [
        ("", _joints(0.1)),
        ("undecodable", b"\xff\xff\xff\xff\x0f"),
        ("invalid", b""),
        ("undecodable", b"\xff"),
        ("", _joints(0.2)),
    ]
    with pytest.raises(messages.MessageDecodeError, match=f"{JOINTS}: a payload the recorder rejected \\(invalid\\)"):
        everything[2].decode()
    with McapRecorderWriter(tmp_path / "no_reason.mcap") as writer, pytest.raises(ValueError, match=JOINTS):
        writer.write_rejected(JOINTS, "", "", b"", 1)


def test_a_channel_of_another_encoding_is_not_read_as_msk_data(tmp_path):
    """A file from another tool (a JSON channel beside a protobuf one): only the msk messages come out."""
    path = tmp_path / "foreign.mcap"
    with open(path, "wb") as stream:
        writer = Writer(stream)
        writer.start(profile="", library="another tool")
        schema = writer.register_schema("msk.JointAngles", "jsonschema", b"{}")  # an msk name, but JSON
        foreign = writer.register_channel("msk/lab/joints", "json", schema)
        writer.add_message(foreign, log_time=1, data=json.dumps({"q": [0.1]}).encode(), publish_time=1)
        writer.finish()
    report = ReadReport()
    assert list(read_messages(path, report=report)) == []
    assert report.left_out == {("msk/lab/joints", "no msk type (encoding 'json', schema 'msk.JointAngles')"): 1}


def test_a_cut_recording_with_rejected_channels_reads_up_to_the_cut(tmp_path):
    path = tmp_path / "cut.mcap"
    with McapRecorderWriter(path, chunk_size=1024) as writer:
        for index in range(400):
            writer.write(JOINTS, "msk.JointAngles", _joints(float(index)), index, index)
            writer.write_rejected(JOINTS, "undecodable", "garbage", bytes([0xFF]) * 8, index)
    whole = path.read_bytes()
    path.write_bytes(whole[: len(whole) // 2])
    report = ReadReport()
    typed = list(read_messages(path, report=report))
    assert report.truncated and 0 < len(typed) < 400
    assert [m.decode().q[0] for m in typed] == [float(i) for i in range(len(typed))]
    assert abs(report.left_out[(JOINTS, "undecodable")] - len(typed)) <= 1


def _with_a_damaged_chunk(tmp_path, n: int = 600, chunk_number: int = 1):
    """A recording of ``n`` load events in small chunks, 8 bytes in the middle of chunk ``chunk_number`` flipped
    (the first chunk holds the channel's and schema's records too)."""
    from mcap.reader import make_reader

    path = tmp_path / "damaged.mcap"
    with McapRecorderWriter(path, chunk_size=4096) as writer:
        for i in range(n):
            writer.write_message(topics.load_key("s"), messages.LoadEvent(barbell_mass_kg=float(i)), log_time_ns=i + 1)
    with open(path, "rb") as stream:
        chunk = make_reader(stream).get_summary().chunk_indexes[chunk_number]
    data = bytearray(path.read_bytes())
    middle = chunk.chunk_start_offset + chunk.chunk_length // 2
    data[middle : middle + 8] = bytes(b ^ 0xFF for b in data[middle : middle + 8])
    path.write_bytes(bytes(data))
    return path


@pytest.mark.parametrize("chunk_number", [0, 1])
def test_a_damaged_chunk_is_skipped_and_the_chunks_after_it_are_read(tmp_path, chunk_number):
    """A recording with one damaged chunk gave 515 of 26,377 messages ("cut short"): every chunk after it was lost.
    The first chunk also holds the channel's record: the summary names the channel of the messages after it."""
    path = _with_a_damaged_chunk(tmp_path, chunk_number=chunk_number)
    report = ReadReport()
    masses = [m.decode().barbell_mass_kg for m in read_messages(path, report=report)]
    assert report.damaged_chunks == 1 and not report.truncated
    lost = 600 - len(masses)
    assert 0 < lost < 300 and masses[-1] == 599.0  # the chunks after the damaged one are read
    assert report.messages_expected == 600 and report.messages_lost == lost
    assert report.damage_text() == f"1 damaged chunk(s) skipped; {lost} of 600 messages lost"


def test_the_session_report_says_what_a_damaged_recording_lost(tmp_path, capsys):
    from services import cli

    path = _with_a_damaged_chunk(tmp_path)
    assert cli.main(["report", str(path), "--out", str(tmp_path / "out")]) == 0
    damage = json.loads((tmp_path / "out" / "report.json").read_text())["recording_damage"]
    assert damage.startswith("1 damaged chunk(s) skipped; ") and damage.endswith(" of 600 messages lost"), damage
    assert f"warning: {path}: {damage}; the readable part is reported" in capsys.readouterr().err
    assert damage in (tmp_path / "out" / "report.html").read_text()
