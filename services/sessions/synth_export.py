"""Export a synthetic session (msk_core.synth) as an MCAP recording and as device streams the simulators replay.

MCAP: the topics of services/transport/topics.py on one timeline (trials back to back, 5 s apart, starting at a fixed epoch so
the same seed gives the same bytes): ``load`` (LoadEvent at each trial's start with the *reported* mass, 0 kg at its
end), ``joints`` (JointAngles q, qd, qdd, phase at the kinematics rate), ``emg/<source>`` (EmgChunk, raw volts,
27-sample chunks at 2000 Hz as a Trigno frame, row-major) and ``imu/<tracker>`` (ImuSample per sample).

Device streams (per trial folder ``raw/<trial>/``):
* ``trigno.npz`` (emg, rate_hz, labels, sensors; acc, acc_rate_hz: each sensor's accelerometer in g at the
  Avanti ACC rate, streamed on the AUX port) for ``drivers.trigno`` sources, and ``trigno_emg.bin``, the EMG
  data port's byte stream (16 little-endian float32 per sample, unpaired slots zero);
* ``xsens_<segment>.npz`` (rate_hz, quaternion, acceleration, rate_of_turn, magnetic_field; ENU) for
  ``drivers.xsens`` sources, and ``xsens_<segment>.bin``, Xbus MTData2 frames (PacketCounter, SampleTimeFine,
  quaternion, acceleration, rate of turn, magnetic field; float32) as the serial line carries them.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from drivers.trigno.protocol import N_SENSORS, encode_samples
from drivers.xsens import xbus
from msk_core.signal.clock_sync import STANDARD_GRAVITY
from msk_core.synth.session import Session, Trial
from services.transport import messages, topics
from services.transport.mcap_io import McapRecorderWriter

#: 2026-01-01T00:00:00Z: a fixed session start keeps the output byte-identical for a given seed.
EPOCH_NS = 1_767_225_600 * 1_000_000_000
TRIAL_GAP_S = 5.0
EMG_CHUNK = 27  # samples per Trigno frame at ~2 kHz
EMG_SOURCE = "trigno-synth"


def _ns(t: float) -> int:
    return int(round(t * 1e9))


_Timed = tuple[int, int, str, object]  # (log_time_ns, tie-break, topic, message)


def trial_messages(trial: Trial, session: str, t0_ns: int, emg_rate_hz: float) -> list[_Timed]:
    """(log_time_ns, tie-break, topic, message) for one trial: its load events, joint angles, EMG chunks and IMU
    samples (tie-breaks 0, 1, 2 and 3 + tracker index)."""
    return (
        _load_messages(trial, session, t0_ns)
        + _joint_messages(trial, session, t0_ns)
        + _emg_messages(trial, session, t0_ns, emg_rate_hz)
        + _imu_messages(trial, session, t0_ns)
    )


def _load_messages(trial: Trial, session: str, t0_ns: int) -> list[_Timed]:
    """The trial's load at its start and 0 kg at its end."""
    load_key = topics.load_key(session)
    end_ns = t0_ns + _ns(float(trial.time[-1]))
    return [
        (
            when,
            0,
            load_key,
            messages.LoadEvent(
                barbell_mass_kg=mass, exercise=trial.exercise.value, device_time_ns=when, host_time_ns=when
            ),
        )
        for when, mass in ((t0_ns, trial.reported_load_kg), (end_ns, 0.0))
    ]


def _joint_messages(trial: Trial, session: str, t0_ns: int) -> list[_Timed]:
    joints_key = topics.joints_key(session)
    out: list[_Timed] = []
    for k, t in enumerate(trial.time):
        when = t0_ns + _ns(float(t))
        out.append(
            (
                when,
                1,
                joints_key,
                messages.JointAngles(
                    coordinates=trial.coordinates,
                    q=trial.q[k].tolist(),
                    qd=trial.qd[k].tolist(),
                    qdd=trial.qdd[k].tolist(),
                    phase=float(trial.phase[k]),
                    device_time_ns=when,
                    host_time_ns=when,
                ),
            )
        )
    return out


