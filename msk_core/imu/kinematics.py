"""Joint kinematics from IMU orientations: sensor-to-segment alignment, joint angles, Kalman angle/velocity/acceleration.

Conventions (documented in docs/signal.md):

* Quaternions are scalar-first ``(w, x, y, z)`` (Xsens order) and give the sensor's orientation in the global frame
  ``G``: ``v_G = R_GS v_S``. The global frame is Z up (Xsens ENU / NWU: any Z-up frame).
* Segment frames follow ISB: X anterior, Y superior (along the segment, towards proximal), Z to the subject's right.
* Joint angles are the intrinsic Z-X-Y Cardan angles of the child segment relative to the parent:
  1. about Z (medio-lateral): flexion (+) / extension (-) — hip, shoulder and elbow flexion are positive, knee
     flexion is negative (the shank rotates backwards), as with a right-hand rule about the right-pointing axis;
  2. about the floating X (anterior): ab/adduction;
  3. about the child's Y (long axis): internal/external rotation.
* Static calibration: in the static pose every segment frame is the N-pose frame (X forward, Y up, Z right) turned
  by the same known heading about global Z. Then ``R_SB = R_GS(static)^T R_GB(static)`` and live
  ``R_GB(t) = R_GS(t) R_SB``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import KalmanFilter
from scipy.spatial.transform import Rotation

from msk_core.errors import ConfigError, InputError

# N-pose segment frame in a Z-up global frame facing +X: segment X -> global X, segment Y (up) -> global Z,
# segment Z (right) -> global -Y.
_NPOSE = Rotation.from_matrix(np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]))


def quats_to_rotation(quats: np.ndarray) -> Rotation:
    """Rotations from scalar-first unit quaternions ``(n, 4)`` or ``(4,)``; rejects zero or non-finite rows."""
    q = np.asarray(quats, dtype=float)
    if q.shape[-1] != 4:
        raise InputError("quaternions must have 4 components (w, x, y, z)", field="quats", value=q.shape)
    norms = np.linalg.norm(q, axis=-1)
    if not np.all(np.isfinite(q)) or np.any(norms < 1e-6):
        raise InputError("quaternions must be finite and non-zero", field="quats")
    return Rotation.from_quat(q, scalar_first=True)


_CONJUGATE = np.array([1.0, -1.0, -1.0, -1.0])


def unit_quats(quats: np.ndarray) -> np.ndarray:
    """Scalar-first quaternions ``(n, 4)`` or ``(4,)`` scaled to unit norm, as ``(n, 4)``; the same checks as
    :func:`quats_to_rotation` (which scipy's ``Rotation`` normalises alike)."""
    q = np.atleast_2d(np.asarray(quats, dtype=float))
    if q.shape[-1] != 4:
        raise InputError("quaternions must have 4 components (w, x, y, z)", field="quats", value=q.shape)
    norms = np.sqrt(np.einsum("ij,ij->i", q, q))
    if not (np.isfinite(norms).all() and norms.min() >= 1e-6):  # a non-finite component makes its norm non-finite
        raise InputError("quaternions must be finite and non-zero", field="quats")
    return q / norms[:, None]


def quat_product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products ``a b`` of scalar-first quaternions ``(n, 4)`` (either may be one ``(4,)``): the rotation
    ``a`` after ``b``, as ``Rotation`` composes them (``Rotation(a) * Rotation(b)``), without building Rotation
    objects (the kinematics node does this for every frame)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = aw * bw - ax * bx - ay * by - az * bz
    out[..., 1] = aw * bx + ax * bw + ay * bz - az * by
    out[..., 2] = aw * by - ax * bz + ay * bw + az * bx
    out[..., 3] = aw * bz + ax * by - ay * bx + az * bw
    return out


def twist_angle_quats(parent: np.ndarray, child: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """:func:`twist_angle` from unit scalar-first quaternions ``(n, 4)`` (either may be one ``(4,)``) and a unit
    ``axis``: ``2 atan2(v . axis, w)`` of ``conj(parent) child``, wrapped to (-pi, pi]."""
    conj = np.asarray(parent, dtype=float) * _CONJUGATE
    rel = np.atleast_2d(quat_product(conj, child))
    angle = 2.0 * np.arctan2(rel[:, 1:] @ axis, rel[:, 0])
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


def npose_segment_orientation(heading_rad: float = 0.0) -> Rotation:
    """Orientation ``R_GB`` of every segment in the static N-pose when the subject faces ``heading_rad`` (about Z)."""
    return Rotation.from_euler("z", heading_rad) * _NPOSE


def sensor_to_segment(
    static_quats: np.ndarray, *, heading_rad: float = 0.0, segment_orientation: Rotation | None = None
) -> Rotation:
    """Fixed sensor-to-segment rotation ``R_SB`` from samples of one sensor during the static pose.

    ``segment_orientation`` is the segment's known static ``R_GB`` (default: N-pose at ``heading_rad``)."""
    r_gs = quats_to_rotation(static_quats)
    if r_gs.single:
        mean = r_gs
    else:
        mean = r_gs.mean()
        spread = np.degrees((mean.inv() * r_gs).magnitude()).max()
        if spread > 10.0:
            raise InputError(
                "the sensor moved during the static pose", field="static_quats", value=f"{spread:.1f} deg from its mean"
            )
    r_gb = segment_orientation if segment_orientation is not None else npose_segment_orientation(heading_rad)
    return mean.inv() * r_gb


def segment_orientation(quats: np.ndarray, r_sb: Rotation) -> Rotation:
    """Segment orientation ``R_GB(t) = R_GS(t) R_SB`` for sensor quaternions ``(n, 4)``."""
    return quats_to_rotation(quats) * r_sb


def joint_angles(parent: Rotation, child: Rotation) -> np.ndarray:
    """Joint angles (rad) ``(n, 3)``: [flexion/extension, ab/adduction, rotation] of ``child`` relative to
    ``parent`` (intrinsic Z-X-Y Cardan angles of ``R_parent^T R_child``)."""
    rel = parent.inv() * child
    return np.atleast_2d(rel.as_euler("ZXY"))


def twist_angle(parent: Rotation, child: Rotation, axis: np.ndarray) -> np.ndarray:
    """Angle (rad, in (-pi, pi]) of ``child`` relative to ``parent`` about ``axis`` (a unit vector in the parent frame):
    the twist of the swing-twist decomposition of ``R_parent^T R_child``. Exact for a hinge about ``axis`` whatever
    its tilt, where the Cardan angles of ``joint_angles`` mix a tilted hinge axis into ab/adduction and rotation."""
    a = np.asarray(axis, dtype=float)
    norm = np.linalg.norm(a)
    if a.shape != (3,) or not np.isfinite(norm) or norm < 1e-9:
        raise InputError("the hinge axis must be a non-zero 3-vector", field="axis", value=a.tolist())
    quat = np.atleast_2d((parent.inv() * child).as_quat(scalar_first=True))
    angle = 2.0 * np.arctan2(quat[:, 1:] @ (a / norm), quat[:, 0])
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


def model_ground_orientation(gravity: np.ndarray, heading_rad: float = 0.0) -> Rotation:
    """Orientation ``R_GM`` of a musculoskeletal model's ground frame (OpenSim: X anterior, Y up, Z right) in the
    Z-up global frame when the subject faces ``heading_rad`` and the model's ``gravity`` vector points down.

    Upright models (gravity along -Y) give ``npose_segment_orientation(heading_rad)``; a supine bench-press model
    (gravity along -X) is that frame turned by the smallest rotation taking its gravity to -Z (chest up)."""
    g = np.asarray(gravity, dtype=float)
    if g.shape != (3,) or not np.all(np.isfinite(g)) or np.linalg.norm(g) < 1e-9:
        raise InputError("gravity must be a finite non-zero 3-vector", field="gravity", value=g.tolist())
    upright = npose_segment_orientation(heading_rad)
    g_global = upright.apply(g / np.linalg.norm(g))
    down = np.array([0.0, 0.0, -1.0])
    axis = np.cross(g_global, down)
    s, c = float(np.linalg.norm(axis)), float(g_global @ down)
    if s < 1e-12:
        # already down, or straight up: a half turn about the heading's horizontal right axis
        fix = Rotation.identity() if c > 0 else Rotation.from_rotvec(np.pi * upright.apply([0.0, 0.0, 1.0]))
    else:
        fix = Rotation.from_rotvec(axis / s * np.arctan2(s, c))
    return fix * upright


@dataclass(frozen=True)
class KinematicsFilterConfig:
    """Constant-acceleration model per angle: state [angle, velocity, acceleration], angle measured.

    ``jerk_std`` (rad/s^3) sets the process noise: filterpy ``Q_discrete_white_noise(dim=3, dt, var=(jerk_std*dt)^2)``,
    i.e. the acceleration changes by about ``jerk_std * dt`` per step. ``angle_std`` (rad) is the measurement noise.
    Larger ``jerk_std``: less lag, more noise. Set it near the jerk of the movement (fast curls: 10-50 rad/s^3)."""

    dt: float
    jerk_std: float = 30.0
    angle_std: float = np.radians(1.0)

    def __post_init__(self) -> None:
        for name in ("dt", "jerk_std", "angle_std"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ConfigError("must be positive", field=name, value=value)


#: how many steps' (F, Q) a filter keeps (JointKinematicsFilter._matrices_for)
MATRICES_KEPT = 64


def _matrices(n: int, cfg: KinematicsFilterConfig, dt: float) -> tuple[np.ndarray, np.ndarray]:
    f1 = np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
    # discrete white-noise acceleration increments: per step the acceleration changes by N(0, (jerk_std dt)^2)
    q1 = Q_discrete_white_noise(dim=3, dt=dt, var=(cfg.jerk_std * dt) ** 2)
    return np.kron(np.eye(n), f1), np.kron(np.eye(n), q1)


class JointKinematicsFilter:
    """Causal Kalman filter (filterpy) of ``n_angles`` joint angles: angle, velocity and acceleration.

    State: the filterpy ``KalmanFilter`` (x, P). Initialised at the first measurement with zero velocity and
    acceleration and a wide covariance."""

    def __init__(self, n_angles: int, config: KinematicsFilterConfig) -> None:
        if n_angles < 1:
            raise ConfigError("need at least one angle", field="n_angles", value=n_angles)
        self.n = n_angles
        self.config = config
        kf = KalmanFilter(dim_x=3 * n_angles, dim_z=n_angles)
        kf.F, kf.Q = _matrices(n_angles, config, config.dt)
        kf.H = np.kron(np.eye(n_angles), np.array([[1.0, 0.0, 0.0]]))
        kf.R = np.eye(n_angles) * config.angle_std**2
        self.kf = kf
        self.initialised = False
        self._dt = config.dt
        self._by_dt: dict[float, tuple[np.ndarray, np.ndarray]] = {config.dt: (kf.F, kf.Q)}

    def _matrices_for(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """F and Q for a step of ``dt`` s, kept per dt: the trackers' sample times make a few steps recur (about
        one frame in three changes dt in the kinematics node, and building them cost as much as the filter step)."""
        matrices = self._by_dt.get(dt)
        if matrices is None:
            if len(self._by_dt) >= MATRICES_KEPT:
                self._by_dt.clear()
            matrices = self._by_dt[dt] = _matrices(self.n, self.config, dt)
        return matrices

    def _init(self, z: np.ndarray) -> None:
        x = np.zeros(3 * self.n)
        x[0::3] = z
        self.kf.x = x
        p1 = np.diag([self.config.angle_std**2, 10.0**2, 100.0**2])  # rad, rad/s, rad/s^2 before any motion is seen
        self.kf.P = np.kron(np.eye(self.n), p1)
        self.initialised = True

    def step(self, angles: np.ndarray, dt: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Filter one sample of ``n_angles`` angles (rad), ``dt`` s after the previous one (default config.dt).
        Returns (angle, velocity, acceleration), each ``(n_angles,)``. NaN angles are predicted, not updated."""
        z = np.asarray(angles, dtype=float).reshape(-1)
        if z.shape[0] != self.n:
            raise InputError(f"expected {self.n} angles", field="angles", value=z.shape)
        if not self.initialised:
            if np.all(np.isfinite(z)):
                self._init(z)
            x = self.kf.x if self.initialised else np.full(3 * self.n, np.nan)
            return x[0::3].copy(), x[1::3].copy(), x[2::3].copy()
        if dt is not None and dt != self._dt:
            if not dt > 0:
                raise InputError("time must increase", field="dt", value=dt)
            self.kf.F, self.kf.Q = self._matrices_for(dt)
            self._dt = dt
        self.kf.predict()
        if np.all(np.isfinite(z)):
            self.kf.update(z)
        x = self.kf.x
        return x[0::3].copy(), x[1::3].copy(), x[2::3].copy()

    def filter(self, angles: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``step`` over a series ``(n_samples, n_angles)`` at the config rate."""
        out = [self.step(a) for a in np.atleast_2d(np.asarray(angles, dtype=float))]
        q, qd, qdd = (np.array([o[k] for o in out]) for k in range(3))
        return q, qd, qdd


def smooth_kinematics(angles: np.ndarray, config: KinematicsFilterConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """OFFLINE (non-causal) Rauch-Tung-Striebel smoother of the same model: (angle, velocity, acceleration)."""
    z = np.atleast_2d(np.asarray(angles, dtype=float))
    if not np.all(np.isfinite(z)):
        raise InputError("the smoother needs finite angles (interpolate gaps first)", field="angles")
    f = JointKinematicsFilter(z.shape[1], config)
    f._init(z[0])
    kf = f.kf
    means, covs, _, _ = kf.batch_filter(list(z))
    xs, _, _, _ = kf.rts_smoother(means, covs)
    return xs[:, 0::3], xs[:, 1::3], xs[:, 2::3]


@dataclass(frozen=True)
class Joint:
    """A joint between two instrumented segments; angles are the child's relative to the parent."""

    name: str
    parent: str
    child: str


@dataclass(frozen=True)
class SensorCalibration:
    """Per segment, the fixed sensor-to-segment rotation ``R_SB``. Serialisable for the subject profile."""

    sensor_to_segment: dict[str, Rotation]
    heading_rad: float = 0.0

    @classmethod
    def from_static_pose(cls, static_quats: dict[str, np.ndarray], *, heading_rad: float = 0.0) -> SensorCalibration:
        """Calibrate every segment from its sensor's samples during the static N-pose."""
        out = {}
        for segment, q in static_quats.items():
            try:
                out[segment] = sensor_to_segment(q, heading_rad=heading_rad)
            except InputError as exc:
                raise InputError(f"segment {segment!r}: {exc}", field=segment) from None
        return cls(out, heading_rad)

    def joint_angles(self, quats: dict[str, np.ndarray], joints: list[Joint]) -> dict[str, np.ndarray]:
        """Angles ``(n, 3)`` (rad) of each joint from the sensors' live quaternions ``(n, 4)``."""
        seg: dict[str, Rotation] = {}
        out = {}
        for j in joints:
            for s in (j.parent, j.child):
                if s not in seg:
                    if s not in self.sensor_to_segment or s not in quats:
                        raise InputError(
                            f"joint {j.name!r} needs segment {s!r}, which is not calibrated or has no sensor data",
                            field=s,
                        )
                    seg[s] = segment_orientation(quats[s], self.sensor_to_segment[s])
            out[j.name] = joint_angles(seg[j.parent], seg[j.child])
        return out

    def to_dict(self) -> dict[str, object]:
        return {
            "heading_rad": self.heading_rad,
            "sensor_to_segment_wxyz": {
                k: r.as_quat(scalar_first=True).tolist() for k, r in self.sensor_to_segment.items()
            },
        }

    @classmethod
    def from_dict(cls, d: dict[str, object]) -> SensorCalibration:
        try:
            table = d["sensor_to_segment_wxyz"]
        except KeyError as exc:
            raise ConfigError("sensor calibration misses a field", field=str(exc.args[0])) from None
        heading = d.get("heading_rad", 0.0)
        if not isinstance(table, dict):
            raise ConfigError(
                "must map each segment to a quaternion [w, x, y, z]", field="sensor_to_segment_wxyz", value=table
            )
        if isinstance(heading, bool) or not isinstance(heading, (int, float)):
            raise ConfigError("must be a number (radians)", field="heading_rad", value=heading)
        rots = {str(k): quats_to_rotation(np.asarray(v, dtype=float)) for k, v in table.items()}
        return cls(rots, float(heading))
