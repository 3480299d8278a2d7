"""Message schemas: every type round-trips; the generated code is protoc's of the current msk.proto; topics are documented."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from msk_core.errors import ConfigError
from services.transport import messages, schemas, topics
from services.transport.schemas import msk_pb2

SCHEMA_DIR = Path(msk_pb2.__file__).parent


def sample_messages():
    yield messages.EmgChunk(
        source_id="trigno-1",
        channel_labels=["s1.EMG", "s2.EMG"],
        sample_rate_hz=2000.0,
        first_sample_index=27,
        device_time_ns=13_500_000,
        host_time_ns=1_700_000_000_000_000_000,
        n_samples=2,
        n_channels=2,
        samples=[0.5, -0.25, 1e-3, 2e-3],
        units="V",
    )
    yield messages.AccChunk(
        source_id="trigno-1",
        sensor_labels=["sensor01", "sensor03"],
        sample_rate_hz=2 / 0.0135,
        first_sample_index=2,
        device_time_ns=13_500_000,
        host_time_ns=1_700_000_000_000_000_000,
        n_samples=1,
        n_sensors=2,
        samples=[0.0, 0.0, 1.0, 0.5, -0.25, 0.75],
        units="g",
    )
    yield messages.ImuSample(
        tracker_id="0343A1B2",
        segment="upper_arm_r",
        packet_counter=65535,
        sample_time_fine=864_000_000 - 1,
        orientation=messages.Quaternion(w=0.5, x=0.5, y=-0.5, z=0.5),
        acceleration=messages.Vector3(x=0.0, y=-7.26, z=-1.2),
        rate_of_turn=messages.Vector3(x=0.1, y=0.2, z=0.3),
        magnetic_field=messages.Vector3(x=1.0, y=0.0, z=0.0),
        device_time_ns=10,
        host_time_ns=11,
        coordinate_frame="ENU",
    )
    yield messages.JointAngles(
        coordinates=["hip_flexion_r", "knee_angle_r"], q=[0.1, -0.2], qd=[1.0, 2.0], qdd=[3.0, 4.0], phase=0.25
    )
    yield messages.LoadEvent(barbell_mass_kg=60.0, exercise="bench_press", device_time_ns=5)
    yield messages.ActivationFrame(
        time_s=1.25,
        method="proposed",
        groups=["BRA", "BRD"],
        activations=[0.2, 0.3],
        forces_n=[200.0, 90.0],
        activation_std=[0.01, 0.02],
        torques=[
            messages.CoordinateTorque(
                coordinate="elbow_flexion", inverse_dynamics_nm=10.0, model_nm=9.5, residual_nm=0.5
            )
        ],
        solver_status="solved",
        iterations=7,
        solve_time_s=3e-5,
        input_arrival_ns=1,
        publish_ns=2,
        flags=["nan_input"],
        phase=0.4,
        measured_envelope=[float("nan"), 0.31],
    )
    yield messages.EmgEnvelope(
        time_s=1.25, groups=["BRD"], envelope=[0.31], device_time_ns=1_250_000_000, host_time_ns=3, flags=["emg_gap"]
    )
    yield messages.DeviceStatus(
        device_id="trigno-1",
        kind="trigno",
        connected=True,
        samples_received=10,
        samples_lost=2,
        errors=1,
        last_error="gap",
    )


@pytest.mark.parametrize("message", list(sample_messages()), ids=lambda m: m.DESCRIPTOR.name)
def test_every_message_type_round_trips(message):
    name = messages.type_name(message)
    decoded = messages.decode(name, messages.encode(message))
    assert decoded == message
    assert decoded.ListFields()  # not an empty message by accident


def test_all_top_level_types_are_covered_by_the_round_trip():
    assert {m.DESCRIPTOR.full_name for m in sample_messages()} == set(messages.MESSAGE_TYPES)


def test_decode_rejects_garbage_with_a_precise_error():
    with pytest.raises(messages.MessageDecodeError, match="msk.EmgChunk"):
        messages.decode("msk.EmgChunk", b"\xff\xff\xff\xff")
    with pytest.raises(messages.MessageDecodeError, match="unknown message type"):
        messages.decode("msk.Nope", b"")


def test_generated_code_is_protocs_of_the_current_proto(tmp_path):
    """The imported msk_pb2 is what the pinned protoc makes of msk.proto now."""
    schemas.generate(tmp_path)
    for name in schemas.GENERATED:
        assert (tmp_path / name).read_text() == (SCHEMA_DIR / name).read_text(), f"{name} does not match msk.proto"


def test_a_changed_proto_makes_its_code_again(tmp_path):
    """Code made from another msk.proto is stale whatever the file times say (pip and git do not keep them): the
    proto's SHA-256 beside the code decides, and generation replaces it (a new field appears in the stub)."""
    proto = tmp_path / "msk.proto"
    proto.write_text(schemas.PROTO.read_text())
    schemas.generate(tmp_path, proto)
    assert schemas.is_current(tmp_path, proto)
    made = {name: (tmp_path / name).stat().st_mtime for name in schemas.GENERATED}
    proto.write_text(
        schemas.PROTO.read_text().replace("message LoadEvent {", "message LoadEvent {\n  int32 added_here = 999;", 1)
    )
    os.utime(proto, (min(made.values()) - 3600,) * 2)  # older than the code, as an installed copy can be
    assert not schemas.is_current(tmp_path, proto)
    schemas.generate(tmp_path, proto)
    assert schemas.is_current(tmp_path, proto)
    assert "added_here" in (tmp_path / "msk_pb2.pyi").read_text()
    assert not list(tmp_path.glob(".protoc-*")), "protoc's scratch folder was left behind"
    (tmp_path / schemas.STAMP).unlink()  # code of unknown origin (a copy without its stamp)
    assert not schemas.is_current(tmp_path, proto)


