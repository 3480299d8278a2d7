"""Xsens-like inertial streams of the body segments, consistent with the pack's rigid-body kinematics.

Each tracker is strapped to one pack body (at its centre of mass, with a random mounting rotation of up to ~10°).
Orientation, rate of turn and specific force come from pinocchio's forward kinematics of the pack's rigid model, so
they agree with each other and with the joint angles. Global frame: ENU with the subject facing north (model +X ->
north, +Y -> up, +Z -> east), rotated so that the pack's gravity points down. Sensor errors: gyroscope white noise
and a random-walk bias, accelerometer white noise, smooth orientation error (~0.3°) plus a slow heading drift (the Kalman
filter's yaw is only magnetometer-aided), magnetometer noise.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import pinocchio as pin
from scipy.spatial.transform import Rotation

from msk_core.errors import ModelError
from msk_core.synth.recruitment import smooth_noise
from msk_core.synth.rng import stream

_MODEL_TO_ENU = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
_FIELD_ENU = np.array([0.0, np.cos(np.radians(65.0)), -np.sin(np.radians(65.0))])  # normalised, 65° inclination


class Motion(NamedTuple):
    """The pack's coordinates over time, from which the simulated sensors' signals follow."""

    time: np.ndarray  # (n,) s
    q: np.ndarray  # (n, n_c) rad or m
    qd: np.ndarray  # (n, n_c) per s
    qdd: np.ndarray  # (n, n_c) per s²


@dataclass(frozen=True)
class ImuStream:
    tracker_id: str  # 8 hex digits
    segment: str
    body: str
    time: np.ndarray  # (n,) s
    orientation: np.ndarray  # (n, 4) w, x, y, z sensor-to-global
    acceleration: np.ndarray  # (n, 3) m/s² sensor frame
    rate_of_turn: np.ndarray  # (n, 3) rad/s sensor frame
    magnetic_field: np.ndarray  # (n, 3) normalised units, sensor frame


def global_frame(gravity: np.ndarray) -> np.ndarray:
    """Rotation model-ground -> ENU: the standard axis map, then the minimal rotation taking gravity to −Z."""
    g = _MODEL_TO_ENU @ (np.asarray(gravity, dtype=float) / np.linalg.norm(gravity))
    down = np.array([0.0, 0.0, -1.0])
    axis = np.cross(g, down)
    s, c = np.linalg.norm(axis), float(g @ down)
    if s < 1e-12:
        fix = np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    else:
        fix = Rotation.from_rotvec(axis / s * np.arctan2(s, c)).as_matrix()
    return fix @ _MODEL_TO_ENU


def find_body(description: dict, pattern: str) -> dict | None:
    """The heaviest moving body whose name matches ``pattern``."""
    matches = [b for b in description["bodies"] if re.search(pattern, b["name"], flags=re.IGNORECASE)]
    return max(matches, key=lambda b: float(b["mass"]), default=None)


def joint_motion(rigid, dq: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pinocchio joint positions, velocities, accelerations (n, n_joints) for coordinate offsets dq = q − q_ref.

    Linear joints follow the pack's gains; a joint with a ``function`` (polynomial of one coordinate, e.g. a rolling
    knee or the patella) follows it, with the chain rule for its rates (as RigidModel.inverse_dynamics does)."""
    qp, vp, ap = dq @ rigid.gains.T, qd @ rigid.gains.T, qdd @ rigid.gains.T
    for j, joint in enumerate(rigid.description["joints"]):
        f = joint.get("function")
        if not f:
            continue
        k = int(f["coordinate"])
        coef = np.asarray(f["coefficients"], dtype=float)
        half = float(f["half_width"])
        x = (dq[:, k] - float(f["centre"])) / half
        poly = np.polynomial.polynomial
        d1 = poly.polyval(x, poly.polyder(coef)) / half if coef.size > 1 else np.zeros_like(x)
        d2 = poly.polyval(x, poly.polyder(coef, 2)) / half**2 if coef.size > 2 else np.zeros_like(x)
        qp[:, j] = poly.polyval(x, coef)
        vp[:, j] = d1 * qd[:, k]
        ap[:, j] = d1 * qdd[:, k] + d2 * qd[:, k] ** 2
    return qp, vp, ap


