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


def quat_from_rotation_matrix(m) -> tuple[float, float, float, float]:
    """The orientation quaternion (w first) of an MTData2 RotationMatrix, nine values a..i that the Xsens low-level
    protocol lays out column by column: R_GS = [[a, d, g], [b, e, h], [c, f, i]]. Shepperd's method: the largest of
    w, x, y, z is found first, so no division by a small number."""
    a, b, c, d, e, f, g, h, i = m
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = a, d, g, b, e, h, c, f, i
    trace = r00 + r11 + r22
    if trace >= max(r00, r11, r22):
        w = 0.5 * math.sqrt(max(1.0 + trace, 0.0))
        q = (w, (r21 - r12) / (4 * w), (r02 - r20) / (4 * w), (r10 - r01) / (4 * w))
    elif r00 >= r11 and r00 >= r22:
        x = 0.5 * math.sqrt(max(1.0 + r00 - r11 - r22, 0.0))
        q = ((r21 - r12) / (4 * x), x, (r01 + r10) / (4 * x), (r02 + r20) / (4 * x))
    elif r11 >= r22:
        y = 0.5 * math.sqrt(max(1.0 - r00 + r11 - r22, 0.0))
        q = ((r02 - r20) / (4 * y), (r01 + r10) / (4 * y), y, (r12 + r21) / (4 * y))
    else:
        z = 0.5 * math.sqrt(max(1.0 - r00 - r11 + r22, 0.0))
        q = ((r10 - r01) / (4 * z), (r02 + r20) / (4 * z), (r12 + r21) / (4 * z), z)
    return q if q[0] >= 0.0 else (-q[0], -q[1], -q[2], -q[3])