def test_missing_protoc_is_named(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "grpc_tools", None)
    with pytest.raises(
        schemas.SchemaGenerationError,
        match=r"msk_pb2\.py is missing or not made from .*msk\.proto as it is, and grpcio-tools",
    ):
        schemas.generate(tmp_path)


def test_a_proto_protoc_refuses_is_reported(tmp_path, capfd):
    proto = tmp_path / "msk.proto"
    proto.write_text('syntax = "proto3";\nmessage Broken { int32 x = ; }\n')
    with pytest.raises(schemas.SchemaGenerationError, match=r"protoc failed on .*msk\.proto \(exit code 1\)"):
        schemas.generate(tmp_path / "out", proto)
    assert "msk.proto:2" in capfd.readouterr().err, "protoc's own message (file:line) is not shown"


def test_file_descriptor_set_describes_every_type():
    from google.protobuf import descriptor_pb2

    fds = descriptor_pb2.FileDescriptorSet.FromString(messages.file_descriptor_set())
    names = {f"{f.package}.{m.name}" for f in fds.file for m in f.message_type}
    assert set(messages.MESSAGE_TYPES) <= names


def test_topic_table_is_documented(repo_root):
    doc = (repo_root / "docs" / "topics.md").read_text()
    rows = [line for line in doc.splitlines() if line.startswith("| `msk/")]
    for template, type_name in topics.TOPIC_TABLE:
        key = f"`msk/<session>/{template}`"
        matching = [row for row in rows if row.startswith(f"| {key}")]
        assert matching, f"docs/topics.md has no row for {key}"
        assert f"`{type_name.split('.')[1]}`" in matching[0], f"docs/topics.md gives the wrong type for {key}"


def test_topic_keys_and_types():
    assert topics.emg_key("s1", "trigno") == "msk/s1/emg/trigno"
    assert topics.message_type_for_key("msk/s1/emg/trigno") == "msk.EmgChunk"
    assert topics.message_type_for_key("msk/s1/activations/so") == "msk.ActivationFrame"
    assert topics.message_type_for_key("msk/s1/unknown/x") is None
    assert topics.rename_session("msk/a/imu/t1", "b") == "msk/b/imu/t1"
    with pytest.raises(ConfigError, match="session"):
        topics.emg_key("bad/session", "x")


def test_add_packed_floats_is_the_same_message_as_extend() -> None:
    import numpy as np

    rng = np.random.default_rng(3)
    rows = rng.normal(size=(27, 16)).astype(np.float32)[:, ::2]  # not contiguous, as a column selection can be
    for cls, shape in ((messages.EmgChunk, rows), (messages.AccChunk, rng.normal(size=(2, 4, 3)))):
        fast, slow = cls(source_id="t", n_samples=3), cls(source_id="t", n_samples=3)
        messages.add_packed_floats(fast, "samples", shape)
        slow.samples.extend(np.asarray(shape, dtype=np.float32).ravel().tolist())
        assert fast == slow
        assert fast.SerializeToString() == slow.SerializeToString()
    with pytest.raises(TypeError, match="not a packed repeated float"):
        messages.add_packed_floats(messages.EmgChunk(), "channel_labels", rows)


def test_an_installed_package_makes_its_schema_code_anew_from_the_proto_it_ships(tmp_path, repo_root):
    """As the Dockerfile installs it (pip install ., not editable) from a working tree whose generated code is stale
    (msk.proto gained a field since): the installed package ships msk.proto, and its first import, from outside the
    source tree, makes msk_pb2 inside the installed package from that proto."""
    source = tmp_path / "source"
    tracked = subprocess.run(["git", "-C", str(repo_root), "ls-files", "-z"], capture_output=True, check=True).stdout
    for name in filter(None, tracked.decode().split("\0")):  # the working tree's tracked files, as a clone has them
        if (repo_root / name).is_file():
            (source / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(repo_root / name, source / name)
    schema_dir = source / "services" / "transport" / "schemas"
    schemas.generate(schema_dir, schema_dir / "msk.proto")  # the code of today's proto, then the proto changes
    proto = schema_dir / "msk.proto"
    proto.write_text(
        proto.read_text().replace("message LoadEvent {", "message LoadEvent {\n  int32 added_here = 999;", 1)
    )
    target = tmp_path / "site"
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--target", str(target),
         str(source)],
        check=True, capture_output=True, timeout=120, cwd=tmp_path,
    )  # fmt: skip
    installed = target / "services" / "transport" / "schemas"
    assert (installed / "msk.proto").is_file()
    imported = subprocess.run(
        [sys.executable, "-c", "import services.transport.schemas.msk_pb2 as m; print(m.__file__, m.LoadEvent(added_here=1))"],
        env={**os.environ, "PYTHONPATH": str(target)}, cwd=tmp_path, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert imported.returncode == 0, imported.stderr
    assert imported.stdout.split()[0] == str(installed / "msk_pb2.py") and "added_here: 1" in imported.stdout