def body_point_motion(
    pack, points: list[tuple[dict, float]], q: np.ndarray, qd: np.ndarray, qdd: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Motion of points fixed on pack bodies, from pinocchio's forward kinematics of the rigid model. ``points``: per
    point, (pack body, where on it: 0 at the body's joint centre, 1 at its centre of mass, on the line between).
    Returns, per point and sample, the body's rotation (P, n, 3, 3: body -> model ground), its angular velocity
    (P, n, 3, rad/s) and the point's specific force (P, n, 3, m/s²: acceleration minus gravity, what an accelerometer
    measures), the last two in the body frame."""
    rigid = pack.rigid
    model, data = rigid.model, rigid.model.createData()
    gravity = rigid.gravity
    n = q.shape[0]
    dq = q - pack.reference_pose[None, :]
    qp, vp, ap = joint_motion(rigid, dq, qd, qdd)
    positions = [np.asarray(j["position"], dtype=float) for j in rigid.description["joints"]]
    joints = sorted({int(body["joint"]) for body, _ in points})
    rot_j = np.empty((len(joints), n, 3, 3))
    gravity_j = np.empty((len(joints), n, 3))  # gravity in the body frame
    v_lin, v_ang, a_lin, a_ang = (np.empty((len(joints), n, 3)) for _ in range(4))
    for i in range(n):
        pin.forwardKinematics(model, data, qp[i], vp[i], ap[i])
        for s, joint in enumerate(joints):
            jid = joint + 1
            r = data.oMi[jid].rotation
            v = pin.getVelocity(model, data, jid, pin.LOCAL)
            a = pin.getAcceleration(model, data, jid, pin.LOCAL)
            rot_j[s, i], gravity_j[s, i] = r, r.T @ gravity
            v_lin[s, i], v_ang[s, i], a_lin[s, i], a_ang[s, i] = v.linear, v.angular, a.linear, a.angular
    rot = np.empty((len(points), n, 3, 3))
    omega = np.empty((len(points), n, 3))
    spec_force = np.empty((len(points), n, 3))
    for p, (body, along) in enumerate(points):
        s = joints.index(int(body["joint"]))
        c = np.asarray(body["com"], dtype=float) - positions[int(body["joint"])]
        if along != 1.0:
            c = along * c
        w = v_ang[s]
        v_point = v_lin[s] + np.cross(w, c)
        acc = a_lin[s] + np.cross(a_ang[s], c) + np.cross(w, v_point)  # classical acceleration of the point
        rot[p], omega[p], spec_force[p] = rot_j[s], w, acc - gravity_j[s]
    return rot, omega, spec_force


def simulate_imu(
    pack,
    segments: dict[str, str],
    motion: Motion,
    *,
    seed: int,
    key: tuple,
) -> list[ImuStream]:
    """IMU streams for every segment label whose body regex matches a body of the pack (others are skipped)."""
    time = motion.time
    rigid = pack.rigid
    to_global = global_frame(rigid.gravity)
    streams: list[ImuStream] = []
    found = [(label, find_body(rigid.description, pattern)) for label, pattern in segments.items()]
    chosen = [(label, body) for label, body in found if body is not None]
    if not chosen:
        raise ModelError(f"pack {pack.name!r}: no body matches the IMU segments {list(segments)}")
    n = time.size
    rot, omega, spec_force = body_point_motion(
        pack, [(body, 1.0) for _, body in chosen], motion.q, motion.qd, motion.qdd
    )
    for s, (label, body) in enumerate(chosen):
        rng = stream(seed, "imu", *key, label)
        tracker_id = f"{int(stream(seed, 'tracker-id', label).integers(0x00B40000, 0x00B4FFFF)):08X}"
        mount = Rotation.from_rotvec(rng.normal(0.0, np.radians(6.0), 3)).as_matrix()
        rate = 1.0 / float(np.median(np.diff(time))) if n > 1 else 100.0
        drift = np.cumsum(rng.normal(0.0, np.radians(0.6) / np.sqrt(60.0 * rate), n))  # ~0.6°/√min heading walk
        heading = Rotation.from_rotvec(np.outer(drift, [0.0, 0.0, 1.0])).as_matrix()
        # the device's orientation filter output wanders smoothly (~0.3°, < 1 Hz) rather than jumping per sample
        jitter = Rotation.from_rotvec(np.radians(0.3) * smooth_noise(n, 3, rate, min(1.0, 0.2 * rate), rng)).as_matrix()
        r_sensor = np.einsum("ij,njk,kl->nil", to_global, rot[s], mount)  # sensor -> global
        r_meas = heading @ r_sensor @ jitter
        quat = Rotation.from_matrix(r_meas).as_quat(scalar_first=True)
        quat *= np.where(quat[:, :1] < 0, -1.0, 1.0)  # w >= 0, as Xsens reports
        bias = np.radians(0.2) + np.cumsum(rng.normal(0.0, 2e-5, (n, 3)), axis=0)
        gyro = omega[s] @ mount + bias + rng.normal(0.0, 0.005, (n, 3))  # (R_m^T ω) row-wise
        accel = spec_force[s] @ mount + rng.normal(0.0, 0.02, (n, 3))
        mag = np.einsum("nji,j->ni", r_sensor, _FIELD_ENU) + rng.normal(0.0, 0.01, (n, 3))
        streams.append(ImuStream(tracker_id, label, body["name"], time.copy(), quat, accel, gyro, mag))
    return streams


@dataclass(frozen=True)
class ElectrodeAccStream:
    """What the accelerometers of the EMG sensors (Trigno Avanti, AUX port) measure: per channel, the specific force
    of its site in its own axes."""

    channels: list[str]
    bodies: list[str | None]  # pack body under each sensor; None: a part the pack keeps still
    time: np.ndarray  # (n,) s
    acceleration: np.ndarray  # (n, C, 3) m/s², sensor frame (at rest: +|g| along the sensor's up axis)


def simulate_electrode_acc(
    pack,
    sites: dict,
    channels: list[str],
    motion: Motion,
    *,
    seed: int,
    key: tuple,
) -> ElectrodeAccStream:
    """Accelerometer of each EMG sensor: the specific force of its site (``sites``: channel -> ElectrodeSite), as the
    same rigid-body kinematics give the trackers', so a sensor and a tracker on one body measure one motion at two
    points of it. A sensor's axes follow the muscle it is stuck on, not the body's: a uniformly random mounting
    rotation per channel. A channel without a site, or whose body the pack lacks, lies on a part the pack keeps
    still (the bench-press trunk on the bench): it measures gravity alone. White noise 0.02 m/s² (about 2 mg), as the
    trackers' accelerometers."""
    rigid = pack.rigid
    bodies: list[dict | None] = []
    for channel in channels:
        site = sites.get(channel)
        bodies.append(None if site is None or site.body is None else find_body(rigid.description, site.body))
    moving = [(b, sites[ch].along) for ch, b in zip(channels, bodies) if b is not None]
    time, n = motion.time, motion.time.size
    gravity = np.asarray(rigid.gravity, dtype=float)
    spec_force = body_point_motion(pack, moving, motion.q, motion.qd, motion.qdd)[2] if moving else np.empty((0, n, 3))
    acc = np.empty((n, len(channels), 3))
    m = 0
    for k, (channel, body) in enumerate(zip(channels, bodies)):
        rng = stream(seed, "electrode-acc", *key, channel)
        mount = Rotation.random(random_state=rng).as_matrix()
        if body is None:
            force = np.broadcast_to(-gravity, (n, 3))  # still in the ground frame: the support pushes up
        else:
            force, m = spec_force[m], m + 1
        acc[:, k] = force @ mount + rng.normal(0.0, 0.02, (n, 3))
    return ElectrodeAccStream(list(channels), [None if b is None else b["name"] for b in bodies], time.copy(), acc)
