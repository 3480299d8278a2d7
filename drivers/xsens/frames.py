"""Global coordinate frames of Xsens orientation output (ENU default, NED, NWU) and conversions between them.

A quaternion q_F rotates sensor to global frame F. With R_FE the rotation taking ENU coordinates to F coordinates,
q_F = r_FE * q_ENU. NED: x=north=ENU y, y=east=ENU x, z=-up (a half turn about (1,1,0)/sqrt2).
NWU: x=north=ENU y, y=west=-ENU x, z=up (a quarter turn of -90 deg about z).
"""

from __future__ import annotations

import math

from drivers.xsens.xbus import CoordinateFrame

_S = math.sqrt(0.5)
#: r_FE for each frame, w first.
ENU_TO: dict[CoordinateFrame, tuple[float, float, float, float]] = {
    CoordinateFrame.ENU: (1.0, 0.0, 0.0, 0.0),
    CoordinateFrame.NED: (0.0, _S, _S, 0.0),
    CoordinateFrame.NWU: (_S, 0.0, 0.0, -_S),
}


def quat_multiply(a, b) -> tuple[float, float, float, float]:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def quat_conjugate(q) -> tuple[float, float, float, float]:
    return (q[0], -q[1], -q[2], -q[3])


def from_enu(q_enu, frame: CoordinateFrame) -> tuple[float, float, float, float]:
    return quat_multiply(ENU_TO[frame], q_enu)


def to_enu(q_frame, frame: CoordinateFrame) -> tuple[float, float, float, float]:
    return quat_multiply(quat_conjugate(ENU_TO[frame]), q_frame)


def rotate(q, v) -> tuple[float, float, float]:
    """Rotate vector v by unit quaternion q."""
    w, x, y, z = quat_multiply(quat_multiply(q, (0.0, *v)), quat_conjugate(q))
    return (x, y, z)


def quat_from_euler_deg(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """The orientation quaternion (w first) of Xsens Euler angles in degrees: a rotation about the global x axis by
    roll, then y by pitch, then z by yaw (R_GS = Rz(yaw) Ry(pitch) Rx(roll), the MTi's Euler output definition and the
    inverse of XsEuler_fromQuaternion)."""
    r, p, y = (math.radians(a) / 2.0 for a in (roll, pitch, yaw))
    qx = (math.cos(r), math.sin(r), 0.0, 0.0)
    qy = (math.cos(p), 0.0, math.sin(p), 0.0)
    qz = (math.cos(y), 0.0, 0.0, math.sin(y))
    return quat_multiply(qz, quat_multiply(qy, qx))