def _emg_messages(trial: Trial, session: str, t0_ns: int, emg_rate_hz: float) -> list[_Timed]:
    """Whole EMG_CHUNK-sample frames, each logged when its last sample is in."""
    emg_key = topics.emg_key(session, EMG_SOURCE)
    out: list[_Timed] = []
    first_index = int(round(t0_ns * 1e-9 * emg_rate_hz)) - int(round(EPOCH_NS * 1e-9 * emg_rate_hz))
    samples = trial.emg.astype(np.float32)
    for start in range(0, samples.shape[0] - EMG_CHUNK + 1, EMG_CHUNK):
        block = samples[start : start + EMG_CHUNK]
        device = t0_ns + _ns(start / emg_rate_hz)
        host = t0_ns + _ns((start + EMG_CHUNK) / emg_rate_hz)  # the frame is complete after its last sample
        out.append(
            (
                host,
                2,
                emg_key,
                messages.EmgChunk(
                    source_id=EMG_SOURCE,
                    channel_labels=trial.channels,
                    sample_rate_hz=emg_rate_hz,
                    first_sample_index=first_index + start,
                    device_time_ns=device,
                    host_time_ns=host,
                    n_samples=EMG_CHUNK,
                    n_channels=block.shape[1],
                    samples=block.reshape(-1).tolist(),
                    units="V",
                ),
            )
        )
    return out


def _imu_messages(trial: Trial, session: str, t0_ns: int) -> list[_Timed]:
    out: list[_Timed] = []
    for s, imu in enumerate(trial.imu):
        key = topics.imu_key(session, imu.segment)
        for k, t in enumerate(imu.time):
            when = t0_ns + _ns(float(t))
            q, a, w, m = imu.orientation[k], imu.acceleration[k], imu.rate_of_turn[k], imu.magnetic_field[k]
            out.append(
                (
                    when,
                    3 + s,
                    key,
                    messages.ImuSample(
                        tracker_id=imu.tracker_id,
                        segment=imu.segment,
                        packet_counter=k & 0xFFFF,
                        sample_time_fine=int(round((when - EPOCH_NS) * 1e-5)) & 0xFFFFFFFF,
                        orientation=messages.Quaternion(w=q[0], x=q[1], y=q[2], z=q[3]),
                        acceleration=messages.Vector3(x=a[0], y=a[1], z=a[2]),
                        rate_of_turn=messages.Vector3(x=w[0], y=w[1], z=w[2]),
                        magnetic_field=messages.Vector3(x=m[0], y=m[1], z=m[2]),
                        device_time_ns=when,
                        host_time_ns=when,
                        coordinate_frame="ENU",
                    ),
                )
            )
    return out


def trial_offsets(session: Session) -> dict[str, float]:
    """Start time (s after EPOCH) of every trial on the recording's timeline."""
    offsets, t = {}, 0.0
    for ex in session.exercises:
        for trial in ex.trials:
            offsets[trial.name] = t
            t += float(trial.time[-1]) + TRIAL_GAP_S
    return offsets


def write_mcap(session: Session, path: str | Path, *, session_name: str = "synth") -> Path:
    """Write every trial of ``session`` to one MCAP file (deterministic bytes). Returns the path."""
    path = Path(path)
    offsets = trial_offsets(session)
    # no time-based flushing: chunk boundaries then depend only on the content
    with McapRecorderWriter(path, flush_interval_s=float("inf")) as writer:
        for ex in session.exercises:
            for trial in ex.trials:
                batch = trial_messages(
                    trial, session_name, EPOCH_NS + _ns(offsets[trial.name]), session.config.emg_rate_hz
                )
                batch.sort(key=lambda m: (m[0], m[1]))
                for log_time, _, topic, message in batch:
                    writer.write_message(topic, message, log_time)
    return path


def _mtdata2(packet_counter: int, fine: int, quat, acc, gyr, mag) -> bytes:
    items = [
        struct.pack(">HBH", 0x1020, 2, packet_counter & 0xFFFF),
        struct.pack(">HBI", 0x1060, 4, fine & 0xFFFFFFFF),
        struct.pack(">HB4f", xbus.make_data_id(0x2010), 16, *quat),
        struct.pack(">HB3f", xbus.make_data_id(0x4020), 12, *acc),
        struct.pack(">HB3f", xbus.make_data_id(0x8020), 12, *gyr),
        struct.pack(">HB3f", xbus.make_data_id(0xC020), 12, *mag),
    ]
    return xbus.encode_message(xbus.Mid.MT_DATA2, b"".join(items))


def savez_deterministic(path: Path, **arrays: ArrayLike) -> Path:
    """Like ``np.savez`` but with fixed zip timestamps, so equal arrays give equal bytes."""
    import io
    import zipfile

    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as zf:
        for name, value in arrays.items():
            buffer = io.BytesIO()
            np.lib.format.write_array(buffer, np.asanyarray(value), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            zf.writestr(info, buffer.getvalue())
    return path


def write_device_streams(session: Session, out: str | Path) -> list[Path]:
    """Per trial: Trigno and Xsens replay files (npz) and raw byte streams (bin). Returns the files written."""
    out = Path(out)
    written: list[Path] = []
    for ex in session.exercises:
        for trial in ex.trials:
            written += write_trial_device_streams(
                trial,
                out / "raw" / trial.name,
                emg_rate_hz=session.config.emg_rate_hz,
                imu_rate_hz=session.config.imu_rate_hz,
            )
    return written


def write_trial_device_streams(trial: Trial, folder: Path, *, emg_rate_hz: float, imu_rate_hz: float) -> list[Path]:
    """One trial's replay files in ``folder``: ``trigno.npz`` (with each sensor's accelerometer, ``acc`` in g at
    ``acc_rate_hz``, when the trial has them), ``trigno_emg.bin``, ``xsens_<segment>.npz`` and ``.bin``."""
    folder.mkdir(parents=True, exist_ok=True)
    n_ch = len(trial.channels)
    if n_ch > N_SENSORS:
        raise ValueError(f"{n_ch} EMG channels exceed the Trigno's {N_SENSORS} sensors")
    acc: dict[str, ArrayLike] = {}
    if trial.emg_acc is not None:
        rate = 1.0 / float(np.median(np.diff(trial.emg_acc.time)))
        acc = {"acc": (trial.emg_acc.acceleration / STANDARD_GRAVITY).astype(np.float32), "acc_rate_hz": rate}
    savez_deterministic(
        folder / "trigno.npz",
        emg=trial.emg.astype(np.float32),
        rate_hz=emg_rate_hz,
        labels=np.asarray(trial.channels),
        sensors=np.arange(1, n_ch + 1),
        **acc,
    )
    rows = np.zeros((trial.emg.shape[0], N_SENSORS), dtype=np.float32)
    rows[:, :n_ch] = trial.emg
    (folder / "trigno_emg.bin").write_bytes(encode_samples(rows))
    written = [folder / "trigno.npz", folder / "trigno_emg.bin"]
    for imu in trial.imu:
        npz = folder / f"xsens_{imu.segment}.npz"
        savez_deterministic(
            npz,
            rate_hz=imu_rate_hz,
            quaternion=imu.orientation,
            acceleration=imu.acceleration,
            rate_of_turn=imu.rate_of_turn,
            magnetic_field=imu.magnetic_field,
        )
        frames = [
            _mtdata2(
                k,
                int(round(t * 1e4)),
                imu.orientation[k],
                imu.acceleration[k],
                imu.rate_of_turn[k],
                imu.magnetic_field[k],
            )
            for k, t in enumerate(imu.time)
        ]
        binary = folder / f"xsens_{imu.segment}.bin"
        binary.write_bytes(b"".join(frames))
        written += [npz, binary]
    return written
